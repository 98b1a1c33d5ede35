"""Write the validation pairs of the committed estimation recordings into ``bags/``.

For each ``NAME=SOURCE`` pair, a second run of the same plant (the parameter set, hidden
effects and noise model of ``bags/SOURCE/truth.yaml``: the values the source's plant drew, with
the record of the draw) driven offline through the driver's supervisor
(:mod:`dvt_driver.plant.offline`) with the source's experiment at experiment seed + 100 and
plant seed + 100 (the validation runs of ``tests/test_undeclared_effects.py``).

Usage: ``.venv/bin/python scripts/make_validation_bags.py [OUTDIR] [NAME=SOURCE ...]``
(default ``bags``, ``ident-coulomb-val=ident-coulomb ident-none-val=ident-none-1``).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import yaml

from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import run_offline
from dvt_driver.run.experiment_core import build
from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATE_TYPE, JOINT_STATES, SPEED_NAMES
from dvt_model.params import load_parameters
from dvt_model.recording import read_run_info, read_truth, write_truth
from dvt_model.recording.cdr import joint_state_cdr
from dvt_model.recording.write import BagRecorder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ("ident-coulomb-val=ident-coulomb", "ident-none-val=ident-none-1")
LIMIT_BYTES = 3_000_000


def make(out: Path, name: str, source: Path) -> Path:
    """Record the validation run of ``source`` as ``out/name``; returns its path."""
    truth = read_truth(source)
    made = read_run_info(source)
    if truth is None or made is None:
        raise SystemExit(f"{source}: needs truth.yaml and run.yaml")
    experiment = build(made["experiment"]["name"], seed=int(made["experiment"]["seed"]) + 100)
    dst = out / name
    if dst.exists():
        shutil.rmtree(dst)
    # the source's drawn plant, with the record of its draw (written into the truth again)
    hidden = dataclasses.replace(parse_hidden(truth["hidden"], source=f"{source.name}/truth.yaml"),
                                 draw=truth.get("hidden_draw"))
    run = run_offline(experiment, load_parameters(truth["plant"]["params"]), hidden,
                      seed=int(truth["plant"]["seed"]) + 100)
    stamps = 1_700_000_000_000_000_000 + np.round(run.t * 1e9).astype(np.int64)
    # zstd chunks like the recorder's bags (the plain writer would give ~10 MB)
    with BagRecorder(dst, fsync=False, flush_period=math.inf, compression="zstd") as rec:
        rec.add_topic(JOINT_STATES, JOINT_STATE_TYPE)
        rec.add_topic(CURRENTS, JOINT_STATE_TYPE)
        for i, s in enumerate(int(v) for v in stamps):
            rec.write(JOINT_STATES, joint_state_cdr(s, SPEED_NAMES, velocity=run.speeds[i]), s)
            rec.write(CURRENTS, joint_state_cdr(s, CURRENT_NAMES, effort=run.currents[i]), s)
    made_truth = yaml.safe_load(run.truth) or {}
    made_truth["made_by"] = (f"scripts/make_validation_bags.py: dvt_driver.plant.offline "
                             f"(experiment {experiment.name} seed "
                             f"{int(made['experiment']['seed']) + 100}, validation of "
                             f"{source.name})")
    write_truth(dst, made_truth)
    size = sum(f.stat().st_size for f in dst.iterdir())
    if size > LIMIT_BYTES:
        raise SystemExit(f"{dst}: {size / 1e6:.2f} MB, over the 3 MB limit")
    print(f"{name:18s} from {source.name}: {size / 1e6:.2f} MB")
    return dst


def main(argv: list[str]) -> int:
    out = Path(argv[0]) if argv else ROOT / "bags"
    pairs = argv[1:] or list(DEFAULT)
    out.mkdir(parents=True, exist_ok=True)
    for pair in pairs:
        name, _, src = pair.partition("=")
        if not name or not src:
            print(f"make_validation_bags: expected NAME=SOURCE, got {pair!r}", file=sys.stderr)
            return 2
        make(out, name, ROOT / "bags" / src)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
