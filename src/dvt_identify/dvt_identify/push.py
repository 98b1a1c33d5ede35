"""Map an identified model onto the live model node's parameters (pure, no rclpy).

The DVT structure (``descriptions/dvt.yaml``: mechanical, symmetric M and D entries
``M11, M12, M22, D11, D12, D22``) maps to the model node's ``M`` and ``D``; accepted force
effects map to its ``effects`` JSON (:mod:`dvt_model.terms`): Coulomb (with offset), Stribeck,
windage; measurement delay and sensor gain map to output transforms. Effects the model node
cannot represent (backlash on an input, an extra brake-engagement stage) are listed in
``skipped`` and not pushed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dvt_identify.effects import (
    CoulombFriction,
    MeasurementDelay,
    SensorGain,
    StribeckFriction,
    Windage,
)
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.loop import Stage


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
    for k, (eff, p) in enumerate(zip(fit.model.effects, params, strict=True)):
        if k < n_model_effects:
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
    if not np.all(np.isfinite(out["M"] + out["D"])):
        raise DvtIdentifyError(f"cannot push non-finite M/D: {out['M']} {out['D']}")
    return Push(parameters=out, skipped=skipped)
