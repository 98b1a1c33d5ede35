"""Do the parameters hold over the recording? Window refits against the sandwich uncertainty.

A parameter that changes during a run (damping falling as the oil warms, a band wearing in) is
not a missing static effect; an augment loop that only knows static terms would pile them up to
mimic it. :func:`drift_check` therefore gives each free structure parameter, one at a time, a
separate value in each of ``K`` consecutive windows of the estimation data (each segment cut into
``K`` equal pieces; the simulation runs through the whole segment, the state carried across the
window edges), every other parameter held at the fitted estimate and the initial states
re-estimated, and gives each window's value its HAC sandwich standard deviation
(:func:`dvt_identify.uncertainty.sandwich_by_segment`). One parameter at a time keeps each
window's estimate well conditioned (in a window where the parameters are not jointly determined,
e.g. a locked gear, a joint refit wanders). A weighted straight line over the window centre
times gives the trend ``b`` and its standard error; the parameter **drifts** when

- the trend is significant: two-sided ``p < alpha / n`` (Bonferroni over the ``n`` parameters
  tested),
- it is material: the change over the recording, ``|b| (t_K - t_1)``, is at least
  ``min_change`` (default 10 %) of the parameter's mean magnitude, and
- the window values are monotone: a drift goes one way over the run, whereas a parameter that
  only stands in for a state-dependent effect (windage raises the apparent damping at speed)
  goes up and down with the experiment's phases.

The first condition asks that the drift exceed the parameter's uncertainty; the second keeps a
statistically clear but physically irrelevant wobble (a 1 % change on a long clean recording)
from stopping the augment loop. The heterogeneity ``chi2 = sum (a_k - mean)^2 / s_k^2`` with its
``K - 1`` degrees of freedom is reported too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.linalg import solve_triangular
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.fit import OEFit
from dvt_identify.parallel import fork_map
from dvt_identify.sensitivity import simulate_sens_states
from dvt_identify.simulation import DivergedError
from dvt_identify.streamls import Block, Factored
from dvt_identify.structures import PENALTY
from dvt_identify.uncertainty import sandwich_by_segment

Array = NDArray[np.float64]
MIN_PIECE = 100
"""Fewest samples of one window piece; shorter segments are not cut."""


@dataclass(frozen=True)
class ParameterDrift:
    """Window estimates of one parameter and the trend test (see module docstring).

    Attributes:
        name: parameter name.
        times: window centre times [s from the segment start], shape (K,).
        values, stds: window estimates and their sandwich standard deviations.
        slope, slope_std: trend [unit/s] and its standard error.
        p_value: two-sided p-value of the trend.
        change: change over the recording relative to the mean magnitude (signed).
        span: ``t_K - t_1`` [s].
        chi2, chi2_p: heterogeneity of the window estimates.
        drifting: significant and material.
    """

    name: str
    times: tuple[float, ...]
    values: tuple[float, ...]
    stds: tuple[float, ...]
    slope: float
    slope_std: float
    p_value: float
    change: float
    span: float
    chi2: float
    chi2_p: float
    drifting: bool

    def statement(self) -> str:
        """'D11 falls 35 % over 30 s (trend 12 x its standard error, p = ...)'."""
        verb = "rises" if self.change > 0 else "falls"
        ratio = abs(self.slope) / self.slope_std if self.slope_std > 0 else math.inf
        return (f"{self.name} {verb} {100 * abs(self.change):.3g} % over {self.span:.3g} s "
                f"(window estimates {', '.join(f'{v:.4g}' for v in self.values)}; trend "
                f"{ratio:.3g} x its standard error, p = {self.p_value:.2g})")

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"name": self.name, "times": list(self.times), "values": list(self.values),
                "stds": list(self.stds), "slope": self.slope, "slope_std": self.slope_std,
                "p_value": self.p_value, "relative_change": self.change, "span_s": self.span,
                "chi2": self.chi2, "chi2_p": self.chi2_p, "drifting": self.drifting}


@dataclass
class DriftReport:
    """Result of :func:`drift_check`: per-parameter trends and the settings."""

    windows: int
    alpha: float
    min_change: float
    parameters: list[ParameterDrift] = field(default_factory=list)
    skipped: str = ""

    @property
    def drifting(self) -> list[ParameterDrift]:
        """The drifting parameters."""
        return [p for p in self.parameters if p.drifting]

    def summary(self) -> list[str]:
        """Lines for people."""
        if self.skipped:
            return [f"drift not checked: {self.skipped}"]
        if not self.drifting:
            return [f"no parameter drifts beyond its uncertainty over {self.windows} windows "
                    f"(trend test at {self.alpha:g}, Bonferroni; material change >= "
                    f"{100 * self.min_change:g} %)"]
        return [p.statement() for p in self.drifting]

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"windows": self.windows, "alpha": self.alpha, "min_change": self.min_change,
                "skipped": self.skipped, "drifting": [p.name for p in self.drifting],
                "parameters": [p.as_dict() for p in self.parameters],
                "summary": self.summary()}


def _edges(seg: Segment, windows: int) -> Array:
    return np.linspace(0, seg.n, windows + 1).astype(int)


def _simulate_windows(fit: OEFit, i: int, values: Array, seg: Segment, x0: Array,
                      edges: Array) -> Array:
    """Simulated outputs of ``seg`` with parameter ``i`` piecewise constant over the windows
    (``values[k]`` in window ``k``), the state carried across the window edges; (N, ny)."""
    m = fit.model
    out = []
    x = np.asarray(x0, float)
    th = fit.theta_.copy()
    for k in range(len(edges) - 1):
        a, b = int(edges[k]), int(edges[k + 1])
        stop = min(b + 1, seg.n)  # one sample into the next window: its initial state
        th[i] = values[k]
        piece = seg.rows(a, stop)
        with np.errstate(all="ignore"):
            if m.C is None:
                xs = m.simulate(th, piece, x)
                states = xs
            else:  # hidden states: carry the states, not the outputs
                states, xs = m.simulate_states(th, piece, x)
        out.append(xs[: b - a])
        x = states[-1]
    return np.vstack(out)


def _windows_jacobian(fit: OEFit, i: int, values: Array, seg: Segment, x0: Array,
                      edges: Array) -> Array:
    """``d (simulated outputs) / d (values, x0)`` of :func:`_simulate_windows`, shape
    (N, ny, K + nx): each window's simulation differentiated by its own value and its initial
    state (:func:`~dvt_identify.sensitivity.simulate_sens_states`), chained through the state
    carried across the window edges."""
    m = fit.model
    K, nx = len(edges) - 1, m.nx
    out = []
    x = np.asarray(x0, float)
    T = np.zeros((nx, K + nx))  # d (carried state) / d (values, x0)
    T[:, K:] = np.eye(nx)
    th = fit.theta_.copy()
    for k in range(K):
        a, b = int(edges[k]), int(edges[k + 1])
        stop = min(b + 1, seg.n)
        th[i] = values[k]
        with np.errstate(all="ignore"):
            states, tstates, ys, S = simulate_sens_states(m, th, seg.rows(a, stop), x, [i])
        Jp = S[:, :, 1:] @ T
        Jp[:, :, k] += S[:, :, 0]
        out.append(Jp[: b - a])
        # the carried state (the outputs' last sample for C = I, as _simulate_windows)
        carried, tc = (ys, S) if m.C is None else (states, tstates)
        Tn = tc[-1, :, 1:] @ T
        Tn[:, k] += tc[-1, :, 0]
        x, T = carried[-1], Tn
    return np.concatenate(out)


def _refit_one(fit: OEFit, i: int, segs: Sequence[Segment], windows: int
               ) -> tuple[Array, Array]:
    """Parameter ``i`` refitted per window (everything else at the fit, initial states
    re-estimated): (values (K,), sandwich std (K,))."""
    m = fit.model
    w = fit.weights_
    nx = m.nx
    spec = m.specs[i]
    edges = [_edges(s, windows) for s in segs]

    q = windows + len(segs) * nx

    def rows(z: Array, k: int) -> Block:
        """Segment ``k``'s rows of the Jacobian over its unknowns (the window values and its
        initial state) and of the residual (:data:`~dvt_identify.streamls.Block`)."""
        seg = segs[k]
        vals = z[:windows]
        x0 = z[windows + k * nx: windows + (k + 1) * nx]
        cols = np.concatenate([np.arange(windows), windows + k * nx + np.arange(nx)])
        try:
            S = _windows_jacobian(fit, i, vals, seg, x0, edges[k])
            yh = _simulate_windows(fit, i, vals, seg, x0, edges[k])
        except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError,
                DivergedError):
            return (np.zeros((seg.y.size, windows + nx)), np.full(seg.y.size, PENALTY),
                    cols.astype(np.int64))
        J = -(S / w[None, :, None]).reshape(seg.y.size, windows + nx)
        r = np.nan_to_num(((seg.y - yh) / w).ravel(), nan=PENALTY, posinf=PENALTY,
                          neginf=-PENALTY)
        return (np.asarray(np.nan_to_num(J, nan=0.0, posinf=0.0, neginf=0.0)),
                np.asarray(np.clip(r, -PENALTY, PENALTY)), cols.astype(np.int64))

    v0 = float(np.clip(fit.theta_[i], spec.lower, spec.upper))
    z0 = np.concatenate([np.full(windows, v0), *fit.x0_[: len(segs)]])
    zlo = np.concatenate([np.full(windows, spec.lower), np.full(len(segs) * nx, -np.inf)])
    zhi = np.concatenate([np.full(windows, spec.upper), np.full(len(segs) * nx, np.inf)])
    if np.any(zlo >= zhi):
        return np.full(windows, v0), np.full(windows, np.inf)
    # by the problem's triangular factor (dvt_identify.streamls), whatever the length
    fac = Factored(lambda z: (rows(z, k) for k in range(len(segs))), q)
    got = _gauss_newton(fac, z0, zlo, zhi, windows, sum(sg.y.size for sg in segs))
    # not settled in GN_STEPS: the trust-region solver from the fit
    z = got if got is not None else least_squares(
        fac.residual, z0, jac=fac.jacobian, bounds=(zlo, zhi), x_scale="jac",
        method="trf", ftol=1e-8, xtol=1e-8, gtol=1e-8).x
    _, cov = sandwich_by_segment(lambda k: rows(z, k), [s.n for s in segs], m.ny, q)
    return np.asarray(z[:windows], float), np.asarray(cov.std[:windows], float)


GN_STEPS = 6
"""Most Gauss-Newton steps of a window refit (:func:`_gauss_newton`)."""
GN_HALVINGS = 2
"""A Gauss-Newton step that raises the cost is halved at most this many times (one pass
each) before the point before it stands."""
GN_TOLERANCE = 0.1
"""A window refit has converged when its next Gauss-Newton step would move every window value
by at most this fraction of the value's standard deviation (the trend test's scale: a tenth of
a standard deviation moves no verdict)."""


def _gauss_newton(fac: Factored, z0: Array, lo: Array, hi: Array, windows: int,
                  m_rows: int) -> Array | None:
    """Gauss-Newton steps from the fit (``z0``) on a factored problem, each kept only when it
    lowers the cost: the window values start at the fitted value, which the data put within a
    few standard deviations of each window's own. Each step costs one pass over the data
    (the factor :class:`~dvt_identify.streamls.Factored` takes at every evaluation), where the
    trust-region solver spent 6-12 (measured on an hour at 200 Hz: 13-15 passes per
    parameter with the final covariance, 4-5 now; on the 38-s `dvt-bench identify` recording
    at 1 kHz the six refits took 0.21 s on both cores with the solver, 0.10 s now).

    Returns the point when a step moves no window value by more than :data:`GN_TOLERANCE` of
    its standard deviation, or when a step and its halves (:data:`GN_HALVINGS`) all raise the
    cost (the simulation's dry-friction branches make the cost ragged below a fraction of a
    standard deviation: the point before it stands); ``None`` when
    :data:`GN_STEPS` steps did not settle, a step left the bounds or the factor is singular:
    the caller then runs the trust-region solver."""
    z = np.array(z0, dtype=float)
    qtr = fac.residual(z)[:-1]
    cost = fac.rr
    for _ in range(GN_STEPS):
        R = fac.R
        try:
            dz = -np.asarray(solve_triangular(R, qtr, check_finite=True), float)
            Rinv = solve_triangular(R, np.eye(R.shape[0]), check_finite=True)
        except (np.linalg.LinAlgError, ValueError):
            return None
        # the values' standard deviations (white residual: the test's scale, not the report's)
        s2 = cost / max(m_rows - len(qtr), 1)
        sd = math.sqrt(s2) * np.sqrt(np.sum(Rinv[:windows] ** 2, axis=1))
        if not (np.all(np.isfinite(dz)) and np.all(np.isfinite(sd)) and np.all(sd > 0)):
            return None
        if np.all(np.abs(dz[:windows]) <= GN_TOLERANCE * sd):
            return z
        for _half in range(GN_HALVINGS + 1):  # the step, then shorter ones
            trial = z + dz
            if np.any(trial < lo) or np.any(trial > hi):
                return None
            qtr = fac.residual(trial)[:-1]
            if fac.rr <= cost:
                break
            dz = 0.5 * dz
            if np.all(np.abs(dz[:windows]) <= GN_TOLERANCE * sd):
                return z
        else:
            return z
        z, cost = trial, fac.rr
    return None


def drift_check(fit: OEFit, segments: Sequence[Segment] | None = None, windows: int = 4,
                alpha: float = 0.01, min_change: float = 0.10) -> DriftReport:
    """Trend of the structure's free parameters over ``windows`` windows (module docstring).

    Args:
        fit: a fitted :class:`OEFit` (its ``segments_`` and ``x0_`` are used by default).
        segments: the fit's segments (default ``fit.segments_``).
        windows: K >= 3.
        alpha: family-wise level of the trend tests.
        min_change: smallest relative change over the recording called a drift.
    """
    segs = list(fit.segments_ if segments is None else segments)
    rep = DriftReport(windows=windows, alpha=alpha, min_change=min_change)
    if windows < 3:
        rep.skipped = f"windows = {windows}: at least 3 are needed for a trend"
        return rep
    m = fit.model
    idx = np.array([i for i in range(m.n_struct) if m.free[i]], dtype=int)
    if idx.size == 0:
        rep.skipped = "the structure has no free parameter"
        return rep
    segs = [sg for sg in segs if sg.n >= windows * MIN_PIECE]
    if not segs or len(segs) != len(fit.segments_ if segments is None else segments):
        rep.skipped = (f"a segment is shorter than {windows} x {MIN_PIECE} samples (at the "
                       "fitting rate)")
        return rep
    # one refit per parameter, shared between the cores (dvt_identify.parallel)
    cols = fork_map(lambda i: _refit_one(fit, int(i), segs, windows), list(idx))
    e0 = _edges(segs[0], windows)
    times = [float(np.mean([0.5 * (sg.t[int(_edges(sg, windows)[k])]
                                   + sg.t[int(_edges(sg, windows)[k + 1]) - 1]) - sg.t[0]
                            for sg in segs])) for k in range(len(e0) - 1)]
    vals = [np.array([c[0][k] for c in cols]) for k in range(windows)]
    stds = [np.array([c[1][k] for c in cols]) for k in range(windows)]
    V, S, T = np.array(vals), np.array(stds), np.array(times)
    finite = np.all(np.isfinite(S) & (S > 0), axis=0)
    n_tested = max(int(np.sum(finite)), 1)
    span = float(T[-1] - T[0])
    for j, i in enumerate(idx):
        name = m.names[i]
        if not finite[j]:
            continue
        wgt = 1.0 / S[:, j] ** 2
        tbar = float(np.sum(wgt * T) / np.sum(wgt))
        sxx = float(np.sum(wgt * (T - tbar) ** 2))
        if sxx <= 0:
            continue
        slope = float(np.sum(wgt * (T - tbar) * V[:, j]) / sxx)
        se = math.sqrt(1.0 / sxx)
        p = float(2.0 * stats.norm.sf(abs(slope) / se))
        mean = float(np.sum(wgt * V[:, j]) / np.sum(wgt))
        chi2 = float(np.sum(wgt * (V[:, j] - mean) ** 2))
        scale = float(np.mean(np.abs(V[:, j]))) or 1.0
        change = slope * span / scale
        steps = np.diff(V[:, j])
        monotone = bool(np.all(steps > 0) or np.all(steps < 0))
        drifting = bool(p < alpha / n_tested and abs(change) >= min_change and monotone)
        rep.parameters.append(ParameterDrift(
            name=name, times=tuple(T.tolist()), values=tuple(V[:, j].tolist()),
            stds=tuple(S[:, j].tolist()), slope=slope, slope_std=se, p_value=p, change=change,
            span=span, chi2=chi2, chi2_p=float(stats.chi2.sf(chi2, windows - 1)),
            drifting=drifting))
    return rep
