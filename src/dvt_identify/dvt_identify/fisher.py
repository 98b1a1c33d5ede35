"""The Fisher rule of the identifiability check (:mod:`dvt_identify.identifiability`, rule 2):
the output sensitivities to the relative change of each parameter and to the initial states
(central differences of the full simulation), the parameters' information with the initial
states marginalised, and each parameter's inflated predicted relative std."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.simulation import OEModel
from dvt_identify.structures import initial_state

Array = NDArray[np.float64]

COLOUR_FACTOR = 10.0
"""Inflation of white-noise parameter figures for coloured OE residuals."""
MAX_RELATIVE_STD = 1.0
"""A parameter whose predicted relative std exceeds this is not determined."""
STATE_RCOND = 1e-9
"""Relative tolerance of the pseudo-inverse that marginalises the initial states: a direction
of the initial-state sensitivities with a singular value below this times the largest is one
that no output sees (it is not projected out)."""
NULL_RCOND = 1e-5
"""A direction of the marginal parameter sensitivities with a singular value at most this times
the largest is an exact null direction. Central differences with a relative step of 1e-3 leave
an error of about 1e-6 of a column (measured on the two-mass drive: the exact scale direction of
a sensor gain with the whole structure comes out at 4e-6, a parameter duplicated under another
name at 2e-8); a genuinely weak direction sits far above (the dampers to ground of the two-mass
drive, 2e-3)."""
NULL_WEIGHT = 1e-3
"""A parameter whose squared share in the null directions exceeds this lies in one (its
predicted std is infinite); below, the share is the numerical mixing of nearby directions."""


def _x0s(segs: Sequence[Segment], model: OEModel | None = None) -> list[Array]:
    y0s = [np.asarray(s.y[: min(3, s.n)].mean(axis=0), float) for s in segs]
    return y0s if model is None else [initial_state(model.structure, y) for y in y0s]


def _sensitivities(model: OEModel, theta: Array, segs: Sequence[Segment], w: Array,
                   rel_step: float = 1e-3) -> Array:
    """Columns: d(yhat/w)/d(log theta_i) for every parameter, then d/dx0 per segment. A chaotic
    output map (a rattling load) is passed as the identity except along its own parameters
    (:meth:`~dvt_identify.simulation.OEModel.passing_chaotic`, as the fit's tangents)."""
    x0s = _x0s(segs, model)
    passed = model.passing_chaotic()
    own = set(model.chaotic_parameters())

    def sim(th: Array, xs: Sequence[Array], m: OEModel = passed) -> Array:
        with np.errstate(all="ignore"):
            return np.concatenate([(m.simulate(th, s, x) / w).ravel()
                                   for s, x in zip(segs, xs, strict=True)])
    cols = []
    for i in range(theta.size):
        scale = abs(float(theta[i])) or 1.0
        h = rel_step * scale
        spec = model.specs[i]
        hi = min(theta[i] + h, spec.upper)
        lo = max(theta[i] - h, spec.lower)
        tp, tm = theta.copy(), theta.copy()
        tp[i], tm[i] = hi, lo
        if hi <= lo:
            cols.append(np.zeros(sum(s.y.size for s in segs)))
            continue
        m = model if i in own else passed
        cols.append((sim(tp, x0s, m) - sim(tm, x0s, m)) / (hi - lo) * scale)
    wx = w if model.C is None else np.full(model.nx, float(np.max(w)))  # hidden states
    for k in range(len(segs)):
        for j in range(model.nx):
            h = 1e-3 * float(wx[j])
            xp = [x.copy() for x in x0s]
            xm = [x.copy() for x in x0s]
            xp[k][j] += h
            xm[k][j] -= h
            cols.append((sim(theta, xp) - sim(theta, xm)) / (2 * h) * float(wx[j]))
    return np.asarray(np.nan_to_num(np.column_stack(cols)))


def marginal_information(J: Array, n_params: int) -> tuple[Array, Array, NDArray[np.bool_]]:
    """The parameters' information with the initial states marginalised, as an SVD.

    Args:
        J: sensitivities, shape (m, n_params + n_states): the parameters' columns first.
        n_params: number of parameter columns.

    Returns:
        ``(s, V, null)``: singular values (n_params,), right singular vectors as columns
        (n_params, n_params) of the parameter columns projected on the orthogonal complement
        of the initial-state columns (:data:`STATE_RCOND`), and which directions are null
        (:data:`NULL_RCOND`).
    """
    Jp, Jx = J[:, :n_params], J[:, n_params:]
    if Jx.shape[1]:
        U, sx, _ = np.linalg.svd(Jx, full_matrices=False)
        seen = sx > STATE_RCOND * float(sx[0]) if sx.size and sx[0] > 0 else sx > math.inf
        Ux = U[:, seen]
        Jp = Jp - Ux @ (Ux.T @ Jp)
    if Jp.shape[0] < n_params:  # fewer rows than parameters: pad, the rest is null
        Jp = np.vstack([Jp, np.zeros((n_params - Jp.shape[0], n_params))])
    _, s, Vt = np.linalg.svd(Jp, full_matrices=False)
    top = float(s[0]) if s.size else 0.0
    null = s <= NULL_RCOND * top if top > 0 else np.ones(s.size, dtype=bool)
    return np.asarray(s, float), np.asarray(Vt.T, float), np.asarray(null, bool)


def predicted_std(J: Array, n_params: int, sigma: float) -> tuple[Array, list[list[int]]]:
    """Inflated predicted relative std of each parameter (module docstring, Fisher rule) and,
    for one in a null direction (``inf``), the other parameters of that direction.

    Args:
        J: sensitivities, shape (m, n_params + n_states).
        n_params: number of parameter columns.
        sigma: residual level [output standard deviations].
    """
    s, V, null = marginal_information(J, n_params)
    Vn = V[:, null]
    weight = np.sum(Vn ** 2, axis=1)
    live = ~null
    inv = np.sum(V[:, live] ** 2 / s[live] ** 2, axis=1) if np.any(live) else np.zeros(n_params)
    rel = COLOUR_FACTOR * sigma * np.sqrt(inv)
    in_null = weight > NULL_WEIGHT
    rel = np.where(in_null, np.inf, rel)
    P = Vn @ Vn.T
    partners = [[j for j in range(n_params) if j != i and in_null[j]
                 and abs(float(P[i, j])) > NULL_WEIGHT] if in_null[i] else []
                for i in range(n_params)]
    return rel, partners

