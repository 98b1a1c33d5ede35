"""Topic level: a change injected into the running plant is detected by the model node.

Real processes: ``dvt-plant``, clean, with a change scheduled by ``--change-at 50:coulomb`` (a
step to the ``coulomb`` preset's friction on the sun shaft and carrier 3 at plant time 50 s,
written into ``truth.yaml`` with the host time of the sample at which it took effect), ``dvt_driver_node`` (autostart) and ``dvt_model_node``
(physical model, change detector with a 5 s reference window). This process drives the motor
at a constant current (the friction only shows on a turning machine) and listens to
``/dvt/model/change``, ``/diagnostics`` and ``/dvt/model/residual``.

Checked: no alarm on the clean segment between the end of the detector's reference window and
the change (at least 8 s of testing); an alarm after the change with an estimated change time
within [-0.5, +1.0] s of the truth's time (the residual grows with the mechanical time constants
of the transmission, 0.1-0.5 s, so the CUSUM's last zero lies a little after the step; it can
lie a little before it through noise) and a detection delay below 3 s; the alarm as a WARN
``dvt_model: change detector`` status on ``/diagnostics``; the model node keeps publishing
residuals after the alarm.
"""

from __future__ import annotations

import json
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
from dvt_model.node import DETECTOR_STATUS

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

CHANGE_AT = 50.0  # plant time of the scheduled friction step [s]
LEARN_S = 5.0
MOTOR_CURRENT = 4.0  # A: the sun runs at about 147 rad/s, carrier 3 at about 36 rad/s
CHANGE_TOL = (-0.5, 1.0)  # estimated change time - true change time [s]
MAX_DELAY = 3.0  # detection stamp - true change time [s]
MIN_CLEAN_S = 8.0  # clean testing before the change [s]


class Listener:
    """The test's node: drives the motor, records alarms, detector statuses, residual count."""

    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("change_detection_test", context=ctx)
        self.exe = EventsExecutor(context=ctx)
        self.exe.add_node(self.node)
        self.alarms: list[tuple[float, dict[str, Any]]] = []  # (receive time, alarm)
        self.statuses: list[tuple[float, int, str, dict[str, str]]] = []
        self.residuals = 0
        self.last_residual = 0.0
        n = self.node
        n.create_subscription(String, contract.MODEL_CHANGE, self._on_change,
                              rosutil.qos(contract.CHANGE_QOS))
        n.create_subscription(DiagnosticArray, contract.DIAGNOSTICS, self._on_diag, 50)
        n.create_subscription(JointState, contract.MODEL_RESIDUAL, self._on_res,
                              rosutil.SENSOR_QOS, raw=True)
        self.pub_current = n.create_publisher(Float64, contract.CMD_MOTOR_CURRENT,
                                              rosutil.COMMAND_QOS)

    def _on_change(self, msg: String) -> None:
        self.alarms.append((time.time(), json.loads(msg.data)))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == DETECTOR_STATUS:
                self.statuses.append((time.time(), st.level[0], st.message,
                                      {kv.key: kv.value for kv in st.values}))

    def _on_res(self, raw: bytes) -> None:
        self.residuals += 1
        self.last_residual = time.time()

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
    if not truth.exists():
        return []
    doc = yaml.safe_load(truth.read_text()) or {}
    return list(doc.get("changes_applied") or [])


def test_friction_step_is_detected(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    truth = tmp_path / "truth.yaml"
    link = tmp_path / "plant.tty"
    plant = procs.start("dvt-plant", "--link", str(link), "--hidden", "none",
                        "--change-at", f"{CHANGE_AT:g}:coulomb", "--seed", "3",
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
        model = procs.start("dvt_model_node", "--ros-args", "-p", "params:=physical",
                            "-p", f"detector.learn_s:={LEARN_S:g}")
        lis.run(30.0, until=lambda: lis.residuals > 0)
        assert lis.residuals > 0, procs.log(model)
        # the clean segment: the detector tests until the change
        deadline = started_unix + CHANGE_AT + 30.0
        lis.run(max(0.0, deadline - time.time()), until=lambda: bool(_applied(truth)))
        applied = _applied(truth)
        assert applied, "the plant did not apply its scheduled change"
        change_unix = float(applied[0]["unix_s"])
        assert applied[0]["at_s"] == pytest.approx(CHANGE_AT, abs=0.002)
        testing = [(t, v) for t, _, _, v in lis.statuses
                   if v.get("state") == "testing" and t < change_unix]
        for t, lvl, msg, v in lis.statuses:  # the timeline, shown on failure
            print(f"{t - started_unix:7.2f} s: {lvl} {msg}: samples {v.get('samples')}")
        assert testing, f"the detector was not testing before the change: {lis.statuses[-3:]}"
        clean_from = testing[0][0] - 1.0  # statuses come at 1 Hz
        assert change_unix - clean_from >= MIN_CLEAN_S, (
            f"only {change_unix - clean_from:.1f} s of clean testing before the change")
        early = [a for t, a in lis.alarms if a["stamp_s"] < change_unix]
        assert not early, f"false alarm(s) on the clean plant: {early}"
        # the change
        lis.run(MAX_DELAY + 5.0, until=lambda: bool(lis.alarms))
        assert lis.alarms, f"no alarm within {MAX_DELAY + 5:g} s of the change; statuses: " \
            f"{lis.statuses[-2:]}"
        alarm = lis.alarms[0][1]
        offset = alarm["change_s"] - change_unix
        delay = alarm["stamp_s"] - change_unix
        print(f"\nchange at unix {change_unix:.3f}: alarm on {alarm['name']} "
              f"(direction {alarm['direction']:+d}, shift {alarm['shift']:.3g} rad/s), "
              f"estimated change time {offset:+.3f} s, detection delay {delay:.3f} s, "
              f"clean testing before it {change_unix - clean_from:.1f} s; detector before the "
              f"change: {testing[-1][1]}")
        assert CHANGE_TOL[0] <= offset <= CHANGE_TOL[1], alarm
        assert 0.0 < delay <= MAX_DELAY, alarm
        assert alarm["direction"] == -1, alarm  # friction: measured below predicted
        # /diagnostics shows it, and the node keeps running
        lis.run(3.0, until=lambda: any(lvl == rosutil.WARN and "change on" in msg
                                       for _, lvl, msg, _ in lis.statuses))
        assert any(lvl == rosutil.WARN and "change on" in msg
                   for _, lvl, msg, _ in lis.statuses), lis.statuses[-3:]
        n_before = lis.residuals
        lis.run(2.0)
        assert lis.residuals - n_before > 1000, "the model node stopped publishing"
        assert model.poll() is None, procs.log(model)
    finally:
        lis.close()
