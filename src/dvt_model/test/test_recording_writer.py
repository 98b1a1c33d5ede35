"""Unit tests of the one writer (crash-safe ``BagRecorder``), ``recover`` and ``bag_summary``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from dvt_model import recording
from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATES, SPEED_NAMES
from dvt_model.errors import BagError, RecordingError
from dvt_model.recording import BagRecorder, joint_state_cdr, recover, typestore

JS = "sensor_msgs/msg/JointState"
TOPICS = {JOINT_STATES: JS, CURRENTS: JS}
T0 = 1_700_000_000_000_000_000


class FakeClock:
    """Monotonic clock under test control [s]."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _sample(rec: BagRecorder, i: int) -> None:
    st = T0 + i * 1_000_000
    rec.write(JOINT_STATES,
              joint_state_cdr(st, SPEED_NAMES, velocity=[float(i), -float(i)]), st)
    rec.write(CURRENTS,
              joint_state_cdr(st, CURRENT_NAMES, effort=[i, 1.0, 2.0, 3.0]), st)


def _record(path: Path, n: int, **kw: object) -> BagRecorder:
    rec = BagRecorder(path, TOPICS, fsync=False, **kw)  # type: ignore[arg-type]
    for i in range(n):
        _sample(rec, i)
    return rec


def _salvageable(mcap: Path) -> int:
    """Messages that mcap's non-seeking reader gets out of a (possibly unfinished) file."""
    n = 0
    with mcap.open("rb") as fh:
        try:
            for _ in NonSeekingReader(fh, validate_crcs=False).iter_messages(
                    log_time_order=False):
                n += 1
        except Exception:
            pass
    return n


def test_round_trip_readable_by_rosbags_mcap_and_recording(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with _record(path, 300) as rec:
        rec.add_topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        rec.add_topic(JOINT_STATES, JS)  # again, same type: no-op
    assert rec.closed
    assert rec.stats == {JOINT_STATES: 300, CURRENTS: 300, "/diagnostics": 0}
    # rosbags
    with Reader(path) as reader:
        assert reader.message_count == 600
        conns = {c.topic: c for c in reader.connections}
        assert conns[JOINT_STATES].msgtype == JS
        assert conns[JOINT_STATES].msgcount == 300
        assert conns["/diagnostics"].msgcount == 0
        assert sum(1 for _ in reader.messages()) == 600
    # mcap with its summary, and decoded with mcap_ros2
    with (path / "bag.mcap").open("rb") as fh:
        reader2 = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader2.get_header().profile == "ros2"
        summary = reader2.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 600
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        decoded = [m for _, _, _, m in reader2.iter_decoded_messages(topics=[CURRENTS])]
    assert decoded[7].effort[0] == 7.0
    # contract reader
    run = recording.read_run(path)
    assert run.n == 300 and run.unmatched == 0
    np.testing.assert_array_equal(run.speeds[:, 0], np.arange(300))


def test_zstd_compression(tmp_path: Path) -> None:
    with _record(tmp_path / "bag", 50, compression="zstd"):
        pass
    assert recording.read_run(tmp_path / "bag").n == 50


def test_flush_makes_messages_durable_before_close(tmp_path: Path) -> None:
    clock = FakeClock()
    path = tmp_path / "bag"
    rec = BagRecorder(path, TOPICS, flush_period=0.5, fsync=False, clock=clock)
    mcap = path / "bag.mcap"
    for i in range(10):
        _sample(rec, i)
    assert _salvageable(mcap) == 0  # still in the open chunk
    assert not rec.poll()  # not due yet
    clock.now = 0.6
    assert rec.poll()
    assert _salvageable(mcap) == 20
    _sample(rec, 10)  # due only 0.5 s after the last flush
    assert _salvageable(mcap) == 20
    clock.now = 1.2
    _sample(rec, 11)  # the joint_states write flushes (due); the currents one waits
    assert _salvageable(mcap) == 23
    rec.close()


def test_flush_period_zero_flushes_every_message(tmp_path: Path) -> None:
    rec = _record(tmp_path / "bag", 3, flush_period=0.0)
    assert _salvageable(tmp_path / "bag" / "bag.mcap") == 6
    rec.close()


def test_recover_truncated_at_any_offset_gives_a_prefix(tmp_path: Path) -> None:
    src = tmp_path / "src"
    rec = _record(src, 40, flush_period=0.0)  # one chunk per message
    rec.flush()
    data = (src / "src.mcap").read_bytes()  # unfinished file, as after a SIGKILL
    rec.close()
    previous = -1
    for k, cut in enumerate(np.linspace(30, len(data), 12).astype(int)):
        bag = tmp_path / f"cut{k}"
        bag.mkdir()
        (bag / "cut.mcap").write_bytes(data[:cut])
        result = recover(bag)
        assert result.moved == [bag / "cut.mcap.broken"]
        assert (bag / "metadata.yaml").exists()
        if cut < len(data):
            assert "truncated" in result.stopped
        total = result.total
        assert total >= previous
        previous = total
        if total >= 2:
            run = recording.read_run(bag)
            # the recovered samples are exactly the first ones written
            np.testing.assert_array_equal(run.speeds[:, 0], np.arange(run.n))
    assert previous == 80


def test_recover_in_place_and_out(tmp_path: Path) -> None:
    src = tmp_path / "run"
    rec = _record(src, 99, flush_period=0.0)
    st = T0 + 99 * 1_000_000
    rec.write(JOINT_STATES, joint_state_cdr(st, SPEED_NAMES, velocity=[99, 0]), st)
    size = (src / "run.mcap").stat().st_size
    rec.write(CURRENTS, joint_state_cdr(st, CURRENT_NAMES, effort=[0, 0, 0, 0]), st)
    (src / "truth.yaml").write_text("effects: [windage]\n")
    os.truncate(src / "run.mcap", size + 40)  # the last chunk is cut
    with pytest.raises(BagError, match="dvt-bag recover"):
        recording.read_run(src)

    out = recover(src, tmp_path / "fixed")
    assert out.counts == {JOINT_STATES: 100, CURRENTS: 99}
    assert (tmp_path / "fixed" / "truth.yaml").exists()
    assert recording.read_run(tmp_path / "fixed").unmatched == 1
    assert (src / "run.mcap").exists()  # untouched

    with pytest.raises(RecordingError, match="exists already"):
        recover(src, tmp_path / "fixed")

    res = recover(src)
    assert res.counts == out.counts
    assert (src / "run.mcap.broken").exists()
    assert recording.read_run(src).n == 99
    again = recover(src)
    assert again.already_readable
    del rec


def test_recover_rosbags_writer_that_was_aborted(tmp_path: Path) -> None:
    """A bag from rosbags' own Writer that died: complete 1 MiB chunks are recovered."""
    path = tmp_path / "rb"
    ts = typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection(JOINT_STATES, JS, typestore=ts)
    raw = joint_state_cdr(T0, SPEED_NAMES, velocity=[1.0, 2.0])
    for i in range(20000):
        writer.write(conn, T0 + i, raw)
    writer.abort()  # no summary, no metadata.yaml, last chunk lost
    result = recover(path)
    n = result.counts[JOINT_STATES]
    assert 0 < n < 20000
    series = recording.read_topic_series(path, JOINT_STATES)
    assert series.stamps_ns.shape == (n,)


def test_recover_bad_input(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        recover(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no .mcap file"):
        recover(tmp_path / "empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        recover(tmp_path / "junk")
    assert (tmp_path / "junk" / "x.mcap").exists()


def test_recover_header_only(tmp_path: Path) -> None:
    rec = BagRecorder(tmp_path / "b", TOPICS, fsync=False)
    del rec  # killed before the first flush: only the MCAP header is on disk
    result = recover(tmp_path / "b")
    assert result.total == 0
    with Reader(tmp_path / "b") as reader:
        assert reader.message_count == 0


def test_recorder_errors(tmp_path: Path) -> None:
    rec = BagRecorder(tmp_path / "b", TOPICS, fsync=False)
    with pytest.raises(RecordingError, match="topic /x was not added"):
        rec.write("/x", b"", 0)
    with pytest.raises(RecordingError, match="cannot add it again as std_msgs/msg/String"):
        rec.add_topic(JOINT_STATES, "std_msgs/msg/String")
    with pytest.raises(RecordingError, match="not a known ROS 2 Jazzy message"):
        rec.add_topic("/y", "my_msgs/msg/Thing")
    rec.close()
    assert rec.close() == rec.stats  # idempotent
    with pytest.raises(RecordingError, match="recorder is closed"):
        rec.write(JOINT_STATES, b"", 0)
    with pytest.raises(RecordingError, match="exists already"):
        BagRecorder(tmp_path / "b", TOPICS)
    with pytest.raises(RecordingError, match="compression"):
        BagRecorder(tmp_path / "c", TOPICS, compression="lz5")
