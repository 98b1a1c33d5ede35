"""Safety core: refusal (never clamp) policy, watchdog with injected time, trips, gear shifts.
Pure: no ROS, no I/O, no sleeping."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dvt_driver.errors import CommandRefusedError, SafetyConfigError
from dvt_driver.link.safety import (
    HARDWARE_MAX_BRAKE_CURRENT,
    HARDWARE_MAX_MOTOR_CURRENT,
    HARDWARE_MAX_SUN_SPEED,
    Limits,
    MotorMode,
    ShiftSettings,
    Supervisor,
    check_brake_currents,
    check_motor_current,
    check_sun_speed,
    plan_shift,
)

LIM = Limits()


def test_hardware_maxima() -> None:
    assert pytest.approx(12.0 / 0.3732) == HARDWARE_MAX_MOTOR_CURRENT  # 32.15 A
    assert pytest.approx(2400 * 2 * math.pi / 60) == HARDWARE_MAX_SUN_SPEED  # 251.33 rad/s
    assert LIM.max_motor_current == HARDWARE_MAX_MOTOR_CURRENT
    assert LIM.max_sun_speed == HARDWARE_MAX_SUN_SPEED


# -- limits: refuse, never clamp ---------------------------------------------------------------

@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 32.2, -40.0, 1e30])
def test_motor_current_out_of_range_or_non_finite_is_refused(value: float) -> None:
    with pytest.raises(CommandRefusedError, match="motor_current"):
        check_motor_current(value, LIM)


@pytest.mark.parametrize("value", [0.0, 5.0, -5.0, HARDWARE_MAX_MOTOR_CURRENT])
def test_motor_current_in_range_passes_unchanged(value: float) -> None:
    assert check_motor_current(value, LIM) == value


def test_tighter_limit_refuses_what_the_hardware_would_allow() -> None:
    lim = Limits(max_motor_current=10.0, max_sun_speed=100.0, max_brake_current=1.0)
    with pytest.raises(CommandRefusedError, match="10 A"):
        check_motor_current(10.5, lim)
    with pytest.raises(CommandRefusedError, match=r"rpm"):
        check_sun_speed(-100.5, lim)
    assert check_sun_speed(-100.0, lim) == -100.0


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_motor_check_never_returns_anything_unsafe(value: float) -> None:
    try:
        out = check_motor_current(value, LIM)
    except CommandRefusedError:
        return
    assert out == value  # no clamping: either unchanged or refused
    assert math.isfinite(out) and abs(out) <= LIM.max_motor_current


def test_brake_checks() -> None:
    cur = (0.1, 0.2, 0.3)
    assert check_brake_currents(["brake2"], [0.5], cur, LIM) == (0.1, 0.5, 0.3)
    assert check_brake_currents(["brake3", "brake1"], [-0.2, 1.0], cur, LIM) == (1.0, 0.2, -0.2)
    for names, efforts, match in [
        ([], [], "no brake named"),
        (["brake1"], [], "1 names but 0 effort"),
        (["brake4"], [0.1], "unknown brake 'brake4'"),
        (["brake1", "brake1"], [0.1, 0.2], "given twice"),
        (["brake2"], [math.nan], "brake2 is not finite"),
        (["brake2"], [HARDWARE_MAX_BRAKE_CURRENT + 0.1], "exceeds the limit"),
    ]:
        with pytest.raises(CommandRefusedError, match=match):
            check_brake_currents(names, efforts, cur, LIM)


@pytest.mark.parametrize("kwargs,match", [
    ({"max_motor_current": 0.0}, "max_motor_current"),
    ({"max_motor_current": 40.0}, "max_motor_current"),
    ({"max_brake_current": math.nan}, "max_brake_current"),
    ({"max_sun_speed": 300.0}, "max_sun_speed"),
    ({"max_sun_speed": "fast"}, "expected a number"),
])
def test_limits_validated(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(SafetyConfigError, match=match):
        Limits(**kwargs)


# -- supervisor ----------------------------------------------------------------------------------

def _sup(**kw: Any) -> Supervisor:
    return Supervisor(Limits(), watchdog_timeout=0.5, **kw)


def test_refused_motor_command_switches_motor_off_and_is_counted() -> None:
    s = _sup()
    s.motor_current(5.0, now=0.0)
    assert s.output(0.1)[0].mode is MotorMode.CURRENT
    with pytest.raises(CommandRefusedError, match="not finite"):
        s.motor_current(math.nan, now=0.2)
    out, _ = s.output(0.2)
    assert out.mode is MotorMode.OFF and out.setpoint == 0.0
    assert s.refusals == 1 and "not finite" in s.last_refusal
    with pytest.raises(CommandRefusedError, match="exceeds"):
        s.sun_speed(300.0, now=0.3)
    assert s.refusals == 2 and "rad/s" in s.last_refusal


def test_refused_brake_or_gear_command_leaves_brakes_alone() -> None:
    s = _sup()
    s.brake_currents(["brake1"], [0.5], now=0.0)
    s.motor_current(2.0, now=0.0)
    with pytest.raises(CommandRefusedError):
        s.brake_currents(["brake1"], [math.inf], now=0.1)
    with pytest.raises(CommandRefusedError, match="gear"):
        s.select_gear(4, now=0.1)
    out, _ = s.output(0.1)
    assert out.brakes == (0.5, 0.0, 0.0)
    assert out.mode is MotorMode.CURRENT  # a brake refusal does not stop the motor
    assert s.refusals == 2


def test_watchdog_with_injected_time() -> None:
    s = _sup()
    s.brake_currents(["brake2"], [0.5], now=0.0)
    s.motor_current(3.0, now=1.0)
    out, event = s.output(1.5)  # exactly at the timeout: still valid
    assert out.mode is MotorMode.CURRENT and out.setpoint == 3.0 and event is None
    s.motor_current(3.0, now=1.4)  # refreshed
    out, event = s.output(1.85)
    assert out.mode is MotorMode.CURRENT and event is None
    out, event = s.output(1.95)
    assert out.mode is MotorMode.OFF and out.setpoint == 0.0
    assert event is not None and "watchdog" in event
    assert out.brakes == (0.0, 0.5, 0.0)  # brakes hold their last commanded current
    assert s.watchdog_trips == 1
    _, event = s.output(3.0)  # already off: no second trip
    assert event is None and s.watchdog_trips == 1
    s.sun_speed(50.0, now=3.0)  # a fresh command re-enables
    out, _ = s.output(3.1)
    assert out.mode is MotorMode.SPEED and out.setpoint == 50.0


def test_stop_and_release_brakes() -> None:
    s = _sup()
    s.motor_current(3.0, now=0.0)
    s.brake_currents(["brake3"], [0.4], now=0.0)
    s.stop()
    out, _ = s.output(0.01)
    assert out.mode is MotorMode.OFF and out.brakes == (0.0, 0.0, 0.4)
    s.motor_current(3.0, now=0.02)
    s.release_brakes()
    out, _ = s.output(0.03)
    assert out.mode is MotorMode.CURRENT and out.brakes == (0.0, 0.0, 0.0)


def test_overspeed_trip_latches_until_slowed_and_new_command() -> None:
    s = _sup()
    s.motor_current(10.0, now=0.0)
    assert s.observe(200.0) is None
    assert s.observe(253.0) is None  # within the 2 % margin above the 251.3 rad/s limit
    reason = s.observe(262.0)
    assert reason is not None and "overspeed" in reason
    assert s.trips == 1 and s.output(0.01)[0].mode is MotorMode.OFF
    assert s.observe(258.0) is None  # still over: no new trip counted
    with pytest.raises(CommandRefusedError, match="overspeed"):
        s.motor_current(-5.0, now=0.02)
    assert s.observe(240.0) is None
    s.motor_current(1.0, now=0.03)
    assert s.output(0.04)[0].mode is MotorMode.CURRENT
    assert s.observe(math.nan) is not None  # a non-finite measurement trips too


def test_controller_flags_trip_and_watchdog_flag_only_while_driving() -> None:
    s = _sup()
    assert s.observe(0.0, frozenset({"WATCHDOG"})) is None  # motor off anyway: no trip
    s.motor_current(2.0, now=0.0)
    r = s.observe(0.0, frozenset({"WATCHDOG"}))
    assert r is not None and "WATCHDOG" in r
    s.motor_current(2.0, now=0.1)
    r = s.observe(0.0, frozenset({"FAULT", "OVERSPEED"}))
    assert r is not None and "FAULT" in r
    assert s.output(0.11)[0].mode is MotorMode.OFF
    n = s.trips
    s.motor_current(2.0, now=0.12)  # while FAULT still reported: stopped again, counted
    assert s.observe(0.0, frozenset({"FAULT", "OVERSPEED"})) is not None
    assert s.trips == n + 1 and s.mode is MotorMode.OFF


def test_controller_reset_stops_motor_keeps_brakes() -> None:
    s = _sup()
    s.motor_current(2.0, now=0.0)
    s.brake_currents(["brake1"], [0.5], now=0.0)
    assert "reset" in s.controller_reset()
    out, _ = s.output(0.01)
    assert out.mode is MotorMode.OFF and out.brakes == (0.5, 0.0, 0.0)


def test_final_check_catches_corrupted_state() -> None:
    s = _sup()
    s.motor_current(2.0, now=0.0)
    s.setpoint = 1e6  # a bookkeeping bug must not reach the wire
    out, _ = s.output(0.01)
    assert out.mode is MotorMode.OFF and out.setpoint == 0.0
    assert "final limit check" in s.last_trip


@given(st.lists(st.tuples(st.sampled_from(["cur", "spd", "brk", "gear", "obs", "out"]),
                          st.floats(allow_nan=True, allow_infinity=True, width=32)),
                max_size=40))
def test_output_is_always_within_limits(ops: list[tuple[str, float]]) -> None:
    lim = Limits(max_motor_current=20.0, max_brake_current=2.0, max_sun_speed=200.0)
    s = Supervisor(lim, watchdog_timeout=0.5, shift=ShiftSettings(engage_current=1.0))
    now = 0.0
    for op, x in ops:
        now += 0.013
        try:
            if op == "cur":
                s.motor_current(x, now)
            elif op == "spd":
                s.sun_speed(x, now)
            elif op == "brk":
                s.brake_currents(["brake2"], [x], now)
            elif op == "gear":
                s.select_gear(int(x) % 5 if math.isfinite(x) else -1, now)
            elif op == "obs":
                s.observe(x)
        except CommandRefusedError:
            pass
        out, _ = s.output(now)
        limit = {MotorMode.OFF: 0.0, MotorMode.CURRENT: 20.0, MotorMode.SPEED: 200.0}[out.mode]
        assert math.isfinite(out.setpoint) and abs(out.setpoint) <= limit
        assert all(math.isfinite(b) and abs(b) <= 2.0 for b in out.brakes)


# -- gear shifts ---------------------------------------------------------------------------------

SH = ShiftSettings(engage_current=0.5, ramp_time=0.1, overlap=0.0)


def test_shift_releases_engaged_band_then_engages_target() -> None:
    p = plan_shift(2, (0.5, 0.0, 0.0), now=10.0, settings=SH)
    assert p.target == (0.0, 0.5, 0.0)
    assert p.t_release_end == pytest.approx(10.1)
    assert p.t_engage_start == pytest.approx(10.1)
    assert p.t_end == pytest.approx(10.2)
    assert p.at(10.0) == (0.5, 0.0, 0.0)
    assert p.at(10.05) == pytest.approx((0.25, 0.0, 0.0))
    assert p.at(10.1) == pytest.approx((0.0, 0.0, 0.0))
    assert p.at(10.15) == pytest.approx((0.0, 0.25, 0.0))
    assert p.at(10.3) == (0.0, 0.5, 0.0)
    assert not p.done(10.19) and p.done(10.2)


def test_shift_overlap_and_gap() -> None:
    over = plan_shift(3, (0.0, 0.5, 0.0), 0.0, ShiftSettings(0.5, 0.1, overlap=0.04))
    assert over.t_engage_start == pytest.approx(0.06)
    b = over.at(0.08)
    assert b[1] > 0 and b[2] > 0  # both bands partly engaged
    gap = plan_shift(3, (0.0, 0.5, 0.0), 0.0, ShiftSettings(0.5, 0.1, overlap=-0.05))
    assert gap.t_engage_start == pytest.approx(0.15)
    assert gap.at(0.12) == (0.0, 0.0, 0.0)  # neutral gap
    huge = plan_shift(3, (0.0, 0.5, 0.0), 0.0, ShiftSettings(0.5, 0.1, overlap=1.0))
    assert huge.t_engage_start == 0.0  # never before the release starts


def test_shift_from_neutral_engages_at_once_and_neutral_releases_all() -> None:
    p = plan_shift(1, (0.0, 0.0, 0.0), 5.0, SH)
    assert p.t_engage_start == 5.0 and p.t_end == pytest.approx(5.1)
    n = plan_shift(0, (0.5, -0.1, 0.2), 5.0, SH)
    assert n.target == (0.0, 0.0, 0.0) and n.t_end == pytest.approx(5.1)
    assert n.at(5.1) == (0.0, 0.0, 0.0)
    step = plan_shift(2, (0.5, 0.0, 0.0), 0.0, ShiftSettings(0.5, 0.0, 0.0))
    assert step.at(0.0) == (0.0, 0.5, 0.0) and step.done(0.0)


@pytest.mark.parametrize("gear", [-1, 4, 1.5, True, "2"])
def test_invalid_gear_refused(gear: Any) -> None:
    with pytest.raises(CommandRefusedError, match="gear"):
        plan_shift(gear, (0.0, 0.0, 0.0), 0.0, SH)


def test_supervisor_shift_runs_and_can_be_interrupted() -> None:
    s = Supervisor(Limits(), 0.5, SH)
    s.select_gear(1, 0.0)
    assert s.output(0.2)[0].brakes == (0.5, 0.0, 0.0)
    assert s.gear == 1 and s.shift is None
    s.select_gear(3, 1.0)
    mid = s.output(1.05)[0].brakes
    assert mid == pytest.approx((0.25, 0.0, 0.0))
    s.select_gear(2, 1.05)  # re-planned from where the brakes are now
    assert s.shift is not None and s.shift.start == pytest.approx((0.25, 0.0, 0.0))
    assert s.output(1.3)[0].brakes == (0.0, 0.5, 0.0) and s.gear == 2
    s.select_gear(1, 2.0)
    s.brake_currents(["brake3"], [0.3], 2.05)  # manual brake command cancels the shift
    assert s.shift is None and s.gear is None
    assert s.output(2.5)[0].brakes == pytest.approx((0.0, 0.25, 0.3))


def test_engage_current_must_fit_the_brake_limit() -> None:
    with pytest.raises(SafetyConfigError, match="gear_engage_current"):
        Supervisor(Limits(max_brake_current=0.4), 0.5, ShiftSettings(engage_current=0.5))
    with pytest.raises(SafetyConfigError, match="gear_ramp_time"):
        ShiftSettings(ramp_time=-0.1)
    with pytest.raises(SafetyConfigError, match="watchdog_timeout"):
        Supervisor(Limits(), 0.0)
