"""Large least-squares problems handed to ``scipy.optimize.least_squares`` by their triangular
factor, built block by block: the memory of a fit no longer grows with the recording.

A fit's Jacobian has one row per sample and output (an hour at 200 Hz and 14 unknowns: 160 MB,
and the trust-region solver keeps two more copies of it). Its thin QR factor ``J = Q R`` is
``q x q``. With ``[J, r]`` folded in block by block (a segment, or a stretch of one, at a
time: ``R_new = triangular factor of [R_old; [J_k, r_k]]``, the tall-skinny QR), the problem
handed to the solver is ``[Q^T r, |r - Q Q^T r|]`` with Jacobian ``[R; 0]``: ``q + 1`` rows with
the same ``J^T J``, ``J^T r``, ``|r|`` and column norms as the full problem, so the trust-region
steps, the scaling (``x_scale="jac"``) and the stopping tests are the full problem's (up to
rounding). The factor is taken at every residual evaluation (where the full problem needs the
Jacobian only at accepted points): used only where the dense Jacobian would be large
(:data:`DENSE_BYTES`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import qr

Array = NDArray[np.float64]
Block = tuple[Array, Array, NDArray[np.int64]]
"""Rows of a Jacobian and of the residual: ``J_k`` (m_k, c_k) over the unknowns ``cols_k``
(c_k indices into the q unknowns; the Jacobian is zero in the others) and ``r_k`` (m_k,)."""
Blocks = Callable[[Array], Iterable[Block]]
"""``blocks(z)``: the blocks at ``z``, in the residual's order."""

DENSE_BYTES = 4 * 2**20
"""A dense Jacobian larger than this [bytes] is handed to the solver by its factor."""


def dense_ok(rows: int, cols: int) -> bool:
    """Whether a dense ``rows x cols`` Jacobian stays within :data:`DENSE_BYTES`."""
    return rows * max(cols, 1) * 8 <= DENSE_BYTES


def reduce(block: Block) -> tuple[Array, NDArray[np.int64], float]:
    """A block reduced to its own triangular factor: ``R`` of ``[J_k, r_k]``
    ((c_k + 1, c_k + 1) at most), its columns and ``|r_k|^2``."""
    J, r, cols = block
    r = np.asarray(r, float).reshape(-1)
    local = qr(np.column_stack([J, r]), mode="r", overwrite_a=True,
               check_finite=False)[0][: J.shape[1] + 1]
    return np.asarray(local), np.asarray(cols, dtype=np.int64), float(r @ r)


def fold(blocks: Iterable[Block], q: int) -> tuple[Array, Array, float, float]:
    """The triangular factor of ``[J, r]`` folded block by block: ``R`` (q, q), ``Q^T r``
    (q,), ``|r - Q Q^T r|`` and ``|r|^2``. Each block is first reduced to its own
    ``(c_k + 1)``-row factor (:func:`reduce`; its rows are zero outside its columns), which is
    then folded into the whole one."""
    return fold_reduced((reduce(b) for b in blocks), q)


def fold_reduced(reduced: Iterable[tuple[Array, NDArray[np.int64], float]], q: int
                 ) -> tuple[Array, Array, float, float]:
    """:func:`fold` of blocks already reduced (:func:`reduce`, e.g. in worker processes)."""
    Ra = np.zeros((0, q + 1))
    rr = 0.0
    for local, cols, rr_k in reduced:
        rr += rr_k
        wide = np.zeros((local.shape[0], q + 1))
        wide[:, np.append(cols, q)] = local
        Ra = qr(np.vstack([Ra, wide]), mode="r", overwrite_a=True,
                check_finite=False)[0][: q + 1]
    if Ra.shape[0] < q + 1:  # fewer rows than unknowns: pad (an underdetermined problem)
        Ra = np.vstack([Ra, np.zeros((q + 1 - Ra.shape[0], q + 1))])
    return (np.ascontiguousarray(Ra[:q, :q]), np.array(Ra[:q, q]), abs(float(Ra[q, q])), rr)


def dense(block: Block, q: int) -> tuple[Array, Array]:
    """A block's rows over all ``q`` unknowns (m_k, q) and its residual."""
    J, r, cols = block
    out = np.zeros((J.shape[0], q))
    out[:, cols] = J
    return out, r


def reduced_in_parallel(blocks: Sequence[Callable[[], Block]]
                        ) -> list[tuple[Array, NDArray[np.int64], float]]:
    """Each block computed and reduced (:func:`reduce`) on both cores
    (:func:`dvt_identify.parallel.fork_map`; a block is a segment's simulation with
    sensitivities, its reduction a small QR: only the small factors come back)."""
    from dvt_identify.parallel import fork_map

    return fork_map(lambda make: reduce(make()), list(blocks))


class Factored:
    """The ``fun``/``jac`` pair of ``least_squares`` for a problem given by its blocks
    (module docstring). The Jacobian is that of the last residual evaluation at the same
    point (``least_squares`` asks for it at the last accepted point, whose residual it has).
    ``parallel(z)``, when given, returns the blocks as thunks to make and reduce on both
    cores (:func:`reduced_in_parallel`) instead of ``blocks(z)``.

    Attributes (after a residual evaluation): ``R`` (q, q) and ``rr`` (the full ``|r|^2``).
    """

    def __init__(self, blocks: Blocks, q: int,
                 parallel: Callable[[Array], Sequence[Callable[[], Block]]] | None = None
                 ) -> None:
        self.blocks = blocks
        self.parallel = parallel
        self.q = q
        self._at: Array | None = None
        self.R = np.zeros((q, q))
        self.rr = math.nan

    def residual(self, z: Array) -> Array:
        if self.parallel is not None:  # the blocks made and reduced on both cores
            R, qtr, rho, rr = fold_reduced(reduced_in_parallel(self.parallel(z)), self.q)
        else:
            R, qtr, rho, rr = fold(self.blocks(z), self.q)
        self._at, self.R, self.rr = np.array(z, dtype=float), R, rr
        return np.concatenate([qtr, [rho]])

    def jacobian(self, z: Array) -> Array:
        if self._at is None or not np.array_equal(self._at, z):
            self.residual(z)
        return np.vstack([self.R, np.zeros((1, self.q))])
