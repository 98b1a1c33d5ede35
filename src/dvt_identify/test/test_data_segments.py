"""A lossy recording is split at long gaps into segments; short pieces are dropped with a warning.

Bags are written to tmp_path with real rosbag2/MCAP; the split segments are fitted jointly, each
with its own initial state.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import signal

from dvt_identify.cli import load_segments
from dvt_identify.data import (
    Checks,
    DataWarning,
    JointStateSeries,
    SignalSpec,
    load_bag_segments,
    load_segment,
    make_segment,
    split_at_gaps,
    write_jointstate_bag,
)
from dvt_identify.description import load_description
from dvt_identify.errors import DataError
from dvt_identify.oe import MechanicalStructure, OEFit, OEModel

IN = [SignalSpec("force", "/toy/drive", "effort", "slide")]
OUT = [SignalSpec("slide", "/toy/joint_states", "velocity", "slide")]
DT = 0.002
M_TRUE, FV_TRUE = 2.0, 5.0


def _structure() -> MechanicalStructure:
    return MechanicalStructure(["slide"], ["force"], [["M"]], [["Fv"]], [[1.0]],
                               {"M": 1.0, "Fv": 1.0})


def _record(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps_ns, force, speed) of one continuous, lossless recording of n samples."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    sos = signal.butter(2, 5.0, fs=1 / DT, output="sos")
    f = 10 * np.sin(2 * np.pi * 0.9 * t) + 30 * signal.sosfilt(sos, rng.normal(size=n))
    seg = make_segment("truth", t, f, np.zeros(n), ["force"], ["slide"])
    y = OEModel(_structure()).simulate(np.array([M_TRUE, FV_TRUE]), seg, np.array([1.0]))[:, 0]
    stamps = (3 * 10**9 + np.round(t * 1e9)).astype(np.int64)
    return stamps, f, y


def _bag(tmp_path: Path, keep: np.ndarray, n: int, name: str = "bag") -> tuple[Path, np.ndarray]:
    """Bag of the samples ``keep`` (boolean, length n) on both topics; returns (bag, speed)."""
    stamps, f, y = _record(n)
    bag = write_jointstate_bag(tmp_path / name, {
        "/toy/joint_states": JointStateSeries(stamps[keep], ("slide",), velocity=y[keep, None]),
        "/toy/drive": JointStateSeries(stamps[keep], ("slide",), effort=f[keep, None]),
    })
    return bag, y


def _toy_description(tmp_path: Path, **extra: object) -> Path:
    """Description file of the toy slide (force in, speed out, M and Fv free)."""
    desc_file = tmp_path / "toy.yaml"
    desc_file.write_text(yaml.safe_dump({
        "name": "toy",
        "inputs": [{"name": "force", "topic": "/toy/drive", "field": "effort",
                    "joint": "slide"}],
        "outputs": [{"name": "slide", "topic": "/toy/joint_states", "field": "velocity",
                     "joint": "slide"}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]],
                      "parameters": {"M": {"initial": 1.0}, "Fv": {"initial": 1.0}}},
        "checks": {"min_samples": 500},
        **extra,
    }))
    return desc_file


def test_split_at_gaps() -> None:
    t = np.array([0.0, 1, 2, 4, 5, 10, 11, 30]) * DT  # gaps of 1, 4 and 18 missing samples
    pieces, gaps = split_at_gaps(t, DT, 3)
    assert pieces == [(0, 5), (5, 7), (7, 8)]
    assert [g.missing for g in gaps] == [4, 18]
    assert str(gaps[0]) == f"{5 * DT:.6g} s (4 missing samples) after t = {5 * DT:.6f} s"
    assert split_at_gaps(t[:5], DT, 3) == ([(0, 5)], [])


def test_long_gap_gives_two_segments_both_fitted(tmp_path: Path) -> None:
    n = 3000
    keep = np.ones(n, bool)
    keep[1200:1500] = False  # 300 lost samples (0.6 s), e.g. a recorder stall
    keep[[100, 101, 2000]] = False  # short gaps: filled
    bag, y = _bag(tmp_path, keep, n)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # nothing is dropped
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    assert [s.name for s in segs] == [f"{bag}#1", f"{bag}#2"]
    assert [s.n for s in segs] == [1200, 1500]
    assert all(s.t[0] == 0.0 and s.dt == pytest.approx(DT) for s in segs)
    filled = y.copy()
    filled[2000] = (y[1999] + y[2001]) / 2  # a short gap is interpolated
    np.testing.assert_allclose(segs[1].y[:, 0], filled[1500:], atol=1e-12)
    assert "piece 2 of 2" in segs[1].notes[0] and "t = 3.000000 .. 5.998000 s" in segs[1].notes[0]
    assert "2 missing samples filled" in segs[0].notes[1]
    assert "1 missing samples filled" in segs[1].notes[1]
    fit = OEFit(OEModel(_structure()), starts=1).fit(segs)
    assert fit.theta_ == pytest.approx([M_TRUE, FV_TRUE], rel=1e-3)
    assert len(fit.x0_) == 2  # one initial state per segment
    assert fit.x0_[0][0] == pytest.approx(y[0], abs=1e-3)
    assert fit.x0_[1][0] == pytest.approx(y[1500], abs=1e-3)
    with pytest.raises(DataError, match=r"split the recording into 2 segments .*bag#1, .*bag#2"):
        load_segment(bag, IN, OUT, Checks(min_samples=500))


@pytest.mark.parametrize("where", ["start", "end"])
def test_short_piece_at_start_or_end_is_dropped_with_warning(tmp_path: Path, where: str) -> None:
    n = 1500
    keep = np.ones(n, bool)
    if where == "start":
        keep[40:140] = False  # 40 samples, then 100 lost
        span, piece, kept_name = "t = 0.000000 .. 0.078000 s", "piece 1 of 2, 40 samples", 2
    else:
        keep[1400:1480] = False  # the last 20 samples after 80 lost
        span, piece, kept_name = "t = 2.960000 .. 2.998000 s", "piece 2 of 2, 20 samples", 1
    bag, _ = _bag(tmp_path, keep, n)
    with pytest.warns(DataWarning) as rec:
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    assert len(rec) == 1
    msg = str(rec[0].message)
    assert msg.startswith(f"{bag}: topic /toy/joint_states: samples at {span} ({piece}")
    assert msg.endswith("dropped: fewer than min_samples = 500")
    assert [s.name for s in segs] == [f"{bag}#{kept_name}"]
    with pytest.warns(DataWarning):
        assert load_segment(bag, IN, OUT, Checks(min_samples=500)).n == segs[0].n


def test_all_pieces_short_is_an_error_naming_bag_and_gaps(tmp_path: Path) -> None:
    n = 1000
    keep = np.ones(n, bool)
    keep[300:350] = False
    keep[650:700] = False
    bag, _ = _bag(tmp_path, keep, n)
    with pytest.raises(DataError) as err, warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always", DataWarning)
        load_bag_segments(bag, IN, OUT, Checks(min_samples=400))
    assert len(rec) == 3
    assert str(err.value) == (
        f"{bag}: topic /toy/joint_states: no piece of at least 400 samples between the 2 gap(s) "
        "of more than 3 missing samples: 0.102 s (50 missing samples) after t = 0.598000 s; "
        "0.102 s (50 missing samples) after t = 1.298000 s (pieces of 300, 300, 300 samples)")


def test_cli_load_segments_keeps_every_segment(tmp_path: Path) -> None:
    n = 2400
    keep = np.ones(n, bool)
    keep[1000:1100] = False
    bag, _ = _bag(tmp_path, keep, n)
    other, _ = _bag(tmp_path, np.ones(n, bool), n, name="other")
    desc_file = _toy_description(tmp_path, preprocess={"decimate": 2})
    segs = load_segments([bag, other], load_description(str(desc_file)))
    assert [s.name for s in segs] == [f"{bag}#1", f"{bag}#2", str(other)]
    assert [s.n for s in segs] == [500, 650, 1200]
    assert all(s.dt == pytest.approx(2 * DT) for s in segs)


def test_cli_runs_on_a_split_bag_and_reports_the_dropped_piece(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """dvt-identify end to end on a lossy estimation bag: two long pieces fitted, a short one
    dropped with a one-line warning on stderr (shown with --quiet too), the report written
    (``--no-plots``: report.json and report.md, no PNG)."""
    from dvt_identify.cli import main

    n = 3000
    keep = np.ones(n, bool)
    keep[1200:1300] = False  # long gap: split
    keep[2960:2980] = False  # leaves a 20-sample piece at the end: dropped
    bag, _ = _bag(tmp_path, keep, n)
    val, _ = _bag(tmp_path, np.ones(n, bool), n, name="val")
    desc_file = _toy_description(tmp_path)
    rc = main([str(bag), "--validate", str(val), "--out", str(tmp_path / "out"),
               "--description", str(desc_file), "--no-augment", "--quiet", "--no-plots"])
    assert rc == 0
    err = capsys.readouterr().err
    warn = [line for line in err.splitlines() if line.startswith("[dvt-identify] warning:")]
    assert len(warn) == 1 and "20 samples" in warn[0] and str(bag) in warn[0]
    report = (tmp_path / "out" / "report.json").read_text()
    assert f"{bag}#1" in report and f"{bag}#2" in report
    assert (tmp_path / "out" / "report.md").is_file()
    assert not list((tmp_path / "out").glob("*.png"))  # --no-plots
