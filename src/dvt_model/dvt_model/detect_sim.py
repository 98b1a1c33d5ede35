"""The change detector (:mod:`dvt_model.detect`) simulated offline, vectorised (pure): false
alarms on clean AR(1) + white residuals (:func:`simulate_clean`), the delay to a step
(:func:`detection_delay`) and the benchmark of the default configuration (:func:`benchmark`,
``python -m dvt_model.detect_sim [HOURS] [WHITE]``; ``docs/loop.md``)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dvt_model.detect import Alarm, ChangeDetector, DetectorConfig, Reference, reference_from_window


@dataclass(frozen=True)
class SimulationResult:
    """Outcome of :func:`simulate_clean`: ``samples`` simulated after learning, ``alarms``,
    ``hours`` of tested data at the configured rate, ``mtbfa_s`` the measured mean time between
    false alarms [s] (``inf`` with no alarm), ``lower_bound_s`` its one-sided 95 % lower
    confidence bound (Poisson/chi-square; ``T / 3`` with no alarm), ``alarm_samples`` the tested-
    sample indices of the alarms."""

    samples: int
    alarms: int
    hours: float
    mtbfa_s: float
    lower_bound_s: float
    alarm_samples: tuple[int, ...]


def rate_bounds(count: int, exposure: float, conf: float = 0.95) -> tuple[float, float]:
    """One-sided ``conf`` lower and upper bounds of a Poisson rate with ``count`` events in
    ``exposure`` (chi-square / Garwood; lower 0 with no event, ``(0, inf)`` without exposure),
    in events per unit of ``exposure``."""
    from scipy.stats import chi2

    if not exposure > 0:
        return 0.0, math.inf
    lower = 0.0 if count == 0 else float(chi2.ppf(1.0 - conf, 2 * count)) / (2 * exposure)
    return lower, float(chi2.ppf(conf, 2 * count + 2)) / (2 * exposure)


def ar1_noise(rng: np.random.Generator, n: int, outputs: int, phi: float,
              white: float = 0.0, zi: NDArray[np.float64] | None = None
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(n, outputs)`` stationary AR(1) noise of unit variance plus white noise of standard
    deviation ``white``; returns it and the filter state to continue with (``zi``)."""
    from scipy.signal import lfilter

    w = rng.standard_normal((n, outputs)) * math.sqrt(1.0 - phi * phi)
    if zi is None:
        zi = rng.standard_normal(outputs) * phi  # x_{-1} ~ N(0, 1) -> state phi * x_{-1}
    x, zf = lfilter([1.0], [1.0, -phi], w, axis=0, zi=zi[None, :])
    if white:
        x = x + white * rng.standard_normal((n, outputs))
    return np.asarray(x, dtype=float), np.asarray(zf[0], dtype=float)


def cusum_run(z: NDArray[np.float64], k: float, h: float, s0: float = 0.0
              ) -> tuple[int, NDArray[np.float64]]:
    """One-sided CUSUM ``S_t = max(0, S_{t-1} + z_t - k)`` from ``S_{-1} = s0``, vectorised.

    Returns the index of the first ``S_t > h`` (``-1`` if none) and the S sequence.
    Uses ``S_t = C_t - min(-s0, min_{s<=t} C_s)`` with ``C`` the cumulative sum of ``z - k``.
    """
    C = np.cumsum(z - k)
    S = C - np.minimum(np.minimum.accumulate(C), -s0)
    S = np.maximum(S, 0.0)
    over = np.flatnonzero(h < S)
    return (int(over[0]) if over.size else -1), S


def simulate_clean(config: DetectorConfig | None = None, hours: float = 1.0, phi: float = 0.9,
                   white: float = 0.0, seed: int = 0, chunk: int = 1 << 20
                   ) -> SimulationResult:
    """False alarms of the detector on simulated clean residuals (AR(1) + white noise).

    Exactly the detector's algorithm, vectorised over chunks: learn a reference window with
    :func:`reference_from_window`, whiten, run the four one-sided CUSUMs (:func:`cusum_run`),
    and after an alarm learn again from the following samples. ``hours`` of tested (not
    learning) data at ``config.sample_rate_hz``.
    """
    cfg = (config or DetectorConfig()).validated()
    rng = np.random.default_rng(seed)
    n_out = len(cfg.names)
    target = round(hours * 3600.0 * cfg.sample_rate_hz)
    L = cfg.learn_samples
    zi: NDArray[np.float64] | None = None
    tested = 0
    alarms: list[int] = []
    pending = np.zeros((0, n_out))

    def take(n: int) -> NDArray[np.float64]:
        nonlocal pending, zi
        while pending.shape[0] < n:
            x, zi = ar1_noise(rng, max(chunk, n), n_out, phi, white, zi)
            pending = np.vstack([pending, x])
        out, pending = pending[:n], pending[n:]
        return out

    while tested < target:
        ref_win = take(L)
        refs = [reference_from_window(ref_win[:, i], cfg) for i in range(n_out)]
        state = [(r.last_r, r.last_a) for r in refs]
        s = np.zeros((n_out, 2))
        alarmed = False
        while tested < target and not alarmed:
            x = take(min(chunk, target - tested))
            first = -1
            finals = np.zeros_like(s)
            new_state = []
            for i, ref in enumerate(refs):
                z, st = _whiten(x[:, i], state[i], ref)
                new_state.append(st)
                for side, sign in ((0, 1.0), (1, -1.0)):
                    idx, S = cusum_run(sign * z, ref.k, ref.h, float(s[i, side]))
                    if idx >= 0 and (first < 0 or idx < first):
                        first = idx
                    finals[i, side] = S[-1]
            if first >= 0:
                alarms.append(tested + first)
                tested += first + 1
                pending = np.vstack([x[first + 1:], pending])
                alarmed = True
            else:
                s = finals
                state = new_state
                tested += x.shape[0]
    hours_done = tested / cfg.sample_rate_hz / 3600.0
    secs = tested / cfg.sample_rate_hz
    if alarms:
        from scipy.stats import chi2

        mtbfa = secs / len(alarms)
        lower = 2.0 * secs / float(chi2.ppf(0.95, 2 * len(alarms) + 2))
    else:
        mtbfa = math.inf
        lower = secs / 3.0
    return SimulationResult(samples=tested, alarms=len(alarms), hours=hours_done,
                            mtbfa_s=mtbfa, lower_bound_s=lower, alarm_samples=tuple(alarms))


def _whiten(x: NDArray[np.float64], state: tuple[float, float], ref: Reference
            ) -> tuple[NDArray[np.float64], tuple[float, float]]:
    """Innovations ``a / sigma_e`` of ``x`` (1-D) continuing from ``state`` = (last residual,
    last innovation); returns them and the new state (exactly the detector's recursion)."""
    from scipy.signal import lfilter

    c = x - ref.level
    zi = [-ref.phi * (state[0] - ref.level) - ref.theta * state[1]]
    a, _ = lfilter([1.0, -ref.phi], [1.0, ref.theta], c, zi=zi)
    a = np.asarray(a, dtype=float)
    return a / ref.sigma_e, (float(x[-1]), float(a[-1]))


def detection_delay(config: DetectorConfig | None = None, phi: float = 0.9,
                    shift_sigma: float = 0.5, seed: int = 0, clean_s: float = 5.0,
                    max_s: float = 120.0, output: int = 0, white: float = 0.0
                    ) -> tuple[float, Alarm | None]:
    """Delay [s] of :class:`ChangeDetector` to a step of ``shift_sigma`` residual standard
    deviations on ``output`` of unit-variance AR(1) noise plus white noise of standard deviation
    ``white``, ``clean_s`` after learning ended (``inf`` and ``None`` if not detected within
    ``max_s``), and the alarm."""
    cfg = (config or DetectorConfig()).validated()
    rate = cfg.sample_rate_hz
    rng = np.random.default_rng(seed)
    n_out = len(cfg.names)
    L = cfg.learn_samples
    n_clean = round(clean_s * rate)
    x, _ = ar1_noise(rng, L + n_clean + round(max_s * rate), n_out, phi, white)
    x[L + n_clean:, output] += shift_sigma * math.sqrt(1.0 + white * white)
    det = ChangeDetector(cfg)
    change = (L + n_clean) / rate
    for j, row in enumerate(x.tolist()):
        alarm = det.update(j / rate, row)
        if alarm is not None:
            if j < L + n_clean:
                continue  # a false alarm before the step: keep going (it re-learns)
            return alarm.stamp_s - change, alarm
    return math.inf, None


def benchmark(hours: float = 10.0, phis: Sequence[float] = (0.0, 0.5, 0.9, 0.98),
              white: float = 0.0, seed: int = 1) -> list[dict[str, float]]:
    """Measured false alarms and detection delays of the default configuration (see
    ``docs/loop.md``): per ``phi``, ``hours`` of clean 1 kHz AR(1) residual (2 outputs) and the
    median delay to a 0.5-sigma step over 5 seeds."""
    cfg = DetectorConfig()
    out: list[dict[str, float]] = []
    for phi in phis:
        sim = simulate_clean(cfg, hours=hours, phi=phi, white=white, seed=seed)
        ref = reference_from_window(ar1_noise(np.random.default_rng(seed), cfg.learn_samples,
                                              1, phi, white)[0][:, 0], cfg)
        delays = [detection_delay(cfg, phi, cfg.shift_sigma, seed=s, white=white)[0]
                  for s in range(5)]
        out.append({"phi": phi, "white": white, "theta": ref.theta, "k": ref.k, "h": ref.h,
                    "design_mtbfa_h": ref.arl0_s / (2 * len(cfg.names)) / 3600.0,
                    "hours": sim.hours, "false_alarms": float(sim.alarms),
                    "mtbfa_h": sim.mtbfa_s / 3600.0, "mtbfa_lower95_h": sim.lower_bound_s / 3600.0,
                    "delay_median_s": float(np.median(delays)), "delay_max_s": max(delays)})
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m dvt_model.detect_sim [HOURS] [WHITE]``: print :func:`benchmark` as JSON lines."""
    import sys

    args = list(sys.argv[1:] if argv is None else argv)
    hours = float(args[0]) if args else 10.0
    white = float(args[1]) if len(args) > 1 else 0.0
    for row in benchmark(hours=hours, white=white):
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
