"""dvt-identify end to end on small synthetic bags; bad input gives one line and status 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import signal

from dvt_identify.cli import main
from dvt_identify.data import JointStateSeries, write_jointstate_bag

DESC = {
    "name": "toy",
    "inputs": [{"name": "force", "topic": "/toy/drive", "field": "effort", "joint": "slide"}],
    "outputs": [{"name": "slide", "topic": "/toy/joint_states", "field": "velocity",
                 "joint": "slide"}],
    "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                  "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                  "parameters": {"M": {"initial": 5.0, "lower": 0.01},
                                 "Fv": {"initial": 10.0, "lower": 0.0}}},
    "candidates": [{"effect": "coulomb_friction", "where": "slide"},
                   {"effect": "windage", "where": "slide"}],
    "fit": {"starts": 2, "refit_starts": 1},
}


def _bag(path: Path, seed: int, fc: float = 4.0) -> Path:
    """M = 10 kg, Fv = 20 N s/m, Coulomb fc, simulated with a plain Euler-free exact step."""
    from dvt_identify.data import make_segment
    from dvt_identify.effects import make_effect
    from dvt_identify.simulation import OEModel
    from dvt_identify.structures import MechanicalStructure

    rng = np.random.default_rng(seed)
    n, dt = 2000, 0.002
    t = np.arange(n) * dt
    sos = signal.butter(2, 3.0, fs=1 / dt, output="sos")
    f = 30 * np.sin(2 * np.pi * 0.7 * t + seed) + 60 * signal.sosfilt(sos, rng.normal(size=n))
    st = MechanicalStructure(["slide"], ["force"], [["M"]], [["Fv"]], [[1.0]],
                             {"M": 10.0, "Fv": 20.0})
    model = OEModel(st, [make_effect("coulomb_friction", "slide", ["slide"], ["force"])])
    seg = make_segment("s", t, f, np.zeros(n), ["force"], ["slide"])
    y = model.simulate(np.array([10.0, 20.0, fc, 0.5]), seg, np.array([0.1]))[:, 0]
    y = y + 0.01 * np.std(y) * rng.normal(size=n)
    stamps = (10**9 + np.round(t * 1e9)).astype(np.int64)
    return write_jointstate_bag(path, {
        "/toy/joint_states": JointStateSeries(stamps, ("slide",), velocity=y[:, None]),
        "/toy/drive": JointStateSeries(stamps, ("slide",), effort=f[:, None]),
    })


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp("bags")
    desc = d / "toy.yaml"
    desc.write_text(yaml.safe_dump(DESC))
    return _bag(d / "est", 1), _bag(d / "val", 2), desc


def test_cli_end_to_end(bags: tuple[Path, Path, Path], tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    est, val, desc = bags
    out = tmp_path / "out"
    assert main([str(est), "--validate", str(val), "--out", str(out), "--description",
                 str(desc), "--quiet"]) == 0
    summary = capsys.readouterr().out
    assert "accepted: coulomb_friction@slide" in summary
    rep = json.loads((out / "report.json").read_text())
    assert rep["estimation_bags"] == [str(est)] and rep["validation_bags"] == [str(val)]
    assert rep["effects"][0]["name"] == "coulomb_friction" and rep["effects"][0]["accepted"]
    assert rep["final"]["parameters"]["Fc"] == pytest.approx(4.0, rel=0.1)
    assert rep["final"]["fit_percent"]["slide"] > rep["baseline"]["fit_percent"]["slide"]
    assert set(rep["baseline"]["rmse"]) == {"slide"}
    assert (out / "report.md").exists() and (out / "fit_slide.png").exists()


def test_cli_no_augment(bags: tuple[Path, Path, Path], tmp_path: Path) -> None:
    est, val, desc = bags
    assert main([str(est), "--validate", str(val), "--out", str(tmp_path), "--description",
                 str(desc), "--no-augment", "--quiet"]) == 0
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["effects"] == [{"name": "none", "accepted": True}]
    assert rep["final"] == rep["baseline"]


def test_cli_bad_input_one_line(bags: tuple[Path, Path, Path], tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    est, val, desc = bags
    assert main([str(est), "--validate", str(est), "--out", str(tmp_path), "--description",
                 str(desc), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "used for both estimation and validation" in err[0]
    # the console script: missing bag -> one line on stderr, status 2
    exe = Path(sys.executable).parent / "dvt-identify"
    r = subprocess.run([str(exe), str(tmp_path / "nope"), "--validate", str(val), "--out",
                        str(tmp_path), "--description", str(desc)],
                       capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("[dvt-identify]")]
    assert lines == [f"dvt-identify: error: {tmp_path / 'nope'}: bag not found"]


def test_the_cli_and_the_node_share_the_pipeline() -> None:
    import ast
    import importlib.util

    def imports(module: str) -> set[str]:
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin is not None
        tree = ast.parse(Path(spec.origin).read_text())
        return {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "dvt_identify.pipeline" in imports("dvt_identify.cli")
    node = imports("dvt_identify.node")
    assert "dvt_identify.pipeline" in node and "dvt_identify.cli" not in node


def test_loop_config_overrides() -> None:
    from dvt_identify.description import load_description
    from dvt_identify.pipeline import loop_config

    desc = load_description("dvt")
    same = loop_config(desc)
    assert (same.starts, same.fit_decimate, same.augment) == (
        desc.fit.starts, desc.preprocess.fit_decimate, True)
    cfg = loop_config(desc, augment=False, starts=0, fit_decimate=3)
    assert (cfg.starts, cfg.fit_decimate, cfg.augment) == (1, 3, False)
