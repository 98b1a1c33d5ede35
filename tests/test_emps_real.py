"""Acceptance on real data: the EMPS benchmark through examples/emps/run.sh.

Reads the two EMPS records from ``../shared/data/emps`` relative to the repository root (the
folder beside the work tree); skipped with a reason when the folder is absent. The figures checked
come from the folder's README: baseline (inertia + viscous) validation velocity fit ~ 81.7 %,
Coulomb friction with offset ranked first and accepted, final validation fit >= 93 %, M within
3 % of 95.11 kg, Fc within 10 % of 20.39 N (IDIM-LS, benchmark authors).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
EMPS = ROOT.parent / "shared" / "data" / "emps"
RUN = ROOT / "examples" / "emps" / "run.sh"

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (EMPS / "emps_estimation.npz").is_file(),
                       reason=f"EMPS data not found at {EMPS} (shared data folder absent)"),
]


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("emps")
    r = subprocess.run(["bash", str(RUN), str(out)], capture_output=True, text=True,
                       timeout=900, check=False, env={**os.environ, "EMPS_DIR": str(EMPS)})
    assert r.returncode == 0, r.stderr[-3000:]
    assert (out / "report.md").is_file()
    for png in ("fit_carriage.png", "resid_carriage.png", "candidates.png",
                "linear_step_bode.png", "spectrum_carriage.png"):
        assert (out / png).stat().st_size > 10_000, png
    rep: dict[str, Any] = json.loads((out / "report.json").read_text())
    rep["_md"] = (out / "report.md").read_text()
    return rep


def test_contract_keys(report: dict[str, Any]) -> None:
    assert {"estimation_bags", "validation_bags", "baseline", "effects", "final"} <= set(report)
    assert report["estimation_bags"][0].endswith("emps_estimation")
    assert report["validation_bags"][0].endswith("emps_validation")
    for stage in ("baseline", "final"):
        assert set(report[stage]["fit_percent"]) == {"carriage"}
        assert set(report[stage]["rmse"]) == {"carriage"}


def test_baseline_is_inertia_plus_viscous(report: dict[str, Any]) -> None:
    b = report["baseline"]
    assert b["fit_percent"]["carriage"] == pytest.approx(81.7, abs=1.5)
    assert b["rmse"]["carriage"] == pytest.approx(0.0162, rel=0.1)
    assert set(b["parameters"]) == {"M", "Fv"}
    assert b["parameters"]["M"] == pytest.approx(106.1, rel=0.03)
    assert b["parameters"]["Fv"] == pytest.approx(429.6, rel=0.05)


def test_coulomb_with_offset_ranked_first_and_accepted(report: dict[str, Any]) -> None:
    first = report["effects"][0]
    assert first["name"] == "coulomb_friction" and first["accepted"] is True
    assert set(first["parameters"]) >= {"Fc", "offset"}
    assert report["decisions"][0]["round"] == 1
    round1 = [d for d in report["decisions"] if d["round"] == 1 and d["accepted"]]
    assert [d["candidate"] for d in round1] == ["coulomb_friction@carriage"]
    ev = first["evidence"]
    assert ev["p_value"] < 1e-6 and ev["r2_projected"] > 0.1


def test_final_figures(report: dict[str, Any]) -> None:
    f = report["final"]
    assert f["fit_percent"]["carriage"] >= 93.0
    p = f["parameters"]
    assert {"M", "Fv", "Fc", "offset"} <= set(p)
    assert p["M"] == pytest.approx(95.11, rel=0.03)
    assert p["Fc"] == pytest.approx(20.39, rel=0.10)
    assert f["rmse"]["carriage"] < 0.0065


def test_asymmetry_found_or_reported(report: dict[str, Any]) -> None:
    """Stretch goal: direction-dependent viscous friction (Fv+ 166.7, Fv- 240.4 N s/m by
    IDIM-LS). If it is accepted, its figures must be close; the report must mention it."""
    names = [e["name"] for e in report["effects"] if e["accepted"]]
    if "asymmetric_friction" in names:
        p = report["final"]["parameters"]
        assert p["Fv+"] == pytest.approx(166.7, rel=0.10)
        assert p["Fv-"] == pytest.approx(240.4, rel=0.10)
    assert "asymmetric" in report["_md"]
    assert report["remaining"], "the report says what is left in the residual"
