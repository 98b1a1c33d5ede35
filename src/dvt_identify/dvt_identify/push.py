"""Map an identified model onto the live model node's parameters (pure, no rclpy).

The DVT structure (``descriptions/dvt.yaml``: mechanical, symmetric M and D entries
``M11, M12, M22, D11, D12, D22``) maps to the model node's ``M`` and ``D``; each accepted
effect maps to the term of the node's ``effects`` JSON that it declares
(:meth:`dvt_identify.effects.Effect.model_term`; Coulomb with offset, Stribeck, windage,
measurement delay, sensor gain). Effects the model node cannot represent (backlash, an extra
brake-engagement stage or dead time, ...) or whose values it would refuse are listed in
``skipped`` with the reason and not pushed. The baseline's band brakes (``brake_lockup``
``band_gain_*`` [N m/A] and ``brake_engagement`` ``band_time_constant_*`` [s] on the inputs
``brake1..3``) map to the node's ``band_gain`` and ``band_time_constant`` (the name each
effect declares as its ``band_parameter``) when all three bands were identified and the data
determined each value (relative standard deviation at most :data:`MAX_RELATIVE_STD`).

Every term is checked with :func:`dvt_model.contract.validate_term` /
:func:`~dvt_model.contract.validate_effects` and the whole push with
:func:`dvt_model.config.check_parameters`: the push cannot write what the node would refuse.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dvt_identify.effects import Effect, Term
from dvt_identify.errors import PushError
from dvt_identify.loop import Stage
from dvt_model.config import check_parameters
from dvt_model.contract import validate_effects
from dvt_model.errors import DvtModelError

MAX_RELATIVE_STD = 0.5
"""A band parameter whose standard deviation exceeds this fraction of its value (or is not
finite, e.g. at a bound) is not pushed: the data did not determine it."""

BANDS = (1, 2, 3)
"""The band numbers of the model node's per-band parameters (inputs ``brake1..3``)."""


@dataclass(frozen=True)
class Push:
    """Parameters for ``dvt_model_node`` (name -> value) and what could not be pushed (one
    line each, with the reason)."""

    parameters: dict[str, Any]
    skipped: list[str] = field(default_factory=list)


def model_node_parameters(stage: Stage, n_model_effects: int = 0) -> Push:
    """Build the model node's parameters from a fitted stage.

    Args:
        stage: the final (or baseline) stage of an identification.
        n_model_effects: how many leading effects belong to the baseline model (the bands);
            they are represented by the node's own band model (``band_gain``,
            ``band_time_constant``), not by effect terms.

    Raises:
        PushError: the structure has no M and D entries (not the DVT mechanical one), or the
            model node would refuse a value (naming the parameter and the value).
    """
    values = stage.parameters()
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
    out.update(bands)
    terms, not_terms = _effect_terms(pairs[n_model_effects:], outputs)
    skipped = not_terms + skipped
    out["effects"] = json.dumps(terms)
    _check(out)
    return Push(parameters=out, skipped=skipped)


def _effect_terms(pairs: Sequence[tuple[Effect, Any]], outputs: list[str]
                  ) -> tuple[list[Term], list[str]]:
    """The admissible effect terms of ``pairs`` (effect, parameters) and a line per effect
    that is not pushed (the node has no such term, or would refuse its value)."""
    terms: list[Term] = []
    skipped: list[str] = []
    for eff, p in pairs:
        term = eff.model_term(p, outputs)
        if term is None:
            skipped.append(f"{eff.label()} ({eff.why_no_term(outputs)})")
            continue
        try:
            checked = validate_effects([*terms, term], n_outputs=len(outputs))
        except DvtModelError as exc:
            skipped.append(f"{eff.label()} (the model node would refuse it: {exc})")
            continue
        terms.append(checked[-1])
    return terms, skipped


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
    return out, skipped


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
