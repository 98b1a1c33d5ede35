"""Baseline joint requirement (thesis eq. 1.1-1.3).

A uniform arm of length ``L`` and mass ``m_arm`` carries a point load ``m_load`` at its tip and
turns about the joint at angle ``theta`` from the horizontal while accelerating at ``alpha``:

    T     = (m_arm L^2 / 3 + m_load L^2) alpha + (m_arm L / 2 + m_load L) g cos(theta)   (N m)
    T_max = T(theta = 0)                                 (horizontal: worst-case gravity)
    P     = T_max * omega                                                         (W)

With the thesis's 71 in, 200 lb arm and 240 lb load at 1 rad/s^2 this gives about 3181 N m,
the source of the 3200 N m requirement. The equation lives in :class:`dvt_model.load.Arm` (the
same arm the plant and the model node carry as a joint load); :func:`arm_torque` is its
functional form for ``dvt-model requirement`` and ``dvt-model design``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dvt_model.load import INCH, POUND, Arm
from dvt_model.load import G as G

__all__ = [
    "INCH",
    "POUND",
    "G",
    "Requirement",
    "arm_inertia",
    "arm_torque",
    "baseline_requirement",
]


@dataclass(frozen=True)
class Requirement:
    """Joint requirement: inertia [kg m^2], gravity torque [N m], T_max [N m], power [W]."""

    inertia: float
    gravity_torque: float
    inertial_torque: float
    torque: float
    power: float


def arm_inertia(length: float, arm_mass: float, load_mass: float) -> float:
    """Inertia of the uniform arm plus tip load about the joint [kg m^2] (eq. 1.1, first term).

    Raises:
        ModelError (a ValueError): a non-positive length or negative mass.
    """
    return Arm(length=length, mass=arm_mass, payload=load_mass).inertia


def arm_torque(length: float, arm_mass: float, load_mass: float, alpha: float | NDArray[np.float64],
               g: float = G, theta: float = 0.0) -> float | NDArray[np.float64]:
    """Joint torque of thesis eq. 1.1 [N m]; eq. 1.2 (``T_max``) at ``theta = 0``.

    Args:
        length: arm length [m]. arm_mass, load_mass: [kg]. alpha: joint acceleration
            [rad/s^2] (scalar or array). g: [m/s^2]. theta: arm angle from horizontal [rad].

    Raises:
        ModelError (a ValueError): a non-positive length or negative mass.
    """
    return Arm(length=length, mass=arm_mass, payload=load_mass, g=g).torque(alpha, theta)


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
