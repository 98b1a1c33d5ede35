"""What the arm asks of the drive (thesis ch. 1, eq. 1.1-1.3) and how it is split per gear.

The joint torque and power come from :func:`dvt_model.requirements.arm_torque` (the one place
the arm equation lives). Per gear, the speed/load pairing of the thesis's figure 9 idea: gear 1
(lowest ratio) moves the unloaded arm at the no-load speed, gear 2 half the payload at the
half-load speed, gear 3 the full payload at the full-load speed, each horizontal and
accelerating at ``alpha_max``. A further reduction ``R`` after the DVT is sized so that the
motor's peak torque covers every gear:

    R = max_g T_g / (eta T_peak r_g)         motor torque  T_m,g = T_g / (eta r_g R)
    motor speed n_g = omega_g r_g R           motor power   P_g = T_g omega_g / eta

``eta`` is the thesis's lumped motor-to-joint efficiency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from dvt_model.design.checks import Check
from dvt_model.design.spec import ArmSpec, MotorSpec
from dvt_model.requirements import arm_inertia, arm_torque

RPM = 60.0 / (2.0 * math.pi)  # rpm per rad/s


@dataclass(frozen=True)
class GearDuty:
    """One gear's share: payload [kg], joint torque [N m] and speed [rad/s], the DVT's output
    torque [N m] and speed [rpm], the motor's torque [N m], speed [rpm] and power [W]."""

    gear: int
    payload_kg: float
    joint_torque: float
    joint_speed: float
    dvt_ratio: float
    dvt_output_torque: float
    dvt_output_speed_rpm: float
    motor_torque: float
    motor_speed_rpm: float
    motor_power: float


@dataclass(frozen=True)
class RequirementResult:
    """Requirement figures, the two curves, the per-gear duties and the checks."""

    inertia: float
    gravity_torque: float
    torque_max: float
    alpha: list[float]
    torque_curve: list[float]
    speed: list[float]
    power_output_curve: list[float]
    power_input_curve: list[float]
    power_full_load_speed: float
    power_holding_full_load_speed: float
    reduction: float
    duties: tuple[GearDuty, GearDuty, GearDuty]
    checks: tuple[Check, ...]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__
               if k not in ("duties", "checks")}
        out["duties"] = [d.__dict__ for d in self.duties]
        return out


def requirement(arm: ArmSpec, motor: MotorSpec, ratios: dict[int, Fraction],
                points: int = 21) -> RequirementResult:
    """Eq. 1.1-1.3 for the design's arm, the curves of figures 3-4 and the per-gear duties."""
    L, ma, mp, g = arm.length_m, arm.arm_mass_kg, arm.payload_kg, arm.gravity_m_s2
    inertia = arm_inertia(L, ma, mp)
    gravity = float(arm_torque(L, ma, mp, 0.0, g))
    t_max = float(arm_torque(L, ma, mp, arm.alpha_max_rad_s2, g))
    alpha = np.linspace(0.0, arm.alpha_max_rad_s2, points)
    torque = np.asarray(arm_torque(L, ma, mp, alpha, g), dtype=float)
    speed = np.linspace(arm.speed_range_rad_s[0], arm.speed_range_rad_s[1], points)
    p_out = t_max * speed
    eta = arm.efficiency
    loads = {1: (0.0, arm.speed_no_load), 2: (0.5 * mp, arm.speed_half_load),
             3: (mp, arm.speed_full_load)}
    t_gear = {k: float(arm_torque(L, ma, m, arm.alpha_max_rad_s2, g)) for k, (m, _) in
              loads.items()}
    r = {k: float(v) for k, v in ratios.items()}
    reduction = max(t_gear[k] / (eta * motor.peak_torque_Nm * r[k]) for k in (1, 2, 3))
    duties = []
    for k in (1, 2, 3):
        m, w = loads[k]
        tm = t_gear[k] / (eta * r[k] * reduction)
        duties.append(GearDuty(
            gear=k, payload_kg=m, joint_torque=t_gear[k], joint_speed=w, dvt_ratio=r[k],
            dvt_output_torque=tm * r[k], dvt_output_speed_rpm=w * reduction * RPM,
            motor_torque=tm, motor_speed_rpm=w * r[k] * reduction * RPM,
            motor_power=t_gear[k] * w / eta))
    p_full = t_max * arm.speed_full_load / eta
    p_hold = gravity * arm.speed_full_load / eta
    p_need = max(max(d.motor_power for d in duties), p_full)
    n_need = max(d.motor_speed_rpm for d in duties)
    checks = (
        Check("requirement.torque", "the stated torque requirement covers eq. 1.2",
              "T_max = (m_arm L^2/3 + m_p L^2) alpha + (m_arm L/2 + m_p L) g <= stated",
              t_max <= arm.torque_min_Nm,
              f"T_max = {t_max:.1f} N·m at {arm.alpha_max_rad_s2:g} rad/s² vs stated "
              f"{arm.torque_min_Nm:g} N·m", {"T_max_Nm": t_max}),
        Check("requirement.motor_power", "the stated motor power covers eq. 1.3 at the "
              "full-load speed", "P = T_max omega_full / eta <= stated",
              p_need <= 1000.0 * arm.motor_power_min_kW,
              f"P = {t_max:.1f}·{arm.speed_full_load:g}/{eta:g} = {p_full / 1000:.3f} kW "
              f"(holding only, alpha = 0: {p_hold / 1000:.3f} kW; largest per-gear duty "
              f"{max(d.motor_power for d in duties) / 1000:.3f} kW) vs stated "
              f"{arm.motor_power_min_kW:g} kW", {"P_full_W": p_full, "P_hold_W": p_hold}),
        Check("requirement.motor_speed", "the motor reaches the speed every gear needs",
              "omega_g r_g R <= motor speed", n_need <= motor.speed_rpm,
              f"largest need {n_need:.0f} rpm (R = {reduction:.2f}) vs {motor.speed_rpm:g} rpm",
              {"motor_speed_needed_rpm": n_need}),
    )
    return RequirementResult(
        inertia=inertia, gravity_torque=gravity, torque_max=t_max, alpha=alpha.tolist(),
        torque_curve=torque.tolist(), speed=speed.tolist(), power_output_curve=p_out.tolist(),
        power_input_curve=(p_out / eta).tolist(), power_full_load_speed=p_full,
        power_holding_full_load_speed=p_hold, reduction=reduction,
        duties=(duties[0], duties[1], duties[2]), checks=checks)
