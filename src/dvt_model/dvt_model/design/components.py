"""Shafts, bearings and splines (thesis eq. 3.17-3.20), sized for the motor's peak torque.

Shafts. Torsion of a (hollow) round shaft: ``tau = 16 T D / (pi (D^4 - d^4))``. The thesis sizes
the solid sun shaft with eq. 3.17, ``D = (16 T N / (pi S_yp))^(1/3)`` (tensile yield used as the
allowable *shear* stress) and the hollow carrier shafts with eq. 3.18,
``D = (32 T N / (pi (1 - R_D^4) S_yp))^(1/3)`` (maximum-shear-stress criterion,
``tau_allow = S_yp / 2``). Both are reported as printed; the minimum size checked is the
distortion-energy (von Mises) one, ``tau_allow = S_yp / sqrt(3) = 0.577 S_yp``, for the chosen
bore. The torque is the largest the member sees in any gear at the motor's peak torque.

Bearings. ``L10 = (C/P)^p 10^6`` revolutions, ``p = 3`` for ball and ``10/3`` for roller (needle)
bearings; hours ``L10 / (60 n)`` (eq. 3.19 uses ``p = 3`` for all). A planet's needle bearing
carries the two tooth normal forces ``F_n = T_sun / (N r_b,sun)`` acting along the two lines of
action: ``|F_pin| = 2 F_n cos((a'_sp + a'_pr) / 2)``.

Splines (ANSI B92.1, 30 deg, side fit). Pitch diameter ``D_p = N / P``, external minor diameter
``D_re = (N - 1.35)/P`` (flat root) or ``(N - 1.8)/P`` (fillet root). Eq. 3.20: the length
whose tooth shear strength (a quarter of the teeth carrying, shear on the pitch cylinder)
equals the torsional strength of the shaft at ``D_re``: ``L = D_re^3 (1 - (d/D_re)^4) / D_p^2``.
For the actual torque: ``tau = 16 T / (pi D_p^2 L)`` gives
``L_req = 16 T N / (pi D_p^2 tau_allow)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from dvt_model.design.checks import Check
from dvt_model.design.gears import GearTrain
from dvt_model.design.spec import BearingSpec, Design, ShaftSpec, SplineSpec

VON_MISES_SHEAR = 1.0 / math.sqrt(3.0)  # tau_y / S_y, distortion energy
INCH_MM = 25.4


def eq_3_17(torque: float, safety: float, s_y: float) -> float:
    """Thesis eq. 3.17 as printed: ``(16 T N / (pi S_yp))^(1/3)`` [m] (T [N m], S_yp [Pa])."""
    return float((16.0 * torque * safety / (math.pi * s_y)) ** (1.0 / 3.0))


def eq_3_18(torque: float, safety: float, s_y: float, ratio: float) -> float:
    """Thesis eq. 3.18 as printed: ``(32 T N / (pi (1 - R_D^4) S_yp))^(1/3)`` [m]."""
    return float((32.0 * torque * safety / (math.pi * (1.0 - ratio**4) * s_y)) ** (1.0 / 3.0))


def min_diameter(torque: float, safety: float, tau_allow: float, bore: float = 0.0) -> float:
    """Smallest outer diameter [m] with ``16 T D / (pi (D^4 - d^4)) <= tau_allow / N``
    for a fixed bore ``d`` [m] (bisection; closed form when solid)."""
    k = 16.0 * torque * safety / (math.pi * tau_allow)
    if bore <= 0.0:
        return float(k ** (1.0 / 3.0))
    lo, hi = bore, bore + k ** (1.0 / 3.0) + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if (mid**4 - bore**4) / mid >= k:
            hi = mid
        else:
            lo = mid
    return hi


def l10_hours(C: float, P: float, rpm: float, exponent: float) -> float:
    """Basic rating life [h]: ``(C/P)^p 10^6 / (60 n)``; ``inf`` if unloaded or at rest."""
    if P <= 0.0 or rpm <= 0.0:
        return math.inf
    return float((C / P) ** exponent * 1e6 / (60.0 * rpm))


def member_torque(train: GearTrain, member: str, peak: float) -> tuple[float, int]:
    """Largest torque [N m] ``member`` carries at input torque ``peak`` and the gear it is in."""
    if member == "sun":
        return peak, 1
    k = int(member[-1]) - 1
    best = max((train.carrier_torque[g][k], g) for g in (1, 2, 3))
    return best[0] * peak, best[1]


def planet_pin_load(train: GearTrain, stage: int, gear: int, peak: float) -> float:
    """Radial load on one planet's bearing [N] at input torque ``peak`` [N m] in ``gear``."""
    st = train.stages[stage - 1]
    f_n = train.sun_torque[gear][stage - 1] * peak / (st.spec.planets * st.sun.d_b / 2000.0)
    half = math.radians(st.sun_planet.alpha_op_deg + st.planet_ring.alpha_op_deg) / 2.0
    return 2.0 * f_n * math.cos(half)


def member_speed_rpm(train: GearTrain, expr: str, motor_rpm: float, gear: int) -> float:
    """|speed| [rpm] of a member (or ``a-b``, relative) with the motor at ``motor_rpm``
    (exact rational speed forms: a member at rest gives exactly 0)."""
    inv_ratio = 1 / train.gear_ratios[gear]
    parts = expr.split("-")
    a, b = train.kin.forms[parts[0]]
    if len(parts) == 2:
        a2, b2 = train.kin.forms[parts[1]]
        a, b = a - a2, b - b2
    return float(abs(a + b * inv_ratio)) * motor_rpm


@dataclass(frozen=True)
class ShaftResult:
    """A shaft: torque [N m], printed-equation and von Mises minimum diameters [mm], the
    chosen diameter [mm] and the safety factor it achieves [-]."""

    spec: ShaftSpec
    torque: float
    gear: int
    d_printed_eq: float
    d_min_von_mises: float
    d_min_tresca: float
    safety_achieved: float
    hob_limit: float | None


def shafts(design: Design, train: GearTrain) -> tuple[list[ShaftResult], list[Check]]:
    """Every shaft of the design file, with its checks."""
    out: list[ShaftResult] = []
    checks: list[Check] = []
    for sh in design.shafts:
        torque, gear = member_torque(train, sh.member, design.motor.peak_torque_Nm)
        s_y = design.materials[sh.material].yield_MPa * 1e6
        D, d = sh.outer_diameter_mm / 1000.0, sh.bore_mm / 1000.0
        printed = (eq_3_17(torque, sh.safety_factor, s_y) if sh.equation == "3.17"
                   else eq_3_18(torque, sh.safety_factor, s_y, d / D))
        vm = min_diameter(torque, sh.safety_factor, VON_MISES_SHEAR * s_y, d)
        tr = min_diameter(torque, sh.safety_factor, 0.5 * s_y, d)
        tau = 16.0 * torque * D / (math.pi * (D**4 - d**4))
        n = VON_MISES_SHEAR * s_y / tau
        hob = None
        if sh.member == "sun":
            hob = min(s.sun.d_f - (s.sun.d_a - s.sun.d_f) / 4.0 for s in train.stages)
        res = ShaftResult(spec=sh, torque=torque, gear=gear, d_printed_eq=printed * 1000.0,
                          d_min_von_mises=vm * 1000.0, d_min_tresca=tr * 1000.0,
                          safety_achieved=n, hob_limit=hob)
        out.append(res)
        checks.append(Check(
            f"shaft.{sh.name}.strength", f"{sh.name}: chosen diameter carries the peak torque",
            f"D >= D_min (von Mises, tau_allow = 0.577 S_y / {sh.safety_factor:g})",
            sh.outer_diameter_mm >= res.d_min_von_mises,
            f"T = {torque:.2f} N·m (gear {gear}), S_y = {s_y / 1e6:g} MPa: D_min = "
            f"{res.d_min_von_mises:.2f} mm (eq. {sh.equation} as printed "
            f"{res.d_printed_eq:.2f} mm) vs chosen {sh.outer_diameter_mm:.3f} mm "
            f"(bore {sh.bore_mm:g} mm): achieved safety factor {n:.1f}",
            {"torque_Nm": torque, "d_min_mm": res.d_min_von_mises, "safety": n}))
        if hob is not None:
            checks.append(Check(
                f"shaft.{sh.name}.hob_clearance", f"{sh.name}: the hob clears the shaft "
                "next to each integral sun", "D <= d_f,sun - h/2 (h = tooth height), every sun",
                sh.outer_diameter_mm <= hob,
                f"smallest d_f - h/2 = {hob:.3f} mm vs D = {sh.outer_diameter_mm:.3f} mm",
                {"limit_mm": hob}))
    return out, checks


@dataclass(frozen=True)
class BearingResult:
    """A bearing's speed [rpm], load [N] and L10 life [h] per gear, and eq. 3.19's life."""

    spec: BearingSpec
    speed_rpm: dict[int, float]
    load_N: dict[int, float]
    life_h: dict[int, float]
    life_eq_3_19_h: dict[int, float]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (inf as None)."""
        def fin(v: dict[int, float]) -> dict[str, float | None]:
            return {str(k): (x if math.isfinite(x) else None) for k, x in v.items()}
        return {"name": self.spec.name, "designation": self.spec.designation,
                "kind": self.spec.kind, "C_N": self.spec.C_N, "speed": self.spec.speed,
                "note": self.spec.note, "speed_rpm": fin(self.speed_rpm),
                "load_N": fin(self.load_N), "L10_h": fin(self.life_h),
                "L10_eq_3_19_h": fin(self.life_eq_3_19_h)}


def bearings(design: Design, train: GearTrain) -> list[BearingResult]:
    """L10 life of every bearing in each gear at the motor's peak torque and rating speed."""
    out = []
    for b in design.bearings:
        p = 3.0 if b.kind == "ball" else 10.0 / 3.0
        speed, load, life, life_t = {}, {}, {}, {}
        for g in (1, 2, 3):
            n = member_speed_rpm(train, b.speed, design.motor.speed_rpm, g)
            P = (planet_pin_load(train, int(b.load[-1]), g, design.motor.peak_torque_Nm)
                 if isinstance(b.load, str) else float(b.load))
            speed[g], load[g] = n, P
            life[g] = l10_hours(b.C_N, P, n, p)
            life_t[g] = l10_hours(b.C_N, P, n, 3.0)
        out.append(BearingResult(b, speed, load, life, life_t))
    return out


@dataclass(frozen=True)
class SplineResult:
    """A spline: D_p, D_re [mm], torque [N m], eq. 3.20 length and torque-based length [mm]."""

    spec: SplineSpec
    d_pitch: float
    d_minor: float
    torque: float
    length_eq_3_20: float
    length_torque: float


def splines(design: Design, train: GearTrain) -> tuple[list[SplineResult], list[Check]]:
    """Spline lengths (eq. 3.20 and from the torque) with their checks."""
    out, checks = [], []
    for sp in design.splines:
        dp = sp.teeth / sp.diametral_pitch * INCH_MM
        dre = (sp.teeth - (1.35 if sp.root == "flat" else 1.8)) / sp.diametral_pitch * INCH_MM
        l320 = dre**3 * (1.0 - (sp.bore_mm / dre) ** 4) / dp**2
        torque, _ = member_torque(train, sp.member, design.motor.peak_torque_Nm)
        tau = VON_MISES_SHEAR * design.materials[sp.material].yield_MPa * 1e6
        lt = 16.0 * torque * sp.safety_factor / (math.pi * (dp / 1000.0) ** 2 * tau) * 1000.0
        res = SplineResult(sp, dp, dre, torque, l320, lt)
        out.append(res)
        if sp.length_mm is None:
            continue
        checks.append(Check(
            f"spline.{sp.name}.length", f"{sp.name}: spline long enough for the peak torque",
            "L >= 16 T N / (pi D_p^2 0.577 S_y) (a quarter of the teeth carrying)",
            sp.length_mm >= lt,
            f"T = {torque:.1f} N·m: L_req = {lt:.2f} mm, eq. 3.20 (equal-strength) "
            f"{l320:.1f} mm, actual {sp.length_mm:g} mm",
            {"L_req_mm": lt, "L_eq_3_20_mm": l320}))
    return out, checks
