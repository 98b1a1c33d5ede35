"""Map an identified model onto the live model node's parameters (pure, no rclpy).

The DVT structure (``descriptions/dvt.yaml``: mechanical, symmetric M and D entries
``M11, M12, M22, D11, D12, D22``) maps to the model node's ``M`` and ``D``; accepted force
effects map to its ``effects`` JSON (:mod:`dvt_model.terms`): Coulomb (with offset), Stribeck,
windage; measurement delay and sensor gain map to output transforms. Effects the model node
cannot represent (backlash, an extra brake-engagement stage or dead time) are listed in
``skipped`` and not pushed. The baseline's band brakes (``brake_lockup`` gains [N m/A] and
``brake_engagement`` time constants [s] on the inputs ``brake1..3``) map to the node's
``brake_gain`` and ``brake_time_constant`` when all three bands were identified and the data
determined each value (relative standard deviation at most :data:`MAX_RELATIVE_STD`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dvt_identify.effects import (
    BrakeEngagement,
    BrakeLockup,
    CoulombFriction,
    MeasurementDelay,
    SensorGain,
    StribeckFriction,
    Windage,
)
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.loop import Stage

MAX_RELATIVE_STD = 0.5
"""A band parameter whose standard deviation exceeds this fraction of its value (or is not
finite, e.g. at a bound) is not pushed: the data did not determine it."""


@dataclass(frozen=True)
class Push:
    """Parameters for ``dvt_model_node`` (name -> value) and what could not be pushed."""

    parameters: dict[str, Any]
    skipped: list[str] = field(default_factory=list)


def model_node_parameters(stage: Stage, n_model_effects: int = 0) -> Push:
    """Build the model node's parameters from a fitted stage.

    Args:
        stage: the final (or baseline) stage of an identification.
        n_model_effects: how many leading effects belong to the baseline model (the bands);
            they are represented by the node's own brake model and not pushed.

    Raises:
        DvtIdentifyError: the structure has no M and D entries (not the DVT mechanical one).
    """
    values = stage.parameters()
    try:
        M = [values["M11"], values["M12"], values["M12"], values["M22"]]
        D = [values["D11"], values["D12"], values["D12"], values["D22"]]
    except KeyError as exc:
        raise DvtIdentifyError(f"cannot push to the model node: the structure has no {exc} "
                               "(expected the DVT mechanical structure with M11..D22)") from exc
    terms: list[dict[str, Any]] = []
    skipped: list[str] = []
    fit = stage.fit
    params = fit.model.effect_params(fit.theta_)
    outputs = list(fit.model.structure.state_names)
    inputs = list(fit.model.structure.input_names)
    std = fit.parameter_std()
    bands: dict[str, dict[int, float]] = {"brake_gain": {}, "brake_time_constant": {}}
    vague: dict[str, list[int]] = {"brake_gain": [], "brake_time_constant": []}
    for k, (eff, p) in enumerate(zip(fit.model.effects, params, strict=True)):
        if k < n_model_effects:
            band = _band(inputs, eff.index)
            key = ("brake_gain" if isinstance(eff, BrakeLockup) else "brake_time_constant"
                   if isinstance(eff, BrakeEngagement) else None)
            if band is not None and key is not None:
                value = float(p[0])
                sd = std.get(eff.params[0].name, math.nan)
                if math.isfinite(sd) and value > 0.0 and sd <= MAX_RELATIVE_STD * value:
                    bands[key][band] = value
                else:
                    vague[key].append(band)
            continue
        member = None if eff.member is None else [float(v) for v in eff.member]
        if isinstance(eff, CoulombFriction):
            entry: dict[str, Any] = {"kind": "coulomb", "member": member, "Fc": float(p[0])}
            if len(p) > 1:
                entry["offset"] = float(p[1])
            terms.append(entry)
        elif isinstance(eff, StribeckFriction):
            terms.append({"kind": "stribeck", "member": member, "Fs": float(p[0]),
                          "vs": float(p[1])})
        elif isinstance(eff, Windage):
            terms.append({"kind": "windage", "member": member, "Cw": float(p[0])})
        elif isinstance(eff, MeasurementDelay):
            terms.append({"kind": "delay", "seconds": float(p[0])})
        elif isinstance(eff, SensorGain) and eff.where in outputs:
            terms.append({"kind": "gain", "output": outputs.index(eff.where),
                          "gain": float(p[0])})
        else:
            skipped.append(eff.label())
    out: dict[str, Any] = {"M": [float(v) for v in M], "D": [float(v) for v in D],
                           "effects": json.dumps(terms)}
    for key, per_band in bands.items():
        vals = [per_band.get(b) for b in (1, 2, 3)]
        if all(v is not None and np.isfinite(v) and v > 0.0 for v in vals):
            out[key] = [float(v) for v in vals if v is not None]
        elif vague[key]:
            skipped.append(f"{key} (band(s) {sorted(vague[key])} not determined by the data: "
                           f"standard deviation above {MAX_RELATIVE_STD:.0%} of the value)")
        elif per_band:
            missing = [b for b, v in zip((1, 2, 3), vals, strict=True) if not (v and v > 0.0)]
            skipped.append(f"{key} (band(s) {missing} not identified)")
    if not np.all(np.isfinite(out["M"] + out["D"])):
        raise DvtIdentifyError(f"cannot push non-finite M/D: {out['M']} {out['D']}")
    return Push(parameters=out, skipped=skipped)


def _band(inputs: list[str], index: int) -> int | None:
    """Band number 1..3 of input ``index`` when it is named ``brake1..3``, else ``None``."""
    if not 0 <= index < len(inputs):
        return None
    name = inputs[index]
    if name in ("brake1", "brake2", "brake3"):
        return int(name[-1])
    return None
