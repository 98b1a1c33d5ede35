"""Position-dependent effect terms of the model node: contract, evaluation, live model."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest

from dvt_model.config import build_predictor, resolve
from dvt_model.contract import EFFECT_TERMS, term_needs_angle, validate_effects, validate_term
from dvt_model.errors import ContractError, ModelError
from dvt_model.hybrid import HybridModel
from dvt_model.terms import parse_terms

Array = np.ndarray


# ------------------------------------------------------------------------------ contract
def test_new_kinds_are_normalised_with_their_defaults() -> None:
    assert validate_term({"kind": "gravity", "member": [0, 1], "a": 1, "b": -2}) == {
        "kind": "gravity", "member": [0.0, 1.0], "a": 1.0, "b": -2.0, "reduction": 1.0}
    assert validate_term({"kind": "angle_periodic", "member": [1, 0], "angle": [1, -0.5],
                          "a": 0.1, "b": 0, "order": 16}) == {
        "kind": "angle_periodic", "member": [1.0, 0.0], "angle": [1.0, -0.5], "a": 0.1,
        "b": 0.0, "order": 16.0}
    assert validate_term({"kind": "library", "member": [0, 1], "k": 0.5}) == {
        "kind": "library", "member": [0.0, 1.0], "k": 0.5, "order": 0.0, "eps": 0.5,
        "speed": "", "trig": "", "input": "", "input_power": ""}
    assert EFFECT_TERMS["gravity"].driving and not EFFECT_TERMS["coulomb"].driving


@pytest.mark.parametrize(("entry", "message"), [
    ({"kind": "gravity", "member": [0, 1], "a": 1, "b": 0, "reduction": 0},
     "effects[0].reduction: 0.0 [1] is not admissible: expected (0, 1e+06] (member turns per "
     "turn of the loaded shaft, > 0)"),
    ({"kind": "gravity", "member": [0, 1], "a": math.nan, "b": 0},
     "effects[0].a: expected a finite number [N m], got nan"),
    ({"kind": "gravity", "member": [0, 1], "a": 1},
     "effects[0].b: missing (kind 'gravity' needs ['a', 'b'])"),
    ({"kind": "gravity", "member": [0, 1], "a": 1, "b": 0, "order": 2},
     "effects[0]: unknown field(s) ['order'] for kind 'gravity' (expected ['a', 'angle', 'b', "
     "'kind', 'member', 'reduction'])"),
    ({"kind": "angle_periodic", "member": [1, 0], "a": 1, "b": 0, "order": -1},
     "effects[0].order: -1.0 [1/rev] is not admissible: expected [0, 10000] (angle order per "
     "member revolution, >= 0)"),
    ({"kind": "angle_periodic", "member": [1, 0], "angle": [0, 0], "a": 1, "b": 0, "order": 1},
     "effects[0].angle: expected 2 finite numbers, not all zero, each |m| <= 1000, got [0, 0]"),
    ({"kind": "library", "member": [0, 1], "k": 1, "speed": "sgn"},
     "effects[0].speed: expected one of ['', 'sign', 'abs_sq', 'cube', 'lin', 'abs'], got "
     "'sgn' (speed factor S(v): '' 1, 'sign' sign_eps(v), 'abs_sq' |v| v, 'cube' v^3, 'lin' v, "
     "'abs' |v|)"),
    ({"kind": "library", "member": [0, 1], "k": 1, "input": "brake1", "input_power": "sq"},
     "effects[0].input_power: expected one of ['', 'abs_sq', 'cube'], got 'sq' (power P(u) of "
     "the input: '' u, 'abs_sq' |u| u, 'cube' u^3 (ignored without input))"),
    ({"kind": "library", "member": [0, 1], "k": 1, "trig": "tan"},
     "effects[0].trig: expected one of ['', 'cos', 'sin'], got 'tan' (angle factor T: '' 1, "
     "'cos' cos(order theta_a), 'sin' sin(order theta_a))"),
    ({"kind": "library", "member": [0, 1], "k": 1, "input": "motor"},
     "effects[0].input: expected one of ['', 'drive_motor', 'brake1', 'brake2', 'brake3'], "
     "got 'motor' (input factor u [A]: '' 1, else that current of /dvt/currents)"),
    ({"kind": "library", "member": [0, 1], "k": 1, "input": 0},
     "effects[0].input: expected one of ['', 'drive_motor', 'brake1', 'brake2', 'brake3'], "
     "got 0 (input factor u [A]: '' 1, else that current of /dvt/currents)"),
    ({"kind": "library", "member": [0, 1], "k": 1e7},
     "effects[0].k: 10000000.0 [N m per unit of the factors] is not admissible: expected "
     "[-1e+06, 1e+06] (coefficient)"),
    ({"kind": "library", "member": [0, 1], "k": 1, "eps": 0},
     "effects[0].eps: 0.0 [rad/s] is not admissible: expected [1e-06, 1000] (speed below "
     "which the sign is smoothed)"),
])
def test_bad_values_and_choices_are_refused_exactly(entry: dict[str, Any], message: str
                                                   ) -> None:
    with pytest.raises(ContractError) as exc:
        validate_term(entry)
    assert str(exc.value) == message


def test_the_entry_index_is_named_in_a_list() -> None:
    good = {"kind": "gravity", "member": [0, 1], "a": 1, "b": 0}
    with pytest.raises(ContractError, match=r"^effects\[1\]\.trig: expected one of"):
        validate_effects(json.dumps([good, {"kind": "library", "member": [1, 0], "k": 1,
                                            "trig": "COS"}]))


def test_which_terms_need_the_angle() -> None:
    lib = {"kind": "library", "member": [1.0, 0.0], "k": 1.0}
    assert term_needs_angle({"kind": "gravity"}) and term_needs_angle({"kind": "angle_periodic"})
    assert term_needs_angle({**lib, "trig": "cos"})
    assert not term_needs_angle({**lib, "trig": ""})
    assert not term_needs_angle({"kind": "coulomb"})


# ------------------------------------------------------------------------------ evaluation
def test_point_torques_match_the_hand_computed_laws() -> None:
    theta = np.array([0.7, 2.3])
    omega = np.array([30.0, -4.0])
    u = np.array([2.0, 0.1, 0.2, 0.3])
    terms = parse_terms([
        {"kind": "gravity", "member": [0, 1], "a": 1.5, "b": -0.4, "reduction": 20},
        {"kind": "angle_periodic", "member": [1, 0], "angle": [1.0, -1.0], "a": 0.02,
         "b": 0.03, "order": 16},
        {"kind": "library", "member": [0.5, 1.0], "k": 0.25, "speed": "sign", "trig": "sin",
         "order": 3, "input": "drive_motor", "eps": 0.1},
        {"kind": "library", "member": [1, 0], "k": 1e-5, "speed": "abs_sq"},
        {"kind": "library", "member": [0, 1], "k": 2e-3, "speed": "cube", "trig": "cos",
         "order": 2, "input": "brake3"},
        # actuator maps: a saturating torque constant, a gain that depends on the speed
        {"kind": "library", "member": [1, 0], "k": -0.01, "input": "drive_motor",
         "input_power": "abs_sq"},
        {"kind": "library", "member": [1, 0], "k": 3e-4, "input": "brake2",
         "input_power": "cube"},
        {"kind": "library", "member": [0, 1], "k": -5e-3, "speed": "lin",
         "input": "drive_motor"},
        {"kind": "library", "member": [1, 0], "k": 7e-3, "speed": "abs", "input": "brake1"},
    ])
    th_c3, th_mesh, w_m = 2.3, 0.7 - 2.3, 0.5 * 30.0 - 4.0
    grav = 1.5 * math.cos(th_c3 / 20) - 0.4 * math.sin(th_c3 / 20)
    ripple = 0.02 * math.cos(16 * th_mesh) + 0.03 * math.sin(16 * th_mesh)
    lib1 = 0.25 * math.tanh(w_m / 0.1) * math.sin(3 * (0.5 * 0.7 + 2.3)) * 2.0
    lib2 = 1e-5 * 30.0 * 30.0
    lib3 = 2e-3 * (-4.0) ** 3 * math.cos(2 * 2.3) * 0.3
    maps = (np.array([1.0, 0.0]) * (-0.01 * 2.0 * 2.0 + 3e-4 * 0.2 ** 3 + 7e-3 * 30.0 * 0.1)
            + np.array([0.0, 1.0]) * (-5e-3 * -4.0 * 2.0))
    expected = (np.array([0.0, 1.0]) * grav + np.array([1.0, 0.0]) * ripple
                + np.array([0.5, 1.0]) * lib1 + np.array([1.0, 0.0]) * lib2
                + np.array([0.0, 1.0]) * lib3 + maps)
    np.testing.assert_allclose(terms.angle_force(theta, omega, 0.0, u), expected, rtol=1e-13)
    # without inputs the input products vanish
    no_u = expected - np.array([0.5, 1.0]) * lib1 - np.array([0.0, 1.0]) * lib3 - maps
    np.testing.assert_allclose(terms.angle_force(theta, omega), no_u, rtol=1e-13)
    assert terms.extra_force(omega, 0.0).tolist() == [0.0, 0.0]


def test_a_held_torque_is_the_mean_over_the_steps_angle_interval() -> None:
    terms = parse_terms([{"kind": "angle_periodic", "member": [1, 0], "a": 0.3, "b": -0.2,
                          "order": 16}])
    theta, omega, dt = np.array([0.4, 0.0]), np.array([120.0, 0.0]), 1e-3
    grid = 0.4 + np.linspace(0.0, 120.0 * dt, 200001)
    law = 0.3 * np.cos(16 * grid) - 0.2 * np.sin(16 * grid)
    mean = float(np.sum(0.5 * (law[1:] + law[:-1])) / (len(grid) - 1))
    f = terms.angle_force(theta, omega, 0.0, None, dt)
    assert f[1] == 0.0
    assert f[0] == pytest.approx(mean, abs=1e-10)
    # 16 * 120 rad/s * 1 ms = 1.92 rad per step: clearly not the point value
    assert abs(f[0] - terms.angle_force(theta, omega)[0]) > 0.05


def test_terms_are_empty_only_without_any() -> None:
    assert parse_terms("[]").empty
    assert not parse_terms([{"kind": "library", "member": [1, 0], "k": 0.1}]).empty


# ------------------------------------------------------------------------------ hybrid + node
def test_the_hybrid_model_passes_inputs_and_step_to_the_angle_input_force() -> None:
    seen: list[tuple[list[float], float]] = []

    def spy(theta: Array, omega: Array, t: float, u: Array, dt: float) -> Array:
        seen.append((list(u), dt))
        return np.zeros(2)
    cfg = resolve({})
    model = HybridModel(cfg.rigid, cfg.brake, angle_input_force=spy)
    model.step(model.initial_state((10.0, 2.0)), 1e-3, 1.5, [0.0, 0.2, 0.0])
    assert ([1.5, 0.0, 0.2, 0.0], 1e-3) in seen  # the force held over the step
    assert all(u == [1.5, 0.0, 0.2, 0.0] for u, _ in seen)
    np.testing.assert_array_equal(model.angle_forces((0.0, 0.0), (1.0, 1.0), 0.0, np.ones(4)),
                                  [0.0, 0.0])


def test_angle_terms_need_the_physical_model() -> None:
    with pytest.raises(ModelError, match="^effects: force terms need the physical model"):
        resolve({"A": [-1.0, 0.0, 0.0, -2.0], "B": [1.0, 0.0, 0.0, 1.0],
                 "effects": json.dumps([{"kind": "gravity", "member": [0, 1], "a": 1,
                                         "b": 0}])})


def _run(effects: list[dict[str, Any]], reference: HybridModel, theta0: tuple[float, float],
         n: int = 1500, dt: float = 1e-3) -> tuple[Array, str]:
    """Feed the reference's simulated speeds and angles to the node's predictor built with
    ``effects``; the speed residuals (n, 2) and the model description."""
    t = np.arange(n) * dt
    im = 4.0 * np.sin(2 * np.pi * 1.5 * t) + 1.0
    ib = np.zeros((n, 3))
    state0 = reference.initial_state((5.0, 1.0), t=0.0, theta=theta0)
    sim = reference.simulate(t, im, ib, state0=state0)
    predictor, desc = build_predictor({"effects": json.dumps(effects)})
    res = np.array([predictor.update(float(t[k]), float(im[k]), ib[k], sim.omega[k],
                                     sim.theta[k]).residual for k in range(n)])
    return res, desc


def test_a_gravity_term_reproduces_the_hybrid_model_with_the_same_angle_force() -> None:
    cfg = resolve({})
    c, a, b, red = np.array([0.0, 1.0]), 0.8, -0.5, 2.0
    gravity = {"kind": "gravity", "member": c.tolist(), "a": a, "b": b, "reduction": red}

    def point_law(theta: Array, omega: Array, t: float) -> Array:
        th = float(c @ theta) / red
        return np.asarray(c * (a * math.cos(th) + b * math.sin(th)))

    def held_law(theta: Array, omega: Array, t: float, u: Array, dt: float) -> Array:
        """The law's exact mean over [theta, theta + omega dt] (held over the step)."""
        th0, d = float(c @ theta) / red, float(c @ omega) * dt / red
        if dt == 0.0 or abs(d) < 1e-9:
            return point_law(theta, omega, t)
        cm = (math.sin(th0 + d) - math.sin(th0)) / d
        sm = (math.cos(th0) - math.cos(th0 + d)) / d
        return np.asarray(c * (a * cm + b * sm))

    # a hand-written reference with the same held law: identical to round-off
    hand = HybridModel(cfg.rigid, cfg.brake, angle_input_force=held_law)
    res, desc = _run([gravity], hand, (0.3, 1.2))
    assert "1 angle term(s)" in desc
    assert float(np.max(np.abs(res))) < 1e-9
    # the law at the step start instead (no mean): the same up to O(dt); without the term
    # the prediction is far off (sign, phase and reduction matter)
    point = HybridModel(cfg.rigid, cfg.brake, angle_force=point_law)
    res_point, _ = _run([gravity], point, (0.3, 1.2))
    res_none, _ = _run([], point, (0.3, 1.2))
    assert float(np.max(np.abs(res_none))) > 10.0
    assert float(np.max(np.abs(res_point))) < 0.03 * float(np.max(np.abs(res_none)))
