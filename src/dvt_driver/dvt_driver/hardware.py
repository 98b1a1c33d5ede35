"""The bench's hardware figures, each defined once (pure constants; thesis values).

The driver's safety limits (:mod:`dvt_driver.link.safety`), the experiments' limits
(:mod:`dvt_driver.run.experiment_core`) and the simulated controller's own clamps
(:mod:`dvt_driver.plant.core`) all take them from here.
"""

from __future__ import annotations

import math

__all__ = [
    "HARDWARE_MAX_BRAKE_CURRENT",
    "HARDWARE_MAX_MOTOR_CURRENT",
    "HARDWARE_MAX_SUN_SPEED",
    "MOTOR_CONSTANT",
    "MOTOR_PEAK_TORQUE",
    "RPM",
]

RPM = 2.0 * math.pi / 60.0
"""One rpm in rad/s."""
MOTOR_CONSTANT = 0.3732
"""Drive-motor torque constant K_M [N m/A]."""
MOTOR_PEAK_TORQUE = 12.0
"""Drive-motor peak torque [N m]."""
HARDWARE_MAX_MOTOR_CURRENT = MOTOR_PEAK_TORQUE / MOTOR_CONSTANT
"""Largest drive-motor current [A] (peak torque / K_M = 32.15 A): the controller's clamp and
the most the driver ever allows."""
HARDWARE_MAX_SUN_SPEED = 2400.0 * RPM
"""The thesis's safe maximum sun-shaft speed, 2400 rpm [rad/s] (251.33 rad/s)."""
HARDWARE_MAX_BRAKE_CURRENT = 6.0
"""Largest band-brake coil current [A] (either sign); the controller's own clamp (6 A = 48 N m
static band torque, enough to hold the peak motor torque in every gear)."""
