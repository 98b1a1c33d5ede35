"""Backlash (vocabulary word ``backlash``): a dead zone on an input, lost motion between a member
and its speed sensor, or play in a compliant spline to a load (option ``compliant: true``).

The registry tries :class:`CompliantOutputBacklash`, then :class:`OutputBacklash` (``where`` a
state), then :class:`Backlash` (``where`` an input). The laws are :mod:`dvt_model.backlash`'s,
which the model node's terms use too: a dead zone is pushed as a ``dead_zone`` term, play on an
output as ``play``, the compliant spline as ``spline_play``.
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
    numbers_option,
)
from dvt_identify.errors import DescriptionError
from dvt_identify.simloop import spline_load
from dvt_model.backlash import dead_zone, play, spline_substeps

SECANT_SHARE = 0.3
"""The compliant play's difference step in the fit, as a share of the parameter's value.

The load rattling in the play is chaotic: the output's difference along a step ``h`` is the
play's mean effect plus the divergence of two rattles, which does not shrink with ``h`` (a step
of 1e-9 moved the load speed by O(1) a few seconds later), so the secant carries a part that
grows as ``1/h`` and the fit's covariance shrinks with the step. The share is where the gap's
std stops growing with it (``ident-backlash``: 0.03 -> 0.00009 rad, 0.1 -> 0.0002, 0.2 ->
0.00037, 0.3 -> 0.00043, 0.5 -> 0.00042, 1.0 -> 0.00056; docs/identification.md)."""


def _not_an_output(where: str, outputs: Sequence[str]) -> str:
    return f"{where!r} is not one of the model's outputs {list(outputs)}"


@dataclass
class Backlash(Effect):
    """Dead zone of half-width ``delta`` on one input: ``u -> u - clip(u, -delta, delta)``.

    Models transmission backlash/lost motion seen from the input side (no position state is
    needed). Parameter ``delta`` (>= 0, input unit). Model node: a ``dead_zone`` term on the
    input's current (the push maps the input name).
    """

    name = "backlash"
    order = 42
    node_input_transform = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("delta" + ctx.suffix, 0.0, 0.0, math.inf,
                                                      "input unit"),),
                   index=ctx.input_index(), options=dict(ctx.options))

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        out = u.copy()
        out[:, self.index] = dead_zone(u[:, self.index], max(float(p[0]), 0.0))
        return out

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        return {"kind": "dead_zone", "input": self.where, "delta": max(float(p[0]), 0.0)}


@dataclass
class OutputBacklash(Effect):
    """Lost motion of half-width ``delta`` between a member and its speed sensor (play
    operator on the integrated output): after a reversal the sensed shaft stands still until
    the gap is crossed. ``theta_out`` follows ``theta = integral of x_j`` within
    ``[theta - delta, theta + delta]``; the measured speed is ``d theta_out / dt``.
    Parameter ``delta`` (in [0, 1], rad or m). Model node: a ``play`` term on that output.
    """

    name = "backlash"
    order = 41

    @classmethod
    def accepts(cls, ctx: BuildContext) -> bool:
        return ctx.at_state

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        su = ctx.speed_unit
        unit = su.split("/")[0] if su else ""
        return cls(where=ctx.where, params=(ParamSpec("delta" + ctx.suffix, 0.0, 0.0, 1.0, unit,
                                                      step=2e-3),),
                   index=ctx.state_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        d = max(float(p[0]), 0.0)
        if d == 0.0:
            return None
        j = self.index
        theta = np.concatenate([[0.0], np.cumsum(y[:-1, j]) * dt])
        out_pos = np.empty_like(theta)
        pos = 0.0
        for k, th in enumerate(theta.tolist()):
            pos = play(pos, th, d)
            out_pos[k] = pos
        out = y.copy()
        speed = np.empty(y.shape[0])
        speed[:-1] = np.diff(out_pos) / dt
        speed[-1] = y[-1, j] if abs(theta[-1] - out_pos[-1]) >= d else 0.0
        out[:, j] = speed
        return out

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        if self.where not in outputs:
            return None
        return {"kind": "play", "output": list(outputs).index(self.where),
                "delta": max(float(p[0]), 0.0)}

    def why_no_term(self, outputs: Sequence[str]) -> str:
        return _not_an_output(self.where, outputs)


@dataclass
class CompliantOutputBacklash(Effect):
    """Free play in a compliant spline between a member and the shaft that carries its speed
    sensor and a load (vocabulary name ``backlash``; description option ``compliant: true``).

    The sensed shaft (load speed ``w_L``) is driven one way by the model's member speed ``w``
    through the play ``gap`` and a spring-damper contact: with the twist ``z = theta - theta_L``,
    ``w_L' = max(0, wn^2 (z - gap/2) + 2 zeta wn (w - w_L))`` for ``z > gap/2`` (mirrored for
    ``z < -gap/2``, nothing inside the gap), ``z' = w - w_L``; the output is ``w_L`` averaged over
    the sample interval centred on the sample (the zero-phase anti-alias filter of decimated
    data leaves no more of a sub-sample impact transient). ``wn`` is the contact frequency of the
    load on the spline (``sqrt(k / J_load)``) and ``zeta`` its damping ratio. The load's
    inertia and drag load the member at low frequency like a rigid part of it, which the fitted
    structure absorbs; the reaction of the impacts on the member is not modelled (one-way).

    Parameters: ``gap`` [rad, total play, in [0, 1]; 0 = rigid: the effect vanishes, compliance
    included], ``wn`` [rad/s, in [10, 1e4]] and ``zeta`` [1, in [1e-3, 2]] (shape parameters,
    scanned by the scorer; options ``wn``, ``zeta`` are their starts). The effect is not
    differentiable at ``gap = 0`` (an impact oscillator), so the scorer's gap regressor is the
    secant to a probe play (option ``probe_gap``, default 0.01 rad). Model node: a
    ``spline_play`` term on that output (the load speed at the sample instant,
    :class:`dvt_model.backlash.OutputSpline`).
    """

    name = "backlash"
    order = 40
    chaotic_output = True

    @classmethod
    def accepts(cls, ctx: BuildContext) -> bool:
        return ctx.at_state and bool(ctx.options.get("compliant"))

    def secant_step(self, loc: int, value: float) -> float | None:
        """:data:`SECANT_SHARE` of the value (of the probe play for a gap below it), times the
        option ``secant_scale`` (default 1: :meth:`dvt_identify.fit.OEFit.add_landing_spread`
        refits with others)."""
        floor = (self.params[0].step or 0.0) if loc == 0 else 0.0
        scale = self.options.get("secant_scale", 1.0)
        return SECANT_SHARE * float(scale) * max(abs(value), floor) or None  # type: ignore[arg-type]

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        su, sfx = ctx.speed_unit, ctx.suffix
        unit = su.split("/")[0] if su else ""
        # starts only (generic: a steel spline to a small load, lightly damped): the scorer
        # scans wn_scan x zeta_scan x gap_scan (variants) and the refit starts from the best
        wn0 = ctx.number("wn", 400.0)
        z0 = ctx.number("zeta", 0.15)
        probe = ctx.number("probe_gap", 0.01)
        scale = ctx.number("secant_scale", 1.0)
        if not (wn0 > 0 and z0 > 0 and probe > 0 and scale > 0):
            raise DescriptionError(f"candidate backlash@{ctx.where} (compliant): wn, zeta, "
                                   f"probe_gap and secant_scale must be > 0, got {wn0}, {z0}, "
                                   f"{probe}, {scale}")
        return cls(where=ctx.where, index=ctx.state_index(), options=dict(ctx.options),
                   params=(ParamSpec("gap" + sfx, 0.0, 0.0, 1.0, unit, step=probe),
                           ParamSpec("wn" + sfx, wn0, 10.0, 1e4,
                                     f"1/{su.split('/')[-1]}" if su else "", null=wn0),
                           ParamSpec("zeta" + sfx, z0, 1e-3, 2.0, "1", null=z0)))

    def label(self) -> str:
        """``backlash@where(compliant)``: distinct from the rigid play on the same output."""
        return f"{self.name}@{self.where}(compliant)"

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        gap, wn, zeta = max(float(p[0]), 0.0), max(float(p[1]), 1e-9), max(float(p[2]), 0.0)
        if gap == 0.0:
            return None
        out = y.copy()
        out[:, self.index] = spline_load(y[:, self.index], dt, 0.5 * gap, wn * wn,
                                          2.0 * zeta * wn, spline_substeps(dt, wn))
        return out

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        if self.where not in outputs:
            return None
        return {"kind": "spline_play", "output": list(outputs).index(self.where),
                "gap": max(float(p[0]), 0.0), "wn": float(p[1]), "zeta": float(p[2])}

    def why_no_term(self, outputs: Sequence[str]) -> str:
        return _not_an_output(self.where, outputs)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        """Grid of contact frequency ``wn`` (below the Nyquist frequency of ``seg``: the data
        cannot show a faster contact), damping ratio and probe play (the gap regressor's
        secant step); options ``wn_scan``, ``zeta_scan``, ``gap_scan``."""
        g_name, wn_name, z_name = (s.name for s in self.params)
        what = f"candidate {self.label()}"
        def grid(key: str, default: tuple[float, ...]) -> list[float]:
            return numbers_option(self.options, key, default, what)
        nyq = math.pi / seg.dt
        return [(f"{g_name}={g:g},{wn_name}={wn:g},{z_name}={z:g}",
                 {g_name: g, wn_name: wn, z_name: z})
                for g in grid("gap_scan", (0.005, 0.01, 0.02, 0.04))
                for wn in grid("wn_scan", (150.0, 250.0, 350.0, 450.0, 600.0, 1000.0)) if wn < nyq
                for z in grid("zeta_scan", (0.05, 0.1, 0.2, 0.4))]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name,)

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        wn = values.get(self.params[1].name)
        if wn is None:
            return {}
        return {f"fn{self.params[1].name[2:]}": wn / (2.0 * math.pi)}
