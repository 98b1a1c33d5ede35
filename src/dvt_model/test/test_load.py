"""The joint load (dvt_model.load) and the hybrid model's angles with it: pure, no ROS."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dvt_model.errors import ModelError
from dvt_model.hybrid import HybridModel
from dvt_model.load import (
    INCH,
    LOAD_PRESETS,
    POUND,
    Arm,
    JointLoad,
    OutputStage,
    load_joint_load,
    parse_joint_load,
    thesis_arm,
)
from dvt_model.params import load_parameters
from dvt_model.requirements import baseline_requirement


def test_thesis_arm_gives_the_baseline_torque_of_the_requirement() -> None:
    arm = thesis_arm()
    assert arm.length == pytest.approx(1.8034) and arm.mass == pytest.approx(90.718474)
    assert arm.payload == pytest.approx(108.8621688)
    assert arm.inertia == pytest.approx(452.3935911672231, rel=1e-12)
    assert arm.gravity_torque(0.0) == pytest.approx(2728.3854843854533, rel=1e-12)
    assert arm.torque(1.0, 0.0) == pytest.approx(3180.7790755526767, rel=1e-12)
    assert round(float(arm.torque(1.0))) == 3181
    # the same figure as dvt_model.requirements (what `dvt-model requirement` prints)
    assert arm.torque(1.0) == pytest.approx(baseline_requirement().torque, rel=1e-12)
    # the equation's terms: (Mp/3 + Ma) l^2 and (Mp/2 + Ma) l g
    mp, ma, l_ = 200 * POUND, 240 * POUND, 71 * INCH
    assert arm.inertia == pytest.approx((mp / 3 + ma) * l_**2)
    assert arm.gravity_coefficient == pytest.approx((mp / 2 + ma) * l_ * 9.81)


def test_gravity_torque_with_the_arm_at_0_and_90_degrees() -> None:
    arm = thesis_arm()
    assert arm.gravity_torque(0.0) == pytest.approx(arm.gravity_coefficient)
    assert abs(arm.gravity_torque(math.pi / 2)) < 1e-9
    assert arm.torque(2.0, math.pi / 2) == pytest.approx(2.0 * arm.inertia)
    vec = np.asarray(arm.torque(np.array([0.0, 1.0]), np.array([0.0, math.pi])))
    assert vec.shape == (2,) and vec[1] == pytest.approx(arm.inertia - arm.gravity_coefficient)


def test_output_stage_reflection_and_efficiency() -> None:
    stage = OutputStage(100.0, 0.8)
    assert stage.input_torque(100.0, 1.0) == pytest.approx(100.0 / 80.0)  # lifting
    assert stage.input_torque(100.0, -1.0) == pytest.approx(100.0 * 0.8 / 100.0)  # lowering
    assert stage.reflected_inertia(500.0) == pytest.approx(0.05)
    load = JointLoad(stage, thesis_arm(zero_angle=-math.pi / 2))
    assert load.reflected_inertia == pytest.approx(thesis_arm().inertia / 1e4)
    assert load.arm_angle(0.0) == pytest.approx(-math.pi / 2)
    assert load.carrier3_angle(load.arm_angle(123.0)) == pytest.approx(123.0)
    # arm horizontal (carrier 3 turned a quarter joint turn): full gravity on carrier 3
    th = load.carrier3_angle(0.0)
    c = thesis_arm().gravity_coefficient
    assert load.carrier3_torque(th, 10.0) == pytest.approx(-c / (100 * 0.8), rel=1e-6)
    assert load.carrier3_torque(th, -10.0) == pytest.approx(-c * 0.8 / 100, rel=1e-6)
    assert load.carrier3_torque(th, 0.0) == pytest.approx(-c / 100 * 0.5 * (1 / 0.8 + 0.8))
    # hanging and straight up: no gravity torque
    assert abs(load.carrier3_torque(0.0, 1.0)) < 1e-9
    assert abs(load.carrier3_torque(load.carrier3_angle(math.pi / 2), 1.0)) < 1e-9
    assert load.carrier3_requirement(1.0, 0.0) == pytest.approx(thesis_arm().torque(1.0) / 80)
    np.testing.assert_allclose(load.generalised_force([5.0, th], [0.0, 10.0]),
                               [0.0, load.carrier3_torque(th, 10.0)])


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"length": 0.0, "mass": 1.0}, "length"), ({"length": 1.0, "mass": -1.0}, "mass"),
    ({"length": 1.0, "mass": 1.0, "payload": float("nan")}, "payload"),
    ({"length": 1.0, "mass": 1.0, "zero_angle": 10.0}, "zero_angle"),
])
def test_arm_refuses_bad_values(kwargs: dict[str, float], field: str) -> None:
    with pytest.raises(ModelError, match=field):
        Arm(**kwargs)


def test_stage_refuses_bad_values() -> None:
    with pytest.raises(ModelError, match="reduction"):
        OutputStage(0.0)
    with pytest.raises(ModelError, match="efficiency"):
        OutputStage(10.0, 1.5)


def test_presets_and_yaml(tmp_path: Path) -> None:
    assert load_joint_load("none") is None
    arm = load_joint_load("arm")
    full = load_joint_load("arm-payload")
    assert arm is LOAD_PRESETS["arm"] and arm is not None and full is not None
    assert arm.arm.payload == 0.0 and full.arm.payload == pytest.approx(240 * POUND)
    path = tmp_path / "load.yaml"
    import yaml
    path.write_text(yaml.safe_dump(full.to_mapping()), encoding="utf-8")
    again = load_joint_load(path)
    assert again is not None and again.arm == full.arm and again.stage == full.stage
    with pytest.raises(ModelError, match="unknown load"):
        load_joint_load("arm-elephant")
    with pytest.raises(ModelError, match="output_stage.reduction"):
        parse_joint_load({"output_stage": {"reduction": -1}, "arm": {"length": 1, "mass": 1}})
    with pytest.raises(ModelError, match="arm.colour"):
        parse_joint_load({"output_stage": {"reduction": 1}, "arm": {"length": 1, "mass": 1,
                                                                     "colour": "red"}})


# -- the hybrid model's angles ---------------------------------------------------------------

def _model(load: JointLoad | None = None) -> HybridModel:
    return HybridModel.from_params(load_parameters("physical"), load=load)


def test_angles_integrate_the_speeds() -> None:
    model = _model()
    n = 2000
    t = np.arange(n) * 1e-3
    im = np.where(t < 1.0, 3.0, -1.0)
    ib = np.zeros((n, 3))
    ib[t > 0.5, 0] = 2.0  # gear 1 engages while turning: slip, lock, then 1-DOF
    res = model.simulate(t, im, ib)
    assert res.theta.shape == (n, 2) and np.all(res.theta[0] == 0.0)
    assert np.any(res.gear == 1)
    # trapezoid of the speeds matches the exact integral closely (smooth between samples)
    trap = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (res.omega[1:] + res.omega[:-1])
                                                    * 1e-3, axis=0)])
    np.testing.assert_allclose(res.theta, trap, atol=2e-3 * max(1.0, np.abs(trap).max()))


def test_locked_phases_keep_the_kinematic_ratio_of_the_angles() -> None:
    model = _model()
    params = load_parameters("physical")
    ratio = float(model.rigid.kin.gear_ratio(1))
    state = model.initial_state((30.0, 30.0 / ratio), locked=(True, False, False),
                                capacity=(40.0, 0.0, 0.0))
    start = state.theta.copy()
    for _ in range(500):
        state = model.step(state, 1e-3, 2.0, (5.0, 0.0, 0.0))
        assert state.locked == (True, False, False)
    d = state.theta - start
    assert d[0] > 1.0 and d[0] / d[1] == pytest.approx(ratio, rel=1e-9)
    # a tie-up (two bands locked): nothing moves
    tied = model.initial_state((0.0, 0.0), locked=(True, True, False), theta=(1.0, 2.0),
                               capacity=(40.0, 40.0, 0.0))
    nxt = model.step(tied, 1e-3, 5.0, (5.0, 5.0, 0.0))
    np.testing.assert_array_equal(nxt.theta, [1.0, 2.0])
    assert params.name


def test_gravity_load_hanging_is_at_rest_and_horizontal_falls() -> None:
    load = LOAD_PRESETS["arm-payload"]
    model = _model(load)
    assert model.rigid.M[1, 1] == pytest.approx(_model().rigid.M[1, 1]
                                                + load.reflected_inertia)
    hang = model.initial_state()
    for _ in range(100):
        hang = model.step(hang, 1e-3, 0.0, (0.0, 0.0, 0.0))
    assert np.all(np.abs(hang.omega) < 1e-9)
    # arm horizontal (0 degrees): gravity pulls carrier 3 backwards, about -T_g/(N J)
    th0 = load.carrier3_angle(0.0)
    flat = model.initial_state(theta=(0.0, th0))
    nxt = model.step(flat, 1e-3, 0.0, (0.0, 0.0, 0.0))
    assert nxt.omega[1] < 0.0 and nxt.theta[1] < th0
    # at 90 degrees (straight up): no gravity torque, stays
    up = model.initial_state(theta=(0.0, load.carrier3_angle(math.pi / 2)))
    nxt = model.step(up, 1e-3, 0.0, (0.0, 0.0, 0.0))
    assert abs(nxt.omega[1]) < 1e-9
    # gear 1 locked and horizontal: the band holds the arm when the motor balances it
    ratio = float(model.rigid.kin.gear_ratio(1))
    c3 = load.carrier3_torque(th0, 0.0)
    i_hold = -c3 / ratio / model.rigid.motor_constant
    held = model.initial_state(theta=(0.0, th0), locked=(True, False, False),
                               capacity=(40.0, 0.0, 0.0))
    for _ in range(50):
        held = model.step(held, 1e-3, i_hold, (5.0, 0.0, 0.0))
    assert abs(held.omega[1]) < 1e-3 and held.locked == (True, False, False)
