"""The output-error fit: recovery of known systems, refused data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import make_segment
from dvt_identify.effects import make_effect
from dvt_identify.errors import FitError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_identify.structures import MechanicalStructure, StateSpaceStructure

A_TRUE = np.array([[-2.0, 1.5], [-3.0, -4.0]])
B_TRUE = np.array([[1.0, 0.0], [0.5, 2.0]])


def _free_2x2() -> StateSpaceStructure:
    names = ["A11", "A12", "A21", "A22", "B11", "B12", "B21", "B22"]
    params = {n: {"initial": 0.0} for n in names}
    return StateSpaceStructure(["w1", "w2"], ["u1", "u2"],
                               [["A11", "A12"], ["A21", "A22"]],
                               [["B11", "B12"], ["B21", "B22"]], params, speed_unit="rad/s")


def _inputs(n: int, dt: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    sos = signal.butter(2, 5.0, fs=1 / dt, output="sos")
    return np.asarray(signal.sosfilt(sos, rng.normal(size=(n, 2)), axis=0) * 5)


def _mech() -> MechanicalStructure:
    return MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[1.0]],
                               {"M": {"initial": 2.0, "lower": 0.01}, "Fv": {"initial": 1.0}},
                               "N", "m/s")


def test_oe_fit_recovers_a_noisy_two_state_system() -> None:
    dt = 0.005
    segs = []
    model_true = OEModel(_free_2x2())
    theta_true = np.concatenate([A_TRUE.ravel(), B_TRUE.ravel()])
    rng = np.random.default_rng(7)
    for i, x0 in enumerate(([0.5, -0.5], [-1.0, 0.3])):
        u = _inputs(2000, dt, i)
        seg0 = make_segment(f"s{i}", np.arange(2000) * dt, u, np.zeros((2000, 2)),
                            ["u1", "u2"], ["w1", "w2"])
        y = model_true.simulate(theta_true, seg0, np.array(x0))
        y = y + 0.02 * np.std(y, axis=0) * rng.normal(size=y.shape)
        segs.append(make_segment(f"s{i}", seg0.t, u, y, ["u1", "u2"], ["w1", "w2"]))
    fit = OEFit(OEModel(_free_2x2()), starts=2, seed=1).fit(segs)
    assert fit is not None and fit.theta_.shape == (8,)
    err = np.abs(fit.theta_ - theta_true)
    assert np.all(err < np.maximum(5 * fit.std_, 0.02 * np.abs(theta_true) + 1e-3)), (
        fit.theta_, fit.std_)
    assert fit.x0_[0] == pytest.approx([0.5, -0.5], abs=0.05)
    assert fit.x0_[1] == pytest.approx([-1.0, 0.3], abs=0.05)
    assert len(fit.starts_) == 2
    assert fit.n_estimated_ == 8 + 4
    # validation initial state estimated with the parameters fixed
    assert fit.estimate_x0(segs[1]) == pytest.approx([-1.0, 0.3], abs=0.05)


def test_fit_refuses_segments_with_other_names() -> None:
    seg = make_segment("s", np.arange(100) * 0.01, np.ones((100, 2)), np.ones((100, 2)),
                       ["a", "b"], ["w1", "w2"])
    with pytest.raises(FitError, match="inputs"):
        OEFit(OEModel(_free_2x2())).fit([seg])


def test_oe_fit_with_coulomb_recovers_friction() -> None:
    dt = 0.002
    n = 2500
    t = np.arange(n) * dt
    F = 8 * np.sin(2 * np.pi * 0.8 * t) + 3 * np.sin(2 * np.pi * 3.1 * t)
    eff = make_effect("coulomb_friction", "v", ["v"], ["F"], "N", "m/s")
    model = OEModel(_mech(), [eff])
    seg = make_segment("s", t, F, np.zeros(n), ["F"], ["v"])
    y = model.simulate(np.array([2.0, 1.0, 2.0, 0.5]), seg, np.array([0.0]))
    y = y + 0.002 * np.random.default_rng(0).normal(size=y.shape)
    seg = make_segment("s", t, F, y, ["F"], ["v"])
    fit = OEFit(model, starts=1, theta0=np.array([1.5, 1.5, 1.0, 0.0])).fit([seg])
    p = fit.parameters()
    assert p["M"] == pytest.approx(2.0, rel=0.02)
    assert p["Fc"] == pytest.approx(2.0, rel=0.03)
    assert p["offset"] == pytest.approx(0.5, abs=0.05)
    assert set(fit.parameter_std()) == {"M", "Fv", "Fc", "offset"}


def test_window_sensitivities_that_overflow_give_the_penalty_and_print_nothing(
        monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]) -> None:
    """With an initialisation window the Jacobian solves the window's sensitivities: when a
    far start makes them overflow, the block is the penalty (as for a diverged simulation),
    not a LAPACK call that prints to stdout and stops the start."""
    from dvt_identify import fit as fit_mod
    from dvt_identify.structures import PENALTY

    n, dt = 200, 0.01
    seg = make_segment("s", np.arange(n) * dt, _inputs(n, dt, 0)[:, :1], np.zeros((n, 1)),
                       ["F"], ["v"])
    f = OEFit(OEModel(_mech()), init_window=10)
    theta = np.array([2.0, 1.0])
    real = fit_mod.simulate_sens

    def overflowing(*args: object, **kwargs: object):
        x, y, S = real(*args, **kwargs)
        return x, y, np.full_like(S, np.inf)

    monkeypatch.setattr(fit_mod, "simulate_sens", overflowing)
    J, r, _ = f._rows(theta, seg, np.zeros(1), np.ones(1), 0)
    assert np.all(r == PENALTY) and np.all(J == 0.0)
    assert capfd.readouterr().out == ""
