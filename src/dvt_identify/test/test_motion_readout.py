"""Effects evaluated on the measured motion (``unlisted``, ``gravity_load``,
``periodic_disturbance``) on a structure with hidden states: a position sensor (the EMPS
benchmark's output, a linear axis) or one speed sensor of two members. Before, such an effect
multiplied the outputs (N, ny) by a member vector over the states (nx) and crashed with a
numpy shape error in the middle of the loop."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from dvt_identify.data import Segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects import Unlisted
from dvt_identify.effects.base import SegmentView
from dvt_identify.effects.position import (
    ANGLE_FROM_POSITION,
    ANGLE_FROM_SPEED,
    POLY,
    legendre_of_travel,
    member_motion,
)
from dvt_identify.errors import DescriptionError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_identify.unlisted import search_unlisted

DT = 0.002
PERIOD = 0.5  # [m] the spatial period of the cart's position-dependent force
ORDER = 2 * np.pi / PERIOD  # [rad/m]


def two_mass(candidates: list[dict[str, Any]]) -> Description:
    """Two members on a spring, only the motor's speed measured."""
    return parse_description({
        "name": "two-mass",
        "inputs": [{"name": "torque", "topic": "/t/drive", "field": "effort", "joint": "m"}],
        "outputs": [{"name": "w_motor", "topic": "/t/joint_states", "field": "velocity",
                     "joint": "m"}],
        "structure": {"type": "mechanical", "members": ["motor", "load"],
                      "mass": [["Jm", 0.0], [0.0, "Jl"]], "damping": [["dm", 0.0], [0.0, 0.0]],
                      "stiffness": [["k", "-k"], ["-k", "k"]], "input_matrix": [[1.0], [0.0]],
                      "outputs": {"w_motor": "motor"},
                      "parameters": {"Jm": {"initial": 1.0, "lower": 1e-6},
                                     "Jl": {"initial": 1.0, "lower": 1e-6},
                                     "dm": {"initial": 1.0, "lower": 0.0},
                                     "k": {"initial": 10.0, "lower": 0.0}}},
        "candidates": candidates,
    }, "test")


def view(y: np.ndarray, dt: float = DT) -> SegmentView:
    return SegmentView(dt, np.zeros((y.shape[0], 1)), y, None)


def test_a_position_output_gives_the_member_its_speed_and_angle(
        axis_desc: Callable[..., Description]) -> None:
    """The member's angle is the measured position, its speed the position's central
    difference (exact for a parabola)."""
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": []}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted) and lib.readout == (0,)  # position reads cart_angle
    t = np.arange(200) * DT
    q = 0.1 + 0.3 * t - 0.5 * t ** 2
    speed, angle, source = member_motion(view(q[:, None]), lib.require_member(), lib.readout)
    assert source == ANGLE_FROM_POSITION
    np.testing.assert_allclose(angle, q)
    np.testing.assert_allclose(speed[1:-1], (0.3 - t)[1:-1], atol=1e-12)
    assert lib.regressors(view(q[:, None])).shape == (200, len(lib.terms))


def test_a_speed_output_of_a_structure_with_angles_integrates_the_angle() -> None:
    """One speed sensor of two members: an effect on the measured member reads its speed and
    integrates it into its angle; on the member without a sensor the description is refused
    at load, naming the candidate, the states it needs and what is measured."""
    desc = two_mass([{"effect": "periodic_disturbance", "where": "motor", "orders": [1.0]}])
    eff = desc.make_candidates()[0]
    t = np.arange(500) * DT
    w = 2.0 + np.sin(t)
    speed, angle, source = member_motion(view(w[:, None]), eff.require_member(), eff.readout)
    assert source == ANGLE_FROM_SPEED
    np.testing.assert_allclose(speed, w)
    np.testing.assert_allclose(angle, 2.0 * t + 1.0 - np.cos(t), atol=1e-6)
    with pytest.raises(DescriptionError) as err:
        two_mass([{"effect": "gravity_load", "where": "load", "reduction": 1.0}]
                 ).make_candidates()
    text = str(err.value)
    assert "gravity_load@load" in text and "neither speed state 3 nor its angle state 1" in text
    assert "w_motor = motor" in text, text
    # an effect that does not read the motion (simulated on the states) is fine there
    assert two_mass([{"effect": "coulomb_friction", "where": "load"}]).make_candidates()


def test_unlisted_finds_a_position_force_from_a_position_sensor(
        axis_desc: Callable[..., Description],
        axis_record: Callable[..., Segment]) -> None:
    """On a cart whose position is measured, the library's angle terms at the axis' spatial
    order find the force that depends on the position (a sine of it, not a friction), and on
    the same cart without it the search proposes nothing."""
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [],
                  "orders": [ORDER / 2, ORDER, 2 * ORDER]}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted)
    seg = axis_record(1, amplitude=1.5, order=ORDER)
    span = float(np.ptp(seg.y[:, 0]))
    assert span > 2 * PERIOD, span  # the cart travels over the force's periods
    fit = OEFit(OEModel(desc.structure), starts=1, init_window=0).fit([seg])
    sc = search_unlisted(fit, [seg], [lib])
    assert sc is not None
    eff = sc.effect
    assert isinstance(eff, Unlisted)
    assert any(t.trig == "sin" and t.order == ORDER and t.speed == "" for t in eff.terms), \
        eff.label()
    assert sc.p_value < 1e-6
    clean = axis_record(2, amplitude=0.0)
    fit0 = OEFit(OEModel(desc.structure), starts=1, init_window=0).fit([clean])
    assert search_unlisted(fit0, [clean], [lib]) is None


def test_travel_polynomials_build_evaluate_and_refuse_bad_options(
        axis_desc: Callable[..., Description]) -> None:
    """``travel: [lo, hi]`` adds ``P_j(x)`` and ``sign(s) P_j(x)``, ``j = 1..degree``, on the
    position normalised to [-1, 1] over the travel (and no periodic terms unless ``orders`` is
    given); the formula says what ``x`` is; the model node has no such factor, so a proposal
    with one is reported as not pushable; a bad travel or degree is refused naming both."""
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [], "travel": [0.5, 1.5],
                  "degree": 3}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted)
    poly = [t for t in lib.terms if t.trig == POLY]
    assert sorted((t.speed, t.order) for t in poly) == sorted(
        (sp, float(j)) for sp in ("", "sign") for j in (1, 2, 3))
    assert not any(t.trig in ("cos", "sin") for t in lib.terms)
    q = np.linspace(0.5, 1.5, 101)
    x = 2 * q - 2.0
    np.testing.assert_allclose(legendre_of_travel(q, 2, (0.5, 1.5)), 1.5 * x ** 2 - 0.5)
    p3 = next(t for t in poly if t.order == 3 and t.speed == "sign")
    w = np.where(np.arange(101) < 50, 1.0, -1.0)
    np.testing.assert_allclose(p3.evaluate(w, q, np.zeros((101, 1))),
                               w * (2.5 * x ** 3 - 1.5 * x), atol=1e-12)
    prop = lib.subset([lib.terms.index(p3)], np.array([2.0]))
    assert "sign(w_cart)*P3(x_cart)" in prop.formula([2.0])
    assert "x_cart = (2*th_cart - (0.5) - (1.5)) / (1)" in prop.formula([2.0])
    assert prop.model_terms(np.array([2.0]), ["position"]) is None
    assert "polynomial" in prop.why_no_term(["position"])
    for bad, needle in (({"travel": [1.0, 1.0]}, "travel: expected [lo, hi] with lo < hi"),
                        ({"travel": [0.0]}, "travel"),
                        ({"travel": [0.0, 1.0], "degree": 9}, "degree: expected an integer"),
                        ({"travel": [0.0, 1.0], "degree": 2.5}, "degree")):
        with pytest.raises(DescriptionError, match="unlisted@cart") as err:
            axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [], **bad}]
                 ).make_candidates()
        assert needle in str(err.value), err.value


def test_unlisted_finds_a_friction_that_grows_along_the_travel(
        axis_desc: Callable[..., Description],
        axis_record: Callable[..., Segment]) -> None:
    """A cart whose friction grows along its travel and has no period (a ball screw's preload
    or a seal: ``2 P1(x) sign(v)``, smoothed over 0.01 m/s, travel [-1, 2] m) is found by the
    travel polynomials as ``sign(w) P1(x)`` with a coefficient within 30 % of the truth's
    ``-2 N`` (``tau`` acts along the motion); the same cart without it gets no proposal."""
    span = (-1.0, 2.0)
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [], "travel": list(span)}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted)

    def friction(q: float, v: float) -> float:
        x = (2 * q - span[0] - span[1]) / (span[1] - span[0])
        return float(np.tanh(v / 0.01) * 2.0 * x)

    seg = axis_record(3, amplitude=0.0, force=friction)
    fit = OEFit(OEModel(desc.structure), starts=1, init_window=0).fit([seg])
    sc = search_unlisted(fit, [seg], [lib])
    assert sc is not None and sc.p_value < 1e-6
    eff = sc.effect
    assert isinstance(eff, Unlisted)
    k = {(t.speed, t.trig, t.order): s.initial for t, s in zip(eff.terms, eff.params,
                                                                 strict=True)}
    assert -2.6 < k.get(("sign", POLY, 1.0), 0.0) < -1.4, eff.label()
    clean = axis_record(4, amplitude=0.0)
    fit0 = OEFit(OEModel(desc.structure), starts=1, init_window=0).fit([clean])
    assert search_unlisted(fit0, [clean], [lib]) is None
