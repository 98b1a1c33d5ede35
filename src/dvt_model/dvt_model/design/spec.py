"""The design file: geometry, materials and loads of a DVT, validated into frozen objects.

A design file is YAML (the thesis's design is bundled as ``thesis.yaml``; see that file for
every key, its unit and where each value comes from). Keys carry their unit in their name
(``_mm``, ``_m``, ``_kg``, ``_N``, ``_MPa``, ``_deg``, ``_rpm``); a value the thesis does not
give is an *assumption*, listed in the file's ``assumptions`` and repeated in the report.

Errors name the file, the key path and the value, e.g.
``thesis.yaml: gears.stages[2].ring: expected an integer > 0, got 'x'``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dvt_model.errors import ParameterError
from dvt_model.presets import read_yaml_setting

MEMBERS_WITH_TORQUE = ("sun", "carrier1", "carrier2", "carrier3")
"""Members whose torque the shafts and splines are sized for."""

SPEED_MEMBERS = ("sun", "ring1", "ring2", "ring3", "carrier1", "carrier2", "carrier3",
                 "planet1_rel", "planet2_rel", "planet3_rel")
"""Member speeds a bearing may see (``a-b`` for the relative speed of two members)."""


@dataclass(frozen=True)
class ArmSpec:
    """The arm and load of the baseline requirement (thesis ch. 1, eq. 1.1-1.3).

    Attributes:
        length_m [m], arm_mass_kg, payload_kg [kg], gravity_m_s2 [m/s^2].
        efficiency: total efficiency between motor and joint [-].
        alpha_max_rad_s2: joint acceleration of T_max and the end of the torque curve [rad/s^2].
        speed_range_rad_s: joint-speed range of the power curve [rad/s].
        speed_no_load, speed_half_load, speed_full_load: joint speeds to reach [rad/s] with
            no, half and the full payload (carried in gear 1, 2 and 3 respectively).
        torque_min_Nm: the stated torque requirement [N m]; motor_power_min_kW: the stated
            drive-motor power [kW].
    """

    length_m: float
    arm_mass_kg: float
    payload_kg: float
    gravity_m_s2: float
    efficiency: float
    alpha_max_rad_s2: float
    speed_range_rad_s: tuple[float, float]
    speed_no_load: float
    speed_half_load: float
    speed_full_load: float
    torque_min_Nm: float
    motor_power_min_kW: float


@dataclass(frozen=True)
class MotorSpec:
    """Drive motor: peak torque [N m] and the speed at which bearings are rated [rpm]."""

    peak_torque_Nm: float
    speed_rpm: float


@dataclass(frozen=True)
class StageSpec:
    """One planetary stage: teeth, planet count, and the planet's profile-shift coefficient."""

    sun: int
    planet: int
    ring: int
    planets: int
    x_planet: float


@dataclass(frozen=True)
class GearSpec:
    """Gear-train inputs (ch. 3.1-3.2). Lengths [mm], angles [deg], coefficients per module.

    Attributes:
        module_mm: hob module. pressure_angle_deg: tool pressure angle.
        centre_distance_mm: operating centre distance common to all meshes (eq. 3.2).
        addendum, dedendum, clearance: tool coefficients h_a*, h_f*, c* (x module).
        min_contact_ratio, min_tip_thickness (x module), pressure_angle_range_deg:
            acceptance limits of the checks.
        stages: three stages, input side first.
    """

    module_mm: float
    pressure_angle_deg: float
    centre_distance_mm: float
    addendum: float
    dedendum: float
    clearance: float
    min_contact_ratio: float
    min_tip_thickness: float
    pressure_angle_range_deg: tuple[float, float]
    stages: tuple[StageSpec, StageSpec, StageSpec]


@dataclass(frozen=True)
class Material:
    """A material: tensile yield strength [MPa] and where the value comes from."""

    name: str
    yield_MPa: float
    note: str


@dataclass(frozen=True)
class ShaftSpec:
    """A shaft section sized for ``member``'s largest torque at the motor's peak torque.

    ``equation`` is the thesis's sizing rule, ``"3.17"`` (solid) or ``"3.18"`` (hollow);
    diameters [mm].
    """

    name: str
    member: str
    material: str
    safety_factor: float
    outer_diameter_mm: float
    bore_mm: float
    equation: str


@dataclass(frozen=True)
class BearingSpec:
    """A bearing: dynamic rating ``C_N`` [N], life exponent (3 ball, 10/3 roller), the member
    speed it sees and its radial load (``planetN`` = the computed planet-pin load, or a number
    [N])."""

    name: str
    designation: str
    kind: str
    C_N: float
    speed: str
    load: str | float
    note: str


@dataclass(frozen=True)
class SplineSpec:
    """An involute spline (ANSI B92.1 30 deg, side fit): teeth, diametral pitch [1/in],
    root form, bore [mm], the member whose torque it carries, and its actual length [mm]
    (``None``: not known, only the required lengths are reported)."""

    name: str
    member: str
    teeth: int
    diametral_pitch: float
    root: str
    bore_mm: float
    length_mm: float | None
    material: str
    safety_factor: float


@dataclass(frozen=True)
class Design:
    """A validated design file."""

    name: str
    description: str
    source: str
    arm: ArmSpec
    motor: MotorSpec
    gears: GearSpec
    materials: dict[str, Material]
    shafts: tuple[ShaftSpec, ...]
    bearings: tuple[BearingSpec, ...]
    splines: tuple[SplineSpec, ...]
    assumptions: tuple[str, ...]
    printed: dict[str, float]


# ---------------------------------------------------------------- validation helpers


class _Reader:
    """Typed access to a mapping that names ``source`` and the key path in every error."""

    def __init__(self, data: Any, where: str, source: str) -> None:
        if not isinstance(data, Mapping):
            raise ParameterError(f"{source}: {where or 'top level'}: expected a mapping, "
                                 f"got {data!r}")
        self.data, self.where, self.source = data, where, source
        self.used: set[str] = set()

    def path(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key: str, expected: str, value: Any) -> ParameterError:
        return ParameterError(f"{self.source}: {self.path(key)}: expected {expected}, "
                              f"got {value!r}")

    def get(self, key: str, default: Any = ...) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise ParameterError(f"{self.source}: {self.path(key)}: missing")
            return default
        return self.data[key]

    def number(self, key: str, *, lo: float | None = None, hi: float | None = None,
               strict_lo: bool = True, default: float | None = None) -> float:
        value = self.get(key, ... if default is None else default)
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(float(value)):
            raise self.fail(key, "a finite number", value)
        out = float(value)
        if lo is not None and (out <= lo if strict_lo else out < lo):
            raise self.fail(key, f"a number {'>' if strict_lo else '>='} {lo:g}", value)
        if hi is not None and out > hi:
            raise self.fail(key, f"a number <= {hi:g}", value)
        return out

    def integer(self, key: str, lo: int = 1) -> int:
        value = self.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise self.fail(key, f"an integer >= {lo}", value)
        return value

    def text(self, key: str, default: str | None = None, choices: Sequence[str] = ()) -> str:
        value = self.get(key, ... if default is None else default)
        if not isinstance(value, str) or (choices and value not in choices):
            raise self.fail(key, f"one of {list(choices)}" if choices else "a string", value)
        return value

    def pair(self, key: str) -> tuple[float, float]:
        value = self.get(key)
        if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
            raise self.fail(key, "a list of 2 increasing numbers", value)
        r = _Reader({"0": value[0], "1": value[1]}, self.path(key), self.source)
        lo, hi = r.number("0", lo=0.0), r.number("1", lo=0.0)
        if not hi > lo:
            raise self.fail(key, "a list of 2 increasing numbers", value)
        return lo, hi

    def child(self, key: str) -> _Reader:
        return _Reader(self.get(key), self.path(key), self.source)

    def items(self, key: str, default: Any = ...) -> list[_Reader]:
        value = self.get(key, default)
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise self.fail(key, "a list of mappings", value)
        return [_Reader(v, f"{self.path(key)}[{i}]", self.source) for i, v in enumerate(value)]

    def done(self) -> None:
        unknown = sorted(set(map(str, self.data)) - self.used)
        if unknown:
            raise ParameterError(f"{self.source}: {self.path(unknown[0])}: unknown key "
                                 f"(expected one of {sorted(self.used)})")


def _speed_expr(r: _Reader, key: str) -> str:
    value = r.text(key)
    parts = value.split("-")
    if len(parts) not in (1, 2) or any(p not in SPEED_MEMBERS for p in parts):
        raise r.fail(key, f"a member of {list(SPEED_MEMBERS)} or 'a-b' of two", value)
    return value


def parse_design(data: Any, source: str = "<mapping>") -> Design:
    """Validate a parsed design mapping.

    Raises:
        ParameterError: naming ``source``, the key path and the value.
    """
    top = _Reader(data, "", source)
    name = top.text("name", default=Path(source).stem)
    description = top.text("description", default="")

    a = top.child("requirement")
    arm = ArmSpec(
        length_m=a.number("length_m", lo=0.0), arm_mass_kg=a.number("arm_mass_kg", lo=0.0,
                                                                     strict_lo=False),
        payload_kg=a.number("payload_kg", lo=0.0, strict_lo=False),
        gravity_m_s2=a.number("gravity_m_s2", lo=0.0),
        efficiency=a.number("efficiency", lo=0.0, hi=1.0),
        alpha_max_rad_s2=a.number("alpha_max_rad_s2", lo=0.0),
        speed_range_rad_s=a.pair("speed_range_rad_s"),
        speed_no_load=a.number("speed_no_load_rad_s", lo=0.0),
        speed_half_load=a.number("speed_half_load_rad_s", lo=0.0),
        speed_full_load=a.number("speed_full_load_rad_s", lo=0.0),
        torque_min_Nm=a.number("torque_min_Nm", lo=0.0),
        motor_power_min_kW=a.number("motor_power_min_kW", lo=0.0),
    )
    a.done()

    mo = top.child("motor")
    motor = MotorSpec(peak_torque_Nm=mo.number("peak_torque_Nm", lo=0.0),
                      speed_rpm=mo.number("speed_rpm", lo=0.0))
    mo.done()

    g = top.child("gears")
    stage_readers = g.items("stages")
    if len(stage_readers) != 3:
        raise g.fail("stages", "a list of 3 stages", g.data.get("stages"))
    stages: list[StageSpec] = []
    for s in stage_readers:
        st = StageSpec(sun=s.integer("sun", 3), planet=s.integer("planet", 3),
                       ring=s.integer("ring", 3), planets=s.integer("planets", 1),
                       x_planet=s.number("x_planet", lo=-2.0, hi=2.0, strict_lo=False))
        if st.ring <= st.planet + 2:
            raise s.fail("ring", f"more teeth than planet + 2 = {st.planet + 2}", st.ring)
        s.done()
        stages.append(st)
    pa = g.number("pressure_angle_deg", lo=0.0, hi=45.0)
    gears = GearSpec(
        module_mm=g.number("module_mm", lo=0.0),
        pressure_angle_deg=pa,
        centre_distance_mm=g.number("centre_distance_mm", lo=0.0),
        addendum=g.number("addendum", lo=0.0), dedendum=g.number("dedendum", lo=0.0),
        clearance=g.number("clearance", lo=0.0, strict_lo=False),
        min_contact_ratio=g.number("min_contact_ratio", lo=0.0),
        min_tip_thickness=g.number("min_tip_thickness", lo=0.0, strict_lo=False),
        pressure_angle_range_deg=g.pair("pressure_angle_range_deg"),
        stages=(stages[0], stages[1], stages[2]),
    )
    g.done()

    materials: dict[str, Material] = {}
    mats = top.child("materials")
    for key in list(mats.data):
        m = mats.child(str(key))
        materials[str(key)] = Material(name=str(key), yield_MPa=m.number("yield_MPa", lo=0.0),
                                       note=m.text("note", default=""))
        m.done()
    mats.done()

    def material(r: _Reader) -> str:
        value = r.text("material")
        if value not in materials:
            raise r.fail("material", f"one of the materials {sorted(materials)}", value)
        return value

    shafts: list[ShaftSpec] = []
    for s in top.items("shafts"):
        eq = s.text("equation", choices=("3.17", "3.18"))
        sh = ShaftSpec(name=s.text("name"), member=s.text("member", choices=MEMBERS_WITH_TORQUE),
                       material=material(s), safety_factor=s.number("safety_factor", lo=0.0),
                       outer_diameter_mm=s.number("outer_diameter_mm", lo=0.0),
                       bore_mm=s.number("bore_mm", lo=0.0, strict_lo=False, default=0.0),
                       equation=eq)
        if sh.bore_mm >= sh.outer_diameter_mm:
            raise s.fail("bore_mm", f"less than outer_diameter_mm = {sh.outer_diameter_mm}",
                         sh.bore_mm)
        s.done()
        shafts.append(sh)

    bearings: list[BearingSpec] = []
    for b in top.items("bearings"):
        load_raw = b.get("load")
        load: str | float
        if isinstance(load_raw, str):
            if load_raw not in ("planet1", "planet2", "planet3"):
                raise b.fail("load", "planet1..planet3 or a load in N", load_raw)
            load = load_raw
        else:
            load = b.number("load", lo=0.0)
        kind = b.text("kind", choices=("ball", "roller"))
        bearings.append(BearingSpec(name=b.text("name"), designation=b.text("designation"),
                                    kind=kind, C_N=b.number("C_N", lo=0.0),
                                    speed=_speed_expr(b, "speed"), load=load,
                                    note=b.text("note", default="")))
        b.done()

    splines: list[SplineSpec] = []
    for s in top.items("splines", default=[]):
        sp = SplineSpec(name=s.text("name"), member=s.text("member", choices=MEMBERS_WITH_TORQUE),
                        teeth=s.integer("teeth", 6),
                        diametral_pitch=s.number("diametral_pitch_per_in", lo=0.0),
                        root=s.text("root", choices=("flat", "fillet")),
                        bore_mm=s.number("bore_mm", lo=0.0, strict_lo=False, default=0.0),
                        length_mm=(s.number("length_mm", lo=0.0) if "length_mm" in s.data
                                   else s.get("length_mm", None)),
                        material=material(s),
                        safety_factor=s.number("safety_factor", lo=0.0))
        s.done()
        splines.append(sp)

    assumptions_raw = top.get("assumptions", [])
    if not isinstance(assumptions_raw, Sequence) or isinstance(assumptions_raw, str) \
            or not all(isinstance(v, str) for v in assumptions_raw):
        raise top.fail("assumptions", "a list of strings", assumptions_raw)
    printed_raw = top.child("printed") if "printed" in top.data else None
    printed: dict[str, float] = {}
    if printed_raw is not None:
        for key in list(printed_raw.data):
            printed[str(key)] = printed_raw.number(str(key))
        printed_raw.done()
    top.done()
    return Design(name=name, description=description, source=source, arm=arm, motor=motor,
                  gears=gears, materials=materials, shafts=tuple(shafts),
                  bearings=tuple(bearings), splines=tuple(splines),
                  assumptions=tuple(assumptions_raw), printed=printed)


def load_design(name_or_path: str | Path | None = None) -> Design:
    """Load a design: a bundled one by name (``thesis``, from ``design/thesis.yaml``) or a
    design YAML file by path; ``None`` = the bundled thesis design.

    Raises:
        ParameterError: unknown name, unreadable file, invalid YAML or invalid content.
    """
    data, source = read_yaml_setting("thesis" if name_or_path is None else name_or_path,
                                     what="design", error=ParameterError,
                                     package="dvt_model.design")
    return parse_design(data, source=source)
