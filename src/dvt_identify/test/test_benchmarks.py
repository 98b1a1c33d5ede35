"""Benchmark protocol: initial state from a window, simulated-output RMS after it, and the fit
for the benchmark's output (dvt_identify.benchmarks), on synthetic records with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.benchmarks import (
    fit_for_output,
    initial_state_from_window,
    protocol_score,
    protocol_score_model,
    window_guess,
)
from dvt_identify.data import Segment
from dvt_identify.description import load_description
from dvt_identify.effects import make_effect
from dvt_identify.errors import DataError, FitError
from dvt_identify.simulation import OEModel
from dvt_identify.structures import MechanicalStructure

STATES = ("position", "carriage")


def position_model(friction: bool) -> OEModel:
    """q' = v, M v' = F - Fv v [- Fc sign v - offset] (the emps-position structure)."""
    st = MechanicalStructure(STATES, ("force",), [[1.0, 0.0], [0.0, "M"]],
                             [[0.0, -1.0], [0.0, "Fv"]], [[0.0], [1.0]],
                             {"M": {"initial": 1.0, "lower": 1e-3},
                              "Fv": {"initial": 1.0, "lower": 0.0}}, "N", "m/s")
    effects = ([make_effect("coulomb_friction", "carriage", STATES, ("force",), "N", "m/s",
                            options={"offset": True})] if friction else [])
    return OEModel(st, effects)


def record(model: OEModel, theta: np.ndarray, x0: np.ndarray, n: int = 3000,
           dt: float = 1e-3, seed: int = 1) -> Segment:
    """A noise-free record of ``model`` driven by a smoothed random force."""
    rng = np.random.default_rng(seed)
    f = np.convolve(rng.normal(0.0, 6.0, n), np.ones(40) / 40, mode="same")
    f += 3.0 * np.sin(2 * np.pi * 1.3 * np.arange(n) * dt)
    t = np.arange(n, dtype=np.float64) * dt
    seg = Segment("synthetic", t, f[:, None], np.zeros((n, 2)), ("force",), STATES, dt)
    y = model.simulate(theta, seg, x0)
    return Segment("synthetic", t, f[:, None], y, ("force",), STATES, dt)


def test_window_guess_is_first_sample_and_slope() -> None:
    y = 0.3 + 2.0 * np.arange(50, dtype=np.float64) * 0.01
    x0 = window_guess(y, 20, 0.01, 3)
    assert x0 == pytest.approx([0.3, 2.0, 0.0], abs=1e-12)


def test_initial_state_of_a_linear_model_is_exact() -> None:
    """Affine in the initial state: Gauss-Newton lands on it (noise-free, to 1e-9)."""
    m = position_model(friction=False)
    theta = np.array([2.0, 3.0])
    x0 = np.array([0.01, -0.2])
    seg = record(m, theta, x0)

    def sim(x: np.ndarray, n: int) -> np.ndarray:
        part = Segment("p", seg.t[:n], seg.u[:n], seg.y[:n], seg.input_names,
                       seg.output_names, seg.dt)
        return m.simulate(theta, part, x)[:, 0]
    got = initial_state_from_window(sim, seg.y[:, 0], 20, np.zeros(2))
    assert got == pytest.approx(x0, rel=1e-6, abs=1e-9)


def test_protocol_score_of_the_true_model_is_zero_and_counts_samples() -> None:
    m = position_model(friction=True)
    theta = np.array([2.0, 3.0, 0.5, 0.1])
    seg = record(m, theta, np.array([0.0, 0.05]))
    sc = protocol_score_model(m, theta, seg, 0, 20, 2)
    assert sc.n_init == 20 and sc.n_scored == seg.n - 20
    # noise-free record, exact model: only the window's fit of the state is left (1e-9 m)
    assert sc.rms < 1e-8
    assert sc.y_sim.shape == (seg.n,)


def test_protocol_score_scores_only_after_the_window() -> None:
    """A simulator exact in the window and off by a constant after it: RMS = that constant."""
    y = np.linspace(0.0, 1.0, 100)

    def sim(x0: np.ndarray, n: int) -> np.ndarray:
        out = y[:n] + x0[0] - y[0]
        out[20:] += 0.25
        return out
    sc = protocol_score(sim, y, 20, np.array([5.0]))
    assert sc.rms == pytest.approx(0.25, abs=1e-12)
    assert sc.x0 == pytest.approx([0.0], abs=1e-12)


def test_protocol_score_needs_samples_after_the_window() -> None:
    y = np.zeros(10)
    with pytest.raises(DataError):
        protocol_score(lambda x, n: np.zeros(n), y, 10, np.zeros(1))
    with pytest.raises(DataError):
        initial_state_from_window(lambda x, n: np.zeros(n), y, 0, np.zeros(1))


def test_fit_for_output_recovers_friction_parameters_from_the_position() -> None:
    """Position only, initial state from the window: M, Fv, Fc, offset of a noise-free record
    are found from a start 20-30 % off (to 0.1 %: the optimiser's tolerance on a stick-rule
    simulation, far below the start error)."""
    m = position_model(friction=True)
    truth = np.array([2.0, 3.0, 0.5, 0.1])
    seg = record(m, truth, np.array([0.0, 0.05]))
    lo = np.array([1e-3, 0.0, 0.0, -np.inf])
    hi = np.full(4, np.inf)
    fit = fit_for_output(m, seg, truth * np.array([1.2, 0.8, 1.3, 0.7]), lo, hi, 0, 20, 2)
    assert fit.theta == pytest.approx(truth, rel=1e-3)
    assert fit.rms < 1e-6
    assert fit.x0 == pytest.approx([0.0, 0.05], abs=1e-6)
    assert fit.weights.shape == (1,)


def test_fit_for_output_rejects_a_start_outside_the_bounds() -> None:
    m = position_model(friction=False)
    seg = record(m, np.array([2.0, 3.0]), np.zeros(2), n=500)
    with pytest.raises(FitError):
        fit_for_output(m, seg, np.array([-1.0, 3.0]), np.array([1e-3, 0.0]),
                       np.full(2, np.inf), 0, 20, 2)


def test_bundled_emps_position_is_a_double_integrator() -> None:
    """descriptions/emps-position.yaml: the benchmark's one output, the position of the member
    ``carriage`` (its speed a hidden state): states (q, v), A = [[0, 1], [0, -Fv/M]],
    B = [0, 1/M], C = [1, 0], effects on the speed state, dry laws with a smoothed sign."""
    d = load_description("emps-position")
    assert d.output_names == ("position",) and d.input_names == ("force",)
    assert d.structure.state_names == ("carriage_angle", "carriage")
    A, B, F = d.structure.matrices(np.array([95.0, 200.0]))
    np.testing.assert_allclose(A, [[0.0, 1.0], [0.0, -200.0 / 95.0]], rtol=1e-12)
    np.testing.assert_allclose(B, [[0.0], [1.0 / 95.0]], rtol=1e-12)
    assert F @ np.array([0.0, 1.0]) == pytest.approx([0.0, 1.0 / 95.0])
    np.testing.assert_array_equal(d.structure.output_matrix(), [[1.0, 0.0]])
    cands = {c.name: c for c in d.make_candidates()}
    assert list(cands["coulomb_friction"].member) == [0.0, 1.0]
    assert cands["coulomb_friction"].eps > 0 and cands["stribeck_friction"].eps > 0


