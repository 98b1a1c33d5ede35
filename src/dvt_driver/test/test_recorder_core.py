"""Unit tests of the crash-safe bag recorder, ``recover`` and ``dvt-bag``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from dvt_driver import bagtool
from dvt_driver.recorder_core import (
    BagRecorder,
    RecorderError,
    StopFlag,
    bag_summary,
    choose_qos,
    match_topics,
    recover,
)
from dvt_model import bagio
from dvt_model.bagio import CURRENT_NAMES, CURRENTS_TOPIC, JOINT_STATES_TOPIC, SPEED_NAMES

JS = "sensor_msgs/msg/JointState"
TOPICS = {JOINT_STATES_TOPIC: JS, CURRENTS_TOPIC: JS}
T0 = 1_700_000_000_000_000_000


class FakeClock:
    """Monotonic clock under test control [s]."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _sample(rec: BagRecorder, i: int) -> None:
    st = T0 + i * 1_000_000
    rec.write(JOINT_STATES_TOPIC,
              bagio.joint_state_cdr(st, SPEED_NAMES, velocity=[float(i), -float(i)]), st)
    rec.write(CURRENTS_TOPIC,
              bagio.joint_state_cdr(st, CURRENT_NAMES, effort=[i, 1.0, 2.0, 3.0]), st)


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


def test_round_trip_readable_by_rosbags_mcap_and_bagio(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with _record(path, 300) as rec:
        rec.add_topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        rec.add_topic(JOINT_STATES_TOPIC, JS)  # again, same type: no-op
    assert rec.closed
    assert rec.stats == {JOINT_STATES_TOPIC: 300, CURRENTS_TOPIC: 300, "/diagnostics": 0}
    # rosbags
    with Reader(path) as reader:
        assert reader.message_count == 600
        conns = {c.topic: c for c in reader.connections}
        assert conns[JOINT_STATES_TOPIC].msgtype == JS
        assert conns[JOINT_STATES_TOPIC].msgcount == 300
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
        decoded = [m for _, _, _, m in reader2.iter_decoded_messages(topics=[CURRENTS_TOPIC])]
    assert decoded[7].effort[0] == 7.0
    # contract reader
    run = bagio.read_run(path)
    assert run.n == 300 and run.unmatched == 0
    np.testing.assert_array_equal(run.speeds[:, 0], np.arange(300))


def test_zstd_compression(tmp_path: Path) -> None:
    with _record(tmp_path / "bag", 50, compression="zstd"):
        pass
    assert bagio.read_run(tmp_path / "bag").n == 50


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
            run = bagio.read_run(bag)
            # the recovered samples are exactly the first ones written
            np.testing.assert_array_equal(run.speeds[:, 0], np.arange(run.n))
    assert previous == 80


def test_recover_in_place_and_out(tmp_path: Path) -> None:
    src = tmp_path / "run"
    rec = _record(src, 99, flush_period=0.0)
    st = T0 + 99 * 1_000_000
    rec.write(JOINT_STATES_TOPIC, bagio.joint_state_cdr(st, SPEED_NAMES, velocity=[99, 0]), st)
    size = (src / "run.mcap").stat().st_size
    rec.write(CURRENTS_TOPIC, bagio.joint_state_cdr(st, CURRENT_NAMES, effort=[0, 0, 0, 0]), st)
    (src / "truth.yaml").write_text("effects: [windage]\n")
    os.truncate(src / "run.mcap", size + 40)  # the last chunk is cut
    with pytest.raises(bagio.BagError, match="dvt-bag recover"):
        bagio.read_run(src)

    out = recover(src, tmp_path / "fixed")
    assert out.counts == {JOINT_STATES_TOPIC: 100, CURRENTS_TOPIC: 99}
    assert (tmp_path / "fixed" / "truth.yaml").exists()
    assert bagio.read_run(tmp_path / "fixed").unmatched == 1
    assert (src / "run.mcap").exists()  # untouched

    with pytest.raises(RecorderError, match="exists already"):
        recover(src, tmp_path / "fixed")

    res = recover(src)
    assert res.counts == out.counts
    assert (src / "run.mcap.broken").exists()
    assert bagio.read_run(src).n == 99
    again = recover(src)
    assert again.already_readable
    del rec


def test_recover_rosbags_writer_that_was_aborted(tmp_path: Path) -> None:
    """A bag from rosbags' own Writer that died: complete 1 MiB chunks are recovered."""
    path = tmp_path / "rb"
    ts = bagio.typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection(JOINT_STATES_TOPIC, JS, typestore=ts)
    raw = bagio.joint_state_cdr(T0, SPEED_NAMES, velocity=[1.0, 2.0])
    for i in range(20000):
        writer.write(conn, T0 + i, raw)
    writer.abort()  # no summary, no metadata.yaml, last chunk lost
    result = recover(path)
    n = result.counts[JOINT_STATES_TOPIC]
    assert 0 < n < 20000
    series = bagio.read_topic_series(path, JOINT_STATES_TOPIC)
    assert series.stamps_ns.shape == (n,)


def test_recover_bad_input(tmp_path: Path) -> None:
    with pytest.raises(RecorderError, match="no such file"):
        recover(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecorderError, match="no .mcap file"):
        recover(tmp_path / "empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(RecorderError, match="not an MCAP file"):
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
    with pytest.raises(RecorderError, match="topic /x was not added"):
        rec.write("/x", b"", 0)
    with pytest.raises(RecorderError, match="cannot add it again as std_msgs/msg/String"):
        rec.add_topic(JOINT_STATES_TOPIC, "std_msgs/msg/String")
    with pytest.raises(RecorderError, match="not a known ROS 2 Jazzy message"):
        rec.add_topic("/y", "my_msgs/msg/Thing")
    rec.close()
    assert rec.close() == rec.stats  # idempotent
    with pytest.raises(RecorderError, match="recorder is closed"):
        rec.write(JOINT_STATES_TOPIC, b"", 0)
    with pytest.raises(RecorderError, match="exists already"):
        BagRecorder(tmp_path / "b", TOPICS)
    with pytest.raises(RecorderError, match="compression"):
        BagRecorder(tmp_path / "c", TOPICS, compression="lz5")


def test_match_topics() -> None:
    graph = [("/dvt/joint_states", [JS]), ("/dvt/cmd/motor_current", ["std_msgs/msg/Float64"]),
             ("/dvt/cmd/gear", ["std_msgs/msg/UInt8", "std_msgs/msg/Int8"]),
             ("/rosout", ["rcl_interfaces/msg/Log"])]
    chosen, problems = match_topics(["/dvt/joint_states", "/dvt/cmd/*"], graph)
    assert chosen == {"/dvt/joint_states": JS, "/dvt/cmd/motor_current": "std_msgs/msg/Float64"}
    assert len(problems) == 1 and "/dvt/cmd/gear has 2 types" in problems[0]


def test_choose_qos() -> None:
    assert choose_qos([]) is None
    assert choose_qos([("reliable", "volatile")]) == ("reliable", "volatile")
    assert choose_qos([("reliable", "volatile"), ("best_effort", "volatile")]) == \
        ("best_effort", "volatile")
    assert choose_qos([("reliable", "transient_local")]) == ("reliable", "transient_local")
    assert choose_qos([("reliable", "transient_local"), ("reliable", "volatile")]) == \
        ("reliable", "volatile")


def test_stop_flag_turns_signals_into_a_flag() -> None:
    flag = StopFlag().install()
    try:
        assert not flag
        signal.raise_signal(signal.SIGINT)  # no KeyboardInterrupt
        assert flag and flag.received == signal.SIGINT
    finally:
        flag.restore()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


_KILLED_WRITER = textwrap.dedent("""
    import os, signal, sys
    from dvt_driver.recorder_core import BagRecorder
    from dvt_model import bagio
    clock = [0.0]
    rec = BagRecorder(sys.argv[1], {"/dvt/joint_states": "sensor_msgs/msg/JointState"},
                      flush_period=0.5, clock=lambda: clock[0])
    for i in range(1000):
        st = 1_700_000_000_000_000_000 + i * 1_000_000
        clock[0] = i * 1e-3  # 1 kHz
        rec.write("/dvt/joint_states",
                  bagio.joint_state_cdr(st, bagio.SPEED_NAMES, velocity=[i, 0.0]), st)
        if rec.poll() or rec.message_count % 500 == 1:
            pass
    print(rec.message_count, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_sigkilled_writer_loses_at_most_one_flush_period(tmp_path: Path) -> None:
    """A real SIGKILL: everything older than one flush period (0.5 s = 500 samples) survives."""
    path = tmp_path / "killed"
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert int(proc.stdout.strip()) == 1000
    assert not (path / "metadata.yaml").exists()
    assert bagtool.main(["recover", str(path)]) == 0
    series = bagio.read_topic_series(path, JOINT_STATES_TOPIC)
    n = series.stamps_ns.shape[0]
    assert 1000 - 501 <= n < 1000
    np.testing.assert_array_equal(series.velocity[:, 0], np.arange(n))


def test_bagtool_info_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with _record(tmp_path / "bag", 11):
        pass
    assert bagtool.main(["info", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert "/dvt/joint_states" in out and "11 msgs" in out and "1000.00 Hz" in out
    summary = bag_summary(tmp_path / "bag")
    assert summary.message_count == 22
    assert summary.duration == pytest.approx(0.010)

    assert bagtool.main(["recover", str(tmp_path / "bag")]) == 0
    assert "already readable" in capsys.readouterr().out

    assert bagtool.main(["recover", str(tmp_path / "nope")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dvt-bag: error:") and "nope" in err[0]

    (tmp_path / "bag" / "metadata.yaml").unlink()
    assert bagtool.main(["info", str(tmp_path / "bag")]) == 1
    assert "dvt-bag recover" in capsys.readouterr().err
    assert bagtool.main(["recover", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert "recovered 22 messages" in out
