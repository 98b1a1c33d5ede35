"""Band-brake effects: engagement lag, engagement dead time and lock-up (dry friction whose
capacity follows the brake input).

A baseline instance of :class:`BrakeLockup` / :class:`BrakeEngagement` on an input
``brake1..3`` is the model node's band model: its first parameter is named like the node's
parameter it sets (``band_gain``, ``band_time_constant``; with the description's suffix, e.g.
``band_gain_ring1``, ``band_time_constant_brake1``), see :mod:`dvt_identify.push`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dvt_identify.effects.base import Array, BuildContext, Effect, ParamSpec, SegmentView
from dvt_identify.errors import DescriptionError
from dvt_model.brake import lag_mean_factor


@dataclass
class BrakeEngagement(Effect):
    """First-order engagement lag of one input: ``tau u_eff' = u - u_eff`` (exact ZOH steps).

    Parameter ``band_time_constant`` (``tau`` in [0, 10] s); ``u_eff`` starts at ``u[0]``.
    The transformed input held over step ``k`` is ``u_eff``'s *mean* over that step, as the
    model node and the plant hold the band capacity (:func:`dvt_model.brake.capacity_step`):
    its value at the step start lags that mean by about half a step, and a fit then shortened
    ``tau`` by that much (measured with ``scripts/band_lags.py``, docs/identification.md §2).
    As a candidate it adds a second lag stage (which the model node does not have).
    """

    name = "brake_engagement"
    order = 61
    band_parameter = "band_time_constant"
    no_term = "the model node has one engagement lag per band (no second stage)"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("band_time_constant" + ctx.suffix, 0.0,
                                                      0.0, 10.0, "s"),),
                   index=ctx.input_index(), options=dict(ctx.options))

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        tau = float(p[0])
        if tau <= 0.0:
            return None
        from dvt_identify.simloop import first_order_lag

        e = math.exp(-dt / tau)
        out = u.copy()
        col = np.ascontiguousarray(u[:, self.index])
        # u_eff[k+1] = e u_eff[k] + (1 - e) u[k], u_eff[0] = u[0] (compiled recursion); held:
        # the step mean u[k] + (u_eff[k] - u[k]) lag_mean_factor (capacity_step's mean)
        start = first_order_lag(col, e)
        out[:, self.index] = col + (start - col) * lag_mean_factor(dt, tau)
        return out

    def time_constants(self, p: Array) -> tuple[float, ...]:
        return (float(p[0]),) if float(p[0]) > 0 else ()


@dataclass
class EngagementDeadTime(Effect):
    """Dead time of a band's engagement (vocabulary name ``brake_engagement``; description
    option ``dead_time: true``): a wet band first squeezes out its oil film and transmits
    (almost) nothing for ``t_d`` seconds after it is energised, then builds its torque; it
    releases at once. On the (already lagged) brake input ``u``:
    ``u_eff(t) = min(u(t), u(t - t_d))`` (linear interpolation, the first value held before the
    start), which delays every rise by ``t_d`` and no fall. Together with the model's
    first-order engagement lag this gives an S-shaped (delayed) engagement; ``t_d = 0`` is the
    lag alone. Parameter ``td`` in ``[0, max_dead_time]`` s (option, default 0.2 s).

    With the description option ``inputs: [brake1, brake2, ...]`` one ``t_d`` applies to every
    listed input (identical bands in the same oil; ``where`` is then only a label, e.g.
    ``brakes``): ``indices`` holds the input columns, ``index`` is -1 (no single input).
    """

    name = "brake_engagement"
    order = 60
    no_term = "the model node has no engagement dead time"
    indices: tuple[int, ...] = ()

    @classmethod
    def accepts(cls, ctx: BuildContext) -> bool:
        return bool(ctx.options.get("dead_time"))

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        what = f"candidate brake_engagement@{ctx.where} (dead_time)"
        tmax = ctx.number("max_dead_time", 0.2)
        if not tmax > 0:
            raise DescriptionError(f"{what}: max_dead_time must be > 0 s, got {tmax}")
        shared = ctx.options.get("inputs")  # one dead time for several bands (same oil, bands)
        if shared is None:
            idx: tuple[int, ...] = (ctx.input_index(),)
        elif isinstance(shared, list | tuple) and shared:
            idx = tuple(ctx.input_index(str(n)) for n in shared)
            if len(set(idx)) != len(idx):
                raise DescriptionError(f"{what}: inputs: duplicate names in {list(shared)}")
        else:
            raise DescriptionError(f"{what}: inputs: expected a non-empty list of input names, "
                                   f"got {shared!r}")
        return cls(where=ctx.where, index=idx[0] if len(idx) == 1 else -1, indices=idx,
                   options=dict(ctx.options),
                   params=(ParamSpec("td" + ctx.suffix, 0.0, 0.0, tmax, "s", step=5e-3),))

    def label(self) -> str:
        """``brake_engagement@where(dead_time)``: distinct from the second lag stage."""
        return f"{self.name}@{self.where}(dead_time)"

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        td = float(p[0])
        if td <= 0.0:
            return None
        cols = self.indices or (self.index,)
        n = u.shape[0]
        k = np.arange(n, dtype=float)
        out = u.copy()
        for j in cols:
            col = u[:, j]
            late = np.interp(k - td / dt, k, col)
            out[:, j] = np.minimum(col, late)
        return out


@dataclass
class BrakeLockup(Effect):
    """Brake on a member: dry friction with capacity ``band_gain * max(u_brake, 0)`` and a
    stick rule.

    The member (``c`` over the states) locks when its speed reaches zero while the holding force
    is within the capacity. Parameter ``band_gain`` (>= 0, force unit per brake-input unit, e.g.
    N m/A); option ``input``: the brake input.
    """

    name = "brake_lockup"
    order = 70
    state_dependent = True
    band_parameter = "band_gain"
    no_term = "the model node's band model takes the brake gains (band_gain), not a term"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        brake = str(ctx.options.get("input", ""))
        return cls(where=ctx.where, params=(ParamSpec("band_gain" + ctx.suffix, 0.0, 0.0,
                                                      math.inf, f"{ctx.force_unit}/input unit"),),
                   member=ctx.member_vector(), index=ctx.input_index(brake),
                   options=dict(ctx.options))

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        return np.asarray(float(p[0]) * np.clip(seg.u[:, self.index], 0.0, None))
