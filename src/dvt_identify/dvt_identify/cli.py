"""``dvt-identify``: fit, trace and report from bags.

    dvt-identify BAG... --validate BAG... --out DIR [--description FILE_OR_NAME] [--no-augment]

Reads the estimation and validation bags named by the actuator description (default ``dvt``),
checks and pre-processes them, fits the baseline output-error model, runs the augment loop and
writes ``DIR/report.json``, ``DIR/report.md`` and PNG plots. Progress goes to stderr; the last line
on stdout summarises the result. Bad input ends with exit status 2 and one line
``dvt-identify: error: <reason>`` on stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from dvt_identify.data import (
    DataWarning,
    Segment,
    _constant,
    check_excitation,
    decimate,
    load_bag_segments,
    lowpass,
)
from dvt_identify.description import DEFAULT_DESCRIPTION, Description, load_description
from dvt_identify.errors import DataError, DvtIdentifyError
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.oe import stderr_progress
from dvt_identify.report import write_report


def load_segments(bags: Sequence[str | Path], desc: Description) -> list[Segment]:
    """Read, check and pre-process ``bags`` as the description says.

    Raises:
        DataError: naming the bag, topic and problem.
    """
    out = []
    for bag in bags:  # a bag split at long gaps gives several segments
        for seg in load_bag_segments(bag, desc.inputs, desc.outputs, desc.checks):
            lp = desc.preprocess.lowpass
            if lp:
                seg = lowpass(seg, float(lp["cutoff_hz"]), int(lp.get("order", 4)),
                              bool(lp.get("zero_phase", True)))
            seg = decimate(seg, desc.preprocess.decimate)
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
    band of a gear the run never used): their parameters could not be identified."""
    keep, dropped = [], []
    for spec, eff in zip(desc.model_effects, desc.make_model_effects(), strict=True):
        j = eff.index
        if 0 <= j < len(desc.input_names) and all(
                _constant(seg.u[:, j], desc.checks) for seg in est):
            dropped.append(eff.label())
        else:
            keep.append(spec)
    return replace(desc, model_effects=tuple(keep)), dropped


def run(est_bags: Sequence[str], val_bags: Sequence[str], out_dir: str | Path,
        description: str | None = None, augment: bool = True, starts: int | None = None,
        fit_decimate: int | None = None, quiet: bool = False, plots: bool = True
        ) -> IdentificationResult:
    """Whole pipeline; returns the result after writing the report (with its PNG plots unless
    ``plots`` is false).

    Raises:
        DvtIdentifyError: bad input (description, bags, data).
    """
    t0 = time.monotonic()
    say = (lambda _m: None) if quiet else stderr_progress
    desc = load_description(description)
    est_paths = [str(Path(b).resolve()) for b in est_bags]
    for b in val_bags:
        if str(Path(b).resolve()) in est_paths:
            raise DataError(f"{b}: used for both estimation and validation; validation must be "
                            "separate data")
    say(f"description {desc.name} ({desc.source}); reading {len(est_bags)} estimation and "
        f"{len(val_bags)} validation bag(s)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        est = load_segments(est_bags, desc)
        val = load_segments(val_bags, desc)
    for w in caught:  # unused parts of a recording: always shown, also with --quiet
        if issubclass(w.category, DataWarning):
            print(f"[dvt-identify] warning: {w.message}", file=sys.stderr, flush=True)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    desc, dropped = drop_unexcited_model_effects(desc, est)
    for label in dropped:
        say(f"model effect {label} dropped: its input never varies in the estimation data")
    check_excitation(est, desc.checks,
                     {s.name: f"{s.topic} {s.field}[{s.joint}]" for s in desc.inputs},
                     used=used_inputs(desc))
    say(f"data read in {time.monotonic() - t0:.1f} s: "
        + ", ".join(f"{Path(s.name).name} {s.n} samples at {1 / s.dt:g} Hz" for s in est + val))
    cfg = LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate)
    over: dict[str, object] = {"augment": augment}
    if starts is not None:
        over["starts"] = max(1, starts)
    if fit_decimate is not None:
        over["fit_decimate"] = max(1, fit_decimate)
    cfg = replace(cfg, **over)  # type: ignore[arg-type]
    result = identify(est, val, desc, cfg, say)
    paths = write_report(result, out_dir, plots_enabled=plots)
    say(f"report written: {paths['json']} and {paths['md']} ({time.monotonic() - t0:.1f} s)")
    return result


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status."""
    ap = argparse.ArgumentParser(
        prog="dvt-identify",
        description="Output-error identification with residual tracing from rosbag2 bags.")
    ap.add_argument("bags", nargs="+", help="estimation bag directories (fitted jointly)")
    ap.add_argument("--validate", nargs="+", required=True, metavar="BAG",
                    help="validation bag directories (never used for fitting)")
    ap.add_argument("--out", required=True, help="output directory for the report")
    ap.add_argument("--description", default=DEFAULT_DESCRIPTION,
                    help=f"actuator description: YAML file or bundled name (default "
                         f"{DEFAULT_DESCRIPTION})")
    ap.add_argument("--no-augment", action="store_true", help="fit the baseline only")
    ap.add_argument("--starts", type=int, default=None, help="starts of the baseline fit")
    ap.add_argument("--fit-decimate", type=int, default=None,
                    help="decimate estimation data for fitting (figures stay at full rate)")
    ap.add_argument("--no-plots", action="store_true",
                    help="write report.json and report.md only (no PNG plots; faster)")
    ap.add_argument("--quiet", action="store_true", help="no progress on stderr")
    args = ap.parse_args(argv)
    try:
        result = run(args.bags, args.validate, args.out, args.description,
                     augment=not args.no_augment, starts=args.starts,
                     fit_decimate=args.fit_decimate, quiet=args.quiet,
                     plots=not args.no_plots)
    except DvtIdentifyError as exc:
        print(f"dvt-identify: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"dvt-identify: error: {exc}", file=sys.stderr)
        return 2
    fin = result.final
    acc = [d.score.label for d in result.accepted] or ["none"]
    print("validation fit: " + ", ".join(
        f"{n} {b:.2f} % -> {f:.2f} %" for n, b, f in zip(fin.val.output_names,
                                                          result.baseline.val.fit_percent,
                                                          fin.val.fit_percent, strict=True))
          + f"; accepted: {', '.join(acc)}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
