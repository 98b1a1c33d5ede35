"""Exact ZOH simulation, linear and with member forces (dry friction with a stick rule, compiled
smooth laws), checked against plain loops and the kernels' interpreted source."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import make_segment
from dvt_identify.effects import make_effect
from dvt_identify.simulation import OEModel, simulate_linear, zoh
from dvt_identify.structures import MechanicalStructure

A_TRUE = np.array([[-2.0, 1.5], [-3.0, -4.0]])
B_TRUE = np.array([[1.0, 0.0], [0.5, 2.0]])


def _inputs(n: int, dt: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    sos = signal.butter(2, 5.0, fs=1 / dt, output="sos")
    return np.asarray(signal.sosfilt(sos, rng.normal(size=(n, 2)), axis=0) * 5)


def _mech() -> MechanicalStructure:
    return MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[1.0]],
                               {"M": {"initial": 2.0, "lower": 0.01}, "Fv": {"initial": 1.0}},
                               "N", "m/s")


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


def test_compiled_loop_matches_python_loop() -> None:
    """The compiled kernel and its source run by the interpreter give the same states (coupled
    model, Coulomb on a member mixing both states, coded smooth terms and a brake-like
    capacity)."""
    from dvt_identify.simloop import COULOMB, STRIBECK, WINDAGE
    from dvt_identify.simulation import simulate_loop

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
    smooth: list[tuple[np.ndarray, Any]] = [(np.array([0.0, 1.0]), (WINDAGE, 0.3, 0.0, 0.0)),
                                            (c, (STRIBECK, 0.4, 0.2, 0.0)),
                                            (np.array([1.0, 0.0]), (COULOMB, 0.3, 0.05, 0.0)),
                                            (c, (STRIBECK, 0.2, 0.3, 0.02))]
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
    from dvt_identify.simloop import ABS_VISCOUS, COULOMB, STRIBECK
    from dvt_identify.simulation import simulate_loop

    dt = 0.001
    n = 4000
    t = np.arange(n) * dt
    A = np.array([[-1.5]])
    F = np.array([[0.5]])
    Ad, Gd = zoh(A, dt)
    w = (F @ np.atleast_2d(6.0 * np.sin(2 * np.pi * 1.3 * t))).T
    d = w @ Gd.T
    cap = np.asarray(1.0 + 0.5 * (np.sin(0.7 * t) > 0), dtype=float)
    smooth: list[tuple[np.ndarray, Any]] = [(np.array([1.0]), (STRIBECK, 0.8, 0.3, 0.0)),
                                            (np.array([-2.0]), (ABS_VISCOUS, 0.1, 0.0, 0.0)),
                                            (np.array([1.0]), (COULOMB, 0.3, 0.05, 0.0))]
    dry: list[tuple[np.ndarray, np.ndarray | float, float]] = [(np.array([1.0]), 2.0, 0.0),
                                                               (np.array([-0.5]), cap, 0.0)]
    x0 = np.array([0.3])
    fast = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry)
    slow = simulate_loop(A, Ad, Gd, F, w, d, x0, smooth, dry, reference=True)
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    assert np.sum(fast[:, 0] == 0.0) > 50  # it did stick
