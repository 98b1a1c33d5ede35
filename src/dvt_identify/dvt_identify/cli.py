"""``dvt-identify``: fit, trace and report from bags.

    dvt-identify BAG... --validate BAG... --out DIR [--description FILE_OR_NAME] [--no-augment]
                 [--test BAG...] [--select-on validation|holdout] [--init-window N] [--mcap]
    dvt-identify BAG... --check [--out DIR] [--description FILE_OR_NAME]

Runs the identification pipeline (:func:`dvt_identify.pipeline.run`): reads the estimation and
validation bags named by the actuator description (default ``dvt``), checks and pre-processes
them, fits the baseline output-error model, runs the augment loop and writes
``DIR/report.json``, ``DIR/report.md``, PNG plots and the series (``DIR/series.npz``,
``DIR/series/*.csv``, with ``--mcap`` bags; :mod:`dvt_identify.series`). The validation bags
choose the effects (a selection figure); ``--test`` bags are read after every choice and give
a figure that took no part in any (``--select-on holdout`` chooses on the held-out end of the
estimation bags instead and treats the validation bags as test data). Progress goes to
stderr; the last line on stdout summarises the result.

Exit status (as ``dvt-bag``): 0 success; 1 bad data or files (a bag that cannot be read or
checked, a bad description, a failed fit), with one line ``dvt-identify: error: <reason>`` on
stderr; 2 bad usage (unknown option, missing ``--validate``/``--out``), argparse's usage
message. ``dvt-bag recover PATH`` is suggested only for a bag directory (or ``.mcap`` file)
whose MCAP cannot be read.

``--check`` only asks whether the estimation bags are enough (no fit,
:mod:`dvt_identify.identifiability`): per parameter of the baseline model whether the recording
excites it, and for those it does not, the experiment (``dvt-experiment ...``) that would; the
verdict goes to stdout (``DIR/check.json`` with ``--out``). Exit status 0 either way.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from dvt_identify.description import DEFAULT_DESCRIPTION
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.pipeline import check_recording, run

EXIT_DATA = 1
"""Exit status for bad data or files (as ``dvt-bag``)."""
EXIT_USAGE = 2
"""Exit status for bad usage (argparse's)."""
_RECOVER = re.compile(r" \((?:if the recording was killed, try|the recording was probably "
                      r"killed; run) `dvt-bag recover (?P<path>[^`]+)`[^)]*\)")


def _has_mcap(path: Path) -> bool:
    """``path`` is a ``.mcap`` file or a directory holding one (what ``dvt-bag recover``
    rebuilds)."""
    if path.is_file():
        return path.suffix == ".mcap"
    return path.is_dir() and any(path.glob("*.mcap"))


def error_line(exc: BaseException) -> str:
    """The one error line for ``exc``: its first line, without a ``dvt-bag recover``
    suggestion for a path that holds no MCAP (a README is not a killed recording)."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__

    def drop(m: re.Match[str]) -> str:
        return m.group(0) if _has_mcap(Path(m.group("path"))) else " (not a bag directory)"

    return _RECOVER.sub(drop, text)


def _check(args: argparse.Namespace) -> int:
    chk, data_warnings = check_recording(args.bags, args.description)
    for w in data_warnings:
        print(f"warning: {w}")
    for line in chk.summary():
        print(line)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        rep = {"estimation_bags": list(args.bags), "warnings": data_warnings, **chk.as_dict()}
        (out / "check.json").write_text(json.dumps(rep, indent=2, allow_nan=False) + "\n")
    print("enough: " + ("yes" if chk.enough else "no, record " + " and ".join(chk.experiments())))
    return 0


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
                         "fit); names the experiment for those they do not")
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
    ap.add_argument("--select-on", choices=("validation", "holdout"), default="validation",
                    help="data that choose the effects: the validation bags (default), or the "
                         "held-out last 30 %% of each estimation bag (the --validate bags are "
                         "then test data)")
    ap.add_argument("--init-window", type=int, default=0, metavar="N",
                    help="test initial states from the first N samples only (benchmark "
                         "style; figures on the rest)")
    ap.add_argument("--mcap", action="store_true",
                    help="also write the series as MCAP bags with the model topics (Foxglove)")
    args = ap.parse_args(argv)
    if not args.check and (not args.out or (not args.validate
                                            and args.select_on != "holdout")):
        ap.error("--validate and --out are required (unless --check; --validate is optional "
                 "with --select-on holdout)")
    try:
        if args.check:
            return _check(args)
        result = run(args.bags, args.validate or [], args.out, args.description,
                     augment=not args.no_augment, starts=args.starts,
                     fit_decimate=args.fit_decimate, quiet=args.quiet,
                     plots=not args.no_plots, test_bags=args.test,
                     select_on=args.select_on, init_window=args.init_window, mcap=args.mcap)
    except (DvtIdentifyError, OSError) as exc:
        print(f"dvt-identify: error: {error_line(exc)}", file=sys.stderr)
        return EXIT_DATA
    fin = result.final
    acc = [d.score.label for d in result.accepted] or ["none"]
    print("validation fit: " + ", ".join(
        f"{n} {b:.2f} % -> {f:.2f} %" for n, b, f in zip(fin.val.output_names,
                                                          result.baseline.val.fit_percent,
                                                          fin.val.fit_percent, strict=True))
          + f"; accepted: {', '.join(acc)}"
          + ("" if result.test is None else "; test fit (no part in any choice): " + ", ".join(
              f"{n} {f:.2f} %" for n, f in zip(result.test.final.output_names,
                                               result.test.final.fit_percent, strict=True))))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
