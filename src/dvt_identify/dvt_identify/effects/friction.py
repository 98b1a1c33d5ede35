"""Friction and drag effects on a member: Coulomb (with offset), Stribeck, windage and
direction-dependent viscous friction.

Their laws are those of :mod:`dvt_model.laws` (coded as ``(kind, p0, p1, p2)``, compiled
in :mod:`dvt_identify.simloop`). The sign of the dry laws (Coulomb, Stribeck) is exact by
default, applied with a stick rule by the simulation; option ``eps`` (> 0, the member's speed
unit) smooths it to ``tanh(s / eps)`` instead, as the model node and the plant do
(:func:`dvt_model.laws.sign_eps`): the simulated output is then smooth in the parameters,
so the output-error optimum is unique where the stick rule's switching leaves many local ones
(measured on the EMPS drive: 15 random starts reach 15 optima with the stick rule, one with
``eps`` = 1 mm/s). ``eps`` is a property of the law, not a fitted parameter: about 1 % of the
member's typical speed; much smaller brings the switching back.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dvt_identify.effects.base import (
    Array,
    BuildContext,
    Effect,
    ParamSpec,
    SegmentView,
    Term,
    speed_scale,
)
from dvt_identify.errors import DescriptionError
from dvt_model.laws import ABS_VISCOUS, COULOMB, STRIBECK, WINDAGE

STRIBECK_REACH = 3.0
"""Stribeck speeds beyond which a Stribeck term is gone (``exp(-REACH^2)`` of ``Fs``)."""
STRIBECK_BEYOND_SHARE = 0.05
"""Share of the samples a member must spend beyond :data:`STRIBECK_REACH` Stribeck speeds for a
fitted Stribeck curve to be one (the plant's drawn Stribeck curves: 20-50 % of the samples of
``dvt-experiment ident``; the curves bent over the operating range: 0 %)."""


def _eps(ctx: BuildContext) -> float:
    """The ``eps`` option of a dry law (0: the exact sign with the stick rule).

    Raises:
        DescriptionError: not a number >= 0.
    """
    eps = ctx.number("eps", 0.0)
    if not (math.isfinite(eps) and eps >= 0.0):
        raise DescriptionError(f"candidate {ctx.name}@{ctx.where}: eps: expected a speed >= 0 "
                               f"(0: the exact sign), got {eps}")
    return eps


@dataclass
class CoulombFriction(Effect):
    """Dry friction ``-Fc sign(s)`` with a stick rule, plus a constant ``-offset`` (optional).

    Parameters ``Fc`` (>= 0) and ``offset`` [force unit]. At rest the member stays stuck while the
    force needed to hold it is within ``Fc``. Option ``offset`` (bool, default true); option
    ``eps`` (> 0): ``-Fc tanh(s / eps)`` without the stick rule (module docstring).
    Model node: a ``coulomb`` term (with its ``eps`` when smoothed).
    """

    name = "coulomb_friction"
    order = 10
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, sfx = ctx.force_unit, ctx.suffix
        params: tuple[ParamSpec, ...] = (ParamSpec("Fc" + sfx, 0.0, 0.0, math.inf, fu),)
        if ctx.options.get("offset", True):
            params += (ParamSpec("offset" + sfx, 0.0, -math.inf, math.inf, fu),)
        _eps(ctx)
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options=dict(ctx.options))

    @property
    def eps(self) -> float:
        """The sign's smoothing speed (0: exact sign, stick rule)."""
        return float(self.options.get("eps", 0.0) or 0.0)  # type: ignore[arg-type]

    def smooth_law(self, p: Array) -> tuple[int, float, float, float] | None:
        return (COULOMB, float(p[0]), self.eps, 0.0) if self.eps > 0 else None

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        return None if self.eps > 0 else float(p[0])

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        if len(self.params) < 2:
            return None
        return np.full(seg.u.shape[0], -float(p[1]))

    def dry_friction(self, p: Array, seg: SegmentView
                     ) -> tuple[Array | float, Array | float] | None:
        """``Fc + offset`` in the positive direction, ``Fc - offset`` in the negative one."""
        off = float(p[1]) if len(p) > 1 else 0.0
        return float(p[0]) + off, float(p[0]) - off

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        term: Term = {"kind": "coulomb", "member": self.member_list(), "Fc": float(p[0])}
        if len(p) > 1:
            term["offset"] = float(p[1])
        if self.eps > 0:
            term["eps"] = self.eps
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

    Parameters ``Fs`` (>= 0, force unit) and ``vs`` (> 0, member speed unit). ``vs`` has no
    prior: the scorer scans it at fractions of the member's measured speed spread
    (:meth:`variants`, a scale from the data) and the refit starts from the best; option ``vs``
    (default 1 speed unit, a placeholder the scan replaces) is only where it is held before
    the scan. Option ``eps`` (> 0): the sign smoothed to ``tanh(s / eps)``, no break-away at
    rest (module docstring). Model node: a ``stribeck`` term.
    """

    name = "stribeck_friction"
    order = 20
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
        _eps(ctx)
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options=dict(ctx.options))

    @property
    def eps(self) -> float:
        """The sign's smoothing speed (0: exact sign, break-away held by the stick rule)."""
        return float(self.options.get("eps", 0.0) or 0.0)  # type: ignore[arg-type]

    def smooth_law(self, p: Array) -> tuple[int, float, float, float] | None:
        return (STRIBECK, float(p[0]), max(float(p[1]), 1e-12), self.eps)

    def breakaway(self, p: Array) -> float:
        return 0.0 if self.eps > 0 else max(float(p[0]), 0.0)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        s_std = speed_scale(seg, self.require_member())
        name = self.params[1].name
        return [(f"{name}={f * s_std:.3g}", {name: f * s_std}) for f in (0.02, 0.05, 0.1, 0.2, 0.5)
                if f * s_std > 2.0 * self.eps]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name,)

    def inadmissible(self, p: Array) -> str | None:
        """Besides the bounds: with a smoothed sign, the Stribeck speed must exceed ``eps``
        (a hump narrower than the sign's own smoothing is not a Stribeck curve, it is the
        smoothing itself made steeper)."""
        why = super().inadmissible(p)
        if why is not None or not self.eps > 0:
            return why
        vs = float(p[1])
        if vs <= self.eps:
            return (f"{self.params[1].name} = {vs:.3g} {self.params[1].unit} is not above the "
                    f"sign's smoothing eps = {self.eps:g}: no Stribeck curve at that scale")
        return None

    def inadmissible_on(self, p: Array, states: Sequence[Array]) -> str | None:
        """Besides :meth:`inadmissible`: the member must run beyond the Stribeck curve on this
        data. A Stribeck curve is the low-speed hump above the sliding friction; beyond
        :data:`STRIBECK_REACH` Stribeck speeds its term is gone (``exp(-9)``, 0.01 % of
        ``Fs``), and at least :data:`STRIBECK_BEYOND_SHARE` of the samples must be there. A
        fitted ``vs`` the member hardly exceeds is not a Stribeck curve: the law bent over the
        whole operating range, a friction falling with speed that stands in for something
        else (measured: a plant with Coulomb friction only named a "Stribeck" term at
        vs = 134 rad/s on a sun shaft that stays below 402 rad/s throughout)."""
        why = self.inadmissible(p)
        if why is not None or not states:
            return why
        vs = float(p[1])
        c = self.require_member()
        speeds = np.concatenate([np.abs(np.asarray(x, float) @ c) for x in states])
        beyond = float(np.mean(speeds > STRIBECK_REACH * vs)) if speeds.size else 0.0
        if beyond < STRIBECK_BEYOND_SHARE:
            unit = f" {self.params[1].unit}" if self.params[1].unit else ""
            return (f"{self.params[1].name} = {vs:.3g}{unit}: the member runs "
                    f"beyond {STRIBECK_REACH:g} vs = {STRIBECK_REACH * vs:.3g} in "
                    f"{100 * beyond:.3g} % of the samples (< "
                    f"{100 * STRIBECK_BEYOND_SHARE:g} %; its speeds reach "
                    f"{float(np.max(speeds)):.3g}): not a low-speed Stribeck curve but a "
                    "friction bent over the whole operating range")
        return None

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        term: Term = {"kind": "stribeck", "member": self.member_list(), "Fs": float(p[0]),
                      "vs": float(p[1])}
        if self.eps > 0:
            term["eps"] = self.eps
        return term


@dataclass
class Windage(Effect):
    """Quadratic drag ``-Cw s |s|``; parameter ``Cw`` (>= 0). Model node: a ``windage`` term."""

    name = "windage"
    order = 30
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, su = ctx.force_unit, ctx.speed_unit
        unit = f"{fu}/({su})^2" if fu and su else ""
        return cls(where=ctx.where, params=(ParamSpec("Cw" + ctx.suffix, 0.0, 0.0, math.inf,
                                                      unit),),
                   member=ctx.member_vector(), options=dict(ctx.options))

    def smooth_law(self, p: Array) -> tuple[int, float, float, float] | None:
        return (WINDAGE, float(p[0]), 0.0, 0.0)

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        return {"kind": "windage", "member": self.member_list(), "Cw": float(p[0])}


@dataclass
class AsymmetricFriction(Effect):
    """Direction-dependent viscous friction ``-dFv |s|`` (project addition to the vocabulary).

    With the structure's viscous coefficient ``Fv`` (option ``viscous``, default ``Fv``):
    ``Fv+ = Fv + dFv``, ``Fv- = Fv - dFv``. Parameter ``dFv`` (any sign).
    """

    name = "asymmetric_friction"
    order = 100
    state_dependent = True
    no_term = "the model node has no direction-dependent viscous term"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        fu, su = ctx.force_unit, ctx.speed_unit
        unit = f"{fu}/({su})" if fu and su else ""
        return cls(where=ctx.where, params=(ParamSpec("dFv" + ctx.suffix, 0.0, -math.inf,
                                                      math.inf, unit),),
                   member=ctx.member_vector(), options=dict(ctx.options))

    def smooth_law(self, p: Array) -> tuple[int, float, float, float] | None:
        return (ABS_VISCOUS, float(p[0]), 0.0, 0.0)

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        fv_name = str(self.options.get("viscous", "Fv"))
        if fv_name not in values:
            return {}
        fv, d = values[fv_name], values[self.params[0].name]
        sfx = self.params[0].name[3:]
        return {f"Fv+{sfx}": fv + d, f"Fv-{sfx}": fv - d}
