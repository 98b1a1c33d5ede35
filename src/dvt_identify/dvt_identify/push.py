"""Map an identified model onto the live model node's parameters (pure, no rclpy).

The DVT structure (``descriptions/dvt.yaml``: mechanical, symmetric M and D entries
``M11, M12, M22, D11, D12, D22``) maps to the model node's ``M`` and ``D``; each accepted
effect maps to the terms of the node's ``effects`` JSON that it declares
(:meth:`dvt_identify.effects.Effect.model_terms`; Coulomb with offset, Stribeck, windage,
measurement delay, sensor gain; the position-dependent ``gravity_load`` -> ``gravity``,
``periodic_disturbance`` -> ``angle_periodic``, ``unlisted`` -> one ``library`` term per
coefficient; ``backlash`` -> ``dead_zone`` on an input, ``play`` on an output, or
``spline_play`` for the compliant spline). Members, angle forms and output indices are
mapped from the model's outputs to the node's speeds (:data:`dvt_model.contract.SPEED_NAMES`)
when the outputs include those names, in any order and with other outputs besides (the
``dvt-position`` description's angle states ``sun_shaft_angle``, ``carrier3_angle``): a form
keeps its entries on the speeds, and a term whose form has a non-zero entry on another output,
or whose ``output`` is not a speed, is not pushed (the node's terms act on its two speeds); a
term's input (``library``, ``dead_zone``) is mapped from the model's input name to the node's
current (:data:`~dvt_model.contract.CURRENT_NAMES`; ``input_joints``, else the name itself or
:data:`INPUT_ALIASES`).

Effects the model node cannot represent (an extra brake-engagement stage or dead time, a
disturbance clocked on time, ...) or whose values it would refuse are listed in
``skipped`` with the reason and not pushed; so are

- a term that depends on an angle (:func:`dvt_model.contract.term_needs_angle`) when the fit's
  segments did not all carry the measured positions: the identifier then integrated the member
  speed from 0 at each segment's first sample
  (:data:`~dvt_identify.effects.position.ANGLE_FROM_SPEED`), a phase relative to the
  recording, while the node's angles are the measured positions;
- a term whose input the identified model transforms (a brake's engagement lag): the
  identifier's term saw the transformed input, the node's takes the raw current. A pushed
  ``dead_zone`` is the exception: the node applies it to the current before everything else,
  so the node's terms see the same input the identifier's did; a dead zone is itself not
  pushed when another effect transforms its input too (the order would differ), and when it
  is not pushed the terms on its input are not either.

An effect is pushed whole or not at all. The baseline's band brakes (``brake_lockup``
``band_gain_*`` [N m/A] and ``brake_engagement`` ``band_time_constant_*`` [s] on the inputs
``brake1..3``) map to the node's ``band_gain`` and ``band_time_constant`` (the name each
effect declares as its ``band_parameter``) when all three bands were identified and the data
determined each value (relative standard deviation at most :data:`MAX_RELATIVE_STD`) and,
when validation segments are given, the fitted band values predict them better than the
values the fit started from (the description's, or the model in use's for a refit from it):
the linearised standard deviation does not see the gain-lag ridge of a band engaged once or
twice, a held-out prediction does (:func:`band_check`).

Every term is checked with :func:`dvt_model.contract.validate_term` /
:func:`~dvt_model.contract.validate_effects` and the whole push with
:func:`dvt_model.config.check_parameters`: the push cannot write what the node would refuse.

:attr:`Push.parameters` is one transaction: the identifier sends it (and a rollback, the
previous values of the same names) through the model node's ``~/set_parameters_atomically``
(:func:`dvt_identify.node.push_parameters`), never parameter by parameter, so the node runs the
old model or the new one, never a mix (``docs/interface.md`` §6).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dvt_identify.data import Segment
from dvt_identify.effects import Effect, Term
from dvt_identify.effects.base import SegmentView
from dvt_identify.effects.position import ANGLE_FROM_POSITION, angle_of
from dvt_identify.errors import PushError
from dvt_identify.fit import OEFit
from dvt_identify.metrics import figures
from dvt_identify.stages import Stage
from dvt_model.config import check_parameters
from dvt_model.contract import (
    CURRENT_NAMES,
    SPEED_NAMES,
    term_needs_angle,
    validate_effects,
)
from dvt_model.errors import DvtModelError

RESEND_S = 5.0
"""A push not answered within this time [s] is sent again
(:func:`dvt_model.contract.answer_of`: a repeated push is no change)."""

MAX_RELATIVE_STD = 0.5
"""A band parameter whose standard deviation exceeds this fraction of its value (or is not
finite, e.g. at a bound) is not pushed: the data did not determine it."""

BANDS = (1, 2, 3)
"""The band numbers of the model node's per-band parameters (inputs ``brake1..3``)."""

INPUT_ALIASES: dict[str, str] = {"motor": "drive_motor"}
"""Model input names that name a model-node current differently (the ``dvt`` description's
``motor`` is the ``drive_motor`` current of ``/dvt/currents``)."""

_PROBE_DT = 1e-3
"""Sample time [s] of the input-transform probe when the fit keeps no segments."""


@dataclass(frozen=True)
class Push:
    """Parameters for ``dvt_model_node`` (name -> value; set together, in one transaction)
    and what could not be pushed (one line each, with the reason)."""

    parameters: dict[str, Any]
    skipped: list[str] = field(default_factory=list)


def model_node_parameters(stage: Stage, n_model_effects: int = 0,
                          input_joints: Sequence[str] | None = None,
                          held: Mapping[str, float] | None = None,
                          validation: Sequence[Segment] | None = None) -> Push:
    """Build the model node's parameters from a fitted stage.

    Args:
        stage: the final (or baseline) stage of an identification; its fit's segments
            (``fit.segments_``) tell whether the angles were measured (none: not known, an
            angle-dependent term is not pushed).
        n_model_effects: how many leading effects belong to the baseline model (the bands);
            they are represented by the node's own band model (``band_gain``,
            ``band_time_constant``), not by effect terms.
        input_joints: the ``/dvt/currents`` joint of each model input, in input order (the
            description's ``inputs[i].joint``); ``None``: an input's own name, or its
            :data:`INPUT_ALIASES` entry.
        held: values of structure parameters the fit held fixed (name -> value, e.g. the
            ``M11..D22`` of the model in use when the supervisor's refit held the structure,
            :func:`dvt_identify.supervisor.held_description`); a fitted value of the same
            name wins.
        validation: held-out segments (the identification's validation data); given, the
            band values are pushed only when :func:`band_check` confirms them on these.

    Raises:
        PushError: the structure has no M and D entries (not the DVT mechanical one), the
            model node would refuse a value (naming the parameter and the value), or
            ``input_joints`` has the wrong length.
    """
    values = {**(held or {}), **stage.parameters()}
    try:
        M = [values["M11"], values["M12"], values["M12"], values["M22"]]
        D = [values["D11"], values["D12"], values["D12"], values["D22"]]
    except KeyError as exc:
        raise PushError(f"cannot push to the model node: the structure has no {exc} "
                        "(expected the DVT mechanical structure with M11..D22)") from exc
    if not np.all(np.isfinite(M + D)):
        raise PushError(f"cannot push non-finite M/D: M {M}, D {D}")
    fit = stage.fit
    model = fit.model
    params = model.effect_params(fit.theta_)
    outputs = list(model.structure.state_names)
    inputs = list(model.structure.input_names)
    std = fit.parameter_std()
    pairs = list(zip(model.effects, params, strict=True))
    out: dict[str, Any] = {"M": [float(v) for v in M], "D": [float(v) for v in D]}
    bands, skipped = _band_parameters(pairs[:n_model_effects], inputs, std)
    if bands and validation:
        why = band_check(fit, [e.params[0].name for e, _ in pairs[:n_model_effects]
                               if e.band_parameter in bands], validation)
        if why:
            skipped.append(f"{', '.join(sorted(bands))} ({why})")
            bands = {}
    out.update(bands)
    segments = list(getattr(fit, "segments_", None) or [])
    ctx = _Mapping(outputs=outputs, order=_speed_order(outputs),
                   inputs=_input_names(inputs, input_joints),
                   transformed=_transformed_inputs(pairs, inputs,
                                                   segments[0].dt if segments else _PROBE_DT),
                   angle_source=_angle_source(segments))
    terms, not_terms = _effect_terms(pairs[n_model_effects:], ctx)
    skipped = not_terms + skipped
    out["effects"] = json.dumps(terms)
    _check(out)
    return Push(parameters=out, skipped=skipped)


@dataclass(frozen=True)
class _Mapping:
    """How the model's terms become the node's.

    Attributes:
        outputs: the model's output (state) names.
        order: ``order[j]`` the model output of node speed ``j``, or ``None`` (positional;
            the outputs do not include the node's speeds).
        inputs: model input name -> node current name, or ``None`` (the node has no such one).
        transformed: model input name -> label of the effect that transforms it (a pushed
            dead zone does not count: the node applies it too).
        angle_source: :data:`~dvt_identify.effects.position.ANGLE_FROM_POSITION` when every
            fit segment carried the measured angles, else where the angles came from.
    """

    outputs: list[str]
    order: list[int] | None
    inputs: dict[str, str | None]
    transformed: dict[str, str]
    angle_source: str


def _effect_terms(pairs: Sequence[tuple[Effect, Any]], ctx: _Mapping
                  ) -> tuple[list[Term], list[str]]:
    """The admissible effect terms of ``pairs`` (effect, parameters) and a line per effect
    that is not pushed (the node has no such term, its angle or input would be wrong live, or
    the node would refuse its value)."""
    terms: list[Term] = []
    skipped: list[str] = []
    for eff, p in pairs:
        n_skipped = len(skipped)
        _effect_term(eff, p, ctx, terms, skipped)
        if len(skipped) > n_skipped and eff.node_input_transform:
            # not pushed: the node's terms on this input would see the raw current
            ctx.transformed.setdefault(eff.where, eff.label())
    return terms, skipped


def _effect_term(eff: Effect, p: Any, ctx: _Mapping, terms: list[Term], skipped: list[str]
                 ) -> None:
    """Append ``eff``'s node terms to ``terms`` (validated together with those before), or a
    line to ``skipped`` saying why it is not pushed."""
    raw = eff.model_terms(p, ctx.outputs)
    if not raw:
        skipped.append(f"{eff.label()} ({eff.why_no_term(ctx.outputs)})")
        return
    mapped: list[Term] = []
    for term in raw:
        node_term, why = _node_term(term, ctx)
        if node_term is None:
            skipped.append(f"{eff.label()} ({why})")
            return
        mapped.append(node_term)
    n_node = len(SPEED_NAMES) if ctx.order is not None else len(ctx.outputs)
    try:
        checked = validate_effects([*terms, *mapped], n_outputs=n_node)
    except DvtModelError as exc:
        skipped.append(f"{eff.label()} (the model node would refuse it: {exc})")
        return
    if any(term_needs_angle(t) for t in checked[len(terms):]) \
            and ctx.angle_source != ANGLE_FROM_POSITION:
        skipped.append(
            f"{eff.label()} (its angle is the {ctx.angle_source}: its phase is relative "
            "to the recording, the model node's angles are the measured positions; "
            "identify on a recording with positions to push it)")
        return
    terms[:] = checked


def _node_term(term: Term, ctx: _Mapping) -> tuple[Term | None, str]:
    """``term`` over the node's speeds and currents, or ``(None, why not)``."""
    out = dict(term)
    if ctx.order is not None:
        others = [i for i in range(len(ctx.outputs)) if i not in ctx.order]
        for key in ("member", "angle"):
            if key in out:
                vec = [float(v) for v in out[key]]
                extra = [ctx.outputs[i] for i in others if i < len(vec) and vec[i] != 0.0]
                if extra:
                    return None, (f"its {key} acts on {extra}, not only on the model node's "
                                  f"speeds {list(SPEED_NAMES)}")
                out[key] = [vec[i] for i in ctx.order]
        if isinstance(out.get("output"), int) and 0 <= out["output"] < len(ctx.outputs):
            if out["output"] not in ctx.order:
                return None, (f"its output {ctx.outputs[out['output']]!r} is not a speed of "
                              f"the model node ({list(SPEED_NAMES)})")
            out["output"] = ctx.order.index(out["output"])
    name = out.get("input")
    if name:
        if name in ctx.transformed:
            if out.get("kind") == "dead_zone":
                return None, (f"its input {name} is also transformed by "
                              f"{ctx.transformed[name]} in the identified model; the model "
                              "node applies a dead zone to the raw current")
            return None, (f"its input {name} is transformed by {ctx.transformed[name]} in the "
                          "identified model; the model node's term takes the raw current")
        node_name = ctx.inputs.get(str(name))
        if node_name is None:
            return None, (f"input {name!r} is not a current of the model node (expected one "
                          f"of {list(CURRENT_NAMES)}, or input_joints naming it)")
        out["input"] = node_name
    return out, ""


def _speed_order(outputs: Sequence[str]) -> list[int] | None:
    """The model output of each node speed when the outputs include :data:`SPEED_NAMES` (in
    any order, other outputs besides, each name once), else ``None`` (members taken as
    given)."""
    names = list(outputs)
    if any(names.count(n) != 1 for n in SPEED_NAMES):
        return None
    return [names.index(n) for n in SPEED_NAMES]


def _input_names(inputs: Sequence[str], input_joints: Sequence[str] | None
                 ) -> dict[str, str | None]:
    """Model input name -> node current name (``None``: the node has none of that name).

    Raises:
        PushError: ``input_joints`` is not one name per input.
    """
    if input_joints is not None and len(input_joints) != len(inputs):
        raise PushError(f"input_joints: expected {len(inputs)} names (one per input "
                        f"{list(inputs)}), got {list(input_joints)}")
    out: dict[str, str | None] = {}
    for i, name in enumerate(inputs):
        joint = input_joints[i] if input_joints is not None else INPUT_ALIASES.get(name, name)
        out[name] = joint if joint in CURRENT_NAMES else None
    return out


def _transformed_inputs(pairs: Sequence[tuple[Effect, Any]], inputs: Sequence[str],
                        dt: float) -> dict[str, str]:
    """Model inputs that an effect's input transform changes (found by applying the
    transforms in model order to a probe with steps and ramps on every input), with the first
    such effect's label."""
    nu = len(inputs)
    n = 64
    k = np.arange(n, dtype=float)
    u = np.column_stack([np.where(k < n // 4, 0.0, 1.0 + j) + 0.01 * (k % 7) - 0.5 * (k > n // 2)
                         for j in range(nu)]) if nu else np.zeros((n, 0))
    out: dict[str, str] = {}
    for eff, p in pairs:
        if eff.node_input_transform:
            continue  # the node applies it to the raw current too
        with np.errstate(all="ignore"):
            ut = eff.input_transform(np.asarray(p, dtype=float), u, dt)
        if ut is None:
            continue
        changed = ~np.all(np.abs(ut - u) <= 1e-12 * (1.0 + np.abs(u)), axis=0)
        for j in np.flatnonzero(changed):
            out.setdefault(inputs[int(j)], eff.label())
        u = ut
    return out


def _angle_source(segments: Sequence[Any]) -> str:
    """:data:`~dvt_identify.effects.position.ANGLE_FROM_POSITION` when every segment carries
    measured angles (the identifier's own test, :func:`~dvt_identify.effects.position.angle_of`),
    else the source of the first that does not (or why it is not known)."""
    if not segments:
        return "angle of unknown source (the fit keeps no segments)"
    for seg in segments:
        y = np.asarray(seg.y, dtype=float)
        view = SegmentView(float(seg.dt), np.asarray(seg.u, dtype=float), y,
                           getattr(seg, "angles", None))
        source = angle_of(view, np.ones(y.shape[1]))[1]
        if source != ANGLE_FROM_POSITION:
            return source
    return ANGLE_FROM_POSITION


def _band_parameters(pairs: Sequence[tuple[Effect, Any]], inputs: list[str],
                     std: dict[str, float]) -> tuple[dict[str, list[float]], list[str]]:
    """The model node's per-band parameters (``band_parameter`` of the baseline effects on
    ``brake1..3``) that all three bands determined, and a line per parameter not pushed."""
    per_key: dict[str, dict[int, float]] = {}
    vague: dict[str, list[int]] = {}
    for eff, p in pairs:
        key = eff.band_parameter
        band = _band(inputs, eff.index)
        if key is None or band is None:
            continue
        per_key.setdefault(key, {})
        vague.setdefault(key, [])
        value = float(p[0])
        sd = std.get(eff.params[0].name, math.nan)
        if math.isfinite(sd) and value > 0.0 and sd <= MAX_RELATIVE_STD * value:
            per_key[key][band] = value
        else:
            vague[key].append(band)
    out: dict[str, list[float]] = {}
    skipped: list[str] = []
    for key in sorted(per_key):  # band_gain, then band_time_constant
        per_band = per_key[key]
        vals = [per_band.get(b) for b in BANDS]
        if all(v is not None and np.isfinite(v) and v > 0.0 for v in vals):
            out[key] = [float(v) for v in vals if v is not None]
        elif vague[key]:
            skipped.append(f"{key} (band(s) {sorted(vague[key])} not determined by the data: "
                           f"standard deviation above {MAX_RELATIVE_STD:.0%} of the value)")
        elif per_band:
            missing = [b for b, v in zip(BANDS, vals, strict=True) if not (v and v > 0.0)]
            skipped.append(f"{key} (band(s) {missing} not identified)")
    if out and len(out) < len(per_key):
        # a band's gain and lag act together: one or two engagements determine the ratio of
        # the rise (OEFit.band_start), and a fit whose lags the data left open moves its gains
        # along that ridge (measured: gain 51 at lag 0.17 s where the plant has 8 at 0.02 s,
        # with the gain's std 7 %): the half that looks determined is not pushed alone
        for key in sorted(out):
            skipped.append(f"{key} (not pushed without "
                           f"{', '.join(k for k in sorted(per_key) if k not in out)}: a band's "
                           "gain and lag are determined together)")
        out = {}
    return out, skipped


def band_check(fit: OEFit, names: Sequence[str], validation: Sequence[Segment]) -> str:
    """Whether the fitted band values ``names`` (parameters of ``fit.model``) predict the
    held-out ``validation`` segments better than the values the fit started from (each
    parameter's ``initial``: the description's, or the model in use's for a refit started
    from it), every other parameter at its fitted value: what the model node runs when the
    band values are pushed, against what it runs when they are not.

    Each simulation starts from the state that best fits its segment
    (:meth:`~dvt_identify.fit.OEFit.estimate_x0`, or the initial window). The criterion is the
    identifier's validation loss ``det(E^T E / N)`` (:func:`dvt_identify.metrics.figures`).

    Returns:
        ``""`` when the fitted values predict better (or equal the start values), else the
        reason, with both losses.
    """
    model = fit.model
    theta = np.asarray(fit.theta_, float)
    start = theta.copy()
    for name in names:
        i = model.names.index(name)
        start[i] = model.specs[i].initial
    if np.array_equal(start, theta):
        return ""

    def loss(th: np.ndarray) -> float:
        preds = [model.simulate(th, s, fit.estimate_x0(s, th)) for s in validation]
        return figures([s.y for s in validation], preds, 0, model.output_names).loss

    fitted, started = loss(theta), loss(start)
    if math.isfinite(fitted) and fitted < started:
        return ""
    return (f"the fitted band values predict the validation data worse than the start values: "
            f"loss {fitted:.4g} against {started:.4g}")


def _check(values: dict[str, Any]) -> None:
    """Check the whole push as the model node would (:func:`dvt_model.config.check_parameters`).

    Raises:
        PushError: naming the parameter and the value.
    """
    try:
        check_parameters(values)
    except DvtModelError as exc:
        raise PushError(f"cannot push to the model node: it would refuse {exc}") from exc


def _band(inputs: list[str], index: int) -> int | None:
    """Band number 1..3 of input ``index`` when it is named ``brake1..3``, else ``None``."""
    if not 0 <= index < len(inputs):
        return None
    name = inputs[index]
    if name in {f"brake{b}" for b in BANDS}:
        return int(name[-1])
    return None


