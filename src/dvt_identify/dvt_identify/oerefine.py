"""Output-error refinement of the black-box linear reference (:mod:`dvt_identify.reference`):
the weighted simulation-error residual over all estimation segments and its analytic Jacobian
(:class:`_OEProblem`), handed to the least-squares solver by its triangular factor
(:class:`_Compressed`), with the stall rule that ends a refinement which stopped paying."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from dvt_identify.data import Segment
from dvt_identify.errors import FitError
from dvt_identify.lti import Array, StateSpace, _rate_jacobian, _sim, _sim_jac
from dvt_identify.streamls import Factored

SELECT_TOL = 0.1
"""Points of mean selection fit [%] within which the smallest order wins."""
PENALTY = 1e10
"""Weighted residual of every sample of a simulation that overflowed."""
FTOL = 1e-6
"""Relative cost change that ends a refinement (a fit change of about ``1e-4`` points)."""
STALL_POINTS = SELECT_TOL / 10
"""Fit gain [points] below which a refinement has stalled (an order drifting to a pole at
infinity or a pole-zero cancellation crawls for hundreds of iterations for nothing)..."""
STALL_ITERATIONS = 10
"""... over this many iterations."""


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
    """The refinement's problem handed to the solver by its triangular factor
    (:class:`~dvt_identify.streamls.Factored`, one block): the solver sees what it would see
    from the full problem (``J^T J``, ``J^T r``, ``|r|`` and the column norms of ``J``), while
    its own factorisation, the cost of an iteration on ``N ny`` rows, runs on ``p + 1``; the
    Jacobian is formed at every residual evaluation instead of at every
    accepted one. The Jacobian request also notes the iteration (the stall rule)."""

    def __init__(self, prob: _OEProblem) -> None:
        cols = np.arange(prob.p, dtype=np.int64)
        super().__init__(lambda th: [(prob.jacobian_at(th), prob.residual(th), cols)], prob.p)
        self.prob = prob

    def jacobian(self, z: Array) -> Array:
        self.prob.stall_check()
        return super().jacobian(z)

