"""Position-dependent effects: member angles, the gravity load, the ``unlisted`` library terms
and the mesh orders of a periodic disturbance (from the parameter set's teeth)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import Segment, make_segment
from dvt_identify.effects import (
    Effect,
    GravityLoad,
    PeriodicDisturbance,
    SegmentView,
    Unlisted,
    make_effect,
)
from dvt_identify.effects.position import (
    ANGLE_FROM_POSITION,
    ANGLE_FROM_SPEED,
    LibTerm,
    angle_of,
    cell_mean_trig,
    mesh_orders,
)
from dvt_identify.errors import DescriptionError
from dvt_identify.fit import OEFit
from dvt_identify.scoring import score_candidates
from dvt_identify.simulation import OEModel
from dvt_identify.structures import MechanicalStructure
from dvt_model.params import load_parameters

DT = 0.002
N = 4000
STATES = ["v"]
INPUTS = ["force"]
Array = np.ndarray


@dataclass(frozen=True)
class ViewWithAngles(SegmentView):
    """A view that carries measured angles (what a recording's ``position`` gives)."""

    angles: Array


def structure() -> MechanicalStructure:
    return MechanicalStructure(STATES, INPUTS, [["M"]], [["Fv"]], [[1.0]],
                               {"M": {"initial": 10, "lower": 1e-3},
                                "Fv": {"initial": 20, "lower": 0}}, "N", "rad/s")


def drive(seed: int) -> tuple[Array, Array]:
    """A force that turns the member mostly one way (the angle covers many revolutions) with
    low-passed noise and a reversal."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    sos = signal.butter(2, 3.0, fs=1 / DT, output="sos")
    f = (60 + 50 * np.sin(2 * np.pi * 0.25 * t) + 20 * np.sin(2 * np.pi * 1.3 * t + 1)
         + 60 * signal.sosfilt(sos, rng.normal(size=N)))
    return t, f


def synthetic(effect: Effect | None, p: list[float], seed: int = 1,
              noise: float = 0.005) -> Segment:
    """Data of ``M v' = -Fv v + f + tau_effect`` (M 10, Fv 20); the effect is locked to the
    measured angle/speed, so iterate to the fixed point."""
    model = OEModel(structure(), [effect] if effect is not None else [])
    t, f = drive(seed)
    y = np.zeros((N, 1))
    theta = np.array([10.0, 20.0, *p])
    for _ in range(10 if effect is not None else 1):
        y = model.simulate(theta, make_segment("s", t, f, y, INPUTS, STATES), np.array([0.5]))
    rng = np.random.default_rng(seed + 100)
    y = y + noise * np.std(y) * rng.normal(size=y.shape)
    return make_segment("s", t, f, y, INPUTS, STATES)


def test_angle_is_the_measured_position_when_present_else_the_integrated_speed() -> None:
    t = np.arange(1000) * 0.01
    y = np.column_stack([np.cos(t), 2.0 * np.ones_like(t)])
    u = np.zeros((1000, 1))
    view = SegmentView(0.01, u, y)
    th, src = angle_of(view, np.array([1.0, 0.5]))
    assert src == ANGLE_FROM_SPEED
    # the trapezoidal integral of cos(t) + 1 from 0: sin(t) + t within O(dt^2)
    assert np.max(np.abs(th - (np.sin(t) + t))) < 1e-4
    angles = np.column_stack([t, 3.0 * t])
    th2, src2 = angle_of(ViewWithAngles(0.01, u, y, angles), np.array([1.0, 0.5]))
    assert src2 == ANGLE_FROM_POSITION
    np.testing.assert_allclose(th2, 2.5 * t)


def test_step_means_of_cos_sin_do_not_alias() -> None:
    theta = np.linspace(0.0, 3.0, 301)
    c, s = cell_mean_trig(theta, 2.0)
    # the exact step mean of cos(2 theta) on [theta_n, theta_n+1]
    exact = (np.sin(2 * theta[1:]) - np.sin(2 * theta[:-1])) / (2 * np.diff(theta))
    np.testing.assert_allclose(c[:-1], exact, atol=1e-12)
    assert abs(s[0] - (1 - math.cos(0.02)) / 0.02) < 1e-12
    # a ripple of many periods per step averages out instead of aliasing to a slow wave
    fast = np.arange(100, dtype=np.float64) * (2 * math.pi + 0.01)
    cf, _ = cell_mean_trig(fast, 1.0)
    assert np.max(np.abs(cf[:-1])) < 0.01
    # a member at rest: the point value
    c0, s0 = cell_mean_trig(np.full(5, 0.3), 3.0)
    np.testing.assert_allclose(c0, math.cos(0.9))
    np.testing.assert_allclose(s0, math.sin(0.9))


def test_gravity_load_build_force_and_derived_figures() -> None:
    eff = make_effect("gravity_load", "v", STATES, INPUTS, "N", "rad/s",
                      options={"reductions": [10, 20]})
    assert isinstance(eff, GravityLoad)
    assert [s.name for s in eff.params] == ["gravity_a", "gravity_b", "reduction"]
    assert eff.gain_names() == ("gravity_a", "gravity_b")
    # a scanned reduction is fitted; a known one is held fixed
    assert eff.fixed_names() == ()
    known = make_effect("gravity_load", "v", STATES, INPUTS, options={"reduction": 20})
    assert known.fixed_names() == ("reduction",)
    view = SegmentView(0.001, np.zeros((3000, 1)), np.full((3000, 1), 4.0))
    assert [v[0] for v in eff.variants(view)] == ["reduction=10", "reduction=20"]
    f = eff.exogenous_force(np.array([0.0, -2.0, 20.0]), view)
    assert f is not None
    theta = 4.0 * np.arange(3000) * 0.001
    # the step mean of -2 sin(theta / 20) at 4 rad/s over 1 ms: the mid-step value
    np.testing.assert_allclose(f[:-1], -2.0 * np.sin((theta[:-1] + 0.002) / 20), atol=1e-9)
    d = eff.derived({"gravity_a": 0.0, "gravity_b": -2.0, "reduction": 20.0})
    # -2 sin(x) = 2 cos(x + pi/2)
    assert d["gravity_amplitude"] == pytest.approx(2.0)
    assert d["gravity_phase"] == pytest.approx(math.pi / 2)
    assert d["gravity_amplitude_behind_stage"] == pytest.approx(40.0)
    assert eff.inadmissible(np.array([0.0, 0.0, 20.0])) is not None
    assert eff.inadmissible(np.array([0.1, 0.0, 20.0])) is None
    with pytest.raises(DescriptionError, match="reductions must be > 0"):
        make_effect("gravity_load", "v", STATES, INPUTS, options={"reductions": [0, 20]})
    with pytest.raises(DescriptionError, match="not a state"):
        make_effect("gravity_load", "force", STATES, INPUTS)


def test_gravity_load_is_ranked_first_with_the_right_reduction() -> None:
    grav = make_effect("gravity_load", "v", STATES, INPUTS, "N", "rad/s",
                       options={"reductions": [20]})
    seg = synthetic(grav, [3.0, -6.0, 20.0])
    entries: list[tuple[str, dict[str, object]]] = [
        ("coulomb_friction", {}), ("windage", {}), ("periodic_disturbance", {"orders": [1, 2]}),
        ("gravity_load", {"reductions": [5, 20, 80]})]
    cands = [make_effect(n, "v", STATES, INPUTS, "N", "rad/s", options=o) for n, o in entries]
    fit = OEFit(OEModel(structure()), starts=1).fit([seg])
    scores = score_candidates(fit, [seg], cands)
    assert scores[0].effect.name == "gravity_load", [(s.label, s.r2) for s in scores]
    assert scores[0].variant == "reduction=20"
    assert scores[0].p_value < 1e-6
    assert scores[0].extra["angle_source"] == ANGLE_FROM_SPEED
    # the implied gains are the effect's (a first-order score on the baseline residual)
    imp = scores[0].implied
    assert imp["gravity_a"] == pytest.approx(3.0, rel=0.3)
    assert imp["gravity_b"] == pytest.approx(-6.0, rel=0.3)


def test_mesh_orders_come_from_the_parameter_set() -> None:
    for name in ("physical", "thesis"):
        teeth = [float(st.sun) for st in load_parameters(name).stages]
        assert mesh_orders(name) == list(dict.fromkeys(teeth))
    eff = make_effect("periodic_disturbance", "v", STATES, INPUTS,
                      options={"orders": [1, 2], "mesh_orders": True})
    assert isinstance(eff, PeriodicDisturbance)
    view = SegmentView(0.001, np.zeros((10, 1)), np.zeros((10, 1)))
    assert [lab for lab, _ in eff.variants(view)] == [
        f"order={k:g}" for k in [1.0, 2.0, *mesh_orders("physical")]]
    with pytest.raises(DescriptionError, match="needs 'orders'"):
        make_effect("periodic_disturbance", "v", STATES, INPUTS)


def test_unlisted_library_terms_formula_and_subset() -> None:
    lib = make_effect("unlisted", "v", STATES, INPUTS, "N", "rad/s",
                      options={"orders": [1], "inputs": ["force"]})
    assert isinstance(lib, Unlisted) and lib.library
    names = [s.name for s in lib.params]
    assert names == ["k_sgn_v", "k_absq_v", "k_cube_v", "k_cos1_v", "k_sgn_cos1_v", "k_sin1_v",
                     "k_sgn_sin1_v", "k_sgn_u_force_v", "k_cos1_u_force_v", "k_sin1_u_force_v",
                     "k_w_u_force_v", "k_absw_u_force_v", "k_u_force_absq_v",
                     "k_u_force_cube_v"]
    assert lib.label() == "unlisted@v"
    assert all(s.initial == s.null == 0.0 for s in lib.params)
    prop = lib.subset([0, 4], np.array([0.5, -0.25]))
    assert not prop.library
    assert prop.formula([0.5, -0.25]) == ("tau_v = 0.5 N*sign(w_v) -0.25 N*sign(w_v)*cos(1*th_v)")
    assert prop.label() == "unlisted@v: " + prop.formula([0.5, -0.25])
    assert LibTerm("abs_sq").unit("N m", "rad/s", "A") == "N m/(rad/s)^2"
    assert LibTerm("", "cos", 16.0, 0).unit("N m", "rad/s", "A") == "N m/A"
    # the force is the sum of the kept terms on the measured speed and angle
    y = np.column_stack([np.linspace(-1.0, 1.0, 2001)])
    view = SegmentView(0.01, np.zeros((2001, 1)), y)
    f = prop.exogenous_force(np.array([0.5, -0.25]), view)
    th, _ = angle_of(view, np.array([1.0]))
    c, _ = cell_mean_trig(th, 1.0)
    assert f is not None
    np.testing.assert_allclose(f, np.sign(y[:, 0]) * (0.5 - 0.25 * c))
    assert prop.inadmissible(np.zeros(2)) is not None
    assert prop.inadmissible(np.array([0.5, 0.0])) is None
    with pytest.raises(DescriptionError, match="not an input"):
        make_effect("unlisted", "v", STATES, INPUTS, options={"inputs": ["nope"]})


def test_unlisted_mesh_orders_use_the_teeth() -> None:
    lib = make_effect("unlisted", "v", STATES, INPUTS, options={"mesh_orders": True})
    assert isinstance(lib, Unlisted)
    orders = {t.order for t in lib.terms if t.trig}
    assert orders == {1.0, 2.0, 3.0, *mesh_orders("physical")}
