#!/usr/bin/env python3
"""Does an identification depend on the process it runs in? Identifies one committed bag
(default ``ident-stribeck``) as ``tests/test_undeclared_effects.py`` does, in fresh processes
that differ only in what they import first (nothing, ``numpy``, ``sensor_msgs.msg``) and,
last, in a plain process whose user set ``OPENBLAS_NUM_THREADS=2``, and prints per process the
accepted effects, the friction levels with their std, and each decision's final cost
(docs/identification.md, Tests: one BLAS thread in every process). The first three agree since
``dvt_model.one_blas_thread``; the last shows what two BLAS threads change.

Usage: .venv/bin/python scripts/layout_dependence.py [BAG]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = """
import sys{first}
sys.path.insert(0, {tests!r})
import json, tempfile
from pathlib import Path
from recorded import identify_recorded
r, _ = identify_recorded({bag!r}, Path(tempfile.mkdtemp()))
p, sd = r.final.parameters(), r.final.fit.parameter_std()
print(json.dumps({{
    "accepted": [d.score.label for d in r.decisions if d.accepted],
    "levels": {{k: [p[k], sd[k]] for k in p if k[:3] in ("Fc_", "Fs_", "Cw_")}},
    "decision_costs": [[d.score.label, None if d.stage is None else d.stage.fit.cost_]
                       for d in r.decisions]}}))
"""
FIRST = {"plain": "", "numpy first": "\nimport numpy", "sensor_msgs first":
         "\nfrom sensor_msgs.msg import JointState", "plain, OPENBLAS_NUM_THREADS=2": ""}


def main() -> int:
    bag = sys.argv[1] if len(sys.argv) > 1 else "ident-stribeck"
    for name, first in FIRST.items():
        code = CHILD.format(first=first, tests=str(ROOT / "tests"), bag=bag)
        env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
        if name.endswith("=2"):
            env["OPENBLAS_NUM_THREADS"] = "2"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True, cwd=ROOT, env=env)
        res = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{name}: accepted {res['accepted']}")
        for k, (v, s) in res["levels"].items():
            print(f"  {k} = {v:.6g} +- {s:.3g}")
        print("  decision costs: " + ", ".join(f"{c:.6g}" for _, c in res["decision_costs"]
                                               if c is not None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
