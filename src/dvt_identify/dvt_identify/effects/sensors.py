"""Output effects of a sensor: measurement delay, gain (scale) error, and the sensor maps
(sign-blind ``|y|``, saturation, quantisation, offset).

Every output effect acts on a *measured output* (``where`` names it; with a structure that has
hidden states the outputs are a subset of the states, :meth:`BuildContext.output_index`). The
sensor maps leave a residual signature a reader can check in ``scoring_evidence``:

- sign-blind: the baseline error is concentrated where the simulated output changes sign
  (a negative simulated value is read as a positive measured one), and the measured output
  never goes below zero while the simulated one does; a lightly damped mode read through
  ``|y|`` puts its energy at *twice* the mode frequency;
- saturation: flat tops, the measured output sits at its extreme values for several samples
  while the simulation goes beyond them;
- quantisation: the measured values fall on a grid (its step is the most common non-zero
  difference of consecutive samples), the residual is a sawtooth within half a step;
- offset: a constant mean residual.
"""

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
                   index=ctx.output_index(), options=dict(ctx.options))

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
                   index=ctx.output_index(), options=dict(ctx.options))

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


SIGN_BLIND_SHARE = 0.002
"""Largest share of measured samples below minus 4 noise standard deviations that still reads
as a sign-blind output (a Gaussian noise alone puts 3e-5 there)."""
FLAT_TOP_SHARE = 0.01
"""Smallest share of samples exactly at the measured extreme that reads as a flat top."""


def _column(y: Array, j: int, values: Array) -> Array:
    out = y.copy()
    out[:, j] = values
    return out


@dataclass
class SignBlindSensor(Effect):
    """Output ``j`` read without its sign: ``y_j = (1 - b) x_j + b |x_j|`` (``b = 1``: the
    sensor reads ``|x_j|``, e.g. a speed from a single-channel pulse counter or a
    tachometer that ignores the direction). The map is not differentiable at ``x_j = 0``; in
    ``b`` it is linear, and the scorer uses the secant to ``b = 1`` (the variant probe, as for
    play). ``b`` is bounded by [0, 2] so that the sensor's own value 1 is not a bound (its
    standard deviation then applies); outside [0.5, 1.5] it is no sensor of this kind
    (inadmissible). No model-node term."""

    name = "sign_blind"
    global_map = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("sign_blind" + ctx.suffix, 0.0, 0.0, 2.0,
                                                      "1"),),
                   index=ctx.output_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        b = float(p[0])
        if b == 0.0:
            return None
        x = y[:, self.index]
        return _column(y, self.index, x + b * (np.abs(x) - x))

    def variants(self, seg: object) -> list[tuple[str, dict[str, float]]]:
        """One variant: the secant probe ``b = 1`` (the map itself)."""
        return [("|y|", {self.params[0].name: 1.0})]

    def inadmissible(self, p: Array) -> str | None:
        why = super().inadmissible(p)
        if why is None and not 0.5 <= float(p[0]) <= 1.5:
            return (f"{self.params[0].name} = {float(p[0]):.3g} is not within [0.5, 1.5]: the "
                    "output is not read sign-blind (a blend of y and |y| is no sensor)")
        return why

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The signature, from the data and the baseline: the measured output stays above
        minus 4 noise standard deviations (``noise_std``: a robust white-noise estimate from
        its second differences) on all but ``SIGN_BLIND_SHARE`` of the samples while its range
        is at least 20 noise standard deviations and every input takes both signs on at least
        10 % of the samples (a linear drive then turns both ways); ``signature: True`` then.
        Also the share of the baseline squared error on the samples where the simulated output is
        negative (what ``|y|`` changes) and that sample share (a baseline can hide the
        map by drifting positive: then both are small)."""
        j = self.index
        neg = tot = 0.0
        nneg = n = 0
        ym = np.concatenate([v.y[:, j] for v in ctx.views])
        um = np.concatenate([v.u for v in ctx.views])
        for v, yb in zip(ctx.views, ctx.simulated, strict=True):
            e = (v.y[:, j] - yb[:, j]) ** 2
            mask = yb[:, j] < 0
            neg += float(e[mask].sum())
            tot += float(e.sum())
            nneg += int(mask.sum())
            n += e.size
        # robust white-noise std from second differences (a smooth signal's slope cancels)
        d2 = np.concatenate([np.abs(np.diff(v.y[:, j], 2)) for v in ctx.views])
        noise = float(np.median(d2) / (0.6745 * np.sqrt(6.0))) if d2.size else 0.0
        below = float(np.mean(ym < -4.0 * noise)) if ym.size else 0.0
        span = float(np.ptp(ym)) if ym.size else 0.0
        two_signed = bool(um.size) and all(
            min(float(np.mean(um[:, i] > 0)), float(np.mean(um[:, i] < 0))) >= 0.1
            for i in range(um.shape[1]))
        signature = bool(below <= SIGN_BLIND_SHARE and span >= 20.0 * noise and two_signed)
        extra: dict[str, object] = {
            "signature": signature,
            "measured_share_below_minus_4_noise": below, "noise_std": noise,
            "measured_range": span, "inputs_take_both_signs": two_signed,
            "measured_minimum": float(np.min(ym)) if ym.size else 0.0,
            "error_share_where_simulated_negative": neg / tot if tot > 0 else 0.0,
            "sample_share_where_simulated_negative": nneg / n if n else 0.0}
        return extra, {}


@dataclass
class SensorOffset(Effect):
    """Output ``j`` read with a constant offset: ``y_j = x_j + c`` (parameter ``sensor_offset`` in
    output units, unbounded, null 0). No model-node term."""

    name = "sensor_offset"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("sensor_offset" + ctx.suffix, 0.0,
                                                      unit=ctx.speed_unit),),
                   index=ctx.output_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        c = float(p[0])
        if c == 0.0:
            return None
        return _column(y, self.index, y[:, self.index] + c)

    def scoring_step(self, name: str, dt: float) -> float | None:
        return 1e-3

    def inadmissible(self, p: Array) -> str | None:
        v = float(p[0])
        return None if np.isfinite(v) and v != 0.0 else f"sensor_offset = {v}: no offset"

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The mean residual (output units), the refit's start."""
        j = self.index
        r = np.concatenate([v.y[:, j] - yb[:, j] for v, yb in zip(ctx.views, ctx.simulated,
                                                                 strict=True)])
        m = float(np.mean(r)) if r.size else 0.0
        return {"mean_residual": m}, ({self.params[0].name: m} if m else {})


def _flat_top(y: Array) -> tuple[float, float, float, float]:
    """(max, share of samples within 1e-6 of the range at the max, min, share at the min)."""
    lo, hi = float(np.min(y)), float(np.max(y))
    tol = 1e-6 * max(hi - lo, 1e-300)
    return hi, float(np.mean(y >= hi - tol)), lo, float(np.mean(y <= lo + tol))


@dataclass
class SensorSaturation(Effect):
    """Output ``j`` clipped by its sensor: ``y_j = min(max(x_j, -L), L)`` (symmetric; level
    ``L`` > 0 in output units). The effect vanishes for ``L`` at its upper bound ``max_level``
    (option, default 1e6 output units: the null). The scorer probes ``L`` at the measured
    output's largest magnitude (the secant to the flat top) and the refit starts there. No
    model-node term."""

    name = "sensor_saturation"
    global_map = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        top = ctx.number("max_level", 1e6)
        return cls(where=ctx.where, params=(ParamSpec("level" + ctx.suffix, top, 0.0, top,
                                                      ctx.speed_unit, null=top),),
                   index=ctx.output_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        level = float(p[0])
        if self.params[0].upper <= level:
            return None
        return _column(y, self.index, np.clip(y[:, self.index], -level, level))

    def variants(self, seg: object) -> list[tuple[str, dict[str, float]]]:
        """The secant to the measured flat top: ``L`` = the measured largest magnitude."""
        y = getattr(seg, "y", None)
        if y is None:
            return [("", {})]
        top = float(np.max(np.abs(y[:, self.index])))
        null = self.params[0].null
        return [(f"L={top:.4g}", {self.params[0].name: top - null})] if 0 < top < null else []

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """Flat tops: the measured maximum and minimum, the share of samples at each and how
        far the simulation goes beyond them; ``signature: True`` when at least
        ``FLAT_TOP_SHARE`` of the samples sit exactly at an extreme (a noisy signal never
        repeats its extreme value). The start value is the largest measured magnitude."""
        j = self.index
        ym = np.concatenate([v.y[:, j] for v in ctx.views])
        ys = np.concatenate([yb[:, j] for yb in ctx.simulated])
        hi, share_hi, lo, share_lo = _flat_top(ym)
        extra: dict[str, object] = {
            "measured_max": hi, "share_at_max": share_hi, "measured_min": lo,
            "share_at_min": share_lo, "simulated_max": float(np.max(ys)),
            "simulated_min": float(np.min(ys))}
        extra["signature"] = bool(max(share_hi, share_lo) >= FLAT_TOP_SHARE)
        top = max(abs(hi), abs(lo))
        return extra, ({self.params[0].name: top} if 0 < top < self.params[0].upper else {})


@dataclass
class SensorQuantisation(Effect):
    """Output ``j`` read on a grid: ``y_j = q round(x_j / q)`` (step ``q`` >= 0 in output units,
    null 0). The map is piecewise constant in ``q``, so the fit barely moves ``q``: it starts
    (and the scorer probes it) at the step read from the data (the most common non-zero
    difference of consecutive measured samples, :meth:`scoring_evidence`; option ``step``
    overrides it). No model-node term."""

    name = "sensor_quantisation"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        q = ctx.number("step", 0.0)
        return cls(where=ctx.where, params=(ParamSpec("quantum" + ctx.suffix, 0.0, 0.0,
                                                      np.inf, ctx.speed_unit),),
                   index=ctx.output_index(), options={**ctx.options, "step": q})

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        q = float(p[0])
        if q <= 0.0:
            return None
        return _column(y, self.index, q * np.round(y[:, self.index] / q))

    @staticmethod
    def grid_step(y: Array) -> float:
        """The most common non-zero absolute difference of consecutive samples (rounded to
        6 significant digits); 0 when the values do not fall on a grid (fewer than half of
        the non-zero differences are integer multiples of it)."""
        d = np.abs(np.diff(y))
        d = d[d > 1e-12 * max(float(np.max(np.abs(y))), 1e-300)]
        if d.size == 0:
            return 0.0
        r = np.array([float(f"{v:.6g}") for v in d])
        vals, counts = np.unique(r, return_counts=True)
        q = float(vals[int(np.argmax(counts))])
        k = d / q
        on = np.abs(k - np.round(k)) < 1e-3
        return q if float(np.mean(on)) > 0.5 else 0.0

    def variants(self, seg: object) -> list[tuple[str, dict[str, float]]]:
        y = getattr(seg, "y", None)
        q = float(self.options.get("step", 0.0) or 0.0)  # type: ignore[arg-type]
        if not q and y is not None:
            q = self.grid_step(y[:, self.index])
        return [(f"q={q:.4g}", {self.params[0].name: q})] if q > 0 else []

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The grid step read from the measured values and the share of samples on it."""
        j = self.index
        ym = np.concatenate([v.y[:, j] for v in ctx.views])
        q = float(self.options.get("step", 0.0) or 0.0)  # type: ignore[arg-type]
        q = q or self.grid_step(ym)
        on = float(np.mean(np.abs(ym / q - np.round(ym / q)) < 1e-3)) if q > 0 else 0.0
        return {"grid_step": q, "share_on_grid": on}, ({self.params[0].name: q} if q else {})
