"""Compiled step loops of the output-error simulation (numba, ``cache=True``).

Also the compliant-spline load of the ``backlash`` candidate (:func:`spline_load`).

The simulation of a model with state-dependent member forces (dry friction with a stick rule,
Stribeck, windage, direction-dependent viscous friction) cannot be vectorised: each step depends
on the previous one. These kernels run that loop in machine code;
:func:`dvt_identify.simulation.simulate_loop` prepares their arrays (and can run the same source
in the interpreter, ``reference=True``, to check the compilation).

Smooth laws are coded as ``(kind, p0, p1, p2)`` (:data:`STRIBECK`, :data:`WINDAGE`,
:data:`ABS_VISCOUS`, :data:`COULOMB`); :func:`smooth_value` evaluates one, compiled or from
Python. The laws themselves, their codes and their exact partials are :mod:`dvt_model.laws`'
(the one law table of the suite), compiled here with ``numba.njit`` unchanged
(:func:`dvt_model.laws.coded_value`, :func:`dvt_model.laws.coded_partials` dispatch on the
code); a member force is minus the resisting force of the law, and a sliding dry member feels
``-coulomb(s, C, 0, 0)`` (the exact sign). What is not the law stays here: the stick rule, the
break-away, the implicit hold of a smoothed sign.

A dry law with a smoothed sign (``tanh(s / eps)``, ``eps > 0``: :data:`COULOMB`, and
:data:`STRIBECK` with ``p2 = eps > 0``) is *stiff*: near ``s = 0`` it acts like a damper
``Fc / eps``, which an explicit hold over a step makes chatter (the speed flips sign every step
at ``|s| ~ dt mobility Fc``) once ``dt * mobility * Fc / eps`` exceeds about 2. Its force is
held at its value at the step's *end* instead (backward Euler for that force, the exact ZOH for
the rest): the member speed ``s+`` solves ``s+ = b + kappa g(s+)``, with ``b`` the speed the
step reaches without this force and ``kappa = c . Gd F c > 0`` the step's own member response;
``g`` decreases, so the root is unique, found by Newton steps kept inside a bracket
(:func:`implicit_force`). The step is then stable and free of chatter at any rate. The other
laws are held at their start value (explicit, unchanged).

The rule implemented: the linear part is advanced by its exact ZOH map, every member force is
evaluated at the start of a step and held over it; a sliding member whose speed would cross zero
within a step crosses it at the share ``th = s / (s - s+)`` of the step (its speed taken linear
over the step, ``s`` at the start, ``s+`` at the end with the friction held throughout), so
its friction acts over that share only; it then sticks if the force needed to hold it is
within its dry capacity (plus break-away), else the friction is reversed for the rest of the
step; a member at rest stays at rest while the holding force is within the capacity. Before
the crossing share the friction acted over the whole step, and the other members felt its
reaction after the member had stopped. First-order in the step still: on the identifier's
own 1-ms simulation of a plant with Coulomb friction on both members, refitted at 5 ms, the
masses come out 2.1-2.6 % low (``scripts/dry_step_bias.py``; the loop refits such a final
model at the recordings' own rate, docs/identification.md section 3).

:func:`loop_members_sens` runs the same loop with forward sensitivities (tangents along any
number of directions, the exact derivative of each step along the branch it takes), which
:mod:`dvt_identify.sensitivity` feeds; :func:`loop_members` is it without directions.

Compilation happens on the first call of a process and is cached on disk next to this file
(``__pycache__``), so later processes load machine code in well under a second. numba keys that
cache on this file only, while the kernels compile in the laws of :mod:`dvt_model.laws` and the
spline of :mod:`dvt_model.backlash`: :func:`_drop_stale_cache` removes the cached kernels at
import when those sources changed (a digest kept beside the cache).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
from numba import njit
from numba.extending import register_jitable
from numpy.typing import NDArray

from dvt_model import backlash, laws

Array = NDArray[np.float64]

STRIBECK = laws.STRIBECK
"""``g(s) = -stribeck(s, p0, p1, eps=p2)`` = ``-p0 exp(-(s/p1)^2) sign_eps(s)`` (``p0 = Fs``,
``p1 = vs > 0``, ``p2 = eps >= 0``: 0 the exact sign, held with the stick rule's break-away)."""
WINDAGE = laws.WINDAGE
"""``g(s) = -windage(s, p0)`` = ``-p0 s |s|`` (``p0 = Cw``)."""
ABS_VISCOUS = laws.ABS_VISCOUS
"""``g(s) = -abs_viscous(s, p0)`` = ``-p0 |s|`` (``p0 = dFv``)."""
COULOMB = laws.COULOMB
"""``g(s) = -coulomb(s, p0, 0, eps=p1)`` = ``-p0 tanh(s/p1)`` (``p0 = Fc``, ``p1 = eps > 0``):
dry friction with a smoothed sign, no stick rule."""
KINDS = tuple(law.code for law in laws.LAWS.values())
"""Every law code of :data:`dvt_model.laws.LAWS` (the kernels dispatch on it)."""



def _drop_stale_cache() -> None:
    """Delete this module's cached kernels in ``__pycache__`` when the sources compiled into
    them (:mod:`dvt_model.laws`, :mod:`dvt_model.backlash`) differ from those of the cache
    (their SHA-256 in ``__pycache__/simloop.deps``). A cache elsewhere (``NUMBA_CACHE_DIR``)
    is not handled: delete it after editing a law."""
    cache = Path(__file__).with_name("__pycache__")
    digest = hashlib.sha256(b"".join(Path(m.__file__).read_bytes()
                                     for m in (laws, backlash) if m.__file__)).hexdigest()
    stamp = cache / "simloop.deps"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    try:
        cache.mkdir(exist_ok=True)
        for f in [*cache.glob("simloop.*.nbi"), *cache.glob("simloop.*.nbc")]:
            f.unlink(missing_ok=True)
        tmp = cache / f"simloop.deps.{os.getpid()}"
        tmp.write_text(digest)
        tmp.replace(stamp)
    except OSError:  # a read-only install: numba then caches elsewhere or not at all
        pass


_drop_stale_cache()
for _fn in laws.JITABLE:  # the laws compile as written in dvt_model.laws (module docstring)
    register_jitable(_fn)
_coded_value = njit(cache=True, nogil=True)(laws.coded_value)
_coded_partials = njit(cache=True, nogil=True)(laws.coded_partials)
_coded_eps = njit(cache=True, nogil=True)(laws.coded_eps)
_coulomb = njit(cache=True, nogil=True)(laws.coulomb)
_spline_substep = njit(cache=True, nogil=True)(backlash.spline_substep)


@njit(cache=True, nogil=True)
def smooth_value(kind: int, p0: float, p1: float, p2: float, s: float) -> float:
    """Member force of a coded smooth law at member speed ``s`` [force unit]: minus the law's
    resisting force (:func:`dvt_model.laws.coded_value`)."""
    if kind == STRIBECK and s == 0.0:
        return 0.0
    return -_coded_value(kind, p0, p1, p2, s)


@njit(cache=True, nogil=True)
def smooth_slope(kind: int, p0: float, p1: float, p2: float, s: float) -> float:
    """``d g / d s`` of a stiff law (a smoothed sign: :data:`COULOMB`, :data:`STRIBECK` with
    ``p2 > 0``) at member speed ``s``; 0 for the laws held explicitly."""
    if _coded_eps(kind, p1, p2) > 0.0:
        return -_coded_partials(kind, p0, p1, p2, s)[1]
    return 0.0


@njit(cache=True, nogil=True)
def stiff(kind: int, p2: float, p1: float) -> bool:
    """Whether a coded law has a smoothed sign (held implicitly, module docstring)."""
    return _coded_eps(kind, p1, p2) > 0.0


@njit(cache=True, nogil=True)
def _value_slope(kind: int, p0: float, p1: float, p2: float, s: float) -> tuple[float, float]:
    """A stiff law's force and its slope at ``s`` (one evaluation of the transcendentals)."""
    f, fs, _, _, _ = _coded_partials(kind, p0, p1, p2, s)
    return -f, -fs


@njit(cache=True, nogil=True)
def implicit_force(kind: int, p0: float, p1: float, p2: float, b: float, kap: float,
                   s0: float) -> float:
    """The stiff law's force at the step's end: ``g(s+)`` with ``s+ = b + kap g(s+)``
    (``kap > 0``), solved by Newton steps kept in the bracket ``[b - kap |g|max,
    b + kap |g|max]`` (bisection where a step leaves it), from the explicit estimate
    ``b + kap g(s0)`` (exact while the member slides far from zero speed)."""
    gmax = abs(p0)
    lo = b - kap * gmax
    hi = b + kap * gmax
    g, _ = _value_slope(kind, p0, p1, p2, s0)
    s = min(max(b + kap * g, lo), hi)
    tol = 1e-12 * (abs(b) + kap * gmax) + 1e-300
    for _ in range(60):
        g, dg = _value_slope(kind, p0, p1, p2, s)
        h = s - b - kap * g
        if h > 0.0:
            hi = s
        else:
            lo = s
        if abs(h) <= tol:
            return g
        sn = s - h / (1.0 - kap * dg)
        if not (lo < sn < hi):
            sn = 0.5 * (lo + hi)
        if abs(sn - s) <= tol:
            s = sn
            break
        s = sn
    g, _ = _value_slope(kind, p0, p1, p2, s)
    return g


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
def smooth_partials(kind: int, p0: float, p1: float, p2: float, s: float
                    ) -> tuple[float, float, float, float]:
    """Partial derivatives ``(dg/ds, dg/dp0, dg/dp1, dg/dp2)`` of a coded smooth law's member
    force ``g`` (:func:`smooth_value`; the stiff laws at their end-of-step speed) at member
    speed ``s``: minus the exact derivatives of :func:`dvt_model.laws.coded_partials` (0 at
    ``s = 0`` for an exact sign, where the law is 0 for every parameter)."""
    _, fs, f0, f1, f2 = _coded_partials(kind, p0, p1, p2, s)
    return -fs, -f0, -f1, -f2


@njit(cache=True, nogil=True)
def _project_t(tv: Array, dc: Array, dfcv: Array, tdfcv: Array, tdcfc: Array, sn: float,
               cfc: float) -> None:  # pragma: no cover - compiled
    """Tangents (nx, P) of the projection ``x - dfcv (dc . x) / cfc`` (a member brought to
    rest), in place on ``tv`` (``sn = dc . x`` before the projection; ``tdfcv`` (nx, P) and
    ``tdcfc`` (P,) the tangents of ``dfcv`` and ``cfc``)."""
    nx, P = tv.shape
    for p in range(P):
        tsn = 0.0
        for i in range(nx):
            tsn += dc[i] * tv[i, p]
        a = tsn / cfc - sn * tdcfc[p] / (cfc * cfc)
        for i in range(nx):
            tv[i, p] -= tdfcv[i, p] * sn / cfc + dfcv[i] * a


@njit(cache=True, nogil=True)
def loop_members_sens(A: Array, Ad: Array, w: Array, d: Array, x0: Array,
                      sc: Array, skind: NDArray[np.int64], spar: Array, sgd: Array, sfc: Array,
                      dc: Array, dcap: Array, dbrk: Array, dgdf: Array, dfcv: Array,
                      dcfc: Array, tA: Array, tAd: Array, tx0: Array, tspar: Array,
                      tsgd: Array, tsfc: Array, tdgdf: Array, tdfcv: Array, tdcfc: Array,
                      Gd: Array, tGd: Array, tw: Array, tdcap: Array
                      ) -> tuple[Array, Array]:  # pragma: no cover - compiled
    """The step loop for any number of states, with forward sensitivities (tangents) along
    ``P = tx0.shape[1]`` directions (``P = 0``: the states alone).

    The tangent of each step is the exact derivative of the step map with the branch the
    states take (sliding, crossing zero and sticking, reversing, held at rest, breaking away):
    the discrete simulation is differentiated, not an approximation of it; a branch switch
    between two parameter values (the step at which a member sticks) is not a derivative and
    is not seen, as by a finite difference small enough not to cross it.

    Args:
        A, Ad: continuous ``A`` and its ZOH ``Ad``, shape (nx, nx).
        w: generalised input per sample [state unit/s], shape (N, nx).
        d: ``w @ Gd.T``, shape (N, nx).
        x0: initial state, shape (nx,).
        sc, skind, spar, sgd, sfc: smooth forces: member vectors (ns, nx), law codes (ns,),
            law parameters (ns, 3), ``Gd F c`` (ns, nx), ``F c`` (ns, nx).
        dc, dcap, dbrk, dgdf, dfcv, dcfc: dry members (one per distinct member): vectors
            (nd, nx), capacity per sample (nd, N), break-away (nd,), ``Gd F c`` (nd, nx),
            ``F c`` (nd, nx), ``c . F c`` (nd,).
        tA, tAd, tx0, tspar, tsgd, tsfc, tdgdf, tdfcv, tdcfc: the tangents of ``A``, ``Ad``
            (nx, nx, P), ``x0`` (nx, P), the smooth laws' parameters (ns, 3, P) and vectors
            (ns, nx, P), the dry members' vectors (nd, nx, P) and ``c . F c`` (nd, P): the
            direction is the last (contiguous) axis.
        Gd, tGd, tw, tdcap: ``Gd`` (nx, nx), its tangent (nx, nx, P), the tangent of ``w``
            (N, nx, P) (that of ``d = w Gd^T`` is formed step by step) and of the
            capacities (N, nd, P).

    Returns:
        States (N, nx) and their tangents (N, nx, P).
    """
    n, nx = d.shape
    ns = sc.shape[0]
    nd = dc.shape[0]
    P = tx0.shape[1]
    out = np.empty((n, nx))
    tout = np.empty((n, nx, P))
    x = x0.copy()
    out[0] = x
    xn = np.empty(nx)
    xp = np.empty(nx)
    extra = np.empty(nx)
    rest = np.zeros(nd, dtype=np.bool_)
    tx = tx0.copy()
    txn = np.empty((nx, P))
    textra = np.empty((nx, P))
    tt = np.empty(P)
    tcap = np.empty(P)
    tcor = np.empty((nx, P))
    for i in range(nx):
        for p in range(P):
            tout[0, i, p] = tx[i, p]
    for k in range(n - 1):
        # sums in the order of the Python reference loop (bitwise-equal results)
        for i in range(nx):
            acc = 0.0
            for j in range(nx):
                acc += Ad[i, j] * x[j]
            xn[i] = acc + d[k, i]
            extra[i] = 0.0
        if P > 0:
            for i in range(nx):
                for p in range(P):
                    txn[i, p] = 0.0
                    textra[i, p] = 0.0
                for j in range(nx):
                    a = Ad[i, j]
                    xj = x[j]
                    gij = Gd[i, j]
                    wj = w[k, j]
                    for p in range(P):
                        txn[i, p] += (a * tx[j, p] + tAd[i, j, p] * xj + gij * tw[k, j, p]
                                      + tGd[i, j, p] * wj)
        for m in range(ns):
            if stiff(skind[m], spar[m, 2], spar[m, 1]):
                continue
            s = _dot(sc[m], x)
            tau = smooth_value(skind[m], spar[m, 0], spar[m, 1], spar[m, 2], s)
            if tau != 0.0:
                for i in range(nx):
                    xn[i] += sgd[m, i] * tau
                    extra[i] += sfc[m, i] * tau
            if P > 0:
                gs, g0, g1, g2 = smooth_partials(skind[m], spar[m, 0], spar[m, 1], spar[m, 2],
                                                 s)
                for p in range(P):
                    tt[p] = g0 * tspar[m, 0, p] + g1 * tspar[m, 1, p] + g2 * tspar[m, 2, p]
                for i in range(nx):
                    c = gs * sc[m, i]
                    for p in range(P):
                        tt[p] += c * tx[i, p]
                for i in range(nx):
                    a = sgd[m, i]
                    b = sfc[m, i]
                    for p in range(P):
                        txn[i, p] += tsgd[m, i, p] * tau + a * tt[p]
                        textra[i, p] += tsfc[m, i, p] * tau + b * tt[p]
        for m in range(ns):  # stiff laws: held at the step's end (module docstring)
            if not stiff(skind[m], spar[m, 2], spar[m, 1]):
                continue
            kap = _dot(sc[m], sgd[m])
            b = _dot(sc[m], xn)
            tau = implicit_force(skind[m], spar[m, 0], spar[m, 1], spar[m, 2],
                                 b, kap, _dot(sc[m], x))
            if P > 0:
                # s+ = b + kap g(s+): dg = (g' (db + dkap g) + g_p dp) / (1 - kap g')
                gs, g0, g1, g2 = smooth_partials(skind[m], spar[m, 0], spar[m, 1], spar[m, 2],
                                                 b + kap * tau)
                r = 1.0 / (1.0 - kap * gs)
                for p in range(P):
                    tt[p] = g0 * tspar[m, 0, p] + g1 * tspar[m, 1, p] + g2 * tspar[m, 2, p]
                for i in range(nx):
                    c = sc[m, i]
                    for p in range(P):
                        tt[p] += gs * c * (txn[i, p] + tsgd[m, i, p] * tau)
                for p in range(P):
                    tt[p] *= r
                for i in range(nx):
                    a = sgd[m, i]
                    c = sfc[m, i]
                    for p in range(P):
                        txn[i, p] += tsgd[m, i, p] * tau + a * tt[p]
                        textra[i, p] += tsfc[m, i, p] * tau + c * tt[p]
            for i in range(nx):
                xn[i] += sgd[m, i] * tau
                extra[i] += sfc[m, i] * tau
        for g in range(nd):
            cap = dcap[g, k]
            cfc = dcfc[g]
            s = _dot(dc[g], x)
            if P > 0:
                for p in range(P):
                    tcap[p] = tdcap[k, g, p]
            if not rest[g] and s != 0.0:
                tau = -_coulomb(s, cap, 0.0, 0.0)
                sg = -1.0 if s > 0.0 else 1.0
                for i in range(nx):
                    xn[i] += dgdf[g, i] * tau
                if P > 0:
                    for i in range(nx):
                        a = dgdf[g, i] * sg
                        for p in range(P):
                            txn[i, p] += tdgdf[g, i, p] * tau + a * tcap[p]
                sn = _dot(dc[g], xn)
                if (sn > 0.0) != (s > 0.0) or sn == 0.0:
                    # crossed zero at the share th of the step (the member's speed linear in
                    # time): the friction acted until then only (module docstring); then stick
                    # if the holding force is within the capacity, else go on with the
                    # friction reversed for the rest of the step
                    th = s / (s - sn)
                    for i in range(nx):
                        xn[i] -= (1.0 - th) * dgdf[g, i] * tau
                    if P > 0:
                        # d th = (s d sn - sn d s) / (s - sn)^2; the correction's tangent
                        for p in range(P):
                            t_s = 0.0
                            t_sn = 0.0
                            for i in range(nx):
                                t_s += dc[g, i] * tx[i, p]
                                t_sn += dc[g, i] * txn[i, p]
                            tt[p] = (s * t_sn - sn * t_s) / ((s - sn) * (s - sn))
                        for i in range(nx):
                            a = dgdf[g, i] * sg
                            for p in range(P):
                                tcor[i, p] = ((1.0 - th) * (tdgdf[g, i, p] * tau + a * tcap[p])
                                              - tt[p] * dgdf[g, i] * tau)
                                txn[i, p] -= tcor[i, p]
                    sn = _dot(dc[g], xn)
                    for i in range(nx):
                        xp[i] = xn[i] - dfcv[g, i] * sn / cfc
                    ca = _member_accel(A, w[k], extra, xp, dc[g])
                    if abs(ca / cfc) <= cap + dbrk[g]:
                        for i in range(nx):
                            xn[i] = xp[i]
                        if P > 0:
                            _project_t(txn, dc[g], dfcv[g], tdfcv[g], tdcfc[g], sn, cfc)
                        rest[g] = True
                    else:
                        for i in range(nx):
                            xn[i] -= (1.0 - th) * dgdf[g, i] * tau
                        if P > 0:
                            for i in range(nx):
                                for p in range(P):
                                    txn[i, p] -= tcor[i, p]
                        sn2 = _dot(dc[g], xn)
                        if (sn2 > 0.0) == (s > 0.0) or sn2 == 0.0:
                            for i in range(nx):
                                xn[i] -= dfcv[g, i] * sn2 / cfc
                            if P > 0:
                                _project_t(txn, dc[g], dfcv[g], tdfcv[g], tdcfc[g], sn2, cfc)
                            rest[g] = True
                continue
            ca = _member_accel(A, w[k], extra, x, dc[g])
            req = -ca / cfc
            if abs(req) <= cap + dbrk[g]:
                for i in range(nx):
                    xn[i] += dgdf[g, i] * req
                if P > 0:
                    # d req = -(d ca / cfc - ca d cfc / cfc^2), d ca = c . (dA x + A dx + dw
                    # + d extra)
                    for p in range(P):
                        tt[p] = ca * tdcfc[g, p] / (cfc * cfc)
                    for i in range(nx):
                        c = dc[g, i] / cfc
                        for p in range(P):
                            v = tw[k, i, p] + textra[i, p]
                            for j in range(nx):
                                v += A[i, j] * tx[j, p] + tA[i, j, p] * x[j]
                            tt[p] -= c * v
                    for i in range(nx):
                        a = dgdf[g, i]
                        for p in range(P):
                            txn[i, p] += tdgdf[g, i, p] * req + a * tt[p]
                sn = _dot(dc[g], xn)
                for i in range(nx):
                    xn[i] -= dfcv[g, i] * sn / cfc
                if P > 0:
                    _project_t(txn, dc[g], dfcv[g], tdfcv[g], tdcfc[g], sn, cfc)
                rest[g] = True
            else:
                tau = -cap if ca > 0.0 else cap
                sg = -1.0 if ca > 0.0 else 1.0
                for i in range(nx):
                    xn[i] += dgdf[g, i] * tau
                if P > 0:
                    for i in range(nx):
                        a = dgdf[g, i] * sg
                        for p in range(P):
                            txn[i, p] += tdgdf[g, i, p] * tau + a * tcap[p]
                rest[g] = False
        for i in range(nx):
            x[i] = xn[i]
            out[k + 1, i] = xn[i]
        if P > 0:
            for i in range(nx):
                for p in range(P):
                    tx[i, p] = txn[i, p]
                    tout[k + 1, i, p] = txn[i, p]
    return out, tout


_NO_TANGENTS: dict[tuple[int, int, int, int], tuple[Array, ...]] = {}


def no_tangents(nx: int, ns: int, nd: int, n: int) -> tuple[Array, ...]:
    """The tangent arguments of :func:`loop_members_sens` for no direction (``P = 0``; empty
    arrays, made once per shape)."""
    key = (nx, ns, nd, n)
    hit = _NO_TANGENTS.get(key)
    if hit is None:
        if len(_NO_TANGENTS) > 64:
            _NO_TANGENTS.clear()
        hit = (np.zeros((nx, nx, 0)), np.zeros((nx, nx, 0)), np.zeros((nx, 0)),
               np.zeros((ns, 3, 0)), np.zeros((ns, nx, 0)), np.zeros((ns, nx, 0)),
               np.zeros((nd, nx, 0)), np.zeros((nd, nx, 0)), np.zeros((nd, 0)),
               np.zeros((nx, nx)), np.zeros((nx, nx, 0)), np.zeros((n, nx, 0)),
               np.zeros((n, nd, 0)))
        _NO_TANGENTS[key] = hit
    return hit


def loop_members(A: Array, Ad: Array, w: Array, d: Array, x0: Array,
                 sc: Array, skind: NDArray[np.int64], spar: Array, sgd: Array, sfc: Array,
                 dc: Array, dcap: Array, dbrk: Array, dgdf: Array, dfcv: Array,
                 dcfc: Array, reference: bool = False) -> Array:
    """The step loop for any number of states without sensitivities (arguments as
    :func:`loop_members_sens`); states, shape (N, nx). ``reference``: the kernel's source
    run by the interpreter."""
    kern = loop_members_sens.py_func if reference else loop_members_sens
    x, _ = kern(A, Ad, w, d, x0, sc, skind, spar, sgd, sfc, dc, dcap, dbrk, dgdf, dfcv, dcfc,
                *no_tangents(d.shape[1], sc.shape[0], dc.shape[0], d.shape[0]))
    return np.asarray(x)


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
            parameters (ns, 3), ``Gd F c`` (ns,).
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
            if stiff(skind[m], spar[m, 2], spar[m, 1]):
                continue
            tau = smooth_value(skind[m], spar[m, 0], spar[m, 1], spar[m, 2], sc[m] * x)
            if tau != 0.0:
                xn += sgd[m] * tau
                extra += tau * sc[m]
        for m in range(ns):  # stiff laws: held at the step's end (module docstring)
            if not stiff(skind[m], spar[m, 2], spar[m, 1]):
                continue
            tau = implicit_force(skind[m], spar[m, 0], spar[m, 1], spar[m, 2], sc[m] * xn,
                                 sc[m] * sgd[m], sc[m] * x)
            xn += sgd[m] * tau
            extra += tau * sc[m]
        if has_dry:
            c = cap[k]
            if not rest and x != 0.0:
                xn -= gdf_unit * c if x > 0.0 else -gdf_unit * c
                if (xn > 0.0) != (x > 0.0) or xn == 0.0:
                    th = x / (x - xn)  # crossed at this share of the step: reversed after it
                    acc0 = w[k] + fmap * extra0
                    if abs(acc0 / fmap) <= c + brk:
                        xn = 0.0
                        rest = True
                    else:
                        xn += (2.0 * (1.0 - th) * gdf_unit * c if x > 0.0
                               else -2.0 * (1.0 - th) * gdf_unit * c)
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
    """Compile (or load from the on-disk cache) the identification's kernels now, on a tiny
    problem: the step loops (with and without sensitivities), the spline and lag kernels and
    the linear reference's simulation kernels; what a process pays once before its first
    identification."""
    from dvt_identify.lti import warm_up as reference_warm_up

    reference_warm_up()
    z2 = np.zeros((2, 2))
    e2 = np.zeros((0, 2))
    e1 = np.zeros(0)
    ek = np.zeros(0, dtype=np.int64)
    loop_members(z2, z2, z2, z2, np.zeros(2), e2, ek, np.zeros((0, 3)), e2, e2, e2,
                 np.zeros((0, 2)), e1, e2, e2, e1)
    loop_members_sens(z2, z2, z2, z2, np.zeros(2), e2, ek, np.zeros((0, 3)), e2, e2, e2,
                      np.zeros((0, 2)), e1, e2, e2, e1, np.zeros((2, 2, 1)), np.zeros((2, 2, 1)),
                      np.ones((2, 1)), np.zeros((0, 3, 1)), np.zeros((0, 2, 1)),
                      np.zeros((0, 2, 1)), np.zeros((0, 2, 1)), np.zeros((0, 2, 1)),
                      np.zeros((0, 1)), z2, np.zeros((2, 2, 1)), np.zeros((2, 2, 1)),
                      np.zeros((2, 0, 1)))
    loop_scalar(0.0, 1.0, np.zeros(2), np.zeros(2), 0.0, e1, ek, np.zeros((0, 3)), e1,
                False, np.zeros(2), 0.0, 1.0, 1.0, 0.0)
    spline_load(np.zeros(2), 1e-3, 0.0, 1.0, 1.0, 2)
    first_order_lag(np.zeros(2), 0.5)
