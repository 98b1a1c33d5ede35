"""A belt drive read by a sign-blind pulse counter, identified as a new user would: a
description that gives scales only (every prior 1), three 300-sample records at 50 Hz as
estimation bags, the choice by cross-validation over them, and the rest of each record as
test bags (``tests/belt_drive.py``).

Before the sign-blind output was unfolded for the starts (:mod:`dvt_identify.unfold`) and the
initial states tried from both signs (:func:`dvt_identify.fitstarts.x0_guesses`), the fit
collapsed on all three drives (a spring run to 1e15, out-of-fold fit below 3 %, nothing
accepted) and the physical model scored worse than the linear reference."""

from __future__ import annotations

import json
from pathlib import Path

import belt_drive
import numpy as np
import pytest

from dvt_identify.cli import main
from dvt_identify.data import JointStateSeries, Segment, write_jointstate_bag

pytestmark = pytest.mark.slow


def write_bag(path: Path, seg: Segment) -> Path:
    stamps = (10**9 + np.round(seg.t * 1e9)).astype(np.int64)
    return write_jointstate_bag(path, {
        "/belt/joint_states": JointStateSeries(stamps, ("pulley",), velocity=seg.y[:, :1]),
        "/belt/drive": JointStateSeries(stamps, ("motor",), effort=seg.u[:, :1]),
    })


def identify(tmp_path: Path, drive: str | dict[str, float], friction: float, seed: int = 21,
             lag: float = 0.0, extra: list[dict[str, object]] | None = None) -> dict:
    """500-sample records (``belt_drive.records`` with ``seed``, ``friction`` and ``lag``): the
    first 300 estimation, the last 200 test; ``extra`` candidates in the description."""
    segs, _ = belt_drive.records(drive, seed=seed, n=500, friction=friction, lag=lag)
    est = [str(write_bag(tmp_path / f"est{k}", s.rows(0, 300))) for k, s in enumerate(segs)]
    test = [str(write_bag(tmp_path / f"test{k}", s.rows(300, 500, from_zero=True)))
            for k, s in enumerate(segs)]
    desc = belt_drive.write_description(tmp_path / "belt-drive.yaml", extra)
    assert main([*est, "--select-on", "cv", "--test", *test, "--description", str(desc),
                 "--out", str(tmp_path / "rep"), "--no-plots"]) == 0
    return json.loads((tmp_path / "rep" / "report.json").read_text())


def accepted(rep: dict) -> list[str]:
    return [f"{e['name']}@{e['where']}" for e in rep["effects"] if e["accepted"]]


@pytest.mark.parametrize("drive", sorted(belt_drive.DRIVES))
def test_a_sign_blind_drive_is_found_from_scale_only_priors(tmp_path: Path, drive: str) -> None:
    """The sign-blind map is accepted and nothing else; the test records (no part in any
    choice) are fitted above 95 % and better than the linear reference."""
    rep = identify(tmp_path, drive, 0.0)
    assert accepted(rep) == ["sign_blind@w_pulley"]
    test = rep["test"]
    fit = test["final"]["fit_percent"]["w_pulley"]
    assert fit > 95.0 and fit > test["linear_reference"]["fit_percent"]["w_pulley"], test


def test_friction_behind_a_sign_blind_sensor_is_named_with_the_drive(tmp_path: Path) -> None:
    """A Coulomb friction on the motor (0.12 N m, a quarter of the smallest command) behind the
    sign-blind sensor: both are accepted, and every structure parameter and the friction level
    lie within 3 reported standard deviations of the drive's."""
    rep = identify(tmp_path, "slow_belt", 0.12)
    assert sorted(accepted(rep)) == ["coulomb_friction@motor", "sign_blind@w_pulley"]
    values, std = rep["final"]["parameters"], rep["final"]["parameter_std"]
    for name, value in {**belt_drive.DRIVES["slow_belt"], "Fc": 0.12}.items():
        assert abs(values[name] - value) <= 3.0 * std[name], (name, values[name], std[name])


def test_a_filtered_reading_keeps_both_maps_and_the_drive_within_3_std(tmp_path: Path) -> None:
    """A drawn drive (``belt_drive.draw`` seed 10: a heavy motor on a light pulley, belt mode
    5.1 Hz) whose counter is read through a 30-ms filter, with the ``sensor_lag`` candidate:
    the sign-blind map and the lag are accepted and every structure parameter and the time
    constant lie within 3 reported std of the drawn ones. Before the restarts of a collapsed
    trust region (``dvt_identify.fit.MAX_RESTARTS``) the refit stopped in the valley of the
    mass ratio with the belt damping 25 std off; with the restarts alone, the recheck's refit
    of the sign-blind map from the model without it missed the current optimum (cost 268
    against 0.52) and took the map out (test fit 8 %): the recheck now also starts there."""
    drive = belt_drive.draw(np.random.default_rng(10))
    rep = identify(tmp_path, drive, 0.0, seed=1000, lag=0.03,
                   extra=[{"effect": "sensor_lag", "where": "w_pulley"}])
    assert sorted(accepted(rep)) == ["sensor_lag@w_pulley", "sign_blind@w_pulley"]
    values, std = rep["final"]["parameters"], rep["final"]["parameter_std"]
    for name, value in {**drive, "tau": 0.03}.items():
        assert abs(values[name] - value) <= 3.0 * std[name], (name, values[name], std[name])
