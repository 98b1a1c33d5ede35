"""Selection and test kept apart: the test bags are read only after every choice is made."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from dvt_identify import pipeline
from dvt_identify.cli import main
from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.errors import DataError
from dvt_identify.simulation import OEModel

SEEDS = {"est": 1, "val": 2, "test": 3}
DESC = {
    "name": "cart",
    "inputs": [{"name": "force", "topic": "/cart/drive", "field": "effort", "joint": "cart"}],
    "outputs": [{"name": "v", "topic": "/cart/joint_states", "field": "velocity",
                 "joint": "cart"}],
    "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                  "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                  "parameters": {"M": {"initial": 2.0, "lower": 0.01},
                                 "Fv": {"initial": 3.0, "lower": 0.0}}},
    "candidates": [{"effect": "sensor_offset", "where": "v"}],
    "preprocess": {"fit_decimate": 1},
    "fit": {"starts": 1, "refit_starts": 1},
}


def record(desc: Description, name: str, seed: int, n: int = 1500, offset: float = 0.0
           ) -> Segment:
    """A cart ``M v' = F - Fv v`` (M 2.5, Fv 4) under random force steps, 1 % noise."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-5, 5, n // 50 + 1), 50)[:n]
    t = np.arange(n) * 0.01
    clean = make_segment(name, t, u, np.zeros(n), desc.input_names, desc.output_names)
    y = OEModel(desc.structure).simulate(np.array([2.5, 4.0]), clean, np.zeros(1))
    y = y + offset + 0.01 * rng.standard_normal(y.shape)
    return make_segment(name, t, u, y, desc.input_names, desc.output_names)


@pytest.fixture
def traced(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> tuple[list[str], Path]:
    """A description file, and ``pipeline`` with reads and ``identify`` traced in order."""
    events: list[str] = []
    path = tmp_path / "cart.yaml"
    path.write_text(yaml.safe_dump(DESC))

    def load(bags: Sequence[str | Path], desc: Description) -> list[Any]:
        out = []
        for b in bags:
            name = Path(b).name
            events.append(f"read {name}")
            out.append(record(desc, name, SEEDS[name], offset=0.3))
        return out

    real = pipeline.identify

    def identify(est: Sequence[Any], val: Sequence[Any], *a: Any, **k: Any) -> Any:
        events.append("identify: " + ",".join(s.name for s in est) + " | "
                      + ",".join(s.name for s in val))
        res = real(est, val, *a, **k)
        events.append("choices made")
        return res

    monkeypatch.setattr(pipeline, "load_segments", load)
    monkeypatch.setattr(pipeline, "identify", identify)
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
    assert "test fit (no part in any choice): v " in out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["test"]["initial_state"].startswith("estimated from the first 20 samples")
    assert (tmp_path / "o" / "series.npz").is_file()
    with pytest.raises(DataError, match="used as test data and for estimation or validation"):
        pipeline.run([tmp_path / "est"], [tmp_path / "val"], tmp_path / "o2", str(desc),
                     quiet=True, plots=False, test_bags=[tmp_path / "val"])
    with pytest.raises(SystemExit):
        main([str(tmp_path / "est"), "--out", str(tmp_path / "o3")])  # no --validate


def test_description_loads(tmp_path: Path) -> None:
    assert parse_description(DESC, "cart.yaml").output_names == ("v",)


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
