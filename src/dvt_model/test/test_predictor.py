"""The model node's core: anchoring, free run, re-anchoring, residual RMS."""

import numpy as np
import pytest

from dvt_model.contract import GAP_REANCHOR_S, GAP_RESET_S
from dvt_model.errors import SimulationError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel
from dvt_model.params import load_parameters
from dvt_model.predictor import GAP_PERIODS, OMEGA_GUARD, Predictor


@pytest.fixture(scope="module")
def params():
    return load_parameters("physical")


def _truth(params, n=2000):
    model = HybridModel.from_params(params)
    t = np.arange(n) * 1e-3
    im = 3.0 + 2.0 * np.sin(2 * np.pi * 1.5 * t)
    ib = np.zeros((n, 3))
    ib[1000:, 0] = 0.5
    return t, im, ib, model.simulate(t, im, ib, omega0=(50.0, 10.0))


def test_exact_model_predicts_exactly(params):
    t, im, ib, r = _truth(params)
    p = Predictor(HybridModel.from_params(params), params.brake)
    res = [p.update(t[k], im[k], ib[k], r.omega[k]).residual for k in range(len(t))]
    assert np.max(np.abs(res)) < 1e-6
    assert p.anchors == 1


def test_reanchor_mode_and_gap(params):
    t, im, ib, r = _truth(params, 1500)
    p = Predictor(HybridModel.from_params(params), params.brake, mode="reanchor",
                  reanchor_period=0.5)
    for k in range(len(t)):
        p.update(t[k], im[k], ib[k], r.omega[k])
    assert p.anchors == 3
    p.update(t[-1] + 5.0, 0.0, (0, 0, 0), (0.0, 0.0))  # gap > gap_reset re-anchors
    assert p.anchors == 4


def test_a_burst_of_lost_samples_reanchors_and_a_lost_sample_does_not(params):
    """Lost samples (transport) at 1 kHz: a gap beyond ``gap_reanchor`` re-anchors (the held
    inputs would leave the free run off) and is no restart, a gap within it is run through;
    a gap beyond ``gap_reset`` is a restart."""
    t, im, ib, r = _truth(params, 2000)
    keep = np.ones(len(t), bool)
    keep[500:503] = False  # 4 ms step: run through
    lost = 1200, 1200 + round(2 * GAP_REANCHOR_S / 1e-3)  # twice gap_reanchor: re-anchor
    keep[lost[0]:lost[1]] = False
    p = Predictor(HybridModel.from_params(params), params.brake)
    out = {k: p.update(t[k], im[k], ib[k], r.omega[k]) for k in np.flatnonzero(keep)}
    assert [k for k, o in out.items() if o.anchored] == [0, lost[1]]
    assert [k for k, o in out.items() if o.restarted] == [0] and p.gap_anchors == 1
    assert [k for k, o in out.items() if o.lost] == [lost[1]]
    restart = p.update(t[-1] + 2 * GAP_RESET_S, im[-1], ib[-1], r.omega[-1])
    assert restart.anchored and restart.restarted and not restart.lost and p.gap_anchors == 1


def test_a_stream_slower_than_gap_reanchor_runs_free_from_its_first_sample(params):
    """62.5 Hz (16 ms > ``gap_reanchor``): the stream runs free from its first sample (the
    first step has no previous one to compare with); a lost sample (32 ms) is run through, two
    (48 ms) re-anchor."""
    step = 16
    assert step * 1e-3 > GAP_REANCHOR_S and 2 * step < GAP_PERIODS * step < 3 * step
    t, im, ib, r = _truth(params, 2000)
    idx = [k for k in range(0, 2000, step) if k not in (800, 1200, 1200 + step)]
    p = Predictor(HybridModel.from_params(params), params.brake)
    anchored = [k for k in idx if p.update(t[k], im[k], ib[k], r.omega[k]).anchored]
    assert anchored == [0, 1200 + 2 * step] and p.gap_anchors == 1


def test_linear_model_with_wrong_A_has_residual(params):
    t, im, ib, r = _truth(params, 800)
    rig = HybridModel.from_params(params).rigid
    lin = LinearModel(rig.A * 0.5, rig.B(1) @ np.diag([rig.motor_constant, 1.0]))
    p = Predictor(lin, params.brake)
    for k in range(len(t)):
        p.update(t[k], im[k], ib[k], r.omega[k])
    assert p.residual_rms[0] > 1.0


def test_rejects_non_finite(params):
    p = Predictor(HybridModel.from_params(params), params.brake)
    with pytest.raises(SimulationError, match="non-finite"):
        p.update(0.0, float("nan"), (0, 0, 0), (0, 0))
    with pytest.raises(SimulationError, match="mode: expected"):
        Predictor(HybridModel.from_params(params), params.brake, mode="bogus")  # type: ignore[arg-type]


def test_guard_reanchors_a_diverging_model(params):
    # an (inadmissible, unchecked) unstable linear model diverges within a few samples
    lin = LinearModel(np.array([[3000.0, 0.0], [0.0, 3000.0]]), np.zeros((2, 2)))
    p = Predictor(lin, params.brake)
    for k in range(200):
        out = p.update(k * 1e-3, 0.0, (0, 0, 0), (10.0, 2.0))
        assert np.all(np.isfinite(out.predicted))
        assert np.max(np.abs(out.predicted)) <= OMEGA_GUARD
    assert p.guard_reanchors > 0
    assert p.anchors == 1 + p.guard_reanchors


def test_guard_catches_non_finite_state(params):
    def nan_force(omega, t):
        return np.array([np.nan, 0.0])

    p = Predictor(HybridModel.from_params(params, extra_force=nan_force), params.brake)
    for k in range(10):
        out = p.update(k * 1e-3, 1.0, (0, 0, 0), (5.0, 1.0))
        assert np.all(np.isfinite(out.predicted)) and np.all(np.isfinite(out.residual))
    assert p.guard_reanchors == 9


def test_guard_bound_is_100_times_the_safe_sun_speed():
    assert abs(OMEGA_GUARD - 100 * 2400 * 2 * np.pi / 60) < 1e-9


# -- angles --------------------------------------------------------------------------------------

def _loaded_run(params, n=1500):
    from dvt_model.load import LOAD_PRESETS
    load = LOAD_PRESETS["arm-payload"]
    model = HybridModel.from_params(params, load=load)
    t = np.arange(n) * 1e-3
    im = np.full(n, 20.0)
    ib = np.zeros((n, 3))
    ib[:, 2] = 5.0  # gear 3 lifts the arm
    state0 = model.initial_state(theta=(0.0, load.carrier3_angle(-0.3)),
                                 locked=(False, False, True), capacity=(0.0, 0.0, 40.0))
    return load, t, im, ib, model.simulate(t, im, ib, state0=state0)


def test_predicted_angles_follow_a_loaded_run_when_the_load_is_known(params):
    load, t, im, ib, res = _loaded_run(params)
    assert res.theta[-1, 1] - res.theta[0, 1] > 0.5  # the arm rose
    p = Predictor(HybridModel.from_params(params, load=load), params.brake)
    out = [p.update(t[k], im[k], ib[k], res.omega[k], res.theta[k]) for k in range(len(t))]
    assert out[0].anchored and out[0].position_residual is not None
    np.testing.assert_allclose(out[0].predicted_position, res.theta[0])
    worst = max(np.max(np.abs(o.position_residual)) for o in out
                if o.position_residual is not None)
    assert worst < 1e-6
    rms = p.position_residual_rms
    assert rms is not None and np.all(rms < 1e-6)
    # without the load the model runs away from the measured angles
    bare = Predictor(HybridModel.from_params(params), params.brake)
    last = [bare.update(t[k], im[k], ib[k], res.omega[k], res.theta[k])
            for k in range(len(t))][-1]
    assert last.position_residual is not None and np.max(np.abs(last.position_residual)) > 0.1


def test_angles_without_measurement_continue_and_carry_no_residual(params):
    p = Predictor(HybridModel.from_params(params), params.brake)
    a = p.update(0.0, 2.0, (0, 0, 0), (10.0, 0.0))
    b = p.update(0.001, 2.0, (0, 0, 0), (10.0, 0.0))
    assert a.position_residual is None and b.position_residual is None
    assert b.predicted_position[0] == pytest.approx(0.5 * 0.001 * (10.0 + b.predicted[0]), rel=1e-3)
    assert p.position_residual_rms is None
    # positions appear: the angles are anchored to them
    c = p.update(0.002, 2.0, (0, 0, 0), (10.0, 0.0), (5.0, 1.0))
    assert c.anchored and c.position_residual is not None
    np.testing.assert_allclose(c.predicted_position, (5.0, 1.0))
    # a non-finite measured angle counts as not measured
    d = p.update(0.003, 2.0, (0, 0, 0), (10.0, 0.0), (float("nan"), 1.0))
    assert d.position_residual is None and d.predicted_position[0] > 5.0


def test_linear_model_integrates_angles(params):
    from dvt_model.linear import LinearModel
    A = np.array([[-1.0, 0.0], [0.0, -1.0]])
    B = np.zeros((2, 2))
    p = Predictor(LinearModel(A, B), params.brake, gap_reanchor=0.05)  # one 10-ms step
    p.update(0.0, 0.0, (0, 0, 0), (2.0, 1.0), (0.0, 0.0))
    out = p.update(0.01, 0.0, (0, 0, 0), (2.0, 1.0), (0.02, 0.01))
    assert out.predicted_position[0] == pytest.approx(2.0 * (1 - np.exp(-0.01)), rel=1e-3)
    assert out.position_residual is not None


def test_residual_blocks_average_and_drop_at_gaps():
    from dvt_model.predictor import ResidualBlocks

    blocks = ResidualBlocks(4, 2, max_gap_s=0.05)
    out = [blocks.add(k * 0.001, [float(k), -2.0 * k]) for k in range(8)]
    assert out[:3] == [None] * 3 and out[4:7] == [None] * 3
    assert out[3] == (0.0, [1.5, -3.0])
    first, means = out[7]
    assert first == pytest.approx(0.004) and means == pytest.approx([5.5, -11.0])
    # a gap drops the unfinished block; the next block starts after it
    assert blocks.add(0.008, [1.0, 1.0]) is None
    assert blocks.add(0.2, [2.0, 2.0]) is None
    assert blocks.dropped == 1
    for k in range(1, 3):
        assert blocks.add(0.2 + k * 0.001, [2.0, 2.0]) is None
    assert blocks.add(0.203, [6.0, 2.0]) == (0.2, [3.0, 2.0])
    with pytest.raises(SimulationError, match="block size"):
        ResidualBlocks(0)
    blocks.add(0.3, [1.0, 1.0])
    blocks.clear()  # an anchor: the unfinished block is dropped
    assert [blocks.add(0.301 + k * 0.001, [0.0, 0.0]) for k in range(4)][-1] == (
        pytest.approx(0.301), [0.0, 0.0])
