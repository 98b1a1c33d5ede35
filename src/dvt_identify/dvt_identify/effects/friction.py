"""Friction and drag effects on a member: Coulomb (with offset), Stribeck, windage and
direction-dependent viscous friction.

Their smooth laws are those of :mod:`dvt_model.friction` (coded as ``(kind, p0, p1)``, compiled
in :mod:`dvt_identify.simloop`); the dry part is applied with a stick rule by the simulation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dvt_identify.effects.base import Array, BuildContext, Effect, ParamSpec, SegmentView, Term
from dvt_identify.errors import DescriptionError
from dvt_identify.simloop import ABS_VISCOUS, STRIBECK, WINDAGE


@dataclass
class CoulombFriction(Effect):
    """Dry friction ``-Fc sign(s)`` with a stick rule, plus a constant ``-offset`` (optional).

    Parameters ``Fc`` (>= 0) and ``offset`` [force unit]. At rest the member stays stuck while the
    force needed to hold it is within ``Fc``. Option ``offset`` (bool, default true).
    Model node: a ``coulomb`` term.
    """

    name = "coulomb_friction"
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, sfx = ctx.force_unit, ctx.suffix
        params: tuple[ParamSpec, ...] = (ParamSpec("Fc" + sfx, 0.0, 0.0, math.inf, fu),)
        if ctx.options.get("offset", True):
            params += (ParamSpec("offset" + sfx, 0.0, -math.inf, math.inf, fu),)
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options=dict(ctx.options))

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        return float(p[0])

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        if len(self.params) < 2:
            return None
        return np.full(seg.u.shape[0], -float(p[1]))

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        term: Term = {"kind": "coulomb", "member": self.member_list(), "Fc": float(p[0])}
        if len(p) > 1:
            term["offset"] = float(p[1])
        return term

    def inadmissible(self, p: Array) -> str | None:
        """Besides the bounds (``Fc >= 0``): the friction in each direction, ``Fc + offset``
        and ``Fc - offset``, must be >= 0 (an offset larger than ``Fc`` would be a friction
        that pushes the member)."""
        why = super().inadmissible(p)
        if why is not None or len(p) < 2:
            return why
        fc, off = float(p[0]), float(p[1])
        sfx = self.params[0].name[2:]
        for label, v in ((f"Fc+{sfx}", fc + off), (f"Fc-{sfx}", fc - off)):
            if v < -1e-9 * max(abs(fc), abs(off), 1e-12):
                return (f"{label} = {self.params[0].name} "
                        f"{'+' if label.startswith('Fc+') else '-'} {self.params[1].name} = "
                        f"{v:.6g} < 0: the friction in each direction must be >= 0 "
                        f"(|{self.params[1].name}| <= {self.params[0].name})")
        return None

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        if len(self.params) < 2:
            return {}
        fc, off = values[self.params[0].name], values[self.params[1].name]
        sfx = self.params[0].name[2:]
        # Force opposing motion: +dir: Fc + offset, -dir: Fc - offset.
        return {f"Fc+{sfx}": fc + off, f"Fc-{sfx}": fc - off}


@dataclass
class StribeckFriction(Effect):
    """Stribeck term ``-Fs exp(-(s/vs)^2) sign(s)``; ``Fs`` adds to the holding capacity at rest.

    Parameters ``Fs`` (>= 0, force unit) and ``vs`` (> 0, member speed unit; scanned; option
    ``vs`` is its start). Model node: a ``stribeck`` term.
    """

    name = "stribeck_friction"
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        vs = ctx.number("vs", 1.0)
        if not vs > 0:
            raise DescriptionError(f"candidate {ctx.name}@{ctx.where}: vs: expected > 0, "
                                   f"got {vs}")
        sfx = ctx.suffix
        params = (ParamSpec("Fs" + sfx, 0.0, 0.0, math.inf, ctx.force_unit),
                  ParamSpec("vs" + sfx, vs, 1e-9, math.inf, ctx.speed_unit, null=vs))
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options=dict(ctx.options))

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (STRIBECK, float(p[0]), max(float(p[1]), 1e-12))

    def breakaway(self, p: Array) -> float:
        return max(float(p[0]), 0.0)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        s_std = float(np.std(seg.y @ self.require_member())) or 1.0
        name = self.params[1].name
        return [(f"{name}={f * s_std:.3g}", {name: f * s_std}) for f in (0.02, 0.05, 0.1, 0.2, 0.5)]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name,)

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        return {"kind": "stribeck", "member": self.member_list(), "Fs": float(p[0]),
                "vs": float(p[1])}


@dataclass
class Windage(Effect):
    """Quadratic drag ``-Cw s |s|``; parameter ``Cw`` (>= 0). Model node: a ``windage`` term."""

    name = "windage"
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, su = ctx.force_unit, ctx.speed_unit
        unit = f"{fu}/({su})^2" if fu and su else ""
        return cls(where=ctx.where, params=(ParamSpec("Cw" + ctx.suffix, 0.0, 0.0, math.inf,
                                                      unit),),
                   member=ctx.member_vector(), options=dict(ctx.options))

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (WINDAGE, float(p[0]), 0.0)

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        return {"kind": "windage", "member": self.member_list(), "Cw": float(p[0])}


@dataclass
class AsymmetricFriction(Effect):
    """Direction-dependent viscous friction ``-dFv |s|`` (project addition to the vocabulary).

    With the structure's viscous coefficient ``Fv`` (option ``viscous``, default ``Fv``):
    ``Fv+ = Fv + dFv``, ``Fv- = Fv - dFv``. Parameter ``dFv`` (any sign).
    """

    name = "asymmetric_friction"
    state_dependent = True
    no_term = "the model node has no direction-dependent viscous term"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, su = ctx.force_unit, ctx.speed_unit
        unit = f"{fu}/({su})" if fu and su else ""
        return cls(where=ctx.where, params=(ParamSpec("dFv" + ctx.suffix, 0.0, -math.inf,
                                                      math.inf, unit),),
                   member=ctx.member_vector(), options=dict(ctx.options))

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (ABS_VISCOUS, float(p[0]), 0.0)

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        fv_name = str(self.options.get("viscous", "Fv"))
        if fv_name not in values:
            return {}
        fv, d = values[fv_name], values[self.params[0].name]
        sfx = self.params[0].name[3:]
        return {f"Fv+{sfx}": fv + d, f"Fv-{sfx}": fv - d}
