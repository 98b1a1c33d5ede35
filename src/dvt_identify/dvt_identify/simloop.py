"""Compiled step loops of the output-error simulation (numba, ``cache=True``).

Also the compliant-spline load of the ``backlash`` candidate (:func:`spline_load`).

The simulation of a model with state-dependent member forces (dry friction with a stick rule,
Stribeck, windage, direction-dependent viscous friction) cannot be vectorised: each step depends
on the previous one. These kernels run that loop in machine code;
:func:`dvt_identify.simulation.simulate_loop` prepares their arrays (and can run the same source
in the interpreter, ``reference=True``, to check the compilation).

Smooth laws are coded as ``(kind, p0, p1)`` (:data:`STRIBECK`, :data:`WINDAGE`,
:data:`ABS_VISCOUS`); :func:`smooth_value` evaluates one, compiled or from Python. The laws
themselves are :mod:`dvt_model.friction`'s (the one friction law of the suite), compiled here
with ``numba.njit`` unchanged; a member force is minus the resisting force of the law, and a
sliding dry member feels ``-coulomb(s, C, 0, 0)`` (the exact sign).

The rule implemented: the linear part is advanced by its exact ZOH map, every member force is
evaluated at the start of a step and held over it; a sliding member whose speed would cross zero
within a step sticks if the force needed to hold it is within its dry capacity (plus
break-away), else the friction is reversed; a member at rest stays at rest while the holding
force is within the capacity.

Compilation happens on the first call of a process and is cached on disk next to this file
(``__pycache__``), so later processes load machine code in well under a second.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from dvt_model import backlash, friction

Array = NDArray[np.float64]

STRIBECK = 0
"""``g(s) = -stribeck(s, p0, p1, eps=0)`` = ``-p0 exp(-(s/p1)^2) sign(s)`` (``p0 = Fs``,
``p1 = vs > 0``)."""
WINDAGE = 1
"""``g(s) = -windage(s, p0)`` = ``-p0 s |s|`` (``p0 = Cw``)."""
ABS_VISCOUS = 2
"""``g(s) = -abs_viscous(s, p0)`` = ``-p0 |s|`` (``p0 = dFv``)."""
KINDS = (STRIBECK, WINDAGE, ABS_VISCOUS)

_stribeck = njit(cache=True, nogil=True)(friction.stribeck)
_windage = njit(cache=True, nogil=True)(friction.windage)
_abs_viscous = njit(cache=True, nogil=True)(friction.abs_viscous)
_coulomb = njit(cache=True, nogil=True)(friction.coulomb)
_spline_substep = njit(cache=True, nogil=True)(backlash.spline_substep)


@njit(cache=True, nogil=True)
def smooth_value(kind: int, p0: float, p1: float, s: float) -> float:
    """Member force of a coded smooth law at member speed ``s`` [force unit]."""
    if kind == 0:
        if s == 0.0:
            return 0.0
        return -_stribeck(s, p0, p1, 0.0, 2.0)
    if kind == 1:
        return -_windage(s, p0)
    return -_abs_viscous(s, p0)


@njit(cache=True, nogil=True)
def _dot(c: Array, x: Array) -> float:  # pragma: no cover - compiled
    """Member speed ``c . x`` (summed in index order)."""
    s = 0.0
    for j in range(x.shape[0]):
        s += c[j] * x[j]
    return s


@njit(cache=True, nogil=True)
def _member_accel(A: Array, w: Array, extra: Array, x: Array,
                  c: Array) -> float:  # pragma: no cover - compiled
    """Member acceleration ``c . (A x + w + extra)`` without dry friction."""
    ca = 0.0
    for i in range(x.shape[0]):
        acc = 0.0
        for j in range(x.shape[0]):
            acc += A[i, j] * x[j]
        ca += c[i] * (acc + w[i] + extra[i])
    return ca


@njit(cache=True, nogil=True)
def loop_members(A: Array, Ad: Array, w: Array, d: Array, x0: Array,
                 sc: Array, skind: NDArray[np.int64], spar: Array, sgd: Array, sfc: Array,
                 dc: Array, dcap: Array, dbrk: Array, dgdf: Array, dfcv: Array,
                 dcfc: Array) -> Array:  # pragma: no cover - compiled
    """The step loop for any number of states.

    Args:
        A, Ad: continuous ``A`` and its ZOH ``Ad``, shape (nx, nx).
        w: generalised input per sample [state unit/s], shape (N, nx).
        d: ``w @ Gd.T``, shape (N, nx).
        x0: initial state, shape (nx,).
        sc, skind, spar, sgd, sfc: smooth forces: member vectors (ns, nx), law codes (ns,),
            law parameters (ns, 2), ``Gd F c`` (ns, nx), ``F c`` (ns, nx).
        dc, dcap, dbrk, dgdf, dfcv, dcfc: dry members (one per distinct member): vectors
            (nd, nx), capacity per sample (nd, N), break-away (nd,), ``Gd F c`` (nd, nx),
            ``F c`` (nd, nx), ``c . F c`` (nd,).

    Returns:
        States, shape (N, nx).
    """
    n, nx = d.shape
    ns = sc.shape[0]
    nd = dc.shape[0]
    out = np.empty((n, nx))
    x = x0.copy()
    out[0] = x
    xn = np.empty(nx)
    xp = np.empty(nx)
    extra = np.empty(nx)
    rest = np.zeros(nd, dtype=np.bool_)
    for k in range(n - 1):
        # sums in the order of the Python reference loop (bitwise-equal results)
        for i in range(nx):
            acc = 0.0
            for j in range(nx):
                acc += Ad[i, j] * x[j]
            xn[i] = acc + d[k, i]
            extra[i] = 0.0
        for m in range(ns):
            tau = smooth_value(skind[m], spar[m, 0], spar[m, 1], _dot(sc[m], x))
            if tau != 0.0:
                for i in range(nx):
                    xn[i] += sgd[m, i] * tau
                    extra[i] += sfc[m, i] * tau
        for g in range(nd):
            cap = dcap[g, k]
            cfc = dcfc[g]
            s = _dot(dc[g], x)
            if not rest[g] and s != 0.0:
                tau = -_coulomb(s, cap, 0.0, 0.0)
                for i in range(nx):
                    xn[i] += dgdf[g, i] * tau
                sn = _dot(dc[g], xn)
                if (sn > 0.0) != (s > 0.0) or sn == 0.0:
                    # crossed zero: stick if the holding force is within the capacity, else go
                    # on with the friction reversed
                    for i in range(nx):
                        xp[i] = xn[i] - dfcv[g, i] * sn / cfc
                    ca = _member_accel(A, w[k], extra, xp, dc[g])
                    if abs(ca / cfc) <= cap + dbrk[g]:
                        for i in range(nx):
                            xn[i] = xp[i]
                        rest[g] = True
                    else:
                        for i in range(nx):
                            xn[i] -= 2.0 * dgdf[g, i] * tau
                        sn2 = _dot(dc[g], xn)
                        if (sn2 > 0.0) == (s > 0.0) or sn2 == 0.0:
                            for i in range(nx):
                                xn[i] -= dfcv[g, i] * sn2 / cfc
                            rest[g] = True
                continue
            ca = _member_accel(A, w[k], extra, x, dc[g])
            req = -ca / cfc
            if abs(req) <= cap + dbrk[g]:
                for i in range(nx):
                    xn[i] += dgdf[g, i] * req
                sn = _dot(dc[g], xn)
                for i in range(nx):
                    xn[i] -= dfcv[g, i] * sn / cfc
                rest[g] = True
            else:
                tau = -cap if ca > 0.0 else cap
                for i in range(nx):
                    xn[i] += dgdf[g, i] * tau
                rest[g] = False
        for i in range(nx):
            x[i] = xn[i]
            out[k + 1, i] = xn[i]
    return out


@njit(cache=True, nogil=True)
def loop_scalar(a: float, ad: float, w: Array, d: Array, x0: float,
                sc: Array, skind: NDArray[np.int64], spar: Array, sgd: Array,
                has_dry: bool, cap: Array, brk: float, gdf_unit: float, fmap: float,
                extra0: float) -> Array:  # pragma: no cover - compiled
    """The one-state loop in generalised coordinates (all dry members lumped).

    Args:
        a, ad: continuous and ZOH scalar dynamics.
        w, d: generalised input and its ZOH response, shape (N,).
        x0: initial state.
        sc, skind, spar, sgd: smooth forces: member coefficients (ns,), law codes (ns,), law
            parameters (ns, 2), ``Gd F c`` (ns,).
        has_dry: whether there is any dry friction.
        cap: generalised dry capacity per sample, shape (N,).
        brk: generalised break-away.
        gdf_unit, fmap: ZOH response and force map of a unit generalised force.
        extra0: generalised smooth force at rest.

    Returns:
        States, shape (N,).
    """
    n = d.shape[0]
    ns = sc.shape[0]
    out = np.empty(n)
    x = x0
    out[0] = x
    rest = False
    for k in range(n - 1):
        xn = ad * x + d[k]
        extra = 0.0
        for m in range(ns):
            tau = smooth_value(skind[m], spar[m, 0], spar[m, 1], sc[m] * x)
            if tau != 0.0:
                xn += sgd[m] * tau
                extra += tau * sc[m]
        if has_dry:
            c = cap[k]
            if not rest and x != 0.0:
                xn -= gdf_unit * c if x > 0.0 else -gdf_unit * c
                if (xn > 0.0) != (x > 0.0) or xn == 0.0:
                    acc0 = w[k] + fmap * extra0
                    if abs(acc0 / fmap) <= c + brk:
                        xn = 0.0
                        rest = True
                    else:
                        xn += 2.0 * gdf_unit * c if x > 0.0 else -2.0 * gdf_unit * c
                        if (xn > 0.0) == (x > 0.0) or xn == 0.0:
                            xn = 0.0
                            rest = True
            else:
                acc = a * x + w[k] + fmap * extra
                req = -acc / fmap
                if abs(req) <= c + brk:
                    xn = 0.0
                    rest = True
                else:
                    xn = ad * x + d[k] + (gdf_unit * (extra - c) if acc > 0.0
                                          else gdf_unit * (extra + c))
                    rest = False
        out[k + 1] = xn
        x = xn
    return out


@njit(cache=True, nogil=True)
def _spline_load_kernel(w: Array, dt: float, half: float, a: float, b: float, sub: int) -> Array:
    """Load-shaft speed behind a compliant spline with play, driven by the member speed.

    The member speed ``w`` (N,) is linearly interpolated over each sample interval, which is cut
    into ``sub`` sub-steps of :func:`dvt_model.backlash.spline_substep` (the contact law and
    its integration, written once; the model node's ``spline_play`` term steps the same).
    Returns the load speed averaged over the sample interval centred on each sample, shape (N,).
    """
    n = w.shape[0]
    h = dt / sub
    wl = w[0]
    z = 0.0
    acc = np.zeros(n)
    half_sub = sub // 2
    for k in range(n - 1):
        w0 = w[k]
        dw = (w[k + 1] - w0) / sub
        for i in range(sub):
            wl_new, z = _spline_substep(wl, z, w0 + dw * (i + 0.5), h, half, a, b)
            # the sub-step's mean speed belongs to the sample whose interval holds it
            if i < half_sub:
                acc[k] += 0.5 * (wl + wl_new)
            else:
                acc[k + 1] += 0.5 * (wl + wl_new)
            wl = wl_new
    out = np.empty(n)
    if n == 1:
        out[0] = w[0]
        return out
    lo = sub - half_sub  # sub-steps of the second half of an interval
    out[0] = acc[0] / half_sub if half_sub else w[0]
    for k in range(1, n - 1):
        out[k] = acc[k] / sub
    out[n - 1] = acc[n - 1] / lo
    return out


spline_load_py = _spline_load_kernel.py_func
"""The interpreted source of the spline kernel (the reference for the compiled one)."""


def spline_load(w: Array, dt: float, half: float, a: float, b: float, sub: int) -> Array:
    """Load-shaft speed behind a compliant spline with play (compiled kernel), shape (N,)."""
    return np.asarray(_spline_load_kernel(np.ascontiguousarray(w, dtype=np.float64), float(dt),
                                          float(half), float(a), float(b), int(sub)))


@njit(cache=True, nogil=True)
def first_order_lag(col: Array, e: float) -> Array:  # pragma: no cover - compiled
    """The ZOH first-order lag of a held input: ``y[0] = col[0]``,
    ``y[k+1] = e y[k] + (1 - e) col[k]`` (``e = exp(-dt / tau)``), shape of ``col``."""
    n = col.shape[0]
    out = np.empty(n)
    if n == 0:
        return out
    y = col[0]
    out[0] = y
    for k in range(n - 1):
        y = e * y + (1.0 - e) * col[k]
        out[k + 1] = y
    return out


def warm_up() -> None:
    """Compile (or load from the on-disk cache) both kernels now, on a tiny problem; what a
    process pays once before its first simulation with member forces."""
    z2 = np.zeros((2, 2))
    e2 = np.zeros((0, 2))
    e1 = np.zeros(0)
    ek = np.zeros(0, dtype=np.int64)
    loop_members(z2, z2, z2, z2, np.zeros(2), e2, ek, np.zeros((0, 2)), e2, e2, e2,
                 np.zeros((0, 2)), e1, e2, e2, e1)
    loop_scalar(0.0, 1.0, np.zeros(2), np.zeros(2), 0.0, e1, ek, np.zeros((0, 2)), e1,
                False, np.zeros(2), 0.0, 1.0, 1.0, 0.0)
    spline_load(np.zeros(2), 1e-3, 0.0, 1.0, 1.0, 2)
    first_order_lag(np.zeros(2), 0.5)
