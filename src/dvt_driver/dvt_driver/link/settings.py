"""The driver's settings: every parameter of ``dvt_driver_node``, validated (pure; no ROS).

:func:`parse_settings` turns the node's parameter values into a frozen :class:`DriverSettings`
or raises :class:`~dvt_driver.errors.SafetyConfigError` naming the parameter, the value and what
is expected. Nothing touches the wire before the settings are valid. Defaults and ranges are
listed in ``docs/driver.md`` (section Parameters) and in :data:`DEFAULT_SETTINGS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dvt_driver.errors import SafetyConfigError
from dvt_driver.link.safety import (
    DEFAULT_MAX_BRAKE_CURRENT,
    HARDWARE_MAX_MOTOR_CURRENT,
    HARDWARE_MAX_SUN_SPEED,
    Limits,
    ShiftSettings,
    check_setting,
)

__all__ = ["BAUD_RATES", "DEFAULT_SETTINGS", "DriverSettings", "parse_settings"]


BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
              1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000, 4000000)
"""Line rates [bit/s] the driver accepts (the standard termios / USB-UART rates)."""

_SAMPLE_FRAME_BYTES = 43  # protocol.SAMPLE_WIRE_LEN
_ACK_FRAME_BYTES = 8  # an ACK per keep-alive COMMAND


@dataclass(frozen=True, slots=True)
class DriverSettings:
    """Everything the driver node reads from its parameters, validated.

    Attributes:
        port: serial device path (``/dev/ttyUSB0``, a pty or a symlink to one).
        baud: line rate [bit/s], one of :data:`BAUD_RATES`.
        sample_rate_hz: controller sample rate requested with CONFIG [Hz], 1..2000, and the
            samples plus one ACK per keep-alive must fit the line (10 bits per byte).
        limits: command limits.
        watchdog_timeout: host command watchdog [s], (0, 60].
        keepalive_rate_hz: COMMAND re-send rate while active [Hz], 5..500.
        shift: gear-shift settings.
        clock_window: stamp-offset window [s] (:class:`dvt_driver.link.clock.ClockMapper`), 0.1..60.
        reconnect_interval: shortest pause between reopen attempts of a vanished port [s],
            0.005..10 (:mod:`dvt_driver.link.session` backs off to at most
            ``max(reconnect_interval, 0.04 s)``).
        release_brakes_on_deactivate: deactivate also releases the brakes (default holds them).
    """

    port: str
    baud: int
    sample_rate_hz: float
    limits: Limits
    watchdog_timeout: float
    keepalive_rate_hz: float
    shift: ShiftSettings
    clock_window: float
    reconnect_interval: float
    release_brakes_on_deactivate: bool

    @property
    def sample_period_us(self) -> int:
        """Sample period for CONFIG [µs]."""
        return round(1e6 / self.sample_rate_hz)


DEFAULT_SETTINGS: dict[str, Any] = {
    "port": "",
    "baud": 921600,
    "sample_rate_hz": 1000.0,
    "max_motor_current": HARDWARE_MAX_MOTOR_CURRENT,
    "max_brake_current": DEFAULT_MAX_BRAKE_CURRENT,
    "max_sun_speed": HARDWARE_MAX_SUN_SPEED,
    "watchdog_timeout": 0.5,
    "keepalive_rate_hz": 50.0,
    "gear_engage_current": 0.5,
    "gear_ramp_time": 0.05,
    "gear_overlap": 0.0,
    "clock_window": 2.0,
    "reconnect_interval": 0.01,
    "release_brakes_on_deactivate": False,
}
"""Parameter names of :func:`parse_settings` and their defaults."""


def parse_settings(values: dict[str, Any]) -> DriverSettings:
    """Validate driver parameter values (missing keys take :data:`DEFAULT_SETTINGS`).

    Raises:
        SafetyConfigError: the first invalid value, naming the parameter, the value and what
            is expected; unknown keys are refused too.
    """
    unknown = sorted(set(values) - set(DEFAULT_SETTINGS))
    if unknown:
        raise SafetyConfigError(f"unknown setting(s) {unknown}")
    v = {**DEFAULT_SETTINGS, **values}
    port = v["port"]
    if not isinstance(port, str) or not port.strip():
        raise SafetyConfigError(f"port: expected a serial device path (e.g. /dev/ttyUSB0), "
                                f"got {port!r}")
    baud = v["baud"]
    if isinstance(baud, float) and baud.is_integer():
        baud = int(baud)
    if isinstance(baud, bool) or not isinstance(baud, int) or baud not in BAUD_RATES:
        raise SafetyConfigError(f"baud: expected one of {list(BAUD_RATES)}, got {baud!r}")
    rate = check_setting("sample_rate_hz", v["sample_rate_hz"], 1.0, 2000.0, low_open=False,
                    unit=" Hz")
    keepalive = check_setting("keepalive_rate_hz", v["keepalive_rate_hz"], 5.0, 500.0,
                         low_open=False, unit=" Hz")
    line = baud / 10.0
    need = rate * _SAMPLE_FRAME_BYTES + keepalive * _ACK_FRAME_BYTES
    if need > line:
        raise SafetyConfigError(
            f"sample_rate_hz: {rate:g} Hz needs {need:.0f} bytes/s with the keep-alive ACKs, "
            f"more than {baud} baud carries ({line:.0f} bytes/s); lower the rate or raise "
            f"the baud rate")
    limits = Limits(v["max_motor_current"], v["max_brake_current"], v["max_sun_speed"])
    watchdog = check_setting("watchdog_timeout", v["watchdog_timeout"], 0.0, 60.0, unit=" s")
    if watchdog < 2.0 / keepalive:
        raise SafetyConfigError(
            f"watchdog_timeout: {watchdog:g} s is shorter than two keep-alive periods "
            f"({2.0 / keepalive:g} s at keepalive_rate_hz {keepalive:g})")
    shift = ShiftSettings(v["gear_engage_current"], v["gear_ramp_time"], v["gear_overlap"])
    if shift.engage_current > limits.max_brake_current:
        raise SafetyConfigError(f"gear_engage_current: {shift.engage_current:g} A exceeds "
                                f"max_brake_current {limits.max_brake_current:g} A")
    window = check_setting("clock_window", v["clock_window"], 0.1, 60.0, low_open=False, unit=" s")
    reconnect = check_setting("reconnect_interval", v["reconnect_interval"], 0.005, 10.0,
                         low_open=False, unit=" s")
    release = v["release_brakes_on_deactivate"]
    if not isinstance(release, bool):
        raise SafetyConfigError(f"release_brakes_on_deactivate: expected true or false, "
                                f"got {release!r}")
    return DriverSettings(port.strip(), baud, rate, limits, watchdog, keepalive, shift, window,
                          reconnect, release)
