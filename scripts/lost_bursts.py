"""What a burst of lost samples does to the model node's free run (the figures of
``dvt_model.contract.GAP_REANCHOR_S`` and ``docs/reference.md``).

Identifies the committed recording ``ident-backlash`` as ``tests/test_backlash_live.py`` does
(its validation run recorded into ``--out``), builds the node's predictor
(:func:`dvt_model.config.build_predictor`) from the pushed parameters, and feeds it the first
8 s of the validation run offline: once whole, then with one burst of consecutive samples left
out, at 12 random positions per burst length. Once with the node's rule (``gap_reanchor``
default: re-anchor) and once run through on held inputs (``gap_reanchor`` 0.5 s). Prints, per
rule and burst length, the median and the maximum over positions of the sun's residual RMS over
the whole one and of the carrier-3 RMS with the pushed term over without it (the test's figure).
About 2 minutes on one core.

Usage::

    .venv/bin/python scripts/lost_bursts.py [--out DIR] [--seed 1]
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

from recorded import identify_recorded  # noqa: E402  (the tests' helper, one place)

from dvt_identify.data import Segment  # noqa: E402
from dvt_identify.description import load_description  # noqa: E402
from dvt_identify.pipeline import load_segments, model_push  # noqa: E402
from dvt_model.config import build_predictor, defaults  # noqa: E402

SLICE = 8000
"""Samples fed (8 s at 1 kHz, the live test's slice)."""
SKIP = 200
"""Samples after the anchor left out of the RMS (as the live test)."""
LOST = (4, 5, 9, 14, 19, 49, 99, 299)
"""Burst lengths [samples lost]; the stamp step over a burst is one more [ms]."""
RULES = {"re-anchor (default)": {}, "held inputs": {"gap_reanchor": 0.5}}


def rms(seg: Segment, values: dict[str, Any], lost: set[int]) -> np.ndarray:
    """Residual RMS [rad/s] (sun, carrier 3) of the node's predictor on the slice, ``lost``
    samples left out."""
    pred, _ = build_predictor({**defaults(), **values, "detector.enabled": False})
    res = []
    angles = seg.angles
    for k in range(SLICE):
        if k in lost:
            continue
        out = pred.update(float(seg.t[k]), float(seg.u[k, 0]), seg.u[k, 1:4], seg.y[k],
                          None if angles is None else angles[k])
        res.append(out.residual)
    r = np.asarray(res)[SKIP:]
    return np.sqrt(np.mean(r**2, axis=0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None,
                        help="directory for the validation run (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the burst positions")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="lost_bursts_"))
    result, val = identify_recorded("ident-backlash", out)
    pushed = dict(model_push(result).parameters)
    pushed["params"] = "physical"
    bare = {**pushed, "effects": "[]"}
    seg = load_segments([val], load_description("dvt"))[0]
    base = rms(seg, bare, set())
    with_term = rms(seg, pushed, set())
    rows = []
    for rule, extra in RULES.items():
        rng = np.random.default_rng(args.seed)
        for n in LOST:
            sun, c3 = [], []
            for start in rng.integers(300, SLICE - 300, 12):
                lost = set(range(int(start), int(start) + n))
                without = rms(seg, {**bare, **extra}, lost)
                sun.append(without[0] / base[0])
                c3.append(rms(seg, {**pushed, **extra}, lost)[1] / without[1])
            rows.append({"rule": rule, "lost_ms": n, "sun_ratio_median": float(np.median(sun)),
                         "sun_ratio_max": float(np.max(sun)),
                         "c3_with_over_without_median": float(np.median(c3)),
                         "c3_with_over_without_max": float(np.max(c3))})
            print(f"{rule:20s} lost {n:3d} ms: sun x{rows[-1]['sun_ratio_max']:.3f} (max), "
                  f"c3 with/without {rows[-1]['c3_with_over_without_max']:.3f} (max)",
                  flush=True)
    print(json.dumps({"lossless_rms_without": base.tolist(),
                      "lossless_rms_with_term": with_term.tolist(), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
