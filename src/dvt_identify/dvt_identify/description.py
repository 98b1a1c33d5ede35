"""Actuator descriptions: which bag signals are inputs/outputs, the model structure, candidates.

A description is a YAML file (see ``descriptions/emps.yaml`` for a complete example)::

    name: emps
    inputs:  [{name: force, topic: /emps/drive, field: effort, joint: carriage,
               scale: 1.0, saturation: [-351.5, 351.5]}]
    outputs: [{name: carriage, topic: /emps/joint_states, field: velocity, joint: carriage}]
    # optional per input   hold: zoh (a held command, default) | linear (a sampled current)
    # optional per output  sampling: instant (default) | interval (an encoder's count rate)
    # (dvt_identify.data.intersample)
    structure:
      type: mechanical            # or state_space, or python
      mass: [[M]]                 # entries: numbers or [-][coef*]parameter
      damping: [[Fv]]
      input_matrix: [[1.0]]
      force_unit: N
      speed_unit: m/s
      parameters: {M: {initial: 100, lower: 0.001, unit: kg}, Fv: {initial: 200, lower: 0}}
    model_effects:                # part of the baseline model (e.g. the band brakes)
      - {effect: brake_lockup, where: ring1, member: {...}, input: brake1,
         initial: {band_gain: 8}}
    candidates:
      - {effect: coulomb_friction, where: carriage, offset: true}
    preprocess: {lowpass: null, decimate: 1, fit_decimate: auto}
    checks: {min_samples: 200, max_gap_samples: 3, max_saturated_fraction: 0.01}
    fit: {starts: 4, refit_starts: 2, alpha: 0.01, min_validation_gain: 0.1, max_effects: 4,
          max_tries_per_round: 3, seed: 0}
    notes: ["free text carried into the report"]
    experiments:                  # optional: what determines a parameter (see below)
      - {parameters: "^(M|Fv)$", run: "a 0.1-10 Hz multisine of +-200 N", excites: "the mass"}

Structure types:

- ``state_space``: ``A`` (nx, nx), ``B`` (nx, nu), optional ``force_map`` (nx, nx, default I).
- ``mechanical``: ``mass``, ``damping``, ``input_matrix``; ``A = -M^-1 D``, ``B = M^-1 Q``,
  ``F = M^-1``.
- ``python``: ``class: "package.module:Class"`` and ``options``; the class is called as
  ``Class(state_names=..., input_names=..., **options)`` and must satisfy
  :class:`dvt_identify.structures.ModelStructure`.

- ``mechanical`` with ``stiffness`` (and/or ``members``): members joined by springs, with
  hidden states (:class:`dvt_identify.structures.SpringMechanicalStructure`)::

      structure:
        type: mechanical
        members: [motor, load]          # states: motor_angle, load_angle, motor, load
        mass: [[Jm, 0], [0, Jl]]
        damping: [["c + dm", "-c"], ["-c", "c + dl"]]   # entries may be sums
        stiffness: [[k, "-k"], ["-k", k]]              # a shaft between the two members
        input_matrix: [[1.0], [0.0]]
        outputs: {w_load: load}         # measured output -> state (a speed or <member>_angle)

  ``A = [[0, I], [-M^-1 K, -M^-1 D]]``; ``y = C x`` with ``C`` selecting the measured states;
  every initial state (hidden ones included) is estimated. Force effects act on member speeds
  (``where: load``); output effects (sensor maps, delay, gain) on measured outputs
  (``where: w_load``).

``experiments`` (optional) names the actuator's own experiments: a list of ``{parameters:
REGEX, run: COMMAND OR PROCEDURE, excites: WHAT}``; the first row whose regex matches a
parameter's name (``re.search``) is the advice for it when a recording does not determine it
(:mod:`dvt_identify.identifiability`; ``excites`` may use the regex's named groups, ``{n}``).
Without the section (or without a matching row) the advice is generic, from the data and the
model.

Otherwise the states are the outputs, in order (C = I). Parameter names must be unique over
the structure, the model effects and the candidates; a clash is refused on loading, with the
names. ``load_description`` takes a file path or the name of
a bundled description (``descriptions/<name>.yaml``); the default name is ``dvt``.
"""

from __future__ import annotations

import copy
import importlib
import importlib.resources
import math
import re
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dvt_identify.data import HOLDS, SAMPLINGS, Checks, SignalSpec
from dvt_identify.effects import VOCABULARY, Effect, make_effect
from dvt_identify.errors import DescriptionError
from dvt_identify.structures import (
    MechanicalStructure,
    ModelStructure,
    SpringMechanicalStructure,
    StateSpaceStructure,
)
from dvt_model.presets import safe_load

DEFAULT_DESCRIPTION = "dvt"


@dataclass(frozen=True)
class Preprocess:
    """Pre-processing of every bag.

    Attributes:
        lowpass: ``{cutoff_hz, order, zero_phase}`` or ``None``.
        decimate: decimation of all data (estimation and validation).
        fit_decimate: further decimation of the estimation data for fitting and scoring only;
            figures are computed at the full rate. 0 (``auto`` in the file, the default): each
            segment's factor follows its rate and the model's dynamics
            (:func:`dvt_identify.fitrate.fit_decimation`).
    """

    lowpass: dict[str, Any] | None = None
    decimate: int = 1
    fit_decimate: int = 0


@dataclass(frozen=True)
class FitOptions:
    """Options of the fit and the augment loop (see :class:`dvt_identify.loop.LoopConfig`)."""

    starts: int = 4
    refit_starts: int = 2
    alpha: float = 0.01
    min_validation_gain: float = 0.1
    max_effects: int = 4
    max_tries_per_round: int = 3
    seed: int = 0


@dataclass(frozen=True)
class CandidateSpec:
    """One candidate entry: effect name, where, explicit member vector and options."""

    effect: str
    where: str
    member: tuple[float, ...] | None = None
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ExperimentSpec:
    """One row of a description's ``experiments`` section.

    Attributes:
        parameters: regex over parameter names (``re.search``; named groups fill ``excites``).
        run: the command or procedure that determines them (e.g. ``dvt-experiment ident``).
        excites: what it excites, for people (may name the regex's groups, ``{n}``).
    """

    parameters: str
    run: str
    excites: str


@dataclass(frozen=True)
class Description:
    """A loaded actuator description (see module docstring)."""

    name: str
    source: str
    inputs: tuple[SignalSpec, ...]
    outputs: tuple[SignalSpec, ...]
    structure: ModelStructure
    candidates: tuple[CandidateSpec, ...]
    preprocess: Preprocess
    checks: Checks
    fit: FitOptions
    notes: tuple[str, ...] = ()
    text: str = ""
    model_effects: tuple[CandidateSpec, ...] = ()
    prior_starts: tuple[dict[str, float], ...] = ()
    """Further starts of the baseline fit (parameter name -> value; names absent: the initial
    value): the initial values that :meth:`with_initial` replaced (e.g. the thesis prior when
    the refit starts from the model in use)."""
    experiments: tuple[ExperimentSpec, ...] = ()
    """The actuator's own experiments (``experiments`` section), in priority order."""

    def initial_values(self) -> dict[str, float]:
        """The initial value of every structure and model-effect parameter, by name."""
        return {p.name: float(p.initial) for p in [
            *self.structure.params, *(q for e in self.make_model_effects() for q in e.params)]}

    def with_initial(self, values: Mapping[str, Any], keep_prior: bool = True) -> Description:
        """A copy whose structure and model-effect parameters start at ``values`` (name ->
        number, e.g. ``{"M22": 0.03, "band_gain_ring1": 7.5}``; names not given keep theirs).

        Args:
            values: new initial values (the names :meth:`initial_values` lists).
            keep_prior: keep the replaced initial values as a further start
                (:attr:`prior_starts`, after those already kept).

        Raises:
            DescriptionError: an unknown name, a value that is not a finite number, or one
                outside the parameter's bounds (each naming the parameter and the value).
        """
        specs = {p.name: p for p in self.structure.params}
        where: dict[str, tuple[int, str]] = {}  # model-effect parameter -> (spec, base name)
        for k, (c, eff) in enumerate(zip(self.model_effects, self.make_model_effects(),
                                         strict=True)):
            for p in eff.params:
                specs[p.name] = p
                where[p.name] = (k, p.name.removesuffix(f"_{c.where}"))
        unknown = sorted(str(n) for n in values if n not in specs)
        if unknown:
            raise DescriptionError(f"{self.source}: initial values: unknown parameter(s) "
                                   f"{unknown} (expected {sorted(specs)})")
        new: dict[str, float] = {}
        for name, v in values.items():
            spec = specs[name]
            if isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer) \
                    or not math.isfinite(float(v)):
                raise DescriptionError(f"{self.source}: initial value of {name}: expected a "
                                       f"finite number, got {v!r}")
            if not spec.lower <= float(v) <= spec.upper:
                raise DescriptionError(f"{self.source}: initial value of {name}: {float(v)!r} "
                                       f"outside its bounds [{spec.lower:g}, {spec.upper:g}]")
            new[name] = float(v)
        prior = self.initial_values()
        structure = copy.copy(self.structure)
        structure.params = tuple(replace(p, initial=new.get(p.name, p.initial))
                                 for p in self.structure.params)
        effects = list(self.model_effects)
        for name, v in new.items():
            if name in where:
                k, base = where[name]
                c = effects[k]
                init = dict(c.options.get("initial") or {})
                init[base] = v
                effects[k] = replace(c, options={**c.options, "initial": init})
        starts = (*self.prior_starts, prior) if keep_prior and new else self.prior_starts
        return replace(self, structure=structure, model_effects=tuple(effects),
                       prior_starts=starts)

    def start_values(self) -> list[np.ndarray]:
        """Full start vectors of the baseline fit (structure parameters, then the model
        effects'): the initial values, then each of :attr:`prior_starts` (clipped into the
        bounds; a name no longer present, e.g. of a dropped band, is ignored)."""
        specs = [*self.structure.params, *(q for e in self.make_model_effects() for q in e.params)]
        out = [np.array([p.initial for p in specs], dtype=float)]
        for prior in self.prior_starts:
            out.append(np.array([min(max(float(prior.get(p.name, p.initial)), p.lower), p.upper)
                                 for p in specs], dtype=float))
        return out

    @property
    def input_names(self) -> tuple[str, ...]:
        """Input names in order."""
        return tuple(s.name for s in self.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Output names in order (the states, unless the structure has hidden states)."""
        return tuple(s.name for s in self.outputs)

    @property
    def state_names(self) -> tuple[str, ...]:
        """The structure's state names (= the outputs unless it has hidden states)."""
        return tuple(self.structure.state_names)

    def check_parameter_names(self) -> None:
        """Refuse parameter names that clash: the structure's with a model effect's or a
        candidate's, a model effect's with another's, a candidate's with another candidate's
        (every candidate may join the model together).

        Raises:
            DescriptionError: naming the file, the clashing names and who owns them.
        """
        owners: dict[str, list[str]] = {}
        for p in self.structure.params:
            owners.setdefault(p.name, []).append("structure")
        for e in [*self.make_model_effects(), *self.make_candidates()]:
            for p in e.params:
                owners.setdefault(p.name, []).append(e.label())
        dup = {n: o for n, o in owners.items() if len(o) > 1}
        if dup:
            raise DescriptionError(f"{self.source}: duplicate parameter names: "
                                   + "; ".join(f"{n} ({', '.join(o)})"
                                               for n, o in sorted(dup.items()))
                                   + " (rename the structure's parameter or use the effect's "
                                     "suffix)")

    def make_candidates(self) -> list[Effect]:
        """Build the candidate effects (parameter names get ``_<where>`` when an effect appears
        more than once; ``_add`` is appended where a name would clash with a model effect's)."""
        taken = {p.name for e in self.make_model_effects() for p in e.params}
        return self._build(self.candidates, always=False, taken=taken)

    def make_model_effects(self) -> list[Effect]:
        """Build the effects that are part of the baseline model (``model_effects``, e.g. the
        band brakes), with the initial values of their ``initial`` option; parameter names are
        ``<name>_<where>`` (``band_gain_ring1``, ``band_time_constant_brake1``)."""
        return self._build(self.model_effects, always=True, taken=set())

    def _build(self, specs: tuple[CandidateSpec, ...], always: bool, taken: set[str]
               ) -> list[Effect]:
        counts = Counter(c.effect for c in specs)
        out = []
        for c in specs:
            suffix = f"_{c.where}" if always or counts[c.effect] > 1 else ""
            states, outs = self.state_names, self.output_names
            readout = tuple(getattr(self.structure, "output_states", ()))
            probe = make_effect(c.effect, c.where, states, self.input_names,
                                member=c.member,
                                options={k: v for k, v in c.options.items() if k != "initial"},
                                suffix=suffix, output_names=outs, output_states=readout)
            if any(p.name in taken for p in probe.params):
                suffix += "_add"
            opts = {k: v for k, v in c.options.items() if k != "initial"}
            eff = make_effect(c.effect, c.where, states, self.input_names,
                              force_unit=self.structure.force_unit,
                              speed_unit=self.structure.speed_unit,
                              member=c.member, options=opts, suffix=suffix, output_names=outs,
                              output_states=readout)
            init = c.options.get("initial")
            if init is not None:
                if not isinstance(init, dict):
                    raise DescriptionError(f"{self.source}: {c.effect}@{c.where}: initial: "
                                           f"expected a mapping, got {init!r}")
                base = {s.name: s.name.removesuffix(suffix) for s in eff.params}
                unknown = sorted(str(k) for k in init if k not in base.values())
                if unknown:
                    raise DescriptionError(f"{self.source}: {c.effect}@{c.where}: initial: "
                                           f"unknown parameter(s) {unknown} (expected "
                                           f"{sorted(base.values())})")
                eff = eff.with_initial({name: float(init[b]) for name, b in base.items()
                                        if b in init})
            out.append(eff)
        return out


def _fit_decimate(raw: object) -> int:
    """``preprocess.fit_decimate``: ``auto`` (or null) -> 0, else an integer >= 1.

    Raises:
        ValueError: anything else (the caller names the file).
    """
    if raw is None or (isinstance(raw, str) and raw.strip().lower() == "auto"):
        return 0
    bad = f"fit_decimate: expected auto or an integer >= 1, got {raw!r}"
    if isinstance(raw, bool) or not isinstance(raw, int | float | str):
        raise ValueError(bad)
    try:
        q = int(float(raw))
    except ValueError:
        raise ValueError(bad) from None
    if q < 1 or q != float(raw):
        raise ValueError(bad)
    return q


def available_descriptions() -> list[str]:
    """Names of the descriptions bundled with the package."""
    root = importlib.resources.files("dvt_identify") / "descriptions"
    try:
        return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".yaml"))
    except (FileNotFoundError, NotADirectoryError):
        return []


def _req(d: dict[str, Any], key: str, where: str) -> Any:
    if key not in d:
        raise DescriptionError(f"{where}: missing key {key!r}")
    return d[key]


def _signals(raw: Any, where: str, kind: str) -> tuple[SignalSpec, ...]:
    """The signal list ``raw`` of ``kind`` ``inputs`` or ``outputs``: an input may say how it
    behaves between samples (``hold``), an output what its sample measures (``sampling``)."""
    if not isinstance(raw, list) or not raw:
        raise DescriptionError(f"{where}: expected a non-empty list of signals")
    out = []
    own, other = ("hold", "sampling") if kind == "inputs" else ("sampling", "hold")
    choices = {"hold": HOLDS, "sampling": SAMPLINGS}
    for i, s in enumerate(raw):
        w = f"{where}[{i}]"
        if not isinstance(s, dict):
            raise DescriptionError(f"{w}: expected a mapping, got {s!r}")
        if other in s:
            raise DescriptionError(f"{w}.{other}: {s[other]!r} is for "
                                   f"{'outputs' if other == 'sampling' else 'inputs'}, not "
                                   f"{kind} (an {kind[:-1]} takes {own}: one of "
                                   f"{list(choices[own])})")
        if own in s and s[own] not in choices[own]:
            raise DescriptionError(f"{w}.{own}: expected one of {list(choices[own])}, got "
                                   f"{s[own]!r}")
        sat = s.get("saturation")
        if sat is not None and (not isinstance(sat, list) or len(sat) != 2):
            raise DescriptionError(f"{w}.saturation: expected [low, high], got {sat!r}")
        field_ = str(_req(s, "field", w))
        if field_ not in ("position", "velocity", "effort"):
            raise DescriptionError(f"{w}.field: expected position, velocity or effort, "
                                   f"got {field_!r}")
        try:
            out.append(SignalSpec(name=str(_req(s, "name", w)), topic=str(_req(s, "topic", w)),
                                  field=field_, joint=str(_req(s, "joint", w)),
                                  scale=float(s.get("scale", 1.0)),
                                  saturation=None if sat is None else (float(sat[0]),
                                                                       float(sat[1])),
                                  hold=str(s.get("hold", "zoh")),
                                  sampling=str(s.get("sampling", "instant"))))
        except (TypeError, ValueError) as exc:
            raise DescriptionError(f"{w}: {exc}") from exc
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise DescriptionError(f"{where}: duplicate names {names}")
    return tuple(out)


def _structure(raw: Any, states: tuple[str, ...], inputs: tuple[str, ...],
               where: str) -> ModelStructure:
    if not isinstance(raw, dict):
        raise DescriptionError(f"{where}: expected a mapping")
    kind = raw.get("type")
    params = raw.get("parameters", {}) or {}
    if not isinstance(params, dict):
        raise DescriptionError(f"{where}.parameters: expected a mapping")
    fu, su = str(raw.get("force_unit", "")), str(raw.get("speed_unit", ""))
    if kind == "state_space":
        return StateSpaceStructure(states, inputs, _req(raw, "A", where), _req(raw, "B", where),
                                   params, raw.get("force_map"), fu, su, what=where)
    if kind == "mechanical" and ("stiffness" in raw or "members" in raw):
        members = raw.get("members", list(states))
        outs = raw.get("outputs")
        if not isinstance(members, list):
            raise DescriptionError(f"{where}.members: expected a list of names, got {members!r}")
        if outs is not None and not isinstance(outs, dict):
            raise DescriptionError(f"{where}.outputs: expected a mapping output -> state, "
                                   f"got {outs!r}")
        n = len(members)
        stiff = raw.get("stiffness", [[0.0] * n for _ in range(n)])
        return SpringMechanicalStructure(members, states, inputs, _req(raw, "mass", where),
                                         _req(raw, "damping", where), stiff,
                                         _req(raw, "input_matrix", where), params, outs, fu,
                                         su, str(raw.get("angle_unit", "")), what=where)
    if kind == "mechanical":
        return MechanicalStructure(states, inputs, _req(raw, "mass", where),
                                   _req(raw, "damping", where), _req(raw, "input_matrix", where),
                                   params, fu, su, what=where)
    if kind == "python":
        target = str(_req(raw, "class", where))
        mod_name, _, cls_name = target.partition(":")
        try:
            cls = getattr(importlib.import_module(mod_name), cls_name)
        except (ImportError, AttributeError) as exc:
            raise DescriptionError(f"{where}.class: cannot import {target!r}: {exc}") from exc
        obj = cls(state_names=states, input_names=inputs, **(raw.get("options") or {}))
        if not isinstance(obj, ModelStructure):
            raise DescriptionError(f"{where}.class: {target} does not implement ModelStructure")
        if tuple(obj.state_names) != states or tuple(obj.input_names) != inputs:
            raise DescriptionError(f"{where}.class: {target} names states {obj.state_names} and "
                                   f"inputs {obj.input_names}; the description has {states} and "
                                   f"{inputs}")
        return obj
    raise DescriptionError(f"{where}.type: expected state_space, mechanical or python, "
                           f"got {kind!r}")


def _candidates(raw: Any, states: tuple[str, ...], where: str) -> tuple[CandidateSpec, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise DescriptionError(f"{where}: expected a list")
    out = []
    for i, c in enumerate(raw):
        w = f"{where}[{i}]"
        if not isinstance(c, dict):
            raise DescriptionError(f"{w}: expected a mapping, got {c!r}")
        eff = str(_req(c, "effect", w))
        if eff not in VOCABULARY or eff == "none":
            raise DescriptionError(f"{w}.effect: {eff!r} is not a candidate effect (known: "
                                   f"{', '.join(VOCABULARY)})")
        member = c.get("member")
        mv: tuple[float, ...] | None = None
        if isinstance(member, dict):
            unknown = set(member) - set(states)
            if unknown:
                raise DescriptionError(f"{w}.member: unknown states {sorted(unknown)}")
            mv = tuple(float(member.get(s, 0.0)) for s in states)
        elif isinstance(member, list):
            mv = tuple(float(v) for v in member)
        opts = {k: v for k, v in c.items() if k not in ("effect", "where", "member")}
        out.append(CandidateSpec(effect=eff, where=str(_req(c, "where", w)), member=mv,
                                 options=opts))
    return tuple(out)


EXPERIMENT_KEYS = ("parameters", "run", "excites")
"""The keys of one ``experiments`` row, all required."""


def _experiments(raw: Any, where: str) -> tuple[ExperimentSpec, ...]:
    """The ``experiments`` section: a list of ``{parameters, run, excites}`` (none: empty).

    Raises:
        DescriptionError: naming ``where`` (the file), the row's key and the value.
    """
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise DescriptionError(f"{where}: expected a list of {{parameters, run, excites}}, "
                               f"got {raw!r}")
    out = []
    for i, row in enumerate(raw):
        w = f"{where}[{i}]"
        if not isinstance(row, dict):
            raise DescriptionError(f"{w}: expected a mapping {{parameters, run, excites}}, "
                                   f"got {row!r}")
        unknown = sorted(str(k) for k in row if k not in EXPERIMENT_KEYS)
        if unknown:
            raise DescriptionError(f"{w}: unknown key(s) {unknown} (expected "
                                   f"{', '.join(EXPERIMENT_KEYS)})")
        vals: dict[str, str] = {}
        for key in EXPERIMENT_KEYS:
            v = _req(row, key, w)
            if not isinstance(v, str) or not v.strip():
                raise DescriptionError(f"{w}.{key}: expected a non-empty text, got {v!r}")
            vals[key] = v.strip()
        try:
            pattern = re.compile(vals["parameters"])
        except re.error as exc:
            raise DescriptionError(f"{w}.parameters: {vals['parameters']!r} is not a regular "
                                   f"expression: {exc}") from exc
        try:
            vals["excites"].format(**{g: "" for g in pattern.groupindex})
        except (KeyError, IndexError) as exc:
            raise DescriptionError(f"{w}.excites: {vals['excites']!r} names {exc} that is not "
                                   f"a named group of parameters {vals['parameters']!r} "
                                   f"(groups: {sorted(pattern.groupindex) or 'none'}; write "
                                   "literal braces as {{ }})") from exc
        except ValueError as exc:
            raise DescriptionError(f"{w}.excites: {vals['excites']!r} is not a format text: "
                                   f"{exc} (write literal braces as {{{{ }}}})") from exc
        out.append(ExperimentSpec(**vals))
    return tuple(out)


def parse_description(data: Any, source: str, text: str = "") -> Description:
    """Build a :class:`Description` from parsed YAML ``data``; errors name ``source``."""
    if not isinstance(data, dict):
        raise DescriptionError(f"{source}: expected a mapping at the top level")
    inputs = _signals(_req(data, "inputs", source), f"{source}: inputs", "inputs")
    outputs = _signals(_req(data, "outputs", source), f"{source}: outputs", "outputs")
    states = tuple(s.name for s in outputs)
    structure = _structure(_req(data, "structure", source), states,
                           tuple(s.name for s in inputs), f"{source}: structure")
    xs = tuple(structure.state_names)
    cands = _candidates(data.get("candidates"), xs, f"{source}: candidates")
    model_fx = _candidates(data.get("model_effects"), xs, f"{source}: model_effects")
    pre = data.get("preprocess") or {}
    chk = data.get("checks") or {}
    fit = data.get("fit") or {}
    try:
        preprocess = Preprocess(lowpass=pre.get("lowpass"), decimate=int(pre.get("decimate", 1)),
                                fit_decimate=_fit_decimate(pre.get("fit_decimate", "auto")))
        checks = Checks(**{k: type(getattr(Checks(), k))(v) for k, v in chk.items()})
        fopts = FitOptions(**{k: type(getattr(FitOptions(), k))(v) for k, v in fit.items()})
    except (TypeError, ValueError, AttributeError) as exc:
        raise DescriptionError(f"{source}: preprocess/checks/fit: {exc}") from exc
    desc = Description(name=str(data.get("name", Path(source).stem)), source=source,
                       inputs=inputs, outputs=outputs, structure=structure, candidates=cands,
                       preprocess=preprocess, checks=checks, fit=fopts,
                       notes=tuple(str(n) for n in data.get("notes", []) or []), text=text,
                       model_effects=model_fx,
                       experiments=_experiments(data.get("experiments"),
                                                f"{source}: experiments"))
    desc.make_candidates()  # validate names and options now
    desc.make_model_effects()
    desc.check_parameter_names()
    return desc


def load_description(spec: str | Path | None = None) -> Description:
    """Load a description from a file path or a bundled name (default ``dvt``).

    Raises:
        DescriptionError: file not found / not YAML / invalid, naming the file and key.
    """
    spec = DEFAULT_DESCRIPTION if spec is None else spec
    path = Path(spec)
    if path.is_file():
        text = path.read_text()
        source = str(path)
    else:
        name = str(spec)
        res = importlib.resources.files("dvt_identify") / "descriptions" / f"{name}.yaml"
        if not res.is_file():
            raise DescriptionError(f"description {name!r}: no such file and no bundled "
                                   f"description of that name (bundled: "
                                   f"{', '.join(available_descriptions()) or 'none'})")
        text = res.read_text()
        source = f"{name} (bundled)"
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        raise DescriptionError(f"{source}: not valid YAML: {exc}") from exc
    return parse_description(data, source, text)
