"""``dvt-identify-batch``: identify a set of recordings in parallel (docs/batch.md).

    dvt-identify-batch MANIFEST --out DIR [--scheduler ADDRESS | --workers N] [--check] [--quiet]

Reads and checks the whole manifest (:func:`dvt_identify.batch.load_manifest`) and the output
folder before any job runs, then runs each job (one :func:`dvt_identify.pipeline.run`) as a
Dask task (:func:`dvt_identify.batch_dask.run_batch`): on a local cluster of ``N`` worker
processes (default one per job, at most the CPU count), or on the workers of the scheduler at
``ADDRESS``. Each job writes ``DIR/<name>/`` (report.json, report.md, plots, series,
job.log); ``DIR/summary.json`` and ``DIR/summary.md`` list every job. A line on stderr as each
job ends (unless ``--quiet``); the last line on stdout counts them. ``--check``: only check
and print the plan.

Exit status: 0 every job ok; 1 nothing run (bad manifest or output folder, no scheduler or
workers), with ``dvt-identify-batch: error: ...`` on stderr (each problem on a line); 2 bad
usage; 3 some job failed (the summary says which and why); 130 interrupted (Ctrl-C or SIGTERM:
the cluster is closed and the summary lists the jobs not finished as failed).
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType

from dvt_identify.batch import FAILED, OK, TOOL, JobOutcome, check_out, load_manifest, plan_lines
from dvt_identify.errors import DvtIdentifyError

EXIT_ERROR = 1
"""Nothing was run: bad manifest, output folder or cluster."""
EXIT_USAGE = 2
"""Bad usage (argparse's)."""
EXIT_JOB_FAILED = 3
"""The batch ran and some job failed."""
EXIT_INTERRUPTED = 130
"""Stopped by Ctrl-C or SIGTERM (the cluster closed, a summary of what finished)."""


def _interrupt(signum: int, frame: FrameType | None) -> None:
    """SIGTERM as Ctrl-C: the cluster is closed and the summary written."""
    raise KeyboardInterrupt


def _progress(total: int) -> Callable[[JobOutcome], None]:
    """A line on stderr as each of ``total`` jobs ends."""
    done = 0

    def say(o: JobOutcome) -> None:
        nonlocal done
        done += 1
        where = o.worker.get("address") or "?"
        wall = "" if o.wall_s is None else f" in {o.wall_s:.1f} s (CPU {o.cpu_s or 0:.1f} s)"
        tail = f": {o.error}" if o.status != OK else ""
        print(f"[{TOOL}] {done}/{total} {o.name} {o.status}{wall} on {where}{tail}",
              file=sys.stderr, flush=True)
    return say


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit status."""
    ap = argparse.ArgumentParser(
        prog=TOOL, description="Identify a set of recordings in parallel (Dask), one report "
                               "per job and a summary.")
    ap.add_argument("manifest", help="YAML (or .json) manifest of the jobs (docs/batch.md)")
    ap.add_argument("--out", required=True, help="output folder: OUT/<job>/ and OUT/summary.*")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on the workers of this Dask scheduler (tcp://host:8786) "
                            "instead of a local cluster")
    where.add_argument("--workers", type=int, metavar="N",
                       help="local worker processes, one thread each (default: one per job, at "
                            "most the CPU count)")
    ap.add_argument("--check", action="store_true",
                    help="only check the manifest and the output folder and print the plan")
    ap.add_argument("--quiet", action="store_true", help="no line per finished job")
    args = ap.parse_args(argv)
    if args.workers is not None and args.workers < 1:
        ap.error(f"--workers: expected at least 1, got {args.workers}")
    try:
        jobs = load_manifest(args.manifest)
        check_out(args.out, jobs)
        if args.check:
            for line in plan_lines(jobs, args.out):
                print(line)
            print(f"{len(jobs)} job(s): manifest ok")
            return 0
        from dvt_identify.batch_dask import run_batch  # Dask only when running

        signal.signal(signal.SIGTERM, _interrupt)
        summary = run_batch(jobs, args.out, manifest=args.manifest, scheduler=args.scheduler,
                            workers=args.workers,
                            on_done=None if args.quiet else _progress(len(jobs)))
    except (DvtIdentifyError, OSError) as exc:
        lines = str(exc).splitlines() or [type(exc).__name__]
        for line in lines:
            print(f"{TOOL}: error: {line}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        done = Path(args.out) / "summary.md"
        print(f"{TOOL}: interrupted; the cluster is closed"
              + (f"; summary of the jobs that finished: {done}" if done.exists() else ""),
              file=sys.stderr)
        return EXIT_INTERRUPTED
    c = summary["counts"]
    print(f"{len(jobs)} job(s): {c[OK]} ok, {c[FAILED]} failed; summary: "
          f"{args.out}/summary.md")
    return EXIT_JOB_FAILED if c[FAILED] else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
