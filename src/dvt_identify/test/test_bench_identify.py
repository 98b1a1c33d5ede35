"""Smoke tests of ``dvt-bench identify`` (tiny runs: keys and finite values, not the targets)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify import bench_identify as bi


def _all_finite(obj: Any, where: str = "") -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _all_finite(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            _all_finite(v, f"{where}[{i}]")
    elif isinstance(obj, float):
        assert math.isfinite(obj), where


def test_power_law_exponent_recovers_the_slope() -> None:
    n = [1000.0, 2000.0, 4000.0]
    assert bi.power_law_exponent(n, [0.5 * v for v in n]) == pytest.approx(1.0)
    assert bi.power_law_exponent(n, [1e-6 * v ** 2 for v in n]) == pytest.approx(2.0)
    assert bi.power_law_exponent([1000.0], [1.0]) is None


def test_crlb_of_a_straight_line_is_sigma_over_the_regressor_norm() -> None:
    # y = a x + noise(sigma): var(a_hat) = sigma^2 / sum(x^2), the bound of the LS estimate
    x = np.linspace(-1.0, 2.0, 50)
    sigma = 0.3
    jac = (x / sigma)[:, None]
    assert bi.crlb_std(jac, 1)[0] == pytest.approx(sigma / np.linalg.norm(x), rel=1e-9)


def test_monte_carlo_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    rc = bi.main(["--monte-carlo", "4", "--mc-seconds", "2", "--mc-rate", "200",
                     "--workers", "2", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["runs"] == 4 and res["runs_ok"] == 4 and res["failed"] == []
    assert res["record"]["samples"] == 400
    assert set(res["parameters"]) == {"M11", "M12", "M22", "D11", "D12", "D22"}
    for p in res["parameters"].values():
        assert {"true", "mean", "std", "crlb_std", "crlb_ratio", "bias",
                "coverage_95"} <= set(p)
        assert p["crlb_std"] > 0 and p["std"] > 0
        assert 0.0 <= p["coverage_95"] <= 1.0
    for key in ("max_crlb_ratio", "mean_coverage_95", "seed", "wall_seconds"):
        assert key in res
    _all_finite(res)


@pytest.mark.slow  # a whole benchmark run: about 2 min of CPU (measured 121 s)
def test_timing_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    # baseline and augment loop on the first 3 s of the committed recordings (the scaling runs
    # repeat the baseline path; the exponent is checked on synthetic figures above)
    rc = bi.main(["--seconds", "3", "--scaling", "none", "--fit-decimate", "2",
                     "--starts", "1", "--max-tries", "1", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert 2990 <= res["samples"] <= 3001  # 1 kHz, stamps as the driver mapped them
    rec = res["recording"]
    assert rec["samples"] == res["samples"] and rec["cut_to_seconds"] == 3.0
    assert [Path(b).name for b in rec["estimation"]] == [bi.DEFAULT_ESTIMATION]
    assert [Path(b).name for b in rec["validation"]] == [bi.DEFAULT_VALIDATION]
    assert res["baseline_seconds"] > 0 and res["loop_seconds"] > 0
    # end to end adds reading the bags and writing the report to the identification
    assert res["baseline_end_to_end_seconds"] > res["baseline_seconds"]
    assert res["loop_end_to_end_seconds"] > res["loop_seconds"]
    assert res["baseline_end_to_end_no_plots_seconds"] > 0  # a separate run: no order
    assert res["breakdown"]["jit_load_seconds"] >= 0
    assert res["settings"]["fit_decimate"] == 2 and res["settings"]["starts"] == 1
    assert res["settings"]["max_tries_per_round"] == 1
    assert [p["samples"] for p in res["scaling"]] == [res["samples"]]
    assert res["scaling"][0]["baseline_seconds"] == res["baseline_seconds"]
    assert res["scaling_exponent"] is None
    for key in ("breakdown", "fit", "meets_targets", "targets"):
        assert key in res
    assert set(res["fit"]["baseline_validation_fit_percent"]) == {"sun_shaft", "carrier3"}
    assert res["breakdown"]["loop_refits"] >= 0
    _all_finite(res)


def test_pretty_output_of_the_monte_carlo(capsys: pytest.CaptureFixture[str]) -> None:
    assert bi.main(["--monte-carlo", "2", "--mc-seconds", "1", "--mc-rate", "100",
                    "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "crlb_ratio" in out and "M11" in out


@pytest.mark.parametrize("argv, message", [
    (["--monte-carlo", "1"], "--monte-carlo: expected N >= 2, got 1"),
    (["--seconds", "0"], "--seconds: expected > 0, got 0.0"),
    (["--estimation", "/nonexistent/bag"], "/nonexistent/bag: no such bag directory"),
    (["--monte-carlo", "3", "--noise", "0"], "--noise: expected > 0, got 0.0"),
])
def test_bad_settings_exit_2_with_a_message(argv: list[str], message: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert bi.main(argv) == 2
    assert message in capsys.readouterr().err


def test_the_bench_needs_no_plant() -> None:
    # the identifier depends on dvt_model only: its benchmark reads recordings
    import ast
    import pkgutil

    for mod in pkgutil.iter_modules(bi.__path__):
        path = Path(bi.__path__[0]) / f"{mod.name}.py"
        tree = ast.parse(path.read_text())
        imported = {n.module for n in ast.walk(tree)
                    if isinstance(n, ast.ImportFrom) and n.module}
        imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import)
                     for a in n.names}
        assert not any(m.split(".")[0] == "dvt_driver" for m in imported), (path, imported)


def test_monte_carlo_coloured_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    rc = bi.main(["--monte-carlo", "3", "--mc-seconds", "2", "--mc-rate", "200",
                     "--workers", "1", "--coloured", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["runs_ok"] == 3
    rec = res["record"]
    assert "AR(1)" in rec["noise"] and "Coulomb" in rec["unmodelled"]
    for p in res["parameters"].values():
        assert 0.0 <= p["coverage_95"] <= 1.0 and 0.0 <= p["coverage_95_nominal"] <= 1.0
        assert p["true"] != p["nominal"]  # pseudo-true values: the misspecified limit


def test_coloured_noise_has_the_asked_std_and_correlation() -> None:
    e = bi.coloured_noise(np.random.default_rng(0), (100000, 2), np.array([1.0, 2.0]), 0.9)
    assert np.std(e, axis=0) == pytest.approx([1.0, 2.0], rel=0.05)
    assert np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1] == pytest.approx(0.9, abs=0.01)


def test_pretty_output_of_the_comparison() -> None:
    peer = {"told": ["coulomb_friction"], "validation_fit_percent_free_run": {"a": 98.8, "b": 98.6},
            "M_error_percent": 0.7, "D_error_percent": 1.1, "fit_seconds": 40.0,
            "build_seconds": 20.0, "cpu_seconds": 21.0, "status": "Solve_Succeeded",
            "iterations": 30, "nodes": 3300}
    row = {"estimation": "bags/ident-coulomb", "validation": "bags/ident-coulomb-val",
           "validation_fit_percent": {"a": 98.9, "b": 98.7},
           "validation_fit_percent_free_run": {"a": 98.9, "b": 98.7},
           "accepted": ["coulomb_friction@carrier3"], "M_error_percent": 0.5,
           "D_error_percent": 1.4, "seconds": 9.0, "cpu_seconds": 8.5, "baseline_fit_seconds": 1.0,
           "baseline_suspect": [], "peer": peer, "meets_targets": {"twice_as_fast": True}}
    text = bi.pretty({"mode": "compare", "runs": [row], "peer_method": "ms",
                      "load_average": {"before": [], "after": []}})
    assert "98.80 / 98.60" in text and "M error 0.50 %" in text and "twice_as_fast yes" in text
    assert "M error 0.70 %" in text and "Solve_Succeeded" in text
    row["peer"] = {"not_run": "peer not run: casadi not installed"}
    del row["meets_targets"]
    text = bi.pretty({"mode": "compare", "runs": [row], "peer_method": "ms",
                      "load_average": {"before": [], "after": []}})
    assert "peer not run: casadi not installed" in text and "98.80" not in text
