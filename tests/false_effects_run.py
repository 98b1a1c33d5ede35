"""One clean seed of ``tests/test_false_effects.py`` (a module of its own, importable by name
from ``tests/`` (pytest's ``pythonpath``), so that spawned worker processes can run it)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_identify.report import at_bounds, build_report
from dvt_model.params import load_parameters

SHORT = {"neutral_prbs": 2.5, "neutral_multisine": 2.0, "steps_dwell": 0.6, "shift": 0.5,
         "excite": 1.2}


def _run(path: Path, seed: int) -> Path:
    exp = build("ident", seed=seed, **SHORT)
    return record_offline(path, exp, load_parameters("physical"), parse_hidden({}),
                          seed=seed + 500)


def one_seed(seed: int, tmp: str) -> dict[str, Any]:
    """Identify on clean run ``seed`` validated on clean run ``seed + 1000``; the figures."""
    t0 = time.monotonic()
    root = Path(tmp)
    est_bag = _run(root / f"est-{seed}", seed)
    val_bag = _run(root / f"val-{seed}", seed + 1000)
    desc = load_description("dvt")
    est = load_segments([est_bag], desc)
    val = load_segments([val_bag], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = replace(LoopConfig.from_options(desc.fit, 10), max_effects=1)
    res = identify(est, val, desc, cfg, check=chk)
    rep = build_report(res)
    bounds = at_bounds(res.final)
    unreported = [n for n in bounds
                  if not any(w.startswith(f"parameter at a bound: {n} ") for w in rep["warnings"])]
    return {"seed": seed, "accepted": [d.score.label for d in res.accepted],
            "tried": [(d.score.label, round(d.lr, 1),
                       None if d.validation is None else round(d.validation.p_value, 4))
                      for d in res.decisions],
            "val_fit": [round(v, 2) for v in res.baseline.val.fit_percent],
            "drift": [p.name for p in res.drift.drifting] if res.drift else [],
            "at_bounds": bounds, "unreported_bounds": unreported,
            "seconds": round(time.monotonic() - t0, 1)}
