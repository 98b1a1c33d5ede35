"""Candidate scoring: what an effect would explain of a fitted model's residual.

A candidate's regressors are the output sensitivities to its gain parameters at their null
values (central/secant differences of the full simulation: exactly the Jacobian columns it
would add). Regressors and residual are projected onto the orthogonal complement of the current
model's Jacobian (all its parameters and initial states, :func:`sensitivities`), so only what
the model cannot already explain counts. Evidence (:class:`CandidateScore`): the fraction
``R^2`` of the residual sum of squares the projected regressors explain (the rank key), the
Lagrange-multiplier statistic ``LM = m R^2`` with its chi2 p-value, the raw correlation before
projection, the implied gain, and each effect's own evidence (delay scan, order spectrum,
signatures). Used by the augment loop (:mod:`dvt_identify.loop`) and the ``unlisted`` term
search (:mod:`dvt_identify.unlisted`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import stats
from scipy.linalg import solve_triangular
from scipy.optimize import lsq_linear

from dvt_identify.data import Segment
from dvt_identify.effects import Effect, ScoringContext, SegmentView
from dvt_identify.errors import FitError
from dvt_identify.fit import OEFit, Progress
from dvt_identify.parallel import fork_map
from dvt_identify.simulation import DivergedError, OEModel

Array = NDArray[np.float64]
ABSORBED = 0.02
"""A regressor with less than this share of its norm outside the model's span is absorbed
(the most the rule asks: a model whose own sensitivities are numerically rough, e.g. a stick
rule's switching, keeps this margin)."""
ABSORBED_MIN = 2e-3
"""The least share outside the span that counts, whatever the numerical floor."""
NOISE_MARGIN = 5.0
"""A regressor counts when its share outside the span exceeds this many times the numerical
floor (:func:`absorbed_threshold`)."""


def absorbed_threshold(fit: OEFit, segments: Sequence[Segment], span: ModelSpan,
                       base: Sequence[Array], most: int = 3) -> float:
    """The share of a regressor's norm outside the model's span below which it is absorbed.

    A candidate's columns are one-sided differences of the full simulation, as are the model's
    own sensitivities (:func:`sensitivities`: central); a column of the model's own, made the
    candidate's way, lies in the span up to numerical error (the simulation's non-smoothness,
    the difference step), so its share outside the span is the numerical floor. The threshold
    is :data:`NOISE_MARGIN` times the largest floor of the ``most`` most sensitive free
    parameters, within [:data:`ABSORBED_MIN`, :data:`ABSORBED`]: a smooth model (a smoothed
    dry friction) tells a regressor 1.6 % outside the span from noise (measured on EMPS:
    direction-dependent viscous friction next to Coulomb friction with an offset, 47 % of the
    residual), a stick rule keeps the 2 % margin."""
    m = fit.model.passing_chaotic()
    w = fit.weights_
    free = np.flatnonzero(m.free)
    if free.size == 0:
        return ABSORBED
    order = np.argsort([-abs(float(fit.theta_[i])) for i in free])[:most]
    floor = 0.0
    for k in order:
        i = int(free[k])
        h = 1e-4 * max(abs(float(fit.theta_[i])), 1e-8)
        spec = m.specs[i]
        if fit.theta_[i] + h > spec.upper:
            h = -h
        col = column(m, fit.theta_, segments, fit.x0_, base, w, i, h)
        nrm = float(np.linalg.norm(col))
        if nrm == 0.0:
            continue
        out = float(np.linalg.norm(span.complement(col))) / nrm
        floor = max(floor, out)
    return float(np.clip(NOISE_MARGIN * floor, ABSORBED_MIN, ABSORBED))


@dataclass
class CandidateScore:
    """Score of one candidate against a model's residual (see module docstring).

    Attributes:
        effect: the candidate with initial values set from the score (implied gains, best
            shape variant) for the refit.
        r2: fraction of the residual sum of squares explained after projection (rank key).
        r2_raw: the same without projection.
        lm, dof, p_value: Lagrange-multiplier statistic, its degrees of freedom and p-value.
        corr: signed correlation (single regressor) or multiple correlation after projection.
        corr_raw: the same before projection.
        variant: chosen shape variant; variants: every variant's r2.
        extra: delay scan, order spectrum, ...
    """

    effect: Effect
    r2: float
    r2_raw: float
    lm: float
    dof: int
    p_value: float
    corr: float
    corr_raw: float
    variant: str
    variants: list[dict[str, object]]
    implied: dict[str, float]
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """``name@where``."""
        return self.effect.label()

    def evidence(self) -> dict[str, object]:
        """JSON-ready evidence."""
        out: dict[str, object] = {
            "r2_projected": self.r2, "r2_raw": self.r2_raw,
            "predicted_sse_reduction_percent": 100.0 * self.r2,
            "lm_statistic": self.lm, "dof": self.dof, "p_value": self.p_value,
            "correlation_projected": self.corr, "correlation_raw": self.corr_raw,
            "implied_parameters": self.implied,
        }
        if self.variant:
            out["variant"] = self.variant
            out["variants"] = self.variants
        out.update(self.extra)
        return out


def candidate_theta(fit: OEFit, cand: Effect, values: Array) -> tuple[OEModel, Array]:
    """The model a candidate's columns difference (the fit's, its chaotic output maps passed
    as the identity: :meth:`~dvt_identify.simulation.OEModel.passing_chaotic`; the candidate's
    own map kept) and its parameters (the fit's, then ``values``)."""
    model = OEModel(fit.model.structure, (*fit.model.passing_chaotic().effects, cand))
    return model, np.concatenate([fit.theta_, values])


def differenced_base(fit: OEFit, segments: Sequence[Segment]) -> list[Array]:
    """The outputs (each (N, ny)) the scoring columns are differences from: the fit's model at
    its parameters, its chaotic output maps passed as the identity (a rattling load's
    divergence is no regressor; the fit's own residual keeps them)."""
    m = fit.model.passing_chaotic()
    return [m.simulate(fit.theta_, s, x0) for s, x0 in zip(segments, fit.x0_, strict=True)]


def column(model: OEModel, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array],
            base: Sequence[Array], w: Array, idx: int, h: float,
            states: Sequence[Array] | None = None) -> Array:
    """The scoring column of parameter ``idx``: the weighted output change per unit of a step
    ``h`` from ``theta``, over every segment stacked, shape (sum N ny,); zeros where the
    probe diverges. ``states`` (each (N, nx)): the segments' states at ``theta``, for a
    parameter that moves no state (:meth:`~dvt_identify.effects.Effect.output_only`): then
    only the output maps are evaluated again."""
    th = theta.copy()
    th[idx] += h
    parts = []
    for k, (seg, x0, y0) in enumerate(zip(segments, x0s, base, strict=True)):
        try:
            with np.errstate(all="ignore"):
                yh = (model.simulate(th, seg, x0) if states is None
                      else model.outputs_of(th, seg, states[k]))
        except DivergedError:  # the probe left the simulable region: no information
            return np.zeros(sum(s.y.size for s in segments))
        parts.append(((yh - y0) / w).ravel() / h)
    col = np.concatenate(parts)
    return col if np.all(np.isfinite(col)) else np.zeros_like(col)


def _states(model: OEModel, theta: Array, segments: Sequence[Segment], x0s: Sequence[Array]
            ) -> list[Array] | None:
    """Each segment's simulated states (N, nx) at ``theta``; ``None`` where a simulation
    diverges (the columns then simulate each probe and score it 0)."""
    try:
        with np.errstate(all="ignore"):
            return [model.simulate_states(theta, s, x0)[0]
                    for s, x0 in zip(segments, x0s, strict=True)]
    except DivergedError:
        return None


def score_candidates(fit: OEFit, segments: Sequence[Segment], candidates: Sequence[Effect],
                     progress: Progress | None = None) -> list[CandidateScore]:
    """Score ``candidates`` against ``fit``'s residual on ``segments`` (the fit's own data);
    returns them ranked by projected ``R^2``, strongest first."""
    e = fit.residual_
    m_rows = e.size
    span = model_span(fit, segments)
    e_p = span.complement(e)
    ee = float(e @ e) or 1.0
    w = fit.weights_
    base = [fit.model.simulate(fit.theta_, s, x0) for s, x0 in zip(segments, fit.x0_,
                                                                     strict=True)]
    diffed = base if fit.model.passing_chaotic() is fit.model else differenced_base(fit,
                                                                                   segments)
    absorbed = absorbed_threshold(fit, segments, span, diffed)
    coarsest = max(segments, key=lambda s: s.dt)  # shape variants the slowest rate can show
    view = SegmentView.of(coarsest)
    ctx = ScoringContext(
        views=[SegmentView.of(s) for s in segments], simulated=base,
        weights=w,
        member_residual=lambda member: member_force_residual(fit, segments[0], member))

    def score_one(cand: Effect) -> CandidateScore:
        t0 = time.monotonic()
        best: CandidateScore | None = None
        variants: list[dict[str, object]] = []
        states: list[Array] | None = None
        one_simulation = cand.output_only()
        for vlabel, shape in cand.variants(view):
            null = cand.null_vector()
            # a variant value for a gain is its secant probe (an effect that is not
            # differentiable at its null, e.g. play); for a shape parameter, its value
            probes = {n: v for n, v in shape.items() if n in cand.gain_names()}
            for name, v in shape.items():
                if name not in probes:
                    null[cand.pindex(name)] = v
            model, theta = candidate_theta(fit, cand, null)
            off = len(fit.theta_)
            if one_simulation:
                # its parameters move no state: one simulation serves every variant and gain
                # (a compliant play scans 80 variants)
                states = _states(model, theta, segments, fit.x0_)
                one_simulation = False
            cols, steps = [], []
            for gname in cand.gain_names():
                gi = cand.pindex(gname)
                spec = cand.params[gi]
                fixed_step = cand.scoring_step(gname, segments[0].dt)
                if fixed_step is not None:
                    h = fixed_step
                elif gname in probes:
                    h = probes[gname]
                elif spec.step is not None:
                    h = spec.step
                else:
                    # probe for the scale of the gain: a unit step can make the simulation blow
                    # up (e.g. quadratic drag at hundreds of rad/s), so shrink until it is finite
                    h = 1.0
                    for _ in range(8):
                        col = column(model, theta, segments, fit.x0_, diffed, w, off + gi, h,
                                     states)
                        rms = float(np.sqrt(np.mean(col ** 2)))
                        if rms > 0:
                            h = 1e-3 / rms
                            break
                        h *= 1e-3
                if null[gi] + h > spec.upper:
                    h = -h
                cols.append(column(model, theta, segments, fit.x0_, diffed, w, off + gi, h,
                                   states))
                steps.append(h)
            Z = np.column_stack(cols)
            Zp = span.complement(Z)
            gains = [cand.pindex(g) for g in cand.gain_names()]
            lb = np.array([cand.params[i].lower - null[i] for i in gains])
            ub = np.array([cand.params[i].upper - null[i] for i in gains])
            outside = np.linalg.norm(Zp, axis=0) / np.maximum(np.linalg.norm(Z, axis=0), 1e-300)
            keep = outside > absorbed
            r2, beta, corr = explained(Zp, e_p, ee, lb, ub, keep)
            r2_raw, _, corr_raw = explained(Z, e, ee, lb, ub, keep)
            variants.append({"variant": vlabel, "r2_projected": r2,
                             "fraction_outside_model_span": outside.tolist(),
                             "absorbed_below": absorbed})
            if best is None or r2 > best.r2:
                # a probed gain starts the refit at its probe (the size whose effect was
                # scored) when the effect fits with the right sign
                implied = {cand.params[cand.pindex(g)].name:
                           float(probes[g] if g in probes and b > 0 else null[cand.pindex(g)] + b)
                           for g, b in zip(cand.gain_names(), beta, strict=True)}
                for name, v in shape.items():
                    if name not in probes:
                        implied[name] = float(v)
                dof = Z.shape[1]
                lm = m_rows * r2
                best = CandidateScore(
                    effect=cand.with_initial(implied), r2=r2, r2_raw=r2_raw, lm=lm, dof=dof,
                    p_value=float(stats.chi2.sf(lm, dof)), corr=corr, corr_raw=corr_raw,
                    variant=vlabel, variants=variants, implied=implied)
        if best is None:
            raise FitError(f"{cand.label()}: no variant to score (its variants() is empty)")
        best.variants = variants
        extra, start = cand.scoring_evidence(ctx)
        best.extra.update(extra)
        if start:
            best.effect = best.effect.with_initial(start)
            best.implied.update(start)
        if progress:
            progress(f"  score {best.label:<40s} R2 {100 * best.r2:7.3f} %  "
                     f"({time.monotonic() - t0:.1f} s)")
        return best
    # the candidates are independent: shared between the cores (dvt_identify.parallel), by
    # their cost: a simulation of every segment per variant and gain (a compliant play scans
    # 80 variants where a Coulomb friction has one)
    cands = list(candidates)
    costs = [len(c.variants(view)) * max(1, len(c.gain_names())) for c in cands]
    scores = fork_map(score_one, cands, costs=costs)
    scores.sort(key=lambda s: s.r2, reverse=True)
    return scores


def member_force_residual(fit: OEFit, seg: Segment, member: Array) -> Array:
    """The OE residual of ``seg`` mapped back to a force on ``member``: ``g = F^-1 (e' - A e)``
    (generalised force, ``e'`` by central differences), ``tau = c.g / c.c``; shape (N,).

    A disturbance force appears here as itself instead of filtered by the model's dynamics."""
    i = next((k for k, s in enumerate(fit.segments_) if s is seg), 0)
    A, _, F = fit.model.structure.matrices(fit.theta_[: fit.model.n_struct])
    yh = fit.model.simulate(fit.theta_, seg, fit.x0_[i])
    e = seg.y - yh
    if fit.model.C is not None:  # hidden states: the residual does not give every state
        return np.full(seg.n, np.nan)
    de = np.gradient(e, seg.dt, axis=0)
    g = np.linalg.solve(F, (de - e @ A.T).T).T
    return np.asarray(g @ member / float(member @ member))


def explained(Z: Array, e: Array, ee: float, lb: Array, ub: Array, keep: NDArray[np.bool_]
                ) -> tuple[float, Array, float]:
    """Bounded LS of ``e`` on the kept columns of ``Z`` (coefficients within ``[lb, ub]``):
    (the sum of squares the columns remove from ``e``, as a fraction of ``ee``; coefficients (0
    for dropped columns); correlation: signed for a single column, else the multiple
    correlation).

    ``e`` may be the residual projected off the model's span and ``ee`` the full residual's sum
    of squares: only what the columns remove from ``e`` itself counts. (Measured ``ee - |e -
    Z b|^2`` instead, every candidate was credited with the part of the residual the model's
    own sensitivities hold - non-zero at a bound-constrained or non-smooth optimum - e.g. the
    same 18.5 % for windage, backlash and delay, which buried the true 0.3 % of Coulomb
    friction on a second member.)"""
    beta = np.zeros(Z.shape[1])
    norms = np.linalg.norm(Z, axis=0)
    use = keep & (norms > 0)
    if not np.any(use):
        return 0.0, beta, 0.0
    Zk = Z[:, use] / norms[use]
    lo, hi = lb[use] * norms[use], ub[use] * norms[use]
    # the same bounded LS on the k x k triangular factor (||e - Z b||^2 = ||Q^T e - R b||^2 +
    # const): one QR instead of iterating on the m x k matrix (measured: 0.2 s -> ms a call),
    # solved exactly when the bounds are not active (_bounded_ls)
    qz, rz = np.linalg.qr(Zk)
    x = _bounded_ls(rz, qz.T @ e, np.minimum(lo, 0.0), np.maximum(hi, 0.0))
    beta[use] = x / norms[use]
    res = e - Zk @ x
    r2 = min(max((float(e @ e) - float(res @ res)) / ee, 0.0), 1.0)
    if Z.shape[1] == 1:
        corr = float(Zk[:, 0] @ e) / math.sqrt(ee)
    else:
        corr = math.sqrt(r2)
    return r2, beta, corr


def _bounded_ls(R: Array, b: Array, lo: Array, hi: Array) -> Array:
    """``argmin |R x - b|`` for ``lo <= x <= hi`` with ``R`` (k, k) upper triangular: the
    unconstrained solution when it is within the bounds (then it is the bounded one), the
    clipped one for one column, else ``scipy.optimize.lsq_linear`` (as for a nearly singular
    ``R``)."""
    d = np.abs(np.diag(R))
    if d.size and float(np.min(d)) > 1e-10 * float(np.max(d)):
        x = solve_triangular(R, b)
        if np.all(x >= lo) and np.all(x <= hi):
            return np.asarray(x, float)
        if x.size == 1:
            return np.asarray(np.clip(x, lo, hi), float)
    return np.asarray(lsq_linear(R, b, bounds=(lo, hi)).x, float)


def _secants(fit: OEFit, segments: Sequence[Segment], rel_step: float = 1e-4
             ) -> tuple[Array, list[Array]]:
    """The central-difference sensitivities of :func:`sensitivities`, in two parts: the free
    parameters' columns over all segments (m, p) and each segment's initial-state columns over
    its own rows (m_k, nx) (they are zero elsewhere; a segment's initial state is differenced
    by simulating that segment alone)."""
    m = fit.model.passing_chaotic()
    w = fit.weights_
    theta = fit.theta_
    free = np.flatnonzero(m.free)
    rows = sum(s.y.size for s in segments)

    def sim(th: Array, segs: Sequence[Segment], x0s: Sequence[Array]) -> Array:
        try:
            with np.errstate(all="ignore"):
                return np.concatenate([(m.simulate(th, s, x0) / w).ravel()
                                       for s, x0 in zip(segs, x0s, strict=True)])
        except DivergedError:  # a step off a bound-hugging optimum (M22 at 1e-6): the
            # column becomes 0 below (nan_to_num), i.e. no direction the model can absorb
            return np.full(sum(s.y.size for s in segs), np.nan)
    Jp = np.zeros((rows, free.size))
    for col, i in enumerate(free):
        h = rel_step * max(abs(float(theta[i])), 1e-8)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        Jp[:, col] = (sim(tp, segments, fit.x0_) - sim(tm, segments, fit.x0_)) / (2 * h)
    wx = w if m.C is None else np.full(m.nx, float(np.max(w)))  # hidden states: output scale
    Jx = []
    for k, seg in enumerate(segments):
        block = np.zeros((seg.y.size, m.nx))
        for j in range(m.nx):
            h = rel_step * max(float(wx[j]), 1e-12) * 10.0
            xp, xm = fit.x0_[k].copy(), fit.x0_[k].copy()
            xp[j] += h
            xm[j] -= h
            block[:, j] = (sim(theta, [seg], [xp]) - sim(theta, [seg], [xm])) / (2 * h)
        Jx.append(np.nan_to_num(block, copy=False))
    return np.nan_to_num(Jp, copy=False), Jx


def sensitivities(fit: OEFit, segments: Sequence[Segment], rel_step: float = 1e-4) -> Array:
    """Jacobian of the weighted simulated outputs with respect to the free parameters and the
    initial states, by central differences with a relative step (secant sensitivities, smoother
    than the fit's own Jacobian when dry friction makes the simulation non-smooth, and made the
    way the candidates' regressors are: measured with the exact tangents instead, a second
    engagement lag on a band scored 0.40 % of the residual at p = 7e-15 where its secant is
    absorbed, 0.02 %). A step that cannot be simulated gives a zero column.

    Returns:
        Shape (m, q), rows ordered like ``fit.residual_``.
    """
    Jp, Jx = _secants(fit, segments, rel_step)
    nx = fit.model.nx
    J = np.zeros((Jp.shape[0], Jp.shape[1] + len(segments) * nx))
    J[:, : Jp.shape[1]] = Jp
    r0 = 0
    for k, block in enumerate(Jx):
        J[r0: r0 + block.shape[0], Jp.shape[1] + k * nx: Jp.shape[1] + (k + 1) * nx] = block
        r0 += block.shape[0]
    return J


@dataclass
class ModelSpan:
    """The span of a fit's sensitivities (:func:`sensitivities`) kept by its parts: each
    segment's initial-state directions over its own rows (orthonormal ``local[k]`` (m_k, nx)),
    and the free parameters' directions with those removed (orthonormal ``params`` (m, p)).
    The two parts are orthogonal and together span the whole Jacobian, so the projection off
    the span is the same as with the Jacobian's QR factor, without an (m, p + segments nx)
    matrix (an hour in ten-minute segments: 1.4 million rows by 26 columns, twice)."""

    params: Array
    local: list[Array]
    rows: list[slice]

    def complement(self, Z: Array) -> Array:
        """``Z`` (m,) or (m, k) with its component in the span removed."""
        out = np.array(Z, dtype=float, copy=True)
        for Q, rs in zip(self.local, self.rows, strict=True):
            out[rs] -= Q @ (Q.T @ out[rs])
        return out - self.params @ (self.params.T @ out)


def _orth(M: Array) -> Array:
    """An orthonormal basis of the columns of ``M`` (its thin QR factor ``Q``)."""
    Q, _ = np.linalg.qr(M)
    return np.asarray(Q)


def model_span(fit: OEFit, segments: Sequence[Segment]) -> ModelSpan:
    """The span of ``fit``'s sensitivities on ``segments`` (:class:`ModelSpan`)."""
    Jp, Jx = _secants(fit, segments)
    rows = []
    local = []
    r0 = 0
    for block in Jx:
        rs = slice(r0, r0 + block.shape[0])
        Q = _orth(block)
        Jp[rs] -= Q @ (Q.T @ Jp[rs])
        rows.append(rs)
        local.append(Q)
        r0 = rs.stop
    return ModelSpan(params=_orth(Jp), local=local, rows=rows)
