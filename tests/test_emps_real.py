"""Acceptance on real data: the EMPS benchmark through examples/emps/run.sh.

Reads the two EMPS records from ``../shared/data/emps`` relative to the repository root (the
folder beside the work tree); a missing folder fails the tests (``DVT_SKIP_EMPS=1`` leaves them
out on request, never silently). run.sh identifies
by the benchmark's own protocol with every choice made on the estimation record (its last 30 %
held out to choose the effects; ``--select-on holdout --init-window 20 --description
emps-position``), reads the test record only after every choice, and recomputes the figure
independently with examples/emps/benchmark.py.

Checked: the summary prints the test figure first, and its spread over halves of the estimation
data second; it is at most the published LTI state-space
figure (5.53 mm, Champneys et al. 2024; the issue's "done when"); the independent recomputation
agrees with the tool's figure; the published IDIM-LS model, simulated here with the exact sign
and stick rule, gives the reproduction of its figure (8.39 mm: deterministic, no fit); the
physical model scores at least as well as the tool's own linear reference on the selection and
the test data; and the tool says that the test record needed more friction than the estimation
record, as the records themselves show away from the pulse edges; and that the chosen
structure, refitted on the test record itself, describes it under the best known figure (the
distance to it is the records' disagreement, not a missing term); and the spread of the test
figure when the same structure is fitted on other parts of the estimation record is measured.
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
    # the module's fixture runs run.sh once (about 5 minutes on two quiet cores, more beside
    # other work; its own bound is 1200 s): above the suite's 300 s per test
    pytest.mark.timeout(1500),
    pytest.mark.skipif(os.environ.get("DVT_SKIP_EMPS") == "1",
                       reason="DVT_SKIP_EMPS=1: the EMPS acceptance left out on request"),
]


@pytest.fixture(scope="module")
def emps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    if not (EMPS / "emps_estimation.npz").is_file():
        pytest.fail(f"EMPS data not found at {EMPS}: the tests read ../shared/data/emps beside "
                    "the repository (set DVT_SKIP_EMPS=1 to leave this acceptance out)")
    out = tmp_path_factory.mktemp("emps")
    r = subprocess.run(["bash", str(RUN), str(out)], capture_output=True, text=True,
                       timeout=1200, check=False, env={**os.environ, "EMPS_DIR": str(EMPS)})
    assert r.returncode == 0, r.stderr[-3000:]
    return {"stdout": r.stdout, "report": json.loads((out / "report.json").read_text()),
            "bench": json.loads((out / "benchmark.json").read_text()),
            "md": (out / "report.md").read_text(), "out": out}


def test_the_test_figure_is_printed_first_and_beats_the_published_lti(
        emps: dict[str, Any]) -> None:
    first = emps["stdout"].splitlines()[0]
    assert first.startswith("test (no part in any choice): position RMSE "), emps["stdout"]
    tool_mm = 1e3 * emps["report"]["test"]["final"]["rmse"]["position"]
    assert f"RMSE {tool_mm / 1e3:.4g} m" in first
    assert tool_mm <= 5.53, tool_mm


def test_choices_on_the_estimation_record_only(emps: dict[str, Any]) -> None:
    rep = emps["report"]
    assert rep["estimation_bags"][0].endswith("emps_estimation")
    assert rep["validation_bags"] == [rep["estimation_bags"][0] + "#holdout"]
    assert rep["test"]["bags"][0].endswith("emps_validation")
    assert "held-out" in rep["selection"]["chosen_on"], rep["selection"]


def test_the_recomputed_figure_agrees_and_the_published_model_is_reproduced(
        emps: dict[str, Any]) -> None:
    bench = emps["bench"]
    assert bench["protocol"]["n_init"] == 20 and bench["protocol"]["n_scored"] == 24821
    assert abs(bench["recomputed_minus_tool_mm"]) < 1e-6, bench["recomputed_minus_tool_mm"]
    idim = next(r for r in bench["rows"] if r["label"].startswith("published IDIM-LS"))
    assert idim["test_rms_mm"] == pytest.approx(8.39, abs=0.05)


def test_the_physical_model_is_not_worse_than_the_linear_reference(
        emps: dict[str, Any]) -> None:
    lr = emps["report"]["linear_reference"]
    assert lr["validation_mean_fit"]["physical"] >= lr["validation_mean_fit"]["linear_reference"]
    assert lr["test_mean_fit"]["physical"] >= lr["test_mean_fit"]["linear_reference"]
    assert lr["flags"] == [] and "Worse than the linear reference" not in emps["md"]
    # the parameters stay physical
    par = emps["report"]["final"]["parameters"]
    assert 80.0 < par["M"] < 110.0 and par["Fc"] > 0.0


def test_the_records_disagreement_is_detected_and_read_as_friction(
        emps: dict[str, Any]) -> None:
    ag = emps["report"]["records_agree"]
    assert ag["disagree"] is True, ag
    need_plus, need_minus = (-x for x in (ag["test_bias"][0] - ag["estimation_bias"][0],
                                           ag["test_bias"][1] - ag["estimation_bias"][1]))
    # more drive in each direction of travel: a higher friction, as the data show
    assert need_plus > 0.3 and need_minus < -0.3, (need_plus, need_minus)
    for q in emps["bench"]["steady_force_difference"]:
        assert q["plus_N"] > 0.4 and q["minus_N"] < -0.4, q
    assert "The test record disagrees" in emps["md"]


def test_the_chosen_structure_describes_the_test_record_when_refitted_on_it(
        emps: dict[str, Any]) -> None:
    """The README's "the structure is not the limit": the tool's chosen terms, refitted on the
    test record by the same protocol (in sample), come under the best known 2.64 mm there, and
    those parameters miss the estimation record by more than the chosen model does: the
    records need different friction levels, whichever one the parameters come from."""
    b = emps["bench"]["test_record_bound"]
    ours = next(r for r in emps["bench"]["rows"] if r["label"].startswith("dvt-identify, "))
    assert b["test_rms_mm"] < 2.64, b
    assert b["test_rms_mm"] < ours["test_rms_mm"], (b, ours)
    assert b["est_rms_mm"] > ours["est_rms_mm"], (b, ours)
    assert set(b["parameters"]) == set(b["tool_parameters"]), b


def test_the_spread_over_parts_of_the_estimation_record_is_measured(
        emps: dict[str, Any]) -> None:
    """examples/emps/README.md's "the figure is fragile": the chosen structure fitted by the
    benchmark's criterion on the whole estimation record, its halves and its quarters (no
    choice on the test record). Refitted on the whole record, where the tool's final fit is
    (the choice made with fits on the first 70 %, :func:`dvt_identify.loop.refit_whole`), the
    benchmark's own criterion lands within 5 % of the tool's test figure (measured 2026-12-06:
    2.49 against 2.44 mm). Each half and quarter is described in sample under a millimetre
    and better than the whole record is by its parameters, the fit on the whole record scores
    on the whole record what it scored in sample (the same protocol on the same samples), and
    the test figures' range is the rows' range. The linear reference fitted on each part alone
    stands beside each row; on the whole record it is the tool's own reference (measured: 4.85
    mm; the physical model better on six of the eight parts)."""
    sp = emps["bench"]["part_fits"]
    names = [r["part"] for r in sp["rows"]]
    assert names == ["first 70 % (where the tool's choice was fitted)",
                     "whole record (the tool's final fit)", "first half", "second half",
                     "quarter 1", "quarter 2", "quarter 3", "quarter 4"], names
    whole = sp["rows"][1]
    ours = next(r for r in emps["bench"]["rows"] if r["label"].startswith("dvt-identify, "))
    assert whole["test_rms_mm"] == pytest.approx(ours["test_rms_mm"], rel=0.05), (whole, ours)
    assert whole["in_sample_rms_mm"] == pytest.approx(whole["est_rms_mm"], rel=1e-9), whole
    for r in sp["rows"][2:]:
        assert r["in_sample_rms_mm"] < 1.0, r
        assert r["in_sample_rms_mm"] < r["est_rms_mm"], r
    t = [r["test_rms_mm"] for r in sp["rows"]]
    assert (sp["test_min_mm"], sp["test_max_mm"]) == (min(t), max(t)), sp
    # the linear reference fitted on the same parts (the tool's order); on the whole record it
    # is the tool's own reference (the same fit on the same samples)
    lin = [r["linear_test_rms_mm"] for r in sp["rows"]]
    ref = next(r for r in emps["bench"]["rows"] if "linear reference" in r["label"])
    assert lin[1] == pytest.approx(ref["test_rms_mm"], rel=1e-3), (lin[1], ref)
    assert sorted(sp["linear_better_on"] + sp["physical_better_on"]) == sorted(names)


def test_the_report_prints_the_test_figure_s_spread_beside_it(emps: dict[str, Any]) -> None:
    """The tool's own spread (dvt_identify.spread), printed right after the test figure: the
    final model refitted on each half of its estimation data (the whole record), scored like
    the test figure. Its final row is the test figure itself; on these records each half's
    refit scores worse on the test record than the whole fit (measured 2026-12-06: 4.06 and
    15.90 mm against 2.44). The linear reference, refined on the same halves and scored like
    its own test figure, spreads wider (6.55 and 16.53 mm against 4.85): the
    fragility is the records', and the physical model's largest figure is the smaller one
    (docs: dvt_identify.spread, examples/emps/README.md)."""
    second = emps["stdout"].splitlines()[1]
    assert second.startswith("test, the final model refitted on each half of its estimation "
                             "data: position RMSE "), emps["stdout"]
    sp = emps["report"]["test_spread"]
    tool = emps["report"]["test"]["final"]["rmse"]["position"]
    assert sp["final"]["rmse"]["position"] == pytest.approx(tool, rel=1e-12), sp
    halves = [p["rmse"]["position"] for p in sp["parts"]]
    assert [p["part"] for p in sp["parts"]] == ["first half", "second half"], sp
    assert min(halves) > tool, (halves, tool)
    assert sp["rmse_range"]["position"] == [tool, max(halves)], sp
    assert sp["statement"] in emps["md"]
    ref = emps["report"]["test"]["linear_reference"]["rmse"]["position"]
    assert sp["reference"]["rmse"]["position"] == pytest.approx(ref, rel=1e-12), sp
    rhalves = [p["rmse"]["position"] for p in sp["reference_parts"]]
    assert min(rhalves) > ref, (rhalves, ref)
    assert max(halves) < max(rhalves), (halves, rhalves)
    assert "(linear reference likewise: " in second, second
