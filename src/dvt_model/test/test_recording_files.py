"""The YAML files of a recording (``metadata.yaml``, ``truth.yaml``, ``run.yaml``) and its raw
messages, each through its one reader in :mod:`dvt_model.recording`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvt_model import recording
from dvt_model.contract import (
    CMD_GEAR,
    CMD_MOTOR_CURRENT,
    COMMAND_PATTERN,
    CURRENTS,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    SPEED_NAMES,
)
from dvt_model.errors import BagError

T0 = 1_700_000_000_000_000_000
STRING = "std_msgs/msg/String"
FLOAT = "std_msgs/msg/Float64"


def _cdr(msgtype: str, **fields: object) -> bytes:
    ts = recording.typestore()
    return bytes(ts.serialize_cdr(ts.types[msgtype](**fields), msgtype))


def _bag(path: Path) -> Path:
    """Samples at T0 + k ms (k = 0..9), a motor-current command at +3 ms and a gear at +5 ms
    (log time = stamp), and a String on /notes at +1 ms."""
    js = [(T0 + k * 10**6, recording.joint_state_cdr(T0 + k * 10**6, SPEED_NAMES,
                                                     velocity=[float(k), -float(k)]))
          for k in range(10)]
    return recording.write_bag(path, [
        (JOINT_STATES, JOINT_STATE_TYPE, js),
        (CMD_MOTOR_CURRENT, FLOAT, [(T0 + 3 * 10**6, _cdr(FLOAT, data=1.5))]),
        (CMD_GEAR, "std_msgs/msg/UInt8", [(T0 + 5 * 10**6, _cdr("std_msgs/msg/UInt8",
                                                                 data=2))]),
        ("/notes", STRING, [(T0 + 10**6, _cdr(STRING, data="hello"))]),
    ])


def test_messages_in_log_time_order_with_topics_types_and_stamps(tmp_path: Path) -> None:
    path = _bag(tmp_path / "bag")
    with recording.BagMessages(path) as bag:
        assert bag.types == {JOINT_STATES: JOINT_STATE_TYPE, CMD_MOTOR_CURRENT: FLOAT,
                             CMD_GEAR: "std_msgs/msg/UInt8", "/notes": STRING}
        every = list(bag.messages())
        samples = list(bag.messages([JOINT_STATES]))
        commands = list(bag.messages(pattern=COMMAND_PATTERN))
        with pytest.raises(BagError, match=rf"topic\(s\) \['{CURRENTS}'\] not in the bag"):
            list(bag.messages([JOINT_STATES, CURRENTS]))
    assert [m.log_time_ns for m in every] == sorted(m.log_time_ns for m in every)
    assert len(every) == 13
    assert [recording.raw_stamp_ns(m.data) for m in samples] == [m.log_time_ns for m in samples]
    assert [m.topic for m in commands] == [CMD_MOTOR_CURRENT, CMD_GEAR]
    note = next(m for m in every if m.topic == "/notes")
    assert recording.decode(note).data == "hello"
    assert recording.first_log_time(path, COMMAND_PATTERN) == T0 + 3 * 10**6
    assert recording.first_log_time(path, "/nothing/*") is None


def test_messages_of_a_missing_or_killed_bag_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=rf"{tmp_path / 'none'}: no such bag directory"):
        recording.BagMessages(tmp_path / "none")
    path = _bag(tmp_path / "bag")
    (path / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="metadata.yaml is missing.*dvt-bag recover"):
        recording.first_log_time(path, COMMAND_PATTERN)
    bad = recording.BagMessage("/x", STRING, 5, b"\x00\x01\x00\x00\xff")
    with pytest.raises(BagError, match="topic /x: message at log time 5 ns is not a valid"):
        recording.decode(bad)


def test_metadata_is_read_once_for_everyone(tmp_path: Path) -> None:
    path = _bag(tmp_path / "bag")
    assert recording.is_bag(path) and not recording.is_bag(tmp_path)
    meta = recording.read_metadata(path)
    assert meta["storage_identifier"] == "mcap" and meta["message_count"] == 13
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: 3\n")
    with pytest.raises(BagError, match="metadata.yaml: no 'rosbag2_bagfile_information'"):
        recording.read_metadata(path)
    (path / "metadata.yaml").write_text("a: [\n")
    with pytest.raises(BagError, match="metadata.yaml: invalid YAML"):
        recording.read_metadata(path)
    with pytest.raises(BagError, match="metadata.yaml is missing"):
        recording.read_metadata(tmp_path)


def test_truth_and_run_info_round_trip_and_changes_applied(tmp_path: Path) -> None:
    truth = {"plant": {"params": "physical"},
             "changes_applied": [{"at_s": 3.0, "unix_s": 12.5, "change": {"at": 3.0}}]}
    recording.write_truth(tmp_path, truth)
    assert recording.read_truth(tmp_path) == truth
    assert recording.changes_applied(recording.read_truth(tmp_path))[0]["unix_s"] == 12.5
    assert recording.changes_applied(None) == []
    assert recording.changes_applied({"plant": {}}) == []
    with pytest.raises(BagError, match="changes_applied: expected a list of mappings"):
        recording.changes_applied({"changes_applied": [3]})
    assert recording.parse_truth("") == {}
    with pytest.raises(BagError, match="plant text: expected a mapping at top level, got list"):
        recording.parse_truth("- 1\n", "plant text")
    assert recording.read_run_info(tmp_path) is None
    recording.write_run_info(tmp_path, {"mode": "sim", "check": {"samples": 3}})
    assert recording.read_run_info(tmp_path) == {"mode": "sim", "check": {"samples": 3}}
    assert (tmp_path / recording.RUN_FILE).read_text().startswith("mode: sim\n")


def test_one_series_type_reads_what_it_writes(tmp_path: Path) -> None:
    stamps = T0 + np.arange(4, dtype=np.int64) * 10**6
    ser = recording.TopicSeries(stamps, ("a", "b"), velocity=np.ones((4, 2)))
    back = recording.read_topics(recording.write_topics(tmp_path / "bag", {"/s": ser}),
                                 ["/s"])["/s"]
    assert back.n == 4 and back.position is None and back.effort is None
    np.testing.assert_array_equal(back.field_array("velocity"), ser.velocity)
    with pytest.raises(KeyError, match="'name': not a JointState field"):
        back.field_array("name")
