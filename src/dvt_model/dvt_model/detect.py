"""Change detection on the model residual: a whitened two-sided CUSUM per output (pure).

The model node feeds every residual sample (measured minus predicted speed [rad/s], one value
per output of :data:`~dvt_model.contract.SPEED_NAMES`) to :meth:`ChangeDetector.update`; the
detector answers ``None`` or an :class:`Alarm`. O(1) per sample, plain Python floats in
preallocated lists (no container allocated per sample: about 1.5 us per sample, about 5 us
with the colour, one numpy dot per output); only the end of
a reference window does one numpy pass over it (about 2 ms, once per ``learn_s``), and the end
of a colour chunk one FFT and a few Toeplitz solves per output (once a minute).

Statistic
---------
1. **Reference window** (``learn_s`` seconds after a start, a :meth:`~ChangeDetector.reset` or
   an alarm). Per output: the level ``m`` (mean of the residual winsorised at the median
   +/- 4 robust sigma) and an ARMA(1, 1) model of the centred residual ``c``,
   ``c_t - phi c_{t-1} = a_t + theta a_{t-1}``, by the method of moments
   (:func:`reference_from_window`), and the innovation scale ``s`` (1.4826 times the median
   absolute deviation of the innovations ``a`` on the window; robust to spikes).
2. **Pre-whitening**. An output-error residual is coloured: a slow model error (AR(1)-like,
   ``phi`` near 1) plus white sensor noise, i.e. ARMA(1, 1). A CUSUM on coloured data raises
   false alarms far more often than its i.i.d. design says, and whitening with an AR(1) alone
   leaves the sensor-noise part coloured (measured: ~100 false alarms per hour for AR(0.9) plus
   white noise of half its size). Each sample is whitened by the inverse ARMA(1, 1) filter,
   ``a_t = (r_t - m) - phi (r_{t-1} - m) - theta a_{t-1}``, ``z_t = a_t / s``: N(0, 1) and
   nearly independent on a clean plant, so the CUSUM's i.i.d. theory applies.
3. **Two-sided CUSUM** per output: ``S+ = max(0, S+ + z - k)``, ``S- = max(0, S- - z - k)``,
   alarm when either exceeds ``h``. A step ``d`` in the residual (in residual standard
   deviations ``sigma``, MAD of the window) reaches ``z`` as ``d sigma (1 - phi) / ((1 + theta)
   s)``; ``k`` is half of that for ``d = shift_sigma`` (the optimal reference for that shift).
4. **Threshold** ``h`` per output from Siegmund's approximation of the in-control average run
   length of a one-sided CUSUM, ``ARL0 = (exp(2 k b) - 2 k b - 1) / (2 k^2)``, ``b = h + 1.166``,
   such that the whole detector (every output, both sides) raises on average one false alarm per
   ``false_alarm_period_s`` at ``sample_rate_hz``. The design averages the false-alarm rate over
   the estimation error of a reference window of ``L`` samples (level error ``N(0, 1/L)`` in
   whitened units, scale error ``N(0, 1.36/L)`` relative, Gauss-Hermite quadrature), because with
   a small ``k`` a level error of a few thousandths of a sigma changes ``ARL0`` several-fold.
   The figure is checked by simulation (:mod:`dvt_model.detect_sim`: ``simulate_clean``,
   ``benchmark``, ``python -m dvt_model.detect_sim``; ``docs/loop.md``).

Colour
------
A residual with several time scales (the simulated plant's carrier 3: about 0.2, 0.6 and 1.4 s
beside sensor noise) is not whitened by an ARMA(1, 1) learned on 20 s: the whitened residual
keeps a slow wander and the CUSUM raises false alarms far above its design (docs/loop.md,
"Colour"). So the detector also learns the residual's colour on a long history,
``colour_s`` (300 s) of residual pooled in chunks of :data:`COLOUR_CHUNK_S`, each centred on its
own mean (:func:`lagged_products`): an AR(p) by Yule-Walker with ``p`` by AIC up to
:attr:`DetectorConfig.colour_order_max` (:func:`ar_by_aic`), fitted when the first chunk
completes and refitted on the newest ``colour_s`` (at most) whenever another one does. From its
first fit on (a new reference window starts then) every reference window learns only the level
and the innovation scale (standard deviation of ``a_t = c_t - sum_j a_j c_(t-j)``), and each
sample is whitened by the newest AR when the window ends; ``k``, ``h`` as above with the step
gain ``1 - sum_j a_j``. While the history grows the colour is fitted on less than ``colour_s``
(:attr:`ChangeDetector.colour_in_use_s`) and leaves slow colour in the whitened residual (a
CUSUM on it alarmed about 7 times an hour on the simulated plant in minutes 1-5): each refit
then whitens the reference window in use again (testing goes on, no new window), and ``h`` is
designed for whitened increments of long-run variance ``lam`` (:attr:`Reference.lam`), the
largest batch-means ratio of the newest chunk whitened by the colour before it (out of
sample; the first colour by itself), over that ratio's sampling uncertainty
(:func:`long_run_spread`, as before the first colour: at the ratio alone minutes 1-5 of 150
starts raised 9 false alarms in 9.2 h, with its uncertainty 2 on the same residual; docs/loop.md
"Limits"). Its first fit on the full ``colour_s``
starts a new reference window once more, with ``lam`` 1
(:attr:`ChangeDetector.colour_complete`: the design holds from there). The colour is kept
across alarms and :meth:`~ChangeDetector.reset`; an alarm removes the history from its
estimated change time on, a reset the chunk in progress, a gap or a non-finite sample ends a
chunk (one shorter than ``10 x`` the longest lag is dropped). Before
the first fit (the first chunk after a start) the detector runs with each window's
ARMA(1, 1), which 20 s cannot make fit a residual of several time scales: there ``h`` is
designed over the long-run variance ratio the window's own whitened residual shows and its
sampling uncertainty (:func:`long_run_spread`; the rate averaged over 16 equal-probability
points), higher than the ARMA's design by itself (docs/loop.md "Limits"). With
``colour_s`` 0 (no colour ever) each window keeps the ARMA's design.

A colour carried from an earlier run of the same model (:class:`CarriedColour`, written and
read by :class:`ColourKeeper`: the model node's ``detector.colour_file``) stands in for the
first minute's and the growing colour: it whitens every reference window from the first on,
until the run's own history reaches ``colour_s``; then the own full colour replaces it with a
new reference window (docs/loop.md, "Colour", item 6). ``h`` is designed over the long-run
variance ratio of the residual whitened by it, with its uncertainty (out of sample): of the
first window until a chunk of the run ends, then of the newest chunk, each chunk whitening the
reference in use again as a growing colour does.

On an alarm the detector returns an :class:`Alarm` (detection stamp, the estimated change time =
the stamp of the first sample after the CUSUM's last zero, output, direction, estimated shift),
then re-learns a new reference window and keeps running. Non-finite residuals are skipped;
a stamp gap longer than ``max_gap_s`` (or a stamp that does not increase) skips the whitening of
the sample after it (the filter memory would be wrong); while a reference window is learned it
starts the window again from the sample after it (a window is contiguous: one spanning a gap,
e.g. the model's re-anchor on lost samples, joins two residual levels and learns a colour near
``max_phi``, a threshold the step never reaches).
"""

from __future__ import annotations

import json
import math
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_model.contract import SPEED_NAMES
from dvt_model.errors import ParameterError

SIEGMUND_OFFSET = 1.166
"""Siegmund's overshoot correction ``2 * 0.583`` added to ``h`` [whitened sigma]."""
MAD_TO_SIGMA = 1.4826
"""Scale factor from the median absolute deviation to a Gaussian standard deviation."""
_MAD_REL_VAR = 1.36
"""Asymptotic variance of the MAD scale estimate relative to sigma^2, times the sample count."""
_WINSOR = 4.0  # robust sigmas: winsorising bound of the reference window
_COLOUR_LAGS_PER_ORDER = 10
"""The colour's history holds at least this many samples per AR order (and so does a chunk)."""
MAX_COLOUR_ORDER = 2000
"""Largest AR order of the colour (its per-sample dot product stays small and on one thread)."""
COLOUR_CHUNK_S = 60.0
"""The colour's history is pooled in chunks of this length [s] (at least the reference
window and ``10 x colour_lag_s``); a gap, a reset or an alarm ends a chunk early."""

LRV_BATCHES_S = (0.5, 1.0, 2.0, 4.0)
"""Batch lengths [s] over which :func:`long_run_ratio` looks for slow colour the whitening
left (the CUSUM's small reference value accumulates a wander of seconds)."""

PREFIX = "detector"
"""Prefix of the model-node parameters that configure the detector (``detector.learn_s``...)."""


@dataclass(frozen=True)
class DetectorConfig:
    """Settings of :class:`ChangeDetector`; :meth:`validated` checks them.

    Attributes:
        sample_rate_hz: nominal sample rate [Hz] (false-alarm period <-> samples).
        learn_s: length of the reference window after a (re)start [s].
        shift_sigma: mean shift to detect, in standard deviations of the residual of the output
            (sets ``k``); smaller shifts are detected later, larger ones sooner.
        false_alarm_period_s: design mean time between false alarms of the whole detector on a
            clean plant [s] (all outputs, both directions).
        max_gap_s: a stamp step longer than this is a gap [s] (the whitening skips a sample).
        max_phi: upper clip of the learned AR(1) coefficient [-].
        names: output names (residual order), default the contract's ``SPEED_NAMES``.
        colour_s: residual history the long-window whitening learns the residual's colour from
            [s]; until then, and with 0 always, every reference window whitens by its own
            ARMA(1, 1). See "Colour" below.
        colour_lag_s: longest lag of that whitening [s] (its AR order is chosen by AIC up to
            :attr:`colour_order_max`: this in samples, at most half a reference window).
    """

    sample_rate_hz: float = 1000.0
    learn_s: float = 20.0
    shift_sigma: float = 0.5
    false_alarm_period_s: float = 4.0 * 3600.0
    max_gap_s: float = 0.05
    max_phi: float = 0.995
    names: tuple[str, ...] = SPEED_NAMES
    colour_s: float = 300.0
    colour_lag_s: float = 3.0

    def validated(self) -> DetectorConfig:
        """Return ``self`` if every field is admissible, else raise :class:`ParameterError`
        naming the parameter (``detector.<field>``), the value and the admissible range."""
        def bad(name: str, value: object, what: str) -> ParameterError:
            return ParameterError(f"{PREFIX}.{name}: expected {what}, got {value!r}")

        def positive(name: str, value: object) -> float:
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value) or value <= 0:
                raise bad(name, value, "a finite number > 0")
            return float(value)

        rate = positive("sample_rate_hz", self.sample_rate_hz)
        learn = positive("learn_s", self.learn_s)
        if learn * rate < 100:
            raise bad("learn_s", self.learn_s,
                      f"at least 100 samples at {rate:g} Hz (>= {100 / rate:g} s)")
        positive("shift_sigma", self.shift_sigma)
        if self.shift_sigma > 20:
            raise bad("shift_sigma", self.shift_sigma, "a shift <= 20 residual sigmas")
        period = positive("false_alarm_period_s", self.false_alarm_period_s)
        if period * rate < 10:
            raise bad("false_alarm_period_s", self.false_alarm_period_s,
                      "a period of at least 10 samples")
        positive("max_gap_s", self.max_gap_s)
        if isinstance(self.max_phi, bool) or not isinstance(self.max_phi, int | float) \
                or not 0.0 <= self.max_phi < 1.0:
            raise bad("max_phi", self.max_phi, "a number in [0, 1)")
        if not self.names or len(set(self.names)) != len(self.names) \
                or not all(isinstance(n, str) and n for n in self.names):
            raise bad("names", self.names, "distinct non-empty output names")
        colour = self.colour_s
        if isinstance(colour, bool) or not isinstance(colour, int | float) \
                or not math.isfinite(colour) or colour < 0:
            raise bad("colour_s", colour, "a finite number >= 0 (0: no long-window whitening)")
        positive("colour_lag_s", self.colour_lag_s)
        lags = self.colour_order_max
        if colour > 0 and colour * rate < _COLOUR_LAGS_PER_ORDER * lags:
            raise bad("colour_s", colour,
                      f"at least {_COLOUR_LAGS_PER_ORDER} x the longest lag "
                      f"{lags / rate:g} s = {_COLOUR_LAGS_PER_ORDER * lags / rate:g} s, or 0")
        return self

    @property
    def colour_order_max(self) -> int:
        """Largest AR order of the long-window whitening: ``colour_lag_s`` in samples, at most
        half a reference window (which holds the whitening's history) and
        :data:`MAX_COLOUR_ORDER`."""
        return max(1, min(round(self.colour_lag_s * self.sample_rate_hz),
                          self.learn_samples // 2, MAX_COLOUR_ORDER))

    @property
    def colour_samples(self) -> int:
        """Samples of residual history the long-window whitening is learned from."""
        return round(self.colour_s * self.sample_rate_hz)

    @property
    def learn_samples(self) -> int:
        """Samples in a reference window."""
        return max(1, round(self.learn_s * self.sample_rate_hz))


@dataclass(frozen=True)
class Reference:
    """What a reference window taught the detector about one output.

    ``level`` [rad/s] the residual's level; ``phi``, ``theta`` [-] its ARMA(1, 1) coefficients
    (``(1 - phi B) c = (1 + theta B) a``); ``sigma_e`` [rad/s] innovation scale of ``a``;
    ``sigma`` [rad/s] the residual's robust scale (MAD); ``k`` and ``h`` [whitened sigma] the
    CUSUM reference value and threshold; ``arl0_s`` [s] the designed mean time between false
    alarms of one side of this output; ``last_r``, ``last_a`` the filter state at the window's
    end [rad/s]; ``order`` the AR order of the long-window whitening (0: the window's own
    ARMA(1, 1)); ``gain`` [-] the steady-state response of the whitened residual to a step of the
    residual (``(1 - phi) / (1 + theta)``, or ``1 - sum(a_j)`` of the AR whitening); ``lam`` [-]
    the long-run variance of the whitened residual relative to its variance that the design
    allowed for (1: white; above 1 while the colour is learned on less than ``colour_s``, and
    before the colour the window's own): the median of the points of its uncertainty over which
    the threshold is designed (:func:`long_run_spread`).
    """

    level: float
    phi: float
    theta: float
    sigma_e: float
    sigma: float
    k: float
    h: float
    arl0_s: float
    last_r: float = 0.0
    last_a: float = 0.0
    order: int = 0
    gain: float = 1.0
    lam: float = 1.0


@dataclass(frozen=True)
class Alarm:
    """A detected change.

    Attributes:
        stamp_s: stamp of the sample that raised the alarm [s] (the residual's stamp).
        change_s: estimated change time [s]: stamp of the first sample after the CUSUM's last
            zero before the alarm.
        output: index of the output (residual order); ``name`` its name.
        direction: ``+1`` residual increased (measured above predicted), ``-1`` decreased.
        statistic: the CUSUM value at the alarm; ``threshold`` its ``h`` [whitened sigma].
        samples: samples from ``change_s`` to ``stamp_s`` (inclusive).
        shift: estimated shift of the residual's level [rad/s] (signed).
        shift_sigma: the same in residual standard deviations [-].
        level, sigma: the reference level and residual scale [rad/s].
    """

    stamp_s: float
    change_s: float
    output: int
    name: str
    direction: int
    statistic: float
    threshold: float
    samples: int
    shift: float
    shift_sigma: float
    level: float
    sigma: float

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready)."""
        return asdict(self)

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict` (the payload of the model node's change topic)."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Alarm:
        """Inverse of :meth:`to_dict`; raises :class:`ParameterError` naming a missing or
        non-numeric field."""
        out: dict[str, Any] = {}
        for f in cls.__dataclass_fields__:
            if f not in data:
                raise ParameterError(f"alarm: field {f!r} missing")
            v = data[f]
            if f == "name":
                out[f] = str(v)
            elif f in ("output", "direction", "samples"):
                if isinstance(v, bool) or not isinstance(v, int):
                    raise ParameterError(f"alarm.{f}: expected an integer, got {v!r}")
                out[f] = v
            else:
                if isinstance(v, bool) or not isinstance(v, int | float):
                    raise ParameterError(f"alarm.{f}: expected a number, got {v!r}")
                out[f] = float(v)
        return cls(**out)


@dataclass
class DetectorCounters:
    """Running counts: ``samples`` given to :meth:`ChangeDetector.update`, ``tested`` samples
    that went through the CUSUM, ``skipped`` non-finite ones, ``gaps`` stamp gaps, ``alarms``,
    ``learned`` completed reference windows, ``colour_fits`` fits of the long-window
    whitening."""

    samples: int = 0
    tested: int = 0
    skipped: int = 0
    gaps: int = 0
    alarms: int = 0
    learned: int = 0
    colour_fits: int = 0
    last_alarm: Alarm | None = field(default=None)


# ---------------------------------------------------------------------- design (Siegmund)
def siegmund_arl(k: float | NDArray[np.float64], h: float | NDArray[np.float64],
                 drift: float | NDArray[np.float64] = 0.0) -> NDArray[np.float64]:
    """Siegmund's average run length [samples] of a one-sided CUSUM on N(drift, 1) increments.

    ``k`` reference value, ``h`` threshold, ``drift`` the increments' mean (all in sigma units).
    """
    delta = np.asarray(drift, dtype=float) - np.asarray(k, dtype=float)
    b = np.asarray(h, dtype=float) + SIEGMUND_OFFSET
    x = -2.0 * delta * b
    small = np.abs(delta) < 1e-9
    d = np.where(small, 1.0, delta)
    with np.errstate(over="ignore"):  # an infinite run length: no false alarm
        arl = (np.exp(np.minimum(x, 700.0)) + (-x) - 1.0) / (2.0 * d * d)
    return np.asarray(np.where(small, b * b, arl), dtype=float)


_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(7)
_GH_W = _GH_W / _GH_W.sum()


def _rates(k: float, h: NDArray[np.float64], learn_samples: int) -> NDArray[np.float64]:
    """:func:`false_alarm_rate` for every threshold in ``h`` (1-D), vectorised."""
    n = max(1, learn_samples)
    eps = (_GH_X / math.sqrt(n))[:, None, None]
    eta = (_GH_X * math.sqrt(_MAD_REL_VAR / n))[None, :, None]
    w = (_GH_W[:, None] * _GH_W[None, :])[:, :, None]
    scale = np.maximum(1.0 + eta, 0.5)
    kk = k * scale
    hh = np.asarray(h, dtype=float)[None, None, :] * scale
    rate = 1.0 / siegmund_arl(kk, hh, drift=-eps) + 1.0 / siegmund_arl(kk, hh, drift=eps)
    return np.asarray(np.sum(w * rate, axis=(0, 1)), dtype=float)


def false_alarm_rate(k: float, h: float, learn_samples: int) -> float:
    """Expected false alarms per sample of one output's two-sided CUSUM (both sides).

    Averaged over the reference window's estimation error (``learn_samples`` samples): level
    error ``eps ~ N(0, 1/L)``, relative scale error ``eta ~ N(0, 1.36/L)`` (7 x 7-point
    Gauss-Hermite); in the units of the true innovations a side then has reference
    ``k (1 + eta) +/- eps`` and threshold ``h (1 + eta)``.
    """
    return float(_rates(k, np.asarray([h], dtype=float), learn_samples)[0])


def design_threshold(k: float, rate_per_sample: float, learn_samples: int,
                     lams: Sequence[float] = (1.0,)) -> float:
    """Smallest ``h`` (to 0.1 %) whose :func:`false_alarm_rate` is at most ``rate_per_sample``;
    with several ``lams`` (long-run variance ratios of the whitened increments, each at least
    1) the rate averaged over them (the CUSUM acts as on unit increments with ``k`` and ``h``
    divided by ``sqrt(lam)``).

    Two vectorised grid passes (about 0.2 ms per ``lam``), cheap enough for the end of a
    reference window.
    """
    roots = [math.sqrt(v) for v in lams]

    def rates(h: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(np.mean([_rates(k / r, h / r, learn_samples) for r in roots], axis=0),
                          dtype=float)

    hi = 8.0
    while rates(np.asarray([hi]))[0] > rate_per_sample and hi < 1e6:
        hi *= 4.0
    lo = 0.0
    for _ in range(3):
        grid = np.linspace(lo, hi, 65)
        ok = rates(grid) <= rate_per_sample
        j = int(np.argmax(ok)) if ok.any() else grid.size - 1
        lo, hi = float(grid[max(j - 1, 0)]), float(grid[j])
        if hi - lo <= 1e-3 * hi:
            break
    return hi


_ACF_LAGS = 10  # autocorrelation lags used to estimate phi


def lagged_products(x: NDArray[np.float64], max_lag: int) -> NDArray[np.float64]:
    """``sum_t c_t c_(t+j)`` for ``j = 0..max_lag`` of ``x`` (1-D) centred on its own mean,
    shape ``(max_lag + 1,)`` (by FFT; zeros beyond the series' length)."""
    c = np.asarray(x, dtype=float) - float(np.mean(x))
    n = c.size
    size = 1 << max(1, (n + max_lag).bit_length())
    f = np.fft.rfft(c, size)
    out = np.fft.irfft(f * np.conj(f), size)[: max_lag + 1]
    if out.size < max_lag + 1:
        out = np.concatenate([out, np.zeros(max_lag + 1 - out.size)])
    out[n:] = 0.0
    return np.asarray(out, dtype=float)


def ar_by_aic(acov: NDArray[np.float64], n: int, max_order: int) -> NDArray[np.float64]:
    """AR coefficients ``a_1..a_p`` (``r_t = sum_j a_j r_(t-j) + e_t``) by Yule-Walker from the
    biased autocovariances ``acov`` (lags ``0..>= max_order``) of ``n`` samples, ``p`` by AIC
    (``n log var_p + 2 p``) among 0, 1, 2, 4, ... and ``max_order``; empty for ``p = 0``
    (a white residual) or a zero series."""
    from scipy.linalg import solve_toeplitz

    g = np.asarray(acov, dtype=float)
    if g.size < max_order + 1:
        raise ParameterError(f"acov: expected at least {max_order + 1} lags, got {g.size}")
    if not g[0] > 0:
        return np.zeros(0)
    orders = sorted({*(1 << e for e in range(max_order.bit_length()) if 1 << e <= max_order),
                     max_order})
    best, best_aic = np.zeros(0), n * math.log(float(g[0]))
    for order in orders:
        coef = np.asarray(solve_toeplitz(g[:order], g[1:order + 1]), dtype=float)
        var = float(g[0] - np.sum(coef * g[1:order + 1]))
        if not var > 0:
            break
        aic = n * math.log(var) + 2 * order
        if aic < best_aic:
            best, best_aic = coef, aic
    return best


def reference_from_window(window: NDArray[np.float64], config: DetectorConfig,
                          colour: NDArray[np.float64] | None = None,
                          lam: float | Sequence[float] | None = 1.0) -> Reference:
    """Learn one output's :class:`Reference` from its reference window (1-D, [rad/s]).

    ARMA(1, 1) by the method of moments on the winsorised, centred window: ``phi`` from the
    geometric decay of the autocorrelation (``sum rho[2..K] / sum rho[1..K-1]`` over the first
    K <= 10 lags whose autocorrelation exceeds ``2 / sqrt(n)``; 0 if none; clipped to
    [0, ``max_phi``]), ``theta`` from the lag-1 autocorrelation ``rho_e`` of
    ``e = c - phi c_prev`` (the invertible root of ``theta / (1 + theta^2) = rho_e``); the
    innovation scale from the MAD of ``a = e - theta a_prev`` (the whitened window).

    With ``colour`` (AR coefficients ``a_1..a_p`` of :func:`ar_by_aic`, learned on a long
    history) the window gives only the level and the scale: ``a_t = c_t - sum_j a_j c_(t-j)``
    from lag ``p`` on, ``phi`` and ``theta`` 0, ``order`` ``p``; ``lam`` (each at least 1) is
    the whitened residual's long-run variance ratio the threshold allows for (:func:`_design`):
    one value, or the points of its uncertainty (:func:`long_run_spread`). ``lam`` ``None``
    (no colour): the ratio the window's own whitened residual shows, with its uncertainty.
    """
    from scipy.signal import lfilter

    r = np.asarray(window, dtype=float)
    med = float(np.median(r))
    mad = float(np.median(np.abs(r - med))) * MAD_TO_SIGMA
    if mad > 0:
        r = np.clip(r, med - _WINSOR * mad, med + _WINSOR * mad)
    level = float(r.mean())
    c = r - level
    n = c.size
    if colour is not None:
        return _ar_reference(window, c, level, mad, np.asarray(colour, dtype=float), config,
                             _points(lam))
    # elementwise products, not BLAS dot: no thread pool wakes up inside the 1 kHz loop
    den = float(np.sum(c * c))
    phi = 0.0
    if den > 0 and n > 2 * _ACF_LAGS:
        rho = np.array([float(np.sum(c[j:] * c[:n - j])) / den
                        for j in range(1, _ACF_LAGS + 1)])
        # only lags whose autocorrelation is clearly above the noise (2 / sqrt(n)) count;
        # an uncorrelated window gives phi = 0 (not a random ratio of noise)
        sig = np.flatnonzero(rho <= 2.0 / math.sqrt(n))
        K = int(sig[0]) if sig.size else _ACF_LAGS  # rho[0..K-1] significant
        if K >= 2:
            phi = float(np.sum(rho[1:K])) / float(np.sum(rho[:K - 1]))
        elif K == 1:
            phi = max(float(rho[1]) / float(rho[0]), 0.0)
    phi = min(max(phi, 0.0), config.max_phi)
    e = c[1:] - phi * c[:-1]
    de = float(np.sum(e * e))
    rho_e = float(np.sum(e[1:] * e[:-1])) / de if de > 0 else 0.0
    rho_e = min(max(rho_e, -0.49), 0.49)
    theta = 0.0 if abs(rho_e) < 1e-9 else (1.0 - math.sqrt(1.0 - 4.0 * rho_e * rho_e)) / (
        2.0 * rho_e)
    a = np.asarray(lfilter([1.0], [1.0, theta], e), dtype=float)
    sigma_e = float(np.median(np.abs(a - np.median(a)))) * MAD_TO_SIGMA
    if not sigma_e > 0:
        sigma_e = float(np.std(a))
    if not sigma_e > 0:
        sigma_e = max(abs(level) * 1e-9, 1e-12)  # a constant residual: any change alarms
    sigma = mad if mad > 0 else sigma_e
    gain = (1.0 - phi) / (1.0 + theta)  # steady-state response of a to a step in r
    # no colour yet (lam None): allow for the slow colour the window's own whitening may
    # leave, over what the window can say about it (docs/loop.md "Limits", the first minute)
    lams = long_run_spread(a, config.sample_rate_hz) if lam is None else _points(lam)
    k, h, arl0_s = _design(sigma, sigma_e, gain, config, lams)
    return Reference(level=level, phi=phi, theta=theta, sigma_e=sigma_e, sigma=sigma, k=k,
                     h=h, arl0_s=arl0_s, last_r=float(window[-1]),
                     last_a=float(a[-1]) if a.size else 0.0, gain=gain, lam=_shown(lams))


def _points(lam: float | Sequence[float] | None) -> tuple[float, ...]:
    """``lam`` of :func:`reference_from_window` as points, each at least 1 (``None``: 1)."""
    if lam is None:
        return (1.0,)
    vals = (lam,) if isinstance(lam, (int, float)) else tuple(lam)
    return tuple(max(1.0, float(v)) for v in vals) or (1.0,)


def _shown(lams: Sequence[float]) -> float:
    """The one long-run variance ratio a :class:`Reference` shows for the points its threshold
    allows for: their median."""
    return float(np.median(np.asarray(lams, dtype=float)))


def _design(sigma: float, sigma_e: float, gain: float, config: DetectorConfig,
            lams: Sequence[float] = (1.0,)) -> tuple[float, float, float]:
    """``k``, ``h`` and one side's designed mean time between false alarms [s] of an output
    whose residual scale is ``sigma``, innovation scale ``sigma_e`` and step gain ``gain``;
    with ``lams`` (each at least 1) other than 1, ``h`` is designed for whitened increments of
    long-run variance ``lam`` (the CUSUM acts as on unit increments with ``k`` and ``h``
    divided by ``sqrt(lam)``), the false-alarm rate averaged over the ``lams`` given (equal
    weights: the points of its uncertainty, :func:`long_run_spread`)."""
    k = 0.5 * config.shift_sigma * sigma * gain / sigma_e
    n_sides = 2 * len(config.names)
    rate = 1.0 / (config.false_alarm_period_s * config.sample_rate_hz * n_sides)
    lams = list(_points(lams))
    h = design_threshold(k, 2.0 * rate, config.learn_samples, lams)
    side = float(np.mean([false_alarm_rate(k / math.sqrt(v), h / math.sqrt(v),
                                           config.learn_samples) for v in lams]))
    return k, h, 1.0 / (0.5 * side) / config.sample_rate_hz


def _batch_ratios(z: NDArray[np.float64], sample_rate_hz: float) -> list[tuple[float, int]]:
    """``(B mean square of the centred means of B samples / variance, number of means)`` of
    ``z`` (1-D) per batch length of :data:`LRV_BATCHES_S` with at least 4 batches."""
    x = np.asarray(z, dtype=float)
    x = x - float(np.mean(x)) if x.size else x
    var = float(np.mean(x * x)) if x.size else 0.0
    out: list[tuple[float, int]] = []
    if not var > 0:
        return out
    for secs in LRV_BATCHES_S:
        b = max(1, round(secs * sample_rate_hz))
        n = x.size // b
        if n < 4:
            break
        m = x[: n * b].reshape(n, b).mean(axis=1)
        out.append((b * float(np.mean(m * m)) / var, n))
    return out


def long_run_ratio(z: NDArray[np.float64], sample_rate_hz: float) -> float:
    """How much slow colour a whitened series ``z`` (1-D) still holds: the largest over the
    batch lengths :data:`LRV_BATCHES_S` of ``B`` times the mean square of its centred means of
    ``B`` samples over its variance (1 for white noise), at least 1; 1 when the series has
    fewer than 4 batches of the shortest length."""
    return max([1.0, *(r for r, _ in _batch_ratios(z, sample_rate_hz))])


SPREAD_POINTS = 16
"""Equal-probability points of the long-run variance ratio's uncertainty in
:func:`long_run_spread`."""
SPREAD_MIN_MEANS = 10
"""Fewest batch means a ratio of :func:`long_run_spread` is measured on (5 means of 4 s in a
20-s window put one threshold in ten above 15 times the white one)."""


def long_run_spread(z: NDArray[np.float64], sample_rate_hz: float) -> tuple[float, ...]:
    """The long-run variance ratio of ``z`` (1-D, whitened) with its sampling uncertainty, for
    a threshold that must hold whatever the ratio the series is consistent with (the
    detector's reference windows before it has a colour: 20 s cannot tell a slow wander from
    noise): :data:`SPREAD_POINTS` equal-probability points of the scale-inverse-chi2
    distribution of the largest batch-means ratio of :func:`long_run_ratio` over the batch
    lengths with at least :data:`SPREAD_MIN_MEANS` means, on its number of means minus 1
    degrees of freedom, each at least 1 (``(1.0,)`` when nothing can be measured)."""
    from scipy.stats import chi2

    ratios = [r for r in _batch_ratios(z, sample_rate_hz) if r[1] >= SPREAD_MIN_MEANS]
    if not ratios:
        return (1.0,)
    lam, n = max(ratios)
    dof = n - 1
    q = (np.arange(SPREAD_POINTS) + 0.5) / SPREAD_POINTS
    return tuple(max(1.0, float(v)) for v in lam * dof / chi2.ppf(1.0 - q, dof))


def _ar_reference(window: NDArray[np.float64], c: NDArray[np.float64], level: float,
                  mad: float, coef: NDArray[np.float64], config: DetectorConfig,
                  lams: Sequence[float] = (1.0,)) -> Reference:
    """:func:`reference_from_window` with the long-window whitening ``coef`` (``a_1..a_p``)."""
    p = coef.size
    a = _ar_whiten(c, coef)
    # the standard deviation, not the MAD: the window is winsorised already, and with the
    # small k of a slow residual the false-alarm rate follows the innovations' variance
    # closely (a MAD 2.4 % below it doubled the rate on the simulated plant's sun shaft)
    sigma_e = float(np.std(a)) if a.size else 0.0
    if not sigma_e > 0:
        sigma_e = max(abs(level) * 1e-9, 1e-12)  # a constant residual: any change alarms
    sigma = mad if mad > 0 else sigma_e
    # Yule-Walker on biased autocovariances is stationary: sum(a_j) < 1
    gain = max(1.0 - float(np.sum(coef)), 1e-6)
    k, h, arl0_s = _design(sigma, sigma_e, gain, config, lams)
    return Reference(level=level, phi=0.0, theta=0.0, sigma_e=sigma_e, sigma=sigma, k=k, h=h,
                     arl0_s=arl0_s, last_r=float(window[-1]), order=p, gain=gain,
                     lam=_shown(lams))


def _ar_whiten(x: NDArray[np.float64], coef: NDArray[np.float64]) -> NDArray[np.float64]:
    """``x`` (1-D) whitened by the AR ``coef`` (``a_1..a_p``): ``x_t - sum_j a_j x_(t-j)`` from
    lag ``p`` on (a level of ``x`` stays a level, times ``1 - sum_j a_j``)."""
    from scipy.signal import lfilter

    p = coef.size
    return np.asarray(lfilter(np.concatenate([[1.0], -coef]), [1.0], np.asarray(x, float)),
                      dtype=float)[p:]


def warm_up(config: DetectorConfig) -> None:
    """Learn one reference from noise, with and (when ``config`` has one) without a colour:
    the first end of a reference window, and the colour's first fit minutes later, then cost
    their milliseconds, not the imports (scipy.signal, scipy.linalg) and first calls that took
    seconds on a loaded machine (the model node calls this at start-up)."""
    window = np.random.default_rng(0).standard_normal(config.learn_samples)
    reference_from_window(window, config)
    if config.colour_s > 0:
        lags = config.colour_order_max
        colour = ar_by_aic(lagged_products(window, lags) / window.size, window.size, lags)
        reference_from_window(window, config, colour)


CARRIED_FORMAT = "dvt-detector-colour/1"
"""``format`` of a carried colour's file (:meth:`CarriedColour.save`)."""


@dataclass(frozen=True)
class CarriedColour:
    """The residual's colour of an earlier run, carried to the next start of the same model
    (``docs/loop.md``, "The first minute"): the AR coefficients ``a_1..a_p`` per output
    (:func:`ar_by_aic`) fitted on ``samples`` samples (at least ``colour_s``) of residual at
    ``sample_rate_hz`` [Hz], up to ``order_max`` lags, for the outputs ``names``; ``model`` names
    the model whose residual it is (the model node: :func:`dvt_model.config.model_key`)."""

    names: tuple[str, ...]
    sample_rate_hz: float
    order_max: int
    samples: int
    coef: tuple[tuple[float, ...], ...]
    model: str = ""

    def mismatch(self, config: DetectorConfig, model: str | None = None) -> str | None:
        """Why this colour cannot whiten a detector of ``config`` running ``model`` (``None``:
        any model), or ``None`` when it can."""
        if config.colour_s <= 0:
            return "the detector learns no colour (detector.colour_s is 0)"
        if tuple(config.names) != tuple(self.names):
            return f"outputs {list(self.names)}, the detector's {list(config.names)}"
        if not math.isclose(self.sample_rate_hz, config.sample_rate_hz, rel_tol=1e-9):
            return (f"sample_rate_hz {self.sample_rate_hz:g}, the detector's "
                    f"{config.sample_rate_hz:g} (detector.sample_rate_hz / block)")
        if self.order_max != config.colour_order_max:
            return (f"order_max {self.order_max}, the detector's {config.colour_order_max} "
                    "(detector.colour_lag_s)")
        if self.samples < config.colour_samples:
            return (f"samples {self.samples}: fitted on less than detector.colour_s "
                    f"({config.colour_samples} samples)")
        if model is not None and self.model != model:
            return f"model {self.model!r}, the model in use {model!r}"
        return None

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-ready), with ``format`` :data:`CARRIED_FORMAT`."""
        return {"format": CARRIED_FORMAT, "names": list(self.names),
                "sample_rate_hz": self.sample_rate_hz, "order_max": self.order_max,
                "samples": self.samples, "model": self.model,
                "coef": [list(c) for c in self.coef]}

    @classmethod
    def from_dict(cls, data: Any, source: str = "colour") -> CarriedColour:
        """Inverse of :meth:`to_dict`; raises :class:`ParameterError` naming ``source``, the
        field and the value (a wrong format, a missing field, a non-finite or non-stationary
        coefficient list, one per output)."""
        if not isinstance(data, dict):
            raise ParameterError(f"{source}: expected a JSON object, got {type(data).__name__}")
        if data.get("format") != CARRIED_FORMAT:
            raise ParameterError(f"{source}: format: expected {CARRIED_FORMAT!r}, got "
                                 f"{data.get('format')!r}")
        for key in ("names", "sample_rate_hz", "order_max", "samples", "coef"):
            if key not in data:
                raise ParameterError(f"{source}: field {key!r} missing")
        names, coef = data["names"], data["coef"]
        if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
            raise ParameterError(f"{source}: names: expected a list of output names, got "
                                 f"{names!r}")
        if not isinstance(coef, list) or len(coef) != len(names):
            raise ParameterError(f"{source}: coef: expected {len(names)} coefficient lists "
                                 f"(one per output of names), got {coef!r:.80}")
        rate, order, samples = data["sample_rate_hz"], data["order_max"], data["samples"]
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not rate > 0:
            raise ParameterError(f"{source}: sample_rate_hz: expected a positive number, got "
                                 f"{rate!r}")
        for key, v in (("order_max", order), ("samples", samples)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ParameterError(f"{source}: {key}: expected a positive integer, got {v!r}")
        out = []
        for name, c in zip(names, coef, strict=True):
            if not isinstance(c, list) or len(c) > order or not all(
                    not isinstance(x, bool) and isinstance(x, int | float) and math.isfinite(x)
                    for x in c):
                raise ParameterError(f"{source}: coef[{name}]: expected at most {order} finite "
                                     f"numbers, got {c!r:.80}")
            if c and not float(np.sum(c)) < 1.0:
                raise ParameterError(f"{source}: coef[{name}]: not stationary (coefficients "
                                     f"sum to {float(np.sum(c)):g}, at least 1)")
            out.append(tuple(float(x) for x in c))
        return cls(names=tuple(names), sample_rate_hz=float(rate), order_max=order,
                   samples=samples, coef=tuple(out), model=str(data.get("model", "")))

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write :meth:`to_dict` as JSON to ``path`` (a temporary file renamed over it: a
        reader never sees half a file)."""
        target = Path(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict()))
        os.replace(tmp, target)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> CarriedColour:
        """Read a file :meth:`save` wrote; :class:`ParameterError` naming the path (unreadable,
        not JSON, or a bad field: :meth:`from_dict`)."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise ParameterError(f"{path}: cannot read a carried colour: {exc}") from exc
        return cls.from_dict(data, str(path))


class ColourKeeper:
    """Carries a detector's colour between runs of the same model in one file (the model
    node's ``detector.colour_file``; ``docs/loop.md``, "The first minute").

    :meth:`load` at a start gives the colour to carry in (or why none); :meth:`after_update`
    after each detector sample writes the detector's own full colour (:meth:`ChangeDetector.
    carry`) whenever it is refitted (once a minute), once the model in use (``model``, a key
    such as :func:`dvt_model.config.model_key`) has run ``colour_s`` of residual: the colour
    is kept across model changes, so until then it may hold the residual of the model before;
    :meth:`model_changed` on every model change. ``saves`` counts the files written.
    """

    def __init__(self, path: str | os.PathLike[str], model: str) -> None:
        # a leading ~ is the user's home (a ROS parameter is not expanded by a shell)
        self.path = Path(path).expanduser()
        self.model = model
        self.saves = 0
        self._samples = 0  # detector samples of the model in use
        self._fits = 0

    def load(self, config: DetectorConfig) -> tuple[CarriedColour | None, str, bool]:
        """The colour the file carries for ``config`` and the model in use, or ``None``; one
        line for the log that says which and why; whether that line is a warning (a bad or
        unfitting file, not used and left as it is; a missing one is the first run's)."""
        if not self.path.exists():
            return None, (f"detector.colour_file: {self.path}: no colour carried yet (written "
                          f"once the colour has {config.colour_s:g} s of this model's "
                          "residual)"), False
        try:
            carried = CarriedColour.load(self.path)
        except ParameterError as exc:
            return None, f"detector.colour_file: not used, learning the colour anew: {exc}", True
        why = carried.mismatch(config, self.model)
        if why is not None:
            return None, (f"detector.colour_file: {self.path}: not used, learning the colour "
                          f"anew: {why}"), True
        return carried, (f"detector.colour_file: {self.path}: colour carried in (fitted on "
                         f"{carried.samples / config.sample_rate_hz:g} s of residual)"), False

    def model_changed(self, model: str) -> None:
        """A new model is in use from the next sample on."""
        self.model = model
        self._samples = 0

    def after_update(self, detector: ChangeDetector) -> str | None:
        """After each ``detector.update``: write its own full colour if it was just refitted
        and the model in use has given ``colour_s`` of samples; returns an error line if the
        file cannot be written (nothing else is lost), else ``None``."""
        self._samples += 1
        fits = detector.counters.colour_fits
        if fits == self._fits:
            return None
        self._fits = fits
        if detector.colour_carried or self._samples < detector.config.colour_samples:
            return None
        carried = detector.carry(self.model)
        if carried is None:
            return None
        try:
            carried.save(self.path)
        except OSError as exc:
            return f"detector.colour_file: {self.path}: cannot write the colour: {exc}"
        self.saves += 1
        return None


# -------------------------------------------------------------------------- the detector
class ChangeDetector:
    """Sequential change detector on the residual vector (see the module docstring).

    ``update(stamp_s, residual)`` per sample; ``reset()`` after the model changed (e.g. a push);
    ``counters`` and ``references`` for diagnostics. Not thread-safe.

    ``carried``: the colour of an earlier run of the same model (:meth:`carry`), used from the
    first reference window on until this run's own history reaches ``colour_s`` (then its own
    full colour replaces it, as below); ``h`` is designed over the long-run variance ratio of
    the residual whitened by it, with its uncertainty (out of sample: the carried colour never
    saw this run), measured on the first reference window, then again on each new chunk of the
    run (the reference in use whitened again). :class:`ParameterError` when it does not fit
    ``config`` (:meth:`CarriedColour.mismatch`).
    """

    def __init__(self, config: DetectorConfig | None = None,
                 carried: CarriedColour | None = None) -> None:
        self.config = (config or DetectorConfig()).validated()
        self.n = len(self.config.names)
        self._L = self.config.learn_samples
        self._buf = [[0.0] * self._L for _ in range(self.n)]
        self.counters = DetectorCounters()
        self.references: list[Reference] = []
        self._level = [0.0] * self.n
        self._phi = [0.0] * self.n
        self._theta = [0.0] * self.n
        self._prev_a = [0.0] * self.n
        self._inv_s = [1.0] * self.n
        self._k = [0.0] * self.n
        self._h = [0.0] * self.n
        self._prev = [0.0] * self.n
        self._hi = [0.0] * self.n
        self._lo = [0.0] * self.n
        self._hi_n = [0] * self.n
        self._lo_n = [0] * self.n
        self._hi_t = [0.0] * self.n
        self._lo_t = [0.0] * self.n
        self._filled = 0
        self._learn_from = math.nan
        self._last_stamp = -math.inf
        self._have_prev = False
        # long-window whitening ("Colour" in docs/loop.md): the current chunk of residual
        # history, the pooled lagged products of the chunks before it, the fitted AR
        # coefficients (reversed, per output) and a doubled ring of the last P residuals
        cfg = self.config
        self._P = cfg.colour_order_max if cfg.colour_s > 0 else 0
        self._chunk_len = max(round(COLOUR_CHUNK_S * cfg.sample_rate_hz), self._L,
                              _COLOUR_LAGS_PER_ORDER * self._P)
        self._chunk: list[list[float]] = [[] for _ in range(self.n)]
        self._chunk_end = -math.inf
        self._pool: deque[tuple[float, int, NDArray[np.float64]]] = deque()
        self._colour: list[NDArray[np.float64]] | None = None
        self._colour_fit_n = 0  # samples the latest colour was fitted on
        # its whitening's long-run variance ratio, as the points of its uncertainty
        self._colour_lam: list[tuple[float, ...]] = [(1.0,)] * self.n
        self._colour_used_n = 0  # ... and the colour the reference in use whitens by
        self._first_lam: float | None = None if self._P else 1.0
        self._colour_rev: list[NDArray[np.float64]] = []
        self._order = 0
        self._ring = np.zeros((self.n, 2 * max(self._P, 1)))
        self._w = 0
        self._hist = 0
        self._carried: CarriedColour | None = None
        self._carried_measured = False  # a chunk of this run measured the carried colour
        if carried is not None:
            why = carried.mismatch(self.config)
            if why is not None:
                raise ParameterError(f"carried colour: {why}")
            self._carried = carried
            self._colour = [np.asarray(c, dtype=float) for c in carried.coef]
        self.reset()

    # ------------------------------------------------------------------ state
    @property
    def learning(self) -> bool:
        """Whether the detector is collecting a reference window (not testing)."""
        return self._filled < self._L

    @property
    def learn_progress(self) -> float:
        """Fraction of the reference window collected [0..1]."""
        return min(1.0, self._filled / self._L)

    @property
    def colour_progress(self) -> float:
        """Fraction of the long-window whitening's full history (``colour_s``) collected
        [0..1] (1 once the colour has been fitted on all of it; 0 without one)."""
        if self._P == 0:
            return 0.0
        if self._colour_fit_n >= self.config.colour_samples:  # the latest fit had it all
            return 1.0
        pooled = sum(m for _, m, _ in self._pool) + len(self._chunk[0])
        return min(1.0, pooled / self.config.colour_samples)

    @property
    def colour_in_use(self) -> bool:
        """Whether the samples tested now are whitened by a long-window colour (from the end
        of the first reference window after its first fit on, one chunk into the history)."""
        return self._order > 0

    @property
    def colour_in_use_s(self) -> float:
        """Residual history [s] the colour the samples are whitened by was fitted on (0
        before the first fit): below ``colour_s`` while the history grows."""
        return self._colour_used_n / self.config.sample_rate_hz if self._order else 0.0

    @property
    def colour_complete(self) -> bool:
        """Whether the samples tested now are whitened by a colour fitted on the full
        ``colour_s`` of history (the detector's design holds from here on)."""
        return self._order > 0 and self._colour_used_n >= self.config.colour_samples

    @property
    def colour_carried(self) -> bool:
        """Whether the colour in use is one carried from an earlier run (until this run's own
        history reaches ``colour_s``)."""
        return self._carried is not None

    def carry(self, model: str = "") -> CarriedColour | None:
        """The colour to carry to the next start of ``model``: this run's own once fitted on
        the full ``colour_s``, else the one carried in if still in use, else ``None``."""
        if self._carried is not None:
            return self._carried
        if self._colour is None or self._colour_fit_n < self.config.colour_samples:
            return None
        cfg = self.config
        return CarriedColour(names=tuple(cfg.names), sample_rate_hz=cfg.sample_rate_hz,
                             order_max=self._P, samples=self._colour_fit_n,
                             coef=tuple(tuple(float(x) for x in a) for a in self._colour),
                             model=model)

    @property
    def colour_history_s(self) -> float:
        """Residual history pooled for the long-window whitening [s] (whole chunks only)."""
        return sum(m for _, m, _ in self._pool) / self.config.sample_rate_hz

    def reset(self) -> None:
        """Forget the reference and start learning a new one (the CUSUMs restart at 0); the
        residual's colour learned on the long window is kept, the chunk in progress dropped
        (the model may have changed)."""
        for ch in self._chunk:
            ch.clear()
        self._relearn()

    def _relearn(self) -> None:
        self._filled = 0
        self._have_prev = False
        self._learn_from = math.nan
        self.references = []
        for i in range(self.n):
            self._hi[i] = self._lo[i] = 0.0
            self._hi_n[i] = self._lo_n[i] = 0

    def statistics(self) -> list[tuple[float, float]]:
        """``(S+, S-)`` per output [whitened sigma] (0 while learning)."""
        return [(self._hi[i], self._lo[i]) for i in range(self.n)]

    def status(self) -> dict[str, str]:
        """Key/values for a ``DiagnosticStatus`` (units in the keys)."""
        c = self.counters
        out = {"state": "learning" if self.learning else "testing",
               "learn_progress": f"{self.learn_progress:.2f}",
               "colour_progress": f"{self.colour_progress:.2f}",
               "colour_carried": str(self.colour_carried).lower(),
               "samples": str(c.samples), "tested": str(c.tested), "skipped": str(c.skipped),
               "gaps": str(c.gaps), "alarms": str(c.alarms),
               "false_alarm_period_s": f"{self.config.false_alarm_period_s:g}"}
        for i, ref in enumerate(self.references):
            name = self.config.names[i]
            out.update({f"{name}.sigma_rad_s": f"{ref.sigma:.6g}", f"{name}.phi": f"{ref.phi:.4f}",
                        f"{name}.k": f"{ref.k:.4g}", f"{name}.h": f"{ref.h:.4g}",
                        f"{name}.ar_order": str(ref.order), f"{name}.lam": f"{ref.lam:.3g}",
                        f"{name}.cusum_up": f"{self._hi[i]:.3g}",
                        f"{name}.cusum_down": f"{self._lo[i]:.3g}"})
        if c.last_alarm is not None:
            out["last_alarm_change_s"] = f"{c.last_alarm.change_s:.6f}"
        return out

    # --------------------------------------------------------------- per sample
    def update(self, stamp_s: float, residual: Sequence[float]) -> Alarm | None:
        """Feed one residual sample (stamp [s], one value [rad/s] per output); O(1).

        Returns an :class:`Alarm` when a change is detected (the detector then re-learns),
        else ``None``. Raises :class:`ParameterError` if ``residual`` has the wrong length.
        """
        n = self.n
        if len(residual) != n:
            raise ParameterError(f"residual: expected {n} values ({', '.join(self.config.names)})"
                                 f", got {len(residual)}")
        c = self.counters
        c.samples += 1
        for i in range(n):
            if not math.isfinite(residual[i]):
                c.skipped += 1
                self._have_prev = False
                if self._P:
                    self._end_chunk()
                return None
        t = float(stamp_s)
        gap = not (0.0 < t - self._last_stamp <= self.config.max_gap_s)
        self._last_stamp = t
        if self._P:
            if gap:
                self._end_chunk()
            for i in range(n):
                self._chunk[i].append(float(residual[i]))
            self._chunk_end = t
            if len(self._chunk[0]) >= self._chunk_len and self._end_chunk():
                return None  # a first or a full colour: a new reference window starts now
        if self._filled < self._L:
            j = self._filled
            if gap and j:  # a reference window is contiguous: a gap starts it again
                c.gaps += 1
                j = 0
            if j == 0:
                self._learn_from = t
            for i in range(n):
                self._buf[i][j] = float(residual[i])
            self._filled = j + 1
            if self._filled == self._L:
                self._finish_learning()
                self._have_prev = True
            return None
        if self._order:
            return self._update_ar(t, residual, gap)
        if gap or not self._have_prev:
            if gap:
                c.gaps += 1
            for i in range(n):
                self._prev[i] = float(residual[i])
                self._prev_a[i] = 0.0
            self._have_prev = True
            return None
        c.tested += 1
        alarm: Alarm | None = None
        for i in range(n):
            r = float(residual[i])
            lev = self._level[i]
            a = (r - lev) - self._phi[i] * (self._prev[i] - lev) - self._theta[i] * self._prev_a[i]
            self._prev[i] = r
            self._prev_a[i] = a
            if self._cusum(i, a * self._inv_s[i], t) and alarm is None:
                alarm = self._alarm(i, t, up=self._hi[i] >= self._lo[i])
        if alarm is not None:
            self._after_alarm(alarm)
        return alarm

    def _cusum(self, i: int, z: float, t: float) -> bool:
        """One step of output ``i``'s two CUSUMs on the whitened sample ``z`` (stamp ``t``);
        whether either is above ``h``."""
        k = self._k[i]
        hi = self._hi[i] + z - k
        if hi > 0.0:
            if self._hi[i] == 0.0:
                self._hi_t[i] = t
                self._hi_n[i] = 0
            self._hi_n[i] += 1
        else:
            hi = 0.0
        lo = self._lo[i] - z - k
        if lo > 0.0:
            if self._lo[i] == 0.0:
                self._lo_t[i] = t
                self._lo_n[i] = 0
            self._lo_n[i] += 1
        else:
            lo = 0.0
        self._hi[i] = hi
        self._lo[i] = lo
        h = self._h[i]
        return hi > h or lo > h

    def _update_ar(self, t: float, residual: Sequence[float], gap: bool) -> Alarm | None:
        """:meth:`update` of a testing sample with the long-window whitening."""
        c = self.counters
        P = self._P
        if gap:
            c.gaps += 1
            self._hist = 0
        w = self._w
        ring = self._ring
        test = self._hist >= self._order
        if test:
            c.tested += 1
        alarm: Alarm | None = None
        for i in range(self.n):
            r = float(residual[i])
            if test:
                coef = self._colour_rev[i]
                p = coef.size
                # a BLAS dot of at most MAX_COLOUR_ORDER elements: OpenBLAS runs it on the
                # calling thread (its pool starts above 10 000), a third of np.sum(a * b)
                pred = float(np.dot(coef, ring[i, w + P - p:w + P])) if p else 0.0
                z = (r - pred - self._level[i]) * self._inv_s[i]
                if self._cusum(i, z, t) and alarm is None:
                    alarm = self._alarm(i, t, up=self._hi[i] >= self._lo[i])
            ring[i, w] = r
            ring[i, w + P] = r
        self._w = w + 1 if w + 1 < P else 0
        if self._hist < P:
            self._hist += 1
        if alarm is not None:
            self._after_alarm(alarm)
        return alarm

    def _after_alarm(self, alarm: Alarm) -> None:
        """Count the alarm, drop the residual history since its change time from the colour's
        chunks (it holds the change) and learn a new reference."""
        c = self.counters
        c.alarms += 1
        c.last_alarm = alarm
        if self._P:
            while self._pool and self._pool[-1][0] >= alarm.change_s:
                self._pool.pop()
        self.reset()

    def _end_chunk(self) -> bool:
        """Pool the chunk in progress (if long enough) and refit the colour once a whole
        chunk is pooled, on the newest ``colour_s`` at most. Returns whether a new reference
        window starts: at the colour's first fit (the present window was whitened otherwise)
        and at its first fit on the full ``colour_s`` while a shorter one is in use."""
        m = len(self._chunk[0])
        if m < _COLOUR_LAGS_PER_ORDER * self._P:
            for ch in self._chunk:
                ch.clear()
            return False
        P = self._P
        raw = [np.asarray(ch, dtype=float) for ch in self._chunk]
        prods = np.stack([lagged_products(x, P) for x in raw])
        for ch in self._chunk:
            ch.clear()
        self._pool.append((self._chunk_end, m, prods))
        need = self.config.colour_samples
        total = sum(mm for _, mm, _ in self._pool)
        while self._pool and total - self._pool[0][1] >= need:
            total -= self._pool.popleft()[1]
        if self._carried is not None and total < need:
            # the carried colour stays until this run's own history is full; how far it
            # whitens this run, measured again on the newest chunk (out of sample), and the
            # reference in use whitened again with it, as a growing colour is
            self._colour_lam = self._left_ratio(raw, self._carried.coef)
            self._carried_measured = True
            if not self.learning and self._order > 0:
                self._rewhiten()
            return False
        if total < min(need, self._chunk_len):
            return False
        acov = np.sum([pp for _, _, pp in self._pool], axis=0) / total
        first = self._colour is None
        previous = self._colour
        self._carried = None
        self._colour = [ar_by_aic(acov[i], total, P) for i in range(self.n)]
        self._colour_fit_n = total
        self.counters.colour_fits += 1
        # the slow colour a colour on less than colour_s leaves: measured on this chunk
        # whitened by the colour before it (out of sample; the first by its own, in sample),
        # allowed for in the threshold until the colour has its full history (then the
        # design holds: docs/loop.md "Colour")
        self._colour_lam = ([(1.0,)] * self.n if total >= need else self._left_ratio(
            raw, self._colour if previous is None else previous))
        # a colour on the full history replaces a shorter one in a reference being tested
        # (one being learned takes the newest colour when it ends)
        testing = not self.learning and self._order > 0
        grown = testing and total >= need and self._colour_used_n < need
        if first or grown:
            self._relearn()
        elif testing and self._colour_used_n < need:
            self._rewhiten()  # a longer, not yet full history: the same reference window
        return first or grown

    def _alarm(self, i: int, t: float, up: bool) -> Alarm:
        ref = self.references[i]
        stat = self._hi[i] if up else self._lo[i]
        count = self._hi_n[i] if up else self._lo_n[i]
        # CUSUM estimate of the whitened shift: k + S / n; back to the residual's units.
        dz = ref.k + stat / max(count, 1)
        shift = (1.0 if up else -1.0) * dz * ref.sigma_e / max(ref.gain, 1e-9)
        return Alarm(stamp_s=t, change_s=self._hi_t[i] if up else self._lo_t[i], output=i,
                     name=self.config.names[i], direction=1 if up else -1, statistic=stat,
                     threshold=ref.h, samples=count, shift=shift,
                     shift_sigma=shift / ref.sigma, level=ref.level, sigma=ref.sigma)

    def _left_ratio(self, series: Sequence[Any], colour: Sequence[Any]
                    ) -> list[tuple[float, ...]]:
        """Per output, the long-run variance ratio that ``colour`` (AR coefficients per
        output) leaves in ``series`` (1-D per output, [rad/s]) once whitened by it, with its
        uncertainty (:func:`long_run_spread`)."""
        return [long_run_spread(_ar_whiten(np.asarray(series[i], dtype=float),
                                           np.asarray(colour[i], dtype=float)),
                                self.config.sample_rate_hz) for i in range(self.n)]

    def _rewhiten(self) -> None:
        """Whiten by the newest colour (on a longer, not yet full history) from now on: the
        references of the same reference window again, with its long-run variance ratio;
        the CUSUMs restart at 0 (testing goes on, no new window)."""
        self._finish_learning(count=False)

    def _finish_learning(self, count: bool = True) -> None:
        colour = self._colour
        if self._carried is not None and not self._carried_measured:
            # how far the carried colour whitens this run: this window whitened by it (until
            # a chunk of this run measures it, :meth:`_end_chunk`)
            self._colour_lam = self._left_ratio(self._buf, self._carried.coef)
        refs = [reference_from_window(np.asarray(self._buf[i]), self.config,
                                      None if colour is None else colour[i],
                                      self._colour_lam[i] if colour is not None else
                                      self._first_lam)
                for i in range(self.n)]
        self.references = refs
        if colour is not None:
            self._colour_used_n = self._colour_fit_n
            self._colour_rev = [np.ascontiguousarray(a[::-1]) for a in colour]
            # history needed before testing; at least 1 so that a white output (order 0)
            # still marks the colour as in use
            self._order = max(1, *(a.size for a in colour))
            if count:  # a rewhitening keeps the history the ring holds
                P = self._P
                for i in range(self.n):
                    tail = np.asarray(self._buf[i][-P:], dtype=float)
                    self._ring[i, :P] = tail
                    self._ring[i, P:] = tail
                self._w = 0
                self._hist = P
        for i, ref in enumerate(refs):
            self._level[i] = ref.level
            self._phi[i] = ref.phi
            self._theta[i] = ref.theta
            self._prev[i] = ref.last_r
            self._prev_a[i] = ref.last_a
            self._inv_s[i] = 1.0 / ref.sigma_e
            if ref.order or colour is not None:
                self._level[i] = ref.level * ref.gain  # subtracted from r - prediction
            self._k[i] = ref.k
            self._h[i] = ref.h
            self._hi[i] = self._lo[i] = 0.0
        if count:
            self.counters.learned += 1
