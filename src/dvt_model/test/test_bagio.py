"""Unit tests of dvt_model.bagio: contract bags written with rosbags, read back and checked."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dvt_model import bagio
from dvt_model.bagio import (
    CURRENT_NAMES,
    CURRENTS_TOPIC,
    JOINT_STATE_TYPE,
    JOINT_STATES_TOPIC,
    SPEED_NAMES,
)
from dvt_model.errors import BagError

T0 = 1_700_000_000_123_000_000


def _data(n: int = 50, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = T0 + np.arange(n, dtype=np.int64) * 1_000_000
    return stamps, rng.normal(size=(n, 2)), rng.normal(size=(n, 4))


def _js(stamps: np.ndarray, names: tuple[str, ...], field: str, values: np.ndarray
        ) -> list[tuple[int, bytes]]:
    return [(int(s), bagio.joint_state_cdr(int(s), names, **{field: values[i]}))
            for i, s in enumerate(stamps)]


def _bag(tmp_path: Path, js: list[tuple[int, bytes]] | None, cu: list[tuple[int, bytes]] | None,
         extra: Sequence[bagio.Stream] = ()) -> Path:
    streams: list[bagio.Stream] = []
    if js is not None:
        streams.append((JOINT_STATES_TOPIC, JOINT_STATE_TYPE, js))
    if cu is not None:
        streams.append((CURRENTS_TOPIC, JOINT_STATE_TYPE, cu))
    streams.extend(extra)
    return bagio.write_bag(tmp_path / "bag", streams)


def test_round_trip(tmp_path: Path) -> None:
    stamps, speeds, currents = _data()
    model = speeds + 0.1
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents, model_speeds=model,
                           residuals=speeds - model, truth={"effects": ["windage"], "c": 0.5})
    assert (path / "metadata.yaml").exists()
    run = bagio.read_run(path)
    assert run.n == 50
    np.testing.assert_array_equal(run.stamps_ns, stamps)
    np.testing.assert_allclose(run.t, (stamps - stamps[0]) * 1e-9)
    np.testing.assert_array_equal(run.speeds, speeds)  # float64 survives CDR exactly
    np.testing.assert_array_equal(run.currents, currents)
    assert run.unmatched == 0
    assert set(run.topics) == {JOINT_STATES_TOPIC, CURRENTS_TOPIC, bagio.MODEL_JOINT_STATES_TOPIC,
                               bagio.MODEL_RESIDUAL_TOPIC}
    assert run.duration == pytest.approx(0.049)
    assert bagio.sample_period(run) == pytest.approx(1e-3)
    series = bagio.read_topic_series(path, bagio.MODEL_RESIDUAL_TOPIC)
    assert series.names == SPEED_NAMES
    np.testing.assert_allclose(series.velocity, speeds - model)
    assert series.effort.shape == (50, 0)
    assert bagio.read_truth(path) == {"effects": ["windage"], "c": 0.5}


def test_truth_absent_or_invalid(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    assert bagio.read_truth(path) is None
    (path / "truth.yaml").write_text("- just\n- a list\n")
    with pytest.raises(BagError, match="truth.yaml: expected a mapping"):
        bagio.read_truth(path)


def test_bag_readable_by_mcap_ros2(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    stamps, speeds, currents = _data(5)
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    with next(path.glob("*.mcap")).open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        msgs = [m for _, _, _, m in reader.iter_decoded_messages(topics=[JOINT_STATES_TOPIC])]
    assert [list(m.name) for m in msgs] == [list(SPEED_NAMES)] * 5
    assert msgs[2].velocity[1] == speeds[2, 1]


def test_unknown_extra_topics_ignored(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(10)
    ts = bagio.typestore()
    string = ts.types["std_msgs/msg/String"]
    extra: list[bagio.Stream] = [
        ("/something/else", "std_msgs/msg/String", [(int(stamps[0]), string(data="hi"))]),
        ("/other/joints", JOINT_STATE_TYPE,
         [(int(stamps[1]), bagio.joint_state_cdr(int(stamps[1]), ["x"], velocity=[np.nan]))]),
    ]
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents, extra=extra)
    run = bagio.read_run(path)
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
    run = bagio.read_run(path)
    both = js_keep & cu_keep
    np.testing.assert_array_equal(run.stamps_ns, stamps[both])
    np.testing.assert_array_equal(run.speeds, speeds[both])
    np.testing.assert_array_equal(run.currents, currents[both])
    assert run.unmatched == 5
    assert run.unmatched_by_topic == {JOINT_STATES_TOPIC: 3, CURRENTS_TOPIC: 2}
    assert run.t[0] == 0.0


def test_no_common_stamp(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds),
                _js(stamps + 1, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="share no header.stamp"):
        bagio.read_run(path)


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"nope: no such bag directory"):
        bagio.read_run(tmp_path / "nope")


def test_missing_metadata_suggests_recover(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(4)
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    (path / "metadata.yaml").unlink()
    with pytest.raises(BagError) as err:
        bagio.read_run(path)
    assert str(path) in str(err.value)
    assert "metadata.yaml is missing" in str(err.value)
    assert f"dvt-bag recover {path}" in str(err.value)


def test_truncated_storage(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(200)
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    mcap = next(path.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:-100])
    with pytest.raises(BagError, match=r"cannot open bag.*dvt-bag recover"):
        bagio.read_run(path)


def test_missing_topic(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), None)
    with pytest.raises(BagError, match=rf"{path}: topic /dvt/currents missing"):
        bagio.read_run(path)


def test_empty_topic(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(4)
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), [])
    with pytest.raises(BagError, match="topic /dvt/currents has no messages"):
        bagio.read_run(path)


def test_wrong_type(tmp_path: Path) -> None:
    stamps, speeds, _ = _data(2)
    string = bagio.typestore().types["std_msgs/msg/String"]
    path = bagio.write_bag(tmp_path / "bag", [
        (JOINT_STATES_TOPIC, JOINT_STATE_TYPE, _js(stamps, SPEED_NAMES, "velocity", speeds)),
        (CURRENTS_TOPIC, "std_msgs/msg/String", [(int(stamps[0]), string(data="x"))])])
    with pytest.raises(BagError, match="topic /dvt/currents: type is std_msgs/msg/String"):
        bagio.read_run(path)


def test_wrong_names(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    path = _bag(tmp_path, _js(stamps, ("sun", "carrier3"), "velocity", speeds),
                _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match=r"topic /dvt/joint_states: field 'name' is \['sun', "):
        bagio.read_run(path)


def test_names_change_between_messages(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    js = _js(stamps, SPEED_NAMES, "velocity", speeds)
    js[2] = (int(stamps[2]), bagio.joint_state_cdr(int(stamps[2]), ("carrier3", "sun_shaft"),
                                                     velocity=speeds[2]))
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="field 'name' of message 2"):
        bagio.read_run(path)


def test_wrong_array_length(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    cu = _js(stamps, CURRENT_NAMES, "effort", currents)
    cu[1] = (int(stamps[1]), bagio.joint_state_cdr(int(stamps[1]), CURRENT_NAMES,
                                                     effort=[1.0, 2.0]))
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds), cu)
    with pytest.raises(BagError, match=r"/dvt/currents: field 'effort' of message 1 has 2 values"):
        bagio.read_run(path)


def test_required_field_empty(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    # currents sent in 'velocity' instead of 'effort'
    path = _bag(tmp_path, _js(stamps, SPEED_NAMES, "velocity", speeds),
                _js(stamps, CURRENT_NAMES, "velocity", currents))
    with pytest.raises(BagError, match="/dvt/currents: field 'effort' is empty"):
        bagio.read_run(path)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite(tmp_path: Path, bad: float) -> None:
    stamps, speeds, currents = _data(10)
    speeds[7, 1] = bad
    speeds[8, 0] = bad
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match=r"/dvt/joint_states: field 'velocity' is not finite at "
                                       rf"message 7 \(stamp {stamps[7]} ns, carrier3\)"):
        bagio.read_run(path)


def test_non_monotonic_stamps(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(10)
    stamps[5] = stamps[4]
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match=r"field 'header.stamp' does not strictly increase at "
                                       r"message 5"):
        bagio.read_run(path)


def test_stamp_order_independent_of_log_time(tmp_path: Path) -> None:
    # Header stamps that go backwards in recorded (log-time) order are rejected, even though
    # every stamp is unique.
    stamps, speeds, currents = _data(5)
    js = [(int(stamps[i]), bagio.joint_state_cdr(int(stamps[4 - i]), SPEED_NAMES,
                                                   velocity=speeds[i])) for i in range(5)]
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="does not strictly increase at message 1"):
        bagio.read_run(path)


def test_write_run_shape_errors(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(5)
    with pytest.raises(BagError, match=r"^speeds: expected shape \(5, 2\), got \(5, 3\)$"):
        bagio.write_run(tmp_path / "a", stamps, np.zeros((5, 3)), currents)
    with pytest.raises(BagError, match=r"^currents: expected shape \(5, 4\), got \(4, 4\)$"):
        bagio.write_run(tmp_path / "b", stamps, speeds, currents[:4])
    with pytest.raises(BagError, match=r"^residuals: expected shape \(5, 2\), got \(5,\)$"):
        bagio.write_run(tmp_path / "c", stamps, speeds, currents, residuals=np.zeros(5))
    with pytest.raises(BagError, match="stamps_ns: expected an integer array"):
        bagio.write_run(tmp_path / "d", stamps * 1.0, speeds, currents)


def test_write_refuses_existing(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(2)
    bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match="exists already"):
        bagio.write_run(tmp_path / "run", stamps, speeds, currents)


def test_topic_series_missing_topic(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(2)
    path = bagio.write_run(tmp_path / "run", stamps, speeds, currents)
    with pytest.raises(BagError, match="topic /dvt/model/residual missing"):
        bagio.read_topic_series(path, bagio.MODEL_RESIDUAL_TOPIC)


_names = st.lists(st.text(max_size=6), max_size=4)
_floats = st.lists(st.floats(allow_nan=False), max_size=5)


@settings(max_examples=150, deadline=None)
@given(stamp=st.integers(-(2**31) * 10**9, 2**31 * 10**9 - 1), names=_names, pos=_floats, vel=_floats, eff=_floats)
def test_fast_cdr_matches_rosbags(stamp: int, names: list[str], pos: list[float],
                                  vel: list[float], eff: list[float]) -> None:
    ts = bagio.typestore()
    raw = bagio.joint_state_cdr(stamp, names, position=pos, velocity=vel, effort=eff)
    reference = bytes(ts.serialize_cdr(
        bagio.joint_state(stamp, names, position=pos, velocity=vel, effort=eff),
        JOINT_STATE_TYPE))
    assert raw == reference
    back = bagio._parse_joint_state(raw + b"\x00\x00\x00\x00")  # rclpy may add 4 bytes
    assert back.stamp_ns == stamp
    assert back.names == tuple(names)
    for got, want in ((back.position, pos), (back.velocity, vel), (back.effort, eff)):
        np.testing.assert_array_equal(got, np.asarray(want, dtype=float))


def test_stamp_out_of_range() -> None:
    with pytest.raises(BagError, match="does not fit builtin_interfaces/Time"):
        bagio.joint_state_cdr(2**31 * 10**9, SPEED_NAMES)


def test_big_endian_cdr_falls_back_to_rosbags() -> None:
    raw = bytearray(bagio.joint_state_cdr(T0, SPEED_NAMES, velocity=[1.0, 2.0]))
    # a big-endian encoding of the same message, as another DDS vendor might produce
    ts = bagio.typestore()
    msg = ts.deserialize_cdr(bytes(raw), JOINT_STATE_TYPE)
    be = bytes(ts.serialize_cdr(msg, JOINT_STATE_TYPE, little_endian=False))
    back = bagio._parse_joint_state(be)
    assert back.names == SPEED_NAMES and list(back.velocity) == [1.0, 2.0]
    assert back.stamp_ns == T0


def test_garbage_message_is_reported(tmp_path: Path) -> None:
    stamps, speeds, currents = _data(3)
    js = _js(stamps, SPEED_NAMES, "velocity", speeds)
    js[1] = (int(stamps[1]), b"\x00\x01\x00\x00\xff\xff")
    path = _bag(tmp_path, js, _js(stamps, CURRENT_NAMES, "effort", currents))
    with pytest.raises(BagError, match="/dvt/joint_states: message 1 is not a valid"):
        bagio.read_run(path)
