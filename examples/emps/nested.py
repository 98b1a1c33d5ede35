"""Does refitting the chosen model on all of its estimation data help? Asked of the estimation
record alone (the test record is not read).

``dvt-identify --select-on holdout`` chooses the effects with fits on the first 70 % of each
estimation segment (the last 30 % held out) and then refits the chosen model on the whole
segment (:func:`dvt_identify.loop.refit_whole`). This script runs that procedure on the first
``cut`` of the EMPS estimation record (a pseudo-estimation record) and scores, on the rest of
it (a pseudo-test record, the benchmark's protocol: simulated position after a 20-sample
state-initialisation window), the chosen model as fitted on the first 70 % of the pseudo-
estimation record and as refitted on all of it; the baseline likewise. Prints one JSON
document (``--json``) or a table.

Usage: ``python examples/emps/nested.py [--data DIR] [--cuts 0.5 0.6 0.7 0.8 0.9] [--json]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
N_INIT = 20


def _import(data: Path, out: Path) -> Path:
    """The estimation record as a bag in ``out`` (the mapping of ``run.sh``)."""
    bag = out / "emps_estimation"
    cmd = [str(Path(sys.executable).parent / "dvt-import"), str(data / "emps_estimation.npz"),
           "--out", str(bag), "--force", "--mapping", str(HERE / "mapping.yaml")]
    r = subprocess.run(cmd, text=True, capture_output=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"nested.py: {' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return bag


def one_cut(bag: Path, cut: float) -> dict[str, Any]:
    """The holdout procedure on the first ``cut`` of the record, scored on the rest [mm]."""
    from dvt_identify import identifiability
    from dvt_identify.description import load_description
    from dvt_identify.loop import identify, refit_whole
    from dvt_identify.pipeline import _read, loop_config
    from dvt_identify.series import evaluate_test, holdout_split

    desc = load_description("emps-position")
    (rec,), _ = _read([bag], [], desc, [])
    k = int(cut * rec.n)
    part = rec.rows(0, k)
    rest = rec.rows(k, None, name=f"{rec.name}[{k}:]", from_zero=True)
    chk = identifiability.check(desc, [part])
    desc = identifiability.apply(desc, chk)
    cfg = replace(loop_config(desc), init_window=N_INIT)
    t0 = time.monotonic()
    fit_part, held = holdout_split([part])
    first = identify(fit_part, held, desc, cfg)
    base_first, final_first = first.baseline.fit, first.final.fit
    accepted = [d.score.label.split(":")[0] for d in first.accepted]
    whole = refit_whole(first, [part])
    out: dict[str, Any] = {"cut": cut, "pseudo_estimation_samples": k,
                           "pseudo_test_samples": rest.n, "accepted": accepted,
                           "refit_notes": [n for n in whole.notes if "refitted" in n]}
    for label, fit in (("final_first_part", final_first), ("final_whole", whole.final.fit),
                       ("baseline_first_part", base_first),
                       ("baseline_whole", whole.baseline.fit)):
        tf = evaluate_test(base_first, fit, [rest], N_INIT)
        out[f"{label}_mm"] = 1e3 * float(tf.final.rmse[0])
    out["seconds"] = time.monotonic() - t0
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "emps",
                    help="folder with emps_estimation.npz (default ../shared/data/emps)")
    ap.add_argument("--cuts", type=float, nargs="+", default=[0.5, 0.6, 0.7, 0.8, 0.9],
                    help="pseudo-estimation shares of the record (default 0.5 to 0.9)")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    a = ap.parse_args(argv)
    for c in a.cuts:
        if not 0.2 <= c <= 0.95:
            ap.error(f"--cuts: each share must lie in [0.2, 0.95], got {c}")
    if not (a.data / "emps_estimation.npz").is_file():
        ap.error(f"--data: {a.data / 'emps_estimation.npz'} not found")
    with tempfile.TemporaryDirectory() as d:
        bag = _import(a.data, Path(d))
        rows = [one_cut(bag, c) for c in a.cuts]
    doc = {"record": "emps_estimation (the test record is not read)", "init_window": N_INIT,
           "rows": rows,
           "whole_better_on": [r["cut"] for r in rows
                               if r["final_whole_mm"] < r["final_first_part_mm"]]}
    if a.json:
        print(json.dumps(doc, indent=1))
    else:
        for r in rows:
            print(f"cut {r['cut']:g}: final {r['final_first_part_mm']:.2f} -> "
                  f"{r['final_whole_mm']:.2f} mm, baseline {r['baseline_first_part_mm']:.2f} "
                  f"-> {r['baseline_whole_mm']:.2f} mm (accepted: {', '.join(r['accepted'])})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
