"""Output effects of a sensor: measurement delay, gain (scale) error, a first-order lag, and the
sensor maps (sign-blind ``|y|``, saturation, quantisation, offset).

Every output effect acts on a *measured output* (``where`` names it; with a structure that has
hidden states the outputs are a subset of the states, :meth:`BuildContext.output_index`). The
sensor maps leave a residual signature a reader can check in ``scoring_evidence``:

- sign-blind: the measured output never goes below zero while the simulated one does, and the
  baseline error sits where the simulated output is negative (a negative value read as a
  positive one: ``error_share_where_simulated_negative`` near 1); a signal oscillating about
  zero read through ``|y|`` puts its energy at *twice* its frequency, so the residual carries
  a second harmonic of the fundamental (``second_harmonic_ratio``, :func:`harmonics`);
  the share of the error in windows around the simulated output's sign changes
  (``error_share_near_sign_changes`` against ``sample_share_near_sign_changes``,
  :func:`sign_change_shares`) tells it from effects acting at reversals;
- saturation: flat tops, the measured output sits at its extreme values for several samples
  while the simulation goes beyond them, and the baseline error is concentrated there
  (``error_share_at_flat_tops`` against ``sample_share_at_flat_tops``);
- quantisation: the measured values fall on a grid (its step is the most common non-zero
  difference of consecutive samples), the residual is a sawtooth within half a step
  (``residual_rms_over_step`` near ``1/sqrt(12) = 0.289`` when the grid is all that is left);
- offset: a constant mean residual (``mean_residual_over_residual_std``).

Every number is computed from the measured outputs and the baseline simulation handed to the
scorer (:class:`ScoringContext`, all scored segments pooled) and lands in the report's
evidence of the candidate under the same name.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter, lfilter_zi

from dvt_identify.effects.base import Array, BuildContext, Effect, ParamSpec, ScoringContext, Term
from dvt_identify.errors import DescriptionError
from dvt_identify.resid import residual_spectrum


@dataclass
class MeasurementDelay(Effect):
    """Output ``j`` measured ``d`` seconds late: ``y_j(t) = x_j(t - d)`` (linear interpolation,
    the first value held before the start). Parameter ``delay`` in ``[0, max_delay]`` s
    (option, default 0.02 s). Model node: a ``delay`` term (all outputs, whole samples)."""

    name = "measurement_delay"
    order = 50

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
    order = 80

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


HARMONIC_BAND = 0.1
"""Half-width of the bands around the fundamental and its second harmonic, relative to the
fundamental frequency."""
PEAK_PROMINENCE = 10.0
"""Smallest prominence (density over the median within half an octave) of a spectral peak of
the simulated output taken as the fundamental; below it the measured output's peak is used."""
SIGN_CHANGE_WINDOW = 0.1
"""Half-width of the window around each sign change of the simulated output, as a share of the
median interval between consecutive sign changes (at least one sample)."""


def _band_power(freq: Array, psd: Array, f: float, half: float) -> float:
    """Power of a PSD within ``f +- half`` [unit^2] (rectangle rule; at least the nearest
    bin)."""
    if freq.size < 2:
        return 0.0
    df = float(freq[1] - freq[0])
    m = np.abs(freq - f) <= max(half, 0.5 * df)
    if not np.any(m):
        m = np.abs(freq - f) == np.min(np.abs(freq - f))
    return float(np.sum(psd[m]) * df)


def harmonics(measured: Sequence[Array], simulated: Sequence[Array], dt: float
              ) -> dict[str, object]:
    """Second-harmonic signature of an output read through ``|y|``.

    The fundamental ``f1`` is the most prominent peak of the simulated output's Welch spectrum
    (:func:`dvt_identify.resid.residual_spectrum`: density over the median within half an
    octave; a forced frequency or a lightly damped mode), or of the measured output's when
    the simulated one has no peak of prominence ``PEAK_PROMINENCE`` (a baseline bent towards
    ``|y|`` can lose the mode). Returned (numbers a reader can check against the residual
    spectrum plot):

    - ``fundamental_hz``: ``f1`` [Hz], and ``fundamental_from``: ``simulated`` or ``measured``;
    - ``second_harmonic_ratio``: residual power within ``2 f1 +- HARMONIC_BAND f1`` over the
      power of the fundamental within ``f1 +- HARMONIC_BAND f1`` (the larger of the simulated
      and the measured output's; dimensionless). ``|sin|`` against ``sin`` gives
      ``(4 / 3 pi)^2 = 0.18``; a linear misfit leaves no second harmonic of a sinusoid and
      white noise only its share of the band (both near 0); an output that seldom crosses
      zero while it oscillates (a mode riding on a one-signed speed) gives little either;
    - ``residual_2f_over_f``: residual power at ``2 f1`` over residual power at ``f1`` (the
      same bands).

    Args:
        measured, simulated: one output's measured and simulated series per segment, each
            shape (N,), all at sample time ``dt`` [s].
    """
    sim = residual_spectrum(list(simulated), dt)
    meas = residual_spectrum(list(measured), dt)
    res = residual_spectrum([m - s for m, s in zip(measured, simulated, strict=True)], dt)
    src = "simulated" if sim.peak_ratio >= PEAK_PROMINENCE else "measured"
    f1 = float(sim.peak_hz if src == "simulated" else meas.peak_hz)
    out: dict[str, object] = {"fundamental_hz": f1, "fundamental_from": src,
                              "second_harmonic_ratio": 0.0, "residual_2f_over_f": 0.0}
    if f1 <= 0.0 or res.freq.size < 2:
        return out
    half = HARMONIC_BAND * f1
    p_f = max(_band_power(sim.freq, sim.psd, f1, half),
              _band_power(meas.freq, meas.psd, f1, half))
    p1 = _band_power(res.freq, res.psd, f1, half)
    p2 = _band_power(res.freq, res.psd, 2.0 * f1, half)
    out["second_harmonic_ratio"] = p2 / p_f if p_f > 0 else 0.0
    out["residual_2f_over_f"] = p2 / p1 if p1 > 0 else 0.0
    return out


def sign_change_shares(errors: Sequence[Array], simulated: Sequence[Array]
                       ) -> dict[str, float]:
    """Where the error sits relative to the simulated output's sign changes.

    Windows of ``+-W`` samples around every sign change of each simulated series, ``W`` =
    ``SIGN_CHANGE_WINDOW`` times the median interval between its sign changes (at least 1).
    Returned: ``error_share_near_sign_changes`` (share of the squared error in the windows),
    ``sample_share_near_sign_changes`` (share of the samples in them) and
    ``sign_change_concentration`` (their ratio: 1 uniform, above 1 the error sits at the sign
    changes as for dry friction or backlash at reversals, below 1 away from them as for a
    sign-blind reading, whose error is largest on the negative lobes), plus
    ``sign_changes`` (count).

    Args:
        errors, simulated: one output's error and simulation per segment, shape (N,) each.
    """
    near = tot = 0.0
    n_in = n = changes = 0
    for e, ys in zip(errors, simulated, strict=True):
        idx = np.flatnonzero(np.diff(np.signbit(ys).astype(np.int8)))
        mask = np.zeros(ys.size, dtype=bool)
        if idx.size:
            gap = float(np.median(np.diff(idx))) if idx.size > 1 else float(ys.size)
            w = max(1, round(SIGN_CHANGE_WINDOW * gap))
            for i in idx:
                mask[max(0, i - w + 1): i + w + 1] = True
        e2 = np.asarray(e, float) ** 2
        near += float(e2[mask].sum())
        tot += float(e2.sum())
        n_in += int(mask.sum())
        n += ys.size
        changes += int(idx.size)
    err_share = near / tot if tot > 0 else 0.0
    samp_share = n_in / n if n else 0.0
    return {"error_share_near_sign_changes": err_share,
            "sample_share_near_sign_changes": samp_share,
            "sign_change_concentration": err_share / samp_share if samp_share > 0 else 0.0,
            "sign_changes": float(changes)}


def _column(y: Array, j: int, values: Array) -> Array:
    out = y.copy()
    out[:, j] = values
    return out


LAG_SCAN = 16
"""Time constants the lag's scan tries besides 0: geometric from a quarter sample to
``max_tau``."""


def first_order_lag(x: Array, tau: float, dt: float) -> Array:
    """``x`` (N,) read through a first-order low-pass ``tau y' = x - y`` [s], shape (N,):
    exact for ``x`` linear between samples (``y[k+1] = a y[k] + b0 x[k+1] + b1 x[k]``, ``a =
    exp(-dt / tau)``, unit static gain), started at rest at ``x[0]``; ``x`` itself for ``tau
    <= 0``."""
    x = np.asarray(x, float)
    if tau <= 0.0 or x.size == 0:
        return x.copy()
    a = math.exp(-dt / tau)
    c = (tau / dt) * (1.0 - a)
    b = np.array([1.0 - c, c - a])
    return np.asarray(lfilter(b, [1.0, -a], x, zi=lfilter_zi(b, [1.0, -a]) * x[0])[0], float)


@dataclass
class SensorLag(Effect):
    """Output ``j`` read through a first-order low-pass (a sensor's or a drive's filter on a
    speed reading, a counter's averaging): ``tau y_j' = x_j - y_j``
    (:func:`first_order_lag`). Parameter ``tau`` in ``[0, max_tau]`` s (option, default 0.1
    s), null 0. Applied after the maps accepted before it (a sign-blind counter read through
    its filter: ``lag(|x|)``). No model-node term.

    Scored by the secant to a one-sample time constant; the scan of ``tau`` over
    :data:`LAG_SCAN` values (the baseline's simulated output filtered, not refitted) gives the
    refit's start and the evidence (``best_tau_s``, ``sse_reduction_percent_at_best_tau``)."""

    name = "sensor_lag"
    order = 115
    no_term = "the model node has no output filter"
    global_map = True  # a structure with a slow mode can take the lag's place (the refit)

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        tmax = ctx.number("max_tau", 0.1)
        if not tmax > 0.0:
            raise DescriptionError(f"candidate sensor_lag@{ctx.where}: max_tau: expected a "
                                   f"time constant > 0 s, got {tmax!r}")
        return cls(where=ctx.where, params=(ParamSpec("tau" + ctx.suffix, 0.0, 0.0, tmax, "s"),),
                   index=ctx.output_index(), options=dict(ctx.options))

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        tau = float(p[0])
        if tau <= 0.0:
            return None
        return _column(y, self.index, first_order_lag(y[:, self.index], tau, dt))

    def output_inverse(self, p: Array, y: Array, dt: float) -> Array | None:
        """``y_j + tau y_j'`` (central differences): the filter's input, for the starts (a
        reading with its dips smoothed away hides where a sign-blind output changes sign)."""
        tau = float(p[0])
        if tau <= 0.0 or y.shape[0] < 2:
            return None
        return _column(y, self.index, y[:, self.index] + tau * np.gradient(y[:, self.index], dt))

    def inverse_probes(self, dt: float) -> list[Array]:
        """Its start (the scan's best) and one and two sample times."""
        taus = [float(self.params[0].initial), dt, 2.0 * dt]
        return [np.array([t]) for t in dict.fromkeys(taus)
                if 0.0 < t <= float(self.params[0].upper)]

    def scoring_step(self, name: str, dt: float) -> float | None:
        """One sample: the regressor is the secant to ``tau = dt``."""
        return dt

    def inadmissible(self, p: Array) -> str | None:
        tau = float(p[0])
        return None if math.isfinite(tau) and tau > 0.0 else f"tau = {tau}: no filter"

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The weighted SSE of the output with the baseline's simulation filtered at ``0`` and
        :data:`LAG_SCAN` time constants (geometric, a quarter of the finest sample time to
        ``max_tau``), summed over the segments; the best one [s] and the SSE reduction there
        [%]; the best is the refit's start when above 0."""
        j, wj = self.index, float(ctx.weights[self.index])
        dt = min(v.dt for v in ctx.views)
        taus = [0.0, *np.geomspace(0.25 * dt, float(self.params[0].upper), LAG_SCAN).tolist()]
        sse = []
        for tau in taus:
            tot = 0.0
            for v, yb in zip(ctx.views, ctx.simulated, strict=True):
                e = (v.y[:, j] - first_order_lag(yb[:, j], tau, v.dt)) / wj
                tot += float(e @ e)
            sse.append(tot)
        k = int(np.argmin(sse))
        extra: dict[str, object] = {
            "lag_scan": [{"tau_s": t, "sse": e} for t, e in zip(taus, sse, strict=True)],
            "best_tau_s": taus[k],
            "sse_reduction_percent_at_best_tau": (100.0 * (sse[0] - sse[k]) / sse[0]
                                                  if sse[0] else 0.0)}
        return extra, ({self.params[0].name: taus[k]} if taus[k] > 0 else {})


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
    order = 110
    global_map = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("sign_blind" + ctx.suffix, 0.0, 0.0, 2.0,
                                                      "1"),),
                   index=ctx.output_index(), options=dict(ctx.options))

    def blind_output(self) -> int | None:
        return self.index

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
        map by drifting positive: then both are small), the second-harmonic ratio of the
        residual (:func:`harmonics`, on the segments at the first one's sample time) and the
        error's share around the simulated output's sign changes
        (:func:`sign_change_shares`)."""
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
        dt0 = ctx.views[0].dt if ctx.views else 0.0
        same = [(v.y[:, j], yb[:, j]) for v, yb in zip(ctx.views, ctx.simulated, strict=True)
                if v.dt == dt0]
        if same:
            extra.update(harmonics([m for m, _ in same], [s for _, s in same], dt0))
        extra.update(sign_change_shares(
            [v.y[:, j] - yb[:, j] for v, yb in zip(ctx.views, ctx.simulated, strict=True)],
            [yb[:, j] for yb in ctx.simulated]))
        return extra, {}


@dataclass
class SensorOffset(Effect):
    """Output ``j`` read with a constant offset: ``y_j = x_j + c`` (parameter ``sensor_offset`` in
    output units, unbounded, null 0). No model-node term."""

    name = "sensor_offset"
    order = 140

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
        """The mean residual (output units), the refit's start, and its size against the
        residual's standard deviation about it (``mean_residual_over_residual_std``: an
        offset alone gives a large value, a zero-mean misfit a small one)."""
        j = self.index
        r = np.concatenate([v.y[:, j] - yb[:, j] for v, yb in zip(ctx.views, ctx.simulated,
                                                                 strict=True)])
        m = float(np.mean(r)) if r.size else 0.0
        sd = float(np.std(r)) if r.size else 0.0
        return ({"mean_residual": m, "mean_residual_over_residual_std": (
                    abs(m) / sd if sd > 0 else (np.inf if m else 0.0))},
                ({self.params[0].name: m} if m else {}))


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
    order = 120
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
        repeats its extreme value) and the baseline error is concentrated there
        (``error_share_at_flat_tops``, the share of the squared error on the flat-top samples,
        above ``sample_share_at_flat_tops``, their share of the samples: a quantised sensor
        repeats its extreme grid value too, but its error is no larger there). Also
        ``simulated_beyond_share_at_flat_tops``: the share of the flat-top samples where the
        simulation goes beyond the extreme (1 for a clipped sensor). The start value is the
        largest measured magnitude."""
        j = self.index
        ym = np.concatenate([v.y[:, j] for v in ctx.views])
        ys = np.concatenate([yb[:, j] for yb in ctx.simulated])
        hi, share_hi, lo, share_lo = _flat_top(ym)
        tol = 1e-6 * max(hi - lo, 1e-300)
        at_hi, at_lo = ym >= hi - tol, ym <= lo + tol
        flat = at_hi | at_lo if max(share_hi, share_lo) >= FLAT_TOP_SHARE else np.zeros_like(at_hi)
        e2 = (ym - ys) ** 2
        e_tot = float(e2.sum())
        err_share = float(e2[flat].sum()) / e_tot if e_tot > 0 else 0.0
        samp_share = float(np.mean(flat)) if flat.size else 0.0
        beyond = (at_hi & (ys > hi)) | (at_lo & (ys < lo))
        extra: dict[str, object] = {
            "measured_max": hi, "share_at_max": share_hi, "measured_min": lo,
            "share_at_min": share_lo, "simulated_max": float(np.max(ys)),
            "simulated_min": float(np.min(ys)),
            "error_share_at_flat_tops": err_share, "sample_share_at_flat_tops": samp_share,
            "simulated_beyond_share_at_flat_tops": (
                float(beyond[flat].mean()) if np.any(flat) else 0.0)}
        extra["signature"] = bool(max(share_hi, share_lo) >= FLAT_TOP_SHARE
                                  and err_share > samp_share)
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
    order = 130

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
        """The grid step ``q`` read from the measured values (or the ``step`` option) and the
        share of samples on it; the baseline residual against the step:
        ``residual_rms_over_step`` (RMS residual / ``q``; ``1/sqrt(12) = 0.289`` when the
        rounding is all that is left, far above when the grid is finer than the model error)
        and ``residual_share_within_half_step`` (share of samples with ``|residual| <= q/2``:
        near 1 when the rounding is all that is left)."""
        j = self.index
        ym = np.concatenate([v.y[:, j] for v in ctx.views])
        r = np.concatenate([v.y[:, j] - yb[:, j] for v, yb in zip(ctx.views, ctx.simulated,
                                                                 strict=True)])
        q = float(self.options.get("step", 0.0) or 0.0)  # type: ignore[arg-type]
        q = q or self.grid_step(ym)
        on = float(np.mean(np.abs(ym / q - np.round(ym / q)) < 1e-3)) if q > 0 else 0.0
        rms = float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0
        extra: dict[str, object] = {
            "grid_step": q, "share_on_grid": on, "residual_rms": rms,
            "residual_rms_over_step": rms / q if q > 0 else 0.0,
            "uniform_rounding_rms_over_step": 1.0 / float(np.sqrt(12.0)),
            "residual_share_within_half_step": (float(np.mean(np.abs(r) <= 0.5 * q))
                                                if q > 0 and r.size else 0.0)}
        return extra, ({self.params[0].name: q} if q else {})
