"""The output-error fit: :class:`OEFit` minimises the simulation error of an
:class:`~dvt_identify.simulation.OEModel` with ``scipy.optimize.least_squares`` (bounded
``trf``, the Jacobian from the simulation's forward sensitivities,
:mod:`dvt_identify.sensitivity`; a problem whose Jacobian would be large is handed to the
solver by its triangular factor built segment by segment, :mod:`dvt_identify.streamls`),
outputs weighted by ``1/std(y_j)``, each segment with its own estimated initial state, from
several starts (equation-error/physics guess plus random perturbations; starts after the first
are screened on decimated data and polished only when they beat the first; the first start's
run and the screens share the two cores).

The start guard (:mod:`dvt_identify.fitstarts`): the band gains start from a fit of each band's
engagements (:meth:`~dvt_identify.fitstarts.StartPoints.band_start`); of the guess and the extra
starts the one that simulates best runs first; a parameter at a bound that is not its null
value (``at_bounds_``, ``suspect_``) or a first start whose estimation fit is more than a point
below another's triggers more starts once (``notes_`` says so and what came of it).

The fit rate (:mod:`dvt_identify.fitrate`: ``fit_segments``, ``fit_decimation``) follows each
segment's rate and the model's dynamics, and the decimation keeps the zero-order hold of the
simulation (:func:`~dvt_identify.simulation.zoh_decimate`). Measured on ``bags/ident-none-1``
validated on an offline second run: the zero-phase decimation by 5 used before biased ``D`` by 9 %
and ``M`` by up to 6 % (validation fit 97.92 / 98.41 %); the hold-consistent one at the same 200 Hz
gives 0.1 % / 0.8 % and 98.93 / 98.75 %, the same as fitting at the full 1 kHz (98.93 / 98.76 %) at
a third of its time; 125 and 100 Hz lose 0.1-0.3 points and up to 3 % on ``D``. """

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.effects import ParamSpec
from dvt_identify.errors import FitError
from dvt_identify.fitrate import (
    MIN_FIT_SAMPLES,
)
from dvt_identify.fitstarts import (
    StartPoints,
    _x0_guess,
    undo_maps,
    window_sign_starts,
    without_blind_maps,
    x0_guesses,
)
from dvt_identify.parallel import fork_map
from dvt_identify.resid import robust_white_floor
from dvt_identify.sensitivity import simulate_sens
from dvt_identify.simulation import DivergedError, OEModel, zoh_decimate
from dvt_identify.streamls import Block, Factored, dense, dense_ok
from dvt_identify.structures import PENALTY
from dvt_identify.uncertainty import sandwich_by_segment, sandwich_covariance
from dvt_identify.unfold import unfold

Array = NDArray[np.float64]
Progress = Callable[[str], None]
"""Receives progress lines."""


def stderr_progress(msg: str) -> None:
    """Print a progress line to stderr."""
    print(f"[dvt-identify] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# The fit rate

PREFIT_SAMPLES = 60_000
"""A first start on more samples than this (five minutes at 200 Hz) first converges on the
first ``PREFIT_SAMPLES`` of them and then on all of them from there: the iterations far from
the optimum are paid on a part of the data (the full-data optimum is the one reached, from a
start near it; an hour converges in a few full-data iterations instead of forty)."""


STALL_PASSES = 4
"""A long recording's first start on all of it stops when its last :data:`STALL_PASSES`
evaluations (passes over the data) lowered the cost by less than :data:`STALL_RTOL` of it
(:class:`_Stall`)."""
STALL_RTOL = 1e-6
"""See :data:`STALL_PASSES`. An hour at 200 Hz has a cost ragged at about 1e-5 of itself near
its optimum (the dry-friction and band branches switch: trial points a trust-region step away
cost 1.2e-5 more), where ``ftol`` 1e-9 kept the solver on trial steps for 16 of its 27 passes
to lower the cost by 5e-8 of itself."""


COLLAPSED_STATUSES = (3, 4)
"""``least_squares`` statuses of a stop on the step tolerance ``xtol`` (alone, or with
``ftol``): the trust region shrank to nothing, which a kink or a long curved valley of the cost
does as well as a minimum. The best start is then restarted from where it stopped with a fresh
trust region (:meth:`OEFit._restart_collapsed`)."""
RESTART_RTOL = 1e-6
"""A restart (:data:`COLLAPSED_STATUSES`) is kept, and followed by another, only when it lowered
the cost by more than this share of it."""
UNSEEN_RTOL = 1e-6
"""Initial-state directions whose sensitivity over a whole segment is below this fraction of
the largest are unseen by every output (a free rigid-body angle): :meth:`OEFit.window_meat`
leaves them out."""
MAX_RESTARTS = 40
"""At most this many restarts of the best start. Measured on a belt drive read sign-blind
through a filter (``scripts/belt_draws.py --sensor-lag 0.03 --lag-candidate --seeds 10``): the
final refit stopped on ``xtol`` 7 times in a row along the valley of the mass ratio (total
inertia, mode and its damping held) with the pulley's initial speed on the kink of ``|w|``;
the restarts took it from cost 0.5418 to 0.5224 in 18 (724 evaluations; the truth's optimum
0.5216), the belt damping from 25 to 2.7 reported std off."""


class _Stall:
    """``least_squares`` callback (called after each iteration, with the evaluations so far
    and the cost of the accepted point): stops the solver when the cost of the last ``passes``
    evaluations is not below the best before them by ``rtol`` of it."""

    def __init__(self, passes: int = STALL_PASSES, rtol: float = STALL_RTOL) -> None:
        self.passes, self.rtol = passes, rtol
        self.seen: list[tuple[int, float]] = []
        self.stalled = False

    def __call__(self, intermediate_result: Any) -> None:
        nfev, cost = int(intermediate_result.nfev), float(intermediate_result.cost)
        before = [c for n, c in self.seen if n <= nfev - self.passes]
        self.seen.append((nfev, cost))
        if before and min(before) - cost < self.rtol * cost:
            self.stalled = True
            raise StopIteration


def bound_hit(spec: ParamSpec, v: float) -> float | None:
    """The bound of ``spec`` that the value ``v`` sits at, else ``None``: the lower bound when
    within ``1e-6`` of the parameter's scale (its start or initial value) above it, the upper
    within ``0.2 %`` of ``|hi|`` (or of the range) below it (the bounded solver stops just
    inside a bound it pushes)."""
    scale = max(abs(spec.initial), abs(spec.null), 1e-12)
    lo, hi = spec.lower, spec.upper
    if math.isfinite(lo) and v - lo <= max(1e-6 * scale, 1e-9 * abs(lo)):
        return lo
    if math.isfinite(hi):
        width = hi - lo if math.isfinite(lo) else abs(hi)
        if hi - v <= 2e-3 * max(abs(hi), width, 1e-12):
            return hi
    return None


def _first_part(segments: Sequence[Segment]) -> list[Segment]:
    """The segments' first :data:`PREFIT_SAMPLES` samples (whole segments in order, the last
    one cut), or ``[]`` when there are not more samples than that."""
    if sum(s.n for s in segments) <= PREFIT_SAMPLES:
        return []
    out: list[Segment] = []
    left = PREFIT_SAMPLES
    for s in segments:
        if left < MIN_FIT_SAMPLES:
            break
        out.append(s if s.n <= left else s.rows(0, left))
        left -= out[-1].n
    return out


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

    sst: float = 1.0

    @classmethod
    def make(cls, fit: OEFit, segments: Sequence[Segment]) -> _Problem:
        m = fit.model
        lo = np.array([s.lower for s in m.specs])
        hi = np.array([s.upper for s in m.specs])
        nseg = len(segments)
        zlo = np.concatenate([lo[m.free], np.full(nseg * fit._nx0, -np.inf)])
        zhi = np.concatenate([hi[m.free], np.full(nseg * fit._nx0, np.inf)])
        q = max(1, sum(sg.n for sg in segments) // max(fit.screen_samples, 1))
        q = max(1, min([q, *(sg.n // 10 for sg in segments)]))
        screen = [zoh_decimate(sg, q) for sg in segments] if q > 1 else list(segments)
        budget = (fit.screen_nfev if fit.max_nfev is None
                  else min(fit.screen_nfev, fit.max_nfev))
        sst = sum(float(np.sum(((sg.y - sg.y.mean(axis=0)) / fit.weights_) ** 2))
                  for sg in segments)
        return cls(segments=list(segments), screen_segments=screen, q=q, nseg=nseg,
                   w=fit.weights_, lo=lo, hi=hi, zlo=zlo, zhi=zhi, screen_nfev=budget,
                   sst=sst if sst > 0 else 1.0)


LANDING_SCALES = (0.5, 2.0)
"""The factors on a chaotic map's secant step of the refits that measure where the fit lands
(:meth:`OEFit.add_landing_spread`): half and twice the share in use."""


class OEFit(StartPoints):
    """Output-error fit of an :class:`OEModel` to segments (each with its own initial state).

    Args:
        model: structure + effects.
        starts: number of starts (at least; the extra starts always run): the guess (run to
            convergence), then ``extra_starts``, then random perturbations of the free
            parameters by factors in [1/3, 3]; only
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
        more_starts: starts added once when the optimum is suspect (default ``max(4,
            starts)``, 1 when ``theta0`` is given: a refit from a previous optimum; 0: none):
            the suspect optimum with its parameters at a bound reset to their start values,
            then random perturbations.
        physics_start: when ``theta0`` is not given, start the band brakes (engagement lag and
            gain of each brake input) from a fit of the ring's deceleration at each engagement
            (:meth:`band_start`) instead of the description's initial values.
        init_window: 0 (default): every segment's initial state is an unknown of the fit.
            ``n > 0``: the initial state of every segment is the one its first ``n`` samples
            give at the current parameters (:meth:`window_x0`), inside the fit as in every
            later use (:meth:`estimate_x0`): the way a benchmark with a state-initialisation
            window scores a model. An integrating output cannot then hide a drift behind a
            free initial state (measured on EMPS, position output: free initial states give
            6.6-12.9 mm on the test record, the window 5.0-5.2 mm).

    Fitted attributes: ``theta_`` (p,), ``x0_`` list of (nx,), ``cost_`` (0.5 sum of squared
    weighted residuals), ``jac_`` (m, q) over the free parameters then the initial states
    (``None`` for a problem too large to hold it: :mod:`dvt_identify.streamls`),
    ``residual_`` (m,), ``std_`` (p,) parameter standard deviations (0 for fixed ones),
    ``starts_`` list of :class:`StartResult`, ``n_estimated_`` (free parameters + initial states),
    ``weights_`` (ny,), ``seconds_``, ``at_bounds_`` (names of the free parameters at a bound,
    also those of an effect at its null value), ``suspect_`` (why the optimum may be a bad
    local one: a parameter at a bound that is not its null value; empty when fine),
    ``notes_`` (what the start guard did). A suspect optimum, or a first start whose
    estimation fit is more than a point below the best start's (several optima), triggers
    ``more_starts`` further starts once; ``notes_`` says so and what came of it.
    ``restarts_``: restarts of the best start kept after its solver stopped on the step
    tolerance (:data:`COLLAPSED_STATUSES`, :meth:`_restart_collapsed`).
    """

    def __init__(self, model: OEModel, starts: int = 4, seed: int = 0,
                 theta0: Array | None = None, extra_starts: Sequence[Array] = (),
                 weights: Array | None = None, max_nfev: int | None = None,
                 progress: Progress | None = None, screen_nfev: int = 30,
                 screen_samples: int = 3000, more_starts: int | None = None,
                 physics_start: bool = True, init_window: int = 0) -> None:
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
        if more_starts is None:  # a refit from a previous optimum: the targeted reset only
            more_starts = 1 if theta0 is not None else max(4, self.starts)
        self.more_starts = max(0, int(more_starts))
        self.physics_start = physics_start
        if isinstance(init_window, bool) or not isinstance(init_window, int) or init_window < 0:
            raise FitError(f"init_window: expected an integer >= 0 (samples), got "
                           f"{init_window!r}")
        self.init_window = int(init_window)

    def __getstate__(self) -> dict[str, Any]:
        """The fit without its progress callback (a fit handed back from a worker process,
        :mod:`dvt_identify.parallel`, is pickled; a callback may be a closure)."""
        state = dict(self.__dict__)
        state["progress"] = None
        return state

    @property
    def _nx0(self) -> int:
        """Initial-state unknowns per segment in the least-squares vector (0 with a window)."""
        return 0 if self.init_window > 0 else self.model.nx

    def window_x0(self, theta: Array, seg: Segment, guess: Array | None = None,
                  iterations: int = 3) -> Array:
        """The initial state (nx,) that best reproduces the first ``init_window`` samples of
        ``seg`` (weighted outputs) at parameters ``theta``: Gauss-Newton from ``guess``
        (default the outputs' first samples mapped to the states) with the simulation's own
        sensitivities (:func:`~dvt_identify.sensitivity.simulate_sens`), solved by SVD so that
        a state the window does not see keeps its guess (exact after one step for a model
        affine in its initial state)."""
        m = self.model
        n = max(1, min(self.init_window or seg.n, seg.n))
        part = seg if n >= seg.n else seg.rows(0, n)
        w = self.weights_ if hasattr(self, "weights_") else self._output_weights([seg])
        target = (part.y / w).ravel()
        starts = x0_guesses(seg, m) if guess is None else [guess]
        if guess is None:  # the window alone: nothing after it sets the state
            starts += window_sign_starts(m, theta, part, w, self._blind_noise(part))
        best: tuple[float, Array] = (math.inf, np.asarray(starts[0], dtype=float))
        # an output read sign-blind: from either sign of its first value and from the states
        # of the window's best sign patterns, the best one
        for start in starts:
            x0 = np.asarray(start, dtype=float).copy()
            for _ in range(max(1, iterations)):
                try:
                    with np.errstate(all="ignore"):
                        _, yb, S = simulate_sens(m, theta, part, x0, (), True)
                except (DivergedError, np.linalg.LinAlgError, ValueError, OverflowError):
                    break
                base = (yb / w).ravel()
                J = (S / w[None, :, None]).reshape(base.size, m.nx)
                r = target - base
                if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
                    break
                step, *_ = np.linalg.lstsq(J, r, rcond=1e-10)
                x0 = x0 + step
                if float(np.max(np.abs(step))) <= 1e-12 * max(1.0, float(np.max(np.abs(x0)))):
                    break
            if len(starts) == 1:
                return x0
            with np.errstate(all="ignore"):
                r = target - (m.simulate(theta, part, x0) / w).ravel()
            cost = float(r @ r) if np.all(np.isfinite(r)) else math.inf
            if cost < best[0]:
                best = (cost, x0)
        return best[1]

    def _blind_noise(self, seg: Segment) -> list[float]:
        """Robust white-noise std of each output of ``seg`` the model reads sign-blind (of
        ``|y|``, as :func:`dvt_identify.unfold.unfold` takes it), 0 for the others, (ny,)."""
        out = [0.0] * seg.y.shape[1]
        for e in self.model.effects:
            j = e.blind_output()
            if j is not None:
                out[j] = robust_white_floor([np.abs(np.asarray(seg.y[:, j], float))])
        return out

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

    def _unpack(self, z: Array, theta_fixed: Array, nseg: int,
                segments: Sequence[Segment] | None = None) -> tuple[Array, list[Array]]:
        """Parameters and initial states of a least-squares vector ``z``; with a window the
        initial states come from ``segments`` (:meth:`window_x0`; empty without them)."""
        m = self.model
        nfree = int(m.free.sum())
        theta = theta_fixed.copy()
        theta[m.free] = z[:nfree]
        if self.init_window > 0:
            return theta, [self.window_x0(theta, sg) for sg in (segments or ())]
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
            except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError,
                    DivergedError):  # a diverged simulation (OEModel names it): the penalty
                parts.append(np.full(seg.y.size, PENALTY))
        return _clean(np.concatenate(parts))

    def _jacobian(self, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array],
                  w: Array, params: bool = True) -> Array:
        """``d residual / d z`` (m, q) of :meth:`_residual`: the free parameters, then each
        segment's initial state (with a window: the parameters alone, through the window's
        initial state, ``dx0/dtheta = -O^+ dyhat_window/dtheta`` with ``O`` the window's
        initial-state sensitivity, Gauss-Newton). From the simulation's forward sensitivities
        (:mod:`dvt_identify.sensitivity`); a segment that cannot be simulated gives zeros.
        ``params`` false: the initial states' columns alone."""
        q = int(self.model.free.sum()) * params + len(segments) * self._nx0
        return np.vstack([dense(self._rows(theta, seg, x0, w, k, params), q)[0]
                          for k, (seg, x0) in enumerate(zip(segments, x0s, strict=True))])

    def _rows(self, theta: Array, seg: Segment, x0: Array, w: Array, k: int,
              params: bool = True) -> Block:
        """Segment ``k``'s rows of :meth:`_jacobian` over its own unknowns (the free
        parameters and its initial state) and of :meth:`_residual`, from one simulation with
        sensitivities (:data:`~dvt_identify.streamls.Block`)."""
        m = self.model
        free = np.flatnonzero(m.free) if params else np.zeros(0, dtype=int)
        nf = int(free.size)
        nx0 = self._nx0
        cols = np.concatenate([np.arange(nf), nf + k * nx0 + np.arange(nx0)]).astype(np.int64)
        J = np.zeros((seg.y.size, nf + nx0))
        got = self._sens(theta, seg, x0, w, free)
        if got is None:  # the residual is the penalty there
            return J, np.full(seg.y.size, PENALTY), cols
        Sk, yh = got
        if self.init_window > 0:
            total = self._through_window(Sk, nf, seg.n)
            if total is None:  # LAPACK would stop on it: the penalty
                return J, np.full(seg.y.size, PENALTY), cols
            J[:, :nf] = total
        else:
            J[:] = Sk
        J = np.nan_to_num(J, nan=0.0, posinf=0.0, neginf=0.0)
        return J, _clean(((seg.y - yh) / w).ravel()), cols

    def _sens(self, theta: Array, seg: Segment, x0: Array, w: Array, free: NDArray[np.int64]
              ) -> tuple[Array, Array] | None:
        """``d residual / d (free parameters, x0)`` of ``seg`` (N ny, nf + nx) and the
        simulated outputs (N, ny), from one simulation with sensitivities; ``None`` where it
        cannot be simulated."""
        try:
            with np.errstate(all="ignore"):
                _, yh, S = simulate_sens(self.model, theta, seg, x0, free, True)
        except (np.linalg.LinAlgError, ValueError, OverflowError, ZeroDivisionError,
                DivergedError):
            return None
        return -(S / w[None, :, None]).reshape(seg.y.size, free.size + self.model.nx), yh

    def _through_window(self, Sk: Array, nf: int, n: int) -> Array | None:
        """The parameters' columns of ``Sk`` (:meth:`_sens`) with the initial state the
        window gives them, ``dx0/dtheta = -O^+ dyhat_window/dtheta`` (``O`` the window's
        initial-state sensitivity, Gauss-Newton), (N ny, nf); ``None`` when the window's rows
        are not finite."""
        nw = min(n, self.init_window) * self.model.ny
        if not np.all(np.isfinite(Sk[:nw])):
            return None
        dx0 = -np.linalg.lstsq(Sk[:nw, nf:], Sk[:nw, :nf], rcond=1e-10)[0]
        with np.errstate(all="ignore"):  # a solver's trial point far out: the callers clean it
            return np.asarray(Sk[:, :nf] + Sk[:, nf:] @ dx0)

    def window_meat(self, theta: Array, seg: Segment, x0: Array, w: Array
                    ) -> tuple[NDArray[np.int64], Array]:
        """With a window: what its noise adds to the covariance of the scores' sum, over the
        free parameters (their indices among the unknowns, and (nf, nf)); zeros without one.

        The window's samples set the initial state (:meth:`window_x0`): their deviation
        ``e`` from the model moves it by ``O^+ e`` and every residual of the segment by
        ``-Phi O^+ e`` (``O`` the window's rows of the initial-state sensitivity ``Phi``).
        The fitted initial state absorbs that part of the window's own residuals, so no
        residual shows it and the sandwich's scores miss it; it adds ``K V K^T`` with
        ``K = J^T Phi O^+`` and ``V`` the window's deviations' covariance, each output's
        residual autocovariance over the window's lags
        (:func:`~dvt_identify.uncertainty.sandwich_covariance` ``extra``): a smooth
        deviation moves the initial state along the directions the window sees well, white
        noise along all of them.
        Without it the noise of a short window, which the whole record shares, was left out
        of every std (``test_window_uncertainty``: 95 % intervals held the truth in 113 and 100
        of 200 runs without it, 197 and 198 with it)."""
        m = self.model
        free = np.flatnonzero(m.free)
        nf = int(free.size)
        cols = np.arange(nf, dtype=np.int64)
        out = np.zeros((nf, nf))
        got = self._sens(theta, seg, x0, w, free) if self.init_window > 0 and nf else None
        if got is None:
            return cols, out
        Sk, yh = got
        total = self._through_window(Sk, nf, seg.n)
        if total is None:
            return cols, out
        J = np.nan_to_num(total, nan=0.0, posinf=0.0, neginf=0.0)
        phi = np.nan_to_num(Sk[:, nf:], nan=0.0, posinf=0.0, neginf=0.0)
        nt = min(seg.n, self.init_window)
        nw = nt * m.ny
        r = _clean(((seg.y - yh) / w).ravel()).reshape(seg.n, m.ny)
        # the deviations' covariance over the window: each output's sample autocovariance at
        # lags 0..nt-1 (Toeplitz, positive semi-definite), the outputs uncorrelated; rows
        # time-major as the residual's
        V = np.zeros((nw, nw))
        lag = np.abs(np.subtract.outer(np.arange(nt), np.arange(nt)))
        for j in range(m.ny):
            rj = r[:, j]
            gam = np.array([float(rj[: seg.n - k] @ rj[k:]) / seg.n for k in range(nt)])
            V[j::m.ny, j::m.ny] = gam[lag]
        # initial-state directions no output of the record sees (a free rigid-body angle:
        # its sensitivity is rounding noise) move no residual: projected out before the
        # window's inverse, which would otherwise divide rounding noise by rounding noise
        _, sv, vt = np.linalg.svd(phi, full_matrices=False)
        seen = vt[sv > UNSEEN_RTOL * float(sv.max(initial=0.0))].T  # (nx, r)
        if not seen.size:
            return cols, out
        phi = phi @ seen
        K = (J.T @ phi) @ np.linalg.pinv(phi[:nw], rcond=1e-10)  # (nf, nw)
        return cols, np.asarray(K @ V @ K.T)

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
        self.notes_: list[str] = []
        self._first_cost = math.nan
        results: list[tuple[Any, Array]] = []
        self._run_starts(problem, starts, results, math.inf, 0)
        reasons = self._suspect(problem, results)
        if reasons and self.more_starts > 0 and results:
            self.notes_.extend(f"suspect optimum after {len(starts)} start(s): {r}"
                               for r in reasons)
            self._say(f"suspect optimum ({'; '.join(reasons)}): {self.more_starts} more "
                      "start(s)")
            best, st = min(results, key=lambda rs: float(rs[0].cost))
            theta_best, _ = self._unpack(best.x, st, problem.nseg)
            more = self._more_start_points(segments, problem, theta_best, starts[0])
            self._run_starts(problem, more, results, float(best.cost), len(starts))
            reasons = self._suspect(problem, results)
            self.notes_.append("after the extra starts: " + ("; ".join(reasons) if reasons
                                                             else "optimum no longer suspect"))
        self._restart_collapsed(problem, results)
        self._keep_best(results, segments)
        self.suspect_ = [r for r in reasons if not r.startswith("the first start")]
        self.seconds_ = time.monotonic() - t_start
        return self

    def _run_starts(self, problem: _Problem, starts: Sequence[Array],
                    results: list[tuple[Any, Array]], ref: float, first: int) -> None:
        """Run ``starts`` (numbered from ``first``; ``first == 0``: the first runs to
        convergence and is the reference) and append the usable results. The first start's
        run and the screens of the others do not depend on each other and are shared between
        the cores (:func:`~dvt_identify.parallel.fork_map`); the decisions (polish a screened
        start that beats the best so far) are then taken in start order, as one after the
        other."""
        total = first + len(starts)

        def run(k: int) -> tuple[Any, BaseException | None, float]:
            t0 = time.monotonic()
            try:
                return self._first_or_screen(problem, first + k, starts[k]), None, t0
            except ValueError as exc:
                return None, exc, t0
        done = fork_map(run, range(len(starts)))
        for k, st in enumerate(starts):
            i = first + k
            r, err, t0 = done[k]
            if err is not None:
                self._say(f"start {i + 1}/{total} failed: {err}")
                continue
            try:
                r, note, same, usable = self._decide(problem, i, st, r, ref)
            except ValueError as exc:
                self._say(f"start {i + 1}/{total} failed: {exc}")
                continue
            if i == 0:
                ref = float(r.cost)
                self._first_cost = ref
            elif usable:
                ref = min(ref, float(r.cost))
            theta, _ = self._unpack(r.x, st, problem.nseg)
            self.starts_.append(StartResult(start=tuple(st.tolist()), theta=tuple(theta.tolist()),
                                            cost=float(r.cost), nfev=int(r.nfev),
                                            status=int(r.status), note=note.strip(" ()"),
                                            same_minimum=same))
            if usable:  # a screened start's residual and Jacobian are not the full data's
                results.append((r, st))
            self._say(f"start {i + 1}/{total}: cost {r.cost:.6g} after {r.nfev} "
                      f"evaluations{note}, {time.monotonic() - t0:.1f} s")

    def _restart_collapsed(self, problem: _Problem, results: list[tuple[Any, Array]]) -> None:
        """The best usable result, when its solver stopped on the step tolerance
        (:data:`COLLAPSED_STATUSES`), restarted from its parameters (the initial states from
        the data, as a start's) with a fresh trust region on the full data, again while each
        restart stops the same way and lowers the cost by more than :data:`RESTART_RTOL` of it
        (at most :data:`MAX_RESTARTS`); the last improving result replaces it in
        ``results``. Sets ``restarts_`` (restarts kept) and adds a note
        when one was kept."""
        self.restarts_ = 0
        if not results:
            return
        k = min(range(len(results)), key=lambda i: float(results[i][0].cost))
        best, st = results[k]
        if not np.isfinite(best.cost) or int(best.status) not in COLLAPSED_STATUSES:
            return
        cost0, nfev, r = float(best.cost), 0, best
        nf = int(self.model.free.sum())
        guesses = ([] if self.init_window > 0
                   else [_x0_guess(sg, self.model) for sg in problem.segments])
        while self.restarts_ < MAX_RESTARTS and int(r.status) in COLLAPSED_STATUSES:
            # the parameters where it stopped, the initial states from the data again: an
            # initial state left on a kink (an output read as |x| from rest) would collapse
            # the new trust region at once
            z0 = np.clip(np.concatenate([r.x[:nf], *guesses]), problem.zlo, problem.zhi)
            try:
                again = self._solve(problem, st, z0, self.max_nfev, problem.segments)
            except ValueError as exc:
                self._say(f"restart from the best start's end failed: {exc}")
                break
            nfev += int(again.nfev)
            if not float(again.cost) < float(r.cost) * (1.0 - RESTART_RTOL):
                break
            r = again
            self.restarts_ += 1
        if self.restarts_:
            results[k] = (r, st)
            self.notes_.append(
                f"the best start's solver stopped on its step tolerance (trust region "
                f"collapsed: a kink or a curved valley); {self.restarts_} restart(s) from its "
                f"end ({nfev} evaluations) lowered the cost from {cost0:.6g} to "
                f"{float(r.cost):.6g}")
            self._say(self.notes_[-1])

    def bounds_hit(self, theta: Array) -> list[tuple[str, bool]]:
        """Free parameters of ``theta`` at a bound: (name, whether that bound is the
        parameter's null value, i.e. an absent effect rather than a suspect optimum), by
        :func:`bound_hit`."""
        m = self.model
        out = []
        for i, spec in enumerate(m.specs):
            if not m.free[i]:
                continue
            at = bound_hit(spec, float(theta[i]))
            if at is not None:
                is_null = i >= m.n_struct and at == spec.null
                out.append((spec.name, is_null))
        return out

    def _fit_percent(self, problem: _Problem, cost: float) -> float:
        """Pooled estimation fit [%] of a cost: ``100 (1 - sqrt(2 cost / SST))`` with ``SST``
        the weighted sum of squares of the outputs about their means."""
        return 100.0 * (1.0 - math.sqrt(max(2.0 * cost, 0.0) / problem.sst))

    def _suspect(self, problem: _Problem, results: Sequence[tuple[Any, Array]]) -> list[str]:
        """Why the best of ``results`` may be a bad optimum (see the class docstring)."""
        if not results:
            return []
        best, st = min(results, key=lambda rs: float(rs[0].cost))
        theta, _ = self._unpack(best.x, st, problem.nseg)
        out = []
        for name, is_null in self.bounds_hit(theta):
            if not is_null:
                i = self.model.names.index(name)
                spec = self.model.specs[i]
                out.append(f"{name} = {theta[i]:.6g} at its bound [{spec.lower:g}, "
                           f"{spec.upper:g}]")
        c0 = self._first_cost
        if math.isfinite(c0):
            f0 = self._fit_percent(problem, c0)
            fb = self._fit_percent(problem, float(best.cost))
            if fb - f0 > 1.0:
                out.append(f"the first start's estimation fit {f0:.2f} % is far below the best "
                           f"start's {fb:.2f} %")
        return out

    def _check(self, segments: Sequence[Segment]) -> None:
        """Raise :class:`FitError` unless there are segments whose names match the structure."""
        st = self.model.structure
        if not segments:
            raise FitError("no estimation segments")
        for seg in segments:
            if seg.output_names != self.model.output_names:
                raise FitError(f"{seg.name}: outputs {list(seg.output_names)} do not match the "
                               f"structure's outputs {list(self.model.output_names)}")
            if seg.input_names != st.input_names:
                raise FitError(f"{seg.name}: inputs {list(seg.input_names)} do not match the "
                               f"structure's inputs {list(st.input_names)}")

    def _solve(self, problem: _Problem, st: Array, z0: Array, budget: int | None,
               segs: Sequence[Segment], stall: _Stall | None = None) -> Any:
        """``least_squares`` over the free parameters and initial states from ``z0``; a
        problem whose dense Jacobian would be large is handed to it by its triangular factor,
        built segment by segment (:mod:`dvt_identify.streamls`: the same steps, memory that
        does not grow with the recording). ``stall``: its callback (:class:`_Stall`)."""
        if not dense_ok(sum(sg.y.size for sg in segs), z0.size):
            return self._solve_factored(problem, st, z0, budget, segs, stall)

        def fun(z: Array) -> Array:
            theta, x0s = self._unpack(z, st, problem.nseg, segs)
            return self._residual(theta, segs, x0s, problem.w)

        def jac(z: Array) -> Array:
            theta, x0s = self._unpack(z, st, problem.nseg, segs)
            return self._jacobian(theta, segs, x0s, problem.w)
        return least_squares(fun, z0, jac=jac, bounds=(problem.zlo, problem.zhi),
                             x_scale="jac", method="trf", max_nfev=budget, ftol=1e-9,
                             xtol=1e-9, gtol=1e-9, callback=stall)

    def _solve_factored(self, problem: _Problem, st: Array, z0: Array, budget: int | None,
                        segs: Sequence[Segment], stall: _Stall | None = None) -> Any:
        """:meth:`_solve` for a large problem (:class:`~dvt_identify.streamls.Factored`); the
        result's ``fun`` and ``jac`` are the factored problem's (``factored`` is set)."""
        def blocks(z: Array) -> Iterator[Block]:
            theta, x0s = self._unpack(z, st, problem.nseg, segs)
            for k, (seg, x0) in enumerate(zip(segs, x0s, strict=True)):
                yield self._rows(theta, seg, x0, problem.w, k)
        def thunks(z: Array) -> list[Callable[[], Block]]:
            theta, x0s = self._unpack(z, st, problem.nseg, segs)
            return [partial(self._rows, theta, seg, x0, problem.w, k)
                    for k, (seg, x0) in enumerate(zip(segs, x0s, strict=True))]
        fac = Factored(blocks, z0.size, thunks if len(segs) > 1 else None)
        r = least_squares(fac.residual, z0, jac=fac.jacobian,
                          bounds=(problem.zlo, problem.zhi), x_scale="jac", method="trf",
                          max_nfev=budget, ftol=1e-9, xtol=1e-9, gtol=1e-9, callback=stall)
        r.factored = True
        return r

    def _cost(self, problem: _Problem, st: Array, z: Array) -> float:
        """Cost (0.5 sum of squared weighted residuals) of ``z`` on the full data."""
        theta, x0s = self._unpack(z, st, problem.nseg, problem.segments)
        r = self._residual(theta, problem.segments, x0s, problem.w)
        return 0.5 * float(r @ r)

    def _first_or_screen(self, problem: _Problem, i: int, st: Array) -> Any:
        """Start ``i`` from ``st``: the first run to convergence on the full data; another
        screened with a small budget on the decimated data, its cost then taken on the full
        data (to compare with the first start's)."""
        guesses = ([] if self.init_window > 0
                   else [_x0_guess(s, self.model) for s in problem.segments])
        z0 = np.clip(np.concatenate([st[self.model.free], *guesses]), problem.zlo, problem.zhi)
        if i == 0:
            part = _first_part(problem.segments)
            if part:  # a long recording: converge on its first part, then on all of it
                sub = _Problem.make(self, part)
                zp = np.clip(np.concatenate([st[self.model.free], *guesses[: len(part)]]),
                             sub.zlo, sub.zhi)
                rp = self._solve(sub, st, zp, self.max_nfev, part)
                nf = int(self.model.free.sum())
                z0 = np.clip(np.concatenate([rp.x, z0[len(rp.x):]]) if len(rp.x) >= nf
                             else z0, problem.zlo, problem.zhi)
                self._say(f"first start on the first {sum(s.n for s in part)} samples: cost "
                          f"{rp.cost:.6g} after {rp.nfev} evaluations; now on all "
                          f"{sum(s.n for s in problem.segments)}")
                stall = _Stall()
                r = self._solve(problem, st, z0, self.max_nfev, problem.segments, stall)
                if stall.stalled:
                    self._say(f"first start on all samples stopped after {r.nfev} evaluations: "
                              f"the last {STALL_PASSES} lowered the cost by less than "
                              f"{STALL_RTOL:g} of it")
                return r
            return self._solve(problem, st, z0, self.max_nfev, problem.segments)
        r = self._solve(problem, st, z0, problem.screen_nfev, problem.screen_segments)
        r.cost = self._cost(problem, st, r.x) if problem.q > 1 else float(r.cost)
        return r

    def _decide(self, problem: _Problem, i: int, st: Array, r: Any, ref: float
                ) -> tuple[Any, str, bool | None, bool]:
        """What start ``i``'s run (:meth:`_first_or_screen`) gives: the first as it is; a
        screened one polished to convergence on the full data only when it is already better
        than the best so far (cost ``ref``). Returns the result, its note, whether a screened
        start reached the first's minimum and whether its residual and Jacobian are the full
        data's."""
        if i == 0:
            return r, "", None, True
        q = problem.q
        note = f" (screened{f' at 1/{q} rate' if q > 1 else ''})"
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
        theta, x0s = self._unpack(best.x, st, nseg, segments)
        self.theta_ = theta
        self.x0_ = [np.asarray(x, float) for x in x0s]
        self.cost_ = float(best.cost)
        # HAC sandwich (lag window): holds for coloured residuals (dvt_identify.uncertainty)
        # with a window its noise moves every residual through the initial state, which the
        # residuals cannot show (OEFit.window_meat)
        q = int(free.sum()) + nseg * self._nx0
        extra = None
        if self.init_window > 0:
            extra = np.zeros((q, q))
            for sg, x0 in zip(segments, x0s, strict=True):
                c, e = self.window_meat(theta, sg, x0, self.weights_)
                extra[np.ix_(c, c)] += e
        if getattr(best, "factored", False):  # built segment by segment, never held whole
            self.jac_ = None
            self.residual_, cov = sandwich_by_segment(
                lambda k: self._rows(theta, segments[k], x0s[k], self.weights_, k),
                [sg.n for sg in segments], segments[0].y.shape[1], q, extra=extra)
            std_free = cov.std
        else:
            self.residual_ = np.asarray(best.fun, float)
            self.jac_ = np.asarray(best.jac, float)
            std_free = sandwich_covariance(self.jac_, self.residual_, segments[0].y.shape[1],
                                           [sg.n for sg in segments], extra=extra).std
        std = np.zeros(len(m.specs))
        std[free] = std_free[: int(free.sum())]
        self.std_ = std
        self.x0_std_ = std_free[int(free.sum()):]
        self.n_estimated_ = int(free.sum()) + nseg * self._nx0
        self.segments_ = list(segments)
        self.at_bounds_ = [name for name, _ in self.bounds_hit(theta)]
    def estimate_x0(self, seg: Segment, theta: Array | None = None) -> Array:
        """Initial state of ``seg`` that best fits it with the parameters fixed, shape (nx,).

        With ``init_window`` > 0: the state the first ``init_window`` samples give
        (:meth:`window_x0`), as in the fit.

        Only the first ``10 / min|Re(eig A)|`` seconds are used (the initial state's influence
        has decayed by ``e^-10`` after that), at least 200 samples; all of it for integrators.
        """
        th = self.theta_ if theta is None else theta
        if self.init_window > 0:
            return self.window_x0(th, seg)
        w = self.weights_
        try:
            A, _, _ = self.model.structure.matrices(th[: self.model.n_struct])
            slow = float(np.min(np.abs(np.linalg.eigvals(A).real)))
        except (np.linalg.LinAlgError, ValueError):
            slow = 0.0
        n = seg.n
        if slow > 0 and np.isfinite(slow):
            n = int(min(seg.n, max(200, math.ceil(10.0 / (slow * seg.dt)))))
        part = seg if n >= seg.n else seg.rows(0, n)

        def fun(x0: Array) -> Array:
            return self._residual(th, [part], [x0], w)

        def jac(x0: Array) -> Array:
            return self._jacobian(th, [part], [x0], w, params=False)
        # an output read sign-blind: from either sign of its first value, and from the
        # states that fit it unfolded, the best one
        fits = [least_squares(fun, x0, jac=jac, method="trf", x_scale="jac")
                for x0 in [*x0_guesses(seg, self.model), *self._unfolded_x0(th, part)]]
        return np.asarray(min(fits, key=lambda r: float(r.cost)).x, float)

    def _unfolded_x0(self, theta: Array, seg: Segment) -> list[Array]:
        """Initial-state starts (each (nx,)) for a model that reads outputs sign-blind: with
        those outputs unfolded (:func:`dvt_identify.unfold.unfold`, either overall sign) the
        model without its sign-blind maps is fitted in its initial state alone (no ``|y|``
        between the state and the data: one basin where the map has one per sign pattern of
        the free response). Output maps with an inverse (:meth:`Effect.output_inverse`: a
        filter on the reading) are undone before the unfolding, at ``theta``, and left out of
        that model. Empty for a model without such an output."""
        m = self.model
        blind, bare = without_blind_maps(m, theta)
        if not blind:
            return []
        # a map with an inverse (a filter on the reading) undone first, at its value here: it
        # smooths the dips of |y| that tell where the sign changes; the state is then fitted
        # on the model without it too
        segs, undone = undo_maps(list(zip(m.effects, m.effect_params(theta), strict=True)),
                                 [seg])
        for k in undone:
            bare[m.effect_slice(k)] = [q.null for q in m.effects[k].params]
        for _, j in blind:
            segs = unfold(segs, j)
        w = self.weights_
        cols = [j for _, j in blind]
        out = []
        for sign in (1.0, -1.0):
            target = np.array(segs[0].y, dtype=float, copy=True)
            target[:, cols] *= sign

            def fun(x0: Array, target: Array = target) -> Array:
                with np.errstate(all="ignore"):
                    r = ((target - m.simulate(bare, seg, x0)) / w).ravel()
                return np.where(np.isfinite(r), r, 1e6)
            out.append(np.asarray(least_squares(fun, _x0_guess(seg, m), method="trf",
                                                x_scale="jac").x, float))
        return out

    def predict(self, seg: Segment, x0: Array | None = None) -> Array:
        """Simulated outputs of ``seg`` (N, ny); ``x0`` estimated when not given."""
        x = self.estimate_x0(seg) if x0 is None else x0
        return self.model.simulate(self.theta_, seg, x)

    def parameters(self) -> dict[str, float]:
        """Physical parameters by name (structure, effects, derived)."""
        return self.model.parameters(self.theta_)

    def add_landing_spread(self, segments: Sequence[Segment],
                           scales: Sequence[float] = LANDING_SCALES) -> OEFit:
        """Add where the fit lands in a chaotic map's rough cost to ``std_``; returns self.

        A model with chaotic output maps (:meth:`OEModel.chaotic_parameters`, a load rattling
        in a play) is fitted along the secants of those maps' own parameters
        (:meth:`Effect.secant_step`), and where the optimiser stops in their rough cost moves
        with that secant by more than the sandwich std. This refits ``segments`` (the fit's
        own) from the start that gave ``theta_`` with each map's secant scaled by each of
        ``scales`` (the effects' option ``secant_scale``) and adds the sample variance of the
        landings (this fit's and the refits', per parameter) to the variance of every free
        parameter. Sets ``landing_spread_`` (p,) (0 without chaotic maps: nothing is
        refitted).
        """
        m = self.model
        self.landing_spread_ = np.zeros(len(m.specs))
        if not m.chaotic_parameters() or not scales:
            return self
        landings = [self.theta_]
        landings.extend(self.refit_secant(segments, f).theta_ for f in scales)
        spread = np.std(np.vstack(landings), axis=0, ddof=1)
        spread[~m.free] = 0.0
        self.landing_spread_ = spread
        self.std_ = np.sqrt(self.std_ ** 2 + spread ** 2)
        self._say("landing spread of the chaotic maps' fit (secant x "
                  + ", ".join(f"{f:g}" for f in (1.0, *scales)) + "): "
                  + ", ".join(f"{m.names[j]} {spread[j]:.3g}" for j in m.chaotic_parameters()))
        return self

    def refit_secant(self, segments: Sequence[Segment], scale: float) -> OEFit:
        """A new fit of ``segments`` with every chaotic output map's secant scaled by ``scale``
        (the effects' option ``secant_scale``), from the start that gave ``theta_`` (refitted
        from ``theta_`` itself the optimiser stays put: where it lands in the rough cost is the
        path's, not a local property), with this fit's weights; its ``std_`` the sandwich's.
        (:meth:`add_landing_spread`; ``scripts/secant_sweep.py`` sweeps ``scale``.)

        Raises:
            FitError: ``scale`` is not finite and > 0.
        """
        if not (math.isfinite(scale) and scale > 0):
            raise FitError(f"refit_secant: scale must be finite and > 0, got {scale}")
        m = self.model
        best = min(self.starts_, key=lambda r: r.cost) if self.starts_ else None
        origin = np.array(best.start, float) if best is not None else self.theta_
        effs = [dataclasses.replace(e, options={**e.options, "secant_scale": float(scale)})
                if e.chaotic_output else e for e in m.effects]
        return OEFit(OEModel(m.structure, effs), theta0=origin, weights=self.weights_,
                     max_nfev=self.max_nfev, more_starts=0, physics_start=False,
                     init_window=self.init_window).fit(segments)

    def parameter_std(self) -> dict[str, float]:
        """Standard deviation of every estimated model parameter by name."""
        return {n: float(s) for n, s, f in zip(self.model.names, self.std_, self.model.free,
                                                strict=True) if f}

