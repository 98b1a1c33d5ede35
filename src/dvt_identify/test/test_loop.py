"""The augment loop: nothing accepted on clean data, the true effect accepted otherwise."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects import make_effect
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.report import build_report, write_report
from dvt_identify.simulation import OEModel

DT = 0.002
N = 2500


def description() -> Description:
    sig = {"topic": "/s/joint_states", "field": "velocity", "joint": "x"}
    data: dict[str, Any] = {
        "name": "synthetic",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "x"}],
        "outputs": [{"name": "v", **sig}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                      "parameters": {"M": {"initial": 5.0, "lower": 0.001},
                                     "Fv": {"initial": 10.0, "lower": 0.0}}},
        "candidates": [
            {"effect": "coulomb_friction", "where": "v", "offset": True},
            {"effect": "stribeck_friction", "where": "v"},
            {"effect": "windage", "where": "v"},
            {"effect": "asymmetric_friction", "where": "v"},
            {"effect": "backlash", "where": "force"},
            {"effect": "measurement_delay", "where": "v", "max_delay": 0.02},
            {"effect": "sensor_gain", "where": "v"},
        ],
        "fit": {"starts": 2, "refit_starts": 1, "max_effects": 3},
        "notes": ["synthetic test data"],
    }
    return parse_description(data, "test")


def make(seed: int, fc: float = 0.0) -> Segment:
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    sos = signal.butter(2, 3.0, fs=1 / DT, output="sos")
    f = (30 * np.sin(2 * np.pi * 0.7 * t + seed) + 15 * np.sin(2 * np.pi * 2.3 * t + 1)
         + 60 * signal.sosfilt(sos, rng.normal(size=N)))
    desc = description()
    effects = [make_effect("coulomb_friction", "v", ["v"], ["force"])] if fc else []
    model = OEModel(desc.structure, effects)
    theta = np.array([10.0, 20.0] + ([fc, 1.0] if fc else []))
    seg = make_segment(f"seg{seed}", t, f, np.zeros(N), ["force"], ["v"])
    y = model.simulate(theta, seg, np.array([0.2]))
    y = y + 0.01 * np.std(y) * rng.normal(size=y.shape)
    return make_segment(f"seg{seed}", t, f, y, ["force"], ["v"])


def test_nothing_accepted_on_clean_data(tmp_path: Path) -> None:
    desc = description()
    res = identify([make(1), make(3)], [make(2)], desc,
                   LoopConfig.from_options(desc.fit))
    assert res.accepted == []
    assert res.final is res.baseline
    assert res.baseline.val.fit_percent[0] > 98.0
    p = res.baseline.parameters()
    assert p["M"] == pytest.approx(10.0, rel=0.02)
    assert p["Fv"] == pytest.approx(20.0, rel=0.02)
    rep = build_report(res)
    assert rep["effects"] == [{"name": "none", "accepted": True}]
    assert rep["final"] == rep["baseline"]
    assert {"estimation_bags", "validation_bags", "baseline", "effects", "final"} <= set(rep)
    assert set(rep["baseline"]["fit_percent"]) == {"v"}
    paths = write_report(res, tmp_path)
    assert json.loads(paths["json"].read_text())["effects"][0]["name"] == "none"
    assert "No candidate was accepted" in paths["md"].read_text()


def test_coulomb_accepted_and_recovered(tmp_path: Path) -> None:
    desc = description()
    res = identify([make(1, fc=6.0)], [make(2, fc=6.0)], desc,
                   replace(LoopConfig.from_options(desc.fit), max_effects=1))
    assert [d.score.effect.name for d in res.accepted] == ["coulomb_friction"]
    assert res.rounds[0][0].effect.name == "coulomb_friction"  # ranked first by its score
    p = res.final.parameters()
    assert p["Fc"] == pytest.approx(6.0, rel=0.05)
    assert p["M"] == pytest.approx(10.0, rel=0.03)
    assert res.final.val.fit_percent[0] > res.baseline.val.fit_percent[0] + 1.0
    dec = res.accepted[0]
    assert dec.lr > dec.lr_threshold and dec.delta_bic < 0
    # the simpler direction-dependent viscous law (1 parameter) passes too, but the richer
    # Coulomb friction (2) is significantly better on validation: parsimony does not apply
    [asym] = [d for d in res.decisions if d.score.effect.name == "asymmetric_friction"]
    assert not asym.accepted and asym.dof < dec.dof
    assert asym.reason.startswith("passes (")
    assert ("but coulomb_friction@v has the larger LR" in asym.reason
            and "and is significantly better on validation (error " in asym.reason)
    rep = build_report(res)
    first = rep["effects"][0]
    assert first["name"] == "coulomb_friction" and first["accepted"] is True
    assert first["where"] == "v"
    assert set(first["parameters"]) >= {"Fc", "offset"}
    assert "r2_projected" in first["evidence"] and first["evidence"]["refits"]
    assert rep["final"]["parameters"]["Fc"] == pytest.approx(p["Fc"])
    paths = write_report(res, tmp_path)
    for name in ("fit_v.png", "resid_v.png", "candidates.png", "linear_step_bode.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
    assert paths["md"].read_text().count("coulomb_friction") >= 2
