"""``dvt-bench model``: the bench's prebuilt messages and its in-process stage profile."""

from __future__ import annotations

import pytest

from dvt_model import bench
from dvt_model.contract import SPEED_NAMES
from dvt_model.recording.cdr import joint_state_cdr, parse_joint_state, restamp


def test_restamp_changes_only_the_stamp() -> None:
    raw = joint_state_cdr(5, SPEED_NAMES, velocity=(100.0, 20.0))
    out = parse_joint_state(restamp(raw, 1_700_000_000_123_456_789))
    assert out.stamp_ns == 1_700_000_000_123_456_789
    assert out.names == SPEED_NAMES and out.velocity == (100.0, 20.0)
    assert restamp(raw, 5) == raw


def test_in_process_profile_reports_every_stage_with_the_detector_testing() -> None:
    pytest.importorskip("rclpy")
    out = bench.profile(samples=6000, learn_s=1.0)
    assert set(out["cpu_us"]) == set(bench.STAGES)
    for stage in bench.STAGES:
        figures = out["cpu_us"][stage]
        assert 0.0 <= figures["median"] <= figures["p99"] <= figures["max"]
    assert out["cpu_us"]["predictor"]["median"] > 0.0
    assert out["detector"]["enabled"] and out["detector"]["state"] == "testing"
    assert int(out["detector"]["tested"]) > 0
