"""Selection and test kept apart: the test bags are read only after every choice is made."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
