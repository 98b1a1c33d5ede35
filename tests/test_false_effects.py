"""False effects on a clean plant: independent clean runs, nothing should be accepted.

Each seed makes two independent runs of the simulated plant with no hidden effect (offline runner
through the driver's supervisor, as ``tests/test_undeclared_effects.py`` makes its validation
runs): a shortened ``ident`` experiment (neutral PRBS and multisine, sun-speed steps with
reversals, gears 1, 2 and 3 each locked by its band with PRBS, stop; about 13 s at 1 kHz) with its
own experiment and noise seeds for estimation, another for validation. The identifier (default
``dvt`` description, identifiability check, drift check, one augmentation round, fit at 100 Hz)
must accept a false effect on at most 1 of the 20 seeds, and every parameter at a bound must
appear in the report's warnings. The figures are printed (``pytest -s``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
from false_effects_run import one_seed

pytestmark = pytest.mark.slow
SEEDS = range(1, 21)


def test_clean_runs_accept_at_most_one_false_effect(tmp_path: Path) -> None:
    t0 = time.monotonic()
    workers = max(1, min(2, os.cpu_count() or 1))
    # spawned workers: by this point the test process holds rclpy/DDS threads of earlier tests,
    # and a forked child of a multi-threaded process can crash (it once segfaulted in the GC)
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(one_seed, SEEDS, [str(tmp_path)] * len(SEEDS)))
    for r in rows:
        print(f"seed {r['seed']:2d}: validation fit {r['val_fit']}, accepted {r['accepted']}, "
              f"refits {r['tried']}, drift {r['drift']}, at bounds {r['at_bounds']}, "
              f"{r['seconds']} s")
    false = [r for r in rows if r["accepted"]]
    print(f"false effects accepted on {len(false)} of {len(rows)} clean seeds; "
          f"{time.monotonic() - t0:.0f} s")
    assert len(false) <= 1, [(r["seed"], r["accepted"]) for r in false]
    assert all(not r["unreported_bounds"] for r in rows), [
        (r["seed"], r["unreported_bounds"]) for r in rows if r["unreported_bounds"]]
    # a clean plant drifts nowhere
    assert sum(1 for r in rows if r["drift"]) <= 1, [(r["seed"], r["drift"]) for r in rows]
