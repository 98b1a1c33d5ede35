"""The output-error fit: :class:`OEFit` minimises the simulation error of an
:class:`~dvt_identify.simulation.OEModel` with ``scipy.optimize.least_squares`` (bounded
``trf``), outputs weighted by ``1/std(y_j)``, each segment with its own estimated initial state,
from several starts (equation-error/physics guess plus random perturbations; starts after the
first are screened on decimated data and polished only when they beat the first).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from dvt_identify.data import Segment, decimate
from dvt_identify.errors import FitError
from dvt_identify.metrics import parameter_std
from dvt_identify.simulation import OEModel
from dvt_identify.structures import PENALTY

Array = NDArray[np.float64]
Progress = Callable[[str], None]
"""Receives progress lines."""


def stderr_progress(msg: str) -> None:
    """Print a progress line to stderr."""
    print(f"[dvt-identify] {msg}", file=sys.stderr, flush=True)


def _x0_guess(seg: Segment) -> Array:
    return np.asarray(seg.y[: min(3, seg.n)].mean(axis=0), dtype=float)


def _clean(r: Array) -> Array:
    r = np.nan_to_num(r, nan=PENALTY, posinf=PENALTY, neginf=-PENALTY)
    return np.asarray(np.clip(r, -PENALTY, PENALTY))


@dataclass(frozen=True)
class StartResult:
    """One start of a multi-start fit: start point, end point, cost at the end point on the full
    data, evaluations, scipy status, how it ran (``note``) and, for a screened start, whether it
    reached the first start's minimum (screening cost within 0.1 % of the reference)."""

    start: tuple[float, ...]
    theta: tuple[float, ...]
    cost: float
    nfev: int
    status: int
    note: str = ""
    same_minimum: bool | None = None



@dataclass(frozen=True)
class _Problem:
    """One fit's least-squares problem: the data, the screening data, the output scale and the
    bounds of the parameters (p,) and of the unknowns ``z`` = free parameters + initial states.

    Attributes:
        segments: estimation segments.
        screen_segments: the same decimated by ``q`` (to about ``screen_samples`` samples).
        q: the screening decimation factor (1: none).
        nseg: number of segments.
        w: output scale (ny,).
        lo, hi: parameter bounds, shape (p,).
        zlo, zhi: bounds of ``z``, shape (n_free + nseg * nx,).
        screen_nfev: evaluation budget of a screened start.
    """

    segments: Sequence[Segment]
    screen_segments: Sequence[Segment]
    q: int
    nseg: int
    w: Array
    lo: Array
    hi: Array
    zlo: Array
    zhi: Array
    screen_nfev: int

    @classmethod
    def make(cls, fit: OEFit, segments: Sequence[Segment]) -> _Problem:
        m = fit.model
        lo = np.array([s.lower for s in m.specs])
        hi = np.array([s.upper for s in m.specs])
        nseg = len(segments)
        zlo = np.concatenate([lo[m.free], np.full(nseg * m.nx, -np.inf)])
        zhi = np.concatenate([hi[m.free], np.full(nseg * m.nx, np.inf)])
        q = max(1, sum(sg.n for sg in segments) // max(fit.screen_samples, 1))
        screen = [decimate(sg, q) for sg in segments] if q > 1 else list(segments)
        budget = (fit.screen_nfev if fit.max_nfev is None
                  else min(fit.screen_nfev, fit.max_nfev))
        return cls(segments=list(segments), screen_segments=screen, q=q, nseg=nseg,
                   w=fit.weights_, lo=lo, hi=hi, zlo=zlo, zhi=zhi, screen_nfev=budget)


class OEFit:
    """Output-error fit of an :class:`OEModel` to segments (each with its own initial state).

    Args:
        model: structure + effects.
        starts: number of starts: the guess (run to convergence), then ``extra_starts``, then
            random perturbations of the structure's parameters by factors in [1/3, 3]; only
            starts with a stable linear part and a non-zero B are used. Starts after the first
            get ``screen_nfev`` evaluations on decimated data and are run to convergence on the
            full data only if they are then already better than the first.
        seed: random seed of the perturbations.
        theta0: start value of all parameters (default: structure guess + effects' initial).
        extra_starts: further full start vectors tried before the random ones.
        weights: output scale (ny,); residuals are divided by it (default std(y) pooled).
        max_nfev: cap on function evaluations per start (``None``: scipy's default).
        progress: called with progress lines.
        screen_nfev: evaluation budget of the screened starts.
        screen_samples: screened starts run on the data decimated to about this many samples
            (their cost is then evaluated on the full data).

    Fitted attributes: ``theta_`` (p,), ``x0_`` list of (nx,), ``cost_`` (0.5 sum of squared
    weighted residuals), ``jac_`` (m, q) over the free parameters then the initial states,
    ``residual_`` (m,), ``std_`` (p,) parameter standard deviations (0 for fixed ones),
    ``starts_`` list of :class:`StartResult`, ``n_estimated_`` (free parameters + initial states),
    ``weights_`` (ny,), ``seconds_``.
    """

    def __init__(self, model: OEModel, starts: int = 4, seed: int = 0,
                 theta0: Array | None = None, extra_starts: Sequence[Array] = (),
                 weights: Array | None = None, max_nfev: int | None = None,
                 progress: Progress | None = None, screen_nfev: int = 30,
                 screen_samples: int = 3000) -> None:
        self.model = model
        self.starts = max(1, int(starts))
        self.seed = seed
        self.theta0 = theta0
        self.extra_starts = list(extra_starts)
        self.weights = weights
        self.max_nfev = max_nfev
        self.screen_nfev = screen_nfev
        self.screen_samples = screen_samples
        self.progress = progress

    def _usable(self, theta: Array) -> bool:
        """A start is usable when its linear part is finite, not unstable (eigenvalues of A with
        real part <= 0) and its B is not all zero."""
        try:
            A, B, _ = self.model.structure.matrices(theta[: self.model.n_struct])
        except (np.linalg.LinAlgError, ValueError):
            return False
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))) or not np.any(B):
            return False
        scale = float(np.max(np.abs(A))) if A.size else 0.0
        return bool(np.max(np.linalg.eigvals(A).real, initial=-np.inf) <= 1e-9 * scale)

    def _say(self, msg: str) -> None:
        if self.progress is not None:
            self.progress(msg)

    def _unpack(self, z: Array, theta_fixed: Array, nseg: int) -> tuple[Array, list[Array]]:
        m = self.model
        nfree = int(m.free.sum())
        theta = theta_fixed.copy()
        theta[m.free] = z[:nfree]
        x0s = [z[nfree + i * m.nx: nfree + (i + 1) * m.nx] for i in range(nseg)]
        return theta, x0s

    def _residual(self, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array],
                  w: Array) -> Array:
        parts = []
        for seg, x0 in zip(segments, x0s, strict=True):
            try:
                with np.errstate(all="ignore"):
                    yh = self.model.simulate(theta, seg, x0)
                parts.append(((seg.y - yh) / w).ravel())
            except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError):
                parts.append(np.full(seg.y.size, PENALTY))
        return _clean(np.concatenate(parts))

    def fit(self, segments: Sequence[Segment]) -> OEFit:
        """Fit to ``segments``; returns self.

        Raises:
            FitError: no segments, inconsistent names, or no start gave a finite cost.
        """
        t_start = time.monotonic()
        self._check(segments)
        self.weights_ = self._output_weights(segments)
        problem = _Problem.make(self, segments)
        starts = self._start_points(segments, problem.lo, problem.hi)
        self.starts_: list[StartResult] = []
        results: list[tuple[Any, Array]] = []
        ref = math.inf
        for i, st in enumerate(starts):
            t0 = time.monotonic()
            try:
                r, note, same, usable = self._run_start(problem, i, st, ref)
            except ValueError as exc:
                self._say(f"start {i + 1}/{len(starts)} failed: {exc}")
                continue
            if i == 0:
                ref = float(r.cost)
            theta, _ = self._unpack(r.x, st, problem.nseg)
            self.starts_.append(StartResult(start=tuple(st.tolist()), theta=tuple(theta.tolist()),
                                            cost=float(r.cost), nfev=int(r.nfev),
                                            status=int(r.status), note=note.strip(" ()"),
                                            same_minimum=same))
            if usable:  # a screened start's residual and Jacobian are not the full data's
                results.append((r, st))
            self._say(f"start {i + 1}/{len(starts)}: cost {r.cost:.6g} after {r.nfev} "
                      f"evaluations{note}, {time.monotonic() - t0:.1f} s")
        self._keep_best(results, segments)
        self.seconds_ = time.monotonic() - t_start
        return self

    def _check(self, segments: Sequence[Segment]) -> None:
        """Raise :class:`FitError` unless there are segments whose names match the structure."""
        st = self.model.structure
        if not segments:
            raise FitError("no estimation segments")
        for seg in segments:
            if seg.output_names != st.state_names:
                raise FitError(f"{seg.name}: outputs {list(seg.output_names)} do not match the "
                               f"structure's states {list(st.state_names)}")
            if seg.input_names != st.input_names:
                raise FitError(f"{seg.name}: inputs {list(seg.input_names)} do not match the "
                               f"structure's inputs {list(st.input_names)}")

    def _output_weights(self, segments: Sequence[Segment]) -> Array:
        """Output scale (ny,): the given weights, else ``std(y_j)`` pooled (1 where it is 0)."""
        if self.weights is not None:
            return np.asarray(self.weights, dtype=float)
        w = np.std(np.vstack([s.y for s in segments]), axis=0)
        w[w == 0] = 1.0
        return np.asarray(w, dtype=float)

    def _start_points(self, segments: Sequence[Segment], lo: Array, hi: Array) -> list[Array]:
        """The guess, the usable extra starts, then usable random perturbations of the
        structure's parameters by factors in [1/3, 3] (all within the bounds), each (p,)."""
        m = self.model
        if self.theta0 is not None:
            guess = np.asarray(self.theta0, dtype=float).copy()
        else:
            guess = m.initial()
            guess[: m.n_struct] = m.structure.initial_guess(segments)
        guess = np.clip(guess, lo, hi)
        rng = np.random.default_rng(self.seed)
        starts = [guess]
        for st in self.extra_starts:
            st = np.clip(np.asarray(st, float), lo, hi)
            if self._usable(st) and not np.allclose(st, guess):
                starts.append(st)
        scale = float(np.max(np.abs(guess[: m.n_struct]))) if m.n_struct else 0.0
        tries = 0
        while len(starts) < self.starts and tries < 50 * self.starts:
            tries += 1
            st = guess.copy()
            for i in range(m.n_struct):
                f = math.exp(rng.uniform(-math.log(3.0), math.log(3.0)))
                st[i] = st[i] * f if st[i] != 0 else rng.normal(0.0, 0.1) * (scale or 1.0)
            st = np.clip(st, lo, hi)
            if self._usable(st):
                starts.append(st)
        return starts

    def _solve(self, problem: _Problem, st: Array, z0: Array, budget: int | None,
               segs: Sequence[Segment]) -> Any:
        """``least_squares`` over the free parameters and initial states from ``z0``."""
        def fun(z: Array) -> Array:
            theta, x0s = self._unpack(z, st, problem.nseg)
            return self._residual(theta, segs, x0s, problem.w)
        return least_squares(fun, z0, bounds=(problem.zlo, problem.zhi), x_scale="jac",
                             method="trf", max_nfev=budget, ftol=1e-9, xtol=1e-9, gtol=1e-9)

    def _cost(self, problem: _Problem, st: Array, z: Array) -> float:
        """Cost (0.5 sum of squared weighted residuals) of ``z`` on the full data."""
        theta, x0s = self._unpack(z, st, problem.nseg)
        r = self._residual(theta, problem.segments, x0s, problem.w)
        return 0.5 * float(r @ r)

    def _run_start(self, problem: _Problem, i: int, st: Array, ref: float
                   ) -> tuple[Any, str, bool | None, bool]:
        """Run start ``i`` from ``st``: the first to convergence; the others screened with a
        small budget on the decimated data and polished only when better than the first
        (cost ``ref``). Returns the result, its note, whether a screened start reached the
        first's minimum and whether its residual and Jacobian are the full data's."""
        z0 = np.clip(np.concatenate([st[self.model.free],
                                     *[_x0_guess(s) for s in problem.segments]]),
                     problem.zlo, problem.zhi)
        if i == 0:
            return self._solve(problem, st, z0, self.max_nfev, problem.segments), "", None, True
        q = problem.q
        r = self._solve(problem, st, z0, problem.screen_nfev, problem.screen_segments)
        note = f" (screened{f' at 1/{q} rate' if q > 1 else ''})"
        # compared with the first start on the full data
        r.cost = self._cost(problem, st, r.x) if q > 1 else float(r.cost)
        same: bool | None = bool(r.cost <= ref * (1 + 1e-3))
        if r.cost < ref * (1 - 1e-4):
            r = self._solve(problem, st, r.x, self.max_nfev, problem.segments)  # polish
            return r, " (screened, then polished)", None, True
        return r, note, same, False

    def _keep_best(self, results: Sequence[tuple[Any, Array]],
                   segments: Sequence[Segment]) -> None:
        """Set the fitted attributes from the cheapest usable result.

        Raises:
            FitError: no usable result, or none with a finite cost.
        """
        m = self.model
        if not results:
            raise FitError("no start gave a usable fit")
        best, st = min(results, key=lambda rs: float(rs[0].cost))
        if not np.isfinite(best.cost) or best.cost >= 0.5 * PENALTY ** 2:
            raise FitError("simulation diverged from every start (no finite cost)")
        nseg = len(segments)
        free = m.free
        theta, x0s = self._unpack(best.x, st, nseg)
        self.theta_ = theta
        self.x0_ = [np.asarray(x, float) for x in x0s]
        self.cost_ = float(best.cost)
        self.residual_ = np.asarray(best.fun, float)
        self.jac_ = np.asarray(best.jac, float)
        std_free = parameter_std(self.jac_, self.residual_)
        std = np.zeros(len(m.specs))
        std[free] = std_free[: int(free.sum())]
        self.std_ = std
        self.x0_std_ = std_free[int(free.sum()):]
        self.n_estimated_ = int(free.sum()) + nseg * m.nx
        self.segments_ = list(segments)
    def estimate_x0(self, seg: Segment, theta: Array | None = None) -> Array:
        """Initial state of ``seg`` that best fits it with the parameters fixed, shape (nx,).

        Only the first ``10 / min|Re(eig A)|`` seconds are used (the initial state's influence
        has decayed by ``e^-10`` after that), at least 200 samples; all of it for integrators.
        """
        th = self.theta_ if theta is None else theta
        w = self.weights_
        try:
            A, _, _ = self.model.structure.matrices(th[: self.model.n_struct])
            slow = float(np.min(np.abs(np.linalg.eigvals(A).real)))
        except (np.linalg.LinAlgError, ValueError):
            slow = 0.0
        n = seg.n
        if slow > 0 and np.isfinite(slow):
            n = int(min(seg.n, max(200, math.ceil(10.0 / (slow * seg.dt)))))
        part = seg if n >= seg.n else replace(seg, t=seg.t[:n], u=seg.u[:n], y=seg.y[:n])

        def fun(x0: Array) -> Array:
            return self._residual(th, [part], [x0], w)
        r = least_squares(fun, _x0_guess(seg), method="trf", x_scale="jac")
        return np.asarray(r.x, float)

    def predict(self, seg: Segment, x0: Array | None = None) -> Array:
        """Simulated outputs of ``seg`` (N, ny); ``x0`` estimated when not given."""
        x = self.estimate_x0(seg) if x0 is None else x0
        return self.model.simulate(self.theta_, seg, x)

    def parameters(self) -> dict[str, float]:
        """Physical parameters by name (structure, effects, derived)."""
        return self.model.parameters(self.theta_)

    def parameter_std(self) -> dict[str, float]:
        """Standard deviation of every estimated model parameter by name."""
        return {n: float(s) for n, s, f in zip(self.model.names, self.std_, self.model.free,
                                                strict=True) if f}

