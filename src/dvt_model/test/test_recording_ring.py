"""Rolling recording (pure): segments, pruning, snapshots across boundaries, killed segments."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATE_TYPE, JOINT_STATES, SPEED_NAMES
from dvt_model.errors import RecordingError
from dvt_model.recording import joint_state_cdr, read_run, read_topics
from dvt_model.recording.cdr import raw_stamp_ns, restamp
from dvt_model.recording.ring import (
    RollingRecorder,
    segment_paths,
    write_snapshot,
)

T0 = 1_700_000_000 * 10**9
DT = 10**6  # 1 kHz
STRING = "std_msgs/msg/String"


def _string_cdr(text: str) -> bytes:
    b = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + len(b).to_bytes(4, "little") + b


def _feed(ring: RollingRecorder, first: int, n: int, latency_ns: int = 300_000) -> None:
    """Samples ``first..first+n-1`` at 1 kHz; log time = stamp + latency (currents later)."""
    for i in range(first, first + n):
        st = T0 + i * DT
        ring.write(JOINT_STATES, joint_state_cdr(st, SPEED_NAMES, velocity=[float(i), 0.0]),
                   st + latency_ns)
        ring.write(CURRENTS, joint_state_cdr(st, CURRENT_NAMES, effort=[0.0, 0.0, 0.0, i]),
                   st + latency_ns + 150_000)
        if i % 500 == 0:
            ring.write("/dvt/cmd/note", _string_cdr(f"n{i}"), st + latency_ns)


def _ring(tmp_path: Path, **kw: float) -> RollingRecorder:
    ring = RollingRecorder(tmp_path / "ring", ring_s=kw.get("ring_s", 3.0),
                           segment_s=kw.get("segment_s", 0.5), fsync=False)
    ring.add_topic(JOINT_STATES, JOINT_STATE_TYPE)
    ring.add_topic(CURRENTS, JOINT_STATE_TYPE)
    ring.add_topic("/dvt/cmd/note", STRING)
    return ring


def test_segments_rotate_and_old_ones_are_deleted(tmp_path: Path) -> None:
    ring = _ring(tmp_path)
    _feed(ring, 0, 6000)  # 6 s of data, ring 3 s, segments 0.5 s
    segs = segment_paths(ring.directory)
    assert 6 <= len(segs) <= 8 and ring.deleted >= 4
    assert ring.oldest_ns is not None and ring.newest_ns is not None
    held = ring.newest_ns - ring.oldest_ns
    assert 3e9 <= held <= 3.6e9  # at least ring_s, at most ring_s + one segment
    ring.close()
    assert all((p / "metadata.yaml").exists() for p in segment_paths(ring.directory))


def test_snapshot_spanning_segments_is_a_contiguous_contract_bag(tmp_path: Path) -> None:
    ring = _ring(tmp_path)
    _feed(ring, 0, 4000)
    t_from = (T0 + 1234 * DT) * 1e-9
    t_to = (T0 + 3210 * DT) * 1e-9
    res = ring.snapshot(t_from, t_to, tmp_path / "snap")
    assert res.segments >= 4 and not res.truncated
    run = read_run(res.path)
    expected = np.arange(1234, 3211)
    assert run.n == expected.size and run.unmatched == 0
    assert np.array_equal(run.stamps_ns, T0 + expected * DT)
    assert np.array_equal(run.speeds[:, 0], expected.astype(float))
    assert np.array_equal(run.currents[:, 3], expected.astype(float))
    # the untimed String topic is cut by log time and keeps its type
    assert res.counts["/dvt/cmd/note"] == 4  # notes at 1500, 2000, 2500, 3000
    # the ring goes on after a snapshot (the current segment was closed, a new one opens)
    _feed(ring, 4000, 1000)
    res2 = ring.snapshot((T0 + 3500 * DT) * 1e-9, (T0 + 4999 * DT) * 1e-9, tmp_path / "snap2")
    assert read_run(res2.path).n == 1500
    ring.close()


def test_window_older_than_the_ring_is_truncated_and_errors(tmp_path: Path) -> None:
    ring = _ring(tmp_path)
    _feed(ring, 0, 6000)
    res = ring.snapshot(T0 * 1e-9, (T0 + 5999 * DT) * 1e-9, tmp_path / "s")
    assert res.truncated and 3000 <= read_run(res.path).n < 6000
    with pytest.raises(RecordingError, match="exists already"):
        ring.snapshot(T0 * 1e-9, (T0 + 10 * DT) * 1e-9, tmp_path / "s")
    with pytest.raises(RecordingError, match="'to'"):
        ring.snapshot((T0 + 10 * DT) * 1e-9, T0 * 1e-9, tmp_path / "s3")
    with pytest.raises(RecordingError, match="from"):
        ring.snapshot(-1.0, 1.0, tmp_path / "s4")
    with pytest.raises(RecordingError, match="segment_s"):
        RollingRecorder(tmp_path / "r2", ring_s=1.0, segment_s=2.0)
    with pytest.raises(RecordingError, match="ring_s"):
        RollingRecorder(tmp_path / "r2", ring_s=0.0)
    ring.close()


def test_pinned_segments_survive_until_released(tmp_path: Path) -> None:
    ring = _ring(tmp_path)
    _feed(ring, 0, 2000)
    plan = ring.prepare(T0, T0 + 1000 * DT)
    _feed(ring, 2000, 4000)  # would delete the first segments
    assert all(s.path.exists() for s in plan.segments)
    res = write_snapshot(plan, tmp_path / "late")
    ring.release(plan)
    assert read_run(res.path).n == 1001
    assert not plan.segments[0].path.exists()
    ring.close()


def test_killed_segments_are_adopted_and_read(tmp_path: Path) -> None:
    ring = _ring(tmp_path, segment_s=5.0, ring_s=60.0)
    _feed(ring, 0, 1500)
    ring._current.flush()  # type: ignore[union-attr]  # durable, as after flush_period
    # "kill": the writer is abandoned without close; a new ring adopts the directory
    ring2 = RollingRecorder(tmp_path / "ring", ring_s=60.0, segment_s=5.0, fsync=False)
    assert len(ring2.segments) == 1 and ring2.segments[0].closed
    ring2.add_topic(JOINT_STATES, JOINT_STATE_TYPE)
    ring2.add_topic(CURRENTS, JOINT_STATE_TYPE)
    _feed_pairs_only = [(T0 + i * DT) for i in range(1500, 1600)]
    for st in _feed_pairs_only:
        ring2.write(JOINT_STATES, joint_state_cdr(st, SPEED_NAMES, velocity=[1.0, 0.0]), st)
        ring2.write(CURRENTS, joint_state_cdr(st, CURRENT_NAMES, effort=[0.0] * 4), st)
    res = ring2.snapshot(T0 * 1e-9, (T0 + 1599 * DT) * 1e-9, tmp_path / "snap")
    series = read_topics(res.path, [JOINT_STATES])[JOINT_STATES]
    assert series.stamps_ns.size == 1600
    assert np.all(np.diff(series.stamps_ns) == DT)
    ring2.close()


def test_header_stamp_parsing() -> None:
    raw = joint_state_cdr(T0 + 123, SPEED_NAMES, velocity=[0.0, 0.0])
    assert raw_stamp_ns(raw) == T0 + 123
    sec, nsec = divmod(T0 + 7, 10**9)
    big_endian = b"\x00\x00\x00\x00" + sec.to_bytes(4, "big") + nsec.to_bytes(4, "big")
    assert raw_stamp_ns(big_endian) == T0 + 7
    with pytest.raises(ValueError, match="2 bytes is too short"):
        raw_stamp_ns(b"\x00\x01")
    with pytest.raises(ValueError, match="unknown CDR encapsulation 0x0007"):
        raw_stamp_ns(b"\x00\x07\x00\x00" + bytes(8))
    moved = restamp(raw, T0 + 5_000_000_123)
    assert raw_stamp_ns(moved) == T0 + 5_000_000_123 and moved[12:] == raw[12:]


def test_float_second_windows_keep_edge_samples() -> None:
    from dvt_model.recording.ring import window_ns

    base = 1_795_477_410_244_000_000
    for i in range(2000):
        st = base + i * 1_000_003
        lo, hi = window_ns(st * 1e-9, st * 1e-9)
        assert lo <= st <= hi and hi - lo < 5_000
