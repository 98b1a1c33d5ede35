"""The compliant play's secant share: the figures of docs/identification.md section 2.

Identifies the committed recording ``ident-backlash`` as ``tests/test_backlash_live.py`` does
(the description's full loop, validated on a fresh run of the same drawn plant), then:

- **the premise**: at the final fit's parameters, the sensed speed after the play's map
  (:class:`dvt_identify.effects.backlash.CompliantOutputBacklash`) when the map's input (the
  member's simulated speed, the play passed) is shifted by ``h`` for several ``h``: the largest
  change, where it first exceeds 1e-3 rad/s, and the largest change divided by ``h`` (a
  derivative would keep that ratio; a divergence makes it grow as ``1/h``);
- **the sweep**: the final structure refitted (:meth:`dvt_identify.fit.OEFit.refit_secant`,
  from the start that gave the final fit) with the play's secant at each share of
  :data:`SHARES` of its parameters' values: the gap and its sandwich std, M11 and its std, the
  cost;
- the identification's own final figures (the share
  :data:`dvt_identify.effects.backlash.SECANT_SHARE`, std with the landing spread) and the
  drawn gap (``truth.yaml``, which only this script and the tests read).

Usage: ``.venv/bin/python scripts/secant_sweep.py [--json]`` (about 20 s on 2 cores);
``scripts/results.sh secant`` writes ``docs/results/secant.json`` from it.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from recorded import BAGS, identify_recorded, truth_effects  # noqa: E402

from dvt_identify.effects.backlash import SECANT_SHARE  # noqa: E402

RECORDING = "ident-backlash"
SHARES = (0.03, 0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 1.0)
"""Secant shares of the sweep (the play's parameters' values)."""
STEPS = (1e-9, 1e-6, 1e-3)
"""Shifts of the map's input [rad/s] of the premise."""
VISIBLE = 1e-3
"""A change of the sensed speed [rad/s] counted as visible (the premise's first sample)."""


def premise(fit: Any) -> list[dict[str, float]]:
    """The map's response to a shift ``h`` of its input on the fit's first segment."""
    m = fit.model
    (i,) = [k for k, e in enumerate(m.effects) if e.chaotic_output]
    eff, p = m.effects[i], fit.theta_[m.effect_slice(i)]
    seg, x0 = fit.segments_[0], fit.x0_[0]
    y = m.passing_chaotic().simulate(fit.theta_, seg, x0)
    base = eff.output_transform(p, y, seg.dt)[:, eff.index]
    rows = []
    for h in STEPS:
        shifted = y.copy()
        shifted[:, eff.index] += h
        d = np.abs(eff.output_transform(p, shifted, seg.dt)[:, eff.index] - base)
        seen = np.flatnonzero(d > VISIBLE)
        rows.append({"step": h, "max_change": float(d.max()),
                     "max_change_over_step": float(d.max() / h),
                     "first_visible_sample": int(seen[0]) if seen.size else -1,
                     "samples": int(d.size), "dt": float(seg.dt)})
    return rows


def sweep(fit: Any) -> list[dict[str, float]]:
    """The final structure refitted at each secant share of :data:`SHARES`."""
    (gap,) = [j for j in fit.model.chaotic_parameters()
              if fit.model.names[j].startswith("gap")]
    gname = fit.model.names[gap]
    rows = []
    for share in SHARES:
        again = fit.refit_secant(fit.segments_, share / SECANT_SHARE)
        std = again.parameter_std()
        rows.append({"share": share, "gap": float(again.theta_[gap]), "gap_std": std[gname],
                     "M11": again.parameters()["M11"], "M11_std": std["M11"],
                     "cost": float(again.cost_)})
        print(f"secant_sweep: share {share:g}: {gname} {rows[-1]['gap']:.5f} +- "
              f"{rows[-1]['gap_std']:.5f}", file=sys.stderr)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    truth = truth_effects(BAGS / RECORDING).backlash
    if truth is None:
        raise SystemExit(f"secant_sweep: {BAGS / RECORDING}/truth.yaml has no backlash")
    with tempfile.TemporaryDirectory() as d:
        result, _ = identify_recorded(RECORDING, Path(d))
    fit, base = result.final.fit, result.baseline.fit
    (gap,) = [j for j in fit.model.chaotic_parameters() if fit.model.names[j].startswith("gap")]
    gname = fit.model.names[gap]
    std = fit.parameter_std()
    doc = {"recording": RECORDING, "drawn_gap": truth.gap,
           "accepted": [dd.score.label for dd in result.accepted],
           "final": {"share": SECANT_SHARE, "gap": float(fit.theta_[gap]), "gap_std": std[gname],
                     "gap_landing_spread": float(fit.landing_spread_[gap]),
                     "M11": fit.parameters()["M11"], "M11_std": std["M11"],
                     "M11_std_baseline": base.parameter_std()["M11"],
                     "parameters": fit.parameters(), "std": std},
           "premise": premise(fit), "sweep": sweep(fit)}
    if args.json:
        print(json.dumps(doc, indent=2, default=float))
    else:
        f = doc["final"]
        print(f"{RECORDING}: drawn gap {truth.gap:.5f}; final {f['gap']:.5f} +- "
              f"{f['gap_std']:.5f} (landing spread {f['gap_landing_spread']:.5f})")
        for r in doc["premise"]:
            print(f"  shift {r['step']:g}: max change {r['max_change']:.3g} "
                  f"(/step {r['max_change_over_step']:.3g}), first > {VISIBLE:g} at sample "
                  f"{r['first_visible_sample']} of {r['samples']}")
        for r in doc["sweep"]:
            print(f"  share {r['share']:g}: gap {r['gap']:.5f} +- {r['gap_std']:.5f}, "
                  f"M11 std {r['M11_std']:.3g}, cost {r['cost']:.5g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
