"""The search for effects that no candidate list names (the ``unlisted`` effect).

When the named candidates leave a structured residual, the loop
(:func:`dvt_identify.loop.identify`) asks :func:`search_unlisted` for a proposal. Each
description entry ``{effect: unlisted, where: <member>}`` is a library of generic terms on that
member
(:class:`dvt_identify.effects.position.Unlisted`: signs, ``|s| s``, ``s^3``, ``cos/sin`` of shaft
and mesh orders of the member angle, products with ``sign(s)``; and the input side, an actuator
map: each listed input ``u`` times ``sign(s)``, ``s``, ``|s|`` and ``cos/sin`` of the angle, and
its powers ``|u| u`` and ``u^3``).

Every term is scored exactly like a named candidate's gain
(:func:`dvt_identify.scoring.score_candidates`): its regressor is the output sensitivity to its
coefficient at 0 (a finite difference of the full simulation), projected onto the orthogonal
complement of the current model's Jacobian. A sparse regression then picks terms: orthogonal
matching pursuit on the projected residual, adding the term most correlated with what is left,
while the added term's log-likelihood gain ``m ln(SSE_old / SSE_new)`` exceeds ``ln m + 2 ln L``
(BIC's penalty plus the risk-inflation penalty for choosing among ``L`` library terms) and at
most ``max_terms`` terms. The library whose selection explains most is proposed as one
``unlisted`` effect with the kept coefficients as its parameters; the loop refits the full
nonlinear output-error model with it and accepts it only by the same tests as every candidate
(likelihood ratio, BIC, validation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats

from dvt_identify.data import Segment
from dvt_identify.effects.base import Array, SegmentView
from dvt_identify.effects.position import Unlisted, member_motion
from dvt_identify.fit import OEFit, Progress
from dvt_identify.scoring import (
    ABSORBED,
    CandidateScore,
    candidate_theta,
    column,
    differenced_base,
    explained,
    sensitivities,
)

PROBE = 1e-3
"""RMS change of the weighted simulated outputs a term's secant step aims at."""
PROBE_BAND = (0.5, 2.0)
"""A first step whose output change is within this factor of :data:`PROBE` is the column."""


def _term_columns(fit: OEFit, segments: Sequence[Segment], lib: Unlisted,
                  base: Sequence[Array]) -> Array:
    """The scoring regressor of every library term (secant sensitivity of the weighted
    simulated outputs to its coefficient, probed for its scale like a named gain).

    The step is sized for an output change of :data:`PROBE`. A term's first step is guessed
    from the output change per unit of term force (RMS of the term's values on the data)
    that the previous term showed; when the change lands within :data:`PROBE_BAND` of the aim,
    that simulation is the column (one simulation per term instead of a unit probe and a
    sized step: the library's cost is about halved), else the step is resized from it."""
    w = fit.weights_
    model, theta = candidate_theta(fit, lib, lib.null_vector())
    off = len(fit.theta_)
    views = [SegmentView.of(s) for s in segments]
    phi = np.sqrt(np.mean(np.vstack([lib.regressors(v) for v in views]) ** 2, axis=0))
    per_force: float | None = None  # output change per unit of term force RMS
    cols = []
    for j in range(len(lib.params)):
        guessed = per_force is not None and phi[j] > 0
        h = PROBE / (per_force * float(phi[j])) if guessed and per_force else 1.0
        col = np.zeros(sum(s.n for s in segments) * w.size)
        for _ in range(8):
            col = column(model, theta, segments, fit.x0_, base, w, off + j, h)
            rms = float(np.sqrt(np.mean(col ** 2)))
            if rms > 0:
                if phi[j] > 0:
                    per_force = rms / float(phi[j])
                if not (guessed and PROBE_BAND[0] <= rms * h / PROBE <= PROBE_BAND[1]):
                    h = PROBE / rms
                    col = column(model, theta, segments, fit.x0_, base, w, off + j, h)
                break
            h *= 1e-3
        cols.append(col)
    return np.column_stack(cols)


def omp(Z: Array, e: Array, max_terms: int, penalty: float) -> tuple[list[int], list[float]]:
    """Orthogonal matching pursuit of ``e`` on the columns of ``Z``.

    Adds the column most correlated with the current residual (after orthogonalising against
    the chosen ones) while ``m ln(SSE_old / SSE_new) > penalty`` and fewer than ``max_terms``.

    Returns:
        The chosen column indices in order and the SSE after each.
    """
    m = e.size
    norms = np.linalg.norm(Z, axis=0)
    chosen: list[int] = []
    sse: list[float] = []
    r = e.copy()
    old = float(e @ e)
    Q = np.zeros((m, 0))
    while len(chosen) < max_terms:
        Zo = Z - Q @ (Q.T @ Z)
        no = np.linalg.norm(Zo, axis=0)
        ok = (no > 1e-6 * np.maximum(norms, 1e-300)) & (norms > 0)
        ok[chosen] = False
        if not np.any(ok):
            break
        score = np.where(ok, np.abs(Zo.T @ r) / np.where(ok, no, 1.0), -1.0)
        j = int(np.argmax(score))
        q = Zo[:, j] / no[j]
        new_r = r - q * float(q @ r)
        new = float(new_r @ new_r)
        if not (new > 0 and m * math.log(old / new) > penalty):
            break
        chosen.append(j)
        sse.append(new)
        Q = np.column_stack([Q, q])
        r, old = new_r, new
    return chosen, sse


def search_unlisted(fit: OEFit, segments: Sequence[Segment], libraries: Sequence[Unlisted],
                    max_terms: int = 3, progress: Progress | None = None,
                    q_mat: Array | None = None) -> CandidateScore | None:
    """Propose an ``unlisted`` effect for ``fit``'s residual on ``segments`` (its own data).

    Args:
        libraries: the description's ``unlisted`` entries (one library per member).
        max_terms: most terms kept (an entry's ``max_terms`` option overrides it).
        q_mat: orthonormal basis of the model's Jacobian (computed when ``None``).

    Returns:
        The score of the best proposal (its effect holds the kept terms with their implied
        coefficients as start values; its evidence the formula and the search), or ``None``
        when no library term passes the stopping rule.
    """
    if not libraries:
        return None
    e = fit.residual_
    m_rows = e.size
    if q_mat is None:
        q_mat, _ = np.linalg.qr(sensitivities(fit, segments))
    e_p = e - q_mat @ (q_mat.T @ e)
    ee = float(e @ e) or 1.0
    base = differenced_base(fit, segments)
    n_lib = sum(len(lib.params) for lib in libraries)
    penalty = math.log(m_rows) + 2.0 * math.log(max(n_lib, 2))
    best: CandidateScore | None = None
    searched: list[dict[str, object]] = []
    taken = set(fit.model.names)
    for lib in libraries:
        lib = lib.avoiding(taken)
        Z = _term_columns(fit, segments, lib, base)
        Zp = Z - q_mat @ (q_mat.T @ Z)
        outside = np.linalg.norm(Zp, axis=0) / np.maximum(np.linalg.norm(Z, axis=0), 1e-300)
        keep = outside > ABSORBED
        Zk = np.where(keep[None, :], Zp, 0.0)
        cap = int(lib.options.get("max_terms", max_terms))  # type: ignore[call-overload]
        idx, _ = omp(Zk, e_p, cap, penalty)
        summary: dict[str, object] = {
            "member": lib.member_name, "library_terms": len(lib.params),
            "absorbed_terms": [lib.params[i].name for i in np.flatnonzero(~keep)],
            "chosen": [lib.params[i].name for i in idx]}
        searched.append(summary)
        if not idx:
            if progress:
                progress(f"  unlisted@{lib.where}: no library term passes the stopping rule")
            continue
        k = len(idx)
        inf = np.full(k, np.inf)
        sel = np.ones(k, dtype=bool)
        r2, beta, corr = explained(Zp[:, idx], e_p, ee, -inf, inf, sel)
        r2_raw, _, corr_raw = explained(Z[:, idx], e, ee, -inf, inf, sel)
        summary["r2_projected"] = r2
        eff = lib.subset(idx, beta).avoiding(taken)
        implied = {s.name: s.initial for s in eff.params}
        lm = m_rows * r2
        score = CandidateScore(
            effect=eff, r2=r2, r2_raw=r2_raw, lm=lm, dof=k,
            p_value=float(stats.chi2.sf(lm, k)), corr=corr, corr_raw=corr_raw,
            variant="", variants=[], implied=implied)
        if progress:
            progress(f"  unlisted@{lib.where}: {eff.formula(beta)}  R2 {100 * r2:7.3f} %")
        if best is None or r2 > best.r2:
            best = score
    if best is None:
        return None
    prop = best.effect
    if not isinstance(prop, Unlisted):  # pragma: no cover - built by Unlisted.subset above
        return best
    first = segments[0]
    _, _, source = member_motion(SegmentView.of(first), prop.require_member(), prop.readout)
    best.extra.update({
        "formula": prop.formula([s.initial for s in prop.params]), "member": prop.member_name,
        "angle_source": source, **({"mesh_angles": prop.mesh_angles()}
                                   if prop.mesh_angles() else {}),
        "search": {"method": "orthogonal matching pursuit on the projected residual",
                   "stopping_rule": f"m ln(SSE_old/SSE_new) > ln m + 2 ln L = {penalty:.4g}",
                   "library_size": n_lib, "libraries": searched},
        "note": "the p-value does not account for the selection among the library terms; "
                "acceptance rests on the refit's tests"})
    return best


def propose(fit: OEFit, segments: Sequence[Segment], candidates: Sequence[object],
            progress: Progress | None = None) -> CandidateScore | None:
    """:func:`search_unlisted` over the ``unlisted`` libraries among ``candidates`` (the loop's
    remaining candidates); ``None`` when there is none or nothing passes the stopping rule."""
    libs = [c for c in candidates if isinstance(c, Unlisted) and c.library]
    return search_unlisted(fit, segments, libs, progress=progress) if libs else None
