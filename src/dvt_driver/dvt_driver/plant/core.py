"""Simulated DVT motor/brake controller and transmission: the plant's core (pure, no I/O).

:class:`PlantSim` is what sits on the other end of the serial line in tests and the demo: the
controller firmware (protocol session, sun-speed PI loop, current loop, safety, sensors),
driving the transmission of :mod:`dvt_driver.plant.physics` (the ``dvt_model`` hybrid physics
plus the hidden effects of :mod:`dvt_driver.plant.hidden`). :mod:`dvt_driver.plant.server`
puts it on a pseudo-terminal in real time.

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

Physics. :class:`~dvt_driver.plant.physics.Transmission` (``PlantSim.physics``) is the
transmission the firmware drives: the hybrid physics, the power stage, the output shaft, the
hidden effects, the declared joint load and a changing plant's schedule
(:mod:`dvt_driver.plant.physics` describes them). ``PlantSim`` forwards its truth (``state``,
``model``, ``hidden``, ``load``, ``changes_applied``, :meth:`PlantSim.add_change`).

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

import math
from collections import deque
from dataclasses import asdict
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_driver.errors import PlantError
from dvt_driver.hardware import RPM
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
    Status,
    sample_wire_len,
    wrap_count,
)
from dvt_driver.plant.hidden import Change, HiddenEffects
from dvt_driver.plant.physics import Transmission
from dvt_driver.plant.settings import DriveConfig, SafetyLimits, SampleValues, SensorConfig
from dvt_model.hybrid import HybridModel, HybridState
from dvt_model.load import JointLoad
from dvt_model.params import TransmissionParams

__all__ = [
    "DEFAULT_SAMPLE_PERIOD_US",
    "FIRMWARE_ID",
    "MAX_SAMPLE_PERIOD_US",
    "MIN_SAMPLE_PERIOD_US",
    "DriveConfig",
    "PlantSim",
    "SafetyLimits",
    "SampleValues",
    "SensorConfig",
]

Array = NDArray[np.float64]

DEFAULT_SAMPLE_PERIOD_US = 1000
MIN_SAMPLE_PERIOD_US = 500
MAX_SAMPLE_PERIOD_US = 1_000_000
FIRMWARE_ID = "dvt-plant-sim 0.1"

_BRAKE_ON = 0.005  # A: a coil current above this counts as "band applied" (status BRAKEk)
_NOISE_BLOCK = 1024  # samples of sensor noise drawn at once
# status bits as plain ints (IntFlag arithmetic is slow in a 1 kHz loop)
_ENABLED = int(Status.ENABLED)
_WATCHDOG = int(Status.WATCHDOG)
_OVERSPEED = int(Status.OVERSPEED)
_FAULT = int(Status.FAULT)
_CURRENT_LIMIT = int(Status.CURRENT_LIMIT)
_BRAKE_BITS = (int(Status.BRAKE1), int(Status.BRAKE2), int(Status.BRAKE3))


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
        self.params = params
        self.seed = seed
        self.limits = limits if limits is not None else SafetyLimits()
        self.sensors = sensors if sensors is not None else SensorConfig()
        self.drive = drive if drive is not None else DriveConfig()
        self.baud = baud
        if self.limits.watchdog_timeout < 0.0:
            raise PlantError(f"watchdog_timeout: expected >= 0 s, got "
                             f"{self.limits.watchdog_timeout!r}")
        if self.drive.current_time_constant < 0.0:
            raise PlantError(f"current_time_constant: expected >= 0 s, got "
                             f"{self.drive.current_time_constant!r}")
        self.physics = Transmission(params, hidden, max_step=max_step, load=load)
        """The transmission this controller drives (:mod:`dvt_driver.plant.physics`)."""
        self._rng = np.random.default_rng(seed)
        self._noise: list[list[float]] = []
        self._sun_zero = 0  # sun-encoder count at the controller's start

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
        n = max(1, math.ceil(period / self.physics.step_limit - 1e-9))
        self._period_us = period_us
        self._n_sub = n
        self._h = period / n
        phys = self.physics
        phys.configure(self._h)
        window = max(1, round(self.drive.speed_window / self._h))
        counts = self._counts()
        self._ctrl_counts = deque([counts] * (window + 1), maxlen=window + 1)
        delay = max(0, round(phys.hidden.measurement_delay / self._h))
        self._hist_theta = deque([phys.theta_sun] * (delay + 1), maxlen=delay + 1)
        self._hist_out = deque([phys.output_speed()] * (delay + 1), maxlen=delay + 1)
        self._hist_out_theta = deque([phys.output_angle()] * (delay + 1), maxlen=delay + 1)
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
                # the band law the plant runs (the parameter set's, or a `bands` draw)
                "bands": {"gain": [float(g) for g in self.physics.brake.gains],
                          "time_constant": [float(t) for t in
                                            self.physics.brake.time_constants]},
                "load": (None if (load := self.physics.initial_load) is None
                         else {"name": load.name, **load.to_mapping()})}

    def truth_yaml(self) -> str:
        """Text of ``truth.yaml`` for this plant."""
        base = self.physics.base_hidden
        return base.to_truth_yaml(
            params_name=self.params.name, seed=self.seed, sample_period_us=self._period_us,
            extra=self.describe(),
            applied=self.physics.changes_applied if base.changes else None)

    # ------------------------------------------------------------------ the transmission
    def add_change(self, change: Change) -> None:
        """Add ``change`` to the plant's schedule (:meth:`Transmission.add_change
        <dvt_driver.plant.physics.Transmission.add_change>`: at or before
        :attr:`physics_time`, applied at the next sample)."""
        self.physics.add_change(change)

    @property
    def changes_applied(self) -> list[dict[str, Any]]:
        """Every change the plant started: ``{"at_s": plant time, "change": mapping}``."""
        return self.physics.changes_applied

    @property
    def hidden(self) -> HiddenEffects:
        """The hidden effects in force (the schedule's values so far)."""
        return self.physics.hidden

    @property
    def load(self) -> JointLoad | None:
        """The declared joint load in force."""
        return self.physics.load

    @property
    def model(self) -> HybridModel:
        """The transmission's hybrid model."""
        return self.physics.model

    @property
    def state(self) -> HybridState:
        """The transmission's true state (settable: a test may start it moving)."""
        return self.physics.state

    @state.setter
    def state(self, value: HybridState) -> None:
        self.physics.state = value

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
            self._integ = float(np.clip(self.physics.i_motor, -self.limits.motor_current_limit,
                                        self.limits.motor_current_limit))
        self._mode = Mode(cmd.mode)
        self._setpoint = sp
        self._brake_cmd = np.clip(brakes, 0.0, self.limits.brake_current_limit)
        self.physics.i_brake = self._brake_cmd.copy()
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
        self.physics.i_brake = np.zeros(3)
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

    # ------------------------------------------------------------------ sensors
    def _counts(self) -> int:
        return math.floor(self.physics.theta_sun * self.sensors.counts_per_rev
                          / (2.0 * math.pi))

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
        """Advance the transmission by one sub-step with the held currents; the sensors
        record what they see (the delay lines of the speed and angle measurements)."""
        phys = self.physics
        phys.advance(self._i_ref, self.drive.current_time_constant)
        self._ctrl_counts.append(self._counts())
        self._hist_theta.append(phys.theta_sun)
        self._hist_out.append(phys.output_speed())
        self._hist_out_theta.append(phys.output_angle())

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
        motor = _quantise(self.physics.i_motor + s.motor_current_noise * noise[1], i_lsb,
                          s.motor_current_range)
        b_lsb = 2.0 * s.brake_current_range / 4096
        ib = self.physics.i_brake.tolist()
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
                            output_true=self.physics.output_speed(), gear=self.state.gear,
                            counts=counts, theta_true=(float(th[0]), float(th[1])),
                            output_angle_true=self.physics.output_angle())

    def tick(self) -> SampleValues:
        """Produce the sample at the present instant, then advance one sample period.

        The clock ``t_us`` runs from controller start; the sequence number counts the samples
        streamed since controller start (samples stream while a session is open), so the first
        sample after a start or reset is number 0 whenever the host says HELLO, and a host
        always sees a controller reset as a backward step of ``seq``.

        Returns:
            The sample (sequence number and clock of the present instant).
        """
        if self.physics.due():
            self.physics.apply_schedule()
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
        return self.physics.output_speed()

    @property
    def motor_current(self) -> float:
        """True motor current [A]."""
        return self.physics.i_motor

    @property
    def physics_time(self) -> float:
        """Simulated time since start [s] (not reset by a controller reset)."""
        return self.physics.t_phys
