"""The augment loop's records (:func:`dvt_identify.loop.identify`): its options
(:class:`LoopConfig`), a fitted model with its figures (:class:`Stage`, evaluated by
:func:`make_stage`), one candidate refit's outcome (:class:`Decision`) and everything the report
needs (:class:`IdentificationResult`); and the leave-one-bag-out folds of cross-validated
selection (:func:`cv_folds`, :func:`fold_fits`)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.description import Description, FitOptions
from dvt_identify.drift import DriftReport
from dvt_identify.effects import Effect
from dvt_identify.errors import FitError
from dvt_identify.fit import OEFit
from dvt_identify.identifiability import Identifiability
from dvt_identify.linref import ReferenceStage
from dvt_identify.metrics import Figures, figures
from dvt_identify.resid import (
    OutputResidual,
    Spectrum,
    residual_analysis,
    residual_spectrum,
)
from dvt_identify.scoring import CandidateScore
from dvt_identify.uncertainty import Comparison

Array = NDArray[np.float64]
MIN_EXPLAINED = 0.10
"""Least share of the validation residual's structured variance (above the sensor noise floor)
an accepted effect must remove (rule (d) of the module docstring)."""
LIKELY_GAIN = 0.2
"""A candidate whose refit cuts the validation loss by at least this share (relative), is
admissible and removes at least :data:`MIN_EXPLAINED` of the structured residual, but misses
significance (the validation test, or LR/BIC on the estimation data) is reported as "likely,
not proven" with its figures (short records: the test lacks the samples, not the effect the
size)."""


@dataclass(frozen=True)
class LoopConfig:
    """Options of :func:`identify`.

    Attributes:
        starts: starts of the baseline fit.
        refit_starts: starts of each candidate refit (the first from the current optimum plus
            the candidate's implied gain).
        alpha: significance level of the LM screen, the LR test and the validation test.
        min_validation_gain: an optional floor on the mean validation fit gain [% points]
            on top of the validation test (default 0: none; the description's
            ``fit.min_validation_gain`` is not used, the test replaces it).
        drift_windows: windows of the drift check (< 3: no check).
        drift_min_change: smallest relative change over the recording called a drift.
        max_effects: most effects accepted.
        max_tries_per_round: candidates refitted per round before giving up.
        augment: run the augment loop (False: baseline only).
        lags: residual-analysis lags.
        seed: random seed of the multi-start perturbations.
        fit_decimate: decimation of the estimation data for fitting/scoring.
        init_window: 0: each segment's initial state is estimated (free in the fit, from the
            segment's start with the parameters fixed elsewhere); ``n > 0``: every
            simulation starts from the state its first ``n`` samples give, in the fit, the
            selection and the test alike (:class:`~dvt_identify.fit.OEFit`).
        reference: fit the black-box linear reference beside the physical model
            (:mod:`dvt_identify.linref`), score it the same way and start the physical fit
            also from the structure its frequency response maps to.
        reference_max_order: highest order of the linear reference.
    """

    starts: int = 4
    refit_starts: int = 2
    alpha: float = 0.01
    min_validation_gain: float = 0.0
    max_effects: int = 4
    max_tries_per_round: int = 3
    augment: bool = True
    lags: int = 25
    seed: int = 0
    fit_decimate: int = 1
    drift_windows: int = 4
    drift_min_change: float = 0.10
    init_window: int = 0
    reference: bool = True
    reference_max_order: int = 4

    @classmethod
    def from_options(cls, opts: FitOptions, fit_decimate: int = 1) -> LoopConfig:
        """Config from a description's ``fit`` section (override fields with
        :func:`dataclasses.replace`)."""
        return cls(starts=opts.starts, refit_starts=opts.refit_starts, alpha=opts.alpha,
                   max_effects=opts.max_effects,
                   max_tries_per_round=opts.max_tries_per_round, seed=opts.seed,
                   fit_decimate=fit_decimate)


@dataclass
class Stage:
    """A fitted model with its figures on estimation (full rate) and validation data.

    Attributes:
        label: ``baseline`` or ``+effect@where``.
        fit: the :class:`OEFit`.
        est, val: :class:`Figures` on estimation / validation data.
        est_pred, val_pred: simulated outputs per segment.
        val_x0: estimated initial states of the validation segments.
        resid_est, resid_val: residual analyses.
        spectrum_val: residual spectrum of each output on validation data.
        folds: with cross-validated selection, the model refitted without each estimation
            bag in turn (:func:`cv_folds` order); its ``val_pred`` are their out-of-sample
            simulations of the left-out bags. After a holdout choice refitted on the whole
            segments (:func:`dvt_identify.loop.refit_whole`): the one fit on their first
            parts, which simulated the held-out ends. Empty otherwise.
    """

    label: str
    fit: OEFit
    est: Figures
    val: Figures
    est_pred: list[Array]
    val_pred: list[Array]
    val_x0: list[Array]
    resid_est: list[OutputResidual]
    resid_val: list[OutputResidual]
    spectrum_val: list[Spectrum]
    folds: list[OEFit] = field(default_factory=list)

    @property
    def effects(self) -> tuple[Effect, ...]:
        """Effects in the model."""
        return self.fit.model.effects

    def parameters(self) -> dict[str, float]:
        """Physical parameters by name."""
        return self.fit.parameters()

    def linear(self) -> tuple[Array, Array]:
        """``A``, ``B`` of the linear part."""
        A, B, _ = self.fit.model.structure.matrices(self.fit.theta_[: self.fit.model.n_struct])
        return A, B


@dataclass
class Decision:
    """Outcome of one candidate refit.

    Attributes:
        round: 1-based round.
        score: the score that put the candidate forward.
        accepted: whether it was added.
        reason: plain-text reason.
        lr, lr_threshold, dof: likelihood-ratio statistic, chi2 threshold, added parameters.
        delta_bic: BIC(new) - BIC(old) on the estimation (fit) data.
        val_fit_before, val_fit_after: mean validation fit [%].
        validation: Diebold-Mariano comparison of the validation errors (before vs after).
        stage: the refitted model (``None`` if the refit failed).
        explained_share: share of the validation residual's structured variance the effect
            removed (:func:`~dvt_identify.selection.explained_share`; rule (d)).
        likely: rejected only for want of significance although its gain is large
            (:data:`LIKELY_GAIN`): "likely, not proven".
        removed_in: the round whose recheck took it out again (a later effect explains it;
            ``accepted`` is then false), else ``None``.
    """

    round: int
    score: CandidateScore
    accepted: bool
    reason: str
    lr: float = math.nan
    lr_threshold: float = math.nan
    dof: int = 0
    delta_bic: float = math.nan
    val_fit_before: float = math.nan
    val_fit_after: float = math.nan
    validation: Comparison | None = None
    stage: Stage | None = None
    explained_share: float = math.nan
    likely: bool = False
    removed_in: int | None = None

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (with the validation test's gain, statistic and p-value)."""
        out: dict[str, object] = {
            "round": self.round, "candidate": self.score.label, "accepted": self.accepted,
            "reason": self.reason, "lr": self.lr, "lr_threshold": self.lr_threshold,
            "dof": self.dof, "delta_bic": self.delta_bic,
            "validation_fit_before": self.val_fit_before,
            "validation_fit_after": self.val_fit_after,
            "validation_fit_gain": self.val_fit_after - self.val_fit_before,
            "explained_share": self.explained_share if math.isfinite(self.explained_share)
            else None, "min_explained_share": MIN_EXPLAINED,
            "likely_not_proven": self.likely, "removed_in_round": self.removed_in}
        if self.validation is not None:
            v = self.validation
            out["validation_test"] = {
                "test": "Diebold-Mariano, one-sided, HAC (Bartlett) variance",
                "loss_reduction_relative": v.relative_gain, "loss_reduction": v.gain,
                "statistic": v.stat, "p_value": v.p_value, "bandwidth": v.bandwidth}
        return out


@dataclass
class IdentificationResult:
    """Everything the report needs."""

    description: Description
    estimation_bags: list[str]
    validation_bags: list[str]
    baseline: Stage
    final: Stage
    rounds: list[list[CandidateScore]]
    decisions: list[Decision]
    config: LoopConfig
    seconds: float
    fit_dt: float
    notes: list[str]
    val_segments: list[Segment] = field(default_factory=list)
    identifiability: Identifiability | None = None
    drift: DriftReport | None = None
    data_warnings: list[str] = field(default_factory=list)
    est_segments: list[Segment] = field(default_factory=list)
    whole: bool = False
    """The parameters were refitted on the whole estimation segments after a choice on their
    held-out ends (:func:`dvt_identify.loop.refit_whole`): ``est_segments`` are the whole
    segments, ``val_segments`` their held-out ends (in them)."""
    test: Any = None
    """Figures on test data read after every choice (:class:`dvt_identify.series.TestFigures`)."""
    reference: ReferenceStage | None = None
    """The black-box linear reference scored like the physical model (``None``: not fitted)."""
    agreement: Any = None
    """Whether the test records agree with the estimation records
    (:class:`dvt_identify.disagree.Agreement`; ``None`` without test records)."""
    carrier: Any = None
    """The final model carrying the disagreement, scored on the test records, chosen on
    estimation data (:class:`dvt_identify.carrier.CarrierOffer`; ``None``: the records agree)."""
    spread: Any = None
    """The test figure beside those of the final model refitted on each half of its estimation
    data (:class:`dvt_identify.spread.FigureSpread`; ``None`` without test records)."""
    selection: str = "validation"
    """Which data chose the effects: ``validation`` (the validation bags), ``holdout`` (the
    held-out end of each estimation segment) or ``cv`` (leave-one-bag-out cross-validation
    across the estimation bags; the validation figures are then out-of-fold)."""

    def records(self) -> list[Segment]:
        """The estimation data as recorded, each sample once: the whole segments after
        :func:`~dvt_identify.loop.refit_whole`, else the estimation and validation segments."""
        return list(self.est_segments) if self.whole else [*self.est_segments,
                                                            *self.val_segments]

    @property
    def accepted(self) -> list[Decision]:
        """Accepted decisions in order."""
        return [d for d in self.decisions if d.accepted]



def make_stage(label: str, fit: OEFit, est: Sequence[Segment], val: Sequence[Segment],
               same_rate: bool, lags: int = 25,
               folds: tuple[Sequence[OEFit], Sequence[Sequence[int]]] | None = None) -> Stage:
    """Evaluate ``fit`` on the full-rate estimation and the validation segments.

    ``folds`` (cross-validated selection, ``val`` then the estimation segments): the fold fits
    and the segment indices each one left out; every validation segment is then simulated by
    the fold fit that did not see it (out of sample)."""
    m = fit.model
    est_x0 = fit.x0_ if same_rate else [fit.estimate_x0(s) for s in est]
    est_pred = [m.simulate(fit.theta_, s, x0) for s, x0 in zip(est, est_x0, strict=True)]
    if folds is None:
        val_x0 = [fit.estimate_x0(s) for s in val]
        val_pred = [m.simulate(fit.theta_, s, x0) for s, x0 in zip(val, val_x0, strict=True)]
    else:
        val_x0, val_pred = _out_of_fold(folds[0], folds[1], val)
    names = est[0].output_names
    inames = est[0].input_names
    k = fit.n_estimated_
    fe = figures([s.y for s in est], est_pred, k, names)
    fv = figures([s.y for s in val], val_pred, k, names)
    re = residual_analysis([s.y - p for s, p in zip(est, est_pred, strict=True)],
                           [s.u for s in est], names, inames, lags)
    rv = residual_analysis([s.y - p for s, p in zip(val, val_pred, strict=True)],
                           [s.u for s in val], names, inames, lags)
    sp = [residual_spectrum([(s.y - p)[:, j] for s, p in zip(val, val_pred, strict=True)],
                            val[0].dt) for j in range(len(names))]
    return Stage(label=label, fit=fit, est=fe, val=fv, est_pred=est_pred, val_pred=val_pred,
                 val_x0=val_x0, resid_est=re, resid_val=rv, spectrum_val=sp,
                 folds=[] if folds is None else list(folds[0]))


CV_MIN_BAGS = 2
"""Fewest estimation bags for leave-one-bag-out cross-validated selection."""


def bag_of(name: str) -> str:
    """The bag a segment came from: its name without the ``#<k>`` suffix of a bag split at a
    gap (:func:`dvt_identify.bagload.load_bag_segments`)."""
    return re.sub(r"#\d+$", "", name)


def cv_folds(est: Sequence[Segment]) -> list[list[int]]:
    """Segment indices of each estimation bag (the folds of leave-one-bag-out), bags in order
    of first appearance; the segments of a bag split at gaps stay together."""
    folds: dict[str, list[int]] = {}
    for i, s in enumerate(est):
        folds.setdefault(bag_of(s.name), []).append(i)
    return list(folds.values())


def fold_fits(fit: OEFit, fit_segs: Sequence[Segment], folds: Sequence[Sequence[int]],
              seed: int = 0) -> list[OEFit]:
    """``fit``'s model refitted without each fold in turn (one start, warm from ``fit``'s
    optimum, the same output weights: a local refinement to the fold's optimum).

    Raises:
        FitError: a fold's refit failed (naming the left-out bag).
    """
    out = []
    for held in folds:
        train = [s for i, s in enumerate(fit_segs) if i not in held]
        try:
            out.append(OEFit(fit.model, starts=1, seed=seed, theta0=fit.theta_.copy(),
                             weights=fit.weights_, more_starts=0,
                             init_window=fit.init_window).fit(train))
        except FitError as exc:
            raise FitError(f"cross-validation fold without {bag_of(fit_segs[held[0]].name)}: "
                           f"{exc}") from exc
    return out


def _out_of_fold(fits: Sequence[OEFit], folds: Sequence[Sequence[int]],
                 segs: Sequence[Segment]) -> tuple[list[Array], list[Array]]:
    """Initial states and simulations of every segment by the fold fit that left it out."""
    x0s: list[Array] = [np.zeros(0)] * len(segs)
    preds: list[Array] = [np.zeros(0)] * len(segs)
    for ff, held in zip(fits, folds, strict=True):
        for i in held:
            x0s[i] = ff.estimate_x0(segs[i])
            preds[i] = ff.model.simulate(ff.theta_, segs[i], x0s[i])
    return x0s, preds
