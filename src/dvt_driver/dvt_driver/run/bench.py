"""``dvt-bench link``: drive plant -> driver -> recorder at a fixed rate and measure it.

    dvt-bench link [--rate 1000] [--seconds 30] [--hidden none] [--json] [--keep DIR]

Starts ``dvt-plant`` (``--rate``), ``dvt_driver_node`` (not autostarted) and ``dvt-recorder``
(``/dvt/joint_states`` and ``/dvt/currents``, the recorder's default settings) as processes.
The bench configures the driver through its lifecycle services, waits until the recorder has
subscribed, activates the driver, lets samples flow for ``--seconds``, deactivates the driver
(publishing stops), lets the recorder drain and close the bag, and reads the bag back. Prints
(JSON with ``--json``)::

    {"rate_hz", "sent", "recorded", "lost", "crc_errors", "latency_ms": {"p50", "p99"},
     "cpu_percent", ...}

* ``rate_hz``: recorded samples per second of controller time (first to last stamp);
* ``sent``: samples the controller sent while the driver was active: published by the driver
  plus those the driver found missing from the sequence numbers (serial losses);
* ``recorded``: ``/dvt/joint_states`` messages in the bag; ``lost = sent - recorded``;
* ``crc_errors``: frames the driver dropped for a bad CRC (its diagnostics);
* ``latency_ms``: recorder reception time (the bag's log time) minus the sample's stamp. The
  stamp is the controller's sample instant mapped to host time by the driver's clock mapping,
  which aligns it with the fastest serial delivery seen in its window, so this is the latency
  from sample to recorder above the minimum serial transfer time (about 0.5 ms on a 921600 baud
  line; a pty is faster);
* ``cpu_percent``: CPU time of the plant, driver and recorder processes over the active window
  divided by its wall time (100 = one core); ``cpu_percent_by_process`` splits it.

Extra keys: ``requested_rate_hz``, ``seconds``, ``published``, ``serial_lost``, ``bag_gaps``
(samples missing between consecutive stamps in the bag), ``frames_bad``, ``latency_ms.max``.
A benchmark, not a test: it prints what it measured.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dvt_driver.errors import LaunchError
from dvt_driver.run.processes import SINGLE_THREAD_BLAS, Children, ready_line, script
from dvt_driver.signals import StopFlag
from dvt_model.contract import CURRENTS, DIAGNOSTICS, JOINT_STATES
from dvt_model.contract import DRIVER_NODE as DRIVER
from dvt_model.recording import (
    TRUTH_FILE,
    BagMessages,
    raw_stamp_ns,
)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` [s] (0 if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


class _BenchNode:
    """Lifecycle client and diagnostics listener of the bench (rclpy, own context)."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from lifecycle_msgs.srv import ChangeState
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain,
                   signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node("dvt_bench_link", context=self.ctx)
        self._ChangeState = ChangeState
        self.change = self.node.create_client(ChangeState, f"/{DRIVER}/change_state")
        self.diag: dict[str, str] = {}
        self.diag_count = 0
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diag, 10)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == DRIVER:
                self.diag = {kv.key: kv.value for kv in st.values}
                self.diag_count += 1

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def transition(self, label: str, timeout: float = 10.0) -> None:
        """Request lifecycle transition ``label`` (by label: refused, never fatal)."""
        from lifecycle_msgs.msg import Transition

        from dvt_model import rosutil

        if not self.change.wait_for_service(timeout_sec=timeout):
            raise LaunchError(f"/{DRIVER}/change_state not available after {timeout:g} s")
        req = self._ChangeState.Request(transition=Transition(label=label))
        ok = rosutil.change_state(self.executor, self.change, req, timeout, self._diag_state)
        if not ok:
            raise LaunchError(f"driver transition {label!r} failed"
                              + ("" if ok is not None else f" (no answer in {timeout:g} s)"))

    def _diag_state(self, timeout: float = 3.0) -> str | None:
        """The driver's lifecycle state in its next diagnostics report (``None``: none came)."""
        seen = self.diag_count
        end = time.monotonic() + timeout
        while self.diag_count == seen and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
        return self.diag.get("lifecycle_state") if self.diag_count > seen else None

    def recorder_subscribed(self) -> bool:
        return all(any(i.node_name == "dvt_recorder"
                       for i in self.node.get_subscriptions_info_by_topic(t))
                   for t in (JOINT_STATES, CURRENTS))

    def fresh_diag(self, state: str, timeout: float = 3.0) -> dict[str, str]:
        """The first driver diagnostics after now whose lifecycle state is ``state``."""
        seen = self.diag_count
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            if self.diag_count > seen and self.diag.get("lifecycle_state") == state:
                return dict(self.diag)
        raise LaunchError(f"no driver diagnostics in state {state!r} within {timeout:g} s")

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def _read_bag(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(header stamps [ns], log times [ns]) of ``/dvt/joint_states`` in recorded order."""
    stamps: list[int] = []
    logs: list[int] = []
    with BagMessages(path) as bag:
        for msg in bag.messages([JOINT_STATES]):
            stamps.append(raw_stamp_ns(msg.data))
            logs.append(msg.log_time_ns)
    return np.asarray(stamps, dtype=np.int64), np.asarray(logs, dtype=np.int64)


def _int(d: dict[str, str], key: str) -> int:
    try:
        return int(d.get(key, "0"))
    except ValueError:
        return 0


def run(rate: float, seconds: float, hidden: str = "none", keep: Path | None = None,
        log: Any = None) -> dict[str, Any]:
    """Run the benchmark; returns the figures (see the module docstring)."""
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(201 + os.getpid() % 30))  # above the tests' 1..200
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env.update(SINGLE_THREAD_BLAS)
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    work = Path(tempfile.mkdtemp(prefix="dvt-bench-link-"))
    bag = work / "bag"
    stop = StopFlag(escalate=False).install()
    kids = Children(work, env, stop, echo=log)
    node: _BenchNode | None = None
    try:
        plant = kids.start("plant", [script("dvt-plant"), "--link", str(work / "plant.tty"),
                                     "--rate", f"{rate:g}", "--hidden", hidden, "--seed", "0",
                                     "--truth-out", str(work / TRUTH_FILE)])

        link = kids.wait_until("the plant's READY line", lambda: ready_line(plant.log), 30.0)
        driver = kids.start("driver", [script("dvt_driver_node"), "--ros-args",
                                       "-p", f"port:={link}", "-p", f"sample_rate_hz:={rate:g}"])
        recorder = kids.start("recorder", [script("dvt-recorder"), "--ros-args",
                                           "-p", f"output:={bag}",
                                           "-p", f"topics:=[{JOINT_STATES},{CURRENTS}]"])
        node = _BenchNode(int(env["ROS_DOMAIN_ID"]))
        node.transition("configure", timeout=20.0)
        bn = node

        def subscribed() -> bool:
            bn.spin(0.05)
            return bn.recorder_subscribed()

        kids.wait_until("the recorder's subscriptions", subscribed, 30.0)
        node.spin(1.0)  # let DDS match the recorder with the driver's publishers
        pids = {"plant": plant.proc.pid, "driver": driver.proc.pid,
                "recorder": recorder.proc.pid}
        before = node.fresh_diag("inactive")
        cpu0 = {k: cpu_seconds(p) for k, p in pids.items()}
        t0 = time.monotonic()
        node.transition("activate")
        end = t0 + seconds
        while time.monotonic() < end:
            if stop:
                raise LaunchError("interrupted")
            kids.check_alive()
            node.spin(min(0.2, max(0.0, end - time.monotonic())))
        node.transition("deactivate")
        wall = time.monotonic() - t0
        cpu1 = {k: cpu_seconds(p) for k, p in pids.items()}
        after = node.fresh_diag("inactive")
        node.spin(1.0)  # the recorder drains what is in flight
        kids.stop_all()
    finally:
        if node is not None:
            node.close()
        kids.stop_all()
        stop.restore()
    stamps, logs = _read_bag(bag)
    period_ns = 1e9 / rate
    published = _int(after, "samples_published") - _int(before, "samples_published")
    serial_lost = _int(after, "lost_samples") - _int(before, "lost_samples")
    sent = published + serial_lost
    recorded = int(stamps.size)
    gaps = np.diff(stamps)
    bag_gaps = int(np.sum(np.maximum(np.round(gaps / period_ns) - 1, 0))) if gaps.size else 0
    span = (stamps[-1] - stamps[0]) * 1e-9 if recorded > 1 else float("nan")
    lat = (logs - stamps) * 1e-6
    cpu = {k: round(100.0 * (cpu1[k] - cpu0[k]) / wall, 1) for k in pids}
    result: dict[str, Any] = {
        "rate_hz": round((recorded - 1) / span, 2) if recorded > 1 else 0.0,
        "sent": sent,
        "recorded": recorded,
        "lost": sent - recorded,
        "crc_errors": _int(after, "crc_errors"),
        "latency_ms": {
            "p50": round(float(np.percentile(lat, 50)), 3) if recorded else None,
            "p99": round(float(np.percentile(lat, 99)), 3) if recorded else None,
            "max": round(float(lat.max()), 3) if recorded else None,
        },
        "cpu_percent": round(sum(cpu.values()), 1),
        "cpu_percent_by_process": cpu,
        "requested_rate_hz": rate,
        "seconds": round(wall, 3),
        "published": published,
        "serial_lost": serial_lost,
        "bag_gaps": bag_gaps,
        "frames_bad": _int(after, "frames_bad"),
    }
    if keep is not None:
        shutil.copytree(work, keep)
    shutil.rmtree(work, ignore_errors=True)
    return result


def print_results(res: dict[str, Any], as_json: bool, width: int) -> None:
    """A benchmark's figures on stdout: one JSON line, or ``name value`` rows (names padded to
    ``width`` characters)."""
    if as_json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:{width}s} {v}")


def main(argv: Sequence[str] | None = None) -> int:
    """``dvt-bench link`` (argv without the ``link`` word); returns the exit status."""
    p = argparse.ArgumentParser(prog="dvt-bench link",
                                description="plant -> driver -> recorder throughput benchmark")
    p.add_argument("--rate", type=float, default=1000.0, help="sample rate [Hz] (1000)")
    p.add_argument("--seconds", type=float, default=30.0, help="active time [s] (30)")
    p.add_argument("--hidden", default="none", help="plant hidden-effects preset (none)")
    p.add_argument("--keep", default=None, help="copy the bag and logs to this new directory")
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    if not 0 < args.rate <= 2000:
        p.error(f"--rate: expected 0 < HZ <= 2000, got {args.rate}")
    if not args.seconds > 0:
        p.error(f"--seconds: expected > 0, got {args.seconds}")
    if args.keep is not None and Path(args.keep).exists():
        p.error(f"--keep: {args.keep} already exists")
    try:
        res = run(args.rate, args.seconds, args.hidden,
                  Path(args.keep) if args.keep else None,
                  log=None if args.json else sys.stderr)
    except LaunchError as exc:
        print(f"dvt-bench link: error: {exc}", file=sys.stderr)
        return 1
    print_results(res, args.json, 24)
    return 0
