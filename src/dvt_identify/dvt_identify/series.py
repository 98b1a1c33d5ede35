"""Selection kept apart from the test, and the series files of a report.

**Which data choose what.** The augment loop (:func:`dvt_identify.loop.identify`) chooses the
effects with the data it is given as "validation" (the Diebold-Mariano acceptance test): so a
figure on those data is a *selection* figure, not an honest one. Two ways keep an honest
figure:

- ``--test BAG...`` (:func:`evaluate_test`): the test bags are read only after every choice is
  made (:func:`dvt_identify.pipeline.run` reads them after ``identify`` returns) and give a
  figure for the baseline and the final model that took no part in any choice;
- ``--select-on holdout`` (:func:`holdout_split`): the effects are chosen on the last part of
  each estimation segment (held out of the fit), and the ``--validate`` bags become test data.

The initial state of a test segment is estimated with the parameters fixed: by default from
the whole segment (as for validation), or, benchmark style (``--init-window N``), from its first
``N`` samples only, the figures then computed on the samples after them.

**Series.** :func:`write_series` writes the measured and simulated outputs and the residuals of
every estimation, validation (selection) and test segment, baseline and final model, as
``series.npz`` (one array per segment and quantity, :func:`series_keys`), one CSV per segment
(``series/<role>-<k>.csv``, every number with 17 significant digits: it reads back to the same
binary value) and, on request, one MCAP bag per segment (``series/<role>-<k>/``) with the
description's output topics (measured) and the contract's model topics
(:data:`dvt_model.contract.MODEL_JOINT_STATES`: the final model's simulated outputs,
:data:`dvt_model.contract.MODEL_RESIDUAL`: measured - simulated), so Foxglove overlays them.
:func:`figures_from_series` recomputes the report's fit figures from ``series.npz``; they are
the same numbers (the test proves it).
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.errors import DataError
from dvt_identify.fit import OEFit
from dvt_identify.metrics import Figures, figures
from dvt_identify.reference import LinearReference

Array = NDArray[np.float64]
ROLES = ("estimation", "validation", "test")
"""Segment roles in the series files (``validation``: the data that chose the effects, or the
held-out part of the estimation data with ``--select-on holdout``)."""
HOLDOUT_FRACTION = 0.3
"""Default share of each estimation segment held out for selection."""


# ---------------------------------------------------------------------------------------------
# Selection and test


def holdout_split(segments: Sequence[Segment], fraction: float = HOLDOUT_FRACTION
                  ) -> tuple[list[Segment], list[Segment]]:
    """Each segment split in time: the first ``1 - fraction`` for fitting, the rest for the
    choice of effects (``<name>#holdout``).

    Raises:
        DataError: ``fraction`` not in (0, 1), or a part would hold fewer than 50 samples.
    """
    if not 0.0 < fraction < 1.0:
        raise DataError(f"holdout fraction: expected 0 < fraction < 1, got {fraction}")
    fit, sel = [], []
    for seg in segments:
        k = round(seg.n * (1.0 - fraction))
        if k < 50 or seg.n - k < 50:
            raise DataError(f"{seg.name}: {seg.n} samples are too few to hold out "
                            f"{100 * fraction:g} % for the choice of effects (50 each)")
        fit.append(seg.rows(0, k))
        sel.append(seg.rows(k, name=f"{seg.name}#holdout", from_zero=True))
    return fit, sel


BLOCK_MIN_SAMPLES = 100
"""Fewest samples of one block of a record split for cross-validation (:func:`block_split`)."""
MAX_BLOCKS = 5
"""Most blocks a record is split into for cross-validation."""


def block_split(segments: Sequence[Segment], blocks: int | None = None) -> list[Segment]:
    """Each segment cut into contiguous blocks (``<name>@block<k>``), the folds of
    cross-validation over segments when there is one record: ``blocks`` per segment (default:
    as many as :data:`MAX_BLOCKS` allows with at least :data:`BLOCK_MIN_SAMPLES` each, and at
    least 2). Each block keeps its own initial state.

    Raises:
        DataError: a segment too short for 2 blocks of :data:`BLOCK_MIN_SAMPLES`.
    """
    out = []
    for seg in segments:
        k = blocks if blocks is not None else min(MAX_BLOCKS, seg.n // BLOCK_MIN_SAMPLES)
        if k < 2 or seg.n // k < BLOCK_MIN_SAMPLES:
            raise DataError(f"{seg.name}: {seg.n} samples are too few for cross-validation "
                            f"over blocks (at least 2 blocks of {BLOCK_MIN_SAMPLES} samples)")
        edges = [round(i * seg.n / k) for i in range(k + 1)]
        for i, (a, b) in enumerate(itertools.pairwise(edges), start=1):
            out.append(seg.rows(a, b, name=f"{seg.name}@block{i}", from_zero=True))
    return out


@dataclass
class TestFigures:
    """Figures of the baseline and the final model on test data that took no part in any
    choice.

    Attributes:
        bags: the test segments' names.
        init_window: samples used to estimate each initial state (0: the whole segment).
        baseline, final: the figures (on the samples after the init window).
        baseline_pred, final_pred: simulated outputs per segment (whole segment, (N, ny)).
        scored_from: first sample of each segment that the figures count.
        reference: the linear reference's figures on the same samples, with the same
            initial-state rule (``None``: no reference).
    """

    bags: list[str]
    init_window: int
    baseline: Figures
    final: Figures
    baseline_pred: list[Array]
    final_pred: list[Array]
    scored_from: int
    reference: Figures | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"bags": self.bags, "role": "test: read after every choice was made; took no "
                "part in fitting or in choosing effects",
                "initial_state": (f"estimated from the first {self.init_window} samples of "
                                  "each segment (benchmark style); figures on the rest"
                                  if self.init_window else "estimated from each whole segment "
                                  "with the parameters fixed"),
                "baseline": self.baseline.as_dict(), "final": self.final.as_dict(),
                "linear_reference": (self.reference.as_dict() if self.reference is not None
                                     else None)}


def predict_test(fit: OEFit, seg: Segment, init_window: int) -> Array:
    """``fit``'s simulated outputs on test segment ``seg`` (N, ny): the initial state from the
    first ``init_window`` samples (0: from the whole segment), the parameters fixed.

    Raises:
        DataError: the window leaves fewer than 10 samples to score.
    """
    if init_window:
        if init_window >= seg.n - 10:
            raise DataError(f"{seg.name}: init window {init_window} samples leaves fewer than "
                            f"10 of {seg.n} to score")
        x0 = fit.estimate_x0(seg.rows(0, init_window))
    else:
        x0 = fit.estimate_x0(seg)
    return np.asarray(fit.model.simulate(fit.theta_, seg, x0), float)


def evaluate_test(baseline: OEFit, final: OEFit, test: Sequence[Segment],
                  init_window: int = 0, reference: LinearReference | None = None
                  ) -> TestFigures:
    """The figures of ``baseline`` and ``final`` (and of the linear ``reference``) on ``test``
    (see :class:`TestFigures`).

    Raises:
        DataError: no test segments, or an init window that leaves too little to score.
    """
    if not test:
        raise DataError("no test segments")
    w = max(0, int(init_window))
    bp = [predict_test(baseline, s, w) for s in test]
    fp = [predict_test(final, s, w) for s in test]
    names = test[0].output_names
    ys = [s.y[w:] for s in test]
    ref = None
    if reference is not None:
        rp = [reference.predict(s, w) for s in test]
        ref = figures(ys, [p[w:] for p in rp], reference.n_estimated_, names)
    return TestFigures(bags=[s.name for s in test], init_window=w,
                       baseline=figures(ys, [p[w:] for p in bp], baseline.n_estimated_, names),
                       final=figures(ys, [p[w:] for p in fp], final.n_estimated_, names),
                       baseline_pred=bp, final_pred=fp, scored_from=w, reference=ref)


# ---------------------------------------------------------------------------------------------
# Series files


def series_keys(role: str, k: int) -> dict[str, str]:
    """The ``series.npz`` keys of segment ``k`` of ``role``: ``t``, ``u``, ``y`` (measured),
    ``baseline``, ``final`` (simulated), ``residual_baseline``, ``residual_final``."""
    return {q: f"{role}/{k}/{q}" for q in ("t", "u", "y", "baseline", "final",
                                            "residual_baseline", "residual_final")}


@dataclass
class SeriesSet:
    """The segments of one role with both models' simulated outputs."""

    role: str
    segments: list[Segment]
    baseline: list[Array]
    final: list[Array]
    scored_from: int = 0


def collect(result: Any, test: TestFigures | None = None,
            test_segments: Sequence[Segment] = ()) -> list[SeriesSet]:
    """The series of an :class:`~dvt_identify.loop.IdentificationResult`: estimation (the full
    rate data the report's estimation figures use), validation and, when given, test."""
    est = list(getattr(result, "est_segments", []) or [])
    out = []
    if est:
        out.append(SeriesSet("estimation", est, list(result.baseline.est_pred),
                             list(result.final.est_pred)))
    out.append(SeriesSet("validation", list(result.val_segments),
                         list(result.baseline.val_pred), list(result.final.val_pred)))
    if test is not None:
        out.append(SeriesSet("test", list(test_segments), test.baseline_pred, test.final_pred,
                             test.scored_from))
    return out


def write_series(sets: Sequence[SeriesSet], out_dir: str | Path, desc: Any = None,
                 mcap: bool = False) -> dict[str, Path]:
    """Write ``series.npz``, ``series/<role>-<k>.csv`` and (``mcap``) ``series/<role>-<k>/``
    bags into ``out_dir``; returns the paths by name. ``desc`` (the description) names the
    topics of the bags and the CSV columns' units come from nowhere: every value is in the
    description's signal units.

    Raises:
        DataError: a bag directory exists already.
    """
    out = Path(out_dir)
    sub = out / "series"
    sub.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Array] = {}
    paths: dict[str, Path] = {}
    for st in sets:
        for k, seg in enumerate(st.segments):
            keys = series_keys(st.role, k)
            b, f = np.asarray(st.baseline[k], float), np.asarray(st.final[k], float)
            arrays.update({keys["t"]: seg.t, keys["u"]: seg.u, keys["y"]: seg.y,
                           keys["baseline"]: b, keys["final"]: f,
                           keys["residual_baseline"]: seg.y - b,
                           keys["residual_final"]: seg.y - f})
            arrays[f"{st.role}/{k}/scored_from"] = np.array([st.scored_from], float)
            cp = sub / f"{st.role}-{k}.csv"
            _write_csv(cp, seg, b, f)
            paths[f"csv:{st.role}-{k}"] = cp
            if mcap and desc is not None:
                paths[f"mcap:{st.role}-{k}"] = _write_mcap(sub / f"{st.role}-{k}", seg, f, desc)
    meta = np.array([f"{st.role}:{k}:{seg.name}" for st in sets
                     for k, seg in enumerate(st.segments)])
    first = sets[0].segments[0] if sets and sets[0].segments else None
    arrays_all: dict[str, Any] = {
        "segments": meta,
        "inputs": np.array(first.input_names if first is not None else []),
        "outputs": np.array(first.output_names if first is not None else []), **arrays}
    np.savez(out / "series.npz", **arrays_all)
    paths["npz"] = out / "series.npz"
    return paths


def _write_csv(path: Path, seg: Segment, b: Array, f: Array) -> None:
    cols = (["t"] + list(seg.input_names) + [f"{n}" for n in seg.output_names]
            + [f"{n}_baseline" for n in seg.output_names]
            + [f"{n}_final" for n in seg.output_names]
            + [f"{n}_residual_final" for n in seg.output_names])
    data = np.column_stack([seg.t, seg.u, seg.y, b, f, seg.y - f])
    with path.open("w", newline="") as fh:
        csv.writer(fh).writerow(cols)
        # the shortest exact text of each value (Python's float repr: also "nan", "inf",
        # "-inf"), rows as the csv module ends them; built in one join, not value by value
        # (1.3 s of a 3.9-s dvt-identify run before)
        fh.writelines(",".join(map(repr, row)) + "\r\n" for row in data.tolist())


def _joint_states(topic: str, signals: Sequence[tuple[Any, Array]], stamps: Sequence[int],
                  scaled: bool = True) -> tuple[str, str, list[tuple[int, bytes]]]:
    """One JointState stream on ``topic`` holding ``signals`` ((spec, values (N,)) pairs): one
    name per joint, each field filled where a signal has it (NaN elsewhere); values divided
    by the spec's scale when ``scaled`` (the bag unit)."""
    from dvt_model.recording import joint_state_cdr

    names = list(dict.fromkeys(sp.joint for sp, _ in signals))
    used = [fld for fld in ("position", "velocity", "effort")
            if any(sp.field == fld for sp, _ in signals)]
    msgs = []
    for i, st in enumerate(stamps):
        kw: dict[str, Array] = {}
        for fld in used:
            vals = np.full(len(names), math.nan)
            for sp, v in signals:
                if sp.field == fld:
                    vals[names.index(sp.joint)] = v[i] / (sp.scale if scaled else 1.0)
            kw[fld] = vals
        msgs.append((st, joint_state_cdr(st, names, **kw)))
    return topic, "sensor_msgs/msg/JointState", msgs


def _write_mcap(path: Path, seg: Segment, f: Array, desc: Any) -> Path:
    """One bag: the measured inputs and outputs on the description's topics (bag units), the
    final model's simulated outputs on the model topic and the residual on the residual topic
    (signal units, the outputs' joints and fields)."""
    from dvt_model.contract import MODEL_JOINT_STATES, MODEL_RESIDUAL
    from dvt_model.errors import BagError
    from dvt_model.recording import write_bag

    specs = {s.name: s for s in desc.outputs}
    outs = [specs[n] for n in seg.output_names]
    stamps = [round(float(t) * 1e9) for t in seg.t]
    signals = [(s, seg.u[:, k]) for k, s in enumerate(desc.inputs)] + [
        (sp, seg.y[:, k]) for k, sp in enumerate(outs)]
    by_topic: dict[str, list[tuple[Any, Array]]] = {}
    for sp, v in signals:
        by_topic.setdefault(sp.topic, []).append((sp, v))
    streams = [_joint_states(topic, sig, stamps) for topic, sig in by_topic.items()]
    streams.append(_joint_states(MODEL_JOINT_STATES,
                                 [(sp, f[:, k]) for k, sp in enumerate(outs)], stamps, False))
    streams.append(_joint_states(MODEL_RESIDUAL,
                                 [(sp, seg.y[:, k] - f[:, k]) for k, sp in enumerate(outs)],
                                 stamps, False))
    try:
        return Path(write_bag(path, streams))
    except BagError as exc:
        raise DataError(f"{path}: {exc}") from exc


def figures_from_series(npz: str | Path, role: str, model: str, n_params: int
                        ) -> Figures:
    """The fit figures of ``model`` (``baseline`` or ``final``) on every segment of ``role``,
    recomputed from ``series.npz`` (from each segment's ``scored_from`` sample).

    Raises:
        DataError: no such role in the file.
    """
    with np.load(npz) as z:
        ks = sorted({int(key.split("/")[1]) for key in z.files if key.startswith(f"{role}/")})
        if not ks:
            raise DataError(f"{npz}: no {role} series")
        names = [str(n) for n in z["outputs"]]
        ys, ps = [], []
        for k in ks:
            keys = series_keys(role, k)
            w = int(z[f"{role}/{k}/scored_from"][0])
            ys.append(z[keys["y"]][w:])
            ps.append(z[keys[model]][w:])
    return figures(ys, ps, n_params, names)
