"""Sensor maps as candidate effects on an output: sign-blind, saturation, quantisation, offset."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.description import Description, parse_description
from dvt_identify.effects import (
    VOCABULARY,
    ScoringContext,
    SegmentView,
    SensorOffset,
    SensorQuantisation,
    SensorSaturation,
    SignBlindSensor,
    make_effect,
)
from dvt_identify.effects.base import Effect

STATES = ("a", "b")
INPUTS = ("u",)


def build(name: str, where: str = "b", **opts: object) -> Effect:
    return make_effect(name, where, STATES, INPUTS, "N", "m/s", options=dict(opts))


def cart_description(candidates: list[dict[str, object]]) -> Description:
    """A cart ``M v' = F - Fv v`` (priors M 2 kg, Fv 3 N s/m), its speed measured, with these
    candidates, fitted at the records' rate."""
    raw = {
        "name": "cart",
        "inputs": [{"name": "force", "topic": "/c/drive", "field": "effort", "joint": "c"}],
        "outputs": [{"name": "v", "topic": "/c/joint_states", "field": "velocity",
                     "joint": "c"}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]],
                      "parameters": {"M": {"initial": 2.0, "lower": 0.01},
                                     "Fv": {"initial": 3.0, "lower": 0.0}}},
        "candidates": candidates,
        "preprocess": {"fit_decimate": 1}}
    return parse_description(raw, "cart.yaml")


def ctx(y_meas: np.ndarray, y_sim: np.ndarray, u: np.ndarray) -> ScoringContext:
    return ScoringContext(views=[SegmentView(0.01, u, y_meas)], simulated=[y_sim],
                          weights=np.ones(y_meas.shape[1]),
                          member_residual=lambda c: np.zeros(y_meas.shape[0]))


def test_vocabulary_and_classes() -> None:
    for name, cls in (("sign_blind", SignBlindSensor), ("sensor_saturation", SensorSaturation),
                      ("sensor_quantisation", SensorQuantisation),
                      ("sensor_offset", SensorOffset)):
        assert name in VOCABULARY
        eff = build(name)
        assert type(eff) is cls and eff.index == 1
        assert eff.model_term(eff.null_vector(), STATES) is None  # no model-node term
        for s in eff.params:
            assert s.lower <= s.null <= s.upper and s.initial == s.null


def test_sign_blind_map_secant_and_admissibility() -> None:
    eff = build("sign_blind")
    y = np.column_stack([np.linspace(-1, 1, 5), np.linspace(-2, 2, 5)])
    assert eff.output_transform(np.array([0.0]), y, 0.01) is None
    out = eff.output_transform(np.array([1.0]), y, 0.01)
    assert out is not None
    assert np.array_equal(out[:, 1], np.abs(y[:, 1])) and np.array_equal(out[:, 0], y[:, 0])
    half = eff.output_transform(np.array([0.5]), y, 0.01)
    assert half is not None and np.allclose(half[:, 1], 0.5 * (y[:, 1] + np.abs(y[:, 1])))
    # the scorer's probe is the secant to b = 1
    assert eff.variants(SegmentView(0.01, np.zeros((5, 1)), y)) == [("|y|", {"sign_blind": 1.0})]
    assert eff.inadmissible(np.array([0.3])) is not None
    assert eff.inadmissible(np.array([0.0])) is not None  # absent
    assert eff.inadmissible(np.array([0.999])) is None
    assert eff.inadmissible(np.array([1.7])) is not None


def test_sign_blind_signature_reads_the_data() -> None:
    rng = np.random.default_rng(0)
    n = 4000
    t = np.arange(n) * 0.01
    x = np.sin(2 * np.pi * 0.3 * t)
    u = np.column_stack([np.cos(2 * np.pi * 0.3 * t)])
    noise = 0.01 * rng.standard_normal(n)
    blind = np.column_stack([x, np.abs(x) + noise])
    clean = np.column_stack([x, x + noise])
    eff = build("sign_blind")
    ev, _ = eff.scoring_evidence(ctx(blind, np.column_stack([x, x]), u))
    assert ev["signature"] is True
    assert ev["noise_std"] == pytest.approx(0.01, rel=0.2)
    # the baseline's error sits where it simulates a negative output
    assert ev["error_share_where_simulated_negative"] == pytest.approx(1.0, abs=1e-3)
    ev, _ = eff.scoring_evidence(ctx(clean, np.column_stack([x, x]), u))
    assert ev["signature"] is False
    # a one-signed input (a drive that only turns one way) is no evidence
    ev, _ = eff.scoring_evidence(ctx(blind, np.column_stack([x, x]), np.abs(u)))
    assert ev["signature"] is False


def test_saturation_flat_tops() -> None:
    eff = build("sensor_saturation", max_level=100.0)
    x = np.column_stack([np.zeros(200), 3 * np.sin(np.linspace(0, 8 * np.pi, 200))])
    assert eff.output_transform(np.array([100.0]), x, 0.01) is None
    clipped = eff.output_transform(np.array([2.0]), x, 0.01)
    assert clipped is not None and np.max(np.abs(clipped[:, 1])) == 2.0
    view = SegmentView(0.01, np.zeros((200, 1)), clipped)
    (_label, probe), = eff.variants(view)
    assert probe["level"] == pytest.approx(2.0 - 100.0)  # the secant from the null to the top
    ev, start = eff.scoring_evidence(ctx(clipped, x, np.zeros((200, 1))))
    assert ev["signature"] is True and start == {"level": 2.0}
    assert float(ev["share_at_max"]) > 0.1  # type: ignore[arg-type]
    assert float(ev["simulated_max"]) > float(ev["measured_max"])  # type: ignore[arg-type]
    ev, _ = eff.scoring_evidence(ctx(x + 1e-3 * np.random.default_rng(1).standard_normal(x.shape),
                                     x, np.zeros((200, 1))))
    assert ev["signature"] is False


def test_quantisation_grid_step() -> None:
    eff = build("sensor_quantisation")
    rng = np.random.default_rng(2)
    x = np.cumsum(rng.standard_normal(3000)) * 0.01
    q = 0.025
    y = q * np.round(x / q)
    assert SensorQuantisation.grid_step(y) == pytest.approx(q, rel=1e-6)
    assert SensorQuantisation.grid_step(x) == 0.0
    out = eff.output_transform(np.array([q]), np.column_stack([x, x]), 0.01)
    assert out is not None and np.allclose(out[:, 1], y)
    ev, start = eff.scoring_evidence(ctx(np.column_stack([x, y]), np.column_stack([x, x]),
                                         np.zeros((3000, 1))))
    assert ev["grid_step"] == pytest.approx(q) and ev["share_on_grid"] == 1.0
    assert start == {"quantum": pytest.approx(q)}


def test_offset() -> None:
    eff = build("sensor_offset")
    y = np.zeros((10, 2))
    out = eff.output_transform(np.array([0.5]), y, 0.01)
    assert out is not None and np.all(out[:, 1] == 0.5) and np.all(out[:, 0] == 0.0)
    ev, start = eff.scoring_evidence(ctx(y + 0.2, y, np.zeros((10, 1))))
    assert ev["mean_residual"] == pytest.approx(0.2) and start == {"sensor_offset": 0.2}
    assert eff.inadmissible(np.array([0.0])) is not None


def test_loop_accepts_a_saturating_sensor_and_nothing_else() -> None:
    """A cart read through a sensor that clips at +-0.8 m/s (3 % of the samples): the
    saturation is scored first, refitted and accepted; the offset and sign-blind maps are not;
    the cart's mass and damping come out within 3 standard deviations."""
    from dvt_identify.data import Segment, make_segment
    from dvt_identify.loop import LoopConfig, identify
    from dvt_identify.simulation import OEModel

    desc = cart_description([{"effect": "sensor_saturation", "where": "v", "max_level": 1000.0},
                             {"effect": "sensor_offset", "where": "v"},
                             {"effect": "sign_blind", "where": "v"}])

    def record(name: str, seed: int, n: int = 1500) -> Segment:
        rng = np.random.default_rng(seed)
        u = np.repeat(rng.uniform(-5, 5, n // 50 + 1), 50)[:n]
        t = np.arange(n) * 0.01
        clean = make_segment(name, t, u, np.zeros(n), ["force"], ["v"])
        y = OEModel(desc.structure).simulate(np.array([2.5, 4.0]), clean, np.zeros(1))
        y = np.clip(y + 0.01 * rng.standard_normal(y.shape), -0.8, 0.8)
        return make_segment(name, t, u, y, ["force"], ["v"])

    est, val = [record("est", 1)], [record("val", 2)]
    assert 0.02 < float(np.mean(np.abs(est[0].y) >= 0.8)) < 0.05
    res = identify(est, val, desc, LoopConfig(starts=1, refit_starts=1, drift_windows=0))
    assert [d.score.label for d in res.accepted] == ["sensor_saturation@v"]
    assert res.accepted[0].score.extra["signature"] is True
    par, std = res.final.parameters(), res.final.fit.parameter_std()
    # clipped after the noise, the flat tops give the level exactly
    assert par["level"] == pytest.approx(0.8, abs=1e-9)
    assert abs(par["M"] - 2.5) < 3 * std["M"] and abs(par["Fv"] - 4.0) < 3 * std["Fv"]


def test_first_order_lag_is_exact_on_a_ramp_and_its_inverse_undoes_it() -> None:
    """``tau y' = x - y`` from rest at ``x(0)``: on a ramp ``x = t`` the sampled law is the
    exact solution ``t - tau (1 - exp(-t / tau))``; the starts' inverse ``y + tau y'`` gives a
    smooth input back to the differences' error."""
    from dvt_identify.effects.sensors import first_order_lag

    dt, tau = 0.01, 0.037
    t = np.arange(300) * dt
    assert first_order_lag(t, tau, dt) == pytest.approx(t - tau * (1 - np.exp(-t / tau)),
                                                        abs=1e-12)
    assert np.array_equal(first_order_lag(t, 0.0, dt), t)
    eff = build("sensor_lag")
    x = np.sin(2 * np.pi * 1.5 * t)
    y = np.column_stack([np.zeros_like(t), x])
    lagged = eff.output_transform(np.array([tau]), y, dt)
    assert lagged is not None and np.all(lagged[:, 0] == 0.0)
    back = eff.output_inverse(np.array([tau]), lagged, dt)
    assert back is not None
    assert np.max(np.abs(back[50:, 1] - x[50:])) < 0.01
    assert eff.inadmissible(np.array([0.0])) is not None
    assert eff.output_transform(np.array([0.0]), y, dt) is None


def _cart_loop(lag: float) -> tuple[list[str], dict[str, float], dict[str, float]]:
    """A cart (``M v' = F - Fv v``, M 2.5 kg, Fv 4 N s/m) read at 100 Hz through a first-order
    filter of time constant ``lag`` [s] (0: none), 1 % noise after it; identified with the
    lag, offset and delay among the candidates."""
    from dvt_identify.data import Segment, make_segment
    from dvt_identify.effects.sensors import first_order_lag
    from dvt_identify.loop import LoopConfig, identify
    from dvt_identify.simulation import OEModel

    desc = cart_description([{"effect": "sensor_lag", "where": "v"},
                             {"effect": "sensor_offset", "where": "v"},
                             {"effect": "measurement_delay", "where": "v", "max_delay": 0.05}])

    def record(name: str, seed: int, n: int = 1500) -> Segment:
        rng = np.random.default_rng(seed)
        u = np.repeat(rng.uniform(-5, 5, n // 20 + 1), 20)[:n]
        t = np.arange(n) * 0.01
        clean = make_segment(name, t, u, np.zeros(n), ["force"], ["v"])
        v = OEModel(desc.structure).simulate(np.array([2.5, 4.0]), clean, np.zeros(1))[:, 0]
        y = first_order_lag(v, lag, 0.01) + 0.01 * float(np.std(v)) * rng.standard_normal(n)
        return make_segment(name, t, u, y[:, None], ["force"], ["v"])

    res = identify([record("est", 1)], [record("val", 2)], desc,
                   LoopConfig(starts=1, refit_starts=1, drift_windows=0))
    return ([d.score.label for d in res.accepted], res.final.parameters(),
            res.final.fit.parameter_std())


def test_loop_names_a_lagging_sensor_with_its_time_constant() -> None:
    """Read through a 30-ms filter (3 samples), the cart gets ``sensor_lag`` and nothing else
    (not the delay that a lag resembles), with the time constant, mass and damping within 3
    reported std."""
    accepted, par, std = _cart_loop(0.03)
    assert accepted == ["sensor_lag@v"]
    for name, truth in (("tau", 0.03), ("M", 2.5), ("Fv", 4.0)):
        assert abs(par[name] - truth) < 3 * std[name], (name, par[name], std[name])


def test_loop_accepts_no_lag_on_a_clean_sensor() -> None:
    accepted, par, std = _cart_loop(0.0)
    assert accepted == []
    assert abs(par["M"] - 2.5) < 3 * std["M"] and abs(par["Fv"] - 4.0) < 3 * std["Fv"]
