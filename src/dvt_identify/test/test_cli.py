"""dvt-identify end to end on small synthetic bags; bad data gives one line and status 1, bad
usage status 2 (as dvt-bag)."""

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
                 str(desc), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "used for both estimation and validation" in err[0]
    # the console script: missing bag -> one line on stderr, status 1 (a data error)
    exe = Path(sys.executable).parent / "dvt-identify"
    r = subprocess.run([str(exe), str(tmp_path / "nope"), "--validate", str(val), "--out",
                        str(tmp_path), "--description", str(desc)],
                       capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 1
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


def test_check_names_undetermined_band_parameters_and_the_experiment(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--check`` on the thesis recording (band 1 only): the gains and lags of bands 2 and 3
    are not determined, and the experiment that determines them is named."""
    bag = Path(__file__).resolve().parents[3] / "bags" / "thesis-none"
    assert main([str(bag), "--check", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for name in ("band_gain_ring2", "band_gain_ring3", "band_time_constant_brake2",
                 "band_time_constant_brake3"):
        assert f"{name}: not determined by this recording" in out, out
    assert "band_gain_ring1: not determined" not in out
    assert "dvt-experiment ident_shifts" in out
    assert out.strip().splitlines()[-1] == "enough: no, record dvt-experiment ident_shifts"
    rep = json.loads((tmp_path / "check.json").read_text())
    assert {"band_gain_ring2", "band_gain_ring3"} <= set(rep["not_determined"])
    assert rep["experiments"] == ["dvt-experiment ident_shifts"]
    fixed = {q["name"] for q in rep["parameters"] if q["fixed_at_prior"]}
    assert fixed == {"band_gain_ring2", "band_gain_ring3", "band_time_constant_brake2",
                     "band_time_constant_brake3"}


def test_check_needs_no_validation_but_a_fit_does(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    bag = Path(__file__).resolve().parents[3] / "bags" / "ident-none-1"
    with pytest.raises(SystemExit) as exc:
        main([str(bag), "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--validate and --out are required" in capsys.readouterr().err


def test_exit_codes_match_dvt_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Usage errors 2, data errors 1: the same convention as ``dvt-bag``."""
    def bag(*args: str) -> int:  # the console script (dvt_identify does not import dvt_driver)
        exe = Path(sys.executable).parent / "dvt-bag"
        return subprocess.run([str(exe), *args], capture_output=True, timeout=60,
                              check=False).returncode

    with pytest.raises(SystemExit) as exc:
        main(["--no-such-option"])
    assert exc.value.code == 2 == bag("no-such-command")
    missing = tmp_path / "nope"
    assert bag("info", str(missing)) == 1
    assert main([str(missing), "--validate", str(tmp_path / "v"), "--out", str(tmp_path / "o"),
                 "--quiet"]) == 1
    capsys.readouterr()


def test_recover_is_suggested_only_for_a_bag_with_an_unreadable_mcap(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("# not a bag\n")
    args = ["--validate", str(tmp_path / "v"), "--out", str(tmp_path / "o"), "--quiet"]
    assert main([str(readme), *args]) == 1
    err = capsys.readouterr().err
    assert "dvt-bag recover" not in err and "not a bag directory" in err, err
    # the recording layer's hint names `dvt-bag recover` only where it can help
    from dvt_model.recording.layout import recover_hint

    killed = _bag(tmp_path / "killed", 3)
    for path, keep in ((killed, True), (readme, False), (tmp_path / "none", False)):
        text = recover_hint(path)
        assert (f"`dvt-bag recover {path}`" in text) is keep, text
        assert keep or "not a bag directory" in text, text


def test_header_names_the_description_once(bags: tuple[Path, Path, Path],
                                           capsys: pytest.CaptureFixture[str]) -> None:
    from dvt_identify.description import load_description
    from dvt_identify.pipeline import description_label

    assert description_label(load_description("dvt")) == "dvt (bundled)"
    _, _, desc = bags
    assert description_label(load_description(str(desc))) == f"toy ({desc})"


def test_negative_likelihood_ratio_reads_no_improvement() -> None:
    from dvt_identify.report import _lr_cell
    from dvt_identify.selection import lr_text

    assert lr_text(-2.8, 3.84) == "no improvement (LR 0 <= chi2 threshold 3.84)"
    assert lr_text(1.5, 3.84) == "LR 1.5 <= chi2 threshold 3.84"
    assert lr_text(float("-inf"), 3.84).startswith("no improvement")
    assert _lr_cell(-2.8) == "0 (no improvement)" and _lr_cell(12.5) == "12.5"
