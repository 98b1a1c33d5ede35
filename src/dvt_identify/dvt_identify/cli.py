"""``dvt-identify``: fit, trace and report from bags.

    dvt-identify BAG... --validate BAG... --out DIR [--description FILE_OR_NAME] [--no-augment]

Runs the identification pipeline (:func:`dvt_identify.pipeline.run`): reads the estimation and
validation bags named by the actuator description (default ``dvt``), checks and pre-processes
them, fits the baseline output-error model, runs the augment loop and writes
``DIR/report.json``, ``DIR/report.md`` and PNG plots. Progress goes to stderr; the last line on
stdout summarises the result. Bad input ends with exit status 2 and one line
``dvt-identify: error: <reason>`` on stderr.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dvt_identify.description import DEFAULT_DESCRIPTION
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.pipeline import run


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
