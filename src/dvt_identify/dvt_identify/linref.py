"""The linear reference beside every physical model, and the starts it gives.

:func:`fit_reference` fits the black-box LTI reference (:class:`~dvt_identify.reference.
LinearReference`: subspace start, output-error refinement, order chosen on the selection data)
on the same estimation data as the physical model and simulates it on the same validation data
with the same initial-state rule, so the report can put the two side by side
(:class:`ReferenceStage`) and flag a physical model that scores worse. :func:`mapped_starts`
turns the reference into starts of the physical fit (:mod:`dvt_identify.startmap`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.effects.base import Effect, SegmentView
from dvt_identify.errors import DataError, FitError
from dvt_identify.fitstarts import undone_at
from dvt_identify.metrics import Figures, figures
from dvt_identify.reference import LinearReference
from dvt_identify.simulation import OEModel, zoh_decimate
from dvt_identify.startmap import MappedStart, frequency_response_starts
from dvt_identify.unfold import unfold

Array = NDArray[np.float64]
MAX_SAMPLES = 6000
"""The reference is fitted on the estimation data decimated (consistently with the hold) to at
most about this many samples per segment: it is a yardstick, fitted in seconds."""
MAX_THIN = 2
"""... but by at most this factor (the fit rate resolves the dynamics; a tenfold thinning of a
long segment would alias them) ..."""
MAX_TOTAL = 4 * MAX_SAMPLES
"""... and on at most this many samples in all: a long recording gives the reference its first
part (in order of the segments), not a coarser rate (an hour at 200 Hz: its first two minutes,
where six ten-minute segments cost two minutes of reference fitting)."""
MIN_PART = 100
"""Fewest samples of a segment's part handed to the reference."""
HOLDOUT = 0.3
"""With cross-validated selection the reference's order is chosen on the last 30 % of each
estimation segment (fitted on the rest)."""


@dataclass
class ReferenceStage:
    """The linear reference scored like the physical model.

    Attributes:
        model: the fitted :class:`LinearReference`.
        val: figures on the validation (selection) data, initial states by the same rule as
            the physical model's.
        val_pred: its simulated outputs per validation segment, (N, ny) each.
        est: figures on the estimation data (at the fit rate).
        chosen_on: what chose its order.
        starts: the structure starts it gave the physical fit (:func:`mapped_starts`).
    """

    model: LinearReference
    val: Figures
    val_pred: list[Array]
    est: Figures
    chosen_on: str
    starts: list[MappedStart] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        m = self.model
        return {"order": m.order_, "chosen_on": self.chosen_on, "sample_time_s": m.dt_,
                "validation": self.val.as_dict(), "estimation": self.est.as_dict(),
                "orders": [r.as_dict() for r in m.orders_], "seconds": m.seconds_,
                "notes": list(m.notes_),
                "poles_hz": [abs(complex(p)) / (2 * math.pi) for p in m.model_.poles_s()],
                "mapped_starts": [{"mismatch": s.mismatch, "origin": s.origin,
                                   "theta": s.theta.tolist()} for s in self.starts]}


def reference_data(segs: Sequence[Segment], init_window: int) -> list[Segment]:
    """The reference's estimation data of the physical fit's ``segs``: as they are with a
    state-initialisation window (it counts samples at the recording's rate), else thinned
    (:data:`MAX_SAMPLES`, :data:`MAX_THIN`, :data:`MAX_TOTAL`)."""
    return list(segs) if init_window > 0 else _thin(segs)


def _thin(segs: Sequence[Segment]) -> list[Segment]:
    """The reference's estimation data (:data:`MAX_SAMPLES`, :data:`MAX_THIN`,
    :data:`MAX_TOTAL`)."""
    out: list[Segment] = []
    total = 0
    for s in segs:
        q = max(1, min(math.ceil(s.n / MAX_SAMPLES), MAX_THIN))
        t = zoh_decimate(s, q) if q > 1 and s.n // q >= 10 else s
        room = MAX_TOTAL - total
        if out and room < 2 * MIN_PART:
            break
        if t.n > room:
            t = t.rows(0, room)
        out.append(t)
        total += t.n
    return out


def fit_reference(fit_segs: Sequence[Segment], val: Sequence[Segment], init_window: int,
                  max_order: int, seed: int, cross_validate: bool) -> ReferenceStage:
    """Fit the reference on ``fit_segs`` (the physical fit's data), choose its order on ``val``
    (with cross-validated selection: on the last :data:`HOLDOUT` of each estimation segment,
    fitted on the rest) and score it on ``val`` with the initial-state rule of the physical
    model (``init_window``).

    Raises:
        FitError, DataError: the reference could not be fitted (the caller notes it and goes
            on without one).
    """
    est = reference_data(fit_segs, init_window)
    if cross_validate:
        fit_part, sel = [], []
        for s in est:
            k = round((1.0 - HOLDOUT) * s.n)
            if k < 20 or s.n - k < 20:
                raise DataError(f"{s.name}: too short to hold out {100 * HOLDOUT:g} % for the "
                                "linear reference's order")
            fit_part.append(s.rows(0, k))
            sel.append(s.rows(k, s.n))
        chosen_on = (f"the last {100 * HOLDOUT:g} % of each estimation segment (fitted on the "
                     "rest); its validation figures below are in sample")
        ref = LinearReference(max_order=max_order, init_window=init_window, seed=seed).fit(
            fit_part, sel)
        ref = LinearReference(max_order=ref.order_, init_window=init_window,
                              seed=seed).fit(est, sel)
    else:
        chosen_on = "the validation (selection) data"
        ref = LinearReference(max_order=max_order, init_window=init_window, seed=seed).fit(
            est, list(val))
    preds = [ref.predict(s) for s in val]
    names = val[0].output_names
    vf = figures([s.y for s in val], preds, ref.n_estimated_, names)
    ef = figures([s.y for s in est], [ref.predict(s) for s in est], ref.n_estimated_, names)
    return ReferenceStage(model=ref, val=vf, val_pred=preds, est=ef, chosen_on=chosen_on)


def mapped_starts(model: OEModel, ref: LinearReference, fit_segs: Sequence[Segment],
                  seed: int, keep: int = 2) -> list[MappedStart]:
    """Starts of the physical structure mapped from the reference's frequency response
    (:func:`dvt_identify.startmap.frequency_response_starts`), as full start vectors (the model
    effects at their initial values) in ``MappedStart.theta``; empty when the structure's
    outputs or inputs differ from the reference's or nothing could be mapped."""
    st = model.structure
    n = model.n_struct
    if n == 0:
        return []
    specs = model.specs[:n]
    prior = np.array([p.initial for p in specs], dtype=float)
    lo = np.array([p.lower for p in specs], dtype=float)
    hi = np.array([p.upper for p in specs], dtype=float)
    duration = max(s.n * s.dt for s in fit_segs)
    try:
        found = frequency_response_starts(st, ref.A_, ref.B_, ref.C_, ref.dt_, duration, prior,
                                          lo, hi, keep=keep, seed=seed)
    except (FitError, ValueError, np.linalg.LinAlgError):
        return []
    full = model.initial()
    out = []
    for s in found:
        th = full.copy()
        th[:n] = s.theta
        out.append(MappedStart(th, s.mismatch, s.origin))
    return out


def unfolded_starts(model: OEModel, fit_segs: Sequence[Segment], seed: int,
                    max_order: int, beside: Sequence[Effect] = (),
                    theta: Array | None = None) -> list[Array]:
    """Start vectors of ``model`` when an effect of it reads an output sign-blind
    (:meth:`Effect.blind_output`): the structure mapped from a linear reference fitted to
    ``fit_segs`` with those outputs unfolded (:func:`dvt_identify.unfold.unfold`), every
    effect at its initial value except a sign-blind map at its probe (the map itself, ``|y|``);
    empty when no output is read sign-blind or no reference could be fitted (its order chosen
    on the last part of each segment, as with cross-validated selection).

    An output map of the model with an inverse (:meth:`Effect.output_inverse`, at its initial
    values: a filter on the reading smooths the dips that tell where the sign changes) is
    undone before the unfolding; so, for further sets of starts, is each map of ``beside``
    (candidates scored beside this one, not in the model) at each of its
    :meth:`Effect.inverse_probes` (its value is not known yet). ``theta`` (the model's
    parameters, e.g. the current optimum with the candidate's start): the model's maps are
    undone at its values instead of their initial ones (the starts keep every effect at its
    initial value: a friction fitted without the map is bent)."""
    blind = [(k, j) for k, e in enumerate(model.effects) if (j := e.blind_output()) is not None]
    if not blind:
        return []
    values = (model.effect_params(np.asarray(theta, float)) if theta is not None
              else [np.array([q.initial for q in e.params], float) for e in model.effects])
    own = [(e, v) for e, v in zip(model.effects, values, strict=True)]
    out = _unfolded_starts(model, undone_at(own, fit_segs), blind, seed, max_order)
    dt = min(s.dt for s in fit_segs) if fit_segs else 0.0
    for eff in beside:
        for p in eff.inverse_probes(dt):
            segs = undone_at([(eff, p)], fit_segs)
            if any(a is not b for a, b in zip(segs, fit_segs, strict=True)):
                out += _unfolded_starts(model, undone_at(own, segs), blind, seed, max_order)
    return out


def _unfolded_starts(model: OEModel, segs: Sequence[Segment], blind: Sequence[tuple[int, int]],
                     seed: int, max_order: int) -> list[Array]:
    """:func:`unfolded_starts` on ``segs`` as given (maps with an inverse already undone)."""
    for _, j in blind:
        segs = unfold(segs, j)
    try:
        ref = fit_reference(segs, segs, 0, max_order, seed, True)
    except (FitError, DataError):
        return []
    # the unfolded sign is open overall: the reference and its mirror (those outputs negated)
    mirror = copy.copy(ref.model)
    mirror.C_ = ref.model.C_.copy()
    mirror.C_[[j for _, j in blind]] *= -1.0
    out = []
    for start in [*mapped_starts(model, ref.model, segs, seed),
                  *mapped_starts(model, mirror, segs, seed)]:
        th = start.theta.copy()
        for k, _ in blind:
            eff = model.effects[k]
            sl = model.effect_slice(k)
            probe = dict(eff.variants(SegmentView.of(segs[0]))[0][1])
            th[sl] = [probe.get(p.name, th[sl.start + i]) for i, p in enumerate(eff.params)]
        out.append(th)
    return out
