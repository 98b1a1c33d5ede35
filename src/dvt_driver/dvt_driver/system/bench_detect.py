"""``dvt-bench loop``: plant -> driver -> model node with its change detector; a change
injected into the running plant; detection delay, false alarms, the model node's latency.

    dvt-bench loop [--clean-seconds 60] [--after-seconds 15] [--change coulomb]
                   [--current 4.0] [--learn-s 20] [--json] [--keep DIR]

Starts ``dvt-plant`` (clean, ``--change-file``), ``dvt_driver_node`` (autostart) and
``dvt_model_node`` (detector on, ``detector.learn_s``), drives the motor at ``--current`` A,
waits until the detector tests (its reference window is over), lets it test the clean plant
for ``--clean-seconds``, then injects the change through the plant's runtime command (a change
file and SIGHUP: a step to the ``--change`` preset's friction) and watches for
``--after-seconds``. The change's time is the host time the plant wrote into ``truth.yaml``.
Prints (JSON with ``--json``)::

    {"detection_delay_s", "change_time_error_s", "alarm", "false_alarms", "clean_tested_s",
     "false_alarms_per_hour", "false_alarms_per_hour_upper95", "restored_s", "restored_note",
     "model_latency_ms": {"p50", "p99", "p999", "max"}, "model_dropped", "model_cpu_percent",
     ...}

* ``detection_delay_s``: the first alarm's detection stamp minus the change's time;
  ``change_time_error_s``: its estimated change time minus the change's time;
* ``false_alarms``: alarms on the clean segment (``clean_tested_s`` of testing);
  ``false_alarms_per_hour`` their rate and ``false_alarms_per_hour_upper95`` its one-sided 95 %
  Poisson bound. A clean segment of a minute cannot show a mean time between false alarms of
  hours: the figure that does is the detector's offline one (``docs/loop.md`` section 1);
* ``restored_s``: null here (``restored_note`` says why): the time from the change to a
  restored residual needs the identifier's supervisor, which ``dvt-bench loop
  --with-identifier`` runs through ``dvt-launch --supervise`` (:mod:`dvt_driver.system.bench_loop`);
* ``model_latency_ms``: per sample, reception of the model node's residual minus reception of
  the driver's ``/dvt/joint_states`` with the same stamp, both in this process (the node's
  processing plus one DDS hop), with the detector on; ``model_dropped``: samples published by the
  driver with no residual; ``model_cpu_percent``: the node's CPU over the run (100 = one core).

A benchmark, not a test: it prints what it measured.

Part of the integration layer (:mod:`dvt_driver.system`): the whole chain as processes
(``dvt-bench loop``; with ``--with-identifier`` :mod:`~dvt_driver.system.bench_loop` runs the
loop with the identifier instead).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dvt_driver.errors import DvtDriverError, LaunchError
from dvt_driver.run.bench import cpu_seconds, print_results
from dvt_driver.run.processes import SINGLE_THREAD_BLAS, Children, ready_line, script
from dvt_driver.signals import StopFlag
from dvt_model.contract import DIAGNOSTICS, JOINT_STATES
from dvt_model.recording import TRUTH_FILE, changes_applied, raw_stamp_ns, read_truth

LOOP_DOC = __doc__
"""The benchmark's description (``--help``)."""



class _LoopNode:
    """The loop bench's node: drives the motor, times samples and residuals, records alarms and
    the model node's diagnostics."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.experimental import EventsExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, String

        from dvt_model import rosutil
        from dvt_model.contract import (
            CHANGE_QOS,
            CMD_MOTOR_CURRENT,
            COMMAND_QOS,
            MODEL_CHANGE,
            MODEL_NODE,
            MODEL_RESIDUAL,
        )

        self._Float64 = Float64
        self.model_status = MODEL_NODE
        self.detector_status = f"{MODEL_NODE}: change detector"
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain,
                   signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node("dvt_bench_loop", context=self.ctx)
        n = self.node
        self.js_at: dict[int, float] = {}
        self.res_at: dict[int, float] = {}
        self.timing = False
        self.alarms: list[dict[str, Any]] = []
        self.detector: list[tuple[float, dict[str, str]]] = []
        self.model: list[tuple[float, dict[str, str]]] = []
        n.create_subscription(JointState, JOINT_STATES, self._on_js, rosutil.SENSOR_QOS,
                              raw=True)
        n.create_subscription(JointState, MODEL_RESIDUAL, self._on_res, rosutil.SENSOR_QOS,
                              raw=True)
        n.create_subscription(String, MODEL_CHANGE, self._on_change, rosutil.qos(CHANGE_QOS))
        n.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diag, 50)
        self.pub = n.create_publisher(Float64, CMD_MOTOR_CURRENT, rosutil.qos(COMMAND_QOS))
        self.executor = EventsExecutor(context=self.ctx)
        self.executor.add_node(n)
        self.current = 0.0
        self._next_cmd = 0.0

    def _on_js(self, raw: bytes) -> None:
        if self.timing:
            self.js_at[raw_stamp_ns(raw)] = time.perf_counter()

    def _on_res(self, raw: bytes) -> None:
        if self.timing:
            self.res_at[raw_stamp_ns(raw)] = time.perf_counter()

    def _on_change(self, msg: Any) -> None:
        self.alarms.append({**json.loads(msg.data), "received_unix": time.time()})

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if st.name == self.detector_status:
                self.detector.append((time.time(), values))
            elif st.name == self.model_status:
                self.model.append((time.time(), values))

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if now >= self._next_cmd:
                self.pub.publish(self._Float64(data=self.current))
                self._next_cmd = now + 0.1
            if now >= end:
                return
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - now)))

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _rms_of(values: dict[str, str]) -> float | None:
    try:
        return max(float(values["residual_rms_sun_shaft"]),
                   float(values["residual_rms_carrier3"]))
    except (KeyError, ValueError):
        return None


def run_loop(clean_seconds: float = 60.0, after_seconds: float = 15.0, change: str = "coulomb",
             current: float = 4.0, learn_s: float = 20.0,
             keep: Path | None = None, log: Any = None) -> dict[str, Any]:
    """Run the loop benchmark; returns the figures (see :data:`LOOP_DOC`)."""
    from dvt_driver.plant.hidden import changes_from_spec

    step = changes_from_spec(change, 0.0)[0]  # checked before anything starts
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(201 + os.getpid() % 30))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env.update(SINGLE_THREAD_BLAS)
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    work = Path(tempfile.mkdtemp(prefix="dvt-bench-loop-"))
    truth = work / TRUTH_FILE
    change_file = work / "change.yaml"
    mapping = step.to_mapping()
    mapping.pop("at")
    change_file.write_text(json.dumps(mapping))
    stop = StopFlag(escalate=False).install()
    kids = Children(work, env, stop, echo=log)
    node: _LoopNode | None = None
    out: dict[str, Any] = {}
    try:
        plant = kids.start("plant", [script("dvt-plant"), "--link", str(work / "plant.tty"),
                                     "--hidden", "none", "--seed", "0",
                                     "--truth-out", str(truth),
                                     "--change-file", str(change_file)])

        link = kids.wait_until("the plant's READY line", lambda: ready_line(plant.log), 30.0)
        kids.start("driver", [script("dvt_driver_node"), "--ros-args", "-p", f"port:={link}",
                              "-p", "autostart:=true"])
        node = _LoopNode(int(env["ROS_DOMAIN_ID"]))
        node.current = current
        ln = node

        def driver_up() -> bool:
            ln.spin(0.1)
            return ln.node.count_publishers(JOINT_STATES) > 0
        kids.wait_until("the driver's samples", driver_up, 30.0)
        node.spin(2.0)  # the machine spins up before the model node starts
        model = kids.start("model", [script("dvt_model_node"), "--ros-args",
                                     "-p", "params:=physical",
                                     "-p", f"detector.learn_s:={learn_s:g}"])

        def testing() -> bool:
            ln.spin(0.2)
            return any(v.get("state") == "testing" for _, v in ln.detector)
        kids.wait_until("the detector's reference window", testing, learn_s + 60.0)
        clean_from = next(t for t, v in node.detector if v.get("state") == "testing") - 1.0
        cpu0, wall0 = cpu_seconds(model.proc.pid), time.monotonic()
        node.timing = True
        node.spin(clean_seconds)
        os.kill(plant.proc.pid, signal.SIGHUP)  # the runtime change command

        def applied() -> list[dict[str, Any]]:
            ln.spin(0.05)
            return changes_applied(read_truth(work))
        entry = kids.wait_until("the plant's change in truth.yaml", applied, 10.0)[0]
        change_unix = float(entry["unix_s"])
        node.spin(after_seconds)
        node.timing = False
        cpu1, wall1 = cpu_seconds(model.proc.pid), time.monotonic()
        clean_s = max(0.0, change_unix - clean_from)
        false_alarms = [a for a in node.alarms if a["stamp_s"] < change_unix]
        after = [a for a in node.alarms if a["stamp_s"] >= change_unix]
        # latency: residual reception - sample reception, same stamp, this process's clock
        common = sorted(set(node.js_at) & set(node.res_at))
        lat = np.asarray([node.res_at[s] - node.js_at[s] for s in common]) * 1e3
        pre = [r for t, v in node.model if clean_from <= t < change_unix
               if (r := _rms_of(v)) is not None]
        restored: float | None = None
        note = ("the time to a restored residual needs the identifier's supervisor: "
                "dvt-bench loop --with-identifier (dvt_driver.system.bench_loop)")
        first = after[0] if after else None
        poisson95 = 2.9957  # one-sided 95 % upper bound of a Poisson mean after 0 events
        hours = clean_s / 3600.0
        out = {
            "detection_delay_s": round(first["stamp_s"] - change_unix, 3) if first else None,
            "change_time_error_s": round(first["change_s"] - change_unix, 3) if first else None,
            "alarm": first,
            "alarms_after_change": len(after),
            "change": {**entry, "preset": change},
            "false_alarms": len(false_alarms),
            "false_alarm_stamps": [a["stamp_s"] for a in false_alarms],
            "clean_tested_s": round(clean_s, 1),
            "false_alarms_per_hour": round(len(false_alarms) / hours, 2) if hours else None,
            "false_alarms_per_hour_upper95": (round(
                (poisson95 if not false_alarms else chi2_upper(len(false_alarms))) / hours, 1)
                if hours else None),
            "false_alarm_note": ("a clean segment of minutes bounds the rate only weakly; the "
                                 "detector's designed mean time between false alarms (4 h) and "
                                 "its offline measurement are in docs/loop.md section 1"),
            "restored_s": restored,
            "restored_note": note,
            "model_latency_ms": {
                "p50": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
                "p99": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
                "p999": round(float(np.percentile(lat, 99.9)), 3) if lat.size else None,
                "max": round(float(lat.max()), 3) if lat.size else None},
            "model_samples_timed": int(lat.size),
            "model_dropped": len(set(node.js_at) - set(node.res_at)),
            "model_cpu_percent": round(100.0 * (cpu1 - cpu0) / (wall1 - wall0), 1),
            "residual_rms_clean_rad_s": round(float(np.median(pre)), 4) if pre else None,
            "detector_status": node.detector[-1][1] if node.detector else {},
            "learn_s": learn_s,
            "load_average_1min": round(os.getloadavg()[0], 2),
        }
        kids.stop_all()
    finally:
        if node is not None:
            node.close()
        kids.stop_all()
        stop.restore()
    if keep is not None:
        shutil.copytree(work, keep)
    shutil.rmtree(work, ignore_errors=True)
    return out


def chi2_upper(n: int) -> float:
    """One-sided 95 % upper bound of a Poisson mean after ``n`` events."""
    from scipy.stats import chi2

    return float(chi2.ppf(0.95, 2 * (n + 1)) / 2.0)


def loop_main(argv: Sequence[str] | None = None) -> int:
    """``dvt-bench loop`` (argv without the ``loop`` word); returns the exit status."""
    p = argparse.ArgumentParser(
        prog="dvt-bench loop", description=LOOP_DOC.split("\n\n")[0],
        epilog="dvt-bench loop --with-identifier [--help]: the whole loop through dvt-launch "
               "--supervise, with the time to a restored residual (dvt_driver.system.bench_loop)")
    p.add_argument("--clean-seconds", type=float, default=60.0,
                   help="testing on the clean plant before the change [s] (60)")
    p.add_argument("--after-seconds", type=float, default=15.0,
                   help="watching after the change [s] (15)")
    p.add_argument("--change", default="coulomb",
                   help="the change: a step to this preset's friction (coulomb)")
    p.add_argument("--current", type=float, default=4.0, help="motor current [A] (4)")
    p.add_argument("--learn-s", type=float, default=20.0,
                   help="the detector's reference window [s] (20)")
    p.add_argument("--keep", default=None, help="copy the logs and truth to this new directory")
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    for name in ("clean_seconds", "after_seconds", "learn_s"):
        if not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')}: expected > 0, got {getattr(args, name)}")
    if args.keep is not None and Path(args.keep).exists():
        p.error(f"--keep: {args.keep} already exists")
    try:
        res = run_loop(args.clean_seconds, args.after_seconds, args.change, args.current,
                       args.learn_s,
                       Path(args.keep) if args.keep else None,
                       log=None if args.json else sys.stderr)
    except (LaunchError, DvtDriverError) as exc:
        print(f"dvt-bench loop: error: {exc}", file=sys.stderr)
        return 1
    print_results(res, args.json, 32)
    return 0


if __name__ == "__main__":
    sys.exit(loop_main())
