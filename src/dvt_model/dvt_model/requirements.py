"""Baseline joint requirement (thesis eq. 1.1-1.3).

A uniform arm of length ``L`` and mass ``m_arm`` carries a point load ``m_load`` at its tip and
is held horizontal (worst-case gravity) while accelerating at ``alpha``:

    T_max = (m_arm L^2 / 3 + m_load L^2) alpha + (m_arm L / 2 + m_load L) g       (N m)
    P     = T_max * omega                                                         (W)

With the thesis's 71 in, 200 lb arm and 240 lb load at 1 rad/s^2 this gives about 3181 N m,
the source of the 3200 N m requirement.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    if not length > 0.0:
        raise ValueError(f"length: expected > 0 m, got {length!r}")
    if arm_mass < 0.0 or load_mass < 0.0:
        raise ValueError(f"masses: expected >= 0 kg, got arm {arm_mass!r}, load {load_mass!r}")
    inertia = arm_mass * length**2 / 3.0 + load_mass * length**2
    gravity = (arm_mass * length / 2.0 + load_mass * length) * g
    inertial = inertia * alpha
    torque = inertial + gravity
    return Requirement(inertia=inertia, gravity_torque=gravity, inertial_torque=inertial,
                       torque=torque, power=torque * omega)
