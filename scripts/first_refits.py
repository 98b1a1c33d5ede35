"""The live loop's first refit (structure held) after a friction step, over plants and phases.

For each seed and change time: the ``watch`` experiment on the ``physical`` plant at
``--rate`` [Hz], its Coulomb friction stepping (``friction_step``: 0 -> 0.05 N m sun,
0.20 N m carrier 3) at that plant time, recorded offline; the refit fits and holds out the
windows of :func:`dvt_driver.system.bench_loop.live_supervisor` at that rate from 0.5 s after
the change, exactly as the supervisor's first stage (the bag of ``tests/first_refit_run.py``;
:func:`dvt_identify.refit.refit`, the
structure held at the model in use, ``fit_decimate`` rate/100). Change times spread over
the ``watch`` cycle (11 s) put the windows on different parts of the excitation.

Per window: the accepted effects; the held-out RMS ratio new/current per output; and the
live loop's test figure: the new model's RMS over the 14 s from 1 s after the held-out part
(the supervisor's watch) against the model in use's over the post-change part before it
(``watch_vs_before``), and against the model in use's on the same 14 s (``watch_paired``).
Both models run the model node's own predictor (:func:`dvt_identify.refit.validation_errors`).

Usage: ``.venv/bin/python scripts/first_refits.py [--rate 250] [--seeds 0,1,2] [--json]``
(about 4 minutes on two cores); ``scripts/results.sh first_refits`` writes
``docs/results/first_refits.json``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CHANGES_S = tuple(34.0 + 1.1 * k for k in range(10))
"""Plant times of the change [s]: ten points over one ``watch`` cycle."""
WATCH_S = (1.0, 15.0)
"""The watch window after the held-out part's end [s] (the supervisor's ``watch_settle_s``
and ``watch_s`` at the live settings, the push taken at the held-out part's end)."""
SUN, CARRIER3 = "coulomb_friction@sun_shaft", "coulomb_friction@carrier3"


def window(case: tuple[int, float, float, str]) -> dict[str, Any]:
    """One refit: ``(seed, change time [s], rate [Hz], work root)``."""
    seed, change_at, rate, root = case
    sys.path.insert(0, str(ROOT / "tests"))
    from first_refit_run import friction_step_bag

    from dvt_driver.system.bench_loop import live_supervisor
    from dvt_identify.refit import RefitSettings, refit, validation_errors
    from dvt_identify.supervisor import RequestFit
    from dvt_model.recording import read_run

    sv = live_supervisor(rate)
    work = Path(root) / f"s{seed}-{change_at:g}"
    work.mkdir(parents=True)
    bag, c = friction_step_bag(work, seed, change_at, change_at
                               + float(sv["min_post_change_s"]) + WATCH_S[1] + 1.0, rate)
    data = read_run(bag)
    stamps = data.stamps_ns
    e0 = c + float(sv["settle_s"])
    v1 = c + float(sv["min_post_change_s"])
    e1 = v1 - float(sv["validation_s"])
    current = {"params": "physical"}
    out = refit(bag, RequestFit(1, (e0, e1), (e1, v1), ("sun_shaft",)), current,
                work / "work", RefitSettings(fit_decimate=max(1, round(rate / 100.0))))
    row: dict[str, Any] = {"seed": seed, "change_s": change_at, "error": out.error or "",
                           "accepted": list(out.summary.get("accepted", []))}
    if out.error or not out.new_parameters:
        return row
    rms = lambda e: np.sqrt(np.mean(np.asarray(e, dtype=float) ** 2, axis=0))  # noqa: E731
    row["held_out_ratio"] = np.round(rms(out.new_errors) / rms(out.current_errors), 3).tolist()
    t = stamps * 1e-9
    seg = t >= e0
    new = {**current, **out.new_parameters}
    ec = validation_errors(current, stamps[seg], data.speeds[seg], data.currents[seg])
    en = validation_errors(new, stamps[seg], data.speeds[seg], data.currents[seg])
    ts = t[seg]
    watch = (ts >= v1 + WATCH_S[0]) & (ts < v1 + WATCH_S[1])
    row["watch_vs_before"] = np.round(rms(en[watch]) / rms(ec[ts < v1]), 3).tolist()
    row["watch_paired"] = np.round(rms(en[watch]) / rms(ec[watch]), 3).tolist()
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rate", type=float, default=250.0, help="controller rate [Hz]")
    ap.add_argument("--seeds", default="0,1,2", help="plant and experiment seeds")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    with tempfile.TemporaryDirectory() as root:
        cases = [(s, ch, args.rate, root) for s in seeds for ch in CHANGES_S]
        with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
            rows = list(pool.map(window, cases))
    ok = [r for r in rows if not r["error"]]
    worst = max((r["watch_vs_before"][0] for r in ok), default=None)
    doc = {
        "rate_hz": args.rate, "windows": len(rows), "errors": len(rows) - len(ok),
        "both_named": sum({SUN, CARRIER3} <= set(r["accepted"]) for r in ok),
        "sun_coulomb_named": sum(SUN in r["accepted"] for r in ok),
        "unlisted_accepted": sum(any(a.startswith("unlisted@") for a in r["accepted"])
                                 for r in ok),
        "worst_sun_watch_vs_before": worst,
        "rows": rows,
    }
    if args.json:
        print(json.dumps(doc))
    else:
        for r in rows:
            print(r)
        print({k: v for k, v in doc.items() if k != "rows"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
