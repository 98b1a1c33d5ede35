"""Bulk decoding and the MCAP index reader of dvt_model.recording against message-by-message truth.

Bags are written with the one writer (``recording.write_bag``) or with the ``mcap`` library
(other chunk sizes, compressions, no index, no chunks), and read back with
:func:`recording.read_topics`; the rosbags message iterator (the fallback reader) must give the
same result.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer

from dvt_model import recording
from dvt_model.contract import (
    CURRENT_NAMES,
    CURRENTS,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    SPEED_NAMES,
)
from dvt_model.errors import BagError
from dvt_model.recording import cdr, mcapindex

T0 = 1_700_000_000_000_000_000
DT = 1_000_000


def _stamps(n: int) -> np.ndarray:
    return T0 + DT * np.arange(n, dtype=np.int64)


def _cdr(stamp: int, names: tuple[str, ...], frame_id: str = "", big_endian: bool = False,
         pad: int = 0, **arrays: Any) -> bytes:
    """One JointState; ``frame_id``/``big_endian``/``pad`` give other byte layouts."""
    if frame_id or big_endian:
        ts = recording.typestore()
        msg = recording.joint_state(stamp, names, **arrays)
        msg.header.frame_id = frame_id
        raw = bytes(ts.serialize_cdr(msg, JOINT_STATE_TYPE, little_endian=not big_endian))
    else:
        raw = recording.joint_state_cdr(stamp, names, **arrays)
    return raw + b"\x00" * pad


def _read_both(path: Path, topics: list[str], monkeypatch: pytest.MonkeyPatch
               ) -> dict[str, recording.TopicSeries]:
    """read_topics with the fast reader, checked equal to the rosbags-iterator fallback."""
    fast = recording.read_topics(path, topics)
    with monkeypatch.context() as m:
        m.setattr(mcapindex, "mcap_files", lambda _path: None)
        slow = recording.read_topics(path, topics)
    for t in topics:
        _assert_same(fast[t], slow[t], strict=True)
    return fast


def _assert_same(a: recording.TopicSeries, b: recording.TopicSeries, strict: bool = False
                 ) -> None:
    """Every field of ``a`` equal to ``b``'s (arrays element by element, ``None`` as ``None``)."""
    for f in dataclasses.fields(recording.TopicSeries):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, strict=strict)
        else:
            assert x == y, (f.name, x, y)


def _odd_layouts(n: int, rng: np.random.Generator) -> tuple[list[tuple[int, bytes]], np.ndarray]:
    """``n`` /dvt/joint_states messages, a few with another byte layout; returns (stream, v)."""
    stamps = _stamps(n)
    v = rng.normal(size=(n, 2))
    msgs = [(int(s), _cdr(int(s), SPEED_NAMES, velocity=v[i])) for i, s in enumerate(stamps)]
    odd: dict[int, dict[str, Any]] = {37: {"frame_id": "base_link"},  # longer message
           38: {"frame_id": "x"},  # same length as "", other bytes
           90: {"big_endian": True},  # same length, every byte differs
           91: {"pad": 4},  # rclpy may add 4 bytes
           n - 1: {"frame_id": "y"}}
    for i, kw in odd.items():
        msgs[i] = (int(stamps[i]), _cdr(int(stamps[i]), SPEED_NAMES, velocity=v[i], **kw))
    return msgs, v


def test_bulk_equals_message_by_message(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1)
    n = 400
    js, v = _odd_layouts(n, rng)
    stamps = _stamps(n)
    cur = rng.normal(size=(n, 4))
    pos = rng.normal(size=(n, 4))
    cu = [(int(s), _cdr(int(s), CURRENT_NAMES, effort=cur[i], position=pos[i]))
          for i, s in enumerate(stamps)]
    path = recording.write_bag(tmp_path / "bag", [(JOINT_STATES, JOINT_STATE_TYPE, js),
                                              (CURRENTS, JOINT_STATE_TYPE, cu)])
    got = _read_both(path, [JOINT_STATES, CURRENTS], monkeypatch)
    a, b = got[JOINT_STATES], got[CURRENTS]
    np.testing.assert_array_equal(a.stamps_ns, stamps)
    np.testing.assert_array_equal(a.velocity, v)
    assert a.names == SPEED_NAMES and a.effort is None and a.position is None
    np.testing.assert_array_equal(b.effort, cur)
    np.testing.assert_array_equal(b.position, pos)
    # message by message, as the single-message parser sees each one
    for i in (0, 37, 38, 90, 91, n - 1):
        ref = cdr.parse_joint_state(js[i][1])
        assert ref.stamp_ns == a.stamps_ns[i]
        np.testing.assert_array_equal(ref.velocity, a.velocity[i])
    run = recording.read_run(path)
    np.testing.assert_array_equal(run.speeds, v)
    np.testing.assert_array_equal(run.currents, cur)


def _mcap_bag(tmp_path: Path, name: str, streams: list[tuple[str, list[tuple[int, bytes]]]],
              sort: bool = True, **writer: Any) -> Path:
    """A bag whose MCAP file is written by the ``mcap`` library with ``writer`` options
    (messages in log-time order if ``sort``, else stream by stream as given)."""
    path = recording.write_bag(tmp_path / name, [(t, JOINT_STATE_TYPE, m[:1]) for t, m in streams])
    mcap_file = next(path.glob("*.mcap"))
    schema_text = "sensor_msgs/msg/JointState definition (not needed by the reader)"
    with mcap_file.open("wb") as fh:
        w = Writer(fh, **writer)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(JOINT_STATE_TYPE, "ros2msg", schema_text.encode())
        cids = [w.register_channel(topic, "cdr", sid) for topic, _ in streams]
        merged = [(t, k, i, raw) for k, (_, msgs) in enumerate(streams)
                  for i, (t, raw) in enumerate(msgs)]
        if sort:
            merged.sort(key=lambda e: (e[0], e[1], e[2]))
        for t, k, i, raw in merged:
            w.add_message(cids[k], log_time=t, data=raw, publish_time=t, sequence=i)
        w.finish()
    return path  # metadata.yaml still counts one message a topic: readers do not use it


@pytest.mark.parametrize("writer", [
    {"compression": CompressionType.ZSTD, "chunk_size": 4096},
    {"compression": CompressionType.LZ4, "chunk_size": 20_000},
    {"compression": CompressionType.NONE, "chunk_size": 1 << 20},
    {"compression": CompressionType.NONE, "chunk_size": 3000, "index_types": IndexType.NONE},
    {"use_chunking": False},
], ids=["zstd", "lz4", "none", "no-index", "no-chunks"])
def test_mcap_writers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                      writer: dict[str, Any]) -> None:
    rng = np.random.default_rng(2)
    n = 600
    js, v = _odd_layouts(n, rng)
    stamps = _stamps(n)
    cur = rng.normal(size=(n, 4))
    cu = [(int(s), _cdr(int(s), CURRENT_NAMES, effort=cur[i])) for i, s in enumerate(stamps)]
    path = _mcap_bag(tmp_path, "bag", [(JOINT_STATES, js), (CURRENTS, cu)],
                     **writer)
    indexed = writer.get("use_chunking", True) and "index_types" not in writer
    files = list(path.glob("*.mcap"))
    if indexed:  # the index reader applies and agrees with rosbags
        raw = mcapindex.mcap_collect(files, [JOINT_STATES])[JOINT_STATES]
        assert [mcapindex.message_at(raw, i) for i in range(n)] == [m for _, m in js]
    else:
        with pytest.raises(mcapindex.McapFastPathError):
            mcapindex.mcap_collect(files, [JOINT_STATES])
    got = _read_both(path, [JOINT_STATES, CURRENTS], monkeypatch)
    np.testing.assert_array_equal(got[JOINT_STATES].stamps_ns, stamps)
    np.testing.assert_array_equal(got[JOINT_STATES].velocity, v)
    np.testing.assert_array_equal(got[CURRENTS].effort, cur)


def test_recorded_order_is_log_time_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                          ) -> None:
    # log times out of write order (and a tie): both readers return log-time order, ties in
    # file order; the header stamps travel with their messages
    stamps = _stamps(6)
    log = [5, 1, 3, 3, 0, 9]
    js = [(T0 + log[i], _cdr(int(stamps[i]), SPEED_NAMES, velocity=[i, -i])) for i in range(6)]
    path = _mcap_bag(tmp_path, "bag", [(JOINT_STATES, js)], sort=False,
                     compression=CompressionType.NONE, chunk_size=100)
    got = _read_both(path, [JOINT_STATES], monkeypatch)[JOINT_STATES]
    assert got.velocity[:, 0].tolist() == [4, 1, 2, 3, 0, 5]


def _bag_with(tmp_path: Path, js: list[tuple[int, bytes]]) -> Path:
    stamps = _stamps(len(js))
    cu = [(int(s), _cdr(int(s), CURRENT_NAMES, effort=[0.0] * 4)) for s in stamps]
    return recording.write_bag(tmp_path / "bag", [(JOINT_STATES, JOINT_STATE_TYPE, js),
                                              (CURRENTS, JOINT_STATE_TYPE, cu)])


def _err(path: Path, monkeypatch: pytest.MonkeyPatch, topics: list[str] | None = None) -> str:
    """The error of both readers (they must agree)."""
    topics = topics or [JOINT_STATES, CURRENTS]
    with pytest.raises(BagError) as fast:
        recording.read_topics(path, topics)
    with monkeypatch.context() as m:
        m.setattr(mcapindex, "mcap_files", lambda _path: None)
        with pytest.raises(BagError) as slow:
            recording.read_topics(path, topics)
    assert str(fast.value) == str(slow.value)
    assert str(fast.value).startswith(f"{path}: topic ")
    return str(fast.value)


def test_same_length_name_change_is_reported(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    stamps = _stamps(50)
    js = [(int(s), _cdr(int(s), ("aa", "bb"), velocity=[1.0, 2.0])) for s in stamps]
    js[7] = (int(stamps[7]), _cdr(int(stamps[7]), ("bb", "aa"), velocity=[1.0, 2.0]))
    js[9] = (int(stamps[9]), b"\x00\x01\x00\x00garbage")
    msg = _err(_bag_with(tmp_path, js), monkeypatch)
    assert msg.endswith("/dvt/joint_states: field 'name' of message 7 is ['bb', 'aa'], "
                        "message 0 has ['aa', 'bb']")


def test_undecodable_message_is_reported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                         ) -> None:
    stamps = _stamps(50)
    js = [(int(s), _cdr(int(s), SPEED_NAMES, velocity=[1.0, 2.0])) for s in stamps]
    good = js[11][1]
    js[11] = (int(stamps[11]), good[:12] + b"\xff\xff\xff\x7f" + good[16:])  # same length
    msg = _err(_bag_with(tmp_path, js), monkeypatch)
    assert "/dvt/joint_states: message 11 is not a valid sensor_msgs/msg/JointState" in msg


@pytest.mark.parametrize("where,values,expected", [
    (23, {"velocity": [1.0]}, "field 'velocity' of message 23 has 1 values, message 0 has 2"),
    (24, {"velocity": [1.0, 2.0], "effort": [3.0, 4.0]},
     "field 'effort' of message 24 has 2 values, message 0 has 0"),
    (0, {"velocity": [1.0, 2.0], "position": [1.0]},
     "field 'position' of message 0 has 1 values, expected 0 or 2 (one per name)"),
])
def test_array_length_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: int,
                             values: dict[str, Any], expected: str) -> None:
    stamps = _stamps(40)
    js = [(int(s), _cdr(int(s), SPEED_NAMES, velocity=[1.0, 2.0])) for s in stamps]
    js[where] = (int(stamps[where]), _cdr(int(stamps[where]), SPEED_NAMES, **values))
    msg = _err(_bag_with(tmp_path, js), monkeypatch)
    assert msg.endswith(f"/dvt/joint_states: {expected}")


def test_topic_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    stamps = _stamps(5)
    js = [(int(s), _cdr(int(s), SPEED_NAMES, velocity=[1.0, 2.0])) for s in stamps]
    path = _bag_with(tmp_path, js)
    assert "topic /nope missing (topics present: ['/dvt/currents', '/dvt/joint_states'])" in \
        _err(path, monkeypatch, [JOINT_STATES, "/nope"])
    got = recording.read_topics(path, [CURRENTS, CURRENTS])  # duplicates read once
    assert list(got) == [CURRENTS]


def test_corrupt_chunk_is_reported(tmp_path: Path) -> None:
    stamps = _stamps(3000)
    js = [(int(s), _cdr(int(s), SPEED_NAMES, velocity=[float(i), 0.0]))
          for i, s in enumerate(stamps)]
    path = _mcap_bag(tmp_path, "bag", [(JOINT_STATES, js)],
                     compression=CompressionType.ZSTD, chunk_size=20_000)
    mcap_file = next(path.glob("*.mcap"))
    data = bytearray(mcap_file.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)  # inside some chunk's compressed records
    mcap_file.write_bytes(bytes(data))
    with pytest.raises(BagError, match=rf"^{path}: topic /dvt/joint_states: cannot read messages"):
        recording.read_topics(path, [JOINT_STATES])


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_one_writer_read_by_fast_path_and_rosbags(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  compression: str) -> None:
    """A bag of the one writer (BagRecorder, small chunks) is read alike by the MCAP index
    reader (which must apply: summary, chunk and message indexes, statistics) and by rosbags."""
    from rosbags.rosbag2 import Reader

    rng = np.random.default_rng(3)
    n = 700
    stamps = _stamps(n)
    v = rng.normal(size=(n, 2))
    cur = rng.normal(size=(n, 4))
    path = tmp_path / "bag"
    with recording.BagRecorder(path, {JOINT_STATES: JOINT_STATE_TYPE, CURRENTS: JOINT_STATE_TYPE},
                               fsync=False, chunk_size=8192, compression=compression) as rec:
        for i, s in enumerate(stamps.tolist()):
            rec.write(JOINT_STATES, recording.joint_state_cdr(s, SPEED_NAMES, velocity=v[i]), s)
            rec.write(CURRENTS, recording.joint_state_cdr(s, CURRENT_NAMES, effort=cur[i]), s)
    files = mcapindex.mcap_files(path)
    assert files == [path / "bag.mcap"]
    raw = mcapindex.mcap_collect(files, [JOINT_STATES, CURRENTS])  # no McapFastPathError
    with Reader(path) as reader:
        assert reader.message_count == 2 * n
        by_topic: dict[str, list[bytes]] = {JOINT_STATES: [], CURRENTS: []}
        ts = recording.typestore()
        for conn, log_time, data in reader.messages():
            by_topic[conn.topic].append(data)
            msg: Any = ts.deserialize_cdr(data, conn.msgtype)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == log_time
    for topic, msgs in by_topic.items():
        assert [mcapindex.message_at(raw[topic], i) for i in range(n)] == msgs
    got = _read_both(path, [JOINT_STATES, CURRENTS], monkeypatch)
    np.testing.assert_array_equal(got[JOINT_STATES].velocity, v)
    np.testing.assert_array_equal(got[CURRENTS].effort, cur)
    run = recording.read_run(path)
    np.testing.assert_array_equal(run.stamps_ns, stamps)


def test_write_topics_round_trip(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    stamps = _stamps(30)
    series = {
        "/a/joint_states": recording.TopicSeries(stamps, ("x", "y"), velocity=np.ones((30, 2)),
                                                 position=np.arange(60.0).reshape(30, 2)),
        "/a/empty": recording.TopicSeries(stamps[:3], ("z",)),
    }
    path = recording.write_topics(tmp_path / "bag", series)
    got = _read_both(path, list(series), monkeypatch)
    for topic, want in series.items():
        _assert_same(got[topic], want)
    # an empty field given as (N, 0) reads back as None (the one representation of "empty")
    zero = {"/a": recording.TopicSeries(stamps, ("x",), effort=np.zeros((30, 0)),
                                        velocity=np.ones((30, 1)))}
    assert recording.read_topics(recording.write_topics(tmp_path / "zero", zero),
                                 ["/a"])["/a"].effort is None
    bad = {"/a/joint_states": dataclasses.replace(series["/a/joint_states"],
                                                  effort=np.zeros((30, 1)))}
    with pytest.raises(BagError, match=rf"^{tmp_path / 'bad'}: topic /a/joint_states: effort: "
                                       r"expected shape \(30, 2\), got \(30, 1\)$"):
        recording.write_topics(tmp_path / "bad", bad)
