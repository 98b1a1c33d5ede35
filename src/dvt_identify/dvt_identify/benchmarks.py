"""Benchmark protocols: simulated-output error with a state-initialisation window, and the fit
for it.

Public system-identification benchmarks (EMPS, Wiener-Hammerstein, Silverbox, ... as split by
the ``nonlinear_benchmarks`` loader) score a model on its *simulated* output over a test record:
the model may look at the first ``n_init`` measured outputs of the test record to set its initial
state (the state-initialisation window), then it is simulated open loop from the measured input
over the whole record, and the figure is the RMS of the output error over the samples after the
window. This module computes that figure for any simulator and fits a model for it:

- :func:`initial_state_from_window`: the initial state that best reproduces the first
  ``n_init`` samples of one output (Gauss-Newton on a finite-difference Jacobian; exact when the
  model is affine in the initial state over the window, deterministic and smooth in the
  parameters otherwise);
- :func:`protocol_score`: the protocol figure (:class:`ProtocolScore`);
- :func:`fit_for_output`: least squares of the simulation error of the benchmark's output on
  the estimation record, starting each simulation from the state that the same window gives
  (what the test will do), so that the parameters are fitted for the benchmark's output rather
  than for another signal.

Pure: no file or bag I/O; a simulator is anything with ``simulate(theta, seg, x0) -> (N, ny)``
(:class:`dvt_identify.simulation.OEModel` is one).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.errors import DataError, FitError

Array = NDArray[np.float64]
WindowSim = Callable[[Array, int], Array]
"""``sim(x0, n)``: simulated benchmark output (n,) for the first ``n`` samples from ``x0``."""

PENALTY = 1e6
"""Residual of a parameter vector whose simulation fails or is not finite."""


class Simulator(Protocol):
    """What :func:`fit_for_output` and :func:`protocol_score_model` need of a model."""

    def simulate(self, theta: Array, seg: Segment, x0: Array) -> Array:
        """Simulated outputs, shape (N, ny)."""
        ...


@dataclass(frozen=True)
class ProtocolScore:
    """The benchmark figure of one simulation.

    Attributes:
        rms: RMS of the output error over the scored samples (after the window), output unit.
        n_init: samples of the state-initialisation window (not scored).
        n_scored: samples scored.
        x0: initial state used, shape (nx,).
        y_sim: simulated benchmark output over the whole record, shape (N,).
    """

    rms: float
    n_init: int
    n_scored: int
    x0: Array
    y_sim: Array


def window_guess(y: Array, n_init: int, dt: float, nx: int) -> Array:
    """A start for the initial state from the window only: ``[y[0], slope, 0, ...]`` (first
    ``nx`` entries; the slope of a straight line through the first ``n_init`` samples).

    Suits a state ``(position, velocity, ...)``; other structures pass their own guess.
    """
    x0 = np.zeros(nx)
    x0[0] = float(y[0])
    if nx > 1 and n_init >= 2:
        tt = np.arange(n_init) * dt
        x0[1] = float(np.polyfit(tt, y[:n_init], 1)[0])
    return x0


def initial_state_from_window(sim: WindowSim, y: Array, n_init: int, x0_guess: Array,
                              iterations: int = 3) -> Array:
    """Initial state (nx,) that best fits the first ``n_init`` samples of ``y`` (one output).

    Gauss-Newton with a forward-difference Jacobian (step ``1e-6 max(|x0_i|, 1)``), least-squares
    solve by SVD (a state the window cannot see keeps its guess); ``iterations`` steps.

    Raises:
        DataError: ``n_init`` < 1 or beyond ``y``.
    """
    if n_init < 1 or n_init > y.shape[0]:
        raise DataError(f"state-initialisation window of {n_init} samples: need 1..{y.shape[0]}")
    x0 = np.array(x0_guess, dtype=float)
    target = np.asarray(y[:n_init], dtype=float)
    for _ in range(max(1, iterations)):
        base = np.asarray(sim(x0, n_init), dtype=float)
        r = target - base
        J = np.empty((n_init, x0.size))
        for i in range(x0.size):
            h = 1e-6 * max(abs(float(x0[i])), 1.0)
            xp = x0.copy()
            xp[i] += h
            J[:, i] = (np.asarray(sim(xp, n_init), dtype=float) - base) / h
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
            break
        step, *_ = np.linalg.lstsq(J, r, rcond=1e-10)
        x0 = x0 + step
        if float(np.max(np.abs(step))) <= 1e-12 * max(1.0, float(np.max(np.abs(x0)))):
            break
    return x0


def protocol_score(sim: WindowSim, y: Array, n_init: int, x0_guess: Array) -> ProtocolScore:
    """The benchmark figure: initial state from the first ``n_init`` samples of ``y``, then
    the full simulation ``sim(x0, len(y))``; RMS of ``y - y_sim`` over samples ``n_init:``.

    Raises:
        DataError: the window leaves no sample to score, or the simulation is not finite.
    """
    y = np.asarray(y, dtype=float)
    n = y.shape[0]
    if n_init >= n:
        raise DataError(f"state-initialisation window of {n_init} samples leaves nothing of "
                        f"{n} samples to score")
    x0 = initial_state_from_window(sim, y, n_init, x0_guess)
    ys = np.asarray(sim(x0, n), dtype=float)
    if ys.shape != (n,) or not np.all(np.isfinite(ys)):
        raise DataError("simulated output is not finite (or has the wrong shape)")
    e = y[n_init:] - ys[n_init:]
    return ProtocolScore(rms=float(np.sqrt(np.mean(e * e))), n_init=n_init,
                         n_scored=n - n_init, x0=x0, y_sim=ys)


def head(seg: Segment, n: int) -> Segment:
    """The first ``n`` samples of ``seg`` (all of it when ``n >= seg.n``)."""
    if n >= seg.n:
        return seg
    return seg.rows(0, n)


def window_simulator(model: Simulator, theta: Array, seg: Segment, output: int) -> WindowSim:
    """``sim(x0, n)`` of output ``output`` of ``model`` on the first ``n`` samples of ``seg``."""
    cache: dict[int, Segment] = {}

    def sim(x0: Array, n: int) -> Array:
        part = cache.get(n)
        if part is None:
            part = cache[n] = head(seg, n)
        with np.errstate(all="ignore"):
            return np.asarray(model.simulate(theta, part, x0)[:, output], dtype=float)
    return sim


def protocol_score_model(model: Simulator, theta: Array, seg: Segment, output: int,
                         n_init: int, nx: int) -> ProtocolScore:
    """:func:`protocol_score` of ``model`` with parameters ``theta`` on ``seg``: output column
    ``output`` of ``seg.y`` is the benchmark output (the only measured signal the window may
    use); the start of the initial state is :func:`window_guess`."""
    y = np.asarray(seg.y[:, output], dtype=float)
    sim = window_simulator(model, theta, seg, output)
    return protocol_score(sim, y, n_init, window_guess(y, n_init, seg.dt, nx))


@dataclass(frozen=True)
class OutputFit:
    """Result of :func:`fit_for_output`.

    Attributes:
        theta: fitted parameters, shape (p,).
        rms: RMS of the output error on the estimation record (after the window).
        x0: initial state of the estimation record from its window, shape (nx,).
        nfev: simulations of the whole record used by the optimiser.
        weights: scale each fitted output's error was divided by, shape (len(outputs),).
    """

    theta: Array
    rms: float
    x0: Array
    nfev: int
    weights: Array


def fit_for_output(model: Simulator, seg: Segment, theta0: Array, lower: Array, upper: Array,
                   output: int, n_init: int, nx: int,
                   also: Sequence[int] = (), max_nfev: int | None = None) -> OutputFit:
    """Fit ``theta`` for the benchmark figure on the estimation record ``seg``.

    Residual: the simulation error of output ``output`` (and of the outputs ``also``, each
    divided by its standard deviation, as :class:`dvt_identify.fit.OEFit` weighs outputs),
    over samples ``n_init:``, with each simulation started from the state that the first
    ``n_init`` samples of output ``output`` give (:func:`initial_state_from_window`): the test
    record gets exactly that, so the fit cannot use a free initial state to absorb the drift of
    an integrating output. Bounded ``scipy.optimize.least_squares`` (``x_scale="jac"``).

    Raises:
        FitError: ``theta0`` outside the bounds or the start does not simulate.
    """
    theta0 = np.asarray(theta0, dtype=float)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    if np.any(theta0 < lower) or np.any(theta0 > upper):
        raise FitError("fit_for_output: theta0 outside the bounds")
    cols = [output, *[j for j in also if j != output]]
    y = np.asarray(seg.y[n_init:, cols], dtype=float)
    w = np.std(seg.y[:, cols], axis=0)
    w[w == 0] = 1.0
    yb = np.asarray(seg.y[:, output], dtype=float)
    guess = window_guess(yb, n_init, seg.dt, nx)

    def x0_of(theta: Array) -> Array:
        return initial_state_from_window(window_simulator(model, theta, seg, output), yb,
                                         n_init, guess)

    def residual(theta: Array) -> Array:
        try:
            with np.errstate(all="ignore"):
                yh = np.asarray(model.simulate(theta, seg, x0_of(theta)), dtype=float)
            r = ((y - yh[n_init:, cols]) / w).ravel()
        except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError):
            return np.full(y.size, PENALTY)
        return np.where(np.isfinite(r), r, PENALTY)

    r0 = residual(theta0)
    if not np.all(np.abs(r0) < PENALTY):
        raise FitError("fit_for_output: the start does not simulate")
    res = least_squares(residual, theta0, bounds=(lower, upper), x_scale="jac",
                        max_nfev=max_nfev)
    theta = np.asarray(res.x, dtype=float)
    x0 = x0_of(theta)
    yh = np.asarray(model.simulate(theta, seg, x0)[:, output], dtype=float)
    e = yb[n_init:] - yh[n_init:]
    return OutputFit(theta=theta, rms=float(math.sqrt(float(np.mean(e * e)))), x0=x0,
                     nfev=int(res.nfev), weights=w)
