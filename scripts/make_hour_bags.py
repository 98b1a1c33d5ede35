"""Record hours of the simulated plant for ``dvt-bench identify --hours`` (the benchmark of the
identifier, which depends on ``dvt_model`` only, runs this script to make its recording).

The plant with the ``physical`` parameter set and no hidden effect, driven offline through the
driver's supervisor (:func:`dvt_driver.plant.offline.record_offline`) with the ``watch``
experiment (neutral PRBS and multisine, then gears 1-3 engaged with PRBS, repeated with fresh
signals): runs of ``--run-minutes`` each (run ``k``: experiment seed ``SEED + k``, plant seed
``SEED + 10000 + k``; the last run shorter to make up the hours, at least 20 s) written as
``OUT/est-000``, ``OUT/est-001``, ..., and one ``ident`` run (experiment seed ``SEED + 9999``)
as ``OUT/val``; the runs are recorded on both cores. ``OUT/done.json`` is written last (what
was made, and how long it took).

Usage: ``.venv/bin/python scripts/make_hour_bags.py OUT --hours H [--run-minutes 5]
[--seed 0]``; prints ``done.json``'s content.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify.parallel import fork_map
from dvt_model.params import load_parameters

MIN_RUN_SECONDS = 20.0


def run_lengths(hours: float, run_minutes: float) -> list[float]:
    """The runs' lengths [s] that make up ``hours``."""
    total, step, out = hours * 3600.0, run_minutes * 60.0, []
    while total > 1e-9:
        out.append(max(min(step, total), MIN_RUN_SECONDS))
        total -= step
    return out


def make(out: Path, hours: float, run_minutes: float, seed: int) -> dict[str, object]:
    """Record the runs into ``out`` (a new directory); returns what ``done.json`` holds."""
    lengths = run_lengths(hours, run_minutes)
    out.mkdir(parents=True)
    params = load_parameters("physical")
    t0 = time.perf_counter()

    def one(k: int) -> str:
        if k < 0:
            path = out / "val"
            record_offline(path, build("ident", seed=seed + 9999), params, None,
                           seed=seed + 19999)
            return str(path)
        path = out / f"est-{k:03d}"
        record_offline(path, build("watch", seed=seed + k, duration=lengths[k],
                                   gears=(1, 2, 3)), params, None, seed=seed + 10000 + k)
        return str(path)
    paths = fork_map(one, [-1, *range(len(lengths))])
    info: dict[str, object] = {
        "hours": hours, "run_minutes": run_minutes, "seed": seed, "runs_s": lengths,
        "validation": paths[0], "estimation": paths[1:],
        "generate_seconds": time.perf_counter() - t0,
        "made_by": "scripts/make_hour_bags.py: dvt_driver.plant.offline.record_offline, watch "
                   "(gears 1-3) runs, params physical, no hidden effect; validation: ident"}
    (out / "done.json").write_text(json.dumps(info, indent=1))
    return info


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", help="new directory for the runs")
    p.add_argument("--hours", type=float, required=True)
    p.add_argument("--run-minutes", type=float, default=5.0)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if not (a.hours > 0 and math.isfinite(a.hours)) or not a.run_minutes > 0:
        p.error(f"--hours and --run-minutes: expected > 0, got {a.hours}, {a.run_minutes}")
    if Path(a.out).exists():
        p.error(f"{a.out}: exists (remove it, or give a new directory)")
    print(json.dumps(make(Path(a.out), a.hours, a.run_minutes, a.seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
