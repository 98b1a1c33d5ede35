"""How the fit step biases a model with dry friction, on the identifier's own simulation.

A fresh draw of the ``coulomb`` plant (``scripts/effect_draws.py``'s recording: draw
:data:`DRAW`) is identified at the recording's own rate (1 ms, ``--fit-decimate 1``); that
final model, simulated at 1 ms on the estimation inputs, is the data: noise-free and exactly
the model's own law. Decimated by ``q`` as the loop decimates
(:func:`dvt_identify.simulation.zoh_decimate`) and refitted from the 1-ms optimum, each
parameter's relative error [%] against the 1-ms values is the step's own bias (0 at ``q`` = 1).

Usage: ``.venv/bin/python scripts/dry_step_bias.py [--json]`` (about a minute);
``scripts/results.sh dry_step`` writes ``docs/results/dry_step.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from effect_draws import record_draw  # noqa: E402  (this script's folder)
from recorded import identify_bags  # noqa: E402

from dvt_identify.fit import OEFit  # noqa: E402
from dvt_identify.simulation import zoh_decimate  # noqa: E402

DRAW = 301
STEPS = (1, 2, 5, 10)
"""Decimations of the 1-ms data refitted."""
SHOWN = ("M11", "M12", "M22", "D11", "D12", "D22", "Fc_sun_shaft", "Fc_carrier3")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        est, val = record_draw("coulomb", DRAW, Path(tmp))
        r = identify_bags(est, val, fit_decimate=1)
    fit = r.final.fit
    seg = fit.segments_[0]
    own = dataclasses.replace(seg, y=fit.model.simulate(fit.theta_, seg, fit.x0_[0]))
    names = fit.model.names
    rows: list[dict[str, Any]] = []
    for q in STEPS:
        again = OEFit(fit.model, theta0=fit.theta_, more_starts=0, physics_start=False,
                      weights=fit.weights_).fit([zoh_decimate(own, q)])
        rows.append({"decimation": q, "step_s": seg.dt * q, "relative_error_percent": {
            n: 100.0 * (float(again.theta_[i]) / float(fit.theta_[i]) - 1.0)
            for i, n in enumerate(names) if n in SHOWN}})
    doc = {"draw": DRAW, "accepted": [d.score.label for d in r.accepted], "rows": rows}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        for row in rows:
            print(f"step {row['step_s'] * 1e3:g} ms: " + ", ".join(
                f"{n} {v:+.2f} %" for n, v in row["relative_error_percent"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
