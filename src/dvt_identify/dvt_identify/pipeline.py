"""The identification pipeline used by ``dvt-identify`` (:mod:`dvt_identify.cli`) and the
identify node (:mod:`dvt_identify.node`); pure, no rclpy.

Steps (:func:`run`): load the description; read, check and pre-process the estimation and
validation bags into segments (:func:`load_segments`); drop the model effects whose input never
varies in the estimation data (:func:`drop_unexcited_model_effects`); check the excitation;
fit the baseline and run the augment loop (:func:`dvt_identify.loop.identify`); write the
report. :func:`model_push` builds the model node's parameters from a result.
"""

from __future__ import annotations

import math
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from dvt_identify import identifiability
from dvt_identify.bagload import check_excitation, load_bag_segments
from dvt_identify.data import DataWarning, Segment, _constant, decimate, lowpass
from dvt_identify.description import Description, load_description
from dvt_identify.errors import DataError, DvtIdentifyError
from dvt_identify.fit import Progress, stderr_progress
from dvt_identify.fitrate import model_time_scales, resolves_intersample
from dvt_identify.loop import IdentificationResult, LoopConfig, identify, refit_whole
from dvt_identify.push import Push, model_node_parameters
from dvt_identify.report import write_report
from dvt_identify.simulation import OEModel
from dvt_identify.stages import CV_MIN_BAGS, bag_of
from dvt_model.progress import ProgressLine, fraction


def _quiet(_msg: str) -> None:
    return None


def description_label(desc: Description) -> str:
    """``dvt (bundled)`` for a bundled description, ``NAME (PATH)`` for a file (the name once)."""
    if desc.source == desc.name or desc.source.startswith(f"{desc.name} ("):
        return desc.source
    return f"{desc.name} ({desc.source})"


def load_segments(bags: Sequence[str | Path], desc: Description) -> list[Segment]:
    """Read, check and pre-process ``bags`` as the description says (a bag split at long gaps
    gives several segments).

    Raises:
        DataError: naming the bag, topic and problem.
    """
    out = []
    scales: tuple[float, list[float]] | None = None
    for bag in bags:
        for seg in load_bag_segments(bag, desc.inputs, desc.outputs, desc.checks):
            lp = desc.preprocess.lowpass
            if lp:
                seg = lowpass(seg, float(lp["cutoff_hz"]), int(lp.get("order", 4)),
                              bool(lp.get("zero_phase", True)))
            seg = decimate(seg, desc.preprocess.decimate)
            if seg.input_hold is not None or seg.output_lag is not None:
                if scales is None:
                    scales = model_time_scales(OEModel(desc.structure,
                                                       desc.make_model_effects()))
                if not resolves_intersample(seg.dt, *scales):
                    seg = replace(seg, input_hold=None, output_lag=None, notes=(
                        *seg.notes, f"signals between samples not modelled (hold, sampling "
                        f"of the description): {1.0 / seg.dt:g} Hz does not resolve the "
                        "model's dynamics (dvt_identify.fitrate.resolves_intersample)"))
            out.append(seg)
    return out


def used_inputs(desc: Description) -> set[str]:
    """Inputs the baseline model uses: a non-zero column of the structure's ``B`` or an input
    of a model effect."""
    structure = desc.structure
    theta = np.array([p.initial for p in structure.params], dtype=float)
    _, B, _ = structure.matrices(theta)
    names = set(desc.input_names)
    used = {n for j, n in enumerate(desc.input_names) if np.any(B[:, j] != 0.0)}
    for eff in desc.make_model_effects():
        if 0 <= eff.index < len(desc.input_names):
            used.add(desc.input_names[eff.index])
    return used & names


def drop_unexcited_model_effects(desc: Description, est: Sequence[Segment]
                                 ) -> tuple[Description, list[str]]:
    """Remove model effects whose input is constant in every estimation segment (e.g. the
    band of a gear the run never used): their parameters could not be identified.

    Returns:
        The description without them and their labels.
    """
    keep, dropped = [], []
    for spec, eff in zip(desc.model_effects, desc.make_model_effects(), strict=True):
        j = eff.index
        if 0 <= j < len(desc.input_names) and all(
                _constant(seg.u[:, j], desc.checks) for seg in est):
            dropped.append(eff.label())
        else:
            keep.append(spec)
    return replace(desc, model_effects=tuple(keep)), dropped


def _read(est_bags: Sequence[str | Path], val_bags: Sequence[str | Path], desc: Description,
          sink: list[str] | None = None) -> tuple[list[Segment], list[Segment]]:
    """Estimation and validation segments; the data warnings (unused parts of a recording)
    are always shown on stderr, also when quiet.

    Raises:
        DataError: a bag used for both, or unusable data.
    """
    est_paths = [str(Path(b).resolve()) for b in est_bags]
    for b in val_bags:
        if str(Path(b).resolve()) in est_paths:
            raise DataError(f"{b}: used for both estimation and validation; validation must be "
                            "separate data")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        est = load_segments(est_bags, desc)
        val = load_segments(val_bags, desc)
    for w in caught:
        if issubclass(w.category, DataWarning):
            print(f"[dvt-identify] warning: {w.message}", file=sys.stderr, flush=True)
            if sink is not None:
                sink.append(str(w.message))
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return est, val


def _distinct(est: Sequence[str | Path], val: Sequence[str | Path],
              test: Sequence[str | Path]) -> None:
    """Refuse a test bag that is also an estimation or validation bag."""
    seen = {str(Path(b).resolve()) for b in [*est, *val]}
    for b in test:
        if str(Path(b).resolve()) in seen:
            raise DataError(f"{b}: used as test data and for estimation or validation; the "
                            "test must be separate data")


def loop_config(desc: Description, augment: bool = True, starts: int | None = None,
                fit_decimate: int | None = None) -> LoopConfig:
    """The description's loop options with the caller's overrides (``None``: keep)."""
    cfg = LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate)
    return replace(cfg, augment=augment,
                   starts=cfg.starts if starts is None else max(1, starts),
                   fit_decimate=cfg.fit_decimate if fit_decimate is None
                   else max(1, fit_decimate))


def run(est_bags: Sequence[str | Path], val_bags: Sequence[str | Path], out_dir: str | Path,
        description: str | None = None, augment: bool = True, starts: int | None = None,
        fit_decimate: int | None = None, quiet: bool = False, plots: bool = True,
        progress: Progress | None = None, test_bags: Sequence[str | Path] = (),
        select_on: str = "validation", init_window: int = 0, series: bool = True,
        mcap: bool = False, initial: Mapping[str, float] | None = None
        ) -> IdentificationResult:
    """The whole pipeline; returns the result after writing the report to ``out_dir`` (with
    its PNG plots unless ``plots`` is false).

    Args:
        est_bags, val_bags: estimation and validation bag directories (distinct).
        out_dir: report directory.
        description: description file or bundled name (``None``: the default, ``dvt``).
        augment: run the augment loop after the baseline.
        starts, fit_decimate: overrides of the description's (``None``: keep).
        quiet: no progress lines (data warnings are still shown).
        plots: write the PNG plots.
        progress: receives the progress lines (default: stderr).
        test_bags: read only after every choice is made (:mod:`dvt_identify.series`); their
            figures took no part in fitting or choosing effects.
        select_on: ``validation`` (the validation bags choose the effects), ``holdout``
            (the last 30 % of each estimation segment chooses them) or ``cv`` (leave-one-bag-out
            cross-validation across the estimation bags; with one bag, across contiguous blocks
            of it, :func:`dvt_identify.series.block_split`); with ``holdout`` and ``cv``
            the validation bags are test data, read after every choice.
        init_window: every simulation (fit, selection, test) starts from the state the first
            ``init_window`` samples of its segment give (benchmark style); 0: initial states
            estimated (free in the fit).
        series: write ``series.npz`` and ``series/*.csv``
            (:func:`dvt_identify.series.write_series`).
        mcap: also write each segment's series as an MCAP bag with the model topics.
        initial: start the baseline fit from these values (structure and model-effect
            parameter name -> value, e.g. the model in use: :func:`model_initial`); the
            description's own initial values are kept as a further start
            (:meth:`Description.with_initial`, :meth:`Description.start_values`).

    Raises:
        DvtIdentifyError: bad input (description, bags, data, ``initial``).
    """
    from dvt_identify import series as series_mod

    if select_on not in ("validation", "holdout", "cv"):
        raise DataError(f"select_on: expected validation, holdout or cv, got {select_on!r}")
    if select_on in ("holdout", "cv"):  # the validation bags become test data
        test_bags, val_bags = [*val_bags, *test_bags], []
    _distinct(est_bags, val_bags, test_bags)
    t0 = time.monotonic()
    say = _quiet if quiet else (progress or stderr_progress)
    desc = load_description(description)
    if initial:
        desc = desc.with_initial(initial)
        say("initial values: " + ", ".join(f"{k} {v:.6g}" for k, v in initial.items())
            + " (the description's kept in prior_starts)")
    say(f"description {description_label(desc)}; reading {len(est_bags)} estimation and "
        f"{len(val_bags)} validation bag(s)")
    data_warnings: list[str] = []
    est, val = _read(est_bags, val_bags, desc, data_warnings)
    # is this recording enough? (folds in drop_unexcited_model_effects: unused bands)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    for line in chk.headline():  # what is fixed or not determined: always shown (stderr)
        if chk.enough:
            say(line)
        else:
            print(f"[dvt-identify] check: {line}", file=sys.stderr, flush=True)
    for line in chk.summary()[len(chk.headline()):]:
        say(line)
    check_excitation(est, desc.checks,
                     {s.name: f"{s.topic} {s.field}[{s.joint}]" for s in desc.inputs},
                     used=used_inputs(desc))
    say(f"data read in {time.monotonic() - t0:.1f} s: "
        + ", ".join(f"{Path(s.name).name} {s.n} samples at {1 / s.dt:g} Hz" for s in est + val))
    cfg = replace(loop_config(desc, augment, starts, fit_decimate), init_window=init_window)
    if select_on == "holdout":
        fit_part, held = series_mod.holdout_split(est)
        say(f"selection on the held-out last {100 * series_mod.HOLDOUT_FRACTION:g} % of each "
            "estimation segment")
        result = refit_whole(identify(fit_part, held, desc, cfg, say, check=chk), est, say)
    elif select_on == "cv":
        if len({bag_of(s.name) for s in est}) < CV_MIN_BAGS:
            # one record: the folds are contiguous blocks of it (cross-validation over segments)
            est = series_mod.block_split(est)
            say(f"cross-validation over {len(est)} contiguous blocks of the estimation "
                "record(s): each block simulated by the model fitted on the others")
        result = identify(est, [], desc, cfg, say, check=chk, cross_validate=True)
    else:
        result = identify(est, val, desc, cfg, say, check=chk)
    result.selection = select_on
    result.data_warnings = data_warnings
    # the Fisher rule is local: taken again at the fitted values (identifiability.at_fit)
    result.identifiability = identifiability.at_fit(
        chk, desc, est, result.final.parameters(),
        max(1.0 - f / 100.0 for f in result.final.est.fit_percent))
    if result.identifiability.revised:
        print(f"[dvt-identify] check: {result.identifiability.revised_line()}",
              file=sys.stderr, flush=True)
    test: list[Segment] = []
    if test_bags:  # read only now: every choice is made
        _, test = _read([], test_bags, desc, data_warnings)
        result.test = series_mod.evaluate_test(
            result.baseline.fit, result.final.fit, test, init_window,
            result.reference.model if result.reference is not None else None)
        try:
            from dvt_identify.disagree import compare_records

            result.agreement = compare_records(
                result.final.fit, result.records(), test,
                desc.structure.force_unit)
            say(result.agreement.statement)
        except DvtIdentifyError as exc:
            say(f"records not compared: {exc}")
        if result.agreement is not None and result.agreement.disagree:
            _offer_carrier(result, test, init_window, desc.structure.force_unit, say)
        try:
            from dvt_identify.spread import figure_spread

            result.spread = figure_spread(
                result.final.fit, test, init_window,
                reference=result.reference.model if result.reference is not None else None)
            say(result.spread.statement)
        except DvtIdentifyError as exc:
            result.notes.append(f"Test figure's spread not measured: {exc}")
            say(result.notes[-1])
        say("test fit (no part in any choice): " + ", ".join(
            f"{n} {b:.2f} % -> {f:.2f} %" for n, b, f in zip(
                result.test.final.output_names, result.test.baseline.fit_percent,
                result.test.final.fit_percent, strict=True)))
    paths = write_report(result, out_dir, plots_enabled=plots)
    if series:
        sp = series_mod.write_series(series_mod.collect(result, result.test, test), out_dir,
                                     desc, mcap=mcap)
        say(f"series written: {sp['npz']}")
    say(f"report written: {paths['json']} and {paths['md']} ({time.monotonic() - t0:.1f} s)")
    return result


def _offer_carrier(result: IdentificationResult, test: Sequence[Segment], init_window: int,
                   unit: str, say: Progress) -> None:
    """Score the final model carrying the disagreement on ``test``, the carrier chosen on the
    estimation records alone (:func:`dvt_identify.carrier.offer_carrier`); why not, as a note."""
    from dvt_identify.carrier import offer_carrier

    try:
        result.carrier = offer_carrier(
            result.final.fit, result.records(), test, init_window,
            result.test.final, unit)
        say(result.carrier.statement)
    except DvtIdentifyError as exc:
        result.notes.append(f"No model carrying the records' disagreement offered: {exc}")
        say(result.notes[-1])


def check_recording(est_bags: Sequence[str | Path], description: str | None = None
                    ) -> tuple[identifiability.Identifiability, list[str]]:
    """``dvt-identify --check``: is the estimation data enough? (no fit); returns the check
    and the data warnings of loading.

    Raises:
        DvtIdentifyError: bad input (description, bags, data).
    """
    desc = load_description(description)
    data_warnings: list[str] = []
    est, _ = _read(est_bags, [], desc, data_warnings)
    return identifiability.check(desc, est), data_warnings


def model_initial(desc: Description, values: Mapping[str, Any]) -> dict[str, float]:
    """The description's initial values that the model node's parameter ``values`` (as
    :func:`dvt_model.config.resolve` takes them; ``M``/``D`` empty: its parameter set's) set:
    ``M11, M12, M22, D11, D12, D22`` from ``M``/``D`` (the inverse of :func:`model_push`) and
    each band model effect's first parameter (``band_gain_ring1``, ``band_time_constant_brake1``
    ...) from ``band_gain``/``band_time_constant`` of its band. Only the names the description
    has are returned (none for a structure without ``M11..D22``).

    Raises:
        DvtModelError: ``values`` the model node would refuse.
    """
    from dvt_model.config import resolve

    cfg = resolve(values)
    M, D = np.asarray(cfg.rigid.M, float), np.asarray(cfg.rigid.D, float)
    node = {"M11": M[0, 0], "M12": 0.5 * (M[0, 1] + M[1, 0]), "M22": M[1, 1],
            "D11": D[0, 0], "D12": 0.5 * (D[0, 1] + D[1, 0]), "D22": D[1, 1]}
    names = {p.name for p in desc.structure.params}
    out = {k: float(v) for k, v in node.items() if k in names}
    per_band = {"band_gain": np.asarray(cfg.brake.gains, float),
                "band_time_constant": np.asarray(cfg.brake.time_constants, float)}
    inputs = desc.input_names
    for eff in desc.make_model_effects():
        key = eff.band_parameter
        if key not in per_band or not eff.params or not 0 <= eff.index < len(inputs):
            continue
        name = inputs[eff.index]
        if name in ("brake1", "brake2", "brake3"):
            v = float(per_band[key][int(name[-1]) - 1])
            out[eff.params[0].name] = v
    specs = {p.name: p for p in [*desc.structure.params,
                                 *(q for e in desc.make_model_effects() for q in e.params)]}
    return {k: v for k, v in out.items()
            if math.isfinite(v) and specs[k].lower <= v <= specs[k].upper}


def structure_at_bounds(result: IdentificationResult, stage: str = "final") -> list[str]:
    """The structure parameters of a stage's optimum (``final`` or ``baseline``) that sit at a
    bound their start (the description's initial value) was not at, as ``"M22 = 1e-06 at its
    lower bound 1e-06"`` (:meth:`dvt_identify.fit.OEFit.bounds_hit`)."""
    fit = (result.final if stage == "final" else result.baseline).fit
    model = fit.model
    out = []
    for name, _ in fit.bounds_hit(fit.theta_):
        i = model.names.index(name)
        if i >= model.n_struct:
            continue
        spec = model.specs[i]
        v = float(fit.theta_[i])
        lower = math.isfinite(spec.lower) and (not math.isfinite(spec.upper)
                                               or abs(v - spec.lower) <= abs(v - spec.upper))
        bound = spec.lower if lower else spec.upper
        if spec.initial == bound:
            continue
        out.append(f"{name} = {v:.6g} at its {'lower' if lower else 'upper'} bound {bound:g}")
    return out


def model_push(result: IdentificationResult, held: Mapping[str, float] | None = None) -> Push:
    """The model node's parameters for the result's final model (the description's model
    effects, as kept, are the node's band model; ``held``: structure values the fit held,
    :func:`dvt_identify.push.model_node_parameters`). The band values are pushed only when
    they predict the result's validation segments better than the values the fit started
    from (:func:`dvt_identify.push.band_check`).

    Raises:
        PushError: not the DVT structure, or a value the node would refuse.
    """
    n_model = len(result.description.make_model_effects())
    return model_node_parameters(result.final, n_model,
                                 input_joints=[s.joint for s in result.description.inputs],
                                 held=held, validation=result.val_segments or None)


class TerminalProgress:
    """``dvt-identify``'s progress on a terminal (a :class:`~dvt_model.progress.ProgressLine`):
    the milestones (the baseline's figures, each acceptance, the test figure, the report) stay as
    lines; everything else (reading, fit starts, candidates scored, refits) rewrites one status
    line: ``round 2: scored 7/20 (35 %): windage@carrier3 ...``, a fit start with the stage it
    belongs to. Silent when the line is (stderr is not a terminal)."""

    MILESTONES = ("baseline:", "test fit", "report written", "series written")

    def __init__(self, line: ProgressLine) -> None:
        self.line = line
        self.context = ""
        self.round = ""
        self.scored = 0
        self.to_score = 0

    def __call__(self, msg: str) -> None:
        m = " ".join(msg.split())
        if m.startswith(self.MILESTONES) or ": ACCEPTED " in m:
            self.line.note(f"{self.line.prefix}{m}")
            return
        if m.startswith("round ") and ": scoring " in m:
            head, _, rest = m.partition(": scoring ")
            self.round, self.scored = head, 0
            self.to_score = int(rest.split()[0]) if rest.split()[0].isdigit() else 0
            self.context = m
        elif m.startswith("score "):
            self.scored += 1
            m = f"{self.round}: scored {fraction(self.scored, self.to_score)}: {m[6:]}"
        elif m.startswith("start "):  # a fit start: after the (short) stage it belongs to
            m = f"{self.context}; {m}" if self.context else m
        elif m.startswith(("round ", "baseline fit")):
            ctx = m if m.startswith("round ") else m.split(":")[0]
            self.context = ctx if len(ctx) <= 48 else ctx[:47] + "…"
        self.line.update(m)

