"""Hidden effects on fresh draws: does the default description name what the plant has?

For each plant preset and draw: the plant with the preset's hidden effects drawn anew
(:func:`dvt_driver.plant.hidden.load_hidden` with ``draw``; the committed recordings use
other draws), two runs of ``dvt-experiment ident`` recorded offline (estimation: experiment
seed 400 + draw, noise seed 500 + draw; validation: 600 + draw, 700 + draw; a case run at
several fit decimations shares nothing but the seeds), identified as
``dvt-identify`` does with the default ``dvt`` description (``tests/recorded.py``
``identify_bags``). Each row: the accepted effects, the effects the plant has
(``HiddenEffects.effect_names`` and where they act), the fitted effect parameters with their
std, the masses' largest relative error against the plant's.

Each row says whether the accepted effects name what the plant hides, where it acts, and
nothing else (``tests/recorded.py`` ``named_as_drawn``, the rule of the tests on the committed
recordings). A wet band is recorded with ``ident_shifts`` (:data:`EXPERIMENT`).

Usage: ``.venv/bin/python scripts/effect_draws.py [--presets P ...] [--draws N ...] [--json]``
(about 15 s per row on 2 cores, two rows at a time; ``--presets other``: the presets beside the
frictions, :data:`OTHER_PRESETS`); ``scripts/results.sh draws`` writes
``docs/results/draws.json`` with the defaults, ``scripts/results.sh draws_other`` with
``--presets other``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

PRESETS = ("coulomb", "stribeck", "windage")
DRAWS = (301, 302, 303, 304)
OTHER_PRESETS = ("delay", "backlash", "wet_brake", "gravity_arm", "mesh_ripple",
                 "position_friction")
"""The plant's other hidden-effect presets (``scripts/results.sh draws_other``)."""
EXPERIMENT = {"wet_brake": "ident_shifts"}
"""The experiment a preset is recorded with when not ``ident``: a wet band shows only in
engagements, which ``ident`` has too few of to determine (the identifiability check's advice)."""


def record_draw(preset: str, draw: int, root: Path) -> tuple[Path, Path]:
    """The estimation and validation runs of ``preset`` at ``draw`` (module docstring: seeds
    400/500 + draw and 600/700 + draw), recorded offline under ``root``."""
    from dvt_driver.plant.hidden import load_hidden
    from dvt_driver.plant.offline import record_offline
    from dvt_driver.run.experiment_core import build
    from dvt_model.params import load_parameters

    params = load_parameters("physical")
    hidden = load_hidden(preset, draw=draw)
    experiment = EXPERIMENT.get(preset, "ident")
    return (record_offline(root / "est", build(experiment, seed=400 + draw), params, hidden,
                           seed=500 + draw),
            record_offline(root / "val", build(experiment, seed=600 + draw), params, hidden,
                           seed=700 + draw))


def one(preset: str, draw: int, tmp: str, fit_decimate: int | None = None) -> dict[str, Any]:
    """Record and identify ``preset`` at ``draw`` (module docstring), fitted at the
    description's rate or with ``fit_decimate``; the row."""
    from recorded import PLANT_MEMBER, identify_bags, named_as_drawn

    from dvt_driver.plant.hidden import load_hidden
    from dvt_identify.bench_identify.compare import md_errors, truth_md

    hidden = load_hidden(preset, draw=draw)
    t0 = time.monotonic()
    est, val = record_draw(preset, draw, Path(tmp) / f"{preset}-{draw}-{fit_decimate}")
    r = identify_bags(est, val, fit_decimate=fit_decimate)
    fit = r.final.fit
    std = fit.parameter_std()
    structure = set(fit.model.names[: fit.model.n_struct])
    plant = {kind: {PLANT_MEMBER.get(m, m): v for m, v in getattr(hidden, kind).items()}
             for kind in ("coulomb", "stribeck", "windage") if getattr(hidden, kind)}
    accepted = [(d.score.effect.name, d.score.effect.where, d.score.label) for d in r.accepted]
    return {"preset": preset, "draw": draw, "fit_decimate": fit_decimate,
            "experiment": EXPERIMENT.get(preset, "ident"), "fit_dt": r.fit_dt,
            "accepted": [label for _, _, label in accepted],
            "named_as_drawn": named_as_drawn(hidden, accepted),
            "plant": json.loads(json.dumps(plant, default=lambda o: vars(o))),
            "effect_parameters": {k: [v, std.get(k)] for k, v in fit.parameters().items()
                                  if k not in structure and k in std},
            **md_errors(fit.parameters(), truth_md(est)),
            "seconds": round(time.monotonic() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=list(PRESETS),
                    help="plant presets ('other': " + ", ".join(OTHER_PRESETS) + ")")
    ap.add_argument("--draws", nargs="+", type=int, default=list(DRAWS))
    ap.add_argument("--fit-decimate", nargs="+", type=int, default=[None],
                    help="fit decimations to run each case at (default: the description's)")
    ap.add_argument("--json", action="store_true", help="print one JSON document")
    args = ap.parse_args(argv)
    args.presets = [q for p in args.presets for q in (OTHER_PRESETS if p == "other" else [p])]
    cases = [(p, d, f) for p in args.presets for d in args.draws for f in args.fit_decimate]
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(
            max_workers=2, mp_context=mp.get_context("spawn")) as pool:
        presets, draws, decims = zip(*cases, strict=True)
        rows = list(pool.map(one, presets, draws, [tmp] * len(cases), decims))
    if args.json:
        print(json.dumps({"rows": rows}, indent=2, default=float))
        return 0
    for r in rows:
        print(f"{r['preset']} draw {r['draw']} (fit step {r['fit_dt']:g} s): accepted "
              f"{', '.join(r['accepted']) or 'none'} (named as drawn: {r['named_as_drawn']}); "
              f"plant {r['plant']}; M off by {r.get('M_error_percent', np.nan):.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
