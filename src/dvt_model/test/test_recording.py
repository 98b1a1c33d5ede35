"""Unit tests of dvt_model.recording: contract bags written by the one writer, read back and checked."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from dvt_model import recording
from dvt_model.contract import (
    CURRENT_NAMES,
    CURRENTS,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    MODEL_RESIDUAL,
    SPEED_NAMES,
)
from dvt_model.errors import BagError, RecordingWarning
from dvt_model.recording import cdr

T0 = 1_700_000_000_123_000_000


def _data(n: int = 50, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = T0 + np.arange(n, dtype=np.int64) * 1_000_000
    return stamps, rng.normal(size=(n, 2)), rng.normal(size=(n, 4))


def _js(stamps: np.ndarray, names: tuple[str, ...], field: str, values: np.ndarray
        ) -> list[tuple[int, bytes]]:
    return [(int(s), recording.joint_state_cdr(int(s), names, **{field: values[i]}))
            for i, s in enumerate(stamps)]


def _bag(tmp_path: Path, js: list[tuple[int, bytes]] | None, cu: list[tuple[int, bytes]] | None,
         extra: Sequence[recording.Stream] = ()) -> Path:
    streams: list[recording.Stream] = []
    if js is not None:
        streams.append((JOINT_STATES, JOINT_STATE_TYPE, js))
    if cu is not None:
        streams.append((CURRENTS, JOINT_STATE_TYPE, cu))
    streams.extend(extra)
    return recording.write_bag(tmp_path / "bag", streams)


def test_round_trip(tmp_path: Path) -> None:
    stamps, speeds, currents = _data()
    model = speeds + 0.1
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents, model_speeds=model,
                           residuals=speeds - model, truth={"effects": ["windage"], "c": 0.5})
    assert (path / "metadata.yaml").exists()
    run = recording.read_run(path)
    assert run.n == 50
    np.testing.assert_array_equal(run.stamps_ns, stamps)
    np.testing.assert_allclose(run.t, (stamps - stamps[0]) * 1e-9)
    np.testing.assert_array_equal(run.speeds, speeds)  # float64 survives CDR exactly
    np.testing.assert_array_equal(run.currents, currents)
    assert run.unmatched == 0
    assert set(run.topics) == {JOINT_STATES, CURRENTS, MODEL_JOINT_STATES,
                               MODEL_RESIDUAL}
    assert run.duration == pytest.approx(0.049)
    assert recording.sample_period(run) == pytest.approx(1e-3)
    series = recording.read_topic_series(path, MODEL_RESIDUAL)
    assert series.names == SPEED_NAMES
    np.testing.assert_allclose(series.velocity, speeds - model)
    assert series.effort is None and series.position is None
    assert recording.read_truth(path) == {"effects": ["windage"], "c": 0.5}


def test_truth_absent_or_invalid(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    assert recording.read_truth(path) is None
    (path / "truth.yaml").write_text("- just\n- a list\n")
    with pytest.raises(BagError, match="truth.yaml: expected a mapping"):
        recording.read_truth(path)


def test_bag_readable_by_mcap_ros2(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    stamps, speeds, currents = _data(5)
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    with next(path.glob("*.mcap")).open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        msgs = [m for _, _, _, m in reader.iter_decoded_messages(topics=[JOINT_STATES])]
    assert [list(m.name) for m in msgs] == [list(SPEED_NAMES)] * 5
    assert msgs[2].velocity[1] == speeds[2, 1]


def test_unknown_extra_topics_ignored(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(10)
    ts = recording.typestore()
    string = ts.types["std_msgs/msg/String"]
    extra: list[recording.Stream] = [
        ("/something/else", "std_msgs/msg/String", [(int(stamps[0]), string(data="hi"))]),
        ("/other/joints", JOINT_STATE_TYPE,
         [(int(stamps[1]), recording.joint_state_cdr(int(stamps[1]), ["x"], velocity=[np.nan]))]),
    ]
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents, extra=extra)
    run = recording.read_run(path)
    assert run.n == 10
    assert "/something/else" in run.topics
    np.testing.assert_array_equal(run.speeds, speeds)


def test_unmatched_stamps_dropped_and_counted(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(20)
    js_keep = np.ones(20, bool)
    js_keep[[3, 4]] = False
    cu_keep = np.ones(20, bool)
    cu_keep[[10, 19]] = False
    cu_keep[0] = False
    path = _bag(tmp_path,
                _js(stamps[js_keep], SPEED_NAMES, "velocity", speeds[js_keep]),
                _js(stamps[cu_keep], CURRENT_NAMES, "effort", currents[cu_keep]))
    run = recording.read_run(path)
    both = js_keep & cu_keep
    np.testing.assert_array_equal(run.stamps_ns, stamps[both])
    np.testing.assert_array_equal(run.speeds, speeds[both])
    np.testing.assert_array_equal(run.currents, currents[both])
    assert run.unmatched == 5
    assert run.unmatched_by_topic == {JOINT_STATES: 3, CURRENTS: 2}
    assert run.t[0] == 0.0


def test_no_common_stamp(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds),
                _js(stamps + 1, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="share no header.stamp"):
        recording.read_run(path)


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"nope: no such bag directory"):
        recording.read_run(tmp_path / "nope")


def test_missing_metadata_suggests_recover(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(4)
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    (path / "metadata.yaml").unlink()
    with pytest.raises(BagError) as err:
        recording.read_run(path)
    assert str(path) in str(err.value)
    assert "metadata.yaml is missing" in str(err.value)
    assert f"dvt-bag recover {path}" in str(err.value)


def test_truncated_storage(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(200)
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    mcap = next(path.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:-100])
    with pytest.raises(BagError, match=r"cannot open bag.*dvt-bag recover"):
        recording.read_run(path)  # the strict contract reader refuses it
    with pytest.raises(BagError, match=r"cannot open bag.*dvt-bag recover"):
        recording.read_topics(path, [JOINT_STATES], salvage=False)
    with pytest.warns(RecordingWarning, match=rf"^{mcap}: the recording was not closed .*400 "
                                              r"messages kept \(/dvt/joint_states: 200\)"):
        series = recording.read_topics(path, [JOINT_STATES])  # only the summary was cut
    np.testing.assert_array_equal(series[JOINT_STATES].stamps_ns, stamps)
    np.testing.assert_array_equal(series[JOINT_STATES].velocity, speeds)


def _chunked_run(path: Path, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed contract recording of n samples in small chunks (both messages of a sample in
    one chunk); returns (stamps, speeds, currents)."""
    stamps, speeds, currents = _data(n)
    with recording.BagRecorder(path, {JOINT_STATES: JOINT_STATE_TYPE,
                                      CURRENTS: JOINT_STATE_TYPE}, fsync=False,
                               flush_period=math.inf, chunk_size=1 << 30) as rec:
        for i, st in enumerate(stamps.tolist()):
            rec.write(JOINT_STATES, recording.joint_state_cdr(st, SPEED_NAMES,
                                                              velocity=speeds[i]), st)
            rec.write(CURRENTS, recording.joint_state_cdr(st, CURRENT_NAMES,
                                                          effort=currents[i]), st)
            if i % 10 == 9:
                rec.flush()  # closes the chunk: 10 samples per chunk
    return stamps, speeds, currents


def test_truncated_mid_chunk_is_read_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "run"
    stamps, speeds, currents = _chunked_run(path, 95)
    mcap = path / "run.mcap"
    with mcap.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and len(summary.chunk_indexes) == 10
    cut = summary.chunk_indexes[6]  # 60 samples in the 6 chunks before it
    mcap.write_bytes(mcap.read_bytes()[:cut.chunk_start_offset + cut.chunk_length - 3])
    with pytest.warns(RecordingWarning) as rec:
        series = recording.read_topics(path, [JOINT_STATES, CURRENTS])
    assert len(rec) == 1
    msg = str(rec[0].message)
    assert msg.startswith(f"{mcap}: the recording was not closed (no summary/footer); reading "
                          f"stopped at run.mcap: truncated record after offset "
                          f"{cut.chunk_start_offset}")
    assert msg.endswith("read up to its last complete chunk: 120 messages kept "
                        f"(/dvt/joint_states: 60, /dvt/currents: 60); `dvt-bag recover {path}` "
                        "rewrites it as a complete bag")
    np.testing.assert_array_equal(series[JOINT_STATES].stamps_ns, stamps[:60])
    np.testing.assert_array_equal(series[CURRENTS].effort, currents[:60])
    with pytest.raises(BagError, match=r"cannot open bag.*dvt-bag recover"):
        recording.read_run(path)
    with pytest.warns(RecordingWarning, match="120 messages kept"):
        run = recording.read_run(path, salvage=True)
    assert run.n == 60 and run.topics == (CURRENTS, JOINT_STATES)
    np.testing.assert_array_equal(run.speeds, speeds[:60])


def test_killed_recording_without_metadata_is_read_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "run"
    stamps, _, _ = _chunked_run(path, 30)
    (path / "metadata.yaml").unlink()
    mcap = path / "run.mcap"
    mcap.write_bytes(mcap.read_bytes()[:-10])
    with pytest.warns(RecordingWarning, match=rf"^{mcap}: metadata.yaml is missing \(the "
                                              r"recording was not closed\).* 60 messages kept"):
        series = recording.read_topic_series(path, JOINT_STATES)
    np.testing.assert_array_equal(series.stamps_ns, stamps)
    with pytest.raises(BagError, match="metadata.yaml is missing"):
        recording.read_topic_series(path, JOINT_STATES, salvage=False)
    with pytest.raises(BagError, match=rf"{path}: topic /nope missing \(topics present: "
                                       r"\['/dvt/currents', '/dvt/joint_states'\]\)"), \
            warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)
        recording.read_topics(path, ["/nope"])


@pytest.mark.parametrize("size,why", [
    (0, "not readable: not an MCAP file (empty)"),
    (6, "not readable: not an MCAP file (6 bytes)"),
    (8, "nothing readable: no complete message in the recording: run.mcap: truncated record"),
    (200, "nothing readable: no complete message in the recording: run.mcap: truncated record"),
])
def test_truncated_to_nothing_names_the_file(tmp_path: Path, size: int, why: str) -> None:
    path = tmp_path / "run"
    _chunked_run(path, 30)
    mcap = path / "run.mcap"
    mcap.write_bytes(mcap.read_bytes()[:size])
    with pytest.raises(BagError) as err:
        recording.read_topics(path, [JOINT_STATES])
    assert str(err.value).startswith(f"{mcap}: {why}")


def test_read_topics_returns_values_and_stamps_as_recorded(tmp_path: Path) -> None:
    """NaN and stamps that do not increase are the caller's to judge (read_run refuses them,
    the identifier splits the recording there)."""
    stamps, speeds, currents = _data(10)
    stamps[5] = stamps[4]
    speeds[7, 1] = np.nan
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    series = recording.read_topics(path, [JOINT_STATES])[JOINT_STATES]
    np.testing.assert_array_equal(series.stamps_ns, stamps)
    assert np.isnan(series.velocity[7, 1])
    with pytest.raises(BagError, match="is not finite at message 7"):
        recording.read_run(path)


def test_missing_topic(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), None)
    with pytest.raises(BagError, match=rf"{path}: topic /dvt/currents missing"):
        recording.read_run(path)


def test_empty_topic(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), [])
    with pytest.raises(BagError, match="topic /dvt/currents has no messages"):
        recording.read_run(path)


def test_wrong_type(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(2)
    string = recording.typestore().types["std_msgs/msg/String"]
    path = recording.write_bag(tmp_path / "bag", [
        (JOINT_STATES, JOINT_STATE_TYPE, _js(stamps, SPEED_NAMES, "velocity", speeds)),
        (CURRENTS, "std_msgs/msg/String", [(int(stamps[0]), string(data="x"))])])
    with pytest.raises(BagError, match="topic /dvt/currents: type is std_msgs/msg/String"):
        recording.read_run(path)


def test_wrong_names(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    path = _bag(tmp_path, _js(stamps, ("sun", "carrier3"), "velocity", speeds),
                _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match=r"topic /dvt/joint_states: field 'name' is \['sun', "):
        recording.read_run(path)


def test_names_change_between_messages(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    js = _js(stamps, SPEED_NAMES, "velocity", speeds)
    js[2] = (int(stamps[2]), recording.joint_state_cdr(int(stamps[2]), ("carrier3", "sun_shaft"),
                                                     velocity=speeds[2]))
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="field 'name' of message 2"):
        recording.read_run(path)


def test_wrong_array_length(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    cu = _js(stamps, CURRENT_NAMES, "effort", currents)
    cu[1] = (int(stamps[1]), recording.joint_state_cdr(int(stamps[1]), CURRENT_NAMES,
                                                     effort=[1.0, 2.0]))
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), cu)
    with pytest.raises(BagError, match=r"/dvt/currents: field 'effort' of message 1 has 2 values"):
        recording.read_run(path)


def test_required_field_empty(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    # currents sent in 'velocity' instead of 'effort'
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds),
                _js(stamps, CURRENT_NAMES, "velocity", currents))
    with pytest.raises(BagError, match="/dvt/currents: field 'effort' is empty"):
        recording.read_run(path)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite(tmp_path: Path, bad: float) -> None:
    stamps, speeds, currents = _data(10)
    speeds[7, 1] = bad
    speeds[8, 0] = bad
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match=r"/dvt/joint_states: field 'velocity' is not finite at "
                                       rf"message 7 \(stamp {stamps[7]} ns, carrier3\)"):
        recording.read_run(path)


def test_non_monotonic_stamps(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(10)
    stamps[5] = stamps[4]
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match=r"field 'header.stamp' does not strictly increase at "
                                       r"message 5"):
        recording.read_run(path)


def test_stamp_order_independent_of_log_time(tmp_path: Path) -> None:
    # Header stamps that go backwards in recorded (log-time) order are rejected, even though
    # every stamp is unique.
    stamps, speeds, currents = _data(5)
    js = [(int(stamps[i]), recording.joint_state_cdr(int(stamps[4 - i]), SPEED_NAMES,
                                                   velocity=speeds[i])) for i in range(5)]
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="does not strictly increase at message 1"):
        recording.read_run(path)


def test_write_run_shape_errors(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(5)
    with pytest.raises(BagError, match=r"^speeds: expected shape \(5, 2\), got \(5, 3\)$"):
        recording.write_run(tmp_path / "a", stamps, np.zeros((5, 3)), currents)
    with pytest.raises(BagError, match=r"^currents: expected shape \(5, 4\), got \(4, 4\)$"):
        recording.write_run(tmp_path / "b", stamps, speeds, currents[:4])
    with pytest.raises(BagError, match=r"^residuals: expected shape \(5, 2\), got \(5,\)$"):
        recording.write_run(tmp_path / "c", stamps, speeds, currents, residuals=np.zeros(5))
    with pytest.raises(BagError, match="stamps_ns: expected an integer array"):
        recording.write_run(tmp_path / "d", stamps * 1.0, speeds, currents)


def test_write_refuses_existing(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(2)
    recording.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match="exists already"):
        recording.write_run(tmp_path / "run", stamps, speeds, currents)


def test_topic_series_missing_topic(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(2)
    path = recording.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match="topic /dvt/model/residual missing"):
        recording.read_topic_series(path, MODEL_RESIDUAL)


_names = st.lists(st.text(max_size=6), max_size=4)
_floats = st.lists(st.floats(allow_nan=False), max_size=5)


@settings(max_examples=150, deadline=None)
@given(stamp=st.integers(-(2**31) * 10**9, 2**31 * 10**9 - 1), names=_names, pos=_floats, vel=_floats, eff=_floats)
def test_fast_cdr_matches_rosbags(stamp: int, names: list[str], pos: list[float],
                                  vel: list[float], eff: list[float]) -> None:
    ts = recording.typestore()
    raw = recording.joint_state_cdr(stamp, names, position=pos, velocity=vel, effort=eff)
    reference = bytes(ts.serialize_cdr(
        recording.joint_state(stamp, names, position=pos, velocity=vel, effort=eff),
        JOINT_STATE_TYPE))
    assert raw == reference
    back = cdr.parse_joint_state(raw + b"\x00\x00\x00\x00")  # rclpy may add 4 bytes
    assert back.stamp_ns == stamp
    assert back.names == tuple(names)
    for got, want in ((back.position, pos), (back.velocity, vel), (back.effort, eff)):
        np.testing.assert_array_equal(got, np.asarray(want, dtype=float))


def test_stamp_out_of_range() -> None:
    with pytest.raises(BagError, match="does not fit builtin_interfaces/Time"):
        recording.joint_state_cdr(2**31 * 10**9, SPEED_NAMES)


def test_big_endian_cdr_falls_back_to_rosbags() -> None:
    raw = bytearray(recording.joint_state_cdr(T0, SPEED_NAMES, velocity=[1.0, 2.0]))
    # a big-endian encoding of the same message, as another DDS vendor might produce
    ts = recording.typestore()
    msg = ts.deserialize_cdr(bytes(raw), JOINT_STATE_TYPE)
    be = bytes(ts.serialize_cdr(msg, JOINT_STATE_TYPE, little_endian=False))
    back = cdr.parse_joint_state(be)
    assert back.names == SPEED_NAMES and list(back.velocity) == [1.0, 2.0]
    assert back.stamp_ns == T0


def test_garbage_message_is_reported(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    js = _js(stamps, SPEED_NAMES, "velocity", speeds)
    js[1] = (int(stamps[1]), b"\x00\x01\x00\x00\xff\xff")
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="/dvt/joint_states: message 1 is not a valid"):
        recording.read_run(path)
