"""A lossy recording is split at long gaps into segments; short pieces are dropped with a warning.

What is sound is salvaged: a non-finite sample or a stamp that goes backwards or repeats splits
the recording with a warning, a killed recording (truncated MCAP) is read up to its last
complete chunk with a warning. Bags are written to tmp_path with real rosbag2/MCAP; the split
segments are fitted jointly, each with its own initial state.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from scipy import signal

from dvt_identify.bagload import load_bag_segments, load_segment, split_at_gaps
from dvt_identify.data import (
    Checks,
    DataWarning,
    JointStateSeries,
    SignalSpec,
    make_segment,
    write_jointstate_bag,
)
from dvt_identify.description import load_description
from dvt_identify.errors import DataError
from dvt_identify.fit import OEFit
from dvt_identify.pipeline import load_segments
from dvt_identify.simulation import OEModel
from dvt_identify.structures import MechanicalStructure
from dvt_model.recording import BagRecorder, joint_state_cdr

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


def _recorded(path: Path, stamps: np.ndarray, f: np.ndarray, y: np.ndarray,
              log_times: np.ndarray | None = None, chunk_size: int = 1 << 20) -> Path:
    """A bag as the recorder writes it: per sample both topics, log time = ``log_times``
    (default: the stamps), chunks closed by size; closed properly (metadata.yaml)."""
    logs = stamps if log_times is None else log_times
    js = "sensor_msgs/msg/JointState"
    with BagRecorder(path, {"/toy/joint_states": js, "/toy/drive": js}, fsync=False,
                     flush_period=math.inf, chunk_size=chunk_size) as rec:
        for st, lt, fi, yi in zip(stamps.tolist(), logs.tolist(), f.tolist(), y.tolist(),
                                  strict=True):
            rec.write("/toy/joint_states", joint_state_cdr(st, ["slide"], velocity=[yi]), lt)
            rec.write("/toy/drive", joint_state_cdr(st, ["slide"], effort=[fi]), lt)
    return path


def _warned(rec: Iterable[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in rec if issubclass(w.category, DataWarning)]


def test_non_finite_sample_splits_the_recording_with_a_warning(tmp_path: Path) -> None:
    n = 3000
    stamps, f, y = _record(n)
    y_bad = y.copy()
    y_bad[1500] = np.nan  # one bad speed sample in the middle
    bag = _recorded(tmp_path / "bag", stamps, f, y_bad)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    msgs = _warned(rec)
    assert msgs == [f"{bag}: topic /toy/joint_states: velocity[slide] (slide) is nan at "
                    f"t = 3.000000 s (stamp {stamps[1500]} ns, message 1500): 1 sample with a "
                    "non-finite value dropped, the recording is split there"]
    assert [s.name for s in segs] == [f"{bag}#1", f"{bag}#2"]
    assert [s.n for s in segs] == [1500, 1499]
    assert "split at non-finite samples" in segs[1].notes[0]
    np.testing.assert_allclose(segs[1].y[:, 0], y[1501:], atol=1e-12)
    fit = OEFit(OEModel(_structure()), starts=1).fit(segs)
    assert fit.theta_ == pytest.approx([M_TRUE, FV_TRUE], rel=1e-3)


def test_non_finite_samples_on_several_signals_are_counted(tmp_path: Path) -> None:
    n = 2000
    stamps, f, y = _record(n)
    f_bad, y_bad = f.copy(), y.copy()
    f_bad[[700, 701, 1050]] = [np.inf, -np.inf, np.nan]
    y_bad[1050] = np.inf
    bag = _recorded(tmp_path / "bag", stamps, f_bad, y_bad)
    with pytest.warns(DataWarning) as rec:
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=400))
    msgs = _warned(rec)
    assert len(msgs) == 3  # one per signal, one for the dropped piece
    assert msgs[0].startswith(f"{bag}: topic /toy/joint_states: velocity[slide] (slide) is inf "
                              "at t = 2.100000 s")
    assert msgs[1].startswith(f"{bag}: topic /toy/drive: effort[slide] (force) is inf at "
                              "t = 1.400000 s")
    assert "and in 2 more samples: 3 samples with a non-finite value dropped" in msgs[1]
    assert "(piece 2 of 3, 348 samples between non-finite samples) dropped" in msgs[2]
    assert [s.n for s in segs] == [700, 949]
    assert [s.name for s in segs] == [f"{bag}#1", f"{bag}#3"]


def test_backwards_stamp_splits_the_recording_with_a_warning(tmp_path: Path) -> None:
    """The controller clock jumps back 0.5 s at sample 1500 (log times go on): two segments."""
    n = 3000
    stamps, f, y = _record(n)
    jumped = stamps.copy()
    jumped[1500:] -= 10**9  # 500 samples back
    bag = _recorded(tmp_path / "bag", jumped, f, y, log_times=stamps)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    msgs = _warned(rec)
    assert len(msgs) == 2  # one per topic
    assert msgs[0] == (f"{bag}: topic /toy/joint_states: header.stamp does not strictly "
                       f"increase at message 1500 (goes backwards: {jumped[1500]} ns after "
                       f"{jumped[1499]} ns, t = 2.998000 s): the recording is split there (a "
                       "stamp that does not increase)")
    assert msgs[1].startswith(f"{bag}: topic /toy/drive: header.stamp does not strictly increase")
    assert [s.name for s in segs] == [f"{bag}#1", f"{bag}#2"]
    assert [s.n for s in segs] == [1500, 1500]
    assert "split at stamps that do not increase" in segs[0].notes[0]
    np.testing.assert_allclose(segs[1].y[:, 0], y[1500:], atol=1e-12)
    fit = OEFit(OEModel(_structure()), starts=1).fit(segs)
    assert fit.theta_ == pytest.approx([M_TRUE, FV_TRUE], rel=1e-3)


def test_repeated_stamp_on_one_topic_splits_without_losing_samples(tmp_path: Path) -> None:
    n = 2000
    stamps, f, y = _record(n)
    # /toy/drive sends sample 999 twice (a duplicate between 999 and 1000)
    drive = np.insert(stamps, 1000, stamps[999])
    force = np.insert(f, 1000, f[999])
    bag = write_jointstate_bag(tmp_path / "bag", {
        "/toy/joint_states": JointStateSeries(stamps, ("slide",), velocity=y[:, None]),
        "/toy/drive": JointStateSeries(drive, ("slide",), effort=force[:, None]),
    })
    with pytest.warns(DataWarning) as rec:
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    msgs = _warned(rec)
    assert msgs == [f"{bag}: topic /toy/drive: header.stamp does not strictly increase at "
                    f"message 1000 (repeats: {stamps[999]} ns after {stamps[999]} ns, "
                    "t = 1.998000 s): the recording is split there (a stamp that does not "
                    "increase)"]
    assert [s.n for s in segs] == [1000, 1000]
    with pytest.raises(DataError, match=r"stamps that do not increase split the recording into "
                                        r"2 segments"), warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        load_segment(bag, IN, OUT, Checks(min_samples=500))


def test_nothing_usable_left_is_an_error_naming_the_problems(tmp_path: Path) -> None:
    n = 1000
    stamps, f, y = _record(n)
    y_bad = y.copy()
    y_bad[::300] = np.nan  # pieces of 299 samples
    bag = _recorded(tmp_path / "bag", stamps, f, y_bad)
    with pytest.raises(DataError) as err, warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        load_bag_segments(bag, IN, OUT, Checks(min_samples=400))
    assert str(err.value) == (
        f"{bag}: topic /toy/joint_states: no piece of at least 400 samples between the splits "
        "of the recording: topic /toy/joint_states: velocity[slide] non-finite in 4 samples "
        f"(first at t = 0.000000 s (stamp {stamps[0]} ns, message 0)) (pieces of 299, 299, "
        "299, 99 samples)")


def test_truncated_recording_is_read_to_its_last_complete_chunk(tmp_path: Path) -> None:
    """A recording whose writer was killed mid-chunk (bytes chopped off the .mcap file): the
    identifier reads the complete chunks with a warning and fits them."""
    n = 3000
    stamps, f, y = _record(n)
    bag = _recorded(tmp_path / "bag", stamps, f, y, chunk_size=64 * 1024)
    mcap = bag / "bag.mcap"
    with mcap.open("rb") as fh:  # messages per topic in all chunks but the last (mcap's reader)
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and len(summary.chunk_indexes) >= 3
        last = summary.chunk_indexes[-1]
        topic_of = {c.id: c.topic for c in summary.channels.values()}
        kept = dict.fromkeys(("/toy/joint_states", "/toy/drive"), 0)
        for chunk in summary.chunk_indexes[:-1]:
            fh.seek(chunk.chunk_start_offset)
            record = next(iter(StreamReader(fh, skip_magic=True, emit_chunks=True).records))
            assert isinstance(record, Chunk)
            for rec in breakup_chunk(record):
                if isinstance(rec, Message):
                    kept[topic_of[rec.channel_id]] += 1
    with mcap.open("r+b") as fh:
        fh.truncate(last.chunk_start_offset + last.chunk_length // 2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        segs = load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
    msgs = _warned(caught)
    assert len(msgs) == 1 and msgs[0].startswith(f"{mcap}: the recording was not closed")
    assert (f"{sum(kept.values())} messages kept (/toy/joint_states: "
            f"{kept['/toy/joint_states']}, /toy/drive: {kept['/toy/drive']})") in msgs[0]
    assert f"`dvt-bag recover {bag}` rewrites it" in msgs[0]
    assert [s.name for s in segs] == [str(bag)]
    n_kept = min(kept.values())  # samples with both messages
    assert 2000 < segs[0].n == n_kept < n
    np.testing.assert_allclose(segs[0].y[:, 0], y[:n_kept], atol=1e-12)
    fit = OEFit(OEModel(_structure()), starts=1).fit(segs)
    assert fit.theta_ == pytest.approx([M_TRUE, FV_TRUE], rel=1e-3)


def test_recording_truncated_to_nothing_is_an_error_naming_the_file(tmp_path: Path) -> None:
    stamps, f, y = _record(600)
    bag = _recorded(tmp_path / "bag", stamps, f, y)
    mcap = bag / "bag.mcap"
    data = mcap.read_bytes()
    for size, why in ((0, "not readable: not an MCAP file (empty)"),
                      (5, "not readable: not an MCAP file (5 bytes)"),
                      (30, "nothing readable: no complete message in the recording: bag.mcap: "
                           "truncated record")):
        mcap.write_bytes(data[:size])
        with pytest.raises(DataError) as err:
            load_bag_segments(bag, IN, OUT, Checks(min_samples=500))
        assert str(err.value).startswith(f"{mcap}: {why}")


def test_pipeline_shows_the_salvage_warnings(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The identifier's reading step prints every salvage warning (as the gap warnings)."""
    from dvt_identify.pipeline import _read

    n = 2400
    stamps, f, y = _record(n)
    y_bad = y.copy()
    y_bad[1200] = np.nan
    bag = _recorded(tmp_path / "bag", stamps, f, y_bad, chunk_size=32 * 1024)
    with (bag / "bag.mcap").open("r+b") as fh:
        fh.truncate(fh.seek(0, 2) - 100)
    val, _ = _bag(tmp_path, np.ones(n, bool), n, name="val")
    desc = load_description(str(_toy_description(tmp_path)))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        est, _ = _read([bag], [val], desc)
    assert [s.name for s in est] == [f"{bag}#1", f"{bag}#2"]
    assert not _warned(rec)  # shown on stderr by _read, not passed on
    warn = [line for line in capsys.readouterr().err.splitlines()
            if line.startswith("[dvt-identify] warning:")]
    assert len(warn) == 2
    assert f"{bag / 'bag.mcap'}: the recording was not closed" in warn[0]
    assert "4800 messages kept" in warn[0]
    assert f"{bag}: topic /toy/joint_states: velocity[slide] (slide) is nan at t = 2.400000 s" \
        in warn[1]
