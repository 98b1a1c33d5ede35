"""Loading and validating hidden effects: presets, YAML mappings and runtime changes (pure, no
I/O but files; the schema is in :mod:`dvt_driver.plant.hidden`).

Errors are :class:`~dvt_driver.errors.HiddenEffectsError` naming the source, the key path and
the value.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from dvt_driver.errors import HiddenEffectsError
from dvt_driver.plant.hidden.draw import draw_record, resolve
from dvt_driver.plant.hidden.effects import (
    BACKLASH_LOCATIONS,
    DEFAULT_FRICTION_VELOCITY,
    MEMBERS,
    Backlash,
    Bands,
    Change,
    HiddenEffects,
    MeshRipple,
    PositionFriction,
    StribeckFriction,
    WetBrake,
)
from dvt_model.errors import ModelError
from dvt_model.laws import LAWS
from dvt_model.load import JointLoad, load_joint_load, parse_joint_load
from dvt_model.presets import bundled_names, read_yaml_setting

__all__ = [
    "MAX_DAMPING_SCALE",
    "available_presets",
    "changes_from_spec",
    "load_hidden",
    "parse_change",
    "parse_hidden",
]

_PRESET_DIR = "config"
"""Where the bundled presets lie (``dvt_driver/plant/config/<name>.yaml``)."""


def available_presets() -> list[str]:
    """Names of the bundled hidden-effect presets (``config/<name>.yaml``)."""
    return bundled_names("dvt_driver.plant", _PRESET_DIR)


def load_hidden(name_or_path: str | Path, draw: int | None = None) -> HiddenEffects:
    """Load a preset by name (``coulomb``) or a YAML file by path, drawing its distributions.

    Args:
        name_or_path: preset name or YAML path.
        draw: the seed of the draw of the preset's distributions (an integer >= 0; the plant
            passes its ``--seed``), or ``None`` for the fixed draw (each distribution's
            ``fixed`` value: the preset's nominal plant). See :mod:`~.draw`; the result's
            ``draw`` records the seed and the distributions for ``truth.yaml``.

    Raises:
        HiddenEffectsError: unknown preset, unreadable file, invalid YAML or content.
    """
    data, source = read_yaml_setting(name_or_path, what="hidden-effects preset",
                                     error=HiddenEffectsError, package="dvt_driver.plant",
                                     directory=_PRESET_DIR)
    values, distributions = resolve(data, draw, source)
    return dataclasses.replace(parse_hidden(values, source=source),
                               draw=draw_record(draw, distributions))


def _num(value: Any, where: str, *, lo: float | None = None, lo_open: bool = False,
         hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise HiddenEffectsError(f"{where}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise HiddenEffectsError(f"{where}: expected a finite number, got {value!r}")
    if lo is not None and (out <= lo if lo_open else out < lo):
        op = ">" if lo_open else ">="
        raise HiddenEffectsError(f"{where}: expected a number {op} {lo:g}, got {value!r}")
    if hi is not None and out > hi:
        raise HiddenEffectsError(f"{where}: expected a number <= {hi:g}, got {value!r}")
    return out


def _map(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise HiddenEffectsError(f"{where}: expected a mapping, got {value!r}")
    return value


def _keys(data: Mapping[str, Any], where: str, required: tuple[str, ...],
          optional: tuple[str, ...] = ()) -> None:
    allowed = required + optional
    for key in data:
        if key not in allowed:
            raise HiddenEffectsError(f"{where}.{key}: unknown key (expected one of "
                                     f"{sorted(allowed)}), value {data[key]!r}")
    for key in required:
        if key not in data:
            raise HiddenEffectsError(f"{where}.{key}: missing (required keys: "
                                     f"{list(required)})")


def _per_band(value: Any, where: str, hi: float) -> tuple[float, float, float] | None:
    """Three numbers in ``(0, hi]``, bands 1..3 (``None``: not given)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 3:
        raise HiddenEffectsError(f"{where}: expected a list of 3 numbers (bands 1, 2, 3), "
                                 f"got {value!r}")
    a, b, c = (_num(v, f"{where}[{i}]", lo=0.0, lo_open=True, hi=hi)
               for i, v in enumerate(value))
    return a, b, c


def _member(name: Any, where: str) -> str:
    if name not in MEMBERS:
        raise HiddenEffectsError(f"{where}.{name}: unknown member (expected one of "
                                 f"{list(MEMBERS)})")
    return str(name)


_TOP = ("coulomb", "stribeck", "windage", "laws", "backlash", "measurement_delay", "wet_brake",
        "friction_velocity", "gravity_arm", "mesh_ripple", "position_friction", "bands",
        "damping_scale", "changes")
_CHANGE_KEYS = ("at", "ramp", "coulomb", "windage", "damping_scale", "load", "note")
MAX_DAMPING_SCALE = 10.0
"""Largest admissible ``damping_scale``."""


def changes_from_spec(spec: str, at: float) -> list[Change]:
    """The changes ``dvt-plant --change-at T:SPEC`` adds: ``spec`` is a preset name or a
    hidden-effects YAML path. If it has ``changes``, those, shifted in time so that the first
    starts at ``at`` [s of plant time] (their spacing kept); else one step at ``at`` to its
    ``coulomb``, ``windage`` and ``damping_scale`` (e.g. ``40:coulomb`` on a clean plant: a
    friction step at 40 s). A preset's distributions take their fixed draw (the nominal
    values): a runtime change is a stated step, not a draw.

    Raises:
        HiddenEffectsError: ``spec`` does not load, or changes nothing that can change.
    """
    h = load_hidden(spec)
    if h.changes:
        first = min(c.at for c in h.changes)
        return [dataclasses.replace(c, at=at + c.at - first) for c in h.changes]
    if not (h.coulomb or h.windage or h.damping_scale != 1.0):
        raise HiddenEffectsError(
            f"{h.source}: changes nothing at runtime (only coulomb, windage, damping_scale and "
            f"changes can change while the plant runs), effects {h.effect_names()}")
    return [Change(at=at, coulomb=dict(h.coulomb), windage=dict(h.windage),
                   damping_scale=None if h.damping_scale == 1.0 else h.damping_scale,
                   note=f"step to {h.source}")]


def parse_change(data: Any, where: str, at: float | None = None) -> Change:
    """Validate one change (a mapping; ``at`` may be left out when ``at`` is given here, e.g.
    a change applied now) into a :class:`Change`.

    Raises:
        HiddenEffectsError: naming ``where``, the key and the value.
    """
    d = _map(data, where)
    for key in d:
        if key not in _CHANGE_KEYS:
            raise HiddenEffectsError(f"{where}.{key}: unknown key (expected one of "
                                     f"{list(_CHANGE_KEYS)}), value {d[key]!r}")
    if "at" in d:
        t = _num(d["at"], f"{where}.at", lo=0.0)
    elif at is not None:
        t = float(at)
    else:
        raise HiddenEffectsError(f"{where}.at: missing (the plant time of the change [s])")
    coulomb = {_member(m, f"{where}.coulomb"): _num(v, f"{where}.coulomb.{m}", lo=0.0)
               for m, v in _map(d.get("coulomb") or {}, f"{where}.coulomb").items()}
    windage = {_member(m, f"{where}.windage"): _num(v, f"{where}.windage.{m}", lo=0.0)
               for m, v in _map(d.get("windage") or {}, f"{where}.windage").items()}
    scale = (None if d.get("damping_scale") is None else
             _num(d["damping_scale"], f"{where}.damping_scale", lo=0.0, hi=MAX_DAMPING_SCALE))
    load = d.get("load")
    if load is not None:
        if not isinstance(load, str) or not load:
            raise HiddenEffectsError(f"{where}.load: expected a load preset name, 'none' or a "
                                     f"load YAML path, got {load!r}")
        try:
            load_joint_load(load)
        except (ModelError, OSError) as exc:
            raise HiddenEffectsError(f"{where}.load: {exc}") from exc
    note = d.get("note", "")
    if not isinstance(note, str):
        raise HiddenEffectsError(f"{where}.note: expected text, got {note!r}")
    if not (coulomb or windage or scale is not None or load is not None):
        raise HiddenEffectsError(f"{where}: changes nothing (expected at least one of coulomb, "
                                 f"windage, damping_scale, load), got {dict(d)!r}")
    return Change(at=t, ramp=_num(d.get("ramp", 0.0), f"{where}.ramp", lo=0.0, hi=1e6),
                  coulomb=coulomb, windage=windage, damping_scale=scale,
                  load=None if load is None else str(load), note=note)


def _parse_laws(data: Any, where: str) -> dict[str, tuple[tuple[str, dict[str, float]], ...]]:
    """``laws``: member -> list of ``{law: NAME, FIELD: value, ...}`` with NAME a law of
    :data:`dvt_model.laws.LAWS` and its fields (a field with a default may be left out; the
    sign's smoothing is the plant's, so no ``eps``), each within the law's bounds.

    Raises:
        HiddenEffectsError: naming ``where``, the member, the entry, the field and the value.
    """
    out: dict[str, tuple[tuple[str, dict[str, float]], ...]] = {}
    if data is None:
        return out
    for m, entries in _map(data, where).items():
        member = _member(m, where)
        mw = f"{where}.{member}"
        if not isinstance(entries, list) or not entries:
            raise HiddenEffectsError(f"{mw}: expected a non-empty list of laws, got "
                                     f"{entries!r}")
        terms: list[tuple[str, dict[str, float]]] = []
        for i, entry in enumerate(entries):
            ew = f"{mw}[{i}]"
            d = _map(entry, ew)
            name = d.get("law")
            if name not in LAWS:
                raise HiddenEffectsError(f"{ew}.law: expected one of {sorted(LAWS)}, got "
                                         f"{name!r}")
            law = LAWS[str(name)]
            _keys(d, ew, ("law", *(p.name for p in law.params if p.default is None)),
                  tuple(p.name for p in law.params if p.default is not None))
            terms.append((law.name, {
                p.name: _num(d.get(p.name, p.default), f"{ew}.{p.name}", lo=p.lower,
                             lo_open=p.lo_open, hi=p.upper) for p in law.params}))
        out[member] = tuple(terms)
    return out


def parse_hidden(data: Any, source: str = "<mapping>") -> HiddenEffects:
    """Validate a parsed YAML mapping (``None`` or ``{}``: no effect) into :class:`HiddenEffects`.

    Raises:
        HiddenEffectsError: naming ``source``, the key path and the value.
    """
    w = f"{source}: "
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise HiddenEffectsError(f"{w}expected a mapping at the top level, got {data!r}")
    for key in data:
        if key not in _TOP:
            raise HiddenEffectsError(f"{w}{key}: unknown effect (expected one of "
                                     f"{list(_TOP)}), value {data[key]!r}")

    coulomb: dict[str, float] = {}
    if data.get("coulomb") is not None:
        for m, v in _map(data["coulomb"], f"{w}coulomb").items():
            name = _member(m, f"{w}coulomb")
            coulomb[name] = _num(v, f"{w}coulomb.{name}", lo=0.0)

    stribeck: dict[str, StribeckFriction] = {}
    if data.get("stribeck") is not None:
        for m, v in _map(data["stribeck"], f"{w}stribeck").items():
            name = _member(m, f"{w}stribeck")
            sw = f"{w}stribeck.{name}"
            d = _map(v, sw)
            _keys(d, sw, ("Fc", "Fs", "vs"), ("delta",))
            fc = _num(d["Fc"], f"{sw}.Fc", lo=0.0)
            fs = _num(d["Fs"], f"{sw}.Fs", lo=0.0)
            if fs < fc:
                raise HiddenEffectsError(f"{sw}.Fs: expected a number >= Fc ({fc:g}), "
                                         f"got {d['Fs']!r}")
            stribeck[name] = StribeckFriction(
                Fc=fc, Fs=fs, vs=_num(d["vs"], f"{sw}.vs", lo=0.0, lo_open=True),
                delta=_num(d.get("delta", 2.0), f"{sw}.delta", lo=0.0, lo_open=True))

    windage: dict[str, float] = {}
    if data.get("windage") is not None:
        for m, v in _map(data["windage"], f"{w}windage").items():
            name = _member(m, f"{w}windage")
            windage[name] = _num(v, f"{w}windage.{name}", lo=0.0)

    speed_laws = _parse_laws(data.get("laws"), f"{w}laws")

    backlash: Backlash | None = None
    if data.get("backlash") is not None:
        bw = f"{w}backlash"
        d = _map(data["backlash"], bw)
        _keys(d, bw, ("gap", "stiffness", "damping", "load_inertia"),
              ("where", "load_damping"))
        where = d.get("where", "carrier3_output")
        if where not in BACKLASH_LOCATIONS:
            raise HiddenEffectsError(f"{bw}.where: expected one of {list(BACKLASH_LOCATIONS)}, "
                                     f"got {where!r}")
        backlash = Backlash(
            where=str(where),
            gap=_num(d["gap"], f"{bw}.gap", lo=0.0, hi=1.0),
            stiffness=_num(d["stiffness"], f"{bw}.stiffness", lo=0.0, lo_open=True),
            damping=_num(d["damping"], f"{bw}.damping", lo=0.0),
            load_inertia=_num(d["load_inertia"], f"{bw}.load_inertia", lo=0.0, lo_open=True),
            load_damping=_num(d.get("load_damping", 0.0), f"{bw}.load_damping", lo=0.0))

    delay = 0.0
    if data.get("measurement_delay") is not None:
        dw = f"{w}measurement_delay"
        raw = data["measurement_delay"]
        if isinstance(raw, Mapping):
            _keys(raw, dw, ("seconds",))
            delay = _num(raw["seconds"], f"{dw}.seconds", lo=0.0, hi=1.0)
        else:
            delay = _num(raw, dw, lo=0.0, hi=1.0)

    wet: dict[int, WetBrake] = {}
    if data.get("wet_brake") is not None:
        ww = f"{w}wet_brake"
        bands = _map(data["wet_brake"], ww)
        allowed = ("all", "band1", "band2", "band3")
        for key, v in bands.items():
            if key not in allowed:
                raise HiddenEffectsError(f"{ww}.{key}: unknown band (expected one of "
                                         f"{list(allowed)}), value {v!r}")
        for key, v in bands.items():
            kw = f"{ww}.{key}"
            d = _map(v, kw)
            _keys(d, kw, ("viscous_time", "viscous_coefficient", "viscous_fraction",
                          "asperity_time", "release_time"))
            shape = WetBrake(
                viscous_time=_num(d["viscous_time"], f"{kw}.viscous_time", lo=0.0, hi=10.0),
                viscous_coefficient=_num(d["viscous_coefficient"],
                                         f"{kw}.viscous_coefficient", lo=0.0),
                viscous_fraction=_num(d["viscous_fraction"], f"{kw}.viscous_fraction",
                                      lo=0.0, hi=1.0),
                asperity_time=_num(d["asperity_time"], f"{kw}.asperity_time", lo=0.0,
                                   lo_open=True, hi=10.0),
                release_time=_num(d["release_time"], f"{kw}.release_time", lo=0.0,
                                  lo_open=True, hi=10.0))
            if key == "all":
                for k in (1, 2, 3):
                    wet.setdefault(k, shape)
            else:
                wet[int(str(key)[-1])] = shape  # bandN overrides "all"

    fv = DEFAULT_FRICTION_VELOCITY
    if data.get("friction_velocity") is not None:
        fv = _num(data["friction_velocity"], f"{w}friction_velocity", lo=0.0, lo_open=True)

    gravity: JointLoad | None = None
    if data.get("gravity_arm") is not None:
        try:
            gravity = parse_joint_load(data["gravity_arm"], source=f"{w}gravity_arm")
        except ModelError as exc:
            raise HiddenEffectsError(str(exc)) from exc

    ripple: MeshRipple | None = None
    if data.get("mesh_ripple") is not None:
        rw = f"{w}mesh_ripple"
        d = _map(data["mesh_ripple"], rw)
        _keys(d, rw, ("amplitude",), ("stage", "phase"))
        stage = d.get("stage", 1)
        if isinstance(stage, bool) or stage not in (1, 2, 3):
            raise HiddenEffectsError(f"{rw}.stage: expected 1, 2 or 3, got {stage!r}")
        ripple = MeshRipple(amplitude=_num(d["amplitude"], f"{rw}.amplitude", lo=0.0, hi=100.0),
                            stage=int(stage), phase=_num(d.get("phase", 0.0), f"{rw}.phase"))

    bumps: dict[str, PositionFriction] = {}
    if data.get("position_friction") is not None:
        pw = f"{w}position_friction"
        for m, v in _map(data["position_friction"], pw).items():
            name = _member(m, pw)
            bw = f"{pw}.{name}"
            d = _map(v, bw)
            _keys(d, bw, ("amplitude", "center", "width"))
            bumps[name] = PositionFriction(
                amplitude=_num(d["amplitude"], f"{bw}.amplitude", lo=0.0, hi=100.0),
                center=_num(d["center"], f"{bw}.center"),
                width=_num(d["width"], f"{bw}.width", lo=0.0, lo_open=True, hi=10.0))

    built: Bands | None = None
    if data.get("bands") is not None:
        bw = f"{w}bands"
        d = _map(data["bands"], bw)
        _keys(d, bw, (), ("gain", "time_constant"))
        built = Bands(gain=_per_band(d.get("gain"), f"{bw}.gain", hi=1000.0),
                      time_constant=_per_band(d.get("time_constant"), f"{bw}.time_constant",
                                              hi=10.0))

    scale = 1.0
    if data.get("damping_scale") is not None:
        scale = _num(data["damping_scale"], f"{w}damping_scale", lo=0.0, hi=MAX_DAMPING_SCALE)
    changes: list[Change] = []
    if data.get("changes") is not None:
        raw_changes = data["changes"]
        if not isinstance(raw_changes, list):
            raise HiddenEffectsError(f"{w}changes: expected a list of changes, got "
                                     f"{raw_changes!r}")
        changes = [parse_change(c, f"{w}changes[{i}]") for i, c in enumerate(raw_changes)]

    return HiddenEffects(coulomb=coulomb, stribeck=stribeck, windage=windage, laws=speed_laws,
                         backlash=backlash,
                         measurement_delay=delay, wet_brake=wet, friction_velocity=fv,
                         gravity_arm=gravity, mesh_ripple=ripple, position_friction=bumps,
                         bands=built, damping_scale=scale, changes=tuple(changes), source=source)
