"""A periodic disturbance force phase-locked to a member's measured angle (or to time)."""

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
    ScoringContext,
    SegmentView,
    Term,
    numbers_option,
)
from dvt_identify.effects.position import (
    cell_mean_trig,
    member_motion,
    mesh_members,
    mesh_orders,
)
from dvt_identify.errors import DescriptionError


@dataclass
class PeriodicDisturbance(Effect):
    """Force ``a cos(k theta) + b sin(k theta)`` phase-locked to the measured member angle
    ``theta`` (order ``k``, e.g. 1 per shaft revolution, tooth count for a mesh), or to time
    (``theta = 2 pi t``, ``k`` in Hz) when the option ``clock`` is ``time``.

    Parameters ``a``, ``b`` (force unit) and ``order`` (>= 0, fixed during a fit; the scorer
    scans the listed ``orders``). The option ``mesh_orders: true`` adds each stage's sun teeth of
    the parameter set ``params`` (default ``physical``; :mod:`dvt_model.params`) to the orders:
    the mesh orders per sun-shaft revolution (exact only while the carriers stand still). The
    option ``mesh_stages: true`` adds variants phase-locked to each stage's true mesh angle:
    the sun relative to its carrier, ``Z_sun_k (theta_sun - theta_carrier_k)`` with the
    member form ``sun - carrier_k`` of :mod:`dvt_model.kinematics`
    (:func:`~dvt_identify.effects.position.mesh_members`; option ``mesh_speeds`` names the
    states of the sun and carrier-3 speeds, default ``[sun_shaft, carrier3]``); it adds the
    fixed parameter ``mesh_stage`` (0: the
    member's own angle at a listed order, ``k``: stage ``k``'s mesh angle at order
    ``Z_sun_k``) that the scorer scans with the orders. The force still acts on the member.
    ``orders``, ``mesh_orders`` or ``mesh_stages`` is required. The force held over a step
    is its mean over the step's angle interval
    (:func:`dvt_identify.effects.position.cell_mean_trig`: a ripple faster than the step does
    not alias). Model node: an ``angle_periodic`` term (not when clocked on time), pushed
    only when the angle was the measured position (:mod:`dvt_identify.push`).
    """

    name = "periodic_disturbance"
    order = 90
    no_term = ("clocked on time (clock: time): the model node's periodic term "
               "(angle_periodic) is phase-locked to an angle")

    def reads_motion(self) -> bool:
        """Unless clocked on time: the member's measured angle."""
        return self.options.get("clock") != "time"

    def depends_on_angle(self) -> bool:
        """Unless clocked on time (``clock: time``)."""
        return self.options.get("clock") != "time"

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        """An ``angle_periodic`` term on the member, its ``angle`` the member's or (a
        ``mesh_stage`` k > 0) stage k's mesh angle; ``None`` when clocked on time."""
        if self.options.get("clock") == "time":
            return None
        term: Term = {"kind": "angle_periodic", "member": self.member_list(),
                      "a": float(p[0]), "b": float(p[1]), "order": float(p[2])}
        stage = self._stage(p)
        if stage:
            term["angle"] = [float(v) for v in self._mesh_form(stage)]
        return term

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        orders = ctx.numbers("orders")
        if ctx.options.get("mesh_orders"):
            orders = list(dict.fromkeys(
                [*orders, *mesh_orders(str(ctx.options.get("params", "physical")))]))
        what = f"candidate periodic_disturbance@{ctx.where}"
        stages = mesh_members(ctx) if ctx.options.get("mesh_stages") else []
        if stages and ctx.options.get("clock") == "time":
            raise DescriptionError(f"{what}: mesh_stages needs the member angles, not clock: "
                                   "time")
        if not orders and not stages:
            raise DescriptionError(f"{what}: needs 'orders' (per member revolution/unit, or Hz "
                                   "with clock: time), mesh_orders: true or mesh_stages: true")
        k0 = orders[0] if orders else stages[0][0].teeth
        fu, sfx, inf = ctx.force_unit, ctx.suffix, math.inf
        params: tuple[ParamSpec, ...] = (
            ParamSpec("a" + sfx, 0.0, -inf, inf, fu), ParamSpec("b" + sfx, 0.0, -inf, inf, fu),
            ParamSpec("order" + sfx, k0, 0.0, inf, "1", null=k0))
        options: dict[str, object] = {**ctx.options, "orders": orders}
        if stages:
            s0 = 0.0 if orders else 1.0
            params += (ParamSpec("mesh_stage" + sfx, s0, 0.0, float(len(stages)), "1",
                                 null=s0),)
            options["mesh_teeth"] = [ms.teeth for ms, _ in stages]
            options["mesh_forms"] = [[float(v) for v in c] for _, c in stages]
        return cls(where=ctx.where, params=params, member=ctx.member_vector(), options=options)

    def _orders(self) -> list[float]:
        return numbers_option(self.options, "orders", [float(self.params[2].initial)],
                              f"candidate {self.label()}")

    def _mesh_form(self, stage: int) -> Array:
        """Stage ``stage``'s relative-angle form over the states, shape (nx,) (option
        ``mesh_forms``, built from ``mesh_stages``)."""
        forms = self.options.get("mesh_forms")
        if not isinstance(forms, list) or not 1 <= stage <= len(forms):
            raise DescriptionError(f"candidate {self.label()}: mesh_stage {stage}: no such "
                                   f"stage (built with mesh_stages: true it has "
                                   f"{len(forms) if isinstance(forms, list) else 0})")
        return np.asarray(forms[stage - 1], dtype=float)

    def _phase(self, seg: SegmentView, stage: int = 0) -> Array:
        """The phase angle, shape (N,): time, the member's angle (``stage`` 0) or stage
        ``stage``'s mesh angle ``theta_sun - theta_carrier_k`` (before the order)."""
        if self.options.get("clock") == "time":
            return np.asarray(2.0 * math.pi * seg.dt * np.arange(seg.u.shape[0]))
        member = self.require_member() if stage == 0 else self._mesh_form(stage)
        return member_motion(seg, member, self.readout)[1]

    @staticmethod
    def _stage(p: Array) -> int:
        """The ``mesh_stage`` parameter (0 without one)."""
        return round(float(p[3])) if len(p) > 3 else 0

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        a, b, k = float(p[0]), float(p[1]), float(p[2])
        c, s = cell_mean_trig(self._phase(seg, self._stage(p)), k)
        return np.asarray(a * c + b * s)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        name = self.params[2].name
        if len(self.params) < 4:
            return [(f"{name}={k:g}", {name: k}) for k in self._orders()]
        stage = self.params[3].name
        teeth = numbers_option(self.options, "mesh_teeth", [], f"candidate {self.label()}")
        listed = numbers_option(self.options, "orders", [], f"candidate {self.label()}")
        return ([(f"{name}={k:g}", {name: k, stage: 0.0}) for k in listed]
                + [(f"{name}={z:g} on the stage-{i} mesh angle", {name: z, stage: float(i)})
                   for i, z in enumerate(teeth, start=1)])

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name, self.params[1].name)

    def fixed_names(self) -> tuple[str, ...]:
        """The order (and the mesh stage) is held fixed while fitting (scanned by the
        scorer)."""
        return tuple(s.name for s in self.params[2:])

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The order spectrum of the residual force on the member (first segment) and where
        the angle came from (measured position or integrated speed)."""
        if self.member is None:
            return {}, {}
        spec = self.order_spectrum(ctx.member_residual(self.member), ctx.views[0])
        out: dict[str, object] = {"order_spectrum": spec}
        if self.options.get("clock") != "time":
            out["angle_source"] = member_motion(ctx.views[0], self.require_member(),
                                                self.readout)[2]
        return out, {}

    def order_spectrum(self, residual: Array, seg: SegmentView, n_grid: int = 200
                       ) -> dict[str, object]:
        """Amplitude of the residual's best-fitting ``cos/sin(k theta)`` pair for the listed
        orders and on a grid up to 1.5x the largest; the ratio to the grid's median is the
        evidence that a listed order stands out. With ``mesh_stages`` each stage's tooth
        order is also given on its own mesh angle (``mesh<k>:<Z>``, ratio to the same median).

        Args:
            residual: weighted residual of the member's output(s), shape (N,).
        """
        orders = self._orders()
        theta = self._phase(seg)
        kmax = 1.5 * max(orders)
        grid = np.linspace(kmax / n_grid, kmax, n_grid)

        def amp(k: float, th: Array = theta) -> float:
            X = np.column_stack([np.cos(k * th), np.sin(k * th)])
            coef, *_ = np.linalg.lstsq(X, residual, rcond=None)
            return float(np.hypot(coef[0], coef[1]))
        base = float(np.median([amp(k) for k in grid])) or 1e-300
        listed = {f"{k:g}": {"amplitude": amp(k), "ratio_to_median": amp(k) / base}
                  for k in orders}
        if len(self.params) > 3:
            teeth = numbers_option(self.options, "mesh_teeth", [], f"candidate {self.label()}")
            for i, z in enumerate(teeth, start=1):
                a_mesh = amp(z, self._phase(seg, i))
                listed[f"mesh{i}:{z:g}"] = {"amplitude": a_mesh,
                                            "ratio_to_median": a_mesh / base}
        return {"orders": listed, "grid_median_amplitude": base,
                "grid": [float(grid[0]), float(grid[-1]), n_grid]}
