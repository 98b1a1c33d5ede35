"""A periodic disturbance force phase-locked to a member's measured angle (or to time)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dvt_identify.effects.base import (
    Array,
    BuildContext,
    Effect,
    ParamSpec,
    ScoringContext,
    SegmentView,
    numbers_option,
)
from dvt_identify.effects.position import angle_of, cell_mean_trig, mesh_orders
from dvt_identify.errors import DescriptionError


@dataclass
class PeriodicDisturbance(Effect):
    """Force ``a cos(k theta) + b sin(k theta)`` phase-locked to the measured member angle
    ``theta`` (order ``k``, e.g. 1 per shaft revolution, tooth count for a mesh), or to time
    (``theta = 2 pi t``, ``k`` in Hz) when the option ``clock`` is ``time``.

    Parameters ``a``, ``b`` (force unit) and ``order`` (>= 0, fixed during a fit; the scorer
    scans the listed ``orders``). The option ``mesh_orders: true`` adds each stage's sun teeth of
    the parameter set ``params`` (default ``physical``; :mod:`dvt_model.params`) to the orders:
    the mesh orders per sun-shaft revolution. ``orders`` or ``mesh_orders`` is required. The
    force held over a step is its mean over the step's angle interval
    (:func:`dvt_identify.effects.position.cell_mean_trig`: a ripple faster than the step does
    not alias). The model node has no periodic term.
    """

    name = "periodic_disturbance"
    no_term = "the model node has no periodic disturbance term"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        orders = ctx.numbers("orders")
        if ctx.options.get("mesh_orders"):
            orders = list(dict.fromkeys(
                [*orders, *mesh_orders(str(ctx.options.get("params", "physical")))]))
        if not orders:
            raise DescriptionError(f"candidate periodic_disturbance@{ctx.where}: needs 'orders' "
                                   "(per member revolution/unit, or Hz with clock: time) or "
                                   "mesh_orders: true")
        k0 = orders[0]
        fu, sfx, inf = ctx.force_unit, ctx.suffix, math.inf
        params = (ParamSpec("a" + sfx, 0.0, -inf, inf, fu),
                  ParamSpec("b" + sfx, 0.0, -inf, inf, fu),
                  ParamSpec("order" + sfx, k0, 0.0, inf, "1", null=k0))
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options={**ctx.options, "orders": orders})

    def _orders(self) -> list[float]:
        return numbers_option(self.options, "orders", [float(self.params[2].initial)],
                              f"candidate {self.label()}")

    def _phase(self, seg: SegmentView) -> Array:
        if self.options.get("clock") == "time":
            return np.asarray(2.0 * math.pi * seg.dt * np.arange(seg.u.shape[0]))
        return angle_of(seg, self.require_member())[0]

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        a, b, k = float(p[0]), float(p[1]), float(p[2])
        c, s = cell_mean_trig(self._phase(seg), k)
        return np.asarray(a * c + b * s)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        name = self.params[2].name
        return [(f"{name}={k:g}", {name: k}) for k in self._orders()]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name, self.params[1].name)

    def fixed_names(self) -> tuple[str, ...]:
        """The order is held fixed while fitting (scanned by the scorer)."""
        return (self.params[2].name,)

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The order spectrum of the residual force on the member (first segment)."""
        if self.member is None:
            return {}, {}
        spec = self.order_spectrum(ctx.member_residual(self.member), ctx.views[0])
        return {"order_spectrum": spec}, {}

    def order_spectrum(self, residual: Array, seg: SegmentView, n_grid: int = 200
                       ) -> dict[str, object]:
        """Amplitude of the residual's best-fitting ``cos/sin(k theta)`` pair for the listed
        orders and on a grid up to 1.5x the largest; the ratio to the grid's median is the
        evidence that a listed order stands out.

        Args:
            residual: weighted residual of the member's output(s), shape (N,).
        """
        orders = self._orders()
        theta = self._phase(seg)
        kmax = 1.5 * max(orders)
        grid = np.linspace(kmax / n_grid, kmax, n_grid)

        def amp(k: float) -> float:
            X = np.column_stack([np.cos(k * theta), np.sin(k * theta)])
            coef, *_ = np.linalg.lstsq(X, residual, rcond=None)
            return float(np.hypot(coef[0], coef[1]))
        base = float(np.median([amp(k) for k in grid])) or 1e-300
        listed = {f"{k:g}": {"amplitude": amp(k), "ratio_to_median": amp(k) / base}
                  for k in orders}
        return {"orders": listed, "grid_median_amplitude": base,
                "grid": [float(grid[0]), float(grid[-1]), n_grid]}
