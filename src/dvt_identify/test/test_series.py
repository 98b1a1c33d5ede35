"""The series files reproduce the report's figures exactly (NPZ, CSV and the MCAP bags)."""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dvt_identify.bagload import load_bag_segments
from dvt_identify.data import Checks, Segment, SignalSpec
from dvt_identify.description import Description
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.metrics import figures
from dvt_identify.report import build_report, write_report
from dvt_identify.series import (
    collect,
    evaluate_test,
    figures_from_series,
    holdout_split,
    series_keys,
    write_series,
)

SCALE = 2.0  # the speed's scale in the description here (the MCAP series undo and redo it)


@pytest.fixture(scope="module")
def result(cart_desc: Callable[..., Description], cart_record: Callable[..., Segment]
           ) -> tuple[IdentificationResult, list[Segment]]:
    desc = cart_desc(SCALE)
    est = [cart_record(desc, "est", 1, offset=0.3)]
    val = [cart_record(desc, "val", 2, offset=0.3)]
    test = [cart_record(desc, "test", 3, offset=0.3),
            cart_record(desc, "test2", 4, 800, offset=0.3)]
    res = identify(est, val, desc, LoopConfig(starts=1, refit_starts=1, drift_windows=0))
    res.test = evaluate_test(res.baseline.fit, res.final.fit, test, init_window=20)
    return res, test


def test_the_loop_found_the_offset(result: tuple[IdentificationResult, list[Segment]]) -> None:
    res, _ = result
    assert [d.score.label for d in res.accepted] == ["sensor_offset@v"]
    assert res.final.parameters()["sensor_offset"] == pytest.approx(0.3, abs=0.01)


def test_npz_reproduces_the_report_exactly(tmp_path: Path,
                                           result: tuple[IdentificationResult, list[Segment]]
                                           ) -> None:
    res, test = result
    paths = write_series(collect(res, res.test, test), tmp_path)
    write_report(res, tmp_path, plots_enabled=False)
    rep = json.loads((tmp_path / "report.json").read_text())  # the figures as written
    assert rep == json.loads(json.dumps(build_report(res)))
    npz = paths["npz"]
    k_b, k_f = res.baseline.fit.n_estimated_, res.final.fit.n_estimated_
    pairs = [("validation", "baseline", k_b, rep["baseline"]["validation"]),
             ("validation", "final", k_f, rep["final"]["validation"]),
             ("estimation", "baseline", k_b, rep["baseline"]["estimation"]),
             ("estimation", "final", k_f, rep["final"]["estimation"]),
             ("test", "baseline", k_b, rep["test"]["baseline"]),
             ("test", "final", k_f, rep["test"]["final"])]
    for role, model, k, fig in pairs:
        got = figures_from_series(npz, role, model, k)
        # the same numbers, bit for bit
        assert got.fit_percent[0] == fig["fit_percent"]["v"], (role, model)
        assert got.rmse[0] == fig["rmse"]["v"], (role, model)
        assert got.loss == fig["loss"], (role, model)
    with np.load(npz) as z:
        keys = series_keys("test", 1)
        assert z[keys["t"]].shape == (800,)
        assert np.array_equal(z[keys["residual_final"]], z[keys["y"]] - z[keys["final"]])
        assert int(z["test/1/scored_from"][0]) == 20
        assert list(z["segments"]) == ["estimation:0:est", "validation:0:val",
                                       "test:0:test", "test:1:test2"]


def test_csv_reproduces_the_report_exactly(tmp_path: Path,
                                           result: tuple[IdentificationResult, list[Segment]]
                                           ) -> None:
    res, test = result
    paths = write_series(collect(res, res.test, test), tmp_path)
    with paths["csv:validation-0"].open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t", "force", "v", "v_baseline", "v_final", "v_residual_final"]
    data = np.array([[float(x) for x in r] for r in rows[1:]])
    fig = figures([data[:, 2:3]], [data[:, 4:5]], res.final.fit.n_estimated_, ["v"])
    assert fig.fit_percent == res.final.val.fit_percent
    assert fig.rmse == res.final.val.rmse


def test_mcap_bags_carry_the_model_topics(tmp_path: Path,
                                          result: tuple[IdentificationResult, list[Segment]],
                                          cart_desc: Callable[..., Description]) -> None:
    from dvt_model.contract import MODEL_JOINT_STATES, MODEL_RESIDUAL

    res, test = result
    desc = cart_desc(SCALE)
    paths = write_series(collect(res, res.test, test), tmp_path, desc, mcap=True)
    bag = paths["mcap:validation-0"]
    ins = desc.inputs
    meas = load_bag_segments(bag, ins, desc.outputs, Checks())
    sim = load_bag_segments(bag, ins, (SignalSpec("v", MODEL_JOINT_STATES, "velocity",
                                                  "cart"),), Checks())
    res_ = load_bag_segments(bag, ins, (SignalSpec("v", MODEL_RESIDUAL, "velocity", "cart"),),
                             Checks())
    val = res.val_segments[0]
    assert np.allclose(meas[0].y, val.y, rtol=0, atol=1e-12)  # scale 2 undone and redone
    assert np.array_equal(sim[0].y, res.final.val_pred[0])
    assert np.array_equal(res_[0].y, val.y - res.final.val_pred[0])


def test_holdout_split_and_init_window(cart_desc: Callable[..., Description],
                                      cart_record: Callable[..., Segment]) -> None:
    desc = cart_desc(SCALE)
    seg = cart_record(desc, "est", 1, n=1000)
    fit, sel = holdout_split([seg], 0.3)
    assert fit[0].n == 700 and sel[0].n == 300 and sel[0].name == "est#holdout"
    assert np.array_equal(np.concatenate([fit[0].y, sel[0].y]), seg.y)
    assert sel[0].t[0] == 0.0
    with pytest.raises(Exception, match="too few to hold out"):
        holdout_split([cart_record(desc, "s", 1, n=100)], 0.3)
