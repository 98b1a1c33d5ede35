"""The augment loop's tests and its choice among a round's passing trials: the validation test
(Diebold-Mariano), the residual's noise floor and the share of its structured part an effect
removes, and :func:`choose` (the simplest of the trials as good on validation as the one with
the largest LR)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dvt_identify.data import Segment
from dvt_identify.effects import Effect
from dvt_identify.resid import STRUCTURED_SHARE, residual_floors
from dvt_identify.stages import Decision, Stage
from dvt_identify.uncertainty import Comparison, diebold_mariano


def lr_text(lr: float, thr: float) -> str:
    """The reason for a likelihood ratio not above its threshold. A ratio <= 0 (the refit's
    loss did not decrease: a local optimum, or the extra parameters cannot help) is shown as 0,
    "no improvement"; the raw value stays in the report's JSON (``lr``)."""
    if not lr > 0:
        return f"no improvement (LR 0 <= chi2 threshold {thr:.3g})"
    return f"LR {lr:.3g} <= chi2 threshold {thr:.3g}"


def validation_test(old: Stage, new: Stage, val: Sequence[Segment]) -> Comparison:
    """Diebold-Mariano test of ``new``'s validation simulation error against ``old``'s (loss:
    squared error per sample weighted by ``1 / std(y_j)^2``, summed over outputs)."""
    e_old = [s.y - p for s, p in zip(val, old.val_pred, strict=True)]
    e_new = [s.y - p for s, p in zip(val, new.val_pred, strict=True)]
    return diebold_mariano(e_old, e_new, weights=1.0 / old.fit.weights_ ** 2)


def stage_floors(stage: Stage, val: Sequence[Segment]) -> list[Any]:
    """Noise floor and structured share of each output's validation residual of ``stage``
    (:func:`dvt_identify.resid.residual_floors`)."""
    A, B = stage.linear()
    return residual_floors(A, B, stage.fit.model.C, val, stage.val_pred)


def at_noise_floor(floors: Sequence[Any]) -> bool:
    """Whether every output's residual has less than ``STRUCTURED_SHARE`` of its variance
    above the sensor noise floor (a share that cannot be computed counts as structured)."""
    return bool(floors) and all(f.structured_share < STRUCTURED_SHARE for f in floors)


def explained_share(old: Stage, new: Stage, val: Sequence[Segment], floors: Sequence[Any]
                    ) -> float:
    """Share of ``old``'s structured validation variance (above the noise floor, ``floors``:
    :func:`stage_floors` of ``old``) that ``new`` removes, outputs weighted by ``1 / std(y)^2``
    as in the validation test: ``sum_j (var_old_j - var_new_j) / w_j^2`` over
    ``sum_j (var_old_j - floor_j^2) / w_j^2`` (negative when ``new`` is worse; ``nan`` when
    nothing of ``old``'s residual is above the floor); at most 1 (the floor is an upper bound
    on the white part, so the structured variance a lower bound)."""
    w = old.fit.weights_
    num = den = 0.0
    for j in range(len(floors)):
        e_old = np.concatenate([(s.y - p)[:, j] for s, p in zip(val, old.val_pred, strict=True)])
        e_new = np.concatenate([(s.y - p)[:, j] for s, p in zip(val, new.val_pred, strict=True)])
        v_old, v_new = float(np.var(e_old)), float(np.var(e_new))
        floor = float(floors[j].floor_rms) ** 2
        if not (math.isfinite(v_old) and math.isfinite(v_new) and math.isfinite(floor)):
            continue
        num += (v_old - v_new) / w[j] ** 2
        den += max(v_old - floor, 0.0) / w[j] ** 2
    return min(num / den, 1.0) if den > 0 else math.nan


def shape_parameters(effect: Effect) -> tuple[str, ...]:
    """Names of ``effect``'s estimated shape parameters: those that are neither gains
    (:meth:`Effect.gain_names`: the effect vanishes at their null values and the scorer
    regresses on them) nor held fixed (:meth:`Effect.fixed_names`). A shape parameter (a
    Stribeck speed, a contact frequency, a damping ratio) enters the model nonlinearly and only
    shapes an effect a gain makes present; the scorer scans it instead of regressing on it."""
    plain = set(effect.gain_names()) | set(effect.fixed_names())
    return tuple(s.name for s in effect.params if s.name not in plain)


@dataclass(frozen=True)
class Choice:
    """Which of a round's passing trials is accepted (:func:`choose`).

    Attributes:
        chosen: the trial to accept.
        largest_lr: the passing trial with the largest LR (the reference of the tie test).
        tied: the passing trials as good on validation as ``largest_lr`` (it included), in
            input order.
        comparisons: for each passing trial, in input order, the Diebold-Mariano test of
            ``largest_lr``'s validation error against the trial's (:func:`validation_test`
            with the trial as the old model; ``None`` for ``largest_lr`` itself).
        losers: every other passing trial, in input order, with why it lost (a clause that
            reads after "passes (...) but").
    """

    chosen: Decision
    largest_lr: Decision
    tied: list[Decision]
    comparisons: list[Comparison | None]
    losers: list[tuple[Decision, str]]

    @property
    def p_values(self) -> list[float]:
        """One-sided p-value of ``largest_lr``'s validation error being smaller than each
        trial's, in input order (1 for ``largest_lr`` itself)."""
        return [1.0 if c is None else c.p_value for c in self.comparisons]


def complexity(d: Decision) -> tuple[int, int]:
    """A trial's complexity: (estimated parameters it adds, estimated shape parameters among
    them, :func:`shape_parameters`); smaller is simpler, compared in that order."""
    return d.dof, len(shape_parameters(d.score.effect))


def choose(passing: Sequence[Decision], val: Sequence[Segment], alpha: float) -> Choice:
    """Choose the trial to accept among a round's passing trials (all refitted from the same
    model): the simplest of those as good on validation as the one with the largest LR.

    The trial with the largest LR is the reference. A trial is *tied* with it when the
    reference's validation error is not significantly smaller than the trial's (one-sided
    Diebold-Mariano test at ``alpha``, :func:`validation_test`; in cross-validated selection
    ``val`` are the estimation segments and the stages' ``val_pred`` are out of fold). Among
    the tied trials the chosen one has the fewest added estimated parameters, then the fewest
    shape parameters (:func:`complexity`), then the largest LR. Two laws that fit the data
    equally well (e.g. a plain Coulomb friction and a Stribeck friction with a fitted
    Stribeck speed, both two parameters, so BIC cannot tell them apart) are then told apart
    by parsimony instead of by a likelihood difference within the noise; a richer law that is
    significantly better on validation is still chosen.

    Args:
        passing: the passing trials (each with its refitted ``stage``).
        val: the validation segments the stages were simulated on.
        alpha: significance level of the tie test.

    Raises:
        ValueError: ``passing`` is empty, or a trial has no refitted stage (naming it).
    """
    if not passing:
        raise ValueError("choose: no passing trial to choose from")
    stages: dict[int, Stage] = {}
    for d in passing:
        if d.stage is None:
            raise ValueError(f"choose: trial {d.score.label} has no refitted stage (its refit "
                             f"failed: {d.reason})")
        stages[id(d)] = d.stage
    ref = max(passing, key=lambda d: d.lr)
    cmp: dict[int, Comparison | None] = {
        id(d): None if d is ref else validation_test(stages[id(d)], stages[id(ref)], val)
        for d in passing}
    tied_ids = {k for k, c in cmp.items() if c is None or not c.better(alpha)}
    tied = [d for d in passing if id(d) in tied_ids]
    chosen = min(tied, key=lambda d: (*complexity(d), -d.lr))
    losers = [(d, _lost(d, chosen, ref, id(d) in tied_ids, cmp))
              for d in passing if d is not chosen]
    return Choice(chosen=chosen, largest_lr=ref, tied=tied,
                  comparisons=[cmp[id(d)] for d in passing], losers=losers)


def _simpler(c: Decision, d: Decision) -> str | None:
    """How trial ``c`` is simpler than ``d`` (:func:`complexity`), or ``None`` if it is not."""
    kc, sc = complexity(c)
    kd, sd = complexity(d)
    if kc < kd:
        return f"{kc} estimated parameter{'s' * (kc != 1)} instead of {kd}"
    if kc == kd and sc < sd:
        d_shape = ", ".join(shape_parameters(d.score.effect))
        if sc == 0:
            return f"no shape parameter; this one fits {d_shape}"
        return f"{sc} shape parameter{'s' * (sc != 1)} instead of {sd} ({d_shape})"
    return None


def _p(c: Comparison | None) -> float:
    """A tie test's p-value (1 for the reference itself, ``None``)."""
    return 1.0 if c is None else c.p_value


def _dm(c: Comparison | None) -> str:
    """A tie test's figures: the reference's validation error relative to the trial's and the
    Diebold-Mariano p-value."""
    if c is None:
        return "Diebold-Mariano p = 1"
    return (f"error {-100 * c.relative_gain:+.3g} % against it, Diebold-Mariano "
            f"p = {c.p_value:.2g}")


def _lost(d: Decision, c: Decision, ref: Decision, tied: bool,
          cmp: dict[int, Comparison | None]) -> str:
    """Why passing trial ``d`` lost to the chosen ``c`` (``ref``: the largest LR; ``tied``:
    ``d`` is as good on validation as ``ref``; ``cmp``: the tie tests by ``id``, the
    reference's validation error against each trial's)."""
    lab, ref_lab = c.score.label, ref.score.label
    p_c, p_d = _p(cmp[id(c)]), _p(cmp[id(d)])
    simp = _simpler(c, d)
    if c is ref:
        why = f"{lab} has the larger LR ({c.lr:.4g} > {d.lr:.4g})"
        if not tied:
            return f"{why} and is significantly better on validation ({_dm(cmp[id(d)])})"
        return f"{why} and is simpler ({simp})" if simp else why
    if d is ref:
        return (f"{lab} is as good on validation (Diebold-Mariano p = {p_c:.2g}) and simpler "
                f"({simp}), at a smaller LR ({c.lr:.4g} < {d.lr:.4g})")
    if not tied:
        return (f"the largest-LR {ref_lab} is significantly better on validation "
                f"({_dm(cmp[id(d)])}), and {lab} is as good as it (p = {p_c:.2g}) and simpler")
    why = (f"{lab} is, like this one, as good on validation as the largest-LR {ref_lab} "
           f"(Diebold-Mariano p = {p_c:.2g}; this one {p_d:.2g})")
    return (f"{why} and simpler ({simp})" if simp
            else f"{why} and has the larger LR ({c.lr:.4g} > {d.lr:.4g})")
