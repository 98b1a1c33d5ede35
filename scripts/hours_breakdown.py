"""Where the hour of ``dvt-bench identify --hours 1`` goes: the identification of the cached
recording run in this process with a timestamp on each progress line (seconds since the start:
reading, the linear reference, the baseline fit, the drift check, each candidate score), and
with ``--profile`` the cProfile of the same run on one core (``DVT_IDENTIFY_WORKERS=1``), its
30 costliest calls by cumulative time (the figures of docs/identification.md §10).

The recording must exist: ``dvt-bench identify --hours 1`` makes it once (about 5 minutes).

Usage::

    .venv/bin/python scripts/hours_breakdown.py [--profile] [--cache DIR]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", action="store_true",
                    help="profile a serial run (DVT_IDENTIFY_WORKERS=1) instead of timing")
    ap.add_argument("--cache", type=Path, default=None,
                    help="the bench's cache (default: dvt-bench identify's)")
    a = ap.parse_args()
    if a.profile:
        os.environ["DVT_IDENTIFY_WORKERS"] = "1"
    from dvt_identify.bench_identify.hours import (
        RUN_MINUTES,
        SEED,
        default_cache,
        identify_runs,
        recording_dir,
    )

    where = recording_dir(a.cache or default_cache(), 1.0, RUN_MINUTES, SEED)
    done = where / "done.json"
    if not done.exists():
        print(f"hours_breakdown: no recording in {where}: run `dvt-bench identify --hours 1` "
              "first", file=sys.stderr)
        return 2
    info = json.loads(done.read_text())
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"{time.perf_counter() - t0:7.1f} s  {msg}", flush=True)
    prof = cProfile.Profile() if a.profile else None
    if prof:
        prof.enable()
    out = identify_runs(info["estimation"], [info["validation"]], "dvt", log=log)
    if prof:
        prof.disable()
        pstats.Stats(prof).sort_stats("cumulative").print_stats(30)
    print(json.dumps({k: out[k] for k in ("loop_seconds", "read_seconds",
                                          "baseline_fit_seconds", "validation_fit_percent")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
