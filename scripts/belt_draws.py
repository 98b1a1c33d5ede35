"""Random belt drives read by a sign-blind pulse counter, identified as a new user would.

For each seed: a drive drawn by ``tests/belt_drive.py`` ``draw`` (inertias, belt mode 1-6 Hz,
damping ratio, the motor's pole), three 500-sample records at 50 Hz (commands of amplitude 0.5,
1 and 1.5), optionally a Coulomb friction on the motor; the first 300 samples of each record
are estimation bags, the last 200 test bags; ``dvt_identify.pipeline.run`` with the belt
drive's scale-only description (every prior 1), ``--select-on cv``. Each row: the drive, the
accepted effects, the test fit of the physical model and of the linear reference, and each
parameter's error in reported standard deviations.

With ``--realizations R``: each drive (its parameters fixed) is recorded ``R`` times with
other commands and noise (records seeds ``REALIZATION_SEED + 10 r``) and identified each time;
per parameter, over the realizations named as drawn and with a finite std for it
(``finite_std`` of them), the spread of the estimates against the reported standard
deviations: ``std_ratio`` (sample std of the estimates over the RMS of the reported std; 1
when the reported std are honest), ``z_rms`` with its two-sided 95 % interval for honest std
(``sqrt(chi2(n) / n)`` quantiles) and ``z_mean`` (a bias shows there); each realization's
error in std and reported std (``error_in_std_each``, ``std_each``, in the order of the
realizations kept).

Usage: ``.venv/bin/python scripts/belt_draws.py [--seeds N ...] [--friction F]
[--init-window N] [--sensor-lag TAU] [--lag-candidate] [--signed] [--realizations R]
[--json]``
(about 10 s per drive and realization); ``scripts/results.sh belt`` writes
``docs/results/belt.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

SEEDS = tuple(range(1, 11))
FRICTION = 0.0


LAG_CANDIDATE = {"effect": "sensor_lag", "where": "w_pulley"}


REALIZATION_SEED = 10_000
"""Records seed of a drive's first realization (``--realizations``; apart from the
``100 * seed`` of the one record set per drive)."""


def one(seed: int, friction: float, tmp: Path, init_window: int = 0, lag: float = 0.0,
        lag_candidate: bool = False, records_seed: int | None = None,
        signed: bool = False) -> dict[str, Any]:
    """Draw, record and identify one drive (module docstring); its row. ``records_seed``:
    the records' seed (default ``100 * seed``); ``signed``: the speed read with its sign."""
    import belt_drive

    from dvt_identify.data import JointStateSeries, Segment, write_jointstate_bag
    from dvt_identify.pipeline import run

    def bag(path: Path, seg: Segment) -> str:
        stamps = (10**9 + np.round(seg.t * 1e9)).astype(np.int64)
        return str(write_jointstate_bag(path, {
            "/belt/joint_states": JointStateSeries(stamps, ("pulley",), velocity=seg.y[:, :1]),
            "/belt/drive": JointStateSeries(stamps, ("motor",), effort=seg.u[:, :1])}))

    drive = belt_drive.draw(np.random.default_rng(seed))
    rs = 100 * seed if records_seed is None else records_seed
    segs, _ = belt_drive.records(drive, seed=rs, n=500, friction=friction, lag=lag,
                                 signed=signed)
    work = tmp / f"drive-{seed}-{rs}"
    est = [bag(work / f"est{k}", s.rows(0, 300)) for k, s in enumerate(segs)]
    test = [bag(work / f"test{k}", s.rows(300, 500, from_zero=True))
            for k, s in enumerate(segs)]
    desc = belt_drive.write_description(work / "belt-drive.yaml",
                                        [LAG_CANDIDATE] if lag_candidate else None)
    t0 = time.monotonic()
    r = run(est, [], work / "report", description=str(desc), select_on="cv", test_bags=test,
            quiet=True, plots=False, series=False, init_window=init_window)
    seconds = time.monotonic() - t0
    values, std = r.final.fit.parameters(), r.final.fit.parameter_std()
    truth = {**drive, **({"Fc": friction} if friction else {}), **({"tau": lag} if lag else {})}
    tf = r.test
    return {"seed": seed, "records_seed": rs, "drive": drive, "friction": friction,
            "init_window": init_window, "sensor_lag": lag, "signed": signed,
            "lag_candidate": lag_candidate,
            "accepted": [d.score.label for d in r.accepted],
            "test_fit_percent": float(tf.final.fit_percent[0]),
            "reference_test_fit_percent": (float(tf.reference.fit_percent[0])
                                           if tf.reference is not None else None),
            "error_in_std": {k: (values[k] - v) / std[k] if std.get(k) else None
                             for k, v in truth.items() if k in values},
            "estimate": {k: values[k] for k in truth if k in values},
            "std": {k: std.get(k) for k in truth if k in values},
            "relative_error_percent": {k: 100.0 * (values[k] / v - 1.0)
                                       for k, v in truth.items() if k in values},
            "seconds": round(seconds, 1)}


def _named_as_drawn(rows: list[dict[str, Any]], drawn: list[str]) -> list[dict[str, Any]]:
    """The rows (of :func:`one`) whose accepted effects are exactly ``drawn``."""
    return [r for r in rows if sorted(r["accepted"]) == sorted(drawn)]


def calibration(rows: list[dict[str, Any]], drawn: list[str]) -> dict[str, Any]:
    """One drive's realizations (rows of :func:`one`): per parameter, over those named as
    drawn, the spread of the estimates against the reported std (module docstring)."""
    from scipy.stats import chi2

    good = _named_as_drawn(rows, drawn)
    out: dict[str, Any] = {"seed": rows[0]["seed"], "realizations": len(rows),
                           "named_as_drawn": len(good), "parameters": {}}
    if len(good) < 2:
        return out
    for k in good[0]["error_in_std"]:
        # a realization whose data leave the parameter undetermined (std inf) reports no std
        kept = [r for r in good if r["std"][k] is not None and math.isfinite(r["std"][k])
                and r["std"][k] > 0]
        if len(kept) < 2:
            out["parameters"][k] = {"finite_std": len(kept)}
            continue
        z = np.array([r["error_in_std"][k] for r in kept])
        est = np.array([r["estimate"][k] for r in kept])
        sd = np.array([r["std"][k] for r in kept])
        lo, hi = (float(np.sqrt(chi2.ppf(q, z.size) / z.size)) for q in (0.025, 0.975))
        out["parameters"][k] = {
            "finite_std": len(kept), "error_in_std_each": [float(v) for v in z],
            "std_each": [float(v) for v in sd],
            "std_ratio": float(np.std(est, ddof=1) / np.sqrt(np.mean(sd ** 2))),
            "z_rms": float(np.sqrt(np.mean(z ** 2))), "z_rms_95_if_honest": [lo, hi],
            "z_mean": float(np.mean(z)), "relative_std_percent": float(
                100.0 * np.sqrt(np.mean(sd ** 2)) / abs(float(np.mean(est))))}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    ap.add_argument("--friction", type=float, default=FRICTION,
                    help="Coulomb friction on the motor [N m] (default 0)")
    ap.add_argument("--init-window", type=int, default=0,
                    help="initial states from the first N samples of every record, as "
                         "dvt-identify --init-window (default 0: estimated)")
    ap.add_argument("--sensor-lag", type=float, default=0.0,
                    help="the counter read through a first-order filter of this time constant "
                         "[s] (default 0: none)")
    ap.add_argument("--lag-candidate", action="store_true",
                    help="add the sensor_lag candidate to the description")
    ap.add_argument("--signed", action="store_true",
                    help="read the speed with its sign (a counter that knows the direction; "
                         "the same noise): what the sign-blind reading costs")
    ap.add_argument("--realizations", type=int, default=0,
                    help="record and identify each drive this many times (module docstring; "
                         "default 0: once, the table of drives)")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    if args.realizations < 0 or args.realizations == 1:
        ap.error(f"--realizations: expected 0 or at least 2, got {args.realizations}")
    drawn = (([] if args.signed else ["sign_blind@w_pulley"])
             + (["coulomb_friction@motor"] if args.friction else [])
             + (["sensor_lag@w_pulley"] if args.sensor_lag else []))
    if args.realizations:
        return _realizations(args, drawn)
    with tempfile.TemporaryDirectory() as tmp:
        rows = [one(s, args.friction, Path(tmp), args.init_window, args.sensor_lag,
                    args.lag_candidate, signed=args.signed) for s in args.seeds]
    good = _named_as_drawn(rows, drawn)
    summary = {"drives": len(rows), "named_as_drawn": len(good),
               "test_fit_above_95": sum(r["test_fit_percent"] > 95.0 for r in rows),
               "better_than_reference": sum(
                   r["reference_test_fit_percent"] is not None
                   and r["test_fit_percent"] > r["reference_test_fit_percent"] for r in rows),
               "test_fit_percent_min_median": [
                   float(np.min([r["test_fit_percent"] for r in rows])),
                   float(np.median([r["test_fit_percent"] for r in rows]))]}
    if args.json:
        print(json.dumps({"summary": summary, "rows": rows}, indent=2, default=float))
        return 0
    for r in rows:
        print(f"seed {r['seed']}: accepted {', '.join(r['accepted']) or 'none'}; test fit "
              f"{r['test_fit_percent']:.2f} % (reference {r['reference_test_fit_percent']}); "
              + ", ".join(f"{k} {v:+.2g} std" for k, v in r["error_in_std"].items()
                          if v is not None))
    print(summary)
    return 0


def _realizations(args: argparse.Namespace, drawn: list[str]) -> int:
    """``--realizations``: every drive identified ``args.realizations`` times, both cores."""
    from concurrent.futures import ProcessPoolExecutor

    jobs = [(s, REALIZATION_SEED + 10 * r) for s in args.seeds for r in range(args.realizations)]
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(2) as pool:
        futures = [pool.submit(one, s, args.friction, Path(tmp), args.init_window,
                               args.sensor_lag, args.lag_candidate, rs, args.signed)
                   for s, rs in jobs]
        rows = [f.result() for f in futures]
    drives = [calibration([r for r in rows if r["seed"] == s], drawn) for s in args.seeds]
    if args.json:
        print(json.dumps({"drives": drives}, indent=2, default=float))
        return 0
    for d in drives:
        print(f"seed {d['seed']}: {d['named_as_drawn']} of {d['realizations']} named as drawn")
        for k, v in d["parameters"].items():
            if "z_rms" not in v:
                print(f"  {k}: a finite std in {v['finite_std']} realizations only")
                continue
            lo, hi = v["z_rms_95_if_honest"]
            print(f"  {k}: std ratio {v['std_ratio']:.2f}, z RMS {v['z_rms']:.2f} (honest: "
                  f"{lo:.2f} to {hi:.2f}), z mean {v['z_mean']:+.2f}, reported std "
                  f"{v['relative_std_percent']:.2g} % ({v['finite_std']} with a finite std)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
