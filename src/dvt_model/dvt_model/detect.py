"""Change detection on the model residual: ARMA(1,1)-whitened two-sided CUSUM per output (pure).

The model node feeds every residual sample (measured minus predicted speed [rad/s], one value
per output of :data:`~dvt_model.contract.SPEED_NAMES`) to :meth:`ChangeDetector.update`; the
detector answers ``None`` or an :class:`Alarm`. O(1) per sample, plain Python floats in
preallocated lists (no numpy, no container allocated per sample: about 1-2 us per sample); only
the end of a reference window does one numpy pass over it (about 2 ms, once per ``learn_s``).

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

On an alarm the detector returns an :class:`Alarm` (detection stamp, the estimated change time =
the stamp of the first sample after the CUSUM's last zero, output, direction, estimated shift),
then re-learns a new reference window and keeps running. Non-finite residuals are skipped;
a stamp gap longer than ``max_gap_s`` (or a stamp that does not increase) skips the whitening of
the sample after it (the filter memory would be wrong).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
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
    """

    sample_rate_hz: float = 1000.0
    learn_s: float = 20.0
    shift_sigma: float = 0.5
    false_alarm_period_s: float = 4.0 * 3600.0
    max_gap_s: float = 0.05
    max_phi: float = 0.995
    names: tuple[str, ...] = SPEED_NAMES

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
        return self

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
    end [rad/s].
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
    ``learned`` completed reference windows."""

    samples: int = 0
    tested: int = 0
    skipped: int = 0
    gaps: int = 0
    alarms: int = 0
    learned: int = 0
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


def design_threshold(k: float, rate_per_sample: float, learn_samples: int) -> float:
    """Smallest ``h`` (to 0.1 %) whose :func:`false_alarm_rate` is at most ``rate_per_sample``.

    Two vectorised grid passes (about 0.2 ms), cheap enough for the end of a reference window.
    """
    hi = 8.0
    while _rates(k, np.asarray([hi]), learn_samples)[0] > rate_per_sample and hi < 1e6:
        hi *= 4.0
    lo = 0.0
    for _ in range(3):
        grid = np.linspace(lo, hi, 65)
        ok = _rates(k, grid, learn_samples) <= rate_per_sample
        j = int(np.argmax(ok)) if ok.any() else grid.size - 1
        lo, hi = float(grid[max(j - 1, 0)]), float(grid[j])
        if hi - lo <= 1e-3 * hi:
            break
    return hi


_ACF_LAGS = 10  # autocorrelation lags used to estimate phi


def reference_from_window(window: NDArray[np.float64], config: DetectorConfig) -> Reference:
    """Learn one output's :class:`Reference` from its reference window (1-D, [rad/s]).

    ARMA(1, 1) by the method of moments on the winsorised, centred window: ``phi`` from the
    geometric decay of the autocorrelation (``sum rho[2..K] / sum rho[1..K-1]`` over the first
    K <= 10 lags whose autocorrelation exceeds ``2 / sqrt(n)``; 0 if none; clipped to
    [0, ``max_phi``]), ``theta`` from the lag-1 autocorrelation ``rho_e`` of
    ``e = c - phi c_prev`` (the invertible root of ``theta / (1 + theta^2) = rho_e``); the
    innovation scale from the MAD of ``a = e - theta a_prev`` (the whitened window).
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
    k = 0.5 * config.shift_sigma * sigma * gain / sigma_e
    n_sides = 2 * len(config.names)
    rate = 1.0 / (config.false_alarm_period_s * config.sample_rate_hz * n_sides)
    h = design_threshold(k, 2.0 * rate, config.learn_samples)
    arl_side = 1.0 / (0.5 * false_alarm_rate(k, h, config.learn_samples))
    return Reference(level=level, phi=phi, theta=theta, sigma_e=sigma_e, sigma=sigma, k=k,
                     h=h, arl0_s=arl_side / config.sample_rate_hz,
                     last_r=float(window[-1]), last_a=float(a[-1]) if a.size else 0.0)


# -------------------------------------------------------------------------- the detector
class ChangeDetector:
    """Sequential change detector on the residual vector (see the module docstring).

    ``update(stamp_s, residual)`` per sample; ``reset()`` after the model changed (e.g. a push);
    ``counters`` and ``references`` for diagnostics. Not thread-safe.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
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

    def reset(self) -> None:
        """Forget the reference and start learning a new one (the CUSUMs restart at 0)."""
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
               "samples": str(c.samples), "tested": str(c.tested), "skipped": str(c.skipped),
               "gaps": str(c.gaps), "alarms": str(c.alarms),
               "false_alarm_period_s": f"{self.config.false_alarm_period_s:g}"}
        for i, ref in enumerate(self.references):
            name = self.config.names[i]
            out.update({f"{name}.sigma_rad_s": f"{ref.sigma:.6g}", f"{name}.phi": f"{ref.phi:.4f}",
                        f"{name}.k": f"{ref.k:.4g}", f"{name}.h": f"{ref.h:.4g}",
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
                return None
        t = float(stamp_s)
        gap = not (0.0 < t - self._last_stamp <= self.config.max_gap_s)
        self._last_stamp = t
        if self._filled < self._L:
            j = self._filled
            if j == 0:
                self._learn_from = t
            for i in range(n):
                self._buf[i][j] = float(residual[i])
            self._filled = j + 1
            if self._filled == self._L:
                self._finish_learning()
                self._have_prev = True
            return None
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
            z = a * self._inv_s[i]
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
            if alarm is None and (hi > self._h[i] or lo > self._h[i]):
                alarm = self._alarm(i, t, up=hi - self._h[i] >= lo - self._h[i])
        if alarm is not None:
            c.alarms += 1
            c.last_alarm = alarm
            self.reset()
        return alarm

    def _alarm(self, i: int, t: float, up: bool) -> Alarm:
        ref = self.references[i]
        stat = self._hi[i] if up else self._lo[i]
        count = self._hi_n[i] if up else self._lo_n[i]
        # CUSUM estimate of the whitened shift: k + S / n; back to the residual's units.
        dz = ref.k + stat / max(count, 1)
        gain = (1.0 - ref.phi) / (1.0 + ref.theta)
        shift = (1.0 if up else -1.0) * dz * ref.sigma_e / max(gain, 1e-9)
        return Alarm(stamp_s=t, change_s=self._hi_t[i] if up else self._lo_t[i], output=i,
                     name=self.config.names[i], direction=1 if up else -1, statistic=stat,
                     threshold=ref.h, samples=count, shift=shift,
                     shift_sigma=shift / ref.sigma, level=ref.level, sigma=ref.sigma)

    def _finish_learning(self) -> None:
        refs = [reference_from_window(np.asarray(self._buf[i]), self.config)
                for i in range(self.n)]
        self.references = refs
        for i, ref in enumerate(refs):
            self._level[i] = ref.level
            self._phi[i] = ref.phi
            self._theta[i] = ref.theta
            self._prev[i] = ref.last_r
            self._prev_a[i] = ref.last_a
            self._inv_s[i] = 1.0 / ref.sigma_e
            self._k[i] = ref.k
            self._h[i] = ref.h
            self._hi[i] = self._lo[i] = 0.0
        self.counters.learned += 1
