"""Selection and test kept apart: the test bags are read only after every choice is made."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify import pipeline
from dvt_identify.cli import main
from dvt_identify.description import parse_description
from dvt_identify.errors import DataError


@pytest.fixture
def traced(traced_pipeline: tuple[list[str], dict[str, float], Path]) -> tuple[list[str], Path]:
    """The cart's description file, and ``pipeline`` with reads and ``identify`` traced in
    order; the bags ``est``, ``val`` and ``test`` are read with a speed offset of 0.3 m/s."""
    events, offsets, path = traced_pipeline
    offsets.update(est=0.3, val=0.3, test=0.3)
    return events, path


def test_test_bags_are_read_after_every_choice(traced: tuple[list[str], Path], tmp_path: Path
                                               ) -> None:
    events, desc = traced
    res = pipeline.run([tmp_path / "est"], [tmp_path / "val"], tmp_path / "out", str(desc),
                       quiet=True, plots=False, test_bags=[tmp_path / "test"])
    assert events.index("read test") > events.index("choices made")
    assert events[events.index("choices made") - 1] == "identify: est | val"
    assert res.test is not None and res.test.bags == ["test"]
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["selection"]["chosen_on"] == "the validation bags"
    assert "selection figures" in rep["selection"]["validation_figures"]
    assert rep["test"]["bags"] == ["test"] and "no part" in rep["test"]["role"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "## Test (took no part in any choice)" in md


def test_holdout_selection_makes_the_validation_bags_test_data(
        traced: tuple[list[str], Path], tmp_path: Path) -> None:
    events, desc = traced
    res = pipeline.run([tmp_path / "est"], [tmp_path / "val"], tmp_path / "out", str(desc),
                       quiet=True, plots=False, select_on="holdout")
    # identify saw only estimation data: its fit part and its held-out end
    assert "identify: est | est#holdout" in events
    assert events.index("read val") > events.index("choices made")
    assert res.selection == "holdout" and res.test is not None and res.test.bags == ["val"]


def test_holdout_refits_the_chosen_model_on_the_whole_estimation_record(
        traced: tuple[list[str], Path], tmp_path: Path) -> None:
    """After the choice on the held-out end, the baseline and the final model are refitted on
    the whole estimation record: their parameters are the refit's (on 1.43 times the data:
    the final model's std smaller), their selection figures still the held-out end simulated
    by the fit on the first part, and the report says so."""
    _, desc = traced
    res = pipeline.run([tmp_path / "est"], [tmp_path / "val"], tmp_path / "out", str(desc),
                       quiet=True, plots=False, select_on="holdout")
    assert res.whole and [s.name for s in res.est_segments] == ["est"]
    assert [s.name for s in res.records()] == ["est"]
    for stage in (res.baseline, res.final):
        (first,) = stage.folds
        span = [sum(s.n * s.dt for s in f.segments_) for f in (first, stage.fit)]
        assert span[1] == pytest.approx(span[0] / 0.7, rel=0.01), span
        held = res.val_segments[0]
        np.testing.assert_allclose(
            stage.val_pred[0], first.model.simulate(first.theta_, held, first.estimate_x0(held)))
    # the final model (the sensor offset accepted) on 1.43 times the data: a smaller std for
    # each parameter (measured: 0.0053 -> 0.0030, 0.0076 -> 0.0036, 0.00046 -> 0.00031); the
    # baseline misses the offset, and its std need not shrink (measured: it grew)
    assert [d.score.label for d in res.accepted] == ["sensor_offset@v"]
    (first,) = res.final.folds
    std_first, std_whole = first.parameter_std(), res.final.fit.parameter_std()
    assert all(std_whole[k] < std_first[k] for k in std_first), (std_first, std_whole)
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert any("refitted on the whole estimation segments" in n for n in rep["notes"]), \
        rep["notes"]


def test_cli_test_option_and_refusals(traced: tuple[list[str], Path], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    _, desc = traced
    rc = main([str(tmp_path / "est"), "--validate", str(tmp_path / "val"), "--test",
               str(tmp_path / "test"), "--out", str(tmp_path / "o"), "--description",
               str(desc), "--no-plots", "--quiet", "--init-window", "20"])
    assert rc == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    # the test figures come first: RMSE in the output's unit and fit, the linear reference beside
    assert first.startswith("test (no part in any choice): v RMSE "), out
    assert " m/s (fit " in first and "linear reference RMSE" in first, first
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["test"]["initial_state"].startswith("estimated from the first 20 samples")
    assert (tmp_path / "o" / "series.npz").is_file()
    with pytest.raises(DataError, match="used as test data and for estimation or validation"):
        pipeline.run([tmp_path / "est"], [tmp_path / "val"], tmp_path / "o2", str(desc),
                     quiet=True, plots=False, test_bags=[tmp_path / "val"])
    with pytest.raises(SystemExit):
        main([str(tmp_path / "est"), "--out", str(tmp_path / "o3")])  # no --validate


def test_description_loads(tmp_path: Path, cart_spec: Callable[..., dict[str, Any]]) -> None:
    assert parse_description(cart_spec(), "cart.yaml").output_names == ("v",)


def test_a_term_clocked_on_time_is_warned_across_segments() -> None:
    from types import SimpleNamespace

    from dvt_identify.effects import make_effect
    from dvt_identify.report import time_clock_warnings

    eff = make_effect("periodic_disturbance", "v", ("v",), ("force",), "N", "m/s",
                      options={"orders": [1.5], "clock": "time"})
    res = SimpleNamespace(final=SimpleNamespace(effects=(eff,)), est_segments=[1, 2],
                          estimation_bags=["a", "b"], val_segments=[3])
    (w,) = time_clock_warnings(res)  # type: ignore[arg-type]
    assert "is clocked on time: its phase restarts at t = 0 in each of the 3 segments" in w
    angle = make_effect("periodic_disturbance", "v", ("v",), ("force",), "N", "m/s",
                        options={"orders": [1.0]})
    res.final.effects = (angle,)
    assert time_clock_warnings(res) == []  # type: ignore[arg-type]
