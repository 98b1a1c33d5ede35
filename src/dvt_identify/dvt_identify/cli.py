"""``dvt-identify``: fit, trace and report from bags.

    dvt-identify BAG... --validate BAG... --out DIR [--description FILE_OR_NAME] [--no-augment]
                 [--test BAG...] [--select-on validation|holdout|cv] [--init-window N]
                 [--mcap]
    dvt-identify BAG... --check [--out DIR] [--description FILE_OR_NAME]

Runs the identification pipeline (:func:`dvt_identify.pipeline.run`): reads the estimation and
validation bags named by the actuator description (default ``dvt``), checks and pre-processes
them, fits the baseline output-error model, runs the augment loop and writes
``DIR/report.json``, ``DIR/report.md``, PNG plots and the series (``DIR/series.npz``,
``DIR/series/*.csv``, with ``--mcap`` bags; :mod:`dvt_identify.series`). The validation bags
choose the effects (a selection figure); ``--test`` bags are read after every choice and give
a figure that took no part in any. ``--select-on holdout`` chooses on the held-out end of the
estimation bags instead (the chosen model then refitted on the whole bags), ``--select-on
cv`` by cross-validation: leave-one-bag-out across the estimation bags, or across contiguous
blocks of a single bag (each simulated by the model
fitted on the others, the pooled out-of-fold errors in the acceptance test, the accepted model
fitted on all of them); both treat the ``--validate`` bags, if any, as test data. Progress goes
to stderr; stdout ends with the summary: the test figures first (RMSE and fit, the linear
reference beside them), then the selection figures and the accepted effects. Progress is one
line rewritten in place when stderr is a terminal (the baseline, each accepted effect and the
report stay as lines) and nothing when it is not (a pipe, a log); data warnings and errors are
always shown.

Exit status (as ``dvt-bag``): 0 success; 1 bad data or files (a bag that cannot be read or
checked, a bad description, a failed fit), with one line ``dvt-identify: error: <reason>`` on
stderr; 2 bad usage (unknown option, missing ``--validate``/``--out``), argparse's usage
message. ``dvt-bag recover
PATH`` is suggested only for a bag directory (or ``.mcap`` file) whose MCAP cannot be read.

``--check`` only asks whether the estimation bags are enough (no fit,
:mod:`dvt_identify.identifiability`): first the verdict and what is fixed at its prior or not
determined, each with the experiment the description names for it (its ``experiments``
section) or generic advice from the data and the model; then the data warnings, every
parameter's predicted relative standard deviation, and a last line ``enough: yes`` or
``enough: no, ...``. All on stdout (``DIR/check.json`` with ``--out``). Exit status 0 either
way.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from dvt_identify.description import DEFAULT_DESCRIPTION
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.identifiability import Identifiability
from dvt_identify.loop import IdentificationResult
from dvt_identify.metrics import Figures
from dvt_identify.pipeline import TerminalProgress, check_recording, run
from dvt_model.progress import ProgressLine

EXIT_DATA = 1
"""Exit status for bad data or files (as ``dvt-bag``)."""
EXIT_USAGE = 2
"""Exit status for bad usage (argparse's)."""
def error_line(exc: BaseException) -> str:
    """The one error line for ``exc``: its first line (the recording layer words the
    ``dvt-bag recover`` hint, :func:`dvt_model.recording.layout.recover_hint`)."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def check_lines(chk: Identifiability, data_warnings: Sequence[str]) -> list[str]:
    """What ``--check`` prints: the verdict and what is fixed or not determined first, then the
    data warnings, a table of every parameter's predicted relative std, and the ``enough:``
    line."""
    lines = list(chk.summary())
    lines += [f"warning: {w}" for w in data_warnings]
    lines.append("parameter: predicted relative std (prior): verdict")
    for p in chk.parameters:
        rs = p.predicted_relative_std
        fig = f"{100 * rs:.3g} %" if math.isfinite(rs) else "infinite"
        verdict = ("determined" if p.determined else
                   "not determined, fixed at its prior" if p.fixed else
                   "not determined, still fitted")
        lines.append(f"  {p.name}: {fig} ({p.prior:.6g}): {verdict}")
    if chk.enough:
        lines.append("enough: yes")
    else:
        cmds = chk.experiments()
        tail = "record " + " and ".join(cmds) if cmds else ""
        if chk.advice():
            tail += ("; " if tail else "") + "see the advice above"
        lines.append(f"enough: no, {tail}")
    return lines


def _check(args: argparse.Namespace) -> int:
    chk, data_warnings = check_recording(args.bags, args.description)
    for line in check_lines(chk, data_warnings):
        print(line)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        rep = {"estimation_bags": list(args.bags), "warnings": data_warnings, **chk.as_dict()}
        (out / "check.json").write_text(json.dumps(rep, indent=2, allow_nan=False) + "\n")
    return 0


def output_units(result: IdentificationResult) -> list[str]:
    """Each output's unit: the structure's angle unit for an output that is an angle state
    (``<member>_angle``), else its speed unit ("" when the description names none)."""
    st = result.description.structure
    states = getattr(st, "output_states", None) or st.state_names
    angle = str(getattr(st, "angle_unit", "") or "")
    return [angle if str(s).endswith("_angle") else (st.speed_unit or "") for s in states]


def summary_lines(result: IdentificationResult) -> list[str]:
    """What ``dvt-identify`` prints when done: the test figures first (when test bags were
    given: RMSE in the output's unit and fit, the final model and the linear reference side
    by side, then the same figure of the final model refitted on each half of its estimation
    data: how much it depends on them), then the selection figures and the accepted
    effects."""
    fin = result.final
    units = output_units(result)
    ref = result.reference
    lines = []
    t = result.test
    if t is not None:
        parts = []
        for j, n in enumerate(t.final.output_names):
            txt = (f"{n} RMSE {t.final.rmse[j]:.4g} {units[j]} (fit {t.final.fit_percent[j]:.2f} "
                   "%)").replace("  ", " ")
            if t.reference is not None:
                txt += (f", linear reference RMSE {t.reference.rmse[j]:.4g} {units[j]} (fit "
                        f"{t.reference.fit_percent[j]:.2f} %)").replace("  ", " ")
            parts.append(txt)
        lines.append("test (no part in any choice): " + "; ".join(parts))
        sp = getattr(result, "spread", None)
        if sp is not None:
            def halves(fs: Sequence[object], j: int) -> str:
                return " / ".join(f"{f.rmse[j]:.4g}" if isinstance(f, Figures) else "-"
                                  for f in fs)

            lines.append("test, the final model refitted on each half of its estimation data: "
                         + "; ".join(
                             f"{n} RMSE {halves([f for _, f in sp.parts], j)} {units[j]}"
                             .rstrip()
                             + (f" (linear reference likewise: "
                                f"{halves([f for _, f in sp.reference_parts], j)})"
                                if sp.reference is not None else "")
                             for j, n in enumerate(sp.output_names)))
    acc = [d.score.label for d in result.accepted] or ["none"]
    sel = {"validation": "validation fit (selection)",
           "holdout": "held-out fit (selection)",
           "cv": "out-of-fold fit (selection, cross-validation)"}.get(
               str(getattr(result, "selection", "validation")), "validation fit (selection)")
    lines.append(f"{sel}: " + ", ".join(
        f"{n} {b:.2f} % -> {f:.2f} %" for n, b, f in zip(fin.val.output_names,
                                                          result.baseline.val.fit_percent,
                                                          fin.val.fit_percent, strict=True))
        + ("" if ref is None else f" (linear reference, order {ref.model.order_}: "
           + ", ".join(f"{f:.2f} %" for f in ref.val.fit_percent) + ")")
        + f"; accepted: {', '.join(acc)}")
    if ref is not None and ref.val.mean_fit > fin.val.mean_fit:
        lines.append("warning: the physical model scores worse than the linear reference on "
                     "the selection data (see the report's first lines)")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status."""
    ap = argparse.ArgumentParser(
        prog="dvt-identify",
        description="Output-error identification with residual tracing from rosbag2 bags.")
    ap.add_argument("bags", nargs="+", help="estimation bag directories (fitted jointly)")
    ap.add_argument("--validate", nargs="+", metavar="BAG",
                    help="validation bag directories (never used for fitting; required "
                         "unless --check)")
    ap.add_argument("--out", help="output directory for the report (required unless --check)")
    ap.add_argument("--check", action="store_true",
                    help="only check whether the bags determine the model's parameters (no "
                         "fit); advice for those they do not: the description's experiment "
                         "or generic advice")
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
    ap.add_argument("--test", nargs="+", metavar="BAG", default=[],
                    help="test bag directories: read only after every choice is made; their "
                         "figures took no part in fitting or choosing effects")
    ap.add_argument("--select-on", choices=("validation", "holdout", "cv"),
                    default="validation",
                    help="data that choose the effects: the validation bags (default), the "
                         "held-out last 30 %% of each estimation bag (holdout: the chosen "
                         "model is then refitted on the whole bags), or "
                         "cross-validation (cv: leave-one-bag-out across the estimation bags, "
                         "or across contiguous blocks of a single bag); with holdout and cv the "
                         "--validate bags are test data")
    ap.add_argument("--init-window", type=int, default=0, metavar="N",
                    help="test initial states from the first N samples only (benchmark "
                         "style; figures on the rest)")
    ap.add_argument("--mcap", action="store_true",
                    help="also write the series as MCAP bags with the model topics (Foxglove)")
    args = ap.parse_args(argv)
    if not args.check and (not args.out or (not args.validate
                                            and args.select_on == "validation")):
        ap.error("--validate and --out are required (unless --check; --validate is optional "
                 "with --select-on holdout or cv)")
    try:
        if args.check:
            return _check(args)
        # progress: one line on a terminal, nothing when stderr is not one (warnings always)
        with ProgressLine.stderr("[dvt-identify] ") as line:
            result = run(args.bags, args.validate or [], args.out, args.description,
                         augment=not args.no_augment, starts=args.starts,
                         fit_decimate=args.fit_decimate, quiet=args.quiet,
                         progress=TerminalProgress(line), plots=not args.no_plots,
                         test_bags=args.test, select_on=args.select_on,
                         init_window=args.init_window, mcap=args.mcap)
    except (DvtIdentifyError, OSError) as exc:
        print(f"dvt-identify: error: {error_line(exc)}", file=sys.stderr)
        return EXIT_DATA
    for text in summary_lines(result):
        print(text)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
