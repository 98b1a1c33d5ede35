"""Subspace starts of the black-box linear reference (:mod:`dvt_identify.reference`):
PO-MOESP (the scheme of the ``nfoursid`` package computed with numpy) on the longest estimation
segment, decimated, and brought back to the fitted sample time by the ``q``-th root of its
poles."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from dvt_identify.data import Segment
from dvt_identify.lti import Array, StateSpace

N4SID_SAMPLES = 1500
"""Most samples handed to ``nfoursid`` (the record is decimated to fit)."""


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


