"""The live loop's first refit on a plant whose Coulomb friction steps (``friction_step``), for
``tests/test_first_refit.py`` (a module of its own, importable by name from ``tests/``, so that
spawned worker processes can run it).

A case is a seed: the ``watch`` experiment (that experiment and noise seed) on the
``physical`` plant at 1 kHz, its Coulomb friction stepping from 0 to 0.05 N m (sun) and
0.20 N m (carrier 3) at 6 s, recorded offline as the supervisor's snapshot bag; the refit
fits 2.5 s from 0.5 s after the change, holds 1.5 s out, keeps the structure at the model in
use (``physical``) and fits at a 10-ms step, as the live loop's first refit does.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import run_offline
from dvt_driver.run.experiment_core import build
from dvt_identify.refit import RefitSettings, refit
from dvt_identify.supervisor import RequestFit
from dvt_model.params import load_parameters
from dvt_model.recording import write_run

T0_NS = 1_800_000_000 * 10**9
"""Host time of the snapshot's first sample [ns]."""
CHANGE_AT_S = 6.0
"""When the plant's Coulomb friction steps, from the snapshot's start [s]."""


def friction_step_bag(root: Path, seed: int, change_at: float = CHANGE_AT_S,
                      duration: float = 12.0, rate: float = 1000.0) -> tuple[Path, float]:
    """The snapshot bag of case ``seed`` under ``root`` and the change time (host time [s]):
    ``duration`` [s] of the ``watch`` experiment at controller rate ``rate`` [Hz], the step at
    plant time ``change_at`` [s] (``scripts/first_refits.py`` varies them)."""
    hidden = load_hidden("friction_step")
    hidden = dataclasses.replace(hidden, changes=tuple(
        dataclasses.replace(c, at=change_at) for c in hidden.changes))
    exp = dataclasses.replace(build("watch", seed=seed, duration=duration),
                              sample_period_us=round(1e6 / rate))
    run = run_offline(exp, load_parameters("physical"), hidden, seed=seed)
    stamps = T0_NS + np.round(run.t * 1e9).astype(np.int64)
    bag = write_run(root / "snapshot", stamps, run.speeds, run.currents,
                    positions=run.positions)
    return bag, T0_NS * 1e-9 + change_at


def first_refit(bag: Path, change: float, work: Path) -> Any:
    """The first refit of the module docstring on ``bag`` (change at host time ``change``)."""
    req = RequestFit(1, (change + 0.5, change + 3.0), (change + 3.0, change + 4.5),
                     ("sun_shaft",))
    return refit(bag, req, {"params": "physical"}, work, RefitSettings(fit_decimate=10))


def refit_row(seed: int, root: str) -> tuple[int, list[str], str]:
    """Case ``seed`` under ``root``: (seed, the accepted effects, the refit's error or "")."""
    work = Path(root) / f"seed{seed}"
    work.mkdir()
    bag, change = friction_step_bag(work, seed)
    out = first_refit(bag, change, work / "work")
    return seed, list(out.summary.get("accepted", [])), out.error or ""
