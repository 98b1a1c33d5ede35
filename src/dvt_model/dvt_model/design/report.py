"""Assemble, print and plot the design report of ``dvt-model design``."""

from __future__ import annotations

import math
from decimal import Decimal
from pathlib import Path
from typing import Any

from dvt_model.design import components
from dvt_model.design.checks import Check
from dvt_model.design.gears import GearTrain, gear_dict, gear_train, mesh_dict
from dvt_model.design.requirement import RequirementResult, requirement
from dvt_model.design.spec import Design
from dvt_model.errors import ParameterError

EQUATIONS = {
    "inertia": ("1.1", "J = m_arm L^2/3 + m_p L^2", "kg·m²"),
    "gravity_torque": ("1.2", "(m_arm L/2 + m_p L) g", "N·m"),
    "torque_max": ("1.2", "T_max = J alpha_max + (m_arm L/2 + m_p L) g", "N·m"),
    "power_full_load_speed": ("1.3", "P = T_max omega_full / eta", "W"),
    "reduction": ("", "R = max_g T_g / (eta T_peak r_g)", "-"),
}


def printed_tolerance(value: float) -> float:
    """Half a unit of the last printed digit of ``value`` (``8.625`` -> 5e-4, ``3`` -> 0.5)."""
    exp = Decimal(repr(value) if not float(value).is_integer() else str(int(value))).as_tuple()
    exponent = exp.exponent if isinstance(exp.exponent, int) else 0
    return 0.5 * 10.0 ** min(exponent, 0)


def _computed(design: Design, train: GearTrain) -> dict[str, float]:
    out: dict[str, float] = {}
    for s in train.stages:
        out[f"stage_ratio_{s.index}"] = float(s.ratio)
    for g, r in train.gear_ratios.items():
        out[f"gear_ratio_{g}"] = float(r)
    out["efficiency_per_stage"] = design.arm.efficiency ** (1.0 / 3.0)
    return out


def design_report(design: Design) -> dict[str, Any]:
    """The full report as a JSON-ready mapping (units in the key names or ``units``).

    Raises:
        ParameterError: the design's teeth cannot run at its centre distance.
    """
    try:
        train = gear_train(design.gears)
    except ValueError as exc:
        raise ParameterError(
            f"{design.source}: gears.centre_distance_mm: {design.gears.centre_distance_mm!r} "
            f"cannot be reached by the teeth: {exc}") from exc
    req: RequirementResult = requirement(design.arm, design.motor, train.gear_ratios)
    shafts, shaft_checks = components.shafts(design, train)
    bearings = components.bearings(design, train)
    splines, spline_checks = components.splines(design, train)
    checks: list[Check] = list(req.checks)
    for s in train.stages:
        checks.extend(s.checks)
    checks.extend(shaft_checks)
    checks.extend(spline_checks)

    computed = _computed(design, train)
    printed = []
    for key, value in design.printed.items():
        if key not in computed:
            raise ParameterError(f"{design.source}: printed.{key}: unknown figure (expected one "
                                 f"of {sorted(computed)}), got {value!r}")
        tol = printed_tolerance(value)
        printed.append({"figure": key, "printed": value, "computed": computed[key],
                        "tolerance": tol, "agrees": abs(computed[key] - value) <= tol})

    stages = []
    for s in train.stages:
        stages.append({
            "stage": s.index, "teeth": {"sun": s.spec.sun, "planet": s.spec.planet,
                                        "ring": s.spec.ring}, "planets": s.spec.planets,
            "ratio": float(s.ratio), "ratio_exact": str(s.ratio),
            "sun": gear_dict(s.sun), "planet": gear_dict(s.planet), "ring": gear_dict(s.ring),
            "sun_planet": mesh_dict(s.sun_planet), "planet_ring": mesh_dict(s.planet_ring),
        })
    return {
        "design": design.name, "source": design.source, "description": design.description,
        "requirement": req.as_dict(),
        "gear_train": {
            "module_mm": design.gears.module_mm,
            "pressure_angle_deg": design.gears.pressure_angle_deg,
            "centre_distance_mm": design.gears.centre_distance_mm,
            "gear_ratios": {str(g): float(r) for g, r in train.gear_ratios.items()},
            "gear_ratios_exact": {str(g): str(r) for g, r in train.gear_ratios.items()},
            "sun_torque_per_unit_input": {str(g): list(v) for g, v in train.sun_torque.items()},
            "carrier_torque_per_unit_input": {str(g): list(v)
                                              for g, v in train.carrier_torque.items()},
            "stages": stages,
        },
        "shafts": [{"name": r.spec.name, "member": r.spec.member, "material": r.spec.material,
                    "equation": r.spec.equation, "torque_Nm": r.torque, "gear": r.gear,
                    "d_printed_equation_mm": r.d_printed_eq, "d_min_von_mises_mm":
                    r.d_min_von_mises, "d_min_tresca_mm": r.d_min_tresca,
                    "chosen_mm": r.spec.outer_diameter_mm, "bore_mm": r.spec.bore_mm,
                    "safety_achieved": r.safety_achieved, "hob_limit_mm": r.hob_limit}
                   for r in shafts],
        "bearings": [b.as_dict() for b in bearings],
        "splines": [{"name": r.spec.name, "member": r.spec.member, "d_pitch_mm": r.d_pitch,
                     "d_minor_external_mm": r.d_minor, "torque_Nm": r.torque,
                     "length_eq_3_20_mm": r.length_eq_3_20, "length_for_torque_mm":
                     r.length_torque, "length_mm": r.spec.length_mm} for r in splines],
        "printed": printed,
        "checks": [c.as_dict() for c in checks],
        "summary": {"checks": len(checks), "passed": sum(c.passed for c in checks),
                    "failed": [c.id for c in checks if not c.passed],
                    "printed_contradicted": [p["figure"] for p in printed if not p["agrees"]]},
        "assumptions": list(design.assumptions),
    }


def _f(x: float | None, fmt: str = ".3f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "inf"
    return format(x, fmt)


def format_report(rep: dict[str, Any]) -> str:
    """Human-readable report: every figure with its formula (thesis equation) and the checks."""
    L: list[str] = []
    r = rep["requirement"]
    L.append(f"DVT design report: {rep['design']} ({rep['source']})")
    L.append("")
    L.append("== Requirement (ch. 1, eq. 1.1-1.3) ==")
    for key, (eq, formula, unit) in EQUATIONS.items():
        tag = f"[eq. {eq}]" if eq else "[-]"
        L.append(f"  {key:24s} {r[key]:12.2f} {unit:7s} {tag:10s} {formula}")
    L.append("  per gear (load, speed) -> joint torque, DVT output, motor:")
    L.append("  gear  payload   T_joint  w_joint  ratio   T_dvt_out  n_dvt_out  T_motor  "
             "n_motor   P_motor")
    L.append("         [kg]     [N·m]   [rad/s]   [-]     [N·m]      [rpm]      [N·m]    "
             "[rpm]     [W]")
    for d in r["duties"]:
        L.append(f"  {d['gear']:4d} {d['payload_kg']:8.1f} {d['joint_torque']:9.1f} "
                 f"{d['joint_speed']:7.2f} {d['dvt_ratio']:7.4f} {d['dvt_output_torque']:9.2f} "
                 f"{d['dvt_output_speed_rpm']:10.2f} {d['motor_torque']:8.2f} "
                 f"{d['motor_speed_rpm']:8.0f} {d['motor_power']:9.0f}")
    g = rep["gear_train"]
    L.append("")
    L.append(f"== Gear train (ch. 2-3, eq. 3.1-3.16): module {g['module_mm']:g} mm, "
             f"{g['pressure_angle_deg']:g} deg, a' = {g['centre_distance_mm']:g} mm ==")
    L.append("  gear ratios omega_sun/omega_carrier3 (ring g held): " + ", ".join(
        f"{k}: {v:.4f} ({g['gear_ratios_exact'][k]})" for k, v in g["gear_ratios"].items()))
    for s in g["stages"]:
        L.append(f"  -- stage {s['stage']}: {s['teeth']['sun']}/{s['teeth']['planet']}/"
                 f"{s['teeth']['ring']}, {s['planets']} planets, ratio 1 + z_r/z_s = "
                 f"{s['ratio']:.4f}")
        L.append("     gear     z     x        d       d_b      d_a      d_f     hob dh   "
                 "s_a   [mm]")
        for role in ("sun", "planet", "ring"):
            q = s[role]
            L.append(f"     {role:7s}{q['teeth']:4d} {q['x']:+7.4f} {q['d_mm']:8.3f} "
                     f"{q['d_b_mm']:8.3f} {q['d_a_mm']:8.3f} {q['d_f_mm']:8.3f} "
                     f"{q['hob_withdrawal_mm']:+7.3f} {_f(q['tip_thickness_mm'])}")
        for name in ("sun_planet", "planet_ring"):
            m = s[name]
            L.append(f"     {name:11s} u {m['ratio']:.4f} (3.6)  a {m['a_ref']:.3f} (3.1)  "
                     f"a' {m['a_op']:.3f} (3.2)  d' {m['d_op_pinion']:.3f}/{m['d_op_gear']:.3f}"
                     f" (3.4-3.5)  m' {m['spread']:.5f} (3.9)  alpha' {m['alpha_op_deg']:.3f} deg"
                     f" (3.10)")
            L.append(f"     {'':11s} x1+x2 {m['shift_sum']:+.4f}  h_a' "
                     f"{m['addendum_op_pinion']:.3f}/{m['addendum_op_gear']:.3f} (3.11-3.12)  "
                     f"eps {m['contact_ratio']:.3f}")
    L.append("")
    L.append("== Shafts (eq. 3.17-3.18, peak motor torque) ==")
    for s in rep["shafts"]:
        L.append(f"  {s['name']:15s} T {s['torque_Nm']:7.2f} N·m (gear {s['gear']})  eq. "
                 f"{s['equation']} {s['d_printed_equation_mm']:6.2f} mm  von Mises "
                 f"{s['d_min_von_mises_mm']:6.2f} mm  chosen {s['chosen_mm']:.3f} mm  "
                 f"safety {s['safety_achieved']:.1f}")
    L.append("")
    L.append("== Bearings (eq. 3.19; L10 at peak torque and the rating speed) ==")
    for b in rep["bearings"]:
        life = ", ".join(f"g{k} {_f(v, '.3g')} h" for k, v in b["L10_h"].items())
        load = ", ".join(f"{_f(v, '.0f')}" for v in b["load_N"].values())
        speed = ", ".join(f"{_f(v, '.0f')}" for v in b["speed_rpm"].values())
        L.append(f"  {b['name']:17s} {b['designation']} C {b['C_N']:.0f} N; n [rpm] {speed}; "
                 f"P [N] {load}; L10 {life}")
    L.append("")
    L.append("== Splines (eq. 3.20) ==")
    for s in rep["splines"]:
        L.append(f"  {s['name']:15s} D_p {s['d_pitch_mm']:.3f} mm  D_re "
                 f"{s['d_minor_external_mm']:.3f} mm  T {s['torque_Nm']:.1f} N·m  L(3.20) "
                 f"{s['length_eq_3_20_mm']:.1f} mm  "
                 f"L(torque) {s['length_for_torque_mm']:.2f} mm  actual "
                 f"{_f(s['length_mm'], 'g') if s['length_mm'] is not None else 'not given'}")
    if rep["printed"]:
        L.append("")
        L.append("== Printed values (thesis) against the recomputation ==")
        for p in rep["printed"]:
            L.append(f"  {p['figure']:22s} printed {p['printed']:g}  computed "
                     f"{p['computed']:.4f}  (+-{p['tolerance']:g})  "
                     f"{'agrees' if p['agrees'] else 'CONTRADICTED (docs/errata.md)'}")
    sm = rep["summary"]
    L.append("")
    L.append(f"== Checks: {sm['passed']} of {sm['checks']} pass ==")
    for c in rep["checks"]:
        L.append(f"  [{'PASS' if c['passed'] else 'FAIL'}] {c['id']}: {c['detail']}")
    if rep["assumptions"]:
        L.append("")
        L.append("== Assumptions ==")
        L.extend(f"  - {a}" for a in rep["assumptions"])
    return "\n".join(L)


def write_plots(rep: dict[str, Any], directory: str | Path) -> list[Path]:
    """Figures 3-4 recomputed: torque vs acceleration and power vs speed, PNG (Agg).

    Raises:
        ParameterError: the directory cannot be created.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(directory)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ParameterError(f"--plots {directory}: cannot create directory: {exc}") from exc
    r = rep["requirement"]
    paths = [out / "torque_vs_acceleration.png", out / "power_vs_speed.png"]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(r["alpha"], r["torque_curve"])
    ax.set_xlabel("joint acceleration [rad/s²]")
    ax.set_ylabel("joint torque [N·m]")
    ax.set_title("Torque vs acceleration, full load, horizontal (eq. 1.2)")
    ax.grid(True)
    fig.tight_layout()
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(r["speed"], [p / 1000.0 for p in r["power_output_curve"]], label="joint (eq. 1.3)")
    ax.plot(r["speed"], [p / 1000.0 for p in r["power_input_curve"]],
            label="motor input (/ efficiency)")
    ax.set_xlabel("joint speed [rad/s]")
    ax.set_ylabel("power [kW]")
    ax.set_title("Power vs speed at T_max, full load, horizontal")
    ax.legend()
    ax.grid(True)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)
    return paths
