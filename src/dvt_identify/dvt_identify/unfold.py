"""The sign of an output read sign-blind, restored for the start of a fit only.

A sign-blind sensor (:class:`dvt_identify.effects.sensors.SignBlindSensor`) reads ``|x|``.
Fitted to ``|x|``, a linear reference has nothing to hold on to (its fit stays near 0 %), so
its modes, and the structure starts mapped from them (:func:`dvt_identify.linref.mapped_starts`),
are noise; from the description's priors the fit collapses (a spring run to 1e15, a damper to
1e11: measured on simulated belt drives of 300-sample records at 50 Hz, three of three).

:func:`unfold` guesses the sign back. The true output can change sign only near the samples
where ``|y|`` has a local minimum below ``max(4 noise std, 40 % of its largest value)`` (the
noise std robust, :func:`dvt_identify.resid.robust_white_floor`; at a few samples per period a
crossing can fall between samples far from 0): the sign may change just before or just after
such a sample, and is constant elsewhere. Among those patterns the signs minimise the equation
error of an ARX model (orders :data:`ARX_ORDER`) from every input to the signed output, pooled
over the segments: alternately the ARX least squares on the signed output and, for that model,
the exact best pattern (dynamic programming over the signs of the last ``ARX_ORDER`` samples),
until the pattern stops changing, from several first patterns (all positive, the sign of the
inputs' low-passed sum, :data:`RANDOM_GUESSES` random ones); the lowest error wins. The overall
sign stays open (a pattern and its opposite fit alike). The unfolded output is used only to
fit a linear reference whose modes give starts (:func:`dvt_identify.linref.unfolded_starts`);
the fit itself runs on the measured ``|y|`` through the sign-blind map, so a wrong piece costs
at most a start.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.signal import lfilter

from dvt_identify.data import Segment
from dvt_identify.resid import robust_white_floor

Array = NDArray[np.float64]

ARX_ORDER = 3
"""Orders ``na = nb`` of the ARX model that decides the signs."""
MAX_ROUNDS = 30
"""Most rounds of the alternating ARX fit and sign choice."""
CUT_NOISE = 4.0
"""A sign change is possible where ``|y|`` dips below this many noise std ..."""
CUT_SHARE = 0.4
"""... or below this share of its largest value, whichever is larger."""
RANDOM_GUESSES = 8
"""Random first sign patterns besides the two guesses (the alternation has local optima)."""
LOWPASS_POLE = 0.8
"""Pole of the first guess's low-pass of the inputs (per sample)."""


def cuts(y: Array, noise: float, ends: bool = False) -> list[int]:
    """Where the sign may change: the local minima of ``y`` (``|x|`` read) below
    ``max(CUT_NOISE noise, CUT_SHARE max(y))``, sample indices in order; with ``ends`` also
    the first and the last sample when below it and not above their one neighbour (a short
    window cut off in a dip: the crossing may lie just outside it)."""
    y = np.asarray(y, float)
    thr = max(CUT_NOISE * noise, CUT_SHARE * float(np.max(np.abs(y)) if y.size else 0.0))
    mid = y[1:-1]
    low = (mid <= y[:-2]) & (mid <= y[2:]) & (mid < thr)
    out = [int(i) + 1 for i in np.flatnonzero(low)]
    if ends and y.size >= 2:
        if y[0] <= y[1] and y[0] < thr:
            out.insert(0, 0)
        if y[-1] <= y[-2] and y[-1] < thr:
            out.append(y.size - 1)
    return out


def _bounds(at: Sequence[int], n: int) -> list[int]:
    """Piece boundaries for sign changes near the samples ``at``: the sign may change before
    or after such a sample (the crossing lies on either side of it), so each is a piece of
    its own; ``[0, ..., n]``."""
    out = {0, n}
    for i in at:
        out.update((i, min(i + 1, n)))
    return sorted(out)


def _signal(n: int, bounds: Sequence[int], signs: Array) -> Array:
    out = np.empty(n)
    for k in range(len(bounds) - 1):
        out[bounds[k]: bounds[k + 1]] = signs[k]
    return out


def _arx_ls(us: Sequence[Array], ys: Sequence[Array], order: int) -> tuple[Array, Array]:
    """The pooled MISO ARX least squares (not checked for stability): ``a`` (order + 1,),
    ``b`` (nu, order + 1) as for :func:`scipy.signal.lfilter`."""
    rows, tgt = [], []
    for u, y in zip(us, ys, strict=True):
        for i in range(order, y.size):
            rows.append(np.concatenate([-y[i - order: i][::-1], u[i - order: i][::-1].T.ravel()]))
            tgt.append(y[i])
    th, *_ = np.linalg.lstsq(np.array(rows), np.array(tgt), rcond=None)
    b = np.zeros((us[0].shape[1], order + 1))
    b[:, 1:] = th[order:].reshape(-1, order)
    return np.concatenate([[1.0], th[:order]]), b


@njit(cache=True, nogil=True)
def _viterbi_kernel(a: Array, y: Array, forced: Array, starts: Array) -> tuple[Array, float]:
    """:func:`_viterbi`'s dynamic programme (``forced``: the inputs' part of each equation)."""
    order = a.size - 1
    n = y.size
    ns = 1 << order
    mask = ns - 1
    top = ns >> 1
    inf = np.inf
    cost = np.full(ns, inf)
    cost[0] = 0.0  # s_0 either sign (the older bits are shifted out unused)
    cost[1] = 0.0
    back = np.zeros((n, ns), dtype=np.int64)
    new = np.empty(ns)
    for i in range(1, n):
        new[:] = inf
        for x in range(2):
            sx = -1.0 if x == 1 else 1.0
            for lo in range(top):
                best = inf
                arg = lo
                for p in (lo, lo | top):
                    c = cost[p]
                    if c == inf or (not starts[i] and (p & 1) != x):
                        continue
                    if i >= order:
                        e = sx * y[i] - forced[i]
                        for m in range(1, order + 1):
                            sm = -1.0 if (p >> (m - 1)) & 1 else 1.0
                            e += a[m] * sm * y[i - m]
                        c = c + e * e
                    if c < best:
                        best = c
                        arg = p
                tgt = ((lo << 1) | x) & mask
                new[tgt] = best
                back[i, tgt] = arg
        cost[:] = new
    st = 0
    for k in range(ns):
        if cost[k] < cost[st]:
            st = k
    total = cost[st]
    signs = np.empty(n)
    for i in range(n - 1, -1, -1):
        signs[i] = -1.0 if st & 1 else 1.0
        st = back[i, st]
    return signs, total


def _viterbi(a: Array, b: Array, u: Array, y: Array, starts: Array) -> tuple[Array, float]:
    """The signs (N,) of ``|y|`` that minimise the ARX equation error ``sum_i (y_s[i] +
    sum_m a_m y_s[i-m] - sum_m b_m u[i-m])^2`` over sign patterns that change only where
    ``starts`` (N,) is true, and that error; exact (dynamic programming over the signs of the
    last ``order`` samples, compiled)."""
    order = a.size - 1
    forced = np.zeros(y.size)
    for m in range(1, order + 1):
        forced[m:] += u[:-m] @ b[:, m]
    signs, total = _viterbi_kernel(np.ascontiguousarray(a, dtype=np.float64),
                                   np.ascontiguousarray(y, dtype=np.float64), forced,
                                   np.ascontiguousarray(starts, dtype=np.bool_))
    return np.asarray(signs), float(total)


def _em(us: Sequence[Array], ys: Sequence[Array], starts: Sequence[Array],
        signs: list[Array]) -> tuple[float, list[Array]]:
    """Alternate the ARX fit on the signed output and the exact sign choice
    (:func:`_viterbi`) until the signs stop changing; the equation error and the signs."""
    total = math.inf
    for _ in range(MAX_ROUNDS):
        a, b = _arx_ls(us, [s * y for s, y in zip(signs, ys, strict=True)], ARX_ORDER)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            break
        got = [_viterbi(a, b, u, y, st) for u, y, st in zip(us, ys, starts, strict=True)]
        new = [g[0] for g in got]
        total = sum(g[1] for g in got)
        changed = any(np.any(n != s) for n, s in zip(new, signs, strict=True))
        signs = new
        if not changed:
            break
    return total, signs


def unfold(segments: Sequence[Segment], j: int, seed: int = 0) -> list[Segment]:
    """``segments`` with output ``j`` (read sign-blind) signed again: ``s(t) |y_j|`` with ``s``
    constant between the possible sign changes and chosen as the module docstring says (the
    random first guesses drawn with ``seed``); the other outputs, the inputs and the times
    unchanged. The segments themselves when there is nothing to decide (no input, or a single
    piece in every segment). The overall sign is the one the inputs give it or its opposite:
    both describe the data (:func:`dvt_identify.linref.unfolded_starts` maps both)."""
    segs = list(segments)
    if not segs or segs[0].u.shape[1] == 0:
        return segs
    us = [np.asarray(s.u, float) for s in segs]
    ys = [np.abs(np.asarray(s.y[:, j], float)) for s in segs]
    bounds = [_bounds(cuts(y, robust_white_floor([y])), y.size) for y in ys]
    if all(len(b) <= 2 for b in bounds):
        return segs
    starts = []
    for y, b in zip(ys, bounds, strict=True):
        st = np.zeros(y.size, bool)
        st[b[1:-1]] = True
        starts.append(st)
    firsts = [[np.ones(y.size) for y in ys]]
    low = [lfilter([1.0 - LOWPASS_POLE], [1.0, -LOWPASS_POLE], u.sum(axis=1)) for u in us]
    firsts.append([_signal(y.size, b, np.array([1.0 if lo[b[k]: b[k + 1]].sum() >= 0 else -1.0
                                                 for k in range(len(b) - 1)]))
                   for y, b, lo in zip(ys, bounds, low, strict=True)])
    rng = np.random.default_rng(seed)
    firsts += [[_signal(y.size, b, rng.choice([-1.0, 1.0], size=len(b) - 1))
                for y, b in zip(ys, bounds, strict=True)] for _ in range(RANDOM_GUESSES)]
    best_cost, best = math.inf, firsts[0]
    for g in firsts:
        cost, signs = _em(us, ys, starts, g)
        if cost < best_cost:
            best_cost, best = cost, signs
    out = []
    for seg, y, s in zip(segs, ys, best, strict=True):
        yy = np.array(seg.y, dtype=float, copy=True)
        yy[:, j] = s * y
        out.append(replace(seg, y=yy))
    return out
