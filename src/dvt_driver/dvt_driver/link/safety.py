"""Command safety for the DVT driver: limits, refusals, watchdog, trips, gear shifts (pure).

No ROS and no I/O here; time is injected (``now`` [s] on any monotonic clock), so every rule is
testable without waiting. The driver node feeds commands and measured samples into a
:class:`Supervisor` and sends whatever :meth:`Supervisor.output` returns.

Policy (see ``docs/driver.md``):

* **Refuse, never clamp.** A command that is not finite or outside its limit is refused with a
  reason (:class:`CommandRefusedError`, counted in ``refusals``, reason in ``last_refusal``).
  A clamped command would silently do something other than what the sender asked for.
  A refused *motor* command (current or speed) also switches the motor off: whoever sends NaN or
  an over-limit set-point is broken, and the safe reaction is to stop driving (the refusal is
  not a trip). A refused brake or gear command leaves the brakes as they are.
* **Watchdog.** A motor set-point is valid for ``watchdog_timeout`` seconds after it arrived.
  With no fresh motor command in that time the motor is switched off (mode OFF, counted in
  ``watchdog_trips``). The brakes keep their last commanded current: releasing a band while the
  output is loaded, or in the middle of a shift, drops the load - holding is the safe side.
* **Trips.** A measured sun speed above ``max_sun_speed * (1 + OVERSPEED_MARGIN)`` (2 %: a
  speed loop holding the limit itself rides a little above it and must not trip), or the
  controller reporting
  OVERSPEED / FAULT / its own WATCHDOG, switches the motor off (counted in ``trips``). The motor
  stays off until a new motor command arrives; while the measured speed is still above the
  limit new motor commands are refused.
* **Final check.** :meth:`Supervisor.output` checks what it is about to return once more and
  returns the motor off if anything is out of range, so nothing outside the limits can reach
  the wire even through a bug in the bookkeeping above.

Gear shifts (:func:`plan_shift`): gear ``g`` in 1..3 engages band brake ``g`` (it holds ring
``g``); gear 0 is neutral (all bands released). A shift ramps every other band linearly to 0
over ``ramp_time`` and ramps the target band to ``engage_current`` over ``ramp_time``, starting
``ramp_time - overlap`` after the release began (``overlap`` > 0: the bands overlap, both
partly engaged; < 0: a neutral gap of ``-overlap`` seconds; the engage never starts before the
release). If no band needs releasing the engage starts at once.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from dvt_driver.errors import CommandRefusedError, SafetyConfigError
from dvt_driver.hardware import (
    HARDWARE_MAX_BRAKE_CURRENT,
    HARDWARE_MAX_MOTOR_CURRENT,
    HARDWARE_MAX_SUN_SPEED,
    MOTOR_CONSTANT,
    MOTOR_PEAK_TORQUE,
)
from dvt_model.contract import BRAKE_NAMES  # brake<g> selects gear g

__all__ = [
    "BRAKE_NAMES",
    "DEFAULT_MAX_BRAKE_CURRENT",
    "HARDWARE_MAX_BRAKE_CURRENT",
    "HARDWARE_MAX_MOTOR_CURRENT",
    "HARDWARE_MAX_SUN_SPEED",
    "MOTOR_CONSTANT",
    "MOTOR_PEAK_TORQUE",
    "Limits",
    "MotorMode",
    "Output",
    "ShiftPlan",
    "ShiftSettings",
    "Supervisor",
    "check_brake_currents",
    "check_motor_current",
    "check_setting",
    "check_sun_speed",
    "plan_shift",
]

DEFAULT_MAX_BRAKE_CURRENT = HARDWARE_MAX_BRAKE_CURRENT
"""Default band-brake current limit [A] (0.5 A engages a band at about 4 N m)."""

Brakes = tuple[float, float, float]


class MotorMode(IntEnum):
    """Drive-motor mode (values equal :class:`dvt_driver.link.protocol.Mode`)."""

    OFF = 0
    CURRENT = 1
    SPEED = 2


def check_setting(name: str, value: Any, low: float, high: float, *, low_open: bool = True,
                  unit: str = "") -> float:
    """``value`` as a float if it is a number in ``(low, high]`` (``[low, high]`` with
    ``low_open=False``), else :class:`SafetyConfigError` naming ``name``, the range and value."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise SafetyConfigError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    lo_ok = v > low if low_open else v >= low
    if not (math.isfinite(v) and lo_ok and v <= high):
        bracket = "(" if low_open else "["
        raise SafetyConfigError(f"{name}: expected a value in {bracket}{low:g}, {high:g}]{unit}, "
                                f"got {value!r}")
    return v


OVERSPEED_MARGIN = 0.02
"""Measured sun speed may exceed ``max_sun_speed`` by this fraction before the driver trips
(the controller trips at 5 %): set-points up to the limit itself stay usable."""


@dataclass(frozen=True, slots=True)
class Limits:
    """Command limits, each > 0 and at most its hardware maximum.

    Attributes:
        max_motor_current: largest |drive-motor current| [A].
        max_brake_current: largest |band-brake current| [A].
        max_sun_speed: largest |sun-shaft speed| [rad/s], commanded or measured.

    Raises:
        SafetyConfigError: a limit is not finite, <= 0 or above its hardware maximum.
    """

    max_motor_current: float = HARDWARE_MAX_MOTOR_CURRENT
    max_brake_current: float = DEFAULT_MAX_BRAKE_CURRENT
    max_sun_speed: float = HARDWARE_MAX_SUN_SPEED

    def __post_init__(self) -> None:
        for name, hw, unit in (("max_motor_current", HARDWARE_MAX_MOTOR_CURRENT, " A"),
                               ("max_brake_current", HARDWARE_MAX_BRAKE_CURRENT, " A"),
                               ("max_sun_speed", HARDWARE_MAX_SUN_SPEED, " rad/s")):
            # a few ulp of slack so that the hardware maximum itself, round-tripped through a
            # parameter or YAML as decimal text, is accepted
            value = check_setting(name, getattr(self, name), 0.0, hw * (1 + 1e-12), unit=unit)
            object.__setattr__(self, name, min(value, hw))


def _finite(what: str, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CommandRefusedError(what, f"{name} is not a number ({value!r})")
    v = float(value)
    if not math.isfinite(v):
        raise CommandRefusedError(what, f"{name} is not finite ({v!r})")
    return v


def check_motor_current(value: Any, limits: Limits) -> float:
    """The drive-motor current set-point [A] if finite and within ``±max_motor_current``.

    Raises:
        CommandRefusedError: otherwise (never clamps).
    """
    v = _finite("motor_current", "current", value)
    if abs(v) > limits.max_motor_current:
        raise CommandRefusedError("motor_current", f"{v:g} A exceeds the limit of "
                             f"{limits.max_motor_current:g} A")
    return v


def check_sun_speed(value: Any, limits: Limits) -> float:
    """The sun-speed set-point [rad/s] if finite and within ``±max_sun_speed``.

    Raises:
        CommandRefusedError: otherwise (never clamps).
    """
    v = _finite("sun_speed", "speed", value)
    if abs(v) > limits.max_sun_speed:
        raise CommandRefusedError("sun_speed", f"{v:g} rad/s exceeds the limit of "
                             f"{limits.max_sun_speed:g} rad/s "
                             f"({limits.max_sun_speed * 60 / (2 * math.pi):.0f} rpm)")
    return v


def check_brake_currents(names: Sequence[str], efforts: Sequence[Any], current: Brakes,
                         limits: Limits) -> Brakes:
    """New brake set-points: ``current`` with the named brakes replaced.

    Args:
        names: a non-empty subset of :data:`BRAKE_NAMES`, each at most once.
        efforts: one current per name [A], finite, ``|i| <= max_brake_current``.
        current: the brake set-points in force (brake1, brake2, brake3) [A].

    Raises:
        CommandRefusedError: unknown or repeated name, length mismatch, empty, non-finite or
            over-limit current; nothing is changed then.
    """
    what = "brake_currents"
    names = list(names)
    efforts = list(efforts)
    if not names:
        raise CommandRefusedError(what, "no brake named (name must be a subset of "
                             f"{list(BRAKE_NAMES)})")
    if len(names) != len(efforts):
        raise CommandRefusedError(what, f"{len(names)} names but {len(efforts)} effort values")
    out = list(current)
    seen: set[str] = set()
    for name, effort in zip(names, efforts, strict=True):
        if name not in BRAKE_NAMES:
            raise CommandRefusedError(what, f"unknown brake {name!r} (expected one of "
                                 f"{list(BRAKE_NAMES)})")
        if name in seen:
            raise CommandRefusedError(what, f"brake {name!r} given twice")
        seen.add(name)
        v = _finite(what, name, effort)
        if abs(v) > limits.max_brake_current:
            raise CommandRefusedError(what, f"{name} {v:g} A exceeds the limit of "
                                 f"{limits.max_brake_current:g} A")
        out[BRAKE_NAMES.index(name)] = v
    return (out[0], out[1], out[2])


# ---------------------------------------------------------------------------------------------
# gear shifts


@dataclass(frozen=True, slots=True)
class ShiftSettings:
    """How a gear shift moves the band brakes.

    Attributes:
        engage_current: current that holds the target band [A], > 0.
        ramp_time: duration of each release / engage ramp [s], >= 0 (0 = steps).
        overlap: engage start relative to the end of the release [s]; > 0 starts the engage
            this long before the release ends (never before it begins), < 0 leaves a neutral
            gap of ``-overlap``; within [-2, 2].
    """

    engage_current: float = 0.5
    ramp_time: float = 0.05
    overlap: float = 0.0

    def __post_init__(self) -> None:
        check_setting("gear_engage_current", self.engage_current, 0.0,
                      HARDWARE_MAX_BRAKE_CURRENT, unit=" A")
        check_setting("gear_ramp_time", self.ramp_time, 0.0, 5.0, low_open=False, unit=" s")
        check_setting("gear_overlap", self.overlap, -2.0, 2.0, low_open=False, unit=" s")


@dataclass(frozen=True, slots=True)
class _Ramp:
    start: float  # value before t0 [A]
    end: float  # value after t1 [A]
    t0: float  # [s]
    t1: float  # [s]

    def at(self, t: float) -> float:
        if t >= self.t1:
            return self.end
        if t <= self.t0:
            return self.start
        return self.start + (self.end - self.start) * (t - self.t0) / (self.t1 - self.t0)


@dataclass(frozen=True, slots=True)
class ShiftPlan:
    """Brake set-points over time for one shift (from :func:`plan_shift`).

    Attributes:
        gear: target gear, 0..3.
        start: brake set-points when the shift began [A].
        target: brake set-points once it is done [A].
        t_start: when it began [s]; ``t_release_end``, ``t_engage_start``, ``t_end`` [s].
    """

    gear: int
    start: Brakes
    target: Brakes
    t_start: float
    t_release_end: float
    t_engage_start: float
    t_end: float
    ramps: tuple[_Ramp, _Ramp, _Ramp] = field(repr=False)

    def at(self, t: float) -> Brakes:
        """Brake set-points (brake1, brake2, brake3) [A] at time ``t`` [s]."""
        r = self.ramps
        return (r[0].at(t), r[1].at(t), r[2].at(t))

    def done(self, t: float) -> bool:
        """Whether the shift is complete at time ``t`` [s]."""
        return t >= self.t_end


def plan_shift(gear: int, start: Brakes, now: float, settings: ShiftSettings) -> ShiftPlan:
    """Plan the shift from brake set-points ``start`` [A] at time ``now`` [s] to ``gear``.

    Gear 0 releases every band; gear g in 1..3 releases the others and engages band g at
    ``settings.engage_current``. A band already at its target is left alone.

    Raises:
        CommandRefusedError: ``gear`` is not an integer in 0..3.
    """
    if isinstance(gear, bool) or not isinstance(gear, int) or not 0 <= gear <= 3:
        raise CommandRefusedError("gear", f"expected 0 (neutral), 1, 2 or 3, got {gear!r}")
    ramp = settings.ramp_time
    target = tuple(settings.engage_current if k == gear - 1 else 0.0 for k in range(3))
    releasing = [k for k in range(3) if k != gear - 1 and start[k] != 0.0]
    t_release_end = now + ramp if releasing else now
    if releasing:
        t_engage = max(now, t_release_end - settings.overlap)
    else:
        t_engage = now
    ramps: list[_Ramp] = []
    for k in range(3):
        if k == gear - 1:
            ramps.append(_Ramp(start[k], target[k], t_engage, t_engage + ramp))
        else:
            ramps.append(_Ramp(start[k], 0.0, now, t_release_end))
    t_end = max(t_release_end, t_engage + ramp if gear else now)
    return ShiftPlan(gear, (start[0], start[1], start[2]), (target[0], target[1], target[2]),
                     now, t_release_end, t_engage, t_end, (ramps[0], ramps[1], ramps[2]))


# ---------------------------------------------------------------------------------------------
# supervisor


@dataclass(frozen=True, slots=True)
class Output:
    """What to send to the controller now.

    Attributes:
        mode: :class:`MotorMode`.
        setpoint: motor current [A] (CURRENT), sun speed [rad/s] (SPEED), 0.0 (OFF).
        brakes: brake current set-points (brake1, brake2, brake3) [A].
    """

    mode: MotorMode
    setpoint: float
    brakes: Brakes


class Supervisor:
    """Holds the commanded state and applies the safety rules (module docstring).

    Args:
        limits: command limits.
        watchdog_timeout: how long a motor set-point stays valid [s], > 0 and <= 60.
        shift: gear-shift settings; ``shift.engage_current`` must be within
            ``limits.max_brake_current``.

    Counters: ``commands`` (accepted), ``refusals``, ``watchdog_trips``, ``trips`` (overspeed
    and controller-reported), ``shifts``; ``last_refusal`` / ``last_trip`` hold the reasons.
    ``gear`` is the gear of the last completed shift, ``None`` when the brakes were set by hand
    (or no shift was made yet), ``shift`` the shift in progress.

    Not thread-safe: the caller serialises access (one lock around every call).
    """

    def __init__(self, limits: Limits, watchdog_timeout: float = 0.5,
                 shift: ShiftSettings | None = None) -> None:
        if not isinstance(limits, Limits):
            raise SafetyConfigError(f"limits: expected a Limits, got {limits!r}")
        self.limits = limits
        self.watchdog_timeout = check_setting("watchdog_timeout", watchdog_timeout, 0.0, 60.0,
                                         unit=" s")
        self.shift_settings = shift if shift is not None else ShiftSettings()
        if self.shift_settings.engage_current > limits.max_brake_current:
            raise SafetyConfigError(
                f"gear_engage_current: {self.shift_settings.engage_current:g} A exceeds "
                f"max_brake_current {limits.max_brake_current:g} A")
        self.mode = MotorMode.OFF
        self.setpoint = 0.0
        self.brakes: Brakes = (0.0, 0.0, 0.0)
        self.shift: ShiftPlan | None = None
        self.gear: int | None = None
        self.last_motor_command: float | None = None
        self.tripped: str | None = None
        self.overspeed = False
        self.commands = 0
        self.refusals = 0
        self.watchdog_trips = 0
        self.trips = 0
        self.shifts = 0
        self.last_refusal = ""
        self.last_trip = ""
        self._controller_flags: frozenset[str] = frozenset()

    # -- commands ------------------------------------------------------------------------------

    def refuse(self, what: str, reason: str, *, motor_off: bool = True) -> CommandRefusedError:
        """Refuse a command for a reason found outside the supervisor (e.g. the driver is not
        active): counted like any refusal; returns the error (not raised)."""
        return self._refuse(CommandRefusedError(what, reason), motor_off=motor_off)

    def _refuse(self, exc: CommandRefusedError, *, motor_off: bool) -> CommandRefusedError:
        self.refusals += 1
        self.last_refusal = str(exc)
        if motor_off:
            self._motor_off()
        return exc

    def _motor_off(self) -> None:
        self.mode = MotorMode.OFF
        self.setpoint = 0.0

    def _motor(self, what: str, mode: MotorMode, value: Any, now: float) -> float:
        try:
            v = (check_motor_current(value, self.limits) if mode is MotorMode.CURRENT
                 else check_sun_speed(value, self.limits))
            if self.overspeed:
                raise CommandRefusedError(what, "the measured sun speed is above the limit of "
                                     f"{self.limits.max_sun_speed:g} rad/s (overspeed trip "
                                     "active); wait until it has slowed down")
        except CommandRefusedError as exc:
            raise self._refuse(exc, motor_off=True) from None
        self.mode, self.setpoint = mode, v
        self.last_motor_command = now
        self.tripped = None
        self.commands += 1
        return v

    def motor_current(self, value: Any, now: float) -> float:
        """Current mode with set-point ``value`` [A] at time ``now`` [s]; returns it.

        Raises:
            CommandRefusedError: not finite, over the limit or overspeed active (motor off then).
        """
        return self._motor("motor_current", MotorMode.CURRENT, value, now)

    def sun_speed(self, value: Any, now: float) -> float:
        """Speed mode with sun-speed set-point ``value`` [rad/s] at time ``now`` [s].

        Raises:
            CommandRefusedError: not finite, over the limit or overspeed active (motor off then).
        """
        return self._motor("sun_speed", MotorMode.SPEED, value, now)

    def brake_currents(self, names: Sequence[str], efforts: Sequence[Any], now: float) -> Brakes:
        """Set the named brakes [A] (a shift in progress is cancelled, its current values
        kept for the unnamed brakes); returns the new set-points.

        Raises:
            CommandRefusedError: see :func:`check_brake_currents` (brakes unchanged then).
        """
        base = self._brakes_now(now)
        try:
            new = check_brake_currents(names, efforts, base, self.limits)
        except CommandRefusedError as exc:
            raise self._refuse(exc, motor_off=False) from None
        self.shift = None
        self.brakes = new
        self.gear = None
        self.commands += 1
        return new

    def select_gear(self, gear: Any, now: float) -> ShiftPlan:
        """Start a shift to ``gear`` (0..3) from the brake set-points in force at ``now``.

        Raises:
            CommandRefusedError: gear not in 0..3 (brakes unchanged then).
        """
        try:
            plan = plan_shift(gear, self._brakes_now(now), now, self.shift_settings)
        except CommandRefusedError as exc:
            raise self._refuse(exc, motor_off=False) from None
        self.brakes = plan.start
        self.shift = plan
        self.shifts += 1
        self.commands += 1
        return plan

    def stop(self) -> None:
        """Motor off now (brakes and a shift in progress unchanged)."""
        self._motor_off()

    def controller_reset(self) -> str:
        """The controller restarted (it lost its set-points): motor off until the next motor
        command, counted as a trip; the brakes are re-sent as they are. Returns the reason."""
        reason = "controller reset: motor off until the next motor command"
        self._motor_off()
        self.trips += 1
        self.last_trip = reason
        self.tripped = reason
        return reason

    def release_brakes(self) -> None:
        """All brakes to 0 A now; a shift in progress is cancelled (motor unchanged)."""
        self.shift = None
        self.brakes = (0.0, 0.0, 0.0)
        self.gear = 0

    # -- measurements ----------------------------------------------------------------------

    def observe(self, sun_speed: float, controller_flags: frozenset[str] = frozenset()
                ) -> str | None:
        """Account one measured sample; returns the trip reason if this sample trips.

        Args:
            sun_speed: measured sun-shaft speed [rad/s].
            controller_flags: controller-reported conditions among ``"OVERSPEED"``,
                ``"FAULT"``, ``"WATCHDOG"``; each counts as a trip when it appears
                (``"WATCHDOG"`` only while the motor is meant to run: the controller's watchdog
                expiring while the host has the motor off anyway is not a trip).
        """
        reason = None
        trip_at = self.limits.max_sun_speed * (1.0 + OVERSPEED_MARGIN)
        over = not math.isfinite(sun_speed) or abs(sun_speed) > trip_at
        if over and not self.overspeed:
            reason = (f"overspeed: measured sun speed {sun_speed:.6g} rad/s exceeds "
                      f"{trip_at:g} rad/s (limit {self.limits.max_sun_speed:g} + "
                      f"{OVERSPEED_MARGIN:.0%})")
        self.overspeed = over
        relevant = frozenset(f for f in controller_flags
                             if f != "WATCHDOG" or self.mode is not MotorMode.OFF)
        new_flags = relevant - self._controller_flags
        self._controller_flags = relevant
        if new_flags and reason is None:
            reason = "controller reports " + ", ".join(sorted(new_flags))
        blocking = over or "FAULT" in controller_flags or "OVERSPEED" in controller_flags
        if blocking and self.mode is not MotorMode.OFF:
            self._motor_off()
            if reason is None:
                reason = ("overspeed" if over else "controller fault") + " persists"
        if reason is not None:
            self.trips += 1
            self.last_trip = reason
            self.tripped = reason
        return reason

    # -- output ----------------------------------------------------------------------------

    def _brakes_now(self, now: float) -> Brakes:
        plan = self.shift
        if plan is None:
            return self.brakes
        if plan.done(now):
            self.brakes = plan.target
            self.gear = plan.gear
            self.shift = None
            return self.brakes
        return plan.at(now)

    def brakes_at(self, now: float) -> Brakes:
        """Brake set-points (brake1, brake2, brake3) [A] in force at ``now`` [s] (a finished
        shift is completed)."""
        return self._brakes_now(now)

    def watchdog_expired(self, now: float) -> bool:
        """Whether the motor set-point is older than ``watchdog_timeout`` at ``now`` [s]."""
        last = self.last_motor_command
        return last is None or now - last > self.watchdog_timeout

    def output(self, now: float) -> tuple[Output, str | None]:
        """What to send at time ``now`` [s], and the reason if the watchdog tripped just now.

        The returned output is always within the limits (final check: anything else becomes
        motor off, brakes 0 A for a non-finite brake value - which cannot happen - and counts
        as a trip).
        """
        event = None
        if self.mode is not MotorMode.OFF and self.watchdog_expired(now):
            last = self.last_motor_command
            age = math.inf if last is None else now - last
            event = (f"watchdog: no motor command for {age:.3f} s "
                     f"(timeout {self.watchdog_timeout:g} s); motor off, brakes held")
            self._motor_off()
            self.watchdog_trips += 1
            self.last_trip = event
            self.tripped = event
        brakes = self._brakes_now(now)
        out = Output(self.mode, self.setpoint if self.mode is not MotorMode.OFF else 0.0, brakes)
        return self._final_check(out), event

    def _final_check(self, out: Output) -> Output:
        lim = self.limits
        sp_limit = (lim.max_motor_current if out.mode is MotorMode.CURRENT
                    else lim.max_sun_speed if out.mode is MotorMode.SPEED else 0.0)
        motor_ok = math.isfinite(out.setpoint) and abs(out.setpoint) <= sp_limit
        brakes_ok = all(math.isfinite(b) and abs(b) <= lim.max_brake_current
                        for b in out.brakes)
        if motor_ok and brakes_ok:
            return out
        self.trips += 1
        self.last_trip = f"internal: output {out} failed the final limit check"
        self._motor_off()
        brakes = out.brakes if brakes_ok else tuple(
            b if math.isfinite(b) and abs(b) <= lim.max_brake_current else 0.0
            for b in out.brakes)
        return Output(MotorMode.OFF, 0.0, (brakes[0], brakes[1], brakes[2]))
