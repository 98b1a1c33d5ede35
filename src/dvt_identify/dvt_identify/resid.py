"""Residual analysis like MATLAB ``resid``, with bounds that stay valid for coloured signals.

For every output ``j`` (residual ``e = y - yhat``, per segment mean removed, products never taken
across segment boundaries):

- whiteness: normalised autocorrelation ``rho_ee(k)``, ``k = 0..L`` (default L = 25), with the
  per-lag 99 % bound ``z / sqrt(N)`` (valid under the null of a white residual); the decision is
  the Ljung-Box statistic ``Q = N (N + 2) sum_k rho_ee(k)^2 / (N - k)`` against chi2(L);
- independence from each input ``i``: cross-correlation ``rho_eu(k) = r_eu(k) / sqrt(r_ee(0)
  r_uu(0))`` with ``r_eu(k) = (1/N) sum_t e(t + k) u(t)`` for ``k = -L..L`` (positive lags: the
  residual after the input). Under the null of no correlation between a coloured residual and a
  coloured input, Bartlett's formula gives ``var rho_eu(k) ~ (1/N) sum_j rho_ee(j) rho_uu(j)``;
  the sum runs over ``|j| <= M`` (``M = min(N/4, 10 sqrt(N))``) with a Bartlett (triangular)
  window. The test bound is ``z' sqrt(var)`` with ``z'`` the Sidak-corrected quantile for the
  2L + 1 lags, so that the whole test (not each lag) has 99 % confidence; the per-lag bound
  ``z sqrt(var)`` is reported too, and so is MATLAB's ``z / sqrt(N)``
  (``ccf_bound_white``): it is only right when one of the two is white, and is far too tight for
  slowly varying inputs.

For an output-error model only the independence test is a test of the model (OE models the noise
as whatever is left); the whiteness test says how coloured the remaining error is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal, stats
from scipy.fft import next_fast_len

from dvt_identify.data import Segment
from dvt_identify.discrete import simulate_linear, zoh
from dvt_identify.uncertainty import NoiseFloor, noise_floor

Array = NDArray[np.float64]


def _xcorr_sum(a: Array, b: Array, maxlag: int) -> Array:
    """``sum_t a(t + k) b(t)`` for ``k = -maxlag..maxlag`` (FFT), shape (2 maxlag + 1,)."""
    n = a.size
    m = min(maxlag, n - 1)
    # zero-padded to n + m: no lag up to m wraps around (a fast length, not 2 n: 3-4x less)
    size = next_fast_len(n + m, real=True)
    fa = np.fft.rfft(a, size)
    fb = np.fft.rfft(b, size)
    c = np.fft.irfft(fa * np.conj(fb), size)
    # c[k] = sum_t a(t + k) b(t) for k >= 0; c[size - k] for negative k
    out = np.zeros(2 * maxlag + 1)
    pos = c[: m + 1]
    neg = c[size - m:][::-1] if m > 0 else np.zeros(0)
    out[maxlag: maxlag + m + 1] = pos
    out[maxlag - m: maxlag] = neg[::-1]
    return out


def _pooled(xs: Sequence[Array], ys: Sequence[Array], maxlag: int) -> tuple[Array, int]:
    tot = np.zeros(2 * maxlag + 1)
    n = 0
    for a, b in zip(xs, ys, strict=True):
        tot += _xcorr_sum(a - a.mean(), b - b.mean(), maxlag)
        n += a.size
    return tot / n, n


@dataclass(frozen=True)
class OutputResidual:
    """Residual analysis of one output.

    Attributes:
        output: output name.
        lags: the lag count L.
        acf: ``rho_ee(k)``, ``k = 0..L``, shape (L + 1,).
        acf_bound: per-lag 99 % bound ``z / sqrt(N)`` (as MATLAB draws it).
        ljung_box, ljung_box_p: Q statistic and its p-value (chi2, L dof).
        white: Ljung-Box p >= 1 - confidence (one test over all lags).
        ccf: input name -> ``rho_eu(k)`` for ``k = -L..L``, shape (2L + 1,).
        ccf_bound: input name -> Bartlett bound at the family-wise level (the test bound).
        ccf_bound_per_lag: input name -> Bartlett bound for one lag at the given level.
        ccf_bound_white: MATLAB-style ``z / sqrt(N)``.
        independent: input name -> all ``|rho_eu(k)|`` within the family-wise Bartlett bound.
        max_ccf_ratio: input name -> ``max_k |rho_eu(k)| / bound``.
        n: pooled sample count.
    """

    output: str
    lags: int
    acf: Array
    acf_bound: float
    ljung_box: float
    ljung_box_p: float
    white: bool
    ccf: dict[str, Array]
    ccf_bound: dict[str, float]
    ccf_bound_per_lag: dict[str, float]
    ccf_bound_white: float
    independent: dict[str, bool]
    max_ccf_ratio: dict[str, float]
    n: int

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        return {
            "lags": self.lags, "acf": self.acf.tolist(), "acf_bound": self.acf_bound,
            "ljung_box": self.ljung_box, "ljung_box_p": self.ljung_box_p, "white": self.white,
            "ccf": {k: v.tolist() for k, v in self.ccf.items()},
            "ccf_bound": self.ccf_bound, "ccf_bound_per_lag": self.ccf_bound_per_lag,
            "ccf_bound_white": self.ccf_bound_white,
            "independent": self.independent, "max_ccf_ratio": self.max_ccf_ratio, "n": self.n,
        }


def residual_analysis(residuals: Sequence[Array], inputs: Sequence[Array],
                      output_names: Sequence[str], input_names: Sequence[str], lags: int = 25,
                      confidence: float = 0.99) -> list[OutputResidual]:
    """Whiteness and input-independence tests per output.

    Args:
        residuals: per segment, ``y - yhat`` of shape (N_i, ny).
        inputs: per segment, inputs of shape (N_i, nu).
        output_names, input_names: ny and nu names.
        lags: L (MATLAB's default 25).
        confidence: two-sided level of the bounds (0.99).

    Returns:
        One :class:`OutputResidual` per output.
    """
    es = [np.asarray(e, float).reshape(len(e), -1) for e in residuals]
    us = [np.asarray(u, float).reshape(len(u), -1) for u in inputs]
    n_total = sum(e.shape[0] for e in es)
    z = float(stats.norm.ppf(0.5 + confidence / 2.0))
    # familywise over the 2L + 1 lags (Sidak): the test as a whole has the given confidence
    z_fw = float(stats.norm.ppf(0.5 + confidence ** (1.0 / (2 * lags + 1)) / 2.0))
    big_m = int(min(n_total // 4, 10 * np.sqrt(n_total)))
    big_m = max(big_m, lags)
    win = 1.0 - np.abs(np.arange(-big_m, big_m + 1)) / (big_m + 1)
    out = []
    for j, oname in enumerate(output_names):
        e_cols = [e[:, j] for e in es]
        ree, n = _pooled(e_cols, e_cols, big_m)
        r0 = ree[big_m]
        rho_ee = ree / r0 if r0 > 0 else np.zeros_like(ree)
        acf = rho_ee[big_m: big_m + lags + 1]
        k = np.arange(1, lags + 1)
        q = float(n * (n + 2) * np.sum(acf[1:] ** 2 / (n - k)))
        p = float(stats.chi2.sf(q, lags))
        bound = z / np.sqrt(n)
        white = bool(p >= 1.0 - confidence)
        ccf, cb, cbl, ind, ratio = {}, {}, {}, {}, {}
        for i, iname in enumerate(input_names):
            u_cols = [u[:, i] for u in us]
            ruu, _ = _pooled(u_cols, u_cols, big_m)
            u0 = ruu[big_m]
            reu, _ = _pooled(e_cols, u_cols, lags)
            if u0 <= 0 or r0 <= 0:
                rho = np.zeros(2 * lags + 1)
                b = bound
            else:
                rho = reu / np.sqrt(r0 * u0)
                var = float(np.sum(win * rho_ee * (ruu / u0))) / n
                b = z_fw * np.sqrt(max(var, 1.0 / n))
            ccf[iname] = rho
            cb[iname] = float(b)
            cbl[iname] = float(b * z / z_fw)
            ind[iname] = bool(np.all(np.abs(rho) <= b))
            ratio[iname] = float(np.max(np.abs(rho)) / b)
        out.append(OutputResidual(output=oname, lags=lags, acf=acf, acf_bound=float(bound),
                                  ljung_box=q, ljung_box_p=p, white=white, ccf=ccf,
                                  ccf_bound=cb, ccf_bound_per_lag=cbl,
                                  ccf_bound_white=float(bound), independent=ind,
                                  max_ccf_ratio=ratio, n=n))
    return out


@dataclass(frozen=True)
class Spectrum:
    """Welch power spectral density of a residual.

    Attributes:
        freq: frequencies [Hz], shape (K,).
        psd: density [unit^2/Hz], shape (K,).
        peak_hz: frequency of the most prominent peak (from the fifth bin up).
        peak_ratio: its prominence: density over the median density within +-half an octave.
    """

    freq: Array
    psd: Array
    peak_hz: float
    peak_ratio: float


def residual_spectrum(residuals: Sequence[Array], dt: float, nperseg: int = 2048) -> Spectrum:
    """Welch PSD of 1-D residuals (averaged over segments, each at least 16 samples)."""
    psds = []
    freq = np.zeros(0)
    for e in residuals:
        e = np.asarray(e, float)
        if e.size < 16:
            continue
        freq, p = signal.welch(e - e.mean(), fs=1.0 / dt, nperseg=min(nperseg, e.size))
        psds.append(p)
    if not psds:
        return Spectrum(np.zeros(1), np.zeros(1), 0.0, 0.0)
    size = min(len(p) for p in psds)
    psd = np.mean([p[:size] for p in psds], axis=0)
    freq = freq[:size]
    if size < 8:
        return Spectrum(freq, psd, 0.0, 0.0)
    # prominence: density over the median density within +-half an octave
    logf = np.log2(np.maximum(freq, freq[1]))  # non-decreasing: each window is a slice
    lo = np.searchsorted(logf, logf - 0.5, side="left")
    hi = np.searchsorted(logf, logf + 0.5, side="right")
    best, best_i = 0.0, 0
    for i in range(4, size):
        bg = float(np.median(psd[lo[i]:hi[i]]))
        if bg > 0 and psd[i] / bg > best:
            best, best_i = float(psd[i] / bg), i
    return Spectrum(freq, psd, float(freq[best_i]), best)


def robust_white_floor(xs: Sequence[Array]) -> float:
    """White-noise std of a signal, robust to sparse jumps (a PRBS switching, a set-point step)
    and to smooth content: the smaller of ``1.4826 MAD(diff x) / sqrt(2)`` and
    ``1.4826 MAD(diff^2 x) / sqrt(6)`` pooled over segments (both equal the std of white
    noise; the first difference of a smooth signal is its slope, which the second difference
    all but removes: measured on a low-pass random force, the first-difference figure took the
    force's slope for noise and made an output-error residual read 0 % structured)."""
    d1 = [np.diff(np.asarray(x, float).reshape(-1)) for x in xs if np.size(x) > 1]
    d2 = [np.diff(d) for d in d1 if d.size > 1]
    out = []
    for parts, k in ((d1, math.sqrt(2.0)), (d2, math.sqrt(6.0))):
        d = np.concatenate(parts) if parts else np.zeros(0)
        d = d[np.isfinite(d)]
        if d.size:
            mad = float(np.median(np.abs(d - np.median(d))))
            out.append(1.4826 * mad / k)
    return min(out) if out else 0.0


def input_noise_response(A: Array, B: Array, dt: float, input_std: Sequence[float],
                         n: int = 20000, seed: int = 0) -> Array:
    """Variance of each output (state) of ``x' = A x + B u`` driven by white input noise of std
    ``input_std`` per input held over each sample (what an output-error simulation fed with
    measured, noisy inputs carries in its error), shape (nx,)."""
    nx, nu = B.shape
    if nx == 0 or nu == 0 or not np.any(np.asarray(input_std) > 0):
        return np.zeros(nx)
    if np.max(np.linalg.eigvals(A).real, initial=-np.inf) >= 0:
        return np.full(nx, np.nan)  # an integrator or unstable part: no stationary variance
    Ad, Gd = zoh(A, dt)
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, nu)) * np.asarray(input_std, float)[None, :]
    x = simulate_linear(Ad, (u @ B.T) @ Gd.T, np.zeros(nx))
    burn = min(n // 5, 2000)
    return np.asarray(np.var(x[burn:], axis=0), dtype=float)


STRUCTURED_SHARE = 0.75
"""A residual is called structured (coloured beyond the sensors) only when at least this share
of its variance lies above the sensor noise floor (:func:`residual_floors`), i.e. its structured
part's RMS is at least sqrt(3) times the floor's. Measured on the committed recordings
(validated on independent offline runs): clean ``ident-none-1`` 0 % (sun shaft) and 61 %
(carrier 3); ``ident-windage`` before windage is modelled 80 % and 94 %. The report's verdict
and the augment loop's stopping rule (:mod:`dvt_identify.loop`) both use it."""


def residual_floors(A: Array, B: Array, C: Array | None, segments: Sequence[Segment],
                    predictions: Sequence[Array]) -> list[NoiseFloor]:
    """Noise floor and structured share of each output's residual ``y - prediction`` over
    ``segments`` (each with ``y`` (N, ny), ``u`` (N, nu), ``dt``), pooled; one
    :class:`~dvt_identify.uncertainty.NoiseFloor` per output.

    The floor is what the sensors alone leave in an output-error residual: the output's white
    noise (from the residual's first difference, :func:`dvt_identify.uncertainty.noise_floor`)
    plus the response of the model's linear part ``(A, B)`` (outputs ``C x``; ``None``: the
    states) to the white noise of the measured inputs (robust first-difference floor of each
    input, :func:`input_noise_response`): an OE simulation is driven by the measured, noisy
    inputs. ``floor_rms`` is their sum in quadrature (at most the RMS) and
    ``structured_share`` the rest of the variance."""
    segs = list(segments)
    if not segs:
        return []
    ys = [np.asarray(s.y, float) for s in segs]
    ny = ys[0].shape[1]
    floors = [noise_floor([y[:, j] - p[:, j] for y, p in zip(ys, predictions, strict=True)])
              for j in range(ny)]
    try:
        u_std = [robust_white_floor([np.asarray(s.u, float)[:, i] for s in segs])
                 for i in range(B.shape[1])]
        var_x = input_noise_response(A, B, float(segs[0].dt), u_std)
        var_in = var_x if C is None else (np.asarray(C, float) ** 2) @ var_x
    except (np.linalg.LinAlgError, ValueError):
        var_in = np.zeros(ny)
    out: list[NoiseFloor] = []
    for j, nf in enumerate(floors):
        vi = float(var_in[j]) if j < var_in.size and np.isfinite(float(var_in[j])) else 0.0
        var = nf.rms ** 2
        if not np.isfinite(var) or var <= 0:
            out.append(nf)
            continue
        fl = min(nf.floor_rms ** 2 + vi, var)
        out.append(NoiseFloor(rms=nf.rms, floor_rms=float(np.sqrt(fl)),
                              structured_share=float(np.clip(1.0 - fl / var, 0.0, 1.0))))
    return out
