"""Output effects of a speed sensor: measurement delay and gain error."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dvt_identify.effects.base import Array, BuildContext, Effect, ParamSpec, ScoringContext, Term


@dataclass
class MeasurementDelay(Effect):
    """Output ``j`` measured ``d`` seconds late: ``y_j(t) = x_j(t - d)`` (linear interpolation,
    the first value held before the start). Parameter ``delay`` in ``[0, max_delay]`` s
    (option, default 0.02 s). Model node: a ``delay`` term (all outputs, whole samples)."""

    name = "measurement_delay"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        dmax = ctx.number("max_delay", 0.02)
        return cls(where=ctx.where, params=(ParamSpec("delay" + ctx.suffix, 0.0, 0.0, dmax,
                                                      "s"),),
                   index=ctx.state_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        d = float(p[0])
        if d == 0.0:
            return None
        out = y.copy()
        n = y.shape[0]
        k = np.arange(n, dtype=float) - d / dt
        out[:, self.index] = np.interp(k, np.arange(n, dtype=float), y[:, self.index])
        return out

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        return {"kind": "delay", "seconds": float(p[0])}

    def scoring_step(self, name: str, dt: float) -> float | None:
        """One sample: the delay regressor is the secant to a one-sample shift."""
        return dt

    def scan(self, y_sim: Array, y_meas: Array, dt: float, weight: float,
             step: float | None = None) -> list[dict[str, float]]:
        """Delay scan: weighted SSE of output ``j`` for the simulated output shifted by
        ``0, step, ..., K step`` seconds (``step`` default ``dt``, K = max_delay / step;
        fractional samples interpolated), without refitting."""
        h = dt if step is None else float(step)
        kmax = max(1, int(np.rint(float(self.params[0].upper) / h)))
        out = []
        for k in range(0, kmax + 1):
            shifted = self.output_transform(np.array([k * h]), y_sim, dt)
            ys = y_sim if shifted is None else shifted
            e = (y_meas[:, self.index] - ys[:, self.index]) / weight
            out.append({"delay_s": k * h, "sse": float(e @ e)})
        return out

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The delay scan summed over the segments (one delay grid, the finest segment's
        sample time, for segments of any rate), its best delay [s] and the SSE reduction
        there [%]; the best delay is the refit's start when it is above 0."""
        step = min(v.dt for v in ctx.views)
        scan = [self.scan(yb, v.y, v.dt, float(ctx.weights[self.index]), step)
                for v, yb in zip(ctx.views, ctx.simulated, strict=True)]
        tot = [{"delay_s": s0["delay_s"], "sse": sum(s[i]["sse"] for s in scan)}
               for i, s0 in enumerate(scan[0])]
        kbest = min(tot, key=lambda d: d["sse"])
        extra: dict[str, object] = {
            "delay_scan": tot, "best_delay_s": kbest["delay_s"],
            "sse_reduction_percent_at_best_delay": (
                100.0 * (tot[0]["sse"] - kbest["sse"]) / tot[0]["sse"] if tot[0]["sse"]
                else 0.0)}
        start = {self.params[0].name: kbest["delay_s"]} if kbest["delay_s"] > 0 else {}
        return extra, start


@dataclass
class SensorGain(Effect):
    """Output ``j`` scaled by ``(1 + g)``; parameter ``gain`` (dimensionless, in [-0.9, 10]).
    Model node: a ``gain`` term on that output (when the node admits the value)."""

    name = "sensor_gain"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("gain" + ctx.suffix, 0.0, -0.9, 10.0, "1",
                                                      step=1e-3),),
                   index=ctx.state_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        g = float(p[0])
        if g == 0.0:
            return None
        out = y.copy()
        out[:, self.index] = (1.0 + g) * y[:, self.index]
        return out

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        if self.where not in outputs:
            return None
        return {"kind": "gain", "output": list(outputs).index(self.where), "gain": float(p[0])}

    def why_no_term(self, outputs: Sequence[str]) -> str:
        return f"{self.where!r} is not one of the model's outputs {list(outputs)}"
