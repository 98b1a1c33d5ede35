"""What ``dvt-launch`` does with a recording once the run ended: the sidecar files and the check
(pure: no rclpy; the bag is read through :mod:`dvt_model.recording`).

:func:`finish_recording` copies the plant's ``truth.yaml`` into the bag, writes ``run.yaml``
(how the run was made, with the check) and returns the launcher's exit status;
:func:`check_bag` measures the recording's completeness; :func:`first_command_time` finds the
experiment's t = 0 in it.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dvt_driver.system.launch_args import experiment_of
from dvt_model.contract import COMMAND_PATTERN, SAMPLE_TOPICS
from dvt_model.errors import BagError
from dvt_model.recording import (
    TRUTH_FILE,
    first_log_time,
    is_bag,
    read_run,
    read_topic_series,
    sample_period,
    write_run_info,
)

__all__ = ["check_bag", "finish_recording", "first_command_time"]


def first_command_time(path: Path) -> int | None:
    """Log time [ns] of the first ``/dvt/cmd/*`` message in the bag (the experiment's t = 0:
    every experiment sends its first command at t = 0), ``None`` if there is none or the bag
    does not read (:func:`check_bag` reports that)."""
    try:
        return first_log_time(path, COMMAND_PATTERN)
    except BagError:
        return None


def check_bag(path: Path, rate: float) -> dict[str, Any]:
    """Read a recording back and measure its completeness.

    Returns ``samples`` (aligned pairs), ``duration_s``, ``rate_hz`` (median), ``unmatched``
    (stamps in only one of the two topics), ``unmatched_inside`` (those between the first and
    the last aligned sample: the ones at the ends only mean the recorder subscribed to, or left,
    the two topics a few samples apart), ``missing`` (samples missing between consecutive
    aligned stamps, from the nominal period ``1 / rate``: lost samples, or a forward step of the
    driver's stamp mapping), ``step_ms`` (smallest and largest stamp step), ``topics`` and
    ``bytes`` (size on disk).

    Raises:
        BagError: the recording does not read back as a contract recording.
    """
    run = read_run(path)
    inside = 0
    if run.n:
        lo, hi = int(run.stamps_ns[0]), int(run.stamps_ns[-1])
        for topic in SAMPLE_TOPICS:
            st = read_topic_series(path, topic).stamps_ns
            st = st[(st >= lo) & (st <= hi)]
            inside += int(st.size - np.isin(st, run.stamps_ns).sum())
    period = sample_period(run)
    size = sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    steps = np.diff(run.stamps_ns) * 1e-9
    missing = int(np.sum(np.maximum(np.round(steps * rate) - 1.0, 0.0))) if steps.size else 0
    return {"samples": run.n, "duration_s": round(run.duration, 3),
            "rate_hz": round(1.0 / period, 2) if period > 0 else None,
            "unmatched": run.unmatched, "unmatched_inside": inside, "missing": missing,
            "step_ms": [round(float(steps.min()) * 1e3, 3), round(float(steps.max()) * 1e3, 3)]
            if steps.size else [],
            "first_stamp_ns": int(run.stamps_ns[0]) if run.n else None,
            "last_stamp_ns": int(run.stamps_ns[-1]) if run.n else None,
            "topics": list(run.topics), "bytes": size}


def finish_recording(args: argparse.Namespace, record: Path, logdir: Path, rate: float,
                     started: float, statuses: dict[str, int | None], exp_status: int | None,
                     status: int, say: Callable[[str], None]) -> int:
    """Copy ``truth.yaml`` (the plant's, in ``logdir``) and write ``run.yaml`` into the bag
    ``record`` and check it (unless ``--no-check``); returns the launcher's exit status
    (``status``, or 1 when the bag is not closed or does not read back, 4 when it misses more
    than ``--max-missing`` samples or does not hold the whole experiment)."""
    if not is_bag(record):
        say(f"error: {record} has no metadata.yaml (the recorder did not close the bag; "
            f"`dvt-bag recover {record}` restores what was written)")
        return status or 1
    if args.mode == "sim":
        truth = logdir / TRUTH_FILE
        if truth.exists():
            shutil.copyfile(truth, record / TRUTH_FILE)  # as the plant wrote it
        else:
            say(f"warning: the plant wrote no {truth}; the bag has no {TRUTH_FILE}")
    run: dict[str, Any] = {
        "made_by": "dvt-launch " + shlex.join(sys.argv[1:] if sys.argv[1:] else [args.mode]),
        "mode": args.mode,
        "started_unix": round(started, 3),
        "sample_rate_hz": rate,
        "params": args.params,
        "hidden": getattr(args, "hidden", None),
        "plant_seed": getattr(args, "seed", None),
        "plant_changes": list(getattr(args, "change_at", [])),
        "experiment": None,
        "exit_status": dict(statuses),
    }
    if args.experiment is not None:
        run["experiment"] = experiment_of(args).to_mapping()
        run["experiment_status"] = exp_status
        run["experiment_start_ns"] = first_command_time(record)
    if not args.no_check:
        status = _check(args, record, rate, run, status, say)
    write_run_info(record, run)
    return status


def _check(args: argparse.Namespace, record: Path, rate: float, run: dict[str, Any],
           status: int, say: Callable[[str], None]) -> int:
    """Check the bag into ``run["check"]``; returns the status."""
    try:
        run["check"] = c = check_bag(record, rate)
        say(f"bag {record}: {c['samples']} samples over {c['duration_s']} s "
            f"({c['rate_hz']} Hz), {c['unmatched']} unmatched ({c['unmatched_inside']} "
            f"inside), {c['missing']} missing between stamps, stamp steps {c['step_ms']} "
            f"ms, {c['bytes'] / 1e6:.2f} MB")
        if args.max_missing is not None and \
                c["missing"] + c["unmatched_inside"] > args.max_missing:
            say(f"error: more than --max-missing {args.max_missing} samples missing or "
                "unmatched inside the recording")
            status = status or 4
        start = run.get("experiment_start_ns")
        if args.experiment is not None:
            end = None if start is None else \
                start + round(run["experiment"]["duration_s"] * 1e9)
            inside = (start is not None and end is not None
                      and c["first_stamp_ns"] <= start and end <= c["last_stamp_ns"])
            c["experiment_inside"] = inside
            if not inside:
                say("error: the recording does not hold the whole experiment (first "
                    f"command at {start} ns, samples {c['first_stamp_ns']}.."
                    f"{c['last_stamp_ns']} ns)")
                status = status or 4
    except Exception as exc:  # report, keep the bag
        say(f"error: the recorded bag does not read back: {exc}")
        run["check"] = {"error": str(exc)}
        status = status or 1
    return status
