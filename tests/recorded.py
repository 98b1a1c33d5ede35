"""Identification on a committed recording in ``bags/`` with a fresh validation run of the same
plant (shared by the tests on undeclared effects).

Validation data: the plant whose hidden effects the recording's ``truth.yaml`` names (only tests
read it, never the identifier), driven offline through the driver's supervisor with another
experiment seed and noise seed.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import yaml

from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_model.params import load_parameters

BAGS = Path(__file__).resolve().parents[1] / "bags"


def validation_run(name: str, out: Path) -> Path:
    """Record the validation run of recording ``name`` into ``out`` (experiment and noise seeds
    + 100); its path."""
    bag = BAGS / name
    truth = yaml.safe_load((bag / "truth.yaml").read_text())
    made = yaml.safe_load((bag / "run.yaml").read_text())
    experiment = build(made["experiment"]["name"], seed=int(made["experiment"]["seed"]) + 100)
    return record_offline(out, experiment, load_parameters(truth["plant"]["params"]),
                          parse_hidden(truth["hidden"]), seed=int(truth["plant"]["seed"]) + 100)


def identify_recorded(name: str, tmp_path: Path, max_effects: int = 1
                      ) -> tuple[IdentificationResult, Path]:
    """Identify the ``dvt`` description on recording ``name`` (estimation) and its validation
    run (recorded under ``tmp_path / 'val'``), at most ``max_effects`` accepted effects; the
    result and the validation run's path."""
    val = validation_run(name, tmp_path / "val")
    desc = load_description("dvt")
    est = load_segments([BAGS / name], desc)
    vals = load_segments([val], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = replace(LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate),
                  max_effects=max_effects)
    return identify(est, vals, desc, cfg, check=chk), val
