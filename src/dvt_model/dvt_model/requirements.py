"""Baseline joint requirement (thesis eq. 1.1-1.3).

A uniform arm of length ``L`` and mass ``m_arm`` carries a point load ``m_load`` at its tip and
turns about the joint at angle ``theta`` from the horizontal while accelerating at ``alpha``:

    T     = (m_arm L^2 / 3 + m_load L^2) alpha + (m_arm L / 2 + m_load L) g cos(theta)   (N m)
    T_max = T(theta = 0)                                 (horizontal: worst-case gravity)
    P     = T_max * omega                                                         (W)

With the thesis's 71 in, 200 lb arm and 240 lb load at 1 rad/s^2 this gives about 3181 N m,
the source of the 3200 N m requirement. :func:`arm_torque` is the one place the equation
lives; ``dvt-model requirement`` and ``dvt-model design`` both call it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

INCH = 0.0254  # m
POUND = 0.45359237  # kg
G = 9.81  # m/s^2, as the thesis rounds it


@dataclass(frozen=True)
class Requirement:
    """Joint requirement: inertia [kg m^2], gravity torque [N m], T_max [N m], power [W]."""

    inertia: float
    gravity_torque: float
    inertial_torque: float
    torque: float
    power: float


def _check_arm(length: float, arm_mass: float, load_mass: float) -> None:
    if not length > 0.0:
        raise ValueError(f"length: expected > 0 m, got {length!r}")
    if arm_mass < 0.0 or load_mass < 0.0:
        raise ValueError(f"masses: expected >= 0 kg, got arm {arm_mass!r}, load {load_mass!r}")


def arm_inertia(length: float, arm_mass: float, load_mass: float) -> float:
    """Inertia of the uniform arm plus tip load about the joint [kg m^2] (eq. 1.1, first term)."""
    _check_arm(length, arm_mass, load_mass)
    return arm_mass * length**2 / 3.0 + load_mass * length**2


def arm_torque(length: float, arm_mass: float, load_mass: float, alpha: float | NDArray[np.float64],
               g: float = G, theta: float = 0.0) -> float | NDArray[np.float64]:
    """Joint torque of thesis eq. 1.1 [N m]; eq. 1.2 (``T_max``) at ``theta = 0``.

    Args:
        length: arm length [m]. arm_mass, load_mass: [kg]. alpha: joint acceleration
            [rad/s^2] (scalar or array). g: [m/s^2]. theta: arm angle from horizontal [rad].

    Raises:
        ValueError: a non-positive length or negative mass.
    """
    inertia = arm_inertia(length, arm_mass, load_mass)
    gravity = (arm_mass * length / 2.0 + load_mass * length) * g * math.cos(theta)
    return inertia * alpha + gravity


def baseline_requirement(length: float = 71 * INCH, arm_mass: float = 200 * POUND,
                         load_mass: float = 240 * POUND, alpha: float = 1.0,
                         omega: float = 1.0, g: float = G) -> Requirement:
    """T_max and power for the arm (SI inputs; defaults are the thesis's arm).

    Args:
        length: arm length [m]. arm_mass, load_mass: [kg]. alpha: [rad/s^2].
        omega: joint speed at which power is quoted [rad/s]. g: [m/s^2].

    Raises:
        ValueError: a non-positive length or negative mass.
    """
    inertia = arm_inertia(length, arm_mass, load_mass)
    gravity = float(arm_torque(length, arm_mass, load_mass, 0.0, g))
    torque = float(arm_torque(length, arm_mass, load_mass, alpha, g))
    return Requirement(inertia=inertia, gravity_torque=gravity, inertial_torque=inertia * alpha,
                       torque=torque, power=torque * omega)
