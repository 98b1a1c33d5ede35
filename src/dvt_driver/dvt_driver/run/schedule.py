"""Experiment schedules as data (pure: no ROS, no I/O): the commands, steps, phases and limits
of an :class:`Experiment`, its validation against the driver's limits, and the excitation
signals the named experiments are built from (:mod:`dvt_driver.run.experiment_core`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_driver.errors import ExperimentError
from dvt_driver.hardware import (
    HARDWARE_MAX_BRAKE_CURRENT,
    HARDWARE_MAX_MOTOR_CURRENT,
    HARDWARE_MAX_SUN_SPEED,
    RPM,
)
from dvt_model import excitation
from dvt_model.errors import SimulationError

__all__ = [
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
    "multisine_signal",
    "prbs_signal",
]


# --------------------------------------------------------------------------- commands
@dataclass(frozen=True)
class MotorCurrent:
    """Drive-motor current set-point [A] (driver mode CURRENT)."""

    amps: float


@dataclass(frozen=True)
class SunSpeed:
    """Sun-shaft speed set-point [rad/s] (driver mode SPEED, the drive's own PI loop)."""

    rad_s: float


@dataclass(frozen=True)
class BrakeCurrents:
    """Band-brake coil current set-points [A] of brakes 1..3 (direct band control)."""

    amps: tuple[float, float, float]


@dataclass(frozen=True)
class Gear:
    """Gear selection: 0 neutral (all bands released), 1..3 (the driver's shift sequence)."""

    gear: int


@dataclass(frozen=True)
class MotorOff:
    """Switch the motor off (the driver's stop service)."""


Command = MotorCurrent | SunSpeed | BrakeCurrents | Gear | MotorOff


@dataclass(frozen=True)
class Step:
    """``command`` sent at ``t`` [s] after the experiment start."""

    t: float
    command: Command


@dataclass(frozen=True)
class Phase:
    """A labelled time span ``[start, end)`` [s] of an experiment."""

    start: float
    end: float
    label: str


@dataclass(frozen=True)
class Limits:
    """The driver's command limits an experiment must respect.

    Attributes:
        motor_current: largest motor current magnitude [A] (12 N m peak / 0.3732 N m/A).
        sun_speed: largest sun-speed set-point magnitude [rad/s] (2400 rpm).
        brake_current: largest brake coil current [A]; brake currents are >= 0.
    """

    motor_current: float = HARDWARE_MAX_MOTOR_CURRENT
    sun_speed: float = HARDWARE_MAX_SUN_SPEED
    brake_current: float = HARDWARE_MAX_BRAKE_CURRENT


@dataclass(frozen=True)
class Experiment:
    """A time-indexed command schedule.

    Attributes:
        name: experiment name (a key of :data:`EXPERIMENTS`).
        description: one line for humans.
        steps: commands sorted by time (ties keep their order).
        phases: labelled time spans covering ``[0, duration)``.
        duration: total length [s]; the last step is at or before it.
        sample_period_us: the controller sample period the experiment is meant for [µs]
            (``16000`` for the thesis replica, ``1000`` otherwise).
        seed: the seed the random signals were drawn with.
        settings: the builder's keyword arguments (provenance).
    """

    name: str
    description: str
    steps: tuple[Step, ...]
    phases: tuple[Phase, ...]
    duration: float
    sample_period_us: int = 1000
    seed: int = 0
    settings: dict[str, Any] = field(default_factory=dict)

    def validate(self, limits: Limits | None = None) -> Experiment:
        """Check times and every set-point against ``limits``; returns ``self``.

        Raises:
            ExperimentError: naming the step index, its time, the field and the value.
        """
        lim = limits or Limits()
        if not (math.isfinite(self.duration) and self.duration > 0):
            raise ExperimentError(f"experiment {self.name!r}: duration: expected a finite "
                                  f"number > 0 s, got {self.duration!r}")
        last = 0.0
        for i, step in enumerate(self.steps):
            where = f"experiment {self.name!r}: step {i} at t={step.t!r} s"
            if not (isinstance(step.t, float | int) and math.isfinite(step.t)):
                raise ExperimentError(f"{where}: time is not a finite number")
            if step.t < last or step.t > self.duration:
                raise ExperimentError(f"{where}: time must be within [{last:.6g}, "
                                      f"{self.duration:.6g}] s (sorted, inside the duration)")
            last = step.t
            _check_command(where, step.command, lim)
        for k, ph in enumerate(self.phases):
            if not (0.0 <= ph.start < ph.end <= self.duration + 1e-9):
                raise ExperimentError(f"experiment {self.name!r}: phase {k} ({ph.label!r}): "
                                      f"expected 0 <= start < end <= {self.duration:.6g} s, "
                                      f"got [{ph.start:.6g}, {ph.end:.6g})")
        return self

    def phase_at(self, t: float) -> str:
        """Label of the phase containing ``t`` [s] (``""`` if none)."""
        for ph in self.phases:
            if ph.start <= t < ph.end:
                return ph.label
        return ""

    def sample(self, t: NDArray[np.float64] | Sequence[float]) -> dict[str, NDArray[Any]]:
        """The held set-points at times ``t`` [s], shape (N,) (for plots, tests, simulation).

        Returns a dict of arrays of shape (N,) unless noted: ``mode`` (0 off, 1 current,
        2 speed), ``setpoint`` (A or rad/s), ``brake`` (N, 3) direct brake currents [A] (the
        last :class:`BrakeCurrents`), ``gear`` (last :class:`Gear`, -1 before any), ``brake_cmd``
        (N,) int: 1 where the last brake-related command was a :class:`BrakeCurrents`, 0 where
        it was a :class:`Gear`.
        """
        tt = np.asarray(t, dtype=np.float64)
        n = tt.shape[0]
        mode = np.zeros(n, dtype=np.int64)
        setpoint = np.zeros(n)
        brake = np.zeros((n, 3))
        gear = np.full(n, -1, dtype=np.int64)
        brake_cmd = np.zeros(n, dtype=np.int64)
        times = np.array([s.t for s in self.steps], dtype=np.float64)
        # index of the first sample at or after each step (a step applies from its time on)
        starts = np.searchsorted(tt, times, side="left")
        for k, step in zip(starts, self.steps, strict=True):
            c = step.command
            if isinstance(c, MotorCurrent):
                mode[k:], setpoint[k:] = 1, c.amps
            elif isinstance(c, SunSpeed):
                mode[k:], setpoint[k:] = 2, c.rad_s
            elif isinstance(c, MotorOff):
                mode[k:], setpoint[k:] = 0, 0.0
            elif isinstance(c, BrakeCurrents):
                brake[k:] = c.amps
                brake_cmd[k:] = 1
            else:
                gear[k:] = c.gear
                brake_cmd[k:] = 0
        return {"mode": mode, "setpoint": setpoint, "brake": brake, "gear": gear,
                "brake_cmd": brake_cmd}

    def to_mapping(self) -> dict[str, Any]:
        """A YAML/JSON-friendly summary (no individual steps)."""
        counts: dict[str, int] = {}
        for s in self.steps:
            key = type(s.command).__name__
            counts[key] = counts.get(key, 0) + 1
        return {
            "name": self.name,
            "description": self.description,
            "seed": self.seed,
            "duration_s": round(self.duration, 6),
            "sample_period_us": self.sample_period_us,
            "settings": {k: _plain(v) for k, v in self.settings.items()},
            "steps": counts,
            "phases": [{"start_s": round(p.start, 6), "end_s": round(p.end, 6),
                        "label": p.label} for p in self.phases],
        }


def _plain(v: Any) -> Any:
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _finite(where: str, what: str, v: float) -> float:
    if isinstance(v, bool) or not isinstance(v, float | int) or not math.isfinite(v):
        raise ExperimentError(f"{where}: {what}: expected a finite number, got {v!r}")
    return float(v)


def _check_command(where: str, c: Command, lim: Limits) -> None:
    if isinstance(c, MotorCurrent):
        v = _finite(where, "motor current", c.amps)
        if abs(v) > lim.motor_current:
            raise ExperimentError(f"{where}: motor current {v:.6g} A exceeds the limit "
                                  f"{lim.motor_current:.6g} A")
    elif isinstance(c, SunSpeed):
        v = _finite(where, "sun speed", c.rad_s)
        if abs(v) > lim.sun_speed:
            raise ExperimentError(f"{where}: sun speed {v:.6g} rad/s ({v / RPM:.1f} rpm) "
                                  f"exceeds the limit {lim.sun_speed:.6g} rad/s "
                                  f"({lim.sun_speed / RPM:.0f} rpm)")
    elif isinstance(c, BrakeCurrents):
        if len(c.amps) != 3:
            raise ExperimentError(f"{where}: brake currents: expected 3 values, "
                                  f"got {len(c.amps)}")
        for j, a in enumerate(c.amps):
            v = _finite(where, f"brake{j + 1} current", a)
            if not 0.0 <= v <= lim.brake_current:
                raise ExperimentError(f"{where}: brake{j + 1} current {v:.6g} A outside "
                                      f"[0, {lim.brake_current:.6g}] A")
    elif isinstance(c, Gear):
        if isinstance(c.gear, bool) or not isinstance(c.gear, int) or c.gear not in (0, 1, 2, 3):
            raise ExperimentError(f"{where}: gear: expected 0 (neutral), 1, 2 or 3, "
                                  f"got {c.gear!r}")
    elif not isinstance(c, MotorOff):
        raise ExperimentError(f"{where}: unknown command {c!r}")


# --------------------------------------------------------------------------- signals
def _rng(seed: int, stream: int) -> np.random.Generator:
    """Independent generator per signal of an experiment (stable when others change)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(stream)])


def prbs_signal(n_bits: int, order: int, seed: int, stream: int = 0) -> NDArray[np.float64]:
    """``n_bits`` values of a maximum-length binary sequence in {-1, +1}
    (:func:`dvt_model.excitation.prbs`: period ``2**order - 1``, flat spectrum up to about
    0.44 / clock period; the seed and stream choose its starting state).

    Raises:
        ExperimentError: ``order`` outside 3..24.
    """
    try:
        return excitation.prbs(n_bits, order, seed, stream)
    except SimulationError as exc:
        raise ExperimentError(str(exc)) from exc


def multisine_signal(t: NDArray[np.float64], period: float, f_lo: float, f_hi: float,
                     seed: int, stream: int = 0) -> NDArray[np.float64]:
    """Random-phase multisine at times ``t`` [s], shape (N,), normalised to peak 1.

    Harmonics ``k / period`` [Hz] in ``[f_lo, f_hi]``, roughly log-spaced (every harmonic up
    to 2 Hz, then about 12 per decade) with equal amplitudes; the phases are drawn from the
    seed, the best crest factor of 20 draws is kept.
    """
    if not (period > 0 and 0 < f_lo <= f_hi):
        raise ExperimentError(f"multisine: expected period > 0 and 0 < f_lo <= f_hi, got "
                              f"period={period}, f_lo={f_lo}, f_hi={f_hi}")
    k_lo = max(1, math.ceil(f_lo * period - 1e-9))
    k_hi = math.floor(f_hi * period + 1e-9)
    if k_hi < k_lo:
        raise ExperimentError(f"multisine: no harmonic of 1/{period} s in [{f_lo}, {f_hi}] Hz")
    ks: list[int] = []
    for k in range(k_lo, k_hi + 1):
        f = k / period
        if f <= 2.0 or not ks or math.log10(f * period / ks[-1]) >= 1.0 / 12.0:
            ks.append(k)
    freqs = np.asarray(ks, dtype=np.float64) / period
    rng = _rng(seed, stream)
    grid = np.linspace(0.0, period, 2048, endpoint=False)
    best_crest = math.inf
    phases = np.zeros(freqs.shape[0])
    for _ in range(20):
        ph = np.asarray(rng.uniform(0.0, 2.0 * math.pi, freqs.shape[0]), dtype=np.float64)
        x = np.cos(2.0 * math.pi * np.outer(grid, freqs) + ph).sum(axis=1)
        crest = float(np.max(np.abs(x)) / np.sqrt(np.mean(x ** 2)))
        if crest < best_crest:
            best_crest = crest
            phases = ph
    x_grid = np.cos(2.0 * math.pi * np.outer(grid, freqs) + phases).sum(axis=1)
    peak = float(np.max(np.abs(x_grid)))
    y = np.cos(2.0 * math.pi * np.outer(np.asarray(t, dtype=np.float64), freqs)
               + phases).sum(axis=1)
    return np.asarray(np.clip(y / peak, -1.0, 1.0), dtype=np.float64)
