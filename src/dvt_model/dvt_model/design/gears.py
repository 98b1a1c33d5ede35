"""Gear train of the DVT: ratios, non-standard (profile-shifted) geometry and the checks.

Every stage is a simple planetary (sun, ``N`` planets, ring) whose two meshes both run at the
design's common operating centre distance ``a'`` (thesis eq. 3.2). The tooth counts do not
satisfy the standard concentricity ``z_r = z_s + 2 z_p``, so the gears are profile shifted:

* sun-planet (external) and planet-ring (internal) each need the shift sum that makes them run
  without backlash at ``a'``: ``x1 + x2 = (inv a' - inv a)(z1 + z2) / (2 tan a)`` with
  ``cos a' = a cos a / a'`` (eq. 3.1, 3.9-3.10; internal gears with negative ``z``);
* the planet's own shift ``x_p`` is the one free choice per stage (design file);
* tips follow from the shifts (``d_a = d + 2 m (h_a* + x)``) and are topped where the mating
  root would leave less than the tool clearance ``c* m`` (eq. 3.11-3.14 in shift form).

Lengths [mm], angles [deg] in the outputs. Ratios come from :mod:`dvt_model.kinematics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from fractions import Fraction
from typing import Any

from dvt_model.design import involute as inv
from dvt_model.design.checks import Check
from dvt_model.design.spec import GearSpec, StageSpec
from dvt_model.kinematics import Kinematics, kinematics, stage_ratio
from dvt_model.params import Stage, load_parameters


@dataclass(frozen=True)
class Gear:
    """One gear's geometry; diameters are magnitudes [mm] (a ring's tip is its inner circle).

    Attributes:
        role: ``sun``, ``planet`` or ``ring``. teeth: tooth count. x: profile shift (ISO
            sign: positive thickens the tooth on its reference circle).
        d: reference (cutting) pitch diameter ``m z`` (eq. 3.3, 3.7-3.8). d_b: base diameter.
        d_a: outside (tip) diameter; for a ring its inside diameter (eq. 3.13-3.14).
        d_f: root diameter. topping: tip reduction for the clearance [mm on the radius].
        hob_withdrawal: cutter held out by ``x m`` [mm] (eq. 3.15-3.16; in, if negative).
        tip_thickness: circular tooth thickness on the tip circle [mm].
    """

    role: str
    teeth: int
    x: float
    d: float
    d_b: float
    d_a: float
    d_f: float
    topping: float
    hob_withdrawal: float
    tip_thickness: float


@dataclass(frozen=True)
class Mesh:
    """One mesh at the operating centre distance.

    Attributes:
        kind: ``external`` or ``internal``. pinion, gear: the two roles.
        ratio: ``u = z_gear / z_pinion`` (eq. 3.6).
        a_ref: nominal centre distance ``m |z2 +- z1| / 2`` [mm] (eq. 3.1).
        a_op: operating centre distance [mm] (eq. 3.2).
        d_op_pinion, d_op_gear: operating pitch diameters [mm] (eq. 3.4-3.5; internal:
            ``2a'/(u - 1)`` and ``2a' u/(u - 1)``).
        spread: ``m' = d'/d = a'/a`` (eq. 3.9). alpha_op_deg: operating pressure angle (3.10).
        shift_sum: ``x1 + x2`` required (ISO sign). a_from_shifts: centre distance the shifts
            give back (independent inverse of the involute function) [mm].
        addendum_op_pinion, addendum_op_gear: operating addenda, tip to operating pitch
            circle [mm] (eq. 3.11-3.12). path: length of the path of contact [mm].
        contact_ratio: path / base pitch.
        interference_margin: the smallest distance on the line of action between a contact
            limit and a base-circle tangent point [mm]; < 0 means involute interference.
    """

    kind: str
    pinion: str
    gear: str
    ratio: float
    a_ref: float
    a_op: float
    d_op_pinion: float
    d_op_gear: float
    spread: float
    alpha_op_deg: float
    shift_sum: float
    a_from_shifts: float
    addendum_op_pinion: float
    addendum_op_gear: float
    path: float
    contact_ratio: float
    interference_margin: float


@dataclass(frozen=True)
class StageGeometry:
    """A stage's gears, meshes, ratio [-] and checks."""

    index: int
    spec: StageSpec
    sun: Gear
    planet: Gear
    ring: Gear
    sun_planet: Mesh
    planet_ring: Mesh
    ratio: Fraction
    checks: tuple[Check, ...]


@dataclass(frozen=True)
class GearTrain:
    """The three stages, the gear ratios and the per-unit torques.

    Attributes:
        gear_ratios: gear -> exact ``omega_sun / omega_carrier3`` (ring ``gear`` held).
        sun_torque: gear -> per stage, the sun's share of one unit of input torque [-].
        carrier_torque: gear -> per stage, carrier torque per unit input torque [-].
        kin: the kinematics (member speed forms).
    """

    stages: tuple[StageGeometry, StageGeometry, StageGeometry]
    gear_ratios: dict[int, Fraction]
    sun_torque: dict[int, tuple[float, float, float]]
    carrier_torque: dict[int, tuple[float, float, float]]
    kin: Kinematics


def train_kinematics(spec: GearSpec) -> Kinematics:
    """The suite's exact kinematics for the design's teeth (the bundled ``thesis`` parameter
    set with its stages replaced: only the teeth enter the kinematics)."""
    stages = tuple(Stage(sun=s.sun, planet=s.planet, ring=s.ring, planets=s.planets)
                   for s in spec.stages)
    params = replace(load_parameters("thesis"), stages=(stages[0], stages[1], stages[2]))
    return kinematics(params)


def stage_torques(spec: GearSpec, gear: int) -> tuple[list[float], list[float]]:
    """Static torque split for one unit of sun-shaft torque with ring ``gear`` held.

    Each stage obeys ``T_s : T_r : T_c = z_s : z_r : -(z_s + z_r)``; ring 1 free leaves stage 1
    unloaded (and so on up the chain), and a free carrier-ring pair transmits ``T_c,k = -T_r,k+1``.
    Returns (sun torques, carrier torque magnitudes), each per stage, per unit input torque.
    """
    sun = [0.0, 0.0, 0.0]
    sun[gear - 1] = 1.0
    for k in range(gear, 3):
        prev, cur = spec.stages[k - 1], spec.stages[k]
        sun[k] = sun[k - 1] * (prev.sun + prev.ring) / prev.sun * cur.sun / cur.ring
    total = sum(sun)
    sun = [s / total for s in sun]
    carrier = [s * (st.sun + st.ring) / st.sun for s, st in zip(sun, spec.stages, strict=True)]
    return sun, carrier


def _gear(role: str, z_signed: int, x: float, spec: GearSpec, r_a: float, r_a0: float) -> Gear:
    m, alpha = spec.module_mm, math.radians(spec.pressure_angle_deg)
    d = m * z_signed
    sign = 1.0 if z_signed > 0 else -1.0
    d_a = sign * 2.0 * r_a
    d_f = d - 2.0 * m * (spec.dedendum - x)
    try:
        s_a = inv.thickness_at_diameter(z_signed, m, x, alpha, d_a)
    except ValueError:
        s_a = float("nan")  # tip inside the base circle (reported by the ring check)
    return Gear(role=role, teeth=abs(z_signed), x=x, d=abs(d), d_b=abs(d) * math.cos(alpha),
                d_a=abs(d_a), d_f=abs(d_f), topping=abs(r_a0 - r_a), hob_withdrawal=x * m,
                tip_thickness=s_a)


def _mesh(kind: str, p: Gear, g: Gear, spec: GearSpec) -> Mesh:
    m, alpha = spec.module_mm, math.radians(spec.pressure_angle_deg)
    sgn = 1 if kind == "external" else -1
    z1, z2 = p.teeth, sgn * g.teeth
    a_op = sgn * spec.centre_distance_mm
    a_ref = inv.reference_centre_distance(z1, z2, m)
    alpha_op = inv.operating_pressure_angle(a_ref, a_op, alpha)
    u = g.teeth / p.teeth
    d_op_p = 2.0 * abs(a_op) / (u + sgn)
    d_op_g = d_op_p * u
    ra1, rb1 = p.d_a / 2.0, p.d_b / 2.0
    ra2, rb2 = sgn * g.d_a / 2.0, sgn * g.d_b / 2.0
    try:
        path = inv.path_of_contact(ra1, rb1, ra2, rb2, a_op, alpha_op)
    except ValueError:
        path = float("nan")  # a tip inside its base circle: no involute contact (check fails)
    t1t2 = abs(a_op) * math.sin(alpha_op)
    g1 = math.sqrt(max(ra1**2 - rb1**2, 0.0))
    g2 = math.sqrt(max(ra2**2 - rb2**2, 0.0))
    if kind == "external":  # each tip's contact limit must stay short of the other tangent point
        margin = min(t1t2 - g1, t1t2 - g2)
    else:  # the ring's tip must not reach inside the planet's base circle
        margin = g2 - t1t2
    return Mesh(kind=kind, pinion=p.role, gear=g.role, ratio=u, a_ref=abs(a_ref),
                a_op=abs(a_op), d_op_pinion=d_op_p, d_op_gear=d_op_g,
                spread=d_op_p / p.d, alpha_op_deg=math.degrees(alpha_op),
                shift_sum=inv.shift_sum(z1, z2, alpha, alpha_op),
                a_from_shifts=abs(inv.centre_distance_from_shifts(
                    z1, z2, p.x, g.x, m, alpha)),
                addendum_op_pinion=(p.d_a - d_op_p) / 2.0,
                addendum_op_gear=sgn * (g.d_a - d_op_g) / 2.0,
                path=path, contact_ratio=inv.contact_ratio(path, m, alpha),
                interference_margin=margin)


def stage_geometry(spec: GearSpec, index: int) -> StageGeometry:
    """Geometry and checks of stage ``index`` (1..3).

    Raises:
        ValueError: the centre distance cannot be reached by these teeth (operating pressure
            angle undefined); the CLI reports it as a design error.
    """
    st = spec.stages[index - 1]
    m, alpha = spec.module_mm, math.radians(spec.pressure_angle_deg)
    a_op = spec.centre_distance_mm
    zs, zp, zr = st.sun, st.planet, -st.ring
    sum_sp = inv.shift_sum(zs, zp, alpha, inv.operating_pressure_angle(
        inv.reference_centre_distance(zs, zp, m), a_op, alpha))
    sum_pr = inv.shift_sum(zp, zr, alpha, inv.operating_pressure_angle(
        inv.reference_centre_distance(zp, zr, m), -a_op, alpha))
    xp = st.x_planet
    xs, xr = sum_sp - xp, sum_pr - xp
    ha, hf, c = spec.addendum * m, spec.dedendum * m, spec.clearance * m
    # root radii (magnitudes) from generation, tips from the shifts, then topping
    rf_s = m * zs / 2.0 - (hf - xs * m)
    rf_p = m * zp / 2.0 - (hf - xp * m)
    rf_r = m * st.ring / 2.0 + (hf - xr * m)
    ra_s0 = m * zs / 2.0 + ha + xs * m
    ra_p0 = m * zp / 2.0 + ha + xp * m
    ra_r0 = m * st.ring / 2.0 - ha - xr * m
    ra_s = min(ra_s0, a_op - rf_p - c)
    ra_p = min(ra_p0, a_op - rf_s - c, rf_r - a_op - c)
    ra_r = max(ra_r0, a_op + rf_p + c)
    sun = _gear("sun", zs, xs, spec, ra_s, ra_s0)
    planet = _gear("planet", zp, xp, spec, ra_p, ra_p0)
    ring = _gear("ring", zr, xr, spec, ra_r, ra_r0)
    sp = _mesh("external", sun, planet, spec)
    pr = _mesh("internal", planet, ring, spec)
    checks = _stage_checks(index, st, spec, sun, planet, ring, sp, pr)
    return StageGeometry(index=index, spec=st, sun=sun, planet=planet, ring=ring,
                         sun_planet=sp, planet_ring=pr, ratio=stage_ratio(st.sun, st.ring),
                         checks=checks)


def admissible_spacing(sun: int, ring: int, planets: int) -> list[float]:
    """Planet angles [deg] nearest to equal spacing at which every planet meshes: multiples
    of ``360 / (z_s + z_r)`` (ring held, sun turned between insertions)."""
    total = sun + ring
    return [round(k * total / planets) * 360.0 / total for k in range(planets)]


def _stage_checks(k: int, st: StageSpec, spec: GearSpec, sun: Gear, planet: Gear, ring: Gear,
                  sp: Mesh, pr: Mesh) -> tuple[Check, ...]:
    m, alpha = spec.module_mm, math.radians(spec.pressure_angle_deg)
    a_op = spec.centre_distance_mm
    out: list[Check] = []
    p = f"stage{k}."
    # concentricity
    dev = max(abs(sp.a_from_shifts - a_op), abs(pr.a_from_shifts - a_op))
    out.append(Check(
        p + "concentricity", f"stage {k}: both meshes on the common centre distance",
        "a'(x_s + x_p) = a'(x_p + x_r) = a' (standard concentricity z_r = z_s + 2 z_p needs no "
        "shift)", dev < 1e-6 * a_op,
        f"z_s + 2 z_p = {st.sun + 2 * st.planet} vs z_r = {st.ring}; nominal a = "
        f"{sp.a_ref:.3f} / {pr.a_ref:.3f} mm, operating {a_op:.3f} mm reached with "
        f"x_s + x_p = {sp.shift_sum:+.4f}, x_p + x_r = {pr.shift_sum:+.4f}; shifts give back "
        f"{sp.a_from_shifts:.6f} / {pr.a_from_shifts:.6f} mm",
        {"a_ref_sun_planet_mm": sp.a_ref, "a_ref_planet_ring_mm": pr.a_ref,
         "a_back_sun_planet_mm": sp.a_from_shifts, "a_back_planet_ring_mm": pr.a_from_shifts}))
    # assembly
    q = Fraction(st.sun + st.ring, st.planets)
    spacing = admissible_spacing(st.sun, st.ring, st.planets)
    gaps = [(spacing[(i + 1) % st.planets] - spacing[i]) % 360.0 for i in range(st.planets)]
    out.append(Check(
        p + "assembly", f"stage {k}: {st.planets} planets assemble equally spaced",
        "(z_s + z_r) / N integer", q.denominator == 1,
        f"({st.sun} + {st.ring}) / {st.planets} = {float(q):.4f}"
        + ("" if q.denominator == 1 else
           f"; nearest admissible planet angles {', '.join(f'{a:.2f}' for a in spacing)} deg "
           f"(gaps {', '.join(f'{g:.2f}' for g in gaps)} deg)"),
        {"quotient": float(q), "admissible_angles_deg": spacing}))
    # neighbours
    chord = 2.0 * a_op * math.sin(math.pi / st.planets)
    out.append(Check(
        p + "neighbours", f"stage {k}: neighbouring planets clear each other",
        "2 a' sin(pi/N) > d_a,planet", chord > planet.d_a,
        f"2·{a_op:.3f}·sin(180°/{st.planets}) = {chord:.3f} mm vs d_a,p = {planet.d_a:.3f} mm "
        f"(gap {chord - planet.d_a:.3f} mm)", {"chord_mm": chord, "gap_mm": chord - planet.d_a}))
    # undercut of the external gears (rack-cutter generation)
    for g in (sun, planet):
        zmin = inv.undercut_teeth_limit(g.x, alpha, spec.addendum)
        out.append(Check(
            p + f"undercut_{g.role}", f"stage {k}: {g.role} free of undercut",
            "z >= 2 (h_a* - x) / sin^2 a", g.teeth >= zmin,
            f"z = {g.teeth}, x = {g.x:+.4f}: z_min = {zmin:.2f}", {"z_min": zmin}))
    out.append(Check(
        p + "ring_tip_involute", f"stage {k}: ring tip circle outside its base circle",
        "d_a,ring > d_b,ring", ring.d_a > ring.d_b,
        f"d_a,r = {ring.d_a:.3f} mm, d_b,r = {ring.d_b:.3f} mm", {}))
    for mesh, name in ((sp, "sun_planet"), (pr, "planet_ring")):
        out.append(Check(
            p + f"interference_{name}", f"stage {k}: {name.replace('_', '-')} free of "
            "involute interference", "contact starts outside the base circles (line of action: "
            "tip limits within T1T2 = a' sin a')", mesh.interference_margin >= 0.0,
            f"margin {mesh.interference_margin:+.3f} mm", {"margin_mm": mesh.interference_margin}))
        out.append(Check(
            p + f"contact_ratio_{name}", f"stage {k}: {name.replace('_', '-')} contact ratio",
            f"eps = path / (pi m cos a) >= {spec.min_contact_ratio:g}",
            mesh.contact_ratio >= spec.min_contact_ratio,
            f"eps = {mesh.contact_ratio:.3f} (path {mesh.path:.3f} mm)",
            {"contact_ratio": mesh.contact_ratio}))
        lo, hi = spec.pressure_angle_range_deg
        out.append(Check(
            p + f"pressure_angle_{name}", f"stage {k}: {name.replace('_', '-')} operating "
            "pressure angle in the usual range", f"{lo:g} deg <= a' <= {hi:g} deg",
            lo <= mesh.alpha_op_deg <= hi, f"a' = {mesh.alpha_op_deg:.2f} deg",
            {"alpha_op_deg": mesh.alpha_op_deg}))
    smin = spec.min_tip_thickness * m
    for g in (sun, planet, ring):
        ok = math.isfinite(g.tip_thickness) and g.tip_thickness >= smin
        out.append(Check(
            p + f"tip_thickness_{g.role}", f"stage {k}: {g.role} teeth not pointed",
            f"s_a = d_a (s/d + inv a - inv a_a) >= {spec.min_tip_thickness:g} m", ok,
            f"s_a = {g.tip_thickness:.3f} mm (x = {g.x:+.4f})", {"s_a_mm": g.tip_thickness}))
    return tuple(out)


def gear_train(spec: GearSpec) -> GearTrain:
    """All three stages, the exact gear ratios and the torque split of every gear."""
    kin = train_kinematics(spec)
    stages = tuple(stage_geometry(spec, k) for k in (1, 2, 3))
    sun_t: dict[int, tuple[float, float, float]] = {}
    car_t: dict[int, tuple[float, float, float]] = {}
    for g in (1, 2, 3):
        s, c = stage_torques(spec, g)
        sun_t[g] = (s[0], s[1], s[2])
        car_t[g] = (c[0], c[1], c[2])
    return GearTrain(stages=(stages[0], stages[1], stages[2]),
                     gear_ratios={g: kin.gear_ratio(g) for g in (1, 2, 3)},
                     sun_torque=sun_t, carrier_torque=car_t, kin=kin)


def gear_dict(g: Gear) -> dict[str, Any]:
    """JSON-ready gear."""
    return {"teeth": g.teeth, "x": g.x, "d_mm": g.d, "d_b_mm": g.d_b, "d_a_mm": g.d_a,
            "d_f_mm": g.d_f, "topping_mm": g.topping, "hob_withdrawal_mm": g.hob_withdrawal,
            "tip_thickness_mm": g.tip_thickness}


def mesh_dict(mesh: Mesh) -> dict[str, Any]:
    """JSON-ready mesh."""
    return {k: getattr(mesh, k) for k in mesh.__dataclass_fields__}
