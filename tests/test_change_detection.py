"""Topic level: a change injected into the running plant is detected by the model node.

Real processes: ``dvt-plant``, clean, with a change in ``--change-file`` (a step to the
``coulomb`` preset's friction on the sun shaft and carrier 3) that the test triggers with SIGHUP
(the plant's runtime command) once the detector has tested the clean plant for 8 s; the plant
writes the change into ``truth.yaml`` with the host time of the sample at which it took effect
(a scheduled change, ``--change-at``/``changes:``, goes through the same code: unit tests and
``tests/test_launch_chain.py``),
``dvt_driver_node`` (autostart) and ``dvt_model_node`` (physical model, change detector with a
10 s reference window). This process drives the motor
at a constant current (the friction only shows on a turning machine) and listens to
``/dvt/model/change`` and ``/diagnostics`` (not to the 1 kHz topics: on a shared 2-core machine
this process must not take the CPU the chain needs).

Checked: no alarm on the clean segment between the end of the detector's reference window and
the change (at least 8 s of testing); an alarm after the change with a detection delay below
3 s and an estimated change time (the first block after the alarming CUSUM's last zero) not
before the detector began testing (the end of its reference window) and at most 0.25 s after
the truth; the alarm as a WARN
``dvt_model: change detector`` status on ``/diagnostics``; the model node keeps publishing
residuals after the alarm.

What the change-time estimate achieves was measured on this scenario offline, on the node's
exact path without ROS (``PlantSim`` clean at 4 A -> ``Predictor`` -> ``ResidualBlocks`` ->
``ChangeDetector``, ``learn_s`` 10, the step after 8-12 s of clean testing; 185 plants, seeds
1-185; 6 of them raised a false alarm before the step, see ``tests/test_detector_clean_plant.py``):
of the 179 others every one detected the step (delay 0.02-0.39 s), never late (estimate minus
truth at most 0.00 s), median -0.21 s; within [-3, 0] s in 159 of 179 (0.89, Clopper-Pearson
95 % 0.83-0.93), below -5 s in 13, below -8 s in 3, earliest -10.7 s (a CUSUM that had wandered
above zero since the start of testing; the residual is strongly coloured, carrier 3 phi about
0.8-0.9 per 10-ms block). The [-3, +1] s once promised here holds in about nine runs of ten, so
a single run cannot assert it: the early side is bounded by what the estimate can be (not
before the detector began testing), the late side by the measured 0 s plus 0.25 s for the
driver's clock mapping (the estimate is a block start, 10 ms, in the driver's stamps; the truth
is the plant's host time of the changed sample); the fraction within [-3, +0.25] s is checked
statistically offline (``tests/test_detector_clean_plant.py``, slow). Live runs on this machine
(loaded by other jobs): -0.06, -0.09, -0.86, -0.83 s and, this version, -1.69 s.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.experimental import EventsExecutor
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String

from conftest import Procs, wait_for
from dvt_model import contract, rosutil
from dvt_model.config import detector_config
from dvt_model.contract import DETECTOR_PREFIX
from dvt_model.node import DETECTOR_STATUS

pytestmark = [pytest.mark.ros, pytest.mark.timeout(150)]  # about 45 s when the machine keeps up

START_BUDGET = 75.0  # the chain must be up and the detector testing by then [s]
LEARN_S = 10.0
MOTOR_CURRENT = 4.0  # A: the sun runs at about 147 rad/s, carrier 3 at about 36 rad/s
MIN_CLEAN_S = 8.0  # clean testing before the change [s]
LATE_TOL = 0.25
"""Latest estimated change time after the true one [s]: measured 0.00 s at most (179 offline
runs, module docstring), plus the driver's clock mapping. The early side is the start of the
detector's testing: the estimate is early by more than 3 s in about one run in ten (the CUSUM
had wandered above zero before the step), down to the whole clean segment; the fraction is
checked over 40 plants offline (tests/test_detector_clean_plant.py)."""
MAX_DELAY = 3.0  # detection stamp - true change time [s]
SETUP = detector_config({f"{DETECTOR_PREFIX}.learn_s": LEARN_S})
"""The model node's detector settings in this test (settling after the first anchor, window)."""


class Listener:
    """The test's node: drives the motor, records alarms, detector statuses, residual count."""

    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("change_detection_test", context=ctx)
        self.exe = EventsExecutor(context=ctx)
        self.exe.add_node(self.node)
        self.alarms: list[tuple[float, dict[str, Any]]] = []  # (receive time, alarm)
        self.statuses: list[tuple[float, int, str, dict[str, str]]] = []
        self.published = 0  # residuals published by the model node (its diagnostics)
        n = self.node
        n.create_subscription(String, contract.MODEL_CHANGE, self._on_change,
                              rosutil.qos(contract.CHANGE_QOS))
        n.create_subscription(DiagnosticArray, contract.DIAGNOSTICS, self._on_diag, 50)
        self.pub_current = n.create_publisher(Float64, contract.CMD_MOTOR_CURRENT,
                                              rosutil.COMMAND_QOS)

    def _on_change(self, msg: String) -> None:
        self.alarms.append((time.time(), json.loads(msg.data)))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == contract.MODEL_NODE:
                for kv in st.values:
                    if kv.key == "published":
                        self.published = int(kv.value)
            if st.name == DETECTOR_STATUS:
                self.statuses.append((time.time(), st.level[0], st.message,
                                      {kv.key: kv.value for kv in st.values}))

    def run(self, seconds: float, until: Any = None) -> None:
        """Spin for ``seconds`` (or until ``until()``), publishing the motor current at 10 Hz."""
        end = time.monotonic() + seconds
        next_cmd = 0.0
        while time.monotonic() < end:
            if time.monotonic() >= next_cmd:
                self.pub_current.publish(Float64(data=MOTOR_CURRENT))
                next_cmd = time.monotonic() + 0.1
            self.exe.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return

    def close(self) -> None:
        self.exe.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


def _applied(truth: Path) -> list[dict[str, Any]]:
    """The changes the plant applied, read through the recording's one truth reader."""
    from dvt_model.recording import changes_applied, read_truth

    return changes_applied(read_truth(truth.parent))


def test_friction_step_is_detected(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    truth = tmp_path / "truth.yaml"
    link = tmp_path / "plant.tty"
    change = tmp_path / "change.yaml"
    change.write_text(yaml.safe_dump({"coulomb": {"sun": 0.05, "carrier3": 0.2},
                                      "note": "friction step (test)"}))
    plant = procs.start("dvt-plant", "--link", str(link), "--hidden", "none",
                        "--change-file", str(change), "--seed", "3",
                        "--truth-out", str(truth))
    wait_for(lambda: "READY" in procs.log(plant), 30, "the plant's READY line")
    started_unix = time.time()
    procs.start("dvt_driver_node", "--ros-args", "-p", f"port:={link}", "-p", "autostart:=true")
    lis = Listener(rclpy_context)
    try:
        # drive the motor before the model node starts: its reference window sees the
        # machine turning steadily
        lis.run(30.0, until=lambda: lis.node.count_publishers(contract.JOINT_STATES) > 0
                and lis.pub_current.get_subscription_count() > 0)
        lis.run(2.0)
        model_started = time.time()  # the node's first sample is stamped after this
        model = procs.start("dvt_model_node", "--ros-args", "-p", "params:=physical",
                            "-p", f"detector.learn_s:={LEARN_S:g}")

        def clean_long_enough() -> bool:
            testing = [t for t, _, _, v in lis.statuses if v.get("state") == "testing"]
            return bool(testing) and time.time() - (testing[0] - 1.0) >= MIN_CLEAN_S

        lis.run(max(0.0, started_unix + START_BUDGET - time.time()), until=clean_long_enough)
        for t, lvl, msg, v in lis.statuses:  # the timeline, shown on failure
            print(f"{t - started_unix:7.2f} s: {lvl} {msg}: samples {v.get('samples')}")
        assert clean_long_enough(), (
            f"the detector did not test {MIN_CLEAN_S:g} s within {START_BUDGET:g} s of the "
            f"start (a machine too loaded to run the chain in real time?): {lis.statuses[-2:]}")
        assert model.poll() is None, procs.log(model)
        os.kill(plant.pid, signal.SIGHUP)  # the plant's runtime change command
        lis.run(10.0, until=lambda: bool(_applied(truth)))
        applied = _applied(truth)
        assert applied, "the plant did not apply the change"
        change_unix = float(applied[0]["unix_s"])
        assert applied[0]["change"]["note"] == "friction step (test)"
        testing = [(t, v) for t, _, _, v in lis.statuses
                   if v.get("state") == "testing" and t < change_unix]
        clean_from = testing[0][0] - 1.0  # statuses come at 1 Hz
        # the change (alarms are told apart by their stamps, not by when they arrive)
        lis.run(MAX_DELAY + 8.0, until=lambda: any(a["stamp_s"] >= change_unix
                                                   for _, a in lis.alarms))
        early = [a for _, a in lis.alarms if a["stamp_s"] < change_unix]
        assert not early, f"false alarm(s) on the clean plant: {early}"
        after = [a for _, a in lis.alarms if a["stamp_s"] >= change_unix]
        assert after, f"no alarm within {MAX_DELAY + 8:g} s of the change; statuses: " \
            f"{lis.statuses[-2:]}"
        alarm = after[0]
        offset = alarm["change_s"] - change_unix
        delay = alarm["stamp_s"] - change_unix
        print(f"\nchange at unix {change_unix:.3f}: alarm on {alarm['name']} "
              f"(direction {alarm['direction']:+d}, shift {alarm['shift']:.3g} rad/s), "
              f"estimated change time {offset:+.3f} s, detection delay {delay:.3f} s, "
              f"clean testing before it {change_unix - clean_from:.1f} s; detector before the "
              f"change: {testing[-1][1]}")
        # within the detector's testing (in data time: after the settling and the reference
        # window that follow the node's first sample), at most LATE_TOL after the change
        tested_from = model_started + SETUP.settle_s + SETUP.config.learn_s
        assert tested_from - 0.5 <= alarm["change_s"] <= change_unix + LATE_TOL, (
            f"estimated change time {offset:+.3f} s outside [{tested_from - 0.5 - change_unix:+.2f}"
            f", {LATE_TOL:+.2f}] s", alarm)
        assert 0.0 < delay <= MAX_DELAY, alarm
        assert alarm["direction"] == -1, alarm  # friction: measured below predicted
        # /diagnostics shows it, and the node keeps running
        lis.run(15.0, until=lambda: any(lvl == rosutil.WARN and "change on" in msg
                                       for _, lvl, msg, _ in lis.statuses))
        assert any(lvl == rosutil.WARN and "change on" in msg
                   for _, lvl, msg, _ in lis.statuses), lis.statuses[-3:]
        got: list[float] = []  # residuals after the alarm (subscribed only now: cheap)
        lis.node.create_subscription(JointState, contract.MODEL_RESIDUAL,
                                     lambda raw: got.append(time.time()), rosutil.SENSOR_QOS,
                                     raw=True)
        lis.run(20.0, until=lambda: len(got) >= 500)
        assert len(got) >= 500, f"the model node stopped publishing ({len(got)} residuals)"
        assert model.poll() is None, procs.log(model)
    finally:
        lis.close()
