"""Linear two-DOF model ``omega' = A omega + B u`` with exact zero-order-hold stepping.

Used when the model node is given identified ``A`` and ``B`` directly (the thesis's free
2x2 structure). Inputs ``u = [i_motor [A], T_cap1, T_cap2, T_cap3 [N m]]``: motor current and
each band's engaged torque profile (the thesis's brake-torque profile, unsigned); a ``B`` with
2 columns uses ``[i_motor, T_cap1]``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm

from dvt_model.errors import ModelError

Array = NDArray[np.float64]


def check_matrix(value: ArrayLike, name: str, shape: tuple[int, ...]) -> Array:
    """Return ``value`` as a finite float array of exactly ``shape`` or raise ModelError."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ModelError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{name}: contains non-finite values: {arr.tolist()}")
    return arr


class LinearModel:
    """``omega' = A omega + B u``.

    Args:
        A: state matrix [1/s], shape (2, 2).
        B: input matrix, shape (2, 2) (inputs motor current, band-1 torque) or (2, 4).
    """

    def __init__(self, A: ArrayLike, B: ArrayLike) -> None:
        self.A = check_matrix(A, "A", (2, 2))
        b = np.asarray(B, dtype=float)
        if b.ndim != 2 or b.shape[0] != 2 or b.shape[1] not in (2, 4):
            raise ModelError(f"B: expected shape (2, 2) or (2, 4), got {b.shape}")
        self.B = check_matrix(b, "B", b.shape)
        self._cache: dict[float, tuple[Array, Array]] = {}
        self._last: tuple[float, tuple[Array, Array]] | None = None  # (dt, its discretisation)

    @property
    def n_inputs(self) -> int:
        return int(self.B.shape[1])

    def discretise(self, dt: float) -> tuple[Array, Array]:
        """Exact ZOH ``(Phi (2, 2), Gamma (2, m))`` for step ``dt`` [s] (cached)."""
        last = self._last
        if last is not None and last[0] == dt:  # the steady rate: skip the rounding and lookup
            return last[1]
        key = round(dt, 12)
        hit = self._cache.get(key)
        if hit is not None:
            self._last = (dt, hit)
            return hit
        m = self.n_inputs
        big = np.zeros((2 + m, 2 + m))
        big[:2, :2] = self.A
        big[:2, 2:] = self.B
        e = expm(big * dt)
        out = (e[:2, :2], e[:2, 2:])
        if len(self._cache) < 64:
            self._cache[key] = out
            self._last = (dt, out)
        return out

    def step(self, omega: Array, dt: float, u: Array) -> Array:
        """Advance ``omega`` (2,) by ``dt`` with ``u`` (4,) held; uses the first B columns."""
        Phi, Gamma = self.discretise(dt)
        return np.asarray(Phi @ omega + Gamma @ u[: self.n_inputs])
