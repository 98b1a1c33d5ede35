"""Driver settings (dvt_driver.link.settings): defaults, every refusal names the parameter."""

from __future__ import annotations

from typing import Any

import pytest

from dvt_driver.errors import SafetyConfigError
from dvt_driver.link.settings import DEFAULT_SETTINGS, parse_settings


def test_parse_settings_defaults_and_errors() -> None:
    s = parse_settings({"port": "/dev/ttyUSB0"})
    assert s.baud == 921600 and s.sample_period_us == 1000
    assert s.watchdog_timeout == 0.5 and s.shift.engage_current == 0.5
    assert parse_settings({"port": "/dev/x", "sample_rate_hz": 2000}).sample_period_us == 500
    cases: list[tuple[dict[str, Any], str]] = [
        ({}, "port"),
        ({"port": "  "}, "port"),
        ({"port": "/dev/x", "baud": 12345}, "baud"),
        ({"port": "/dev/x", "baud": "fast"}, "baud"),
        ({"port": "/dev/x", "sample_rate_hz": 0}, "sample_rate_hz"),
        ({"port": "/dev/x", "sample_rate_hz": 2500}, "sample_rate_hz"),
        ({"port": "/dev/x", "baud": 115200}, "more than 115200 baud carries"),
        ({"port": "/dev/x", "max_motor_current": 50.0}, "max_motor_current"),
        ({"port": "/dev/x", "max_brake_current": -1.0}, "max_brake_current"),
        ({"port": "/dev/x", "watchdog_timeout": 0.0}, "watchdog_timeout"),
        ({"port": "/dev/x", "watchdog_timeout": 0.01}, "two keep-alive periods"),
        ({"port": "/dev/x", "max_brake_current": 0.3}, "gear_engage_current"),
        ({"port": "/dev/x", "release_brakes_on_deactivate": "yes"}, "release_brakes"),
        ({"port": "/dev/x", "bogus": 1}, "unknown setting"),
    ]
    for values, match in cases:
        with pytest.raises(SafetyConfigError, match=match):
            parse_settings(values)


def test_reconnect_interval_default_and_range() -> None:
    assert DEFAULT_SETTINGS["reconnect_interval"] == 0.01
    assert parse_settings({"port": "/dev/x"}).reconnect_interval == 0.01
    assert parse_settings({"port": "/dev/x", "reconnect_interval": 0.005}).reconnect_interval \
        == 0.005
    for bad in (0.0, 0.001, 11.0, "soon"):
        with pytest.raises(SafetyConfigError, match="reconnect_interval"):
            parse_settings({"port": "/dev/x", "reconnect_interval": bad})
