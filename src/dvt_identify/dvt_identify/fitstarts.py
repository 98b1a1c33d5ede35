"""Where an output-error fit starts: the start guard of :class:`~dvt_identify.fit.OEFit`
(the guess with each band's gain from its engagements, the extra starts, random perturbations,
and the further starts of a suspect optimum), as a mixin the fit inherits. Pure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.effects import BrakeEngagement, BrakeLockup
from dvt_identify.simulation import OEModel
from dvt_identify.structures import initial_state

Array = NDArray[np.float64]


def _engagement_windows(segments: Sequence[Segment], j: int, pre: float = 0.05,
                        post: float = 0.4, most: int = 8) -> list[Segment]:
    """Windows around the rises of input ``j`` through half its largest value (at most
    ``most``, each from ``pre`` s before to ``post`` s after the rise)."""
    out: list[Segment] = []
    for seg in segments:
        u = seg.u[:, j]
        top = float(np.max(u)) if u.size else 0.0
        if not top > 0:
            continue
        on = u > 0.5 * top
        edges = np.flatnonzero(on[1:] & ~on[:-1]) + 1
        for e in edges:
            a = max(0, int(e) - round(pre / seg.dt))
            b = min(seg.n, int(e) + round(post / seg.dt))
            if b - a >= 5:
                out.append(seg.rows(a, b))
            if len(out) >= most:
                return out
    return out


def _x0_guess(seg: Segment, model: OEModel | None = None) -> Array:
    """Initial-state start (nx,): the mean of the first 3 outputs, mapped to the states by the
    structure when it has hidden states (:func:`~dvt_identify.structures.initial_state`)."""
    y0 = np.asarray(seg.y[: min(3, seg.n)].mean(axis=0), dtype=float)
    return y0 if model is None else initial_state(model.structure, y0)


def x0_guesses(seg: Segment, model: OEModel) -> list[Array]:
    """Initial-state starts (each (nx,)): :func:`_x0_guess`, and for each output the model
    reads sign-blind (:meth:`Effect.blind_output`) the same with that output's first value
    negated: ``|y|`` does not tell which sign the state starts with, and a local fit from the
    wrong one stays there (the free response runs mirrored until it decays)."""
    out = [_x0_guess(seg, model)]
    y0 = np.asarray(seg.y[: min(3, seg.n)].mean(axis=0), dtype=float)
    for e in model.effects:
        j = e.blind_output()
        if j is not None and y0[j] != 0.0:
            flipped = y0.copy()
            flipped[j] = -flipped[j]
            out.append(initial_state(model.structure, flipped))
    return out


WINDOW_PATTERNS = 256
"""Most sign patterns :func:`window_sign_starts` enumerates in a window (beyond: none)."""
WINDOW_SIGN_STARTS = 2
"""How many of the best-fitting patterns' states :func:`window_sign_starts` returns."""


def without_blind_maps(model: OEModel, theta: Array) -> tuple[list[tuple[int, int]], Array]:
    """The sign-blind maps of ``model`` as ``(effect index, output index)``
    (:meth:`Effect.blind_output`) and ``theta`` (p,) with those maps at their null values (the
    model without them, affine in its initial state for a linear structure)."""
    blind = [(k, j) for k, e in enumerate(model.effects) if (j := e.blind_output()) is not None]
    bare = np.asarray(theta, float).copy()
    for k, _ in blind:
        bare[model.effect_slice(k)] = [q.null for q in model.effects[k].params]
    return blind, bare


def undo_maps(maps: Sequence[tuple[Any, Array]], segs: Sequence[Segment]
              ) -> tuple[list[Segment], list[int]]:
    """``segs`` with the output maps ``(effect, parameters)`` that have an inverse undone
    (:meth:`Effect.output_inverse`, the last applied first), and the indices into ``maps`` of
    those undone."""
    out, undone = list(segs), []
    for k in reversed(range(len(maps))):
        eff, p = maps[k]
        ys = [eff.output_inverse(p, s.y, s.dt) for s in out]
        if any(y is not None for y in ys):
            out = [s if y is None else replace(s, y=y) for s, y in zip(out, ys, strict=True)]
            undone.append(k)
    return out, undone


def undone_at(maps: Sequence[tuple[Any, Array]], segs: Sequence[Segment]) -> list[Segment]:
    """``segs`` with the output maps ``(effect, parameters)`` that have an inverse undone
    (:func:`undo_maps`)."""
    return undo_maps(maps, segs)[0]


def window_sign_starts(model: OEModel, theta: Array, part: Segment, w: Array,
                       noise: Sequence[float]) -> list[Array]:
    """Initial-state starts (each (nx,)) for a short window ``part`` of a model that reads
    outputs sign-blind (:meth:`Effect.blind_output`); empty without one.

    ``|y|`` hides where the output changes sign inside the window, and a local fit from
    either sign of its first value keeps that sign through the window (measured on belt drives
    with a 10-sample window at 50 Hz: test fits 73-94 % where the estimated state gave 96 %).
    The sign may change only next to a dip of ``|y|`` (:func:`dvt_identify.unfold.cuts`, the
    window's ends included, with the output's robust white-noise std ``noise[j]``); every pattern of
    signs over those pieces (at most :data:`WINDOW_PATTERNS`) is a signed target for the model
    without its sign-blind maps, which is affine in its initial state: the state of each
    pattern by linear least squares (weighted outputs ``w``, (ny,)), and the states of the
    :data:`WINDOW_SIGN_STARTS` patterns that fit best are returned (the caller polishes and
    chooses them on the model itself)."""
    from dvt_identify.sensitivity import simulate_sens
    from dvt_identify.simulation import DivergedError
    from dvt_identify.unfold import _bounds, _signal, cuts

    blind, bare = without_blind_maps(model, theta)
    if not blind or part.n < 2:
        return []
    cols = sorted({j for _, j in blind})
    y = np.asarray(part.y, float)
    pieces = {j: _bounds(cuts(np.abs(y[:, j]), float(noise[j]), ends=True), part.n)
              for j in cols}
    count = [len(b) - 1 for b in pieces.values()]
    if 2 ** sum(count) > WINDOW_PATTERNS:
        return []
    try:
        with np.errstate(all="ignore"):
            _, yb, S = simulate_sens(model, bare, part, np.zeros(model.nx), (), True)
    except (DivergedError, np.linalg.LinAlgError, ValueError, OverflowError):
        return []
    J = (S / w[None, :, None]).reshape(-1, model.nx)
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(yb))):
        return []
    # every pattern at once: targets (P, N * ny), states by the pseudo-inverse
    codes = np.arange(2 ** sum(count))
    bits = ((codes[:, None] >> np.arange(sum(count))[None, :]) & 1) * 2.0 - 1.0
    targets = np.repeat((y / w)[None], codes.size, axis=0)
    at = 0
    for j, c in zip(cols, count, strict=True):
        signs = np.array([_signal(part.n, pieces[j], b) for b in bits[:, at: at + c]])
        targets[:, :, j] = signs * np.abs(y[:, j]) / w[j]
        at += c
    r = targets.reshape(codes.size, -1) - (yb / w).ravel()[None, :]
    pinv = np.linalg.pinv(J, rcond=1e-10)
    x0s = r @ pinv.T
    cost = np.sum((r - x0s @ J.T) ** 2, axis=1)
    best = np.argsort(cost, kind="stable")[:WINDOW_SIGN_STARTS]
    return [np.asarray(x0s[i], float) for i in best if np.all(np.isfinite(x0s[i]))]


class StartPoints:
    """The start guard's methods of :class:`~dvt_identify.fit.OEFit` (which sets the
    attributes below and implements the stubs)."""

    model: OEModel
    starts: int
    seed: int
    theta0: Array | None
    extra_starts: list[Array]
    physics_start: bool
    more_starts: int
    init_window: int
    weights: Array | None
    weights_: Array

    def _usable(self, theta: Array) -> bool:
        raise NotImplementedError

    def _say(self, msg: str) -> None:
        raise NotImplementedError

    def _residual(self, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array],
                  w: Array) -> Array:
        raise NotImplementedError

    def bounds_hit(self, theta: Array) -> list[tuple[str, bool]]:
        raise NotImplementedError

    def window_x0(self, theta: Array, seg: Segment, guess: Array | None = None,
                  iterations: int = 3) -> Array:
        raise NotImplementedError

    def _output_weights(self, segments: Sequence[Segment]) -> Array:
        """Output scale (ny,): the given weights, else ``std(y_j)`` pooled (1 where it is 0)."""
        if self.weights is not None:
            return np.asarray(self.weights, dtype=float)
        w = np.std(np.vstack([s.y for s in segments]), axis=0)
        w[w == 0] = 1.0
        return np.asarray(w, dtype=float)

    def _start_points(self, segments: Sequence[Segment], lo: Array, hi: Array) -> list[Array]:
        """The guess (with the band gains from their engagements, :meth:`band_start`), every
        usable extra start, then usable random perturbations of the free parameters
        (:meth:`_random_starts`) up to ``starts`` in all; each (p,)."""
        m = self.model
        if self.theta0 is not None:
            guess = np.asarray(self.theta0, dtype=float).copy()
        else:
            guess = m.initial()
            guess[: m.n_struct] = m.structure.initial_guess(segments)
            guess = np.clip(guess, lo, hi)
            if self.physics_start:
                # the band fit needs the lock-up dynamics: the structure's prior (physical)
                # values, not the equation-error ones (a linear fit across lock-ups)
                prior = np.clip(m.initial(), lo, hi)
                banded = self.band_start(prior, segments, lo, hi)
                guess[m.n_struct:] = banded[m.n_struct:]
        guess = np.clip(guess, lo, hi)
        rng = np.random.default_rng(self.seed)
        starts = [guess]
        for st in self.extra_starts:
            st = np.clip(np.asarray(st, float), lo, hi)
            if self._usable(st) and not np.allclose(st, guess):
                starts.append(st)
        if len(starts) > 1 and self.theta0 is None:
            # the first start runs to convergence: take the guess or extra start that
            # simulates best from where it is (one simulation each; measured: an
            # equation-error guess across lock-ups can be far off and cost 800 evaluations)
            x0s = [_x0_guess(sg, self.model) for sg in segments]
            w = self.weights_

            def cost(th: Array) -> float:
                xs = ([self.window_x0(th, sg) for sg in segments] if self.init_window > 0
                      else x0s)
                r = self._residual(th, segments, xs, w)
                return float(r @ r)
            k = int(np.argmin([cost(st) for st in starts]))
            starts.insert(0, starts.pop(k))
        starts.extend(self._random_starts(starts[0], lo, hi, self.starts - len(starts), rng))
        return starts

    def _random_starts(self, guess: Array, lo: Array, hi: Array, count: int,
                       rng: np.random.Generator) -> list[Array]:
        """``count`` usable random perturbations of ``guess``: every free parameter (structure
        and effects) by a factor in ``[1/spread, spread]`` (a zero one by a normal step of the
        structure's scale), clipped into the bounds; the spread shrinks from 3 towards 1.1
        while perturbations come out unusable, so exactly ``count`` starts are returned (the
        last resort: the effects' parameters alone perturbed)."""
        m = self.model
        out: list[Array] = []
        scale = float(np.max(np.abs(guess[: m.n_struct]))) if m.n_struct else 0.0
        spread = 3.0
        tries = 0
        while len(out) < count:
            tries += 1
            if tries % 20 == 0:
                spread = max(1.1, spread ** 0.7)
            struct = tries < 400
            st = guess.copy()
            for i in np.flatnonzero(m.free):
                if i < m.n_struct and not struct:
                    continue
                f = math.exp(rng.uniform(-math.log(spread), math.log(spread)))
                st[i] = (st[i] * f if st[i] != 0
                         else rng.normal(0.0, 0.1) * (scale if i < m.n_struct and scale else 1.0)
                         if i < m.n_struct else st[i])
            st = np.clip(st, lo, hi)
            if self._usable(st) or tries >= 600:
                out.append(st)
        return out

    def _more_start_points(self, segments: Sequence[Segment], problem: Any,
                           theta_best: Array, guess: Array) -> list[Array]:
        """Starts run when the optimum is suspect: the best point with every parameter at a
        (non-null) bound reset to its first start value (or, when that was the same bound,
        its initial value), then random perturbations of the best point."""
        m = self.model
        out: list[Array] = []
        hit = [name for name, is_null in self.bounds_hit(theta_best) if not is_null]
        if hit:
            st = theta_best.copy()
            for name in hit:
                i = m.names.index(name)
                v = float(guess[i])
                if abs(v - float(theta_best[i])) <= 1e-9 * max(abs(v), 1.0):
                    v = float(m.specs[i].initial)
                st[i] = v
            out.append(np.clip(st, problem.lo, problem.hi))
        rng = np.random.default_rng(self.seed + 7919)
        out.extend(self._random_starts(theta_best, problem.lo, problem.hi,
                                       self.more_starts - len(out), rng))
        return out

    def band_start(self, theta: Array, segments: Sequence[Segment], lo: Array, hi: Array
                   ) -> Array:
        """``theta`` with each band's gain started from its engagements.

        For each brake input with a :class:`~dvt_identify.effects.BrakeEngagement` lag and a
        :class:`~dvt_identify.effects.BrakeLockup` on the same input, the windows around each
        rise of the brake input (0.05 s before to 0.4 s after it crosses half its largest
        value) are simulated from their measured first state with the rest of ``theta``; the
        gain whose simulated ring deceleration and lock-up best match the measured ones
        (weighted squared error over a grid of 0.25-4 x the initial gain, then a
        golden-section polish) replaces the initial value. The lag stays at its initial
        value: with one or two engagements per band only the ratio gain / lag of the rise is
        determined (measured: a joint fit wandered to lags of 1e-4..1 s). Returns a copy."""
        m = self.model
        th = np.asarray(theta, float).copy()
        offs = np.cumsum([m.n_struct] + [len(e.params) for e in m.effects])
        lags = {e.index: int(offs[k]) for k, e in enumerate(m.effects)
                if isinstance(e, BrakeEngagement) and len(e.params) == 1}
        gains = {e.index: int(offs[k]) for k, e in enumerate(m.effects)
                 if isinstance(e, BrakeLockup)}
        w = self.weights_ if hasattr(self, "weights_") else self._output_weights(segments)
        for j, gi in gains.items():
            ti = lags.get(j)
            if ti is None or not (m.free[gi] and m.free[ti]):
                continue
            wins = _engagement_windows(segments, j)
            if not wins:
                continue

            def cost(g: float, tau: float, base: Array = th, gi: int = gi, ti: int = ti,
                     wins: list[Segment] = wins) -> float:
                t2 = base.copy()
                t2[gi], t2[ti] = g, tau
                x0w = [initial_state(m.structure, wn.y[0]) for wn in wins]
                r = self._residual(t2, wins, x0w, w)
                return float(r @ r)
            g0 = float(th[gi]) if th[gi] > 0 else 1.0
            t_best = float(th[ti]) if th[ti] > 0 else 0.02
            grid = sorted({float(np.clip(g0 * fg, lo[gi], hi[gi]))
                           for fg in (0.25, 0.4, 0.6, 0.8, 1.0, 1.25, 1.6, 2.5, 4.0)})
            costs = [cost(g, t_best) for g in grid]
            k = int(np.argmin(costs))
            g_best = grid[k]
            # golden-section polish between the neighbours of the best grid gain
            a_, b_ = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
            for _ in range(12):
                c1, c2 = a_ + 0.382 * (b_ - a_), a_ + 0.618 * (b_ - a_)
                if cost(c1, t_best) <= cost(c2, t_best):
                    b_ = c2
                else:
                    a_ = c1
            g_mid = 0.5 * (a_ + b_)
            if cost(g_mid, t_best) < costs[k]:
                g_best = g_mid
            th[gi], th[ti] = g_best, t_best
            self._say(f"band start {m.names[gi]} {g_best:.4g}, {m.names[ti]} {t_best:.4g} "
                      f"from {len(wins)} engagement(s)")
        return th
