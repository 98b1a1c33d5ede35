"""Discrete-time LTI models for the black-box linear reference (:mod:`dvt_identify.reference`):
the numba-compiled simulation and sensitivity kernels, :class:`StateSpace` and its conversion to
another sample time through the continuous-time equivalent (zero-order hold; Fréchet
derivatives of ``expm`` for the Jacobian of that conversion)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.linalg import expm, expm_frechet, logm

from dvt_identify.errors import FitError

Array = NDArray[np.float64]

X_LIMIT = 1e60
"""A simulated state beyond this magnitude counts as overflow (finite penalty)."""



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

