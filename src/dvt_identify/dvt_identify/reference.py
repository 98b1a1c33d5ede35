"""The black-box linear reference: the best LTI state-space model of the same data, put beside
every physical model and simulated and scored exactly like it (issue 21 item 1).

:class:`LinearReference` fits, for each order ``n = 1..max_order``, the discrete-time model

    x[k+1] = A x[k] + B u[k],   y[k] = C x[k] (+ D u[k] with ``feedthrough``)

at the sample time ``dt_`` of the first estimation segment, and keeps the smallest order whose
selection fit is within :data:`SELECT_TOL` points of the best.

Each order starts from a subspace fit (N4SID/PO-MOESP, the scheme of the ``nfoursid`` package
computed here with numpy, :class:`_N4SID`) on the longest estimation segment at ``dt_``,
decimated to at most :data:`N4SID_SAMPLES` samples and brought back to ``dt_`` by the ``q``-th
root of its poles. When that step fails, or the refined
fit is worse on the estimation data than the previous order's, the order starts from the
previous order's optimum augmented by one small stable mode (rising order); ``orders_`` says
which start was kept.

The start is refined by output error: ``scipy.optimize.least_squares`` minimises the simulation
error over all estimation segments (each with its own initial state as unknowns, outputs
weighted by ``1/std(y_j)`` pooled over segments) with an analytic Jacobian from a
numba-compiled sensitivity recursion, handed to MINPACK by its triangular factor
(:class:`_Compressed`). The orders' subspace starts are refined on both cores. ``A``,
``B``, ``C`` (and ``D``) are fully parametrised.
Poles may leave the unit circle slightly (a drive under closed-loop control can need an
integrator-like pole at 1.0001); a simulation that overflows gives a finite penalty.

Initial states with the parameters fixed (selection, :meth:`LinearReference.estimate_x0`) are
the exact linear least-squares fit on the first ``10 / min|Re(s)|`` seconds (``s`` the
continuous-time poles), at least 200 samples, all of the segment for an integrator: the rule of
:meth:`dvt_identify.fit.OEFit.estimate_x0`; or on the first ``n_init`` samples (benchmark style).

A segment at another sample time is simulated through the continuous-time equivalent: the
matrix logarithm of ``[[A, B], [0, I]]`` (zero-order hold), exponentiated at its own rate; the
fit differentiates through that conversion (Fréchet derivatives of ``expm``).

Measured on EMPS (24 841 samples at 1 kHz, force in, position out; 2 cores shared with other
jobs, load 4-5), before the subspace step was computed here and the Jacobian factored: orders
1..4 fit in 3.4 s (one BLAS thread; 4.7-5.7 s with the default threads), plus 1.3 s the first
time numba compiles the kernels and 0.5 s to import ``nfoursid``/``pandas``; orders 1..6 in
12.8 s. Per iteration the time goes to the sensitivity recursion (``O(N n^2 p)``) and the QR of
the ``N x p`` Jacobian (now one LAPACK QR per evaluation instead of MINPACK's own). Validation
RMS position error, orders 1-4, initial state from the first 20 samples (the benchmark's
protocol): 39.0 / 21.1 / 693 / 20 370 mm (order 2 chosen); from the ``OEFit`` window: 17.3 /
4.75 / 4.45 / 4.44 mm. The fitted models keep a slightly unstable real pole (+0.06 to +0.1 1/s)
beside the integrator, and 20 samples of a drive that is already moving fix the velocity-like
state poorly, so the short window's error grows along the record.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.linalg import expm, expm_frechet, logm
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.errors import DataError, FitError
from dvt_identify.metrics import figures
from dvt_identify.parallel import fork_map, workers
from dvt_identify.streamls import Factored

Array = NDArray[np.float64]

SELECT_TOL = 0.1
"""Points of mean selection fit [%] within which the smallest order wins."""
N4SID_SAMPLES = 1500
"""Most samples handed to ``nfoursid`` (the record is decimated to fit)."""
X_LIMIT = 1e60
"""A simulated state beyond this magnitude counts as overflow (finite penalty)."""
PENALTY = 1e10
"""Weighted residual of every sample of a simulation that overflowed."""
MODE_GAIN = 0.01
"""Output share (of ``std(y)``) of the small stable mode that raises the order."""
FTOL = 1e-6
"""Relative cost change that ends a refinement (a fit change of about ``1e-4`` points)."""
STALL_POINTS = SELECT_TOL / 10
"""Fit gain [points] below which a refinement has stalled (an order drifting to a pole at
infinity or a pole-zero cancellation crawls for hundreds of iterations for nothing)..."""
STALL_ITERATIONS = 10
"""... over this many iterations."""
X0_MIN_SAMPLES = 200
"""Fewest samples of the initial-state window (the rule of ``OEFit.estimate_x0``)."""


# ---------------------------------------------------------------------------------------------
# Compiled kernels


@njit(cache=True, nogil=True)
def _sim(A: Array, B: Array, C: Array, D: Array, u: Array, x0: Array, y: Array) -> bool:
    """Simulate into ``y`` (N, ny); False when a state overflows (``y`` then incomplete)."""
    n = A.shape[0]
    nu = B.shape[1]
    ny = C.shape[0]
    x = x0.copy()
    xn = np.empty(n)
    for k in range(u.shape[0]):
        for r in range(ny):
            s = 0.0
            for i in range(n):
                s += C[r, i] * x[i]
            for j in range(nu):
                s += D[r, j] * u[k, j]
            y[k, r] = s
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += A[i, j] * x[j]
            for j in range(nu):
                s += B[i, j] * u[k, j]
            if not abs(s) < X_LIMIT:
                return False
            xn[i] = s
        x, xn = xn, x
    return True


@njit(cache=True, nogil=True)
def _sim_jac(A: Array, B: Array, C: Array, D: Array, u: Array, x0: Array, feed: bool,
             y: Array, J: Array) -> bool:
    """Simulate into ``y`` (N, ny) and fill ``J`` (N*ny, p), zeroed by the caller, with
    ``d y / d theta``, theta = (A, B, C, [D], x0) row-major; the sensitivities of the state to
    A, B and x0 propagate through A. False when a state overflows."""
    n = A.shape[0]
    nu = B.shape[1]
    ny = C.shape[0]
    na = n * n
    nab = na + n * nu
    ns = nab + n
    c_c = nab
    c_d = c_c + ny * n
    c_x = c_d + (ny * nu if feed else 0)
    S = np.zeros((ns, n))  # S[c, i] = d x_i / d theta_c (A, B, x0 columns)
    Sn = np.empty((ns, n))
    for i in range(n):
        S[nab + i, i] = 1.0
    x = x0.copy()
    xn = np.empty(n)
    for k in range(u.shape[0]):
        for r in range(ny):
            row = k * ny + r
            s = 0.0
            for i in range(n):
                s += C[r, i] * x[i]
                J[row, c_c + r * n + i] = x[i]
            for j in range(nu):
                s += D[r, j] * u[k, j]
                if feed:
                    J[row, c_d + r * nu + j] = u[k, j]
            y[k, r] = s
            for c in range(nab):
                s = 0.0
                for i in range(n):
                    s += C[r, i] * S[c, i]
                J[row, c] = s
            for c in range(n):
                s = 0.0
                for i in range(n):
                    s += C[r, i] * S[nab + c, i]
                J[row, c_x + c] = s
        for c in range(ns):
            for i in range(n):
                s = 0.0
                for m in range(n):
                    s += A[i, m] * S[c, m]
                Sn[c, i] = s
        for i in range(n):
            for j in range(n):
                Sn[i * n + j, i] += x[j]
            for j in range(nu):
                Sn[na + i * nu + j, i] += u[k, j]
            s = 0.0
            for j in range(n):
                s += A[i, j] * x[j]
            for j in range(nu):
                s += B[i, j] * u[k, j]
            if not abs(s) < X_LIMIT:
                return False
            xn[i] = s
        x, xn = xn, x
        S, Sn = Sn, S
    return True


def warm_up() -> None:
    """Load the two kernels (compiled on a process's first use, cached on disk)."""
    z = np.zeros((1, 1))
    y = np.zeros((2, 1))
    _sim(z, z, z, z, np.zeros((2, 1)), np.zeros(1), y)
    _sim_jac(z, z, z, z, np.zeros((2, 1)), np.zeros(1), False, y, np.zeros((2, 4)))


# ---------------------------------------------------------------------------------------------
# Models and rates


@dataclass(frozen=True)
class StateSpace:
    """A discrete-time LTI model at sample time ``dt`` [s]: ``A`` (n, n), ``B`` (n, nu),
    ``C`` (ny, n), ``D`` (ny, nu)."""

    A: Array
    B: Array
    C: Array
    D: Array
    dt: float

    @property
    def nx(self) -> int:
        """State dimension n."""
        return int(self.A.shape[0])

    def poles_s(self) -> NDArray[np.complex128]:
        """Continuous-time poles ``log(z) / dt`` [1/s] (``-inf`` for a pole at 0)."""
        z = np.linalg.eigvals(self.A).astype(complex)
        with np.errstate(divide="ignore"):
            return np.asarray(np.log(z) / self.dt)

    def at(self, dt: float, name: str = "segment") -> tuple[Array, Array]:
        """``(A, B)`` at sample time ``dt`` [s] through the continuous-time equivalent
        (zero-order hold). Raises FitError naming ``name`` and both rates when the matrix
        logarithm does not exist as a real matrix (a pole at 0 or on the negative axis)."""
        if math.isclose(dt, self.dt, rel_tol=1e-9):
            return self.A, self.B
        L = _log_block(self.A, self.B)
        if L is None:
            raise FitError(f"{name}: cannot simulate at dt = {dt:g} s a linear model fitted "
                           f"at dt = {self.dt:g} s: it has no continuous-time equivalent (a "
                           f"pole at 0 or on the negative real axis)")
        M = expm(L * (dt / self.dt))
        n = self.nx
        return np.ascontiguousarray(M[:n, :n]), np.ascontiguousarray(M[:n, n:])


def _log_block(A: Array, B: Array) -> Array | None:
    """Real ``logm([[A, B], [0, I]])`` or None when it does not exist."""
    n, nu = B.shape
    M = np.block([[A, B], [np.zeros((nu, n)), np.eye(nu)]])
    try:
        with np.errstate(all="ignore"):
            L = logm(M)
    except (ValueError, np.linalg.LinAlgError):
        return None
    L = np.asarray(L)
    if not np.all(np.isfinite(L)):
        return None
    if np.iscomplexobj(L):
        if np.max(np.abs(L.imag)) > 1e-8 * max(1.0, float(np.max(np.abs(L.real)))):
            return None
        L = L.real
    if np.max(np.abs(expm(L) - M)) > 1e-6 * max(1.0, float(np.max(np.abs(M)))):
        return None
    return np.asarray(L, dtype=float)


def _expm_jacobian(X: Array) -> Array:
    """``d vec(expm(X)) / d vec(X)`` (row-major vec), shape (m^2, m^2)."""
    m = X.shape[0]
    K = np.empty((m * m, m * m))
    E = np.zeros((m, m))
    for idx in range(m * m):
        E.flat[idx] = 1.0
        K[:, idx] = np.asarray(expm_frechet(X, E, compute_expm=False)).ravel()
        E.flat[idx] = 0.0
    return K


def _rate_jacobian(A: Array, B: Array, ratio: float) -> Array | None:
    """``d (A2, B2) / d (A, B)`` (row-major, A then B) of the conversion to ``ratio * dt``,
    or None when the logarithm does not exist."""
    n, nu = B.shape
    m = n + nu
    L = _log_block(A, B)
    if L is None:
        return None
    try:
        full = ratio * _expm_jacobian(ratio * L) @ np.linalg.inv(_expm_jacobian(L))
    except np.linalg.LinAlgError:
        return None
    idx = np.array([i * m + j for i in range(n) for j in range(n)]
                   + [i * m + n + j for i in range(n) for j in range(nu)])
    return np.asarray(full[np.ix_(idx, idx)])


def _root_rate(Aq: Array, Bq: Array, q: int) -> tuple[Array, Array]:
    """A model at ``dt`` whose ``q``-step (input held) is ``(Aq, Bq)``: the principal ``q``-th
    root of each pole (a negative real pole becomes the root of its magnitude)."""
    if q == 1:
        return Aq, Bq
    lam, V = np.linalg.eig(Aq)
    if np.linalg.cond(V) > 1e8:
        raise np.linalg.LinAlgError("N4SID poles are not diagonalisable")
    neg = (np.abs(lam.imag) <= 1e-12 * np.abs(lam)) & (lam.real < 0)
    mu = np.where(neg, np.abs(lam) ** (1.0 / q), lam.astype(complex) ** (1.0 / q))
    muq = mu ** q
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(np.abs(mu - 1.0) < 1e-12, float(q), (1.0 - muq) / (1.0 - mu))
    Vi = np.linalg.inv(V)
    A = (V * mu) @ Vi
    G = (V * g) @ Vi
    B = np.linalg.solve(G, Bq.astype(complex))
    return np.ascontiguousarray(A.real), np.ascontiguousarray(B.real)


# ---------------------------------------------------------------------------------------------
# Records


@dataclass(frozen=True)
class OrderRecord:
    """One order tried by :meth:`LinearReference.fit`.

    Attributes:
        order: state dimension n.
        est_fit_percent: estimation fit per output [%] (fitted initial states).
        sel_fit_percent: selection fit per output [%] (initial states estimated, parameters
            fixed); ``-inf`` when the model could not be simulated there.
        sel_rmse: selection RMSE per output [output units].
        seconds: wall time of this order (start, refinement, selection) [s].
        start: how the refinement was started (``n4sid``, ``n4sid (decimated by q)``,
            ``previous order + stable mode``) and why a fallback was used.
        nfev: residual evaluations of the refinement.
        model: the refined model.
    """

    order: int
    est_fit_percent: tuple[float, ...]
    sel_fit_percent: tuple[float, ...]
    sel_rmse: tuple[float, ...]
    seconds: float
    start: str
    nfev: int
    model: StateSpace = field(repr=False)

    @property
    def sel_mean_fit(self) -> float:
        """Mean selection fit over outputs [%] (``-inf`` when any is not finite)."""
        v = float(np.mean(self.sel_fit_percent))
        return v if math.isfinite(v) else -math.inf

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (continuous-time poles as ``[re, im]`` pairs, 1/s)."""
        return {"order": self.order, "est_fit_percent": list(self.est_fit_percent),
                "sel_fit_percent": list(self.sel_fit_percent),
                "sel_rmse": list(self.sel_rmse), "seconds": self.seconds,
                "start": self.start, "nfev": self.nfev,
                "poles_s": [[float(p.real), float(p.imag)] for p in self.model.poles_s()]}


# ---------------------------------------------------------------------------------------------
# The reference


class LinearReference:
    """Best black-box LTI model of the data, order chosen on the selection segments.

    Args:
        max_order: highest state dimension tried (orders ``1..max_order``).
        feedthrough: estimate ``D`` (else ``D = 0``).
        init_window: > 0: every simulation starts from the state its first ``init_window``
            samples give, in the fit (an integrating output cannot hide a drift behind a
            free initial state), the selection and :meth:`predict` alike (as
            ``OEFit(init_window=...)``); 0: free initial states in the fit, the
            ``OEFit.estimate_x0`` window rule elsewhere.
        max_nfev: most residual evaluations of each order's refinement.
        seed: seed of the random direction of the mode that raises the order.

    Fitted attributes: ``order_``, ``A_``, ``B_``, ``C_``, ``D_`` (discrete time at ``dt_``
    [s]), ``orders_`` (list of :class:`OrderRecord`), ``x0_`` (per estimation segment, (nx,)),
    ``sel_fit_percent_`` and ``sel_rmse_`` (per output, chosen order), ``weights_`` (ny,),
    ``n_estimated_`` (identifiable parameters ``n (nu + ny)`` [+ ``ny nu``] plus the estimation
    initial states, as ``OEFit.n_estimated_``), ``seconds_`` (whole fit) [s], ``model_`` (the
    chosen :class:`StateSpace`), ``notes_`` (orders that could not be fitted, why).
    """

    def __init__(self, max_order: int = 6, feedthrough: bool = False, init_window: int = 0,
                 max_nfev: int = 200, seed: int = 0) -> None:
        for name, val, low in (("max_order", max_order, 1), ("init_window", init_window, 0),
                               ("max_nfev", max_nfev, 1)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < low:
                raise FitError(f"LinearReference: {name}: expected an integer >= {low}, "
                               f"got {val!r}")
        self.max_order = int(max_order)
        self.feedthrough = bool(feedthrough)
        self.init_window = int(init_window)
        self.max_nfev = int(max_nfev)
        self.seed = int(seed)

    # -- public -------------------------------------------------------------------------------

    def fit(self, est: Sequence[Segment], sel: Sequence[Segment]) -> LinearReference:
        """Fit orders ``1..max_order`` on ``est`` and keep the one chosen on ``sel``.

        Raises:
            DataError: no segment, a segment that is not a Segment, names differing from the
                first estimation segment's, non-finite samples (naming segment and field).
            FitError: no order could be fitted.
        """
        t_all = time.perf_counter()
        est = list(est)
        sel = list(sel)
        _check_segments(est, sel)
        self.dt_ = float(est[0].dt)
        self.input_names_ = est[0].input_names
        self.output_names_ = est[0].output_names
        self.nu_ = len(self.input_names_)
        self.ny_ = len(self.output_names_)
        w = np.std(np.vstack([s.y for s in est]), axis=0)
        self.weights_ = np.where(w > 0, w, 1.0)
        self._rng = np.random.default_rng(self.seed)
        n4 = _N4SID(est, self.dt_, self.max_order, self.ny_)
        self.orders_: list[OrderRecord] = []
        prev: tuple[StateSpace, float] | None = None
        fits: dict[int, tuple[StateSpace, list[Array]]] = {}
        self.notes_: list[str] = []
        # every order's subspace start refined and scored at once, on both cores; what then
        # depends on the previous order (the fallback start, the break) in order, below
        first = self._subspace_orders(n4, est, sel)
        for n in range(1, self.max_order + 1):
            t0 = time.perf_counter()
            tried: list[tuple[float, StateSpace, list[Array], int, str]] = []
            why = []
            got, spent = first[n]
            scores: _Scores | None = None
            if isinstance(got, str):
                why.append(f"n4sid start failed: {got}")
            else:
                tried.append(got[0])
                scores = got[1]
            if not tried or (prev is not None and tried[0][0] > prev[1] * (1 + 1e-9)):
                if tried:
                    why.append("the n4sid start ended worse than the previous order")
                label = ("previous order + stable mode" if prev else "stable mode") + (
                    f" ({'; '.join(why)})" if why else "")
                try:
                    tried.append(self._refine(self._augment(prev[0] if prev else None, est),
                                              est, label))
                except _FAILURES as exc:
                    why.append(f"{label} failed: {exc}")
            if not tried:
                self.notes_.append(f"order {n}: not fitted ({'; '.join(why)}); higher orders "
                                   f"not tried")
                break
            k = min(range(len(tried)), key=lambda i: tried[i][0])
            cost, model, x0s, nfev, label = tried[k]
            fits[n] = (model, x0s)
            prev = (model, cost)
            if k > 0 or scores is None:
                scores = self._scores(model, est, x0s, sel)
            est_fit, sel_fit, sel_rmse = scores
            self.orders_.append(OrderRecord(
                order=n, est_fit_percent=est_fit, sel_fit_percent=sel_fit,
                sel_rmse=sel_rmse, seconds=spent + time.perf_counter() - t0, start=label,
                nfev=nfev, model=model))
        best = max((r.sel_mean_fit for r in self.orders_), default=-math.inf)
        if not math.isfinite(best):
            raise FitError(f"LinearReference: no order 1..{self.max_order} could be fitted and "
                           f"simulated on the selection segments {[s.name for s in sel]} "
                           f"({'; '.join(self.notes_) or 'every simulation overflowed'})")
        chosen = next(r for r in self.orders_ if r.sel_mean_fit >= best - SELECT_TOL)
        model, x0s = fits[chosen.order]
        self.order_ = chosen.order
        self.model_ = model
        self.A_, self.B_, self.C_, self.D_ = model.A, model.B, model.C, model.D
        self.x0_ = x0s
        self.sel_fit_percent_ = chosen.sel_fit_percent
        self.sel_rmse_ = chosen.sel_rmse
        self.n_estimated_ = self._n_params(chosen.order) + (
            0 if self.init_window > 0 else len(est) * chosen.order)
        self.seconds_ = time.perf_counter() - t_all
        return self

    def _scores(self, model: StateSpace, est: Sequence[Segment], x0s: Sequence[Array],
                sel: Sequence[Segment]) -> _Scores:
        """Estimation fit (from the fitted initial states), selection fit and RMSE."""
        est_fit, _ = self._score(model, est, x0s)
        sel_fit, sel_rmse = self._score(model, sel)
        return est_fit, sel_fit, sel_rmse

    def _subspace_orders(self, n4: _N4SID, est: Sequence[Segment], sel: Sequence[Segment]
                         ) -> dict[int, tuple[tuple[_Refined, _Scores] | str, float]]:
        """Each order's subspace start refined and scored, ``order -> (((cost, model, x0s,
        nfev, label), scores) or why it failed, seconds)``; the orders are independent and
        shared between the cores (:func:`dvt_identify.parallel.fork_map`), the largest first
        (the cost of an iteration grows with the square of the parameters)."""
        def one(n: int) -> tuple[tuple[_Refined, _Scores] | str, float]:
            t0 = time.perf_counter()
            try:
                r = self._refine(n4.start(n, self.feedthrough), est, n4.label)
            except _FAILURES as exc:
                return str(exc), time.perf_counter() - t0
            return (r, self._scores(r[1], est, r[2], sel)), time.perf_counter() - t0

        def group(orders: list[int]) -> list[tuple[tuple[_Refined, _Scores] | str, float]]:
            return [one(n) for n in orders]
        work = sorted(range(1, self.max_order + 1), key=self._n_params, reverse=True)
        groups: list[list[int]] = [[] for _ in range(min(workers(), len(work)))]
        load = [0.0] * len(groups)
        for n in work:  # largest first onto the least loaded worker
            g = int(np.argmin(load))
            groups[g].append(n)
            load[g] += float(self._n_params(n) + n) ** 2
        done = fork_map(group, groups)
        return {n: r for orders, res in zip(groups, done, strict=True)
                for n, r in zip(orders, res, strict=True)}

    def simulate(self, seg: Segment, x0: Array) -> Array:
        """Simulated outputs of ``seg`` from initial state ``x0`` (nx,), shape (N, ny).

        Raises:
            DataError: ``seg`` does not match the fitted names.
            FitError: not fitted, ``x0`` of the wrong shape, no equivalent at the segment's
                rate, or the simulation overflows (naming the segment).
        """
        m = self._fitted()
        self._check_seg(seg)
        x = np.asarray(x0, dtype=float).ravel()
        if x.shape != (m.nx,):
            raise FitError(f"{seg.name}: x0: expected shape ({m.nx},), got {np.shape(x0)}")
        y = self._sim(m, seg, x)
        if y is None:
            raise FitError(f"{seg.name}: the linear reference (order {m.nx}) overflowed "
                           f"when simulated")
        return y

    def estimate_x0(self, seg: Segment, n_init: int | None = None) -> Array:
        """Initial state of ``seg`` (nx,) with the parameters fixed: exact weighted least
        squares on the first ``n_init`` samples (``n_init`` > 0; ``None``: ``init_window``) or
        on the ``OEFit`` window (``10 / min|Re(s)|`` seconds, at least 200 samples, all of it
        for an integrator)."""
        m = self._fitted()
        self._check_seg(seg)
        if n_init is None:
            n_init = self.init_window
        if isinstance(n_init, bool) or not isinstance(n_init, (int, np.integer)) or n_init < 0:
            raise FitError(f"{seg.name}: n_init: expected an integer >= 0, got {n_init!r}")
        return self._x0(m, seg, int(n_init))

    def predict(self, seg: Segment, n_init: int | None = None) -> Array:
        """Simulated outputs (N, ny) with the initial state from :meth:`estimate_x0`."""
        return self.simulate(seg, self.estimate_x0(seg, n_init))

    # -- internals ----------------------------------------------------------------------------

    def _fitted(self) -> StateSpace:
        if not hasattr(self, "model_"):
            raise FitError("LinearReference: not fitted (call fit first)")
        return self.model_

    def _check_seg(self, seg: Segment) -> None:
        if not isinstance(seg, Segment):
            raise DataError(f"LinearReference: expected a Segment, got {type(seg).__name__}")
        _check_names(seg, self.input_names_, self.output_names_)
        _check_finite(seg)

    def _n_params(self, n: int) -> int:
        return n * (self.nu_ + self.ny_) + (self.ny_ * self.nu_ if self.feedthrough else 0)

    def _sim(self, m: StateSpace, seg: Segment, x0: Array) -> Array | None:
        """Simulated outputs, or None on overflow (FitError: no equivalent at the rate)."""
        A, B = m.at(seg.dt, seg.name)
        y = np.empty((seg.n, m.C.shape[0]))
        ok = _sim(A, B, m.C, m.D, np.ascontiguousarray(seg.u), np.ascontiguousarray(x0), y)
        return y if ok else None

    def _x0(self, m: StateSpace, seg: Segment, n_init: int) -> Array:
        A, B = m.at(seg.dt, seg.name)
        n = m.nx
        if n_init > 0:
            nw = min(seg.n, n_init)
        else:
            re = np.abs(m.poles_s().real)
            re = re[np.isfinite(re)]
            slow = float(re.min()) if re.size else 0.0
            nw = seg.n
            if slow > 0:
                nw = int(min(seg.n, max(X0_MIN_SAMPLES, math.ceil(10.0 / (slow * seg.dt)))))
        u = np.ascontiguousarray(seg.u[:nw])
        ny = m.C.shape[0]
        forced = np.empty((nw, ny))
        free = np.empty((nw, ny, n))
        ok = _sim(A, B, m.C, m.D, u, np.zeros(n), forced)
        z = np.zeros_like(u)
        for i in range(n):
            yi = np.empty((nw, ny))
            ok = ok and _sim(A, B, m.C, m.D, z, np.eye(n)[i], yi)
            free[:, :, i] = yi
        if not ok:
            return np.zeros(n)
        w = self.weights_
        O = (free / w[None, :, None]).reshape(nw * ny, n)
        r = ((seg.y[:nw] - forced) / w).ravel()
        return np.asarray(np.linalg.lstsq(O, r, rcond=None)[0], dtype=float)

    def _score(self, m: StateSpace, segs: Sequence[Segment], x0s: Sequence[Array] | None = None
               ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Fit [%] and RMSE per output of ``m`` on ``segs`` pooled, from the given initial
        states or ones estimated with the ``init_window`` rule; -inf / inf when it cannot be
        simulated."""
        try:
            ys = [self._sim(m, s, self._x0(m, s, self.init_window) if x0s is None else x0s[i])
                  for i, s in enumerate(segs)]
        except FitError:
            ys = [None]
        if any(y is None for y in ys):
            return ((-math.inf,) * self.ny_, (math.inf,) * self.ny_)
        f = figures([s.y for s in segs], [y for y in ys if y is not None],
                    self._n_params(m.nx), self.output_names_)
        return f.fit_percent, f.rmse

    def _augment(self, prev: StateSpace | None, est: Sequence[Segment]) -> StateSpace:
        """``prev`` (None: the zero model) plus one small stable real mode at the geometric
        mean of the slowest (record) and fastest (Nyquist) rates."""
        nu, ny, dt = self.nu_, self.ny_, self.dt_
        T = max(s.n for s in est) * dt
        p = math.exp(-dt * math.sqrt(math.pi / (dt * T)))
        su = np.std(np.vstack([s.u for s in est]), axis=0)
        su = np.where(su > 0, su, 1.0)
        b = self._rng.standard_normal(nu)
        c = self._rng.standard_normal(ny)
        b *= (1.0 - p) / np.linalg.norm(b) / su
        c *= MODE_GAIN * self.weights_ / np.linalg.norm(c)
        if prev is None:
            return StateSpace(np.array([[p]]), b[None, :], c[:, None], np.zeros((ny, nu)), dt)
        n = prev.nx
        A = np.zeros((n + 1, n + 1))
        A[:n, :n] = prev.A
        A[n, n] = p
        return StateSpace(A, np.vstack([prev.B, b[None, :]]), np.hstack([prev.C, c[:, None]]),
                          prev.D.copy(), dt)

    def _refine(self, start: StateSpace, est: Sequence[Segment], label: str
                ) -> tuple[float, StateSpace, list[Array], int, str]:
        """Output-error refinement from ``start``: (cost, model, x0 per segment, nfev, label)."""
        n, nu, ny = start.nx, self.nu_, self.ny_
        if not self.feedthrough:
            start = StateSpace(start.A, start.B, start.C, np.zeros((ny, nu)), start.dt)
        start = self._stabilise(start, any(not math.isclose(s.dt, self.dt_, rel_tol=1e-9)
                                           for s in est))
        x0s = [self._x0(start, s, 0) for s in est]
        start, x0s = _whiten(start, est, x0s)
        prob = _OEProblem(est, self.weights_, n, nu, ny, self.feedthrough, self.dt_,
                          self.init_window)
        theta0 = prob.pack(start, x0s)
        if prob.residual(theta0)[0] == PENALTY:
            raise FitError(f"order {n}: the start cannot be simulated")
        small = _Compressed(prob)
        try:
            res = least_squares(small.residual, theta0, jac=small.jacobian, method="lm",
                                x_scale="jac", max_nfev=self.max_nfev, ftol=FTOL)
            stop = "converged" if res.status > 0 else f"max_nfev {self.max_nfev} reached"
        except _StalledError:
            stop = (f"stalled (fit gain < {STALL_POINTS} points over {STALL_ITERATIONS} "
                    f"iterations)")
        if prob.best is None:
            raise FitError(f"order {n}: no residual was evaluated")
        cost, th = prob.best
        model, x0s = prob.unpack(th)
        return cost, model, x0s, prob.nfev, f"{label}; {stop}"

    def _stabilise(self, m: StateSpace, positive: bool) -> StateSpace:
        """Poles outside the unit circle moved onto it, and with ``positive`` (estimation
        segments at another rate need a continuous-time equivalent) negative real poles
        mirrored to positive ones: the start of the refinement."""
        lam, V = np.linalg.eig(m.A)
        neg = (lam.imag == 0) & (lam.real <= 0) if positive else np.zeros(lam.shape, bool)
        if (np.all(np.abs(lam) <= 1.0) and not np.any(neg)) or np.linalg.cond(V) > 1e8:
            return m
        lam = np.where(np.abs(lam) > 1.0, lam / np.abs(lam), lam)
        lam = np.where(neg, np.maximum(np.abs(lam), 1e-3), lam)
        A = ((V * lam) @ np.linalg.inv(V)).real
        return StateSpace(np.ascontiguousarray(A), m.B, m.C, m.D, m.dt)


def _whiten(m: StateSpace, est: Sequence[Segment], x0s: list[Array]
            ) -> tuple[StateSpace, list[Array]]:
    """The similar model whose simulated states have unit covariance over ``est``."""
    n = m.nx
    xs = []
    for s, x0 in zip(est, x0s, strict=True):
        A, B = m.at(s.dt, s.name)
        ext = StateSpace(A, B, np.eye(n), np.zeros((n, B.shape[1])), s.dt)
        y = np.empty((s.n, n))
        if not _sim(ext.A, ext.B, ext.C, ext.D, np.ascontiguousarray(s.u), x0, y):
            return m, x0s
        xs.append(y)
    X = np.vstack(xs)
    cov = (X.T @ X) / X.shape[0]
    if not np.all(np.isfinite(cov)):
        return m, x0s
    cov += 1e-12 * max(float(np.trace(cov)), 1e-300) * np.eye(n)
    try:
        T = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return m, x0s
    Ti = np.linalg.inv(T)
    return (StateSpace(Ti @ m.A @ T, Ti @ m.B, m.C @ T, m.D, m.dt),
            [Ti @ x for x in x0s])


_FAILURES = (np.linalg.LinAlgError, ValueError, FitError)
_Refined = tuple[float, "StateSpace", list[Array], int, str]
"""A refinement: cost, model, initial states, evaluations, how it was started."""
_Scores = tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]
"""Estimation fit, selection fit and selection RMSE per output."""
"""What a failed start or refinement of one order raises."""


class _StalledError(Exception):
    """The refinement stopped paying (see :meth:`_OEProblem.jacobian`)."""


class _OEProblem:
    """Weighted output-error residual ``(yhat - y) / w`` over segments and its Jacobian."""

    def __init__(self, segs: Sequence[Segment], w: Array, n: int, nu: int, ny: int,
                 feed: bool, dt: float, window: int = 0) -> None:
        self.segs = list(segs)
        self.w = w
        self.n, self.nu, self.ny, self.feed, self.dt = n, nu, ny, feed, dt
        self.window = int(window)
        self.nab = n * n + n * nu
        self.p_dyn = self.nab + ny * n + (ny * nu if feed else 0)
        # with a window, every initial state is the one the window gives (no unknowns)
        self.p = self.p_dyn + (0 if self.window > 0 else n * len(self.segs))
        self.rows = np.cumsum([0] + [s.n * ny for s in self.segs])
        self.u = [np.ascontiguousarray(s.u) for s in self.segs]
        self.sst = sum(float(np.sum(((s.y - s.y.mean(axis=0)) / w) ** 2)) for s in self.segs)
        self.nfev = 0
        self.best: tuple[float, Array] | None = None
        self.history: list[float] = []

    def fit_points(self, cost: float) -> float:
        """Pooled weighted fit [%] of a cost ``0.5 ||r||^2``."""
        return 100.0 * (1.0 - math.sqrt(2.0 * cost / self.sst)) if self.sst > 0 else 0.0

    def pack(self, m: StateSpace, x0s: Sequence[Array]) -> Array:
        parts = [m.A.ravel(), m.B.ravel(), m.C.ravel()]
        if self.feed:
            parts.append(m.D.ravel())
        if self.window > 0:
            return np.concatenate(parts)
        return np.concatenate(parts + [np.asarray(x, float) for x in x0s])

    def window_x0(self, m: StateSpace, k: int, A: Array, B: Array) -> Array:
        """The initial state of segment ``k`` that best reproduces its first ``window``
        samples (weighted least squares; the model is linear in it)."""
        s = self.segs[k]
        n, ny = self.n, self.ny
        nw = min(s.n, self.window)
        u = np.ascontiguousarray(self.u[k][:nw])
        forced = np.empty((nw, ny))
        if not _sim(A, B, m.C, m.D, u, np.zeros(n), forced):
            return np.zeros(n)
        O = np.empty((nw, ny, n))
        z = np.zeros_like(u)
        for i in range(n):
            yi = np.empty((nw, ny))
            if not _sim(A, B, m.C, m.D, z, np.eye(n)[i], yi):
                return np.zeros(n)
            O[:, :, i] = yi
        Ow = (O / self.w[None, :, None]).reshape(nw * ny, n)
        r = ((s.y[:nw] - forced) / self.w).ravel()
        return np.asarray(np.linalg.lstsq(Ow, r, rcond=1e-10)[0], dtype=float)

    def unpack(self, th: Array) -> tuple[StateSpace, list[Array]]:
        n, nu, ny = self.n, self.nu, self.ny
        i = 0
        A = th[i:i + n * n].reshape(n, n)
        i += n * n
        B = th[i:i + n * nu].reshape(n, nu)
        i += n * nu
        C = th[i:i + ny * n].reshape(ny, n)
        i += ny * n
        D = th[i:i + ny * nu].reshape(ny, nu) if self.feed else np.zeros((ny, nu))
        m = StateSpace(A.copy(), B.copy(), C.copy(), D.copy(), self.dt)
        if self.window > 0:
            x0s = []
            for k, sg in enumerate(self.segs):
                try:
                    Ak, Bk = m.at(sg.dt, sg.name)
                except FitError:
                    x0s.append(np.zeros(n))
                    continue
                x0s.append(self.window_x0(m, k, Ak, Bk))
            return m, x0s
        x0s = [th[self.p_dyn + k * n: self.p_dyn + (k + 1) * n].copy()
               for k in range(len(self.segs))]
        return m, x0s

    def residual(self, th: Array) -> Array:
        self.nfev += 1
        m, x0s = self.unpack(th)
        r = np.empty(int(self.rows[-1]))
        for k, s in enumerate(self.segs):
            try:
                A, B = m.at(s.dt, s.name)
            except FitError:
                return np.full(r.size, PENALTY)
            y = np.empty((s.n, self.ny))
            if not _sim(A, B, m.C, m.D, self.u[k], x0s[k], y):
                return np.full(r.size, PENALTY)
            r[self.rows[k]:self.rows[k + 1]] = ((y - s.y) / self.w).ravel()
        cost = 0.5 * float(np.sum(r * r))
        if self.best is None or cost < self.best[0]:
            self.best = (cost, th.copy())
        return r

    def jacobian(self, th: Array) -> Array:
        """The Jacobian (called once per iteration); raises :class:`_StalledError` when the best
        fit gained less than :data:`STALL_POINTS` over the last :data:`STALL_ITERATIONS`."""
        self.stall_check()
        return self.jacobian_at(th)

    def stall_check(self) -> None:
        """Note the best cost of this iteration; raise :class:`_StalledError` when it gained
        less than :data:`STALL_POINTS` over the last :data:`STALL_ITERATIONS`."""
        if self.best is not None:
            self.history.append(self.best[0])
            h = self.history
            if (len(h) > STALL_ITERATIONS and self.fit_points(h[-1])
                    - self.fit_points(h[-1 - STALL_ITERATIONS]) < STALL_POINTS):
                raise _StalledError

    def jacobian_at(self, th: Array) -> Array:
        """The Jacobian (N ny, p) of :meth:`residual` at ``th``."""
        m, x0s = self.unpack(th)
        n, ny = self.n, self.ny
        J = np.zeros((int(self.rows[-1]), self.p))
        for k, s in enumerate(self.segs):
            ratio = s.dt / self.dt
            T = None
            try:
                A, B = m.at(s.dt, s.name)
            except FitError:
                return J
            if not math.isclose(ratio, 1.0, rel_tol=1e-9):
                T = _rate_jacobian(m.A, m.B, ratio)
                if T is None:
                    return J
            Jk = np.zeros((s.n * ny, self.p_dyn + n))
            y = np.empty((s.n, ny))
            if not _sim_jac(A, B, m.C, m.D, self.u[k], x0s[k], self.feed, y, Jk):
                return np.zeros_like(J)
            if T is not None:
                Jk[:, :self.nab] = Jk[:, :self.nab] @ T
            Jk = (Jk.reshape(s.n, ny, -1) / self.w[None, :, None]).reshape(s.n * ny, -1)
            r0, r1 = self.rows[k], self.rows[k + 1]
            if self.window > 0:
                # x0 = argmin over the window: dx0/dtheta = -O^+ dyhat_window/dtheta (O the
                # window's initial-state sensitivity; Gauss-Newton: exact at a zero window
                # residual)
                nw = min(s.n, self.window) * ny
                O = Jk[:nw, self.p_dyn:]
                dx0 = -np.linalg.lstsq(O, Jk[:nw, :self.p_dyn], rcond=1e-10)[0]
                J[r0:r1, :] = Jk[:, :self.p_dyn] + Jk[:, self.p_dyn:] @ dx0
                continue
            J[r0:r1, :self.p_dyn] = Jk[:, :self.p_dyn]
            J[r0:r1, self.p_dyn + k * n: self.p_dyn + (k + 1) * n] = Jk[:, self.p_dyn:]
        return J


class _Compressed(Factored):
    """The refinement's problem handed to MINPACK by its triangular factor
    (:class:`~dvt_identify.streamls.Factored`, one block): Levenberg-Marquardt sees what it
    would see from the full problem (``J^T J``, ``J^T r``, ``|r|`` and the column norms of
    ``J``), while its own pivoted QR, the cost of an iteration on ``N ny`` rows, runs on
    ``p + 1``; the Jacobian is formed at every residual evaluation instead of at every
    accepted one. The Jacobian request also notes the iteration (the stall rule)."""

    def __init__(self, prob: _OEProblem) -> None:
        cols = np.arange(prob.p, dtype=np.int64)
        super().__init__(lambda th: [(prob.jacobian_at(th), prob.residual(th), cols)], prob.p)
        self.prob = prob

    def jacobian(self, z: Array) -> Array:
        self.prob.stall_check()
        return super().jacobian(z)


class _N4SID:
    """Subspace starts on the longest estimation segment at ``dt``, decimated to at most
    :data:`N4SID_SAMPLES` samples (block means of the input).

    The PO-MOESP scheme of the ``nfoursid`` package (Verhaegen and Verdult, *Filtering and
    system identification*, 2007, pp. 329 and 333; past inputs and outputs as instruments),
    computed here with numpy: the same block Hankel matrices, LQ factor, observability
    estimate and least-squares system matrices, with the observability matrix's singular value
    decomposition taken once (economy size) for every order instead of a full one per order,
    and without the package's import of pandas and matplotlib (a second of a process's first
    identification)."""

    def __init__(self, est: Sequence[Segment], dt: float, max_order: int, ny: int) -> None:
        self.dt = dt
        self.error = ""
        self.vh: Array | None = None
        seg = max((s for s in est if math.isclose(s.dt, dt, rel_tol=1e-9)), key=lambda s: s.n)
        self.q = max(1, math.ceil(seg.n / N4SID_SAMPLES))
        self.label = "n4sid" + (f" (decimated by {self.q})" if self.q > 1 else "")
        rows = max(10, math.ceil(2 * max_order / ny))
        m = seg.n // self.q
        if m < 4 * rows:
            self.error = f"{seg.name}: {m} samples are too few for {rows} block rows"
            return
        self.u = seg.u[: m * self.q].reshape(m, self.q, -1).mean(axis=1)
        self.y = np.ascontiguousarray(seg.y[: m * self.q: self.q])
        self.rows = rows
        try:
            self.s, self.vh = _po_moesp(self.u, self.y, rows)
        except (np.linalg.LinAlgError, ValueError) as exc:
            self.error = f"{type(exc).__name__}: {exc}"

    def start(self, n: int, feedthrough: bool) -> StateSpace:
        """The order-``n`` subspace model at ``dt`` (ValueError / LinAlgError on failure)."""
        if self.vh is None:
            raise ValueError(self.error)
        r = self.rows
        # the state sequence from the observability estimate's leading n directions
        x = (np.sqrt(self.s[:n])[:, None] * self.vh[:n])[:, :-1]
        last_y, last_u = self.y[r:].T, self.u[r:].T
        x_and_y = np.concatenate([x[:, 1:], last_y[:, :-1]])
        x_and_u = np.concatenate([x[:, :-1], last_u[:, :-1]])
        abcd = (np.linalg.pinv(x_and_u @ x_and_u.T) @ x_and_u @ x_and_y.T).T
        Aq, Bq = abcd[:n, :n], abcd[:n, n:]
        C, D = abcd[n:, :n], abcd[n:, n:]
        if not all(np.all(np.isfinite(M)) for M in (Aq, Bq, C, D)):
            raise ValueError(f"order {n}: non-finite subspace matrices")
        A, B = _root_rate(np.asarray(Aq, float), np.asarray(Bq, float), self.q)
        return StateSpace(A, B, np.asarray(C, float),
                          np.asarray(D, float) if feedthrough else np.zeros_like(D), self.dt)


def _block_hankel(a: Array, rows: int) -> Array:
    """Block Hankel matrix of ``a`` (N, k) with ``rows`` block rows: column ``j`` holds
    ``a[j], ..., a[j + rows - 1]`` stacked, shape (rows k, N - rows + 1)."""
    n, k = a.shape
    win = np.lib.stride_tricks.sliding_window_view(a, rows, axis=0)  # (N-rows+1, k, rows)
    return np.ascontiguousarray(np.transpose(win, (2, 1, 0)).reshape(rows * k, n - rows + 1))


def _po_moesp(u: Array, y: Array, rows: int) -> tuple[Array, Array]:
    """Singular values and right singular vectors of the PO-MOESP observability estimate
    ``R32 R22^+ [U; Y]`` (``rows`` block rows; ``u`` (N, nu), ``y`` (N, ny))."""
    uh = _block_hankel(u, rows)
    yh = _block_hankel(y, rows)
    z = np.concatenate([uh[:, rows:], uh[:, :-rows], yh[:, :-rows], yh[:, rows:]])
    _, r = np.linalg.qr(z.T, mode="reduced")
    low = r.T
    yr, ur = y.shape[1] * rows, u.shape[1] * rows
    r32 = low[-yr:, ur:-yr]
    r22 = low[ur:-yr, ur:-yr]
    obs = r32 @ np.linalg.pinv(r22) @ np.concatenate([uh, yh])
    _, s, vh = np.linalg.svd(obs, full_matrices=False)
    return s, vh


# ---------------------------------------------------------------------------------------------
# Checks


def _check_names(seg: Segment, inputs: tuple[str, ...], outputs: tuple[str, ...]) -> None:
    if seg.input_names != inputs:
        raise DataError(f"{seg.name}: input_names: expected {list(inputs)}, got "
                        f"{list(seg.input_names)}")
    if seg.output_names != outputs:
        raise DataError(f"{seg.name}: output_names: expected {list(outputs)}, got "
                        f"{list(seg.output_names)}")
    n = seg.t.shape[0]
    if seg.u.shape != (n, len(inputs)) or seg.y.shape != (n, len(outputs)):
        raise DataError(f"{seg.name}: u, y: expected shapes {(n, len(inputs))}, "
                        f"{(n, len(outputs))}, got {seg.u.shape}, {seg.y.shape}")


def _check_finite(seg: Segment) -> None:
    for fname, arr in (("u", seg.u), ("y", seg.y)):
        if not np.all(np.isfinite(arr)):
            k = int(np.argwhere(~np.isfinite(arr))[0][0])
            raise DataError(f"{seg.name}: {fname}: non-finite value at sample {k}")
    if not (seg.dt > 0 and math.isfinite(seg.dt)):
        raise DataError(f"{seg.name}: dt: expected a positive sample time, got {seg.dt}")


def _check_segments(est: Sequence[Segment], sel: Sequence[Segment]) -> None:
    for label, segs in (("est", est), ("sel", sel)):
        if not segs:
            raise DataError(f"LinearReference.fit: {label}: expected at least one segment, "
                            f"got none")
        for s in segs:
            if not isinstance(s, Segment):
                raise DataError(f"LinearReference.fit: {label}: expected Segment items, got "
                                f"{type(s).__name__}")
    first = est[0]
    if not first.input_names or not first.output_names:
        raise DataError(f"{first.name}: expected at least one input and one output, got "
                        f"inputs {list(first.input_names)}, outputs {list(first.output_names)}")
    for s in (*est, *sel):
        _check_names(s, first.input_names, first.output_names)
        _check_finite(s)
        if s.n < 2:
            raise DataError(f"{s.name}: too little data: {s.n} samples")
