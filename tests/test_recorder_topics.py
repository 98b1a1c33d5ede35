"""Topic level: ``dvt-recorder`` records live JointState streams (real processes, real DDS).

1. Clean stop: 2000 samples at ~500 Hz on ``/dvt/joint_states`` and ``/dvt/currents``, SIGINT,
   and the bag holds every one of them.
2. Crash: SIGKILL mid-run, ``dvt-bag recover``; the bag is readable, holds a gap-free prefix of
   what was published, and misses at most the last second.
3. Rolling mode: the recorder keeps a ring of segments; a JSON request on
   ``/dvt/recorder/snapshot`` writes a window spanning several segments as a normal bag that
   ``read_run`` reads contiguous, with no sample missing; the answer comes on
   ``/dvt/recorder/snapshot_result``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String

from conftest import Procs, script, wait_for
from dvt_driver.recording.node import SNAPSHOT_REQUEST, SNAPSHOT_RESULT
from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATES, SPEED_NAMES
from dvt_model.recording import read_run
from dvt_model.recording.messages import BagMessages, decode

pytestmark = pytest.mark.ros

RATE = 500.0  # Hz
N = 2000
T0 = 1_700_000_000 * 10**9
# What the driver uses for the high-rate streams (see dvt_driver.recording.node docstring).
DRIVER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)


class _Publisher:
    """Publishes contract sample pairs (identical stamps) from the test process."""

    def __init__(self, ctx: Any, qos: QoSProfile = DRIVER_QOS) -> None:
        self.node = rclpy.create_node("test_sample_publisher", context=ctx)
        self.js = self.node.create_publisher(JointState, JOINT_STATES, qos)
        self.cu = self.node.create_publisher(JointState, CURRENTS, qos)

    def wait_matched(self, timeout: float = 30.0) -> None:
        wait_for(lambda: self.js.get_subscription_count() >= 1
                 and self.cu.get_subscription_count() >= 1, timeout,
                 "the recorder to subscribe to both topics")

    @staticmethod
    def stamp(i: int) -> int:
        return T0 + i * 10**9 // int(RATE)

    def publish(self, i: int) -> None:
        st = self.stamp(i)
        js = JointState()
        js.header.stamp.sec, js.header.stamp.nanosec = divmod(st, 10**9)
        js.name = list(SPEED_NAMES)
        js.velocity = [float(i), -0.5 * i]
        cu = JointState()
        cu.header = js.header
        cu.name = list(CURRENT_NAMES)
        cu.effort = [0.001 * i, 0.0, 0.5, 1.0]
        self.js.publish(js)
        self.cu.publish(cu)

    def run(self, n: int, on_sample: Any = None) -> None:
        start = time.monotonic()
        for i in range(n):
            self.publish(i)
            if on_sample is not None:
                on_sample(i)
            delay = start + (i + 1) / RATE - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def wait_acked(self, timeout: float = 10.0) -> bool:
        return bool(self.js.wait_for_all_acked(Duration(seconds=timeout))
                    and self.cu.wait_for_all_acked(Duration(seconds=timeout)))

    def close(self) -> None:
        self.node.destroy_node()


def _start_recorder(procs: Procs, path: Path) -> subprocess.Popen[bytes]:
    return procs.start("dvt-recorder", "--ros-args", "-p", f"output:={path}")


def test_recorder_keeps_every_sample(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    bag = tmp_path / "run1"
    rec = _start_recorder(procs, bag)
    pub = _Publisher(rclpy_context)
    diag = pub.node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    cmd = pub.node.create_publisher(Float64, "/dvt/cmd/test_setpoint", 10)
    try:
        pub.wait_matched()
        wait_for(lambda: diag.get_subscription_count() >= 1 and cmd.get_subscription_count() >= 1,
                 30.0, "the recorder to subscribe to /diagnostics and /dvt/cmd/*")
        for k in range(5):
            d = DiagnosticArray()
            d.status = [DiagnosticStatus(level=DiagnosticStatus.OK, name="dvt: test",
                                         message=f"ok {k}")]
            diag.publish(d)
            cmd.publish(Float64(data=float(k)))
        pub.run(N)
        assert pub.wait_acked(), "the recorder did not acknowledge every sample"
        assert diag.wait_for_all_acked(Duration(seconds=10))
        assert cmd.wait_for_all_acked(Duration(seconds=10))
    finally:
        pub.close()
    assert procs.stop(rec) == 0, procs.log(rec)
    log = procs.log(rec)
    assert f"{JOINT_STATES}={N}" in log and f"{CURRENTS}={N}" in log, log

    run = read_run(bag)
    assert run.n == N
    assert run.unmatched == 0
    np.testing.assert_array_equal(run.stamps_ns, [pub.stamp(i) for i in range(N)])
    np.testing.assert_array_equal(run.speeds[:, 0], np.arange(N, dtype=float))
    np.testing.assert_allclose(run.currents[:, 0], 0.001 * np.arange(N))
    with BagMessages(bag) as reader:
        msgs: list[Any] = [decode(m) for m in reader.messages(["/diagnostics"])]
        cmds = [len(list(reader.messages(["/dvt/cmd/test_setpoint"])))]
    assert [m.status[0].message for m in msgs] == [f"ok {k}" for k in range(5)]
    assert cmds == [5]


def test_killed_recorder_is_recovered(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    bag = tmp_path / "run2"
    rec = _start_recorder(procs, bag)
    kill_at = 1500
    pub = _Publisher(rclpy_context)

    def kill(i: int) -> None:
        if i == kill_at - 1:
            os.killpg(rec.pid, signal.SIGKILL)

    try:
        pub.wait_matched()
        pub.run(N, on_sample=kill)  # keeps publishing after the kill, to nobody
    finally:
        pub.close()
    rec.wait(timeout=10)
    assert rec.returncode == -signal.SIGKILL
    assert not (bag / "metadata.yaml").exists()

    out = subprocess.run([script("dvt-bag"), "recover", str(bag)], capture_output=True,
                         text=True, timeout=60, env=procs.env)
    assert out.returncode == 0, out.stderr
    assert "recovered" in out.stdout

    run = read_run(bag)
    assert run.n > 0
    # a gap-free prefix of what was published ...
    np.testing.assert_array_equal(run.stamps_ns, [pub.stamp(i) for i in range(run.n)])
    # ... missing at most the last second before the kill
    lost = kill_at - run.n
    print(f"recovered {run.n} of {kill_at} samples published before the kill")
    assert 0 <= lost <= RATE, f"lost {lost} samples (> 1 s at {RATE} Hz)"
    assert run.unmatched <= 1

    info = subprocess.run([script("dvt-bag"), "info", str(bag)], capture_output=True,
                          text=True, timeout=60, env=procs.env)
    assert info.returncode == 0 and JOINT_STATES in info.stdout


def test_best_effort_publisher_is_recorded(procs: Procs, rclpy_context: Any,
                                           tmp_path: Path) -> None:
    """A sensor-data (BEST_EFFORT) publisher: the recorder adapts its QoS and still records.

    Best-effort delivery gives no guarantee, so up to 5 % loss is tolerated here; nothing is
    lost on an idle machine.
    """
    from rclpy.qos import qos_profile_sensor_data

    bag = tmp_path / "run3"
    rec = _start_recorder(procs, bag)
    pub = _Publisher(rclpy_context, qos_profile_sensor_data)
    n = 500
    try:
        pub.wait_matched()
        pub.run(n)
        time.sleep(0.5)  # no acknowledgements with best effort: give delivery a moment
    finally:
        pub.close()
    assert procs.stop(rec) == 0
    log = procs.log(rec)
    assert "best_effort/volatile" in log, log
    run = read_run(bag)
    assert run.n >= 0.95 * n, f"recorded {run.n} of {n}"
    assert set(run.stamps_ns.tolist()) <= {_Publisher.stamp(i) for i in range(n)}


class _NowPublisher(_Publisher):
    """Stamps at the host's ROS time (as the driver's clock mapping does), 500 Hz."""

    base = time.time_ns() // 10**6 * 10**6

    @staticmethod
    def stamp(i: int) -> int:
        return _NowPublisher.base + i * 10**9 // int(RATE)


def test_rolling_recorder_writes_a_window_as_a_bag(procs: Procs, rclpy_context: Any,
                                                    tmp_path: Path) -> None:
    ring = tmp_path / "ring"
    rec = procs.start("dvt-recorder", "--ros-args", "-p", f"output:={ring}",
                      "-p", "ring_minutes:=1.0", "-p", "ring_segment_seconds:=0.5",
                      "-p", "snapshot_margin_s:=0.5")
    pub = _NowPublisher(rclpy_context)
    answers: list[dict[str, Any]] = []

    def on_result(msg: String) -> None:
        answers.append(json.loads(msg.data))

    req = pub.node.create_publisher(String, SNAPSHOT_REQUEST, QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
    pub.node.create_subscription(
        String, SNAPSHOT_RESULT, on_result,
        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL))
    n = 2000
    out = tmp_path / "window"
    try:
        pub.wait_matched()
        wait_for(lambda: req.get_subscription_count() >= 1, 30.0,
                 "the recorder to subscribe to the snapshot request")
        # request the window while it is still in the future: served once it has passed
        _NowPublisher.base = time.time_ns() // 10**6 * 10**6 + 10**8  # first stamp in 0.1 s
        lo, hi = 300, 1700
        req.publish(String(data=json.dumps({"from": pub.stamp(lo) * 1e-9,
                                            "to": pub.stamp(hi) * 1e-9,
                                            "out": str(out), "id": "w1"})))
        req.publish(String(data=json.dumps({"from": 1.0, "to": 0.5, "out": "x", "id": "bad"})))
        while time.time_ns() < _NowPublisher.base:
            time.sleep(0.01)
        pub.run(n)
        assert pub.wait_acked(), "the recorder did not acknowledge every sample"

        executor = SingleThreadedExecutor(context=rclpy_context)
        executor.add_node(pub.node)

        def answered() -> bool:
            executor.spin_once(timeout_sec=0.05)
            return {a.get("id") for a in answers} >= {"w1", "bad"}

        wait_for(answered, 60.0, "both snapshot answers")
    finally:
        pub.close()
    assert procs.stop(rec) == 0, procs.log(rec)
    by_id = {a["id"]: a for a in answers}
    assert by_id["bad"]["ok"] is False and "'to'" in by_id["bad"]["error"]
    good = by_id["w1"]
    assert good["ok"] is True, good
    assert good["segments"] >= 3 and not good["truncated"], good
    segments = sorted(p for p in ring.iterdir() if p.name.startswith("seg-"))
    assert len(segments) >= 6  # 4 s of data in 0.5 s segments
    run = read_run(out)
    assert run.unmatched == 0
    np.testing.assert_array_equal(run.stamps_ns, [pub.stamp(i) for i in range(lo, hi + 1)])
    np.testing.assert_array_equal(run.speeds[:, 0], np.arange(lo, hi + 1, dtype=float))
    assert good["counts"][JOINT_STATES] == hi - lo + 1 == good["counts"][CURRENTS]
