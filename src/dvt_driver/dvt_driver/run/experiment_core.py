"""Experiments as time-indexed command schedules (pure: no ROS, no I/O).

An :class:`Experiment` is a list of :class:`Step` items ``(t, command)``: at ``t`` seconds after
the start the runner (:mod:`dvt_driver.run.experiment`) sends ``command`` to the driver, and the
command holds until the next one of its kind. Commands map one to one to the driver's command
interface:

=====================  ============================================  ==========================
command                driver topic / service                        unit
=====================  ============================================  ==========================
:class:`MotorCurrent`  ``/dvt/cmd/motor_current`` std_msgs/Float64   A (mode CURRENT)
:class:`SunSpeed`      ``/dvt/cmd/sun_speed`` std_msgs/Float64       rad/s (mode SPEED)
:class:`BrakeCurrents` ``/dvt/cmd/brake_currents`` JointState effort  A (brake1..3)
:class:`Gear`          ``/dvt/cmd/gear`` std_msgs/Int8               0 neutral, 1..3
:class:`MotorOff`      ``/dvt/driver/stop`` std_srvs/Trigger          -
=====================  ============================================  ==========================

Named experiments (:data:`EXPERIMENTS`, :func:`build`):

``thesis``
    The thesis's protocol at its 16 ms serial period (62.5 Hz): the sun shaft is held by the
    drive's speed loop at 1500, 1600, 2000 and 2400 rpm in turn; at each speed band brake 1 is
    applied at 0.125 A, then released.
``shifts``
    Speed loop at a moderate sun speed, shifting neutral -> 1 -> 2 -> 3 -> 2 -> 1 -> neutral.
``prbs``
    Maximum-length PRBS on the motor current in neutral (zero mean: the shafts reverse).
``multisine``
    Random-phase multisine on the motor current in neutral (0.2-20 Hz).
``speed_steps``
    Sun-speed set-point steps with reversals in neutral.
``gears_excitation``
    Each gear in turn, band held, PRBS motor current with direction changes and no brake
    transient inside the excitation window (the thesis's proposed future work).
``ident``
    The identification-grade run: neutral PRBS and multisine (the two-degree-of-freedom
    system), speed steps up to 2000 rpm (windage), then each gear locked with PRBS (the
    one-degree-of-freedom systems, backlash and friction reversals), shifts in between
    (band engagement).
``ident_shifts``
    A shift-rich identification run: neutral PRBS and multisine, then twelve band engagements
    against slipping rings (each gear from four sun speeds), for band-engagement effects.
``watch``
    Continuous excitation for a given duration, for the live loop (``dvt-launch sim
    --supervise``, ``docs/loop.md``): cycles of neutral PRBS and multisine (fresh random
    signals every cycle), optionally each gear of ``gears`` with PRBS, repeated until
    ``duration``; the plant can change at any time and the data after it still excite what the
    refit needs.
``smoke``
    A 5 s version of ``ident`` (neutral PRBS, gear 1 with PRBS) for end-to-end tests.

The commands, :class:`Experiment` and the signals are in :mod:`dvt_driver.run.schedule` (every
name is importable from here too).

Every experiment is deterministic given its seed (:func:`build`), starts in neutral with the
bands released, ends with the motor stopped and off, and is validated against the driver's
limits (:class:`Limits`). :attr:`Experiment.phases` labels the time spans (e.g.
``neutral-prbs``, ``gear2-prbs``) for progress output and provenance.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from dvt_driver.errors import ExperimentError
from dvt_driver.hardware import RPM
from dvt_driver.run.schedule import (
    BrakeCurrents,
    Command,
    Experiment,
    Gear,
    Limits,
    MotorCurrent,
    MotorOff,
    Phase,
    Step,
    SunSpeed,
    multisine_signal,
    prbs_signal,
)

__all__ = [
    "EXPERIMENTS",
    "BrakeCurrents",
    "Command",
    "Experiment",
    "Gear",
    "Limits",
    "MotorCurrent",
    "MotorOff",
    "Phase",
    "Step",
    "SunSpeed",
    "available",
    "build",
    "multisine_signal",
    "prbs_signal",
]



# --------------------------------------------------------------------------- builder
class _Schedule:
    """Accumulates steps and phases; times are rounded to the microsecond."""

    def __init__(self) -> None:
        self.steps: list[Step] = []
        self.phases: list[Phase] = []
        self.t = 0.0

    def at(self, t: float, command: Command) -> None:
        self.steps.append(Step(round(float(t), 6), command))

    def phase(self, label: str, length: float) -> tuple[float, float]:
        t0, t1 = self.t, round(self.t + length, 6)
        self.phases.append(Phase(t0, t1, label))
        self.t = t1
        return t0, t1

    def build(self, name: str, description: str, sample_period_us: int, seed: int,
              settings: dict[str, Any]) -> Experiment:
        steps = sorted(self.steps, key=lambda s: s.t)  # stable: ties keep insertion order
        return Experiment(name, description, tuple(steps), tuple(self.phases), self.t,
                          sample_period_us, seed, settings).validate()


def _prbs(s: _Schedule, t0: float, t1: float, amplitude: float, offset: float, clock: float,
          order: int, seed: int, stream: int) -> None:
    n = max(1, math.ceil((t1 - t0) / clock - 1e-9))
    bits = prbs_signal(n, order, seed, stream)
    last = None
    for i, b in enumerate(bits):
        level = round(offset + amplitude * float(b), 6)
        if level != last:
            s.at(t0 + i * clock, MotorCurrent(level))
            last = level


def _multisine(s: _Schedule, t0: float, t1: float, amplitude: float, offset: float,
               update: float, period: float, f_lo: float, f_hi: float, seed: int,
               stream: int) -> None:
    n = max(1, math.floor((t1 - t0) * update + 1e-9))
    tt = np.arange(n) / update
    x = multisine_signal(tt, period, f_lo, f_hi, seed, stream)
    for ti, xi in zip(tt, x, strict=True):
        s.at(t0 + float(ti), MotorCurrent(round(offset + amplitude * float(xi), 6)))


def _ramp(s: _Schedule, t0: float, w0: float, w1: float, rate: float, update: float) -> float:
    """Sun-speed ramp from ``w0`` to ``w1`` [rad/s] at ``rate`` [rad/s^2]; returns its end."""
    length = abs(w1 - w0) / rate
    n = max(1, math.ceil(length * update))
    for i in range(1, n + 1):
        s.at(t0 + (i - 1) / update, SunSpeed(round(w0 + (w1 - w0) * i / n, 6)))
    return t0 + length


def _stop(s: _Schedule, length: float) -> None:
    """Final phase: speed loop to zero (active braking), neutral, motor off at the end."""
    t0, t1 = s.phase("stop", length)
    s.at(t0, SunSpeed(0.0))
    s.at(t0, Gear(0))
    s.at(t1, MotorOff())


def thesis(seed: int = 0, speeds_rpm: Sequence[float] = (1500.0, 1600.0, 2000.0, 2400.0),
           brake_current: float = 0.125, settle: float = 3.0, engaged: float = 4.0,
           released: float = 1.0, ramp_rpm_per_s: float = 1500.0) -> Experiment:
    """The thesis's protocol: hold the sun at each speed, apply band 1 at ``brake_current``.

    Per speed: ramp and settle (``settle`` s), band 1 at ``brake_current`` [A] for ``engaged``
    s, band released for ``released`` s. Meant for a 16 ms controller period (62.5 Hz).
    """
    s = _Schedule()
    s.at(0.0, BrakeCurrents((0.0, 0.0, 0.0)))
    w = 0.0
    for rpm in speeds_rpm:
        target = float(rpm) * RPM
        t0, _ = s.phase(f"{rpm:g}rpm-settle", settle)
        _ramp(s, t0, w, target, ramp_rpm_per_s * RPM, 100.0)
        w = target
        t0, _ = s.phase(f"{rpm:g}rpm-brake1", engaged)
        s.at(t0, BrakeCurrents((brake_current, 0.0, 0.0)))
        t0, _ = s.phase(f"{rpm:g}rpm-released", released)
        s.at(t0, BrakeCurrents((0.0, 0.0, 0.0)))
    t0, t1 = s.phase("stop", 2.0)
    _ramp(s, t0, w, 0.0, 2.0 * ramp_rpm_per_s * RPM, 100.0)
    s.at(t1, MotorOff())
    return s.build("thesis", "thesis protocol: sun held at each speed, band 1 applied at "
                   f"{brake_current} A", 16000, seed,
                   {"speeds_rpm": tuple(speeds_rpm), "brake_current_A": brake_current,
                    "settle_s": settle, "engaged_s": engaged, "released_s": released})


def shifts(seed: int = 0, speed_rpm: float = 600.0, dwell: float = 2.0,
           sequence: Sequence[int] = (1, 2, 3, 2, 1, 0)) -> Experiment:
    """Speed loop at ``speed_rpm``; shift through ``sequence`` with ``dwell`` s per gear."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, _ = s.phase("neutral-spinup", dwell)
    _ramp(s, t0, 0.0, speed_rpm * RPM, 1500.0 * RPM, 100.0)
    for g in sequence:
        t0, _ = s.phase(f"shift-gear{g}" if g else "shift-neutral", dwell)
        s.at(t0, Gear(int(g)))
    _stop(s, 1.5)
    return s.build("shifts", f"speed loop at {speed_rpm:g} rpm, shifts through "
                   f"{list(sequence)}", 1000, seed,
                   {"speed_rpm": speed_rpm, "dwell_s": dwell, "sequence": tuple(sequence)})


def prbs(seed: int = 0, length: float = 12.0, amplitude: float = 2.5, clock: float = 0.03,
         order: int = 8) -> Experiment:
    """Zero-mean PRBS of +-``amplitude`` [A] on the motor current in neutral."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, t1 = s.phase("neutral-prbs", length)
    _prbs(s, t0, t1, amplitude, 0.0, clock, order, seed, 1)
    _stop(s, 1.5)
    return s.build("prbs", f"PRBS +-{amplitude:g} A (clock {clock * 1e3:g} ms) on the motor "
                   "current in neutral", 1000, seed,
                   {"length_s": length, "amplitude_A": amplitude, "clock_s": clock,
                    "order": order})


def multisine(seed: int = 0, length: float = 12.0, amplitude: float = 3.0,
              period: float = 5.0, f_lo: float = 0.2, f_hi: float = 20.0,
              update: float = 200.0) -> Experiment:
    """Random-phase multisine (peak ``amplitude`` [A]) on the motor current in neutral."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, t1 = s.phase("neutral-multisine", length)
    _multisine(s, t0, t1, amplitude, 0.0, update, period, f_lo, f_hi, seed, 2)
    _stop(s, 1.5)
    return s.build("multisine", f"multisine {f_lo:g}-{f_hi:g} Hz, peak {amplitude:g} A, on "
                   "the motor current in neutral", 1000, seed,
                   {"length_s": length, "amplitude_A": amplitude, "period_s": period,
                    "f_lo_Hz": f_lo, "f_hi_Hz": f_hi, "update_Hz": update})


SPEED_STEPS_RPM = (800.0, -800.0, 1600.0, 400.0, 2000.0, -1200.0)


def _speed_steps(s: _Schedule, t0: float, levels_rpm: Sequence[float], dwell: float) -> None:
    for i, rpm in enumerate(levels_rpm):
        s.at(t0 + i * dwell, SunSpeed(float(rpm) * RPM))


def speed_steps(seed: int = 0, levels_rpm: Sequence[float] = SPEED_STEPS_RPM,
                dwell: float = 1.5) -> Experiment:
    """Sun-speed set-point steps (with reversals) in neutral, ``dwell`` s each."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, _ = s.phase("neutral-speed-steps", dwell * len(levels_rpm))
    _speed_steps(s, t0, levels_rpm, dwell)
    _stop(s, 1.5)
    return s.build("speed_steps", f"sun-speed steps {list(levels_rpm)} rpm in neutral", 1000,
                   seed, {"levels_rpm": tuple(levels_rpm), "dwell_s": dwell})


def _gear_blocks(s: _Schedule, gears: Sequence[int], shift: float, excite: float,
                 amplitude: float, clock: float, order: int, seed: int) -> None:
    for g in gears:
        t0, _ = s.phase(f"gear{g}-shift", shift)
        s.at(t0, MotorCurrent(0.0))
        s.at(t0, Gear(int(g)))
        t0, t1 = s.phase(f"gear{g}-prbs", excite)
        _prbs(s, t0, t1, amplitude, 0.0, clock, order, seed, 10 + int(g))


def gears_excitation(seed: int = 0, gears: Sequence[int] = (1, 2, 3), shift: float = 1.0,
                     excite: float = 5.0, amplitude: float = 1.5, clock: float = 0.03,
                     order: int = 8) -> Experiment:
    """Each gear in turn: shift with the motor at 0 A, then PRBS current, band held.

    The default amplitude (1.5 A, 0.56 N m) stays within what a band at the driver's default
    engage current (0.5 A, about 4 N m) holds in every gear, gear 3 included.
    """
    s = _Schedule()
    s.at(0.0, Gear(0))
    _gear_blocks(s, gears, shift, excite, amplitude, clock, order, seed)
    _stop(s, 1.5)
    return s.build("gears_excitation", f"PRBS +-{amplitude:g} A in gears {list(gears)}, band "
                   "held (no engagement during excitation)", 1000, seed,
                   {"gears": tuple(gears), "shift_s": shift, "excite_s": excite,
                    "amplitude_A": amplitude, "clock_s": clock, "order": order})


def _neutral_opening(neutral_prbs: float, neutral_multisine: float, amplitude: float,
                     clock: float, order: int, seed: int) -> _Schedule:
    """Schedule opening the identification runs: neutral, PRBS on the motor current
    (``amplitude`` [A], ``neutral_prbs`` s), then a multisine 0.5 A stronger
    (``neutral_multisine`` s)."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, t1 = s.phase("neutral-prbs", neutral_prbs)
    _prbs(s, t0, t1, amplitude, 0.0, clock, order, seed, 1)
    t0, t1 = s.phase("neutral-multisine", neutral_multisine)
    _multisine(s, t0, t1, amplitude + 0.5, 0.0, 200.0, 5.0, 0.2, 20.0, seed, 2)
    return s


def ident(seed: int = 0, neutral_prbs: float = 6.0, neutral_multisine: float = 5.0,
          steps_dwell: float = 1.0, shift: float = 0.8, excite: float = 4.0,
          amplitude: float = 2.5, gear_amplitude: float = 1.5, clock: float = 0.03,
          order: int = 8) -> Experiment:
    """Identification-grade run (about 32 s at 1 kHz).

    Neutral PRBS (``neutral_prbs`` s) and multisine (``neutral_multisine`` s), sun-speed
    steps with reversals up to 2000 rpm (``steps_dwell`` s each), then gears 1, 2, 3: shift
    (``shift`` s at 0 A) and PRBS with the band held (``excite`` s each), then stop.
    ``amplitude`` [A] is the neutral PRBS level (the multisine peak is 0.5 A more),
    ``gear_amplitude`` [A] the in-gear PRBS level (small enough for the band to hold).
    """
    s = _neutral_opening(neutral_prbs, neutral_multisine, amplitude, clock, order, seed)
    t0, _ = s.phase("neutral-speed-steps", steps_dwell * len(SPEED_STEPS_RPM))
    _speed_steps(s, t0, SPEED_STEPS_RPM, steps_dwell)
    _gear_blocks(s, (1, 2, 3), shift, excite, gear_amplitude, clock, order, seed)
    _stop(s, 1.5)
    return s.build("ident", "identification run: neutral PRBS + multisine, speed steps, "
                   "gears 1-3 with PRBS", 1000, seed,
                   {"neutral_prbs_s": neutral_prbs, "neutral_multisine_s": neutral_multisine,
                    "steps_dwell_s": steps_dwell, "shift_s": shift, "excite_s": excite,
                    "amplitude_A": amplitude, "gear_amplitude_A": gear_amplitude,
                    "clock_s": clock, "order": order})


def ident_shifts(seed: int = 0, neutral_prbs: float = 5.0, neutral_multisine: float = 4.0,
                 speeds_rpm: Sequence[float] = (900.0, -700.0, 1200.0, -1000.0),
                 gears: Sequence[int] = (1, 2, 3), spin: float = 0.8, engaged: float = 0.7,
                 amplitude: float = 2.5, clock: float = 0.03, order: int = 8) -> Experiment:
    """Shift-rich identification run (about 29 s at 1 kHz) for band-engagement effects.

    Neutral PRBS (``neutral_prbs`` s) and multisine (``neutral_multisine`` s) as in
    :func:`ident`, then for each sun speed in ``speeds_rpm`` and each gear in ``gears``: the
    speed loop spins the shafts up in neutral (``spin`` s), then the motor goes to 0 A and the
    gear is selected (``engaged`` s): the band engages against a slipping ring (12 engagements
    and releases with the defaults), then stop.
    """
    s = _neutral_opening(neutral_prbs, neutral_multisine, amplitude, clock, order, seed)
    for rpm in speeds_rpm:
        for g in gears:
            t0, _ = s.phase(f"spin-{rpm:g}rpm", spin)
            s.at(t0, Gear(0))
            s.at(t0, SunSpeed(float(rpm) * RPM))
            t0, _ = s.phase(f"gear{g}-engage", engaged)
            s.at(t0, MotorCurrent(0.0))
            s.at(t0, Gear(int(g)))
    _stop(s, 1.5)
    return s.build("ident_shifts", "shift-rich identification run: neutral PRBS + multisine, "
                   f"band engagements in gears {list(gears)} from {list(speeds_rpm)} rpm", 1000,
                   seed, {"neutral_prbs_s": neutral_prbs, "neutral_multisine_s": neutral_multisine,
                          "speeds_rpm": tuple(speeds_rpm), "gears": tuple(gears),
                          "spin_s": spin, "engaged_s": engaged, "amplitude_A": amplitude,
                          "clock_s": clock, "order": order})


def watch(seed: int = 0, duration: float = 180.0, neutral_prbs: float = 6.0,
          neutral_multisine: float = 5.0, gears: Sequence[int] = (), shift: float = 0.8,
          excite: float = 4.0, amplitude: float = 2.5, gear_amplitude: float = 1.5,
          clock: float = 0.03, order: int = 8) -> Experiment:
    """Continuous excitation for ``duration`` [s] (then a 1.5 s stop), for the live loop.

    One cycle: neutral PRBS of +-``amplitude`` [A] (``neutral_prbs`` s, clock ``clock`` s),
    a random-phase multisine (0.2-20 Hz, peak ``amplitude`` + 0.5 A, ``neutral_multisine`` s),
    then for each gear of ``gears`` (default none: neutral only, the stationary residual the
    change detector is designed for; a commanded shift changes the residual of an imperfect
    model) a shift at 0 A (``shift`` s) and PRBS of +-``gear_amplitude`` [A] with the band held
    (``excite`` s). Cycles repeat with fresh random signals (cycle ``k`` draws its PRBS and
    multisine from streams of its own) until ``duration``; the last one is cut there. The
    schedule is that of :func:`ident`'s opening (the two-degree-of-freedom system and its
    friction reversals), so any window of it longer than a cycle can be refitted.

    Raises:
        ExperimentError: ``duration`` not in (0, 86400] s, a phase length not > 0, or a gear
            not in 1..3.
    """
    if isinstance(duration, bool) or not isinstance(duration, int | float) \
            or not (math.isfinite(duration) and 0 < duration <= 86400.0):
        raise ExperimentError(f"watch: duration: expected 0 < S <= 86400 s, got {duration!r}")
    for name, v in (("neutral_prbs", neutral_prbs), ("neutral_multisine", neutral_multisine),
                    ("shift", shift), ("excite", excite), ("clock", clock)):
        if isinstance(v, bool) or not isinstance(v, int | float) \
                or not (math.isfinite(v) and v > 0):
            raise ExperimentError(f"watch: {name}: expected a time > 0 s, got {v!r}")
    for g in gears:
        if g not in (1, 2, 3) or isinstance(g, bool):
            raise ExperimentError(f"watch: gears: expected gears 1..3, got {g!r}")
    s = _Schedule()
    s.at(0.0, Gear(0))
    end = float(duration)
    plan: list[tuple[str, float, int]] = [("neutral-prbs", neutral_prbs, 0),
                                          ("neutral-multisine", neutral_multisine, 0)]
    for g in gears:
        plan += [(f"gear{g}-shift", shift, int(g)), (f"gear{g}-prbs", excite, int(g))]
    k = 0
    while s.t < end - 1e-9:
        for label, length, g in plan:
            if s.t >= end - 1e-9:
                break
            t0, t1 = s.phase(label, min(length, end - s.t))
            stream = 1000 * (k + 1)
            if label == "neutral-prbs":
                if gears and k > 0:
                    s.at(t0, Gear(0))
                _prbs(s, t0, t1, amplitude, 0.0, clock, order, seed, stream + 1)
            elif label == "neutral-multisine":
                _multisine(s, t0, t1, amplitude + 0.5, 0.0, 200.0, 5.0, 0.2, 20.0, seed,
                           stream + 2)
            elif label.endswith("-shift"):
                s.at(t0, MotorCurrent(0.0))
                s.at(t0, Gear(g))
            else:
                _prbs(s, t0, t1, gear_amplitude, 0.0, clock, order, seed, stream + 10 + g)
        k += 1
    _stop(s, 1.5)
    return s.build("watch", f"continuous excitation for {duration:g} s: neutral PRBS + "
                   f"multisine{' and gears ' + str(list(gears)) if gears else ''}, repeated",
                   1000, seed,
                   {"duration_s": float(duration), "neutral_prbs_s": neutral_prbs,
                    "neutral_multisine_s": neutral_multisine, "gears": tuple(gears),
                    "shift_s": shift, "excite_s": excite, "amplitude_A": amplitude,
                    "gear_amplitude_A": gear_amplitude, "clock_s": clock, "order": order,
                    "cycles": k})


def smoke(seed: int = 0) -> Experiment:
    """A 5 s end-to-end check: neutral PRBS, gear 1 with PRBS, stop."""
    s = _Schedule()
    s.at(0.0, Gear(0))
    t0, t1 = s.phase("neutral-prbs", 2.0)
    _prbs(s, t0, t1, 2.0, 0.0, 0.03, 7, seed, 1)
    _gear_blocks(s, (1,), 0.5, 1.5, 1.5, 0.03, 7, seed)
    _stop(s, 1.0)
    return s.build("smoke", "short end-to-end check: neutral PRBS, gear 1 PRBS", 1000, seed,
                   {})


EXPERIMENTS: dict[str, Callable[..., Experiment]] = {
    "thesis": thesis,
    "shifts": shifts,
    "prbs": prbs,
    "multisine": multisine,
    "speed_steps": speed_steps,
    "gears_excitation": gears_excitation,
    "ident": ident,
    "ident_shifts": ident_shifts,
    "watch": watch,
    "smoke": smoke,
}
"""Experiment name -> builder ``f(seed=0, **settings) -> Experiment``."""


def available() -> list[str]:
    """Names of the built-in experiments."""
    return list(EXPERIMENTS)


def build(name: str, seed: int = 0, **settings: Any) -> Experiment:
    """Build the named experiment with ``seed`` (deterministic) and optional settings.

    Raises:
        ExperimentError: unknown name, bad setting, or a set-point beyond the limits.
    """
    if name not in EXPERIMENTS:
        raise ExperimentError(f"unknown experiment {name!r} (expected one of {available()})")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ExperimentError(f"seed: expected an integer >= 0, got {seed!r}")
    try:
        return EXPERIMENTS[name](seed=seed, **settings)
    except TypeError as exc:
        raise ExperimentError(f"experiment {name!r}: bad settings {settings}: {exc}") from exc

