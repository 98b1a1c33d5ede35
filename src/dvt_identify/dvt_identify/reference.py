"""The black-box linear reference: the best LTI state-space model of the same data, put beside
every physical model and simulated and scored exactly like it (issue 21 item 1).

:class:`LinearReference` fits, for each order ``n = 1..max_order``, the discrete-time model

    x[k+1] = A x[k] + B u[k],   y[k] = C x[k] (+ D u[k] with ``feedthrough``)

at the sample time ``dt_`` of the first estimation segment, and keeps the smallest order whose
selection fit is within :data:`SELECT_TOL` points of the best.

Each order starts from a subspace fit (N4SID/PO-MOESP, the scheme of the ``nfoursid`` package
computed here with numpy, :class:`dvt_identify.subspace._N4SID`) on the longest estimation
segment at ``dt_``, decimated to at most :data:`~dvt_identify.subspace.N4SID_SAMPLES` samples
and brought back to ``dt_`` by the ``q``-th root of its poles. When that step fails, or the
refined fit is worse on the estimation data than the previous order's, the order starts from
the previous order's optimum augmented by one small stable mode (rising order); ``orders_`` says
which start was kept.

The start is refined by output error: ``scipy.optimize.least_squares`` minimises the simulation
error over all estimation segments (each with its own initial state as unknowns, outputs
weighted by ``1/std(y_j)`` pooled over segments) with an analytic Jacobian from a
numba-compiled sensitivity recursion (:mod:`dvt_identify.lti`), handed to the trust-region
reflective solver by its triangular factor (:class:`dvt_identify.oerefine._Compressed`). The
orders' subspace starts are refined on both cores. ``A``, ``B``, ``C`` (and ``D``) are fully
parametrised.
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

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from dvt_identify.data import Segment
from dvt_identify.errors import DataError, FitError
from dvt_identify.lti import Array, StateSpace, _sim
from dvt_identify.metrics import figures
from dvt_identify.oerefine import (
    FTOL,
    PENALTY,
    SELECT_TOL,
    STALL_ITERATIONS,
    STALL_POINTS,
    _Compressed,
    _OEProblem,
    _StalledError,
    _whiten,
)
from dvt_identify.parallel import fork_map
from dvt_identify.subspace import _N4SID

MODE_GAIN = 0.01
"""Output share (of ``std(y)``) of the small stable mode that raises the order."""
X0_MIN_SAMPLES = 200
"""Fewest samples of the initial-state window (the rule of ``OEFit.estimate_x0``)."""


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

    def refit(self, est: Sequence[Segment]) -> LinearReference:
        """A copy refined on ``est`` from this reference's model (warm start): its order,
        weights and initial-state rule kept, one refinement (the linear counterpart of a fold
        fit, :func:`dvt_identify.stages.fold_fits`; :mod:`dvt_identify.spread`). Its
        ``orders_``, ``sel_fit_percent_`` and ``sel_rmse_`` are empty: nothing is chosen.

        Raises:
            DataError: bad segments (as :meth:`fit`), or names differing from the fitted ones.
            FitError: not fitted, or the refinement failed (naming the segments).
        """
        m = self._fitted()
        est = list(est)
        _check_segments(est, est)
        for s in est:
            _check_names(s, self.input_names_, self.output_names_)
        t0 = time.perf_counter()
        out = copy.copy(self)
        out._rng = np.random.default_rng(self.seed)
        try:
            _, model, x0s, _, _ = out._refine(m, est, "warm from the fitted reference")
        except _FAILURES as exc:
            raise FitError(f"LinearReference.refit on {[s.name for s in est]}: {exc}") from exc
        out.model_ = model
        out.A_, out.B_, out.C_, out.D_ = model.A, model.B, model.C, model.D
        out.x0_ = x0s
        out.orders_ = []
        out.sel_fit_percent_, out.sel_rmse_ = (), ()  # nothing was chosen on a selection
        out.notes_ = [f"refined on {', '.join(s.name for s in est)} from the order-"
                      f"{self.order_} reference"]
        out.n_estimated_ = self._n_params(self.order_) + (
            0 if self.init_window > 0 else len(est) * self.order_)
        out.seconds_ = time.perf_counter() - t0
        return out

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
        to whichever process is free (the cost of an iteration grows with the square of the
        parameters)."""
        def one(n: int) -> tuple[tuple[_Refined, _Scores] | str, float]:
            t0 = time.perf_counter()
            try:
                r = self._refine(n4.start(n, self.feedthrough), est, n4.label)
            except _FAILURES as exc:
                return str(exc), time.perf_counter() - t0
            return (r, self._scores(r[1], est, r[2], sel)), time.perf_counter() - t0

        orders = list(range(1, self.max_order + 1))
        done = fork_map(one, orders,
                        costs=[float(self._n_params(n) + n) ** 2 for n in orders])
        return dict(zip(orders, done, strict=True))

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
            # TRF, not MINPACK's Levenberg-Marquardt: on this rank-deficient problem scipy
            # 1.17.1's "lm" proposed a first step that depended on leftover heap memory (the
            # same inputs replayed after filling freed blocks with 1.0: 13 of 24 runs stepped
            # elsewhere), so identifications differed from process to process
            res = least_squares(small.residual, theta0, jac=small.jacobian, method="trf",
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


_FAILURES = (np.linalg.LinAlgError, ValueError, FitError)
_Refined = tuple[float, "StateSpace", list[Array], int, str]
"""A refinement: cost, model, initial states, evaluations, how it was started."""
_Scores = tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]
"""Estimation fit, selection fit and selection RMSE per output."""
"""What a failed start or refinement of one order raises."""


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
