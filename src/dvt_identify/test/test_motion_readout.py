"""Effects evaluated on the measured motion (``unlisted``, ``gravity_load``,
``periodic_disturbance``) on a structure with hidden states: a position sensor (the EMPS
benchmark's output, a linear axis) or one speed sensor of two members. Before, such an effect
multiplied the outputs (N, ny) by a member vector over the states (nx) and crashed with a
numpy shape error in the middle of the loop."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects import Unlisted
from dvt_identify.effects.base import SegmentView
from dvt_identify.effects.position import ANGLE_FROM_POSITION, ANGLE_FROM_SPEED, member_motion
from dvt_identify.errors import DescriptionError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_identify.unlisted import search_unlisted

DT = 0.002
N = 5000
PERIOD = 0.5  # [m] the spatial period of the cart's position-dependent force
ORDER = 2 * np.pi / PERIOD  # [rad/m]


def cart(candidates: list[dict[str, Any]]) -> Description:
    """A cart on a linear axis, its position measured, its speed hidden:
    ``q' = v, M v' = F - Fv v + effects``, ``y = q`` [m]."""
    return parse_description({
        "name": "cart",
        "inputs": [{"name": "force", "topic": "/c/drive", "field": "effort", "joint": "x"}],
        "outputs": [{"name": "position", "topic": "/c/joint_states", "field": "position",
                     "joint": "x"}],
        "structure": {"type": "mechanical", "members": ["cart"], "mass": [["M"]],
                      "damping": [["Fv"]], "stiffness": [[0.0]], "input_matrix": [[1.0]],
                      "outputs": {"position": "cart_angle"}, "force_unit": "N",
                      "speed_unit": "m/s", "angle_unit": "m",
                      "parameters": {"M": {"initial": 1.0, "lower": 0.001},
                                     "Fv": {"initial": 1.0, "lower": 0.0}}},
        "candidates": candidates,
        "fit": {"starts": 1, "refit_starts": 1},
    }, "test")


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


def test_a_position_output_gives_the_member_its_speed_and_angle() -> None:
    """The member's angle is the measured position, its speed the position's central
    difference (exact for a parabola)."""
    desc = cart([{"effect": "unlisted", "where": "cart", "inputs": []}])
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


def simulate_cart(seed: int, amplitude: float, noise: float = 2e-5) -> Segment:
    """``2 v' = F - 5 v - amplitude sin(ORDER q)`` (a force that depends on where the cart
    is: a cogging or a cable, no named candidate), simulated by the identifier's own model (the
    position force iterated to its fixed point as an input), the position measured with white
    noise [m]; a filtered random force moves the cart over about three periods."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    sos = signal.butter(2, 2.0, fs=1 / DT, output="sos")
    f = 8 * np.sin(2 * np.pi * 0.2 * t + seed) + 6 * signal.sosfilt(sos, rng.normal(size=N))
    model = OEModel(cart([]).structure, [])
    theta, x0 = np.array([2.0, 5.0]), np.zeros(2)
    y = np.zeros((N, 1))
    for _ in range(12 if amplitude else 1):
        extra = amplitude * np.sin(ORDER * y[:, 0])
        y = model.simulate(theta, make_segment("c", t, f - extra, y, ["force"],
                                               ["position"]), x0)
    y = y + noise * rng.normal(size=y.shape)
    return make_segment(f"cart{seed}", t, f, y, ["force"], ["position"])


def test_unlisted_finds_a_position_force_from_a_position_sensor() -> None:
    """On a cart whose position is measured, the library's angle terms at the axis' spatial
    order find the force that depends on the position (a sine of it, not a friction), and on
    the same cart without it the search proposes nothing."""
    desc = cart([{"effect": "unlisted", "where": "cart", "inputs": [],
                  "orders": [ORDER / 2, ORDER, 2 * ORDER]}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted)
    seg = simulate_cart(1, amplitude=1.5)
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
    clean = simulate_cart(2, amplitude=0.0)
    fit0 = OEFit(OEModel(desc.structure), starts=1, init_window=0).fit([clean])
    assert search_unlisted(fit0, [clean], [lib]) is None
