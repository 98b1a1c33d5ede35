"""Unit tests of the recorder's pure subscription policy and its stop flag (no ROS)."""

from __future__ import annotations

import signal

from dvt_driver.recording.policy import DEFAULT_TOPICS, choose_qos, match_topics, needs_weaker
from dvt_driver.signals import StopFlag
from dvt_model.contract import DEFAULT_RECORD_TOPICS

JS = "sensor_msgs/msg/JointState"


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


def test_recorder_stop_flag_turns_signals_into_a_flag() -> None:
    # the handler before: Python's default_int_handler, or SIG_IGN when the suite was started
    # with SIGINT ignored (a non-interactive shell's background job, `nohup cmd &`)
    before = signal.getsignal(signal.SIGINT)
    flag = StopFlag().install()
    try:
        assert not flag
        assert signal.getsignal(signal.SIGINT) is flag
        signal.raise_signal(signal.SIGINT)  # no KeyboardInterrupt
        assert flag and flag.received == signal.SIGINT
    finally:
        flag.restore()
    assert signal.getsignal(signal.SIGINT) is before


def test_default_topics_are_the_contracts() -> None:
    assert DEFAULT_TOPICS == DEFAULT_RECORD_TOPICS
    chosen, problems = match_topics(DEFAULT_TOPICS, [
        ("/dvt/joint_states", [JS]), ("/dvt/currents", [JS]),
        ("/dvt/model/residual", [JS]), ("/dvt/cmd/gear", ["std_msgs/msg/UInt8"]),
        ("/diagnostics", ["diagnostic_msgs/msg/DiagnosticArray"]),
        ("/rosout", ["rcl_interfaces/msg/Log"]), ("/parameter_events", ["x/msg/Y"])])
    assert set(chosen) == {"/dvt/joint_states", "/dvt/currents", "/dvt/model/residual",
                           "/dvt/cmd/gear", "/diagnostics"}
    assert problems == []


def test_needs_weaker_only_when_a_publisher_needs_less() -> None:
    assert needs_weaker(("best_effort", "volatile"), ("reliable", "volatile"))
    assert needs_weaker(("reliable", "volatile"), ("reliable", "transient_local"))
    assert not needs_weaker(("reliable", "volatile"), ("best_effort", "volatile"))
    assert not needs_weaker(("reliable", "transient_local"), ("reliable", "volatile"))
    assert not needs_weaker(("best_effort", "volatile"), ("best_effort", "volatile"))
