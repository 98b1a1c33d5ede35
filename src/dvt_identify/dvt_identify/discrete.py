"""The exact zero-order-hold discretisation of a linear part and its simulation (a leaf: numpy
and scipy only, so that any module may use it without importing the effects).

:mod:`dvt_identify.simulation` builds its output-error models on these; the residual analysis
(:mod:`dvt_identify.resid`) uses them for the input-noise response.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import signal
from scipy.linalg import expm

Array = NDArray[np.float64]

__all__ = ["simulate_linear", "zoh"]


_ZOH_CACHE: dict[tuple[bytes, float], tuple[Array, Array]] = {}


def zoh(A: Array, dt: float) -> tuple[Array, Array]:
    """Exact ZOH: ``Ad = e^{A dt}``, ``Gd = int_0^dt e^{A s} ds`` (both (nx, nx)); cached."""
    key = (np.ascontiguousarray(A, dtype=float).tobytes(), float(dt))
    hit = _ZOH_CACHE.get(key)
    if hit is not None:
        return hit
    out = _zoh(A, dt)
    if len(_ZOH_CACHE) > 256:
        _ZOH_CACHE.clear()
    _ZOH_CACHE[key] = out
    return out


def _zoh(A: Array, dt: float) -> tuple[Array, Array]:
    nx = A.shape[0]
    M = np.zeros((2 * nx, 2 * nx))
    M[:nx, :nx] = A * dt
    M[:nx, nx:] = np.eye(nx) * dt
    E = expm(M)
    return np.asarray(E[:nx, :nx]), np.asarray(E[:nx, nx:])


def simulate_linear(Ad: Array, d: Array, x0: Array) -> Array:
    """``x[k+1] = Ad x[k] + d[k]``, ``x[0] = x0``; returns x, shape (N, nx).

    Vectorised in modal coordinates with ``lfilter`` (one first-order recursion per eigenvalue);
    a plain loop when ``Ad`` is close to defective.
    """
    n, nx = d.shape
    lam, V = np.linalg.eig(Ad)
    if np.linalg.cond(V) > 1e8:
        x = np.empty((n, nx))
        x[0] = x0
        for k in range(n - 1):
            x[k + 1] = Ad @ x[k] + d[k]
        return x
    real = bool(np.all(np.abs(lam.imag) < 1e-300)) and bool(np.all(np.abs(V.imag) < 1e-300))
    if real:
        lam, V = lam.real, V.real
    Vi = np.linalg.inv(V)
    q = d @ Vi.T
    z0 = Vi @ x0
    kk = np.arange(n)
    z = np.empty((n, nx), dtype=q.dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(nx):
            z[:, i] = signal.lfilter([0.0, 1.0], [1.0, -lam[i]], q[:, i]) + lam[i] ** kk * z0[i]
        x = (z @ V.T).real
    return np.asarray(x, dtype=float)
