"""Structures, exact ZOH simulation (linear and with dry friction) and the OE fit."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import make_segment
from dvt_identify.effects import make_effect
from dvt_identify.errors import DescriptionError, FitError
from dvt_identify.oe import (
    MechanicalStructure,
    ModelStructure,
    OEFit,
    OEModel,
    ParamMatrix,
    StateSpaceStructure,
    simulate_linear,
    zoh,
)

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


def test_zoh_scalar_is_exact() -> None:
    Ad, Gd = zoh(np.array([[-3.0]]), 0.01)
    assert Ad[0, 0] == pytest.approx(math.exp(-0.03))
    assert Gd[0, 0] == pytest.approx((math.exp(-0.03) - 1) / -3.0)


def test_modal_simulation_matches_plain_loop() -> None:
    Ad, Gd = zoh(A_TRUE, 0.005)
    u = _inputs(500, 0.005, 0)
    d = u @ (Gd @ B_TRUE).T
    x0 = np.array([0.3, -0.2])
    x = simulate_linear(Ad, d, x0)
    ref = np.empty_like(x)
    ref[0] = x0
    for k in range(499):
        ref[k + 1] = Ad @ ref[k] + d[k]
    assert x == pytest.approx(ref, abs=1e-12)


def test_structures_satisfy_the_protocol_and_build_matrices() -> None:
    st = _free_2x2()
    assert isinstance(st, ModelStructure)
    a, b, f = st.matrices(np.concatenate([A_TRUE.ravel(), B_TRUE.ravel()]))
    np.testing.assert_allclose(a, A_TRUE)
    np.testing.assert_allclose(b, B_TRUE)
    np.testing.assert_allclose(f, np.eye(2))
    mech = MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[2.0]],
                               {"M": {"initial": 4.0}, "Fv": 8.0})
    A, B, F = mech.matrices(np.array([4.0, 8.0]))
    assert (A[0, 0], B[0, 0], F[0, 0]) == pytest.approx((-2.0, 0.5, 0.25))


def test_param_matrix_entries_and_errors() -> None:
    pm = ParamMatrix([["-a", "2.5*b"], [1.0, "0"]], "X", ["a", "b"])
    assert pm(np.array([2.0, 4.0])) == pytest.approx(np.array([[-2.0, 10.0], [1.0, 0.0]]))
    with pytest.raises(DescriptionError, match=r"X\[0\]\[1\]: 'c' is not a number"):
        ParamMatrix([["a", "c"]], "X", ["a"])
    with pytest.raises(DescriptionError, match=r"X: expected shape \(2, 2\), got \(1, 2\)"):
        ParamMatrix([["a", "a"]], "X", ["a"], (2, 2))


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


def _mech() -> MechanicalStructure:
    return MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[1.0]],
                               {"M": {"initial": 2.0, "lower": 0.01}, "Fv": {"initial": 1.0}},
                               "N", "m/s")


def test_coulomb_stick_rule() -> None:
    """Below the friction level a body at rest stays at rest; above it, it moves; and a
    decelerating body stops exactly at zero and stays there."""
    dt = 0.001
    n = 3000
    t = np.arange(n) * dt
    F = np.where(t < 1.0, 4.0, np.where(t < 2.0, 6.0, 0.0))  # Fc = 5
    coul = make_effect("coulomb_friction", "v", ["v"], ["F"], options={"offset": False})
    model = OEModel(_mech(), [coul])
    seg = make_segment("s", t, F, np.zeros(n), ["F"], ["v"])
    y = model.simulate(np.array([2.0, 1.0, 5.0]), seg, np.array([0.0]))[:, 0]
    assert np.all(y[t < 1.0] == 0.0)
    assert y[int(1.5 / dt)] > 0.1
    assert y[-1] == 0.0 and np.all(y >= 0.0)
    # from rest at 0 with the force lower than Fc the speed stays exactly 0
    stop = int(np.argmax((t > 2.0) & (y == 0.0)))
    assert np.all(y[stop:] == 0.0)


def test_generic_loop_matches_scalar_loop() -> None:
    """A decoupled two-state model with Coulomb on state 1 gives state 1 exactly like the
    one-state model (the generic and the scalar loop implement the same rule)."""
    dt = 0.002
    n = 2000
    t = np.arange(n) * dt
    F = 8 * np.sin(2 * np.pi * 0.8 * t) + 3 * np.sin(2 * np.pi * 3.1 * t)
    one = OEModel(_mech(), [make_effect("coulomb_friction", "v", ["v"], ["F"])])
    seg1 = make_segment("s", t, F, np.zeros(n), ["F"], ["v"])
    y1 = one.simulate(np.array([2.0, 1.0, 6.0, 0.5]), seg1, np.array([0.2]))
    two_st = MechanicalStructure(["v", "w"], ["F"], [["M", 0.0], [0.0, 1.0]],
                                 [["Fv", 0.0], [0.0, 3.0]], [[1.0], [1.0]],
                                 {"M": {"initial": 2.0}, "Fv": {"initial": 1.0}}, "N", "m/s")
    two = OEModel(two_st, [make_effect("coulomb_friction", "v", ["v", "w"], ["F"])])
    seg2 = make_segment("s", t, F, np.zeros((n, 2)), ["F"], ["v", "w"])
    y2 = two.simulate(np.array([2.0, 1.0, 6.0, 0.5]), seg2, np.array([0.2, 0.0]))
    assert y2[:, 0] == pytest.approx(y1[:, 0], abs=1e-9)
    assert np.sum(y1[:, 0] == 0.0) > 10  # it did stick


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


def test_compiled_loop_matches_python_loop() -> None:
    """The compiled kernel and its source run by the interpreter give the same states (coupled
    model, Coulomb on a member mixing both states, coded smooth terms and a brake-like
    capacity)."""
    from dvt_identify.oe import simulate_loop
    from dvt_identify.simloop import STRIBECK, WINDAGE

    dt = 0.002
    n = 1500
    t = np.arange(n) * dt
    u = np.column_stack([8 * np.sin(2 * np.pi * 0.8 * t), (np.sin(t) > 0).astype(float)])
    A = np.array([[-3.0, 1.0], [0.5, -2.0]])
    B = np.array([[1.0, 0.0], [0.3, 0.0]])
    F = np.array([[0.5, 0.1], [0.1, 0.8]])
    Ad, Gd = zoh(A, dt)
    w = u @ B.T
    d = w @ Gd.T
    c = np.array([1.0, -0.4])
    smooth: list[tuple[np.ndarray, Any]] = [(np.array([0.0, 1.0]), (WINDAGE, 0.3, 0.0)),
                                            (c, (STRIBECK, 0.4, 0.2))]
    brake: np.ndarray = np.asarray(6.0 * u[:, 1], dtype=float)
    dry: list[tuple[np.ndarray, np.ndarray | float, float]] = [(c, 3.0, 0.2), (c, brake, 0.0)]
    x0 = np.array([0.5, -0.2])
    fast = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry)
    slow = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry, reference=True)
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    assert np.sum(np.abs(fast @ c) < 1e-12) > 20  # the member did stick


def test_compiled_scalar_loop_matches_python_loop() -> None:
    """One state: the compiled scalar kernel (dry members lumped in generalised coordinates)
    equals its interpreted source, with Coulomb, a time-varying capacity and Stribeck."""
    from dvt_identify.oe import simulate_loop
    from dvt_identify.simloop import ABS_VISCOUS, STRIBECK

    dt = 0.001
    n = 4000
    t = np.arange(n) * dt
    A = np.array([[-1.5]])
    F = np.array([[0.5]])
    Ad, Gd = zoh(A, dt)
    w = (F @ np.atleast_2d(6.0 * np.sin(2 * np.pi * 1.3 * t))).T
    d = w @ Gd.T
    cap = np.asarray(1.0 + 0.5 * (np.sin(0.7 * t) > 0), dtype=float)
    smooth: list[tuple[np.ndarray, Any]] = [(np.array([1.0]), (STRIBECK, 0.8, 0.3)),
                                            (np.array([-2.0]), (ABS_VISCOUS, 0.1, 0.0))]
    dry: list[tuple[np.ndarray, np.ndarray | float, float]] = [(np.array([1.0]), 2.0, 0.0),
                                                               (np.array([-0.5]), cap, 0.0)]
    x0 = np.array([0.3])
    fast = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry)
    slow = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry, reference=True)
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    assert np.sum(fast[:, 0] == 0.0) > 50  # it did stick
