"""Acceptance on real data: the EMPS benchmark through examples/emps/run.sh.

Reads the two EMPS records from ``../shared/data/emps`` relative to the repository root (the
folder beside the work tree); skipped with a reason when the folder is absent. The figures checked
come from the folder's README: baseline (inertia + viscous) validation velocity fit ~ 81.7 %,
Coulomb friction with offset ranked first and accepted, final validation fit >= 93 %, M within
3 % of 95.11 kg, Fc within 10 % of 20.39 N (IDIM-LS, benchmark authors).

The benchmark's own protocol (examples/emps/benchmark.py, run on its own: about 30 s of CPU):
simulated position on the test record (DATA_EMPS_PULSES) after a 20-sample state-initialisation
window, RMS in mm, for the position-state model with the effects the loop accepts (Coulomb with
offset, asymmetric viscous) fitted on the estimation record, and for the published IDIM-LS
parameters simulated the same way.
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
BENCH = ROOT / "examples" / "emps" / "benchmark.py"
PY = ROOT / ".venv" / "bin" / "python"

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
    bench = json.loads((out / "benchmark.json").read_text())
    assert any(r["label"].startswith("velocity loop's final model") for r in bench["rows"])
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


# ---------------------------------------------------------------------------------------------
# The EMPS benchmark protocol (simulated position, 20-sample window), benchmark.py on its own


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("emps_bench")
    r = subprocess.run([str(PY), str(BENCH), "--data", str(EMPS), "--out", str(out)],
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    res: dict[str, Any] = json.loads((out / "benchmark.json").read_text())
    res["_md"] = (out / "benchmark.md").read_text()
    res["_rows"] = {row["label"]: row for row in res["rows"]}
    return res


def _row(bench: dict[str, Any], start: str) -> dict[str, Any]:
    rows = [r for label, r in bench["_rows"].items() if label.startswith(start)]
    assert len(rows) == 1, (start, list(bench["_rows"]))
    return rows[0]


def test_benchmark_protocol(bench: dict[str, Any]) -> None:
    p = bench["protocol"]
    assert p["n_init"] == 20 and p["n_scored"] == 24841 - 20 and p["unit"] == "mm"
    assert [x["test_rms_mm"] for x in bench["published"]] == [5.53, 5.17, 2.64]
    for text in ("LTI state space", "polynomial NARX", "SOTA", "published IDIM-LS"):
        assert text in bench["_md"]


def test_benchmark_published_idim_ls_simulated(bench: dict[str, Any]) -> None:
    """No fit: the authors' parameters, exact ZOH with the stick rule, window x0: 8.39 mm.
    +-0.05 mm: the simulation is deterministic; forward Euler (the issue's 8.9 mm) gives
    8.85 mm, which this tolerance tells apart."""
    r = _row(bench, "published IDIM-LS")
    assert r["test_rms_mm"] == pytest.approx(8.39, abs=0.05)
    assert r["estimation_rms_mm"] == pytest.approx(5.32, abs=0.05)


def test_benchmark_our_models(bench: dict[str, Any]) -> None:
    """Fitted for the position on the estimation record, best of 5 starts by the estimation
    figure. Measured: Coulomb+offset 5.97 mm (est. 2.99), + asymmetric viscous 9.69 mm (est.
    2.15). The other starts reach estimation figures within 15 % of the best and test figures
    0.78 mm (Coulomb) and 2.56 mm (asymmetric) or more away, so +-0.5 mm on the test figure
    checks that the same optimum is chosen, and +-0.05 mm on the estimation figure that the fit
    is as good. (The asymmetric runner-up is only 0.7 % worse on the estimation figure, 2.165 mm,
    and scores 7.13 mm: a flip of that choice fails here, by design.)"""
    c = bench["_rows"]["ours: inertia + viscous + coulomb_friction"]
    a = bench["_rows"]["ours: inertia + viscous + coulomb_friction + asymmetric_friction"]
    assert c["test_rms_mm"] == pytest.approx(5.97, abs=0.5)
    assert c["estimation_rms_mm"] == pytest.approx(2.99, abs=0.05)
    assert a["test_rms_mm"] == pytest.approx(9.69, abs=0.5)
    assert a["estimation_rms_mm"] == pytest.approx(2.15, abs=0.05)
    assert a["test_velocity_fit_percent"] >= 93.0
    assert len(a["starts"]) == 5
    pa = a["parameters"]
    assert pa["M"] == pytest.approx(95.11, rel=0.03)
    assert pa["Fv+"] == pytest.approx(166.7, rel=0.10)
    lin = bench["_rows"]["ours: inertia + viscous"]
    assert lin["test_rms_mm"] > 50.0  # a linear rigid model drifts: friction is needed


def test_benchmark_limit_is_the_change_between_records(bench: dict[str, Any]) -> None:
    """The same structure fitted on the test record reaches < 1.5 mm (measured 0.88): the
    structure is adequate. Away from pulse edges the test record needed more force than the
    estimation record at the same reference in both directions (measured +0.72..+1.04 N and
    -0.58..-1.55 N per quarter; data means with ~0.05 N standard error): friction changed."""
    assert _row(bench, "diagnostic: same structure")["test_rms_mm"] < 1.5
    for q in bench["steady_force_difference"]:
        assert q["plus_N"] > 0.4 and q["minus_N"] < -0.4, q
