"""Models that carry a disagreement of the records: an input bias set in the initial-state
window, chosen on estimation data only.

When the test record disagrees with the estimation record (:mod:`dvt_identify.disagree`: it
needed a systematically different drive at the same state), no parameter fitted on the
estimation record can know the change, but a *disturbance state* can: a bias ``b`` on each
driving input (``u_j + b``), constant over the record, set like the initial state from the
record's first ``init_window`` samples (``--init-window N``) and then held while the rest of
the record is simulated and scored untouched. Two carriers (:data:`KINDS`):

- ``constant``: one bias per driving input;
- ``direction``: one bias per driving input and direction of motion of the member it drives
  (the sign of the state :func:`~dvt_identify.disagree.driving_inputs` names, from the model's
  own simulation with the bias applied): a changed dry friction, as
  :func:`~dvt_identify.disagree.compare_records` measures it. A direction the window never
  moves in keeps a bias of 0 (not determined: infinite std).

:func:`window_bias` estimates the initial state and the bias jointly on the window
(Gauss-Newton, the bias' sensitivities by finite differences with the direction masks held,
HAC std by :func:`~dvt_identify.uncertainty.sandwich_covariance`). :func:`choose_carrier`
chooses among ``none`` and the carriers **on estimation data only**: the estimation segments
are cut into contiguous blocks (:func:`dvt_identify.series.block_split`); in each block the
initial state (and the carrier's bias) comes from its first ``init_window`` samples and the rest
is scored with the final model. A carrier is chosen only when it lowers the blocks' summed
squared error by at least :data:`MIN_GAIN` and in at least half of the blocks (the model's
parameters were fitted on these blocks, the bias only on each block's window: a carrier helps
there only when the bias really changes between blocks). :func:`offer_carrier` scores every
carrier on the test records (their windows alone set the bias) beside the plain model and says
which one the estimation data chose; the test records choose nothing.

Pure; reads nothing but the segments it is given.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.disagree import driving_inputs, with_u
from dvt_identify.errors import DataError
from dvt_identify.fit import OEFit
from dvt_identify.metrics import Figures, figures
from dvt_identify.sensitivity import simulate_sens
from dvt_identify.simulation import DivergedError
from dvt_identify.uncertainty import sandwich_covariance

Array = NDArray[np.float64]
KINDS = ("none", "constant", "direction")
"""The carriers: no bias, one constant bias per driving input, one per input and direction."""
MIN_GAIN = 0.05
"""Least share of the estimation blocks' summed squared error a carrier must remove to be
chosen."""
MIN_SCORED = 10
"""Fewest samples after the window a block or test segment must have to be scored."""
_PASSES = 3
"""Simulations of the fixed point of the direction masks (mask from the previous pass' states)."""
_ITERATIONS = 6
"""Gauss-Newton iterations of :func:`window_bias`."""


@dataclass
class WindowBias:
    """The initial state and input bias one record's initial-state window gives.

    Attributes:
        kind: the carrier (:data:`KINDS`).
        labels: what each bias is (``force``; ``force +`` / ``force -``).
        value, std: the bias [input unit] and its HAC standard error (inf: not determined by
            the window, kept 0), each (k,).
        x0: the initial state (nx,).
    """

    kind: str
    labels: list[str]
    value: Array
    std: Array
    x0: Array

    def as_dict(self) -> dict[str, object]:
        """JSON-ready (an undetermined std as ``None``)."""
        return {"labels": self.labels, "bias": self.value.tolist(),
                "std": [float(s) if np.isfinite(s) else None for s in self.std]}


def bias_labels(fit: OEFit, names: Sequence[str], kind: str) -> list[str]:
    """The labels of ``kind``'s biases for the inputs ``names``."""
    pairs = driving_inputs(fit)
    if kind == "constant":
        return [names[j] for j, _ in pairs]
    if kind == "direction":
        return [f"{names[j]} {d}" for j, _ in pairs for d in ("+", "-")]
    return []


def _columns(fit: OEFit, seg: Segment, kind: str, xs: Array | None) -> list[tuple[int, Array]]:
    """(input, column added to it per unit of each bias) of ``kind``; ``xs`` the states whose
    signs give the directions (N, nx)."""
    out: list[tuple[int, Array]] = []
    for j, k in driving_inputs(fit):
        if kind == "constant":
            out.append((j, np.ones(seg.n)))
        elif kind == "direction":
            s = np.zeros(seg.n) if xs is None else xs[:, k]
            out += [(j, (s > 0).astype(float)), (j, (s < 0).astype(float))]
    return out


def _biased(seg: Segment, cols: Sequence[tuple[int, Array]], b: Array) -> Segment:
    u = seg.u.copy()
    for (j, c), v in zip(cols, b, strict=True):
        u[:, j] += v * c
    return with_u(seg, u)


def simulate_biased(fit: OEFit, seg: Segment, x0: Array, kind: str, b: Array
                    ) -> tuple[Array, Array, list[tuple[int, Array]]]:
    """States (N, nx), outputs (N, ny) and the bias columns of ``fit``'s model on ``seg`` from
    ``x0`` with ``kind``'s biases ``b`` added to the inputs (the directions from the biased
    simulation's own states, :data:`_PASSES` passes).

    Raises:
        DivergedError: the simulation diverged.
    """
    m = fit.model
    xs, y = m.simulate_states(fit.theta_, seg, x0)
    if kind == "none":
        return xs, y, []
    cols = _columns(fit, seg, kind, xs)
    for _ in range(1 if kind == "constant" else _PASSES):
        xs, y = m.simulate_states(fit.theta_, _biased(seg, cols, b), x0)
        if kind == "direction":
            cols = _columns(fit, seg, kind, xs)
    return xs, y, cols


def window_bias(fit: OEFit, seg: Segment, window: int, kind: str) -> WindowBias:
    """The initial state and ``kind``'s input biases that best reproduce the first ``window``
    samples of ``seg`` (weighted outputs) with ``fit``'s parameters fixed (module docstring).

    Raises:
        DataError: ``window`` < 1 or an unknown ``kind``.
    """
    if window < 1:
        raise DataError(f"carrier: the bias is set in the initial-state window; got a window "
                        f"of {window} samples (use --init-window N)")
    if kind not in KINDS:
        raise DataError(f"carrier: unknown kind {kind!r} (expected one of {', '.join(KINDS)})")
    part = seg.rows(0, min(window, seg.n))
    x0 = np.asarray(fit.estimate_x0(part), float)
    labels = bias_labels(fit, seg.input_names, kind)
    b = np.zeros(len(labels))
    if kind == "none":
        return WindowBias(kind, labels, b, b.copy(), x0)
    m = fit.model
    w = fit.weights_
    target = (part.y / w).ravel()
    nx = m.nx

    def evaluate(x: Array, bb: Array) -> tuple[Array, Array] | None:
        """Residual and Jacobian over (x0, b), the masks held."""
        try:
            with np.errstate(all="ignore"):
                _, y, cols = simulate_biased(fit, part, x, kind, bb)
                biased = _biased(part, cols, bb)
                _, _, S = simulate_sens(m, fit.theta_, biased, x, (), True)
                jb = []
                for i, (j, _c) in enumerate(cols):
                    h = 1e-3 * (float(np.std(seg.u[:, j])) or 1.0)
                    one = np.zeros(len(cols))
                    one[i] = h
                    yh = m.simulate(fit.theta_, _biased(biased, cols, one), x)
                    jb.append(((yh - y) / w).ravel() / h)
        except (DivergedError, np.linalg.LinAlgError, ValueError, OverflowError):
            return None
        J = np.column_stack([(S / w[None, :, None]).reshape(-1, nx), *jb])
        r = target - (y / w).ravel()
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
            return None
        return r, J

    ev = evaluate(x0, b)
    if ev is None:
        return WindowBias(kind, labels, b, np.full(b.size, np.inf), x0)
    r, J = ev
    for _ in range(_ITERATIONS):
        step, *_ = np.linalg.lstsq(J, r, rcond=1e-10)
        t = 1.0
        for _half in range(6):  # keep a step only when it lowers the window's cost
            cand = evaluate(x0 + t * step[:nx], b + t * step[nx:])
            if cand is not None and float(cand[0] @ cand[0]) <= float(r @ r):
                break
            t *= 0.5
        else:
            break
        x0, b = x0 + t * step[:nx], b + t * step[nx:]
        r, J = cand
        if float(np.max(np.abs(t * step))) <= 1e-12 * max(1.0, float(np.max(np.abs(x0)))):
            break
    cov = sandwich_covariance(J, r, m.ny, [part.n])
    std = np.asarray(cov.std, float)[nx:]
    seen = np.any(J[:, nx:] != 0.0, axis=0)
    std = np.where(seen, std, np.inf)
    return WindowBias(kind, labels, np.asarray(b, float), std, np.asarray(x0, float))


def predict_carried(fit: OEFit, seg: Segment, window: int, kind: str
                    ) -> tuple[Array, WindowBias]:
    """Simulated outputs (N, ny) of ``seg`` by ``fit`` carrying ``kind``'s bias, initial state
    and bias from the first ``window`` samples, and that window's estimate. ``none`` is the
    plain model exactly as the test figure scores it (:func:`dvt_identify.series.evaluate_test`).

    Raises:
        DataError: a window that leaves fewer than :data:`MIN_SCORED` samples to score.
        DivergedError: the simulation diverged.
    """
    if window >= seg.n - MIN_SCORED:
        raise DataError(f"{seg.name}: init window {window} samples leaves fewer than "
                        f"{MIN_SCORED} of {seg.n} to score")
    wb = window_bias(fit, seg, window, kind)
    _, y, _ = simulate_biased(fit, seg, wb.x0, kind, wb.value)
    return np.asarray(y, float), wb


@dataclass
class KindScore:
    """One carrier over the estimation blocks (:func:`choose_carrier`).

    Attributes:
        kind: the carrier.
        sse: summed squared weighted error over the blocks' scored samples (inf: a block's
            simulation diverged).
        better: blocks where it is below ``none``'s.
        scatter: root mean square of the biases the blocks' windows gave, per bias (k,), over
            the blocks whose window determined it (nan: none did): the window estimate's real
            error where the bias should not change (its reported std counts only the window's
            own residual).
    """

    kind: str
    sse: float
    better: int
    scatter: Array = field(default_factory=lambda: np.zeros(0))


@dataclass
class CarrierChoice:
    """Which carrier the estimation data chose and why.

    Attributes:
        chosen: ``none``, ``constant`` or ``direction``.
        scores: one per kind, in :data:`KINDS` order.
        blocks: estimation blocks scored.
        reason: one plain sentence.
    """

    chosen: str
    scores: list[KindScore]
    blocks: int
    reason: str

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"chosen": self.chosen, "blocks": self.blocks, "reason": self.reason,
                "min_gain": MIN_GAIN,
                "scores": [{"kind": s.kind, "sse": s.sse if np.isfinite(s.sse) else None,
                            "blocks_better_than_none": s.better,
                            "window_bias_scatter": [float(v) if np.isfinite(v) else None
                                                    for v in s.scatter]}
                           for s in self.scores]}


def _rms(values: Sequence[Array]) -> Array:
    """Root mean square over the rows of ``values`` ignoring nan, per column (nan: none)."""
    if not values or not values[0].size:
        return np.zeros(0)
    v = np.vstack(values)
    n = np.sum(np.isfinite(v), axis=0)
    ss = np.nansum(v * v, axis=0)
    return np.where(n > 0, np.sqrt(ss / np.maximum(n, 1)), np.nan)


def choose_carrier(fit: OEFit, est: Sequence[Segment], window: int,
                   blocks: int | None = None) -> CarrierChoice:
    """Choose the carrier on the estimation segments ``est`` alone (module docstring):
    cross-validation over their contiguous blocks (``blocks`` per segment, default as
    :func:`dvt_identify.series.block_split` cuts them), the bias set in each block's window.

    Raises:
        DataError: no window, or no block long enough to score after its window.
    """
    from dvt_identify.series import block_split

    if window < 1:
        raise DataError("carrier: the bias is set in the initial-state window; without "
                        "--init-window N it would come from the scored samples")
    segs = list({id(s): s for s in est}.values())
    parts = []
    for seg in segs:
        try:
            cut = block_split([seg], blocks)
        except DataError:  # too short to cut: one block
            cut = [seg]
        parts += [b for b in cut if b.n > window + MIN_SCORED]
    if not parts:
        raise DataError(f"carrier: no estimation block longer than the {window}-sample window "
                        f"plus {MIN_SCORED} samples to score")
    w = fit.weights_
    sse = {k: np.zeros(len(parts)) for k in KINDS}
    seen: dict[str, list[Array]] = {k: [] for k in KINDS}
    for i, blk in enumerate(parts):
        for kind in KINDS:
            try:
                y, wb = predict_carried(fit, blk, window, kind)
                seen[kind].append(np.where(np.isfinite(wb.std), wb.value, np.nan))
                e = (blk.y[window:] - y[window:]) / w
                sse[kind][i] = float(np.sum(e * e)) if np.all(np.isfinite(e)) else np.inf
            except DivergedError:
                sse[kind][i] = np.inf
    scores = [KindScore(k, float(np.sum(sse[k])), int(np.sum(sse[k] < sse["none"])),
                        _rms(seen[k])) for k in KINDS]
    base = scores[0].sse
    ok = [s for s in scores[1:] if np.isfinite(s.sse) and s.sse <= (1.0 - MIN_GAIN) * base
          and 2 * s.better >= len(parts)]
    desc = "; ".join(f"{s.kind} {s.sse:.4g}" + (f" (better in {s.better}/{len(parts)}, window "
                                                f"biases scattered by {_join(s.scatter)})"
                                                if s.kind != "none" else "") for s in scores)
    head = (f"cross-validation over {len(parts)} blocks of the estimation records (bias and "
            f"initial state from each block's first {window} samples, the rest scored; summed "
            f"squared weighted error: {desc})")
    if ok:
        best = min(ok, key=lambda s: s.sse)
        reason = (f"{best.kind} chosen: it lowers the estimation blocks' error by "
                  f"{100 * (1 - best.sse / base):.3g} % (at least {100 * MIN_GAIN:g} % and in "
                  f"at least half of the blocks), {head}")
        return CarrierChoice(best.kind, scores, len(parts), reason)
    reason = (f"none chosen: no carrier lowers the estimation blocks' error by {100 * MIN_GAIN:g} "
              f"% and in at least half of them (a bias set in a {window}-sample window does not "
              f"predict the rest of an estimation block better than the plain model); {head}")
    return CarrierChoice("none", scores, len(parts), reason)


@dataclass
class Carried:
    """The final model carrying one kind of bias, scored on the test records.

    Attributes:
        kind: the carrier.
        figures: on the samples after each test segment's window.
        biases: each test segment's window estimate.
    """

    kind: str
    figures: Figures
    biases: list[WindowBias]


@dataclass
class CarrierOffer:
    """The plain final model and the models carrying the disagreement, on the test records,
    with the choice made on estimation data (:func:`offer_carrier`)."""

    init_window: int
    unit: str
    choice: CarrierChoice
    plain: Figures
    carried: list[Carried]
    test_names: list[str] = field(default_factory=list)

    @property
    def statement(self) -> str:
        """One plain sentence per model for the progress and the report."""
        names = self.plain.output_names
        rows = [f"plain {_rmse(self.plain, names)}"]
        for c in self.carried:
            rows.append(f"with a {c.kind} input bias {_rmse(c.figures, names)} (bias "
                        + "; ".join(_bias_text(b, self.unit) for b in c.biases) + ")")
        return (f"Models carrying the disagreement (a bias set in the test record's first "
                f"{self.init_window} samples): test " + ", ".join(rows)
                + f"; chosen on estimation data: {self.choice.chosen}.")

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"role": "a disturbance state (an input bias) set in each test segment's "
                "initial-state window, like the initial state; the choice made on estimation "
                "data only", "init_window": self.init_window, "unit": self.unit,
                "chosen": self.choice.chosen, "choice": self.choice.as_dict(),
                "test": [{"kind": "none", "figures": self.plain.as_dict(), "biases": []}]
                + [{"kind": c.kind, "figures": c.figures.as_dict(),
                    "biases": [dict(b.as_dict(), segment=n) for b, n in
                               zip(c.biases, self.test_names, strict=True)]}
                   for c in self.carried],
                "statement": self.statement}


def _join(v: Array) -> str:
    return ", ".join(f"{x:.3g}" if np.isfinite(x) else "-" for x in v) or "-"


def _rmse(f: Figures, names: Sequence[str]) -> str:
    return ", ".join(f"{n} RMSE {r:.4g}" for n, r in zip(names, f.rmse, strict=True))


def _bias_text(b: WindowBias, unit: str) -> str:
    u = f" {unit}" if unit else ""
    return ", ".join(f"{lab} {v:+.3g} ± {s:.2g}{u}" if np.isfinite(s) else
                     f"{lab} not seen in the window (0)"
                     for lab, v, s in zip(b.labels, b.value, b.std, strict=True))


def offer_carrier(fit: OEFit, est: Sequence[Segment], test: Sequence[Segment], window: int,
                  plain: Figures, unit: str = "", blocks: int | None = None) -> CarrierOffer:
    """Score ``fit`` carrying each kind of input bias on ``test`` beside its ``plain`` test
    figures (:class:`dvt_identify.series.TestFigures` ``final``), the choice made on ``est``
    alone (:func:`choose_carrier`).

    Raises:
        DataError: no window, no test segment, or no block to choose on.
    """
    if not test:
        raise DataError("carrier: no test segments")
    choice = choose_carrier(fit, est, window, blocks)
    names = test[0].output_names
    carried = []
    for kind in KINDS[1:]:
        preds, biases = [], []
        for seg in test:
            try:
                y, wb = predict_carried(fit, seg, window, kind)
            except DivergedError:
                y = np.full(seg.y.shape, np.nan)
                wb = window_bias(fit, seg, window, kind)
            preds.append(y[window:])
            biases.append(wb)
        k = int(sum(b.value.size for b in biases))  # each segment's biases are estimated
        carried.append(Carried(kind, figures([s.y[window:] for s in test], preds,
                                             plain.n_params + k, names), biases))
    return CarrierOffer(init_window=window, unit=unit, choice=choice, plain=plain,
                        carried=carried, test_names=[s.name for s in test])
