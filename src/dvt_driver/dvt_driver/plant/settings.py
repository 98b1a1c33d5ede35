"""The simulated controller's settings and its samples (pure data): safety limits, the bench
sensors, the drive (:class:`~dvt_driver.plant.core.PlantSim` takes them; ``dvt-plant`` sets the
limits from its options)."""

from __future__ import annotations

from dataclasses import dataclass

from dvt_driver.hardware import (
    HARDWARE_MAX_BRAKE_CURRENT,
    HARDWARE_MAX_MOTOR_CURRENT,
    HARDWARE_MAX_SUN_SPEED,
)
from dvt_driver.link.protocol import Sample, Status

__all__ = ["DriveConfig", "SafetyLimits", "SampleValues", "SensorConfig"]


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

    speed_limit: float = HARDWARE_MAX_SUN_SPEED
    overspeed_margin: float = 0.05
    motor_current_limit: float = HARDWARE_MAX_MOTOR_CURRENT
    brake_current_limit: float = HARDWARE_MAX_BRAKE_CURRENT
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
