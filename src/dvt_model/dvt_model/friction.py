"""The friction and drag laws, written once (pure; numpy; compilable with numba).

Each law returns the *resisting* force ``F(v)`` [N m, or the member's force unit] at member
speed ``v`` [rad/s]; the generalised force on the member is ``-F(v)``. They work on scalars and
on numpy arrays alike, and ``numba.njit(law)`` compiles them unchanged (the identifier's
simulation kernels do that), so the plant, the identifier and the live model share one
definition. (Each law spells the sign out instead of calling :func:`sign_eps`: a compiled
function cannot call an uncompiled one.)

``eps`` smooths the sign: ``sign_eps(v) = tanh(v / eps)`` for ``eps > 0`` (a stable law for a
fixed-step simulation), the exact ``sign(v)`` for ``eps == 0`` (used with a stick rule).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def sign_eps(v: Any, eps: float) -> Any:
    """``tanh(v / eps)`` for ``eps > 0``, else ``sign(v)`` (0 at v = 0)."""
    if eps > 0.0:
        return np.tanh(v / eps)
    return np.sign(v)


def coulomb(v: Any, fc: float, offset: float, eps: float) -> Any:
    """Dry (Coulomb) friction ``Fc sign_eps(v) + offset``; ``Fc >= 0``."""
    return fc * (np.tanh(v / eps) if eps > 0.0 else np.sign(v)) + offset


def stribeck(v: Any, fs: float, vs: float, eps: float, delta: float = 2.0) -> Any:
    """Stribeck excess ``Fs exp(-|v/vs|^delta) sign_eps(v)``; ``Fs >= 0``, ``vs > 0``."""
    return fs * np.exp(-np.abs(v / vs) ** delta) * (np.tanh(v / eps) if eps > 0.0 else np.sign(v))


def windage(v: Any, cw: float) -> Any:
    """Quadratic drag ``Cw |v| v``; ``Cw >= 0``."""
    return cw * np.abs(v) * v


def viscous(v: Any, b: float) -> Any:
    """Viscous drag ``b v``; ``b >= 0``."""
    return b * v


def abs_viscous(v: Any, dfv: float) -> Any:
    """Direction-dependent part of viscous friction ``dFv |v|`` (``Fv+ = Fv + dFv``)."""
    return dfv * np.abs(v)
