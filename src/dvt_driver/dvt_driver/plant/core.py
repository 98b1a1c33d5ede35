"""Simulated DVT motor/brake controller and transmission: the plant's core (pure, no I/O).

:class:`PlantSim` is what sits on the other end of the serial line in tests and the demo: the
controller firmware (protocol session, sun-speed PI loop, current loop, safety, sensors) and the
transmission it drives (the ``dvt_model`` hybrid physics plus the hidden effects of
:mod:`dvt_driver.plant.hidden`). :mod:`dvt_driver.plant.server` puts it on a pseudo-terminal in
real time.

Time. The controller samples every ``sample_period_us`` [µs] (default 1000, i.e. 1 kHz; the
thesis's 16 ms serial limit is ``16000``). Each :meth:`PlantSim.tick` produces the sample at the
current instant ``t_k`` and then advances the physics to ``t_k + T`` in ``n`` equal sub-steps
of at most ``max_step`` (1 ms; shorter when a stiff hidden effect needs it). Motor and brake
currents are held over each sub-step. The controller's own loops (speed PI, watchdog,
overspeed check) run once per sub-step, i.e. at 1 kHz or faster whatever the sample period:
the serial sample period limits what the host sees, not how the drive controls.

Drive. Mode ``CURRENT``: the set-point is the motor current [A]. Mode ``SPEED``: a PI loop on
the encoder speed (count difference over ``speed_window``) sets the current; its output is
clamped to the motor current limit with conditional integration (no wind-up) and it starts
bumplessly from the present current. The power stage follows the reference with a first-order
lag ``current_time_constant`` (0 = ideal). Brake coil currents follow their set-points ideally;
the band's torque lags them (first-order in ``dvt_model``, or the wet-to-dry shape).

Safety (the controller's own, independent of the driver's):

* current clamp: motor reference clamped to ``motor_current_limit`` (12 N m / K_M by default),
  flag ``CURRENT_LIMIT`` in every sample whose interval clamped; brake set-points are clamped to
  ``[0, brake_current_limit]`` (a negative coil current only releases the band);
* speed set-points beyond ``speed_limit`` (2400 rpm, the thesis's safe maximum) are refused
  (NACK ``INVALID_VALUE``); the overspeed trip fires when the encoder speed exceeds
  ``speed_limit * (1 + overspeed_margin)`` (the margin keeps a PI loop running at the limit
  from tripping on overshoot and quantisation): safe state, ``OVERSPEED`` and ``FAULT``
  latched; COMMANDs with mode ``CURRENT``/``SPEED`` are refused with ``FAULT_LATCHED``; a
  COMMAND with mode ``OFF`` is acknowledged and clears the latch once the speed is below the
  trip threshold again (a controller reset clears it too);
* command watchdog: the first accepted COMMAND arms it, every accepted COMMAND re-arms it;
  after ``watchdog_timeout`` without one the controller enters the safe state and sets
  ``WATCHDOG`` until the next accepted COMMAND.

The safe state (watchdog and faults, as ``docs/protocol.md`` specifies) is motor current 0,
mode ``OFF``, and the brake coils *keep their last commanded currents*: a band released while
the output is loaded, or half-way through a shift, lets the load drive the transmission into
an undefined ratio, whereas a held band with the motor off only lets the drivetrain coast
down under its damping and cannot cause an overspeed.

Sensors, as on the thesis bench:

* sun speed from the drive's incremental encoder (``encoder_lines`` x 4 counts/rev): the count
  difference over the sample period divided by the period, so the speed is quantised to
  ``2 pi / (4 lines T)`` (1.53 rad/s at 1 kHz);
* positions (protocol version 2 only): the raw counts of the sun encoder (4096 counts/rev,
  zero at the controller's start: an incremental encoder, re-zeroed by a controller reset)
  and of an output encoder on carrier 3 (``output_encoder_lines`` x 4 = 16384 counts/rev,
  zero at the plant's start and kept across controller resets: an absolute multi-turn joint
  encoder, so a joint load's angle stays known), both wrapped to i32 on the wire; with
  backlash the output encoder, like the tachometer, reads the output shaft behind the spline;
* carrier-3 (output-shaft) speed from a DC tachometer (``tach_rpm_per_volt`` = 90.793 rpm/V)
  with Gaussian voltage noise, read by a ``adc_bits`` A/D converter over +-``adc_range`` V
  (clipping at the rails); with backlash the tachometer reads the output shaft behind the
  spline;
* motor and brake currents with Gaussian noise and A/D quantisation.

A hidden ``measurement_delay`` delays both speed measurements and both encoder counts (not the
currents, whose measurement path is the drive's own), rounded to the physics sub-step.

Angles and loads. The physics integrates the members' angles (``HybridState.theta``, sun shaft
and carrier 3 from the plant's start; every other member's angle is its linear form of them).
An optional declared joint load (``load=``, ``dvt-plant --load arm|arm-payload|<yaml>``,
:mod:`dvt_model.load`: output stage + arm under gravity, hanging down at the output encoder's
zero in the presets) acts on carrier 3 through the output stage: reflected inertia
``J_arm / reduction^2`` and the gravity torque ``-(Mp/2 + Ma) l g cos(theta_arm) / reduction``
(efficiency by power direction). The arm has no end stops in the simulation. The hidden
effects may add an undeclared ``gravity_arm``, a ``mesh_ripple`` and a ``position_friction``
(:mod:`dvt_driver.plant.hidden`).

A changing plant. ``hidden.changes`` (and ``hidden.damping_scale``) make the plant change while
it runs (:func:`dvt_driver.plant.hidden.scheduled_values`): Coulomb friction and windage per
member, the scale of the transmission's viscous damping ``D`` (applied as the extra generalised
torque ``-(scale - 1) D omega``) and the declared joint load (a step: the model is rebuilt with
the new load, speeds continuous). The schedule is evaluated against the physics time at the
start of each sample period: at every change's ``at`` and, during a ramp, every
:data:`RAMP_UPDATE_S` (the ramp is a staircase of 10 ms steps). :meth:`PlantSim.add_change`
adds a change at runtime (``dvt-plant`` ``--change-at``, SIGHUP). Every change the plant starts
is appended to :attr:`PlantSim.changes_applied` (plant time ``at_s``, the change) and written
into ``truth.yaml``.

Protocol versions. The plant speaks versions 1..``protocol_version`` (default 2,
``dvt-plant --protocol-version 1`` emulates an old controller): it answers a HELLO of a version
it speaks with that version (HELLO_ACK of version 2 carries the encoders' counts per
revolution) and NACKs any other; in a version-2 session every sample carries the counts
(SAMPLE_V2), in a version-1 session none.

Status bits: ``ENABLED`` while mode ``CURRENT``/``SPEED`` drives the motor; ``BRAKEk`` while
coil k carries more than 5 mA (the band is applied; whether it holds is the transmission's
business, reported by the speeds); ``WATCHDOG``, ``OVERSPEED``, ``FAULT`` and
``CURRENT_LIMIT`` as above.

Session (see ``docs/protocol.md``): HELLO -> HELLO_ACK (or NACK ``UNSUPPORTED_VERSION``);
COMMAND and CONFIG before a HELLO -> NACK ``NOT_READY``; accepted COMMAND/CONFIG -> ACK.
Samples are numbered from 0 as they are streamed after the first HELLO following a controller
start or reset, so a host always sees a reset as the sequence number going back.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_driver.errors import PlantError
from dvt_driver.link.protocol import (
    PROTOCOL_VERSION,
    SUPPORTED_VERSIONS,
    Ack,
    Command,
    Config,
    FrameType,
    Hello,
    HelloAck,
    Message,
    Mode,
    Nack,
    NackReason,
    Sample,
    Status,
    sample_wire_len,
    wrap_count,
)
from dvt_driver.plant.hidden import (
    Change,
    FrictionForces,
    HiddenEffects,
    WetBrakeEngagement,
    friction_velocity_floor,
    scheduled_values,
)
from dvt_model.dynamics import rigid_model
from dvt_model.hybrid import HybridModel, HybridState
from dvt_model.load import JointLoad, load_joint_load
from dvt_model.params import TransmissionParams

__all__ = [
    "DEFAULT_SAMPLE_PERIOD_US",
    "FIRMWARE_ID",
    "MAX_SAMPLE_PERIOD_US",
    "MIN_SAMPLE_PERIOD_US",
    "RPM",
    "DriveConfig",
    "PlantSim",
    "SafetyLimits",
    "SampleValues",
    "SensorConfig",
]

Array = NDArray[np.float64]

RPM = 2.0 * math.pi / 60.0
"""One rpm in rad/s."""

DEFAULT_SAMPLE_PERIOD_US = 1000
MIN_SAMPLE_PERIOD_US = 500
MAX_SAMPLE_PERIOD_US = 1_000_000
FIRMWARE_ID = "dvt-plant-sim 0.1"

RAMP_UPDATE_S = 0.01
"""Update period of a ramping change [s of plant time]."""
_BRAKE_ON = 0.005  # A: a coil current above this counts as "band applied" (status BRAKEk)
_NOISE_BLOCK = 1024  # samples of sensor noise drawn at once
_OSC_STEP = 0.35  # rad: largest phase advance of the backlash contact oscillation per sub-step
# status bits as plain ints (IntFlag arithmetic is slow in a 1 kHz loop)
_ENABLED = int(Status.ENABLED)
_WATCHDOG = int(Status.WATCHDOG)
_OVERSPEED = int(Status.OVERSPEED)
_FAULT = int(Status.FAULT)
_CURRENT_LIMIT = int(Status.CURRENT_LIMIT)
_BRAKE_BITS = (int(Status.BRAKE1), int(Status.BRAKE2), int(Status.BRAKE3))


@dataclass(frozen=True)
class SafetyLimits:
    """Controller-side safety settings.

    Attributes:
        speed_limit: largest accepted sun speed set-point [rad/s] (2400 rpm).
        overspeed_margin: the trip fires above ``speed_limit * (1 + margin)``.
        motor_current_limit: motor current clamp [A] (peak 12 N m / 0.3732 N m/A).
        brake_current_limit: brake coil current clamp [A] (6 A = 48 N m static band torque,
            enough to hold the peak motor torque in every gear).
        watchdog_timeout: command watchdog [s]; 0 disables it.
    """

    speed_limit: float = 2400.0 * RPM
    overspeed_margin: float = 0.05
    motor_current_limit: float = 12.0 / 0.3732
    brake_current_limit: float = 6.0
    watchdog_timeout: float = 0.2

    @property
    def trip_speed(self) -> float:
        """Overspeed trip threshold [rad/s]."""
        return self.speed_limit * (1.0 + self.overspeed_margin)


@dataclass(frozen=True)
class SensorConfig:
    """Bench sensors.

    Attributes:
        encoder_lines: sun-shaft encoder lines per revolution (x4 quadrature counts).
        output_encoder_lines: output (carrier-3) encoder lines per revolution (x4 counts).
        tach_rpm_per_volt: tachometer calibration [rpm/V] (thesis: 90.793).
        tach_noise: tachometer voltage noise, standard deviation [V].
        adc_bits: A/D resolution of the tachometer channel [bit].
        adc_range: A/D input range +- [V].
        motor_current_noise: standard deviation [A].
        motor_current_range: motor-current A/D range +- [A] (12 bit).
        brake_current_noise: standard deviation [A].
        brake_current_range: brake-current A/D range +- [A] (12 bit).
    """

    encoder_lines: int = 1024
    output_encoder_lines: int = 4096
    tach_rpm_per_volt: float = 90.793
    tach_noise: float = 0.01
    adc_bits: int = 12
    adc_range: float = 10.0
    motor_current_noise: float = 0.03
    motor_current_range: float = 40.0
    brake_current_noise: float = 0.002
    brake_current_range: float = 8.0

    @property
    def counts_per_rev(self) -> int:
        """Quadrature counts per revolution of the sun-shaft encoder (4096)."""
        return 4 * self.encoder_lines

    @property
    def output_counts_per_rev(self) -> int:
        """Quadrature counts per revolution of the output (carrier-3) encoder (16384)."""
        return 4 * self.output_encoder_lines

    @property
    def tach_lsb(self) -> float:
        """Tachometer A/D step [V]."""
        return 2.0 * self.adc_range / (1 << self.adc_bits)


@dataclass(frozen=True)
class DriveConfig:
    """Drive (servo amplifier) settings.

    Attributes:
        kp: speed-loop proportional gain [A/(rad/s)].
        ki: speed-loop integral gain [A/rad].
        current_time_constant: current-loop lag [s] (0 = ideal current source).
        speed_window: encoder speed window of the speed loop [s].
    """

    kp: float = 0.25
    ki: float = 8.0
    current_time_constant: float = 0.001
    speed_window: float = 0.001


@dataclass(frozen=True)
class SampleValues:
    """One controller sample, plus the true state behind it (not on the wire).

    Attributes:
        seq: sample sequence number (u32, wraps).
        t_us: controller clock [µs].
        sun_speed: measured sun speed [rad/s] (encoder).
        carrier3_speed: measured carrier-3 / output speed [rad/s] (tachometer).
        motor_current: measured motor current [A].
        brake_currents: measured brake coil currents [A].
        status: :class:`~dvt_driver.link.protocol.Status` bits.
        omega_true: true (omega_sun, omega_carrier3) [rad/s] at the sample instant.
        output_true: true output-shaft speed [rad/s] (carrier 3 unless backlash).
        gear: model gear state (1-3, 0 neutral/slipping, -1 tie-up).
        counts: raw encoder counts ``(sun, output)`` (i32, wrapped) in a version-2 session,
            ``None`` in a version-1 session (not sent).
        theta_true: true (theta_sun, theta_carrier3) [rad] from the plant's start.
        output_angle_true: true output-shaft angle [rad] (carrier 3 unless backlash).
    """

    seq: int
    t_us: int
    sun_speed: float
    carrier3_speed: float
    motor_current: float
    brake_currents: tuple[float, float, float]
    status: Status
    omega_true: tuple[float, float]
    output_true: float
    gear: int
    counts: tuple[int, int] | None = None
    theta_true: tuple[float, float] = (0.0, 0.0)
    output_angle_true: float = 0.0

    def to_sample(self) -> Sample:
        """The wire message of this sample (SAMPLE_V2 when it carries counts)."""
        return Sample(self.seq, self.t_us, self.sun_speed, self.carrier3_speed,
                      self.motor_current, self.brake_currents, self.status, self.counts)


def _quantise(x: float, lsb: float, full: float) -> float:
    """``x`` read by a bipolar A/D with step ``lsb`` over +-``full`` (clips at the rails)."""
    top = int(full / lsb + 0.5)
    code = min(max(math.floor(x / lsb + 0.5), -top), top - 1)
    return code * lsb


class PlantSim:
    """The simulated controller + transmission (see the module docstring).

    Args:
        params: transmission parameter set (``load_parameters('physical')``).
        hidden: hidden effects (``None`` = clean plant).
        sample_period_us: controller sample period [µs].
        seed: seed of the sensor-noise generator (``None``: random).
        limits, sensors, drive: controller settings.
        max_step: longest physics sub-step [s].
        baud: line rate [bit/s] used to refuse sample periods the line cannot carry
            (``None``: no check).
        watchdog: ``None`` keeps ``limits.watchdog_timeout``.
        load: declared joint load on carrier 3 (``None``: none).
        protocol_version: newest protocol version the controller speaks (1 or 2).

    Raises:
        PlantError: a setting is out of range.
    """

    # controller state, (re)set by _clear_controller
    seq: int
    t_us: int
    session_open: bool
    _mode: Mode
    _setpoint: float
    _brake_cmd: NDArray[np.float64]
    _integ: float
    _i_ref: float
    _last_cmd_us: int
    _armed: bool
    _watchdog: bool
    _fault: bool
    _overspeed: bool
    _clamped: bool
    _w_enc: float

    def __init__(self, params: TransmissionParams, hidden: HiddenEffects | None = None,
                 sample_period_us: int = DEFAULT_SAMPLE_PERIOD_US, seed: int | None = None, *,
                 limits: SafetyLimits | None = None, sensors: SensorConfig | None = None,
                 drive: DriveConfig | None = None, max_step: float = 0.001,
                 baud: int | None = None, load: JointLoad | None = None,
                 protocol_version: int = PROTOCOL_VERSION) -> None:
        if protocol_version not in SUPPORTED_VERSIONS:
            raise PlantError(f"protocol_version: expected one of {list(SUPPORTED_VERSIONS)}, "
                             f"got {protocol_version!r}")
        self.protocol_version = protocol_version
        self.session_version = 0  # version of the open session (0: none)
        self.load = load
        self._load0 = load  # the declared load at the start (truth.yaml; changes may replace it)
        self.params = params
        self.hidden = hidden if hidden is not None else HiddenEffects()
        self.seed = seed
        self.limits = limits if limits is not None else SafetyLimits()
        self.sensors = sensors if sensors is not None else SensorConfig()
        self.drive = drive if drive is not None else DriveConfig()
        self.baud = baud
        if not (math.isfinite(max_step) and max_step > 0.0):
            raise PlantError(f"max_step: expected a number > 0 s, got {max_step!r}")
        if self.limits.watchdog_timeout < 0.0:
            raise PlantError(f"watchdog_timeout: expected >= 0 s, got "
                             f"{self.limits.watchdog_timeout!r}")
        if self.drive.current_time_constant < 0.0:
            raise PlantError(f"current_time_constant: expected >= 0 s, got "
                             f"{self.drive.current_time_constant!r}")
        self._rng = np.random.default_rng(seed)
        self._noise: list[list[float]] = []

        h = self.hidden
        self._engagement = (WetBrakeEngagement(h.wet_brake, params.brake.time_constant)
                            if h.wet_brake else None)
        rigid0 = rigid_model(params)
        self._gravity = h.gravity_arm
        if self._gravity is not None:  # the undeclared arm's inertia, on carrier 3
            c3 = rigid0.kin.vector("carrier3")
            rigid0 = dataclasses.replace(
                rigid0, M=rigid0.M + self._gravity.reflected_inertia * np.outer(c3, c3))
        self._ripple_teeth = (params.stages[h.mesh_ripple.stage - 1].sun
                              if h.mesh_ripple is not None else 0)
        self._bumps: list[tuple[Array, Any, float]] = []  # (form, bump, v_eps) per member
        self.model = HybridModel(rigid0, params.brake, extra_force=self._extra_force,
                                 engagement=self._engagement, load=load,
                                 angle_force=self._angle_force if h.has_angle_effects else None)
        rigid = self.model.rigid
        self._m_inv = np.linalg.inv(rigid.M)
        self._step_limit = max_step
        if h.backlash is not None:
            j_c3 = 1.0 / float(self._m_inv[1, 1])  # smallest inertia carrier 3 can present
            wn = h.backlash.natural_frequency(j_c3)
            self._step_limit = min(self._step_limit, _OSC_STEP / wn)
        self._friction: FrictionForces | None = None
        self._rigid0 = rigid0
        # the changing plant: the effects in force (base + changes so far), the D correction
        self._base_hidden = self.hidden
        self._damping_extra: Array | None = None  # -(scale - 1) D, or None
        self._next_change_t = math.inf if not self.hidden.changes else 0.0
        self._started_changes = 0
        self.changes_applied: list[dict[str, Any]] = []
        """Every change the plant started: ``{"at_s": plant time, "change": mapping}``."""
        if self.hidden.damping_scale != 1.0:
            self._damping_extra = -(self.hidden.damping_scale - 1.0) * self.model.rigid.D

        # physical state
        self.state: HybridState = self.model.initial_state()
        self._theta_sun = 0.0  # rad
        self._sun_zero = 0  # sun-encoder count at the controller's start
        self._bl_twist = 0.0  # rad, carrier 3 minus output shaft (backlash only)
        self._w_load = 0.0  # rad/s, output shaft (backlash only)
        self._i_motor = 0.0  # A, actual motor current
        self._i_brake = np.zeros(3)  # A, applied coil currents
        self._t_phys = 0.0
        self._memo_key: tuple[float, float] | None = None
        self._memo_force = np.zeros(2)

        # controller state
        self._period_us = 0
        self._n_sub = 1
        self._h = 0.0
        self._clear_controller()
        self._ctrl_counts: deque[int] = deque(maxlen=2)
        self._last_sample_theta = 0.0
        self._hist_theta: deque[float] = deque(maxlen=1)
        self._hist_out: deque[float] = deque(maxlen=1)
        self._hist_out_theta: deque[float] = deque(maxlen=1)
        self.commands_accepted = 0
        self.commands_refused = 0
        self.trips = 0
        self.watchdog_trips = 0
        self.set_sample_period(sample_period_us)

    # ------------------------------------------------------------------ configuration
    @property
    def sample_period_us(self) -> int:
        """Controller sample period [µs]."""
        return self._period_us

    @property
    def substeps(self) -> int:
        """Physics sub-steps per sample."""
        return self._n_sub

    @property
    def step(self) -> float:
        """Physics sub-step [s]."""
        return self._h

    @property
    def mode(self) -> Mode:
        """Active drive mode (``OFF`` while the watchdog or a fault holds the motor off)."""
        if self._fault or self._watchdog:
            return Mode.OFF
        return self._mode

    def check_sample_period(self, period_us: int) -> str | None:
        """Why ``period_us`` [µs] is not acceptable, or ``None`` if it is."""
        if isinstance(period_us, bool) or not isinstance(period_us, int):
            return f"sample period: expected an integer number of µs, got {period_us!r}"
        if not MIN_SAMPLE_PERIOD_US <= period_us <= MAX_SAMPLE_PERIOD_US:
            return (f"sample period: expected {MIN_SAMPLE_PERIOD_US}..{MAX_SAMPLE_PERIOD_US} µs, "
                    f"got {period_us}")
        if self.baud is not None:
            # the frames of the open session, else the longest the controller may send
            version = self.session_version or self.protocol_version
            wire_us = sample_wire_len(version) * 10 * 1e6 / self.baud
            if period_us < wire_us:
                return (f"sample period: {period_us} µs is shorter than one sample frame on a "
                        f"{self.baud} baud line ({wire_us:.0f} µs)")
        return None

    def set_sample_period(self, period_us: int) -> None:
        """Set the sample period [µs] (and the sub-steps); the clock keeps running.

        Raises:
            PlantError: period out of range or more than the line can carry.
        """
        why = self.check_sample_period(period_us)
        if why is not None:
            raise PlantError(why)
        period = period_us * 1e-6
        n = max(1, math.ceil(period / self._step_limit - 1e-9))
        self._period_us = period_us
        self._n_sub = n
        self._h = period / n
        self._rebuild_friction()
        self._bumps = []
        for member, bump in self.hidden.position_friction.items():
            a = self.model.rigid.kin.vector(member)
            floor = friction_velocity_floor(bump.amplitude, float(a @ self._m_inv @ a), self._h)
            self._bumps.append((a, bump, max(self.hidden.friction_velocity, floor)))
        window = max(1, round(self.drive.speed_window / self._h))
        counts = self._counts()
        self._ctrl_counts = deque([counts] * (window + 1), maxlen=window + 1)
        delay = max(0, round(self.hidden.measurement_delay / self._h))
        self._hist_theta = deque([self._theta_sun] * (delay + 1), maxlen=delay + 1)
        self._hist_out = deque([self._output_speed()] * (delay + 1), maxlen=delay + 1)
        self._hist_out_theta = deque([self._output_angle()] * (delay + 1), maxlen=delay + 1)
        self._last_sample_theta = self._hist_theta[0]

    @property
    def delay_steps(self) -> int:
        """The measurement delay in physics sub-steps."""
        return len(self._hist_theta) - 1

    def describe(self) -> dict[str, Any]:
        """Plant settings for ``truth.yaml`` (plain types)."""
        return {"substeps": self._n_sub, "physics_step_s": self._h,
                "limits": asdict(self.limits), "sensors": asdict(self.sensors),
                "drive": asdict(self.drive), "firmware_id": FIRMWARE_ID,
                "protocol_version": self.protocol_version,
                "encoders": {"sun_counts_per_rev": self.sensors.counts_per_rev,
                             "output_counts_per_rev": self.sensors.output_counts_per_rev,
                             "output_member": "carrier3"},
                "load": (None if self._load0 is None
                         else {"name": self._load0.name, **self._load0.to_mapping()})}

    def truth_yaml(self) -> str:
        """Text of ``truth.yaml`` for this plant."""
        return self._base_hidden.to_truth_yaml(
            params_name=self.params.name, seed=self.seed, sample_period_us=self._period_us,
            extra=self.describe(),
            applied=self.changes_applied if self._base_hidden.changes else None)

    # ------------------------------------------------------------------ a changing plant
    def add_change(self, change: Change) -> None:
        """Add ``change`` to the schedule (its ``at`` in plant time; at or before
        :attr:`physics_time`: applied at the next sample)."""
        base = self._base_hidden
        self._base_hidden = dataclasses.replace(base, changes=(*base.changes, change))
        self.hidden = dataclasses.replace(self.hidden, changes=self._base_hidden.changes)
        self._next_change_t = min(self._next_change_t, change.at)

    def _apply_schedule(self) -> None:
        """Bring the changeable effects to the schedule's values at the present plant time."""
        t = self._t_phys
        base = self._base_hidden
        v = scheduled_values(base, t + 1e-6)  # 1 us: the physics time's rounding
        ordered = sorted(base.changes, key=lambda c: c.at)
        for ch in ordered[self._started_changes:v.started]:
            self.changes_applied.append({"at_s": round(t, 6), "change": ch.to_mapping()})
        self._started_changes = v.started
        if v.load is not None:
            load = None if v.load == "none" else load_joint_load(v.load)
            if (load is None) != (self.load is None) or (
                    load is not None and self.load is not None and load != self.load):
                self.load = load
                self.model = HybridModel(self._rigid0, self.params.brake,
                                         extra_force=self._extra_force,
                                         engagement=self._engagement, load=load,
                                         angle_force=self.model.angle_force)
        self.hidden = dataclasses.replace(self.hidden, coulomb=v.coulomb, windage=v.windage,
                                          damping_scale=v.damping_scale)
        self._damping_extra = (None if v.damping_scale == 1.0 else
                               -(v.damping_scale - 1.0) * self.model.rigid.D)
        self._rebuild_friction()
        self._memo_key = None
        upcoming = [c.at for c in ordered[v.started:]]
        nxt = min(upcoming) if upcoming else math.inf
        self._next_change_t = min(nxt, t + RAMP_UPDATE_S) if v.ramping else nxt

    def _rebuild_friction(self) -> None:
        self._friction = None
        if self.hidden.friction_members():
            rigid = self.model.rigid
            forms = {m: rigid.kin.vector(m) for m in self.hidden.friction_members()}
            mob = {m: float(a @ self._m_inv @ a) for m, a in forms.items()}
            self._friction = FrictionForces(self.hidden, forms, mob, self._h)

    # ------------------------------------------------------------------ protocol
    def handle(self, msg: Message) -> list[Message]:
        """Apply a host message; returns the replies to send (HELLO_ACK, ACK or NACK).

        Device-to-host messages (SAMPLE, ACK, ...) are ignored (no reply).
        """
        if isinstance(msg, Hello):
            version = msg.protocol_version
            if version not in SUPPORTED_VERSIONS or version > self.protocol_version:
                return [Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION)]
            self.session_open = True
            self.session_version = version
            wd_us = round(self.limits.watchdog_timeout * 1e6)
            if version < 2:
                return [HelloAck(version, self._period_us, wd_us, FIRMWARE_ID)]
            return [HelloAck(version, self._period_us, wd_us, FIRMWARE_ID,
                             self.sensors.counts_per_rev, self.sensors.output_counts_per_rev)]
        if isinstance(msg, Command):
            reason = self.apply_command(msg) if self.session_open else NackReason.NOT_READY
            if reason is None:
                return [Ack(FrameType.COMMAND, msg.seq)]
            self.commands_refused += 1
            return [Nack(FrameType.COMMAND, msg.seq, reason)]
        if isinstance(msg, Config):
            if not self.session_open:
                return [Nack(FrameType.CONFIG, msg.seq, NackReason.NOT_READY)]
            if self.check_sample_period(msg.sample_period_us) is not None:
                return [Nack(FrameType.CONFIG, msg.seq, NackReason.INVALID_VALUE)]
            self.set_sample_period(msg.sample_period_us)
            return [Ack(FrameType.CONFIG, msg.seq)]
        return []

    def apply_command(self, cmd: Command) -> NackReason | None:
        """Apply a COMMAND (session not checked); ``None`` if accepted, else the NACK reason.

        Any accepted COMMAND clears ``WATCHDOG`` and (re-)arms the watchdog. Mode ``OFF``
        clears a latched fault once the sun speed is below the trip threshold. Refused: mode
        ``CURRENT``/``SPEED`` while a fault is latched (``FAULT_LATCHED``), ``SPEED`` beyond
        the speed limit or non-finite values (``INVALID_VALUE``). The motor current set-point
        is clamped when used (``CURRENT_LIMIT``), brake currents are clamped to
        ``[0, brake_current_limit]``. The command takes effect from the next sample.
        """
        sp = float(cmd.setpoint)
        brakes = np.asarray(cmd.brake_currents, dtype=float)
        if not (math.isfinite(sp) and np.all(np.isfinite(brakes))):
            return NackReason.INVALID_VALUE
        if cmd.mode != Mode.OFF and self._fault:
            return NackReason.FAULT_LATCHED
        if cmd.mode == Mode.SPEED and abs(sp) > self.limits.speed_limit:
            return NackReason.INVALID_VALUE
        if cmd.mode == Mode.OFF:
            if abs(self._w_enc) <= self.limits.trip_speed:  # the cause is gone
                self._fault = False
                self._overspeed = False
            sp = 0.0
        if cmd.mode == Mode.SPEED and self.mode != Mode.SPEED:
            self._integ = float(np.clip(self._i_motor, -self.limits.motor_current_limit,
                                        self.limits.motor_current_limit))
        self._mode = Mode(cmd.mode)
        self._setpoint = sp
        self._brake_cmd = np.clip(brakes, 0.0, self.limits.brake_current_limit)
        self._i_brake = self._brake_cmd.copy()
        self._watchdog = False
        self._armed = True
        self._last_cmd_us = self.t_us
        self.commands_accepted += 1
        return None

    def reset_controller(self) -> None:
        """Controller reset (firmware restart): sequence and clock restart at 0, outputs off
        (motor and brake coils de-energised at boot), faults, watchdog and session cleared, so
        streaming stops until the next HELLO. The transmission keeps turning."""
        self._clear_controller()
        self._i_brake = np.zeros(3)
        # the incremental sun encoder's counter restarts at 0 with the controller
        self._sun_zero = math.floor(self._hist_theta[0] * self.sensors.counts_per_rev
                                    / (2.0 * math.pi))

    def _clear_controller(self) -> None:
        """Controller state at power-up: clock, sequence, session, outputs, loops, flags."""
        self.seq = 0
        self.t_us = 0
        self.session_open = False
        self.session_version = 0
        self._mode = Mode.OFF
        self._setpoint = 0.0
        self._brake_cmd = np.zeros(3)
        self._integ = 0.0
        self._i_ref = 0.0
        self._last_cmd_us = 0
        self._armed = False
        self._watchdog = False
        self._fault = False
        self._overspeed = False
        self._clamped = False
        self._w_enc = 0.0

    # ------------------------------------------------------------------ physics
    def _output_speed(self) -> float:
        return self._w_load if self.hidden.backlash is not None else float(self.state.omega[1])

    def _output_angle(self) -> float:
        theta = float(self.state.theta[1])
        return theta - self._bl_twist if self.hidden.backlash is not None else theta

    def _angle_force(self, theta: Array, omega: Array, t: float) -> Array:
        """Position-dependent hidden generalised torque (2,) [N m]: the undeclared gravity arm,
        the mesh ripple (its mean over the physics step) and the friction bumps."""
        f = np.zeros(2)
        if self._gravity is not None:
            f = f + self._gravity.generalised_force(theta, omega)
        ripple = self.hidden.mesh_ripple
        if ripple is not None:
            f[0] += ripple.mean_torque(self._ripple_teeth, float(theta[0]), float(omega[0]),
                                       self._h)
        for a, bump, eps in self._bumps:
            v = float(a @ omega)
            f = f - a * (bump.level(float(a @ theta)) * math.tanh(v / eps))
        return f

    def _counts(self) -> int:
        return math.floor(self._theta_sun * self.sensors.counts_per_rev / (2.0 * math.pi))

    def _spline_torque(self, w_c3: float) -> float:
        bl = self.hidden.backlash
        if bl is None:
            return 0.0
        half = 0.5 * bl.gap
        d = self._bl_twist
        if d > half:
            return max(0.0, bl.stiffness * (d - half) + bl.damping * (w_c3 - self._w_load))
        if d < -half:
            return min(0.0, bl.stiffness * (d + half) + bl.damping * (w_c3 - self._w_load))
        return 0.0

    def _extra_force(self, omega: Array, t: float) -> Array:
        """Hidden generalised torque (2,) [N m]; memoised per speed within a sub-step (the
        hybrid model asks several times at the same speeds)."""
        key = (float(omega[0]), float(omega[1]))
        if key == self._memo_key:
            return self._memo_force
        f = self._friction.generalised(omega) if self._friction is not None else np.zeros(2)
        if self._damping_extra is not None:
            f = f + self._damping_extra @ omega
        if self.hidden.backlash is not None:
            f = f.copy()
            f[1] -= self._spline_torque(key[1])
        self._memo_key, self._memo_force = key, f
        return f

    def _control(self, clock_us: float) -> None:
        """One pass of the controller: watchdog, overspeed, speed loop -> current reference."""
        lim = self.limits
        counts = self._ctrl_counts
        w_enc = ((counts[-1] - counts[0]) * 2.0 * math.pi / self.sensors.counts_per_rev
                 / ((len(counts) - 1) * self._h))
        self._w_enc = w_enc
        if not self._fault and abs(w_enc) > lim.trip_speed:
            self._fault = True
            self._overspeed = True
            self._mode = Mode.OFF  # safe state: motor off, brakes keep their currents
            self.trips += 1
        if (self._armed and not self._watchdog and lim.watchdog_timeout > 0.0
                and clock_us - self._last_cmd_us > lim.watchdog_timeout * 1e6):
            self.watchdog_trips += 1
            self._watchdog = True
            self._mode = Mode.OFF  # safe state: motor off, brakes keep their currents
        mode = self.mode
        i_max = lim.motor_current_limit
        if mode == Mode.CURRENT:
            ref = self._setpoint
        elif mode == Mode.SPEED:
            e = self._setpoint - w_enc
            raw = self.drive.kp * e + self._integ
            ref = raw
            saturated = abs(raw) > i_max
            if not saturated or (raw > 0.0) != (e > 0.0):
                self._integ = min(i_max, max(-i_max, self._integ + self.drive.ki * e * self._h))
        else:
            ref = 0.0
            self._integ = 0.0
        if abs(ref) > i_max:
            ref = math.copysign(i_max, ref)
            self._clamped = True
        self._i_ref = ref

    def _physics(self) -> None:
        """Advance the transmission by one sub-step with the held currents."""
        h = self._h
        tau = self.drive.current_time_constant
        i0, ref = self._i_motor, self._i_ref
        if tau > 0.0:
            e = math.exp(-h / tau)
            i1 = ref + (i0 - ref) * e
            i_mean = ref + (i0 - ref) * (1.0 - e) * tau / h
        else:
            i1 = i_mean = ref
        w0 = self.state.omega
        bl = self.hidden.backlash
        t_spline = self._spline_torque(float(w0[1])) if bl is not None else 0.0
        self._memo_key = None  # the spline state changed since the last sub-step
        self.state = self.model.step(self.state, h, i_mean, self._i_brake)
        w1 = self.state.omega
        self._i_motor = i1
        self._theta_sun = float(self.state.theta[0])  # exact integral of the step's speed
        if bl is not None:  # symplectic Euler: speeds first, then the twist with new speeds
            self._w_load += h * (t_spline - bl.load_damping * self._w_load) / bl.load_inertia
            self._bl_twist += h * (float(w1[1]) - self._w_load)
        self._t_phys += h
        self._ctrl_counts.append(self._counts())
        self._hist_theta.append(self._theta_sun)
        self._hist_out.append(self._output_speed())
        self._hist_out_theta.append(self._output_angle())

    # ------------------------------------------------------------------ sampling
    def _measure(self, clamped: bool) -> SampleValues:
        s = self.sensors
        if not self._noise:
            self._noise = self._rng.standard_normal((_NOISE_BLOCK, 5)).tolist()
        noise = self._noise.pop()
        theta = self._hist_theta[0]
        cpr = s.counts_per_rev
        c_now = math.floor(theta * cpr / (2.0 * math.pi))
        c_then = math.floor(self._last_sample_theta * cpr / (2.0 * math.pi))
        self._last_sample_theta = theta
        sun = (c_now - c_then) * 2.0 * math.pi / cpr / (self._period_us * 1e-6)
        volts = self._hist_out[0] / (s.tach_rpm_per_volt * RPM) + s.tach_noise * noise[0]
        carrier = _quantise(volts, s.tach_lsb, s.adc_range) * s.tach_rpm_per_volt * RPM
        i_lsb = 2.0 * s.motor_current_range / 4096
        motor = _quantise(self._i_motor + s.motor_current_noise * noise[1], i_lsb,
                          s.motor_current_range)
        b_lsb = 2.0 * s.brake_current_range / 4096
        ib = self._i_brake.tolist()
        brakes = [_quantise(ib[k] + s.brake_current_noise * noise[2 + k], b_lsb,
                            s.brake_current_range) for k in range(3)]
        bits = 0
        if self.mode != Mode.OFF:
            bits |= _ENABLED
        if self._watchdog:
            bits |= _WATCHDOG
        if self._overspeed:
            bits |= _OVERSPEED
        if self._fault:
            bits |= _FAULT
        if clamped:
            bits |= _CURRENT_LIMIT
        for k in range(3):
            if ib[k] > _BRAKE_ON:
                bits |= _BRAKE_BITS[k]
        status = Status(bits)
        w = self.state.omega
        counts: tuple[int, int] | None = None
        if self.session_version >= 2:
            out_cpr = s.output_counts_per_rev
            counts = (wrap_count(c_now - self._sun_zero),
                      wrap_count(math.floor(self._hist_out_theta[0] * out_cpr / (2.0 * math.pi))))
        th = self.state.theta
        return SampleValues(seq=self.seq, t_us=self.t_us, sun_speed=sun, carrier3_speed=carrier,
                            motor_current=motor, brake_currents=(brakes[0], brakes[1], brakes[2]),
                            status=status, omega_true=(float(w[0]), float(w[1])),
                            output_true=self._output_speed(), gear=self.state.gear,
                            counts=counts, theta_true=(float(th[0]), float(th[1])),
                            output_angle_true=self._output_angle())

    def tick(self) -> SampleValues:
        """Produce the sample at the present instant, then advance one sample period.

        The clock ``t_us`` runs from controller start; the sequence number counts the samples
        streamed since controller start (samples stream while a session is open), so the first
        sample after a start or reset is number 0 whenever the host says HELLO, and a host
        always sees a controller reset as a backward step of ``seq``.

        Returns:
            The sample (sequence number and clock of the present instant).
        """
        if self._t_phys >= self._next_change_t - 1e-6:
            self._apply_schedule()
        self._control(self.t_us)
        values = self._measure(self._clamped)
        self._clamped = False
        self._physics()
        for j in range(1, self._n_sub):
            self._control(self.t_us + j * self._h * 1e6)
            self._physics()
        if self.session_open:  # samples are numbered as they are streamed
            self.seq = (self.seq + 1) & 0xFFFFFFFF
        self.t_us += self._period_us
        return values

    # ------------------------------------------------------------------ truth access
    @property
    def omega(self) -> Array:
        """True (omega_sun, omega_carrier3) [rad/s], shape (2,)."""
        return self.state.omega.copy()

    @property
    def theta(self) -> Array:
        """True (theta_sun, theta_carrier3) [rad] from the plant's start, shape (2,)."""
        return self.state.theta.copy()

    @property
    def output_speed(self) -> float:
        """True output-shaft speed [rad/s]."""
        return self._output_speed()

    @property
    def motor_current(self) -> float:
        """True motor current [A]."""
        return self._i_motor

    @property
    def physics_time(self) -> float:
        """Simulated time since start [s] (not reset by a controller reset)."""
        return self._t_phys
