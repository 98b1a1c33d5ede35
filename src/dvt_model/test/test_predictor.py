"""The model node's core: anchoring, free run, re-anchoring, residual RMS."""

import numpy as np
import pytest

from dvt_model.errors import SimulationError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel
from dvt_model.params import load_parameters
from dvt_model.predictor import OMEGA_GUARD, Predictor


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
