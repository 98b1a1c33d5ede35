"""``dvt-bench model``: feed the model node at a fixed rate and measure it.

Starts ``dvt_model_node`` as its own process, publishes ``/dvt/joint_states`` and
``/dvt/currents`` pairs at ``--rate`` Hz for ``--seconds`` from this process, listens to
``/dvt/model/residual`` and prints JSON::

    {"rate_hz", "sent", "received", "published", "dropped",
     "latency_ms": {"p50", "p99", "p999", "max"}, "cpu_percent", "detector"}

``received``: samples the node processed (from its diagnostics); ``published``: residual
messages that reached the bench; ``dropped = sent - published``; latency: publish of the
measured sample to receipt of its residual (same machine clock); ``cpu_percent``: the node
process's CPU time over the run (100 = one core); ``detector``: whether the node's change
detector ran (default on, as in production; ``--no-detector`` starts the node with
``detector.enabled:=false`` for a comparison) and its last ``/diagnostics`` status (``state``,
``samples`` it tested, ``alarms``). The detector learns for ``detector.learn_s`` (20 s) before
it tests; ``--seconds`` beyond that measures the testing path too. A benchmark, not a test: it
prints what it measured.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def run(rate: float, seconds: float, params: str = "physical", detector: bool = True
        ) -> dict[str, Any]:
    """Run the benchmark; returns the figures (see module docstring)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import JointState

    from dvt_model import rosutil
    from dvt_model.contract import (
        CURRENT_NAMES,
        CURRENTS,
        DIAGNOSTICS,
        DIAGNOSTICS_QOS,
        JOINT_STATES,
        MODEL_NODE,
        MODEL_RESIDUAL,
        SPEED_NAMES,
    )

    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    exe_path = Path(sys.executable).parent / "dvt_model_node"
    proc = subprocess.Popen([str(exe_path), "--ros-args", "-p", f"params:={params}",
                             "-p", f"detector.enabled:={'true' if detector else 'false'}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    node = rclpy.create_node("dvt_bench_model", context=ctx)
    sent_at: dict[int, float] = {}
    latencies: list[float] = []
    node_samples = {"n": 0}
    det_status: dict[str, str] = {}
    lock = threading.Lock()

    def on_residual(msg: JointState) -> None:
        now = time.perf_counter()
        key = rosutil.stamp_to_ns(msg.header.stamp)
        with lock:
            t0 = sent_at.pop(key, None)
        if t0 is not None:
            latencies.append(now - t0)

    def on_diag(msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == MODEL_NODE:
                for kv in st.values:
                    if kv.key == "samples":
                        node_samples["n"] = int(kv.value)
            elif st.name == f"{MODEL_NODE}: change detector":
                det_status.clear()
                det_status.update({kv.key: kv.value for kv in st.values})

    node.create_subscription(JointState, MODEL_RESIDUAL, on_residual, rosutil.SENSOR_QOS)
    node.create_subscription(DiagnosticArray, DIAGNOSTICS, on_diag,
                             rosutil.qos(DIAGNOSTICS_QOS))
    pub_js = node.create_publisher(JointState, JOINT_STATES, rosutil.SENSOR_QOS)
    pub_cur = node.create_publisher(JointState, CURRENTS, rosutil.SENSOR_QOS)
    executor = EventsExecutor(context=ctx)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    try:
        deadline = time.monotonic() + 30.0
        while (pub_js.get_subscription_count() < 1 or pub_cur.get_subscription_count() < 1
               or node.count_publishers(MODEL_RESIDUAL) < 1):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("dvt_model_node did not come up within 30 s")
            time.sleep(0.05)
        time.sleep(0.5)
        n = int(rate * seconds)
        period = 1.0 / rate
        cpu0, wall0 = _cpu_seconds(proc.pid), time.monotonic()
        start = time.perf_counter()
        base_ns = time.time_ns()
        for k in range(n):
            due = start + k * period
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            stamp = base_ns + int(k * period * 1e9)
            t = k * period
            i_m = 4.0 + 2.0 * np.sin(2 * np.pi * t)
            js = rosutil.joint_state(stamp, SPEED_NAMES, velocity=(100.0, 20.0))
            cur = rosutil.joint_state(stamp, CURRENT_NAMES, effort=(i_m, 0.0, 0.0, 0.0))
            with lock:
                sent_at[stamp] = time.perf_counter()
            pub_js.publish(js)
            pub_cur.publish(cur)
        send_seconds = time.perf_counter() - start
        time.sleep(1.5)
        cpu1, wall1 = _cpu_seconds(proc.pid), time.monotonic()
        lat = np.asarray(latencies) * 1e3
        return {
            "rate_hz": rate,
            "achieved_send_rate_hz": n / send_seconds,
            "sent": n,
            "received": node_samples["n"],
            "published": len(latencies),
            "dropped": n - len(latencies),
            "latency_ms": {"p50": float(np.percentile(lat, 50)) if lat.size else None,
                           "p99": float(np.percentile(lat, 99)) if lat.size else None,
                           "p999": float(np.percentile(lat, 99.9)) if lat.size else None,
                           "max": float(lat.max()) if lat.size else None},
            "cpu_percent": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
            "detector": {"enabled": detector,
                         **{k: det_status[k] for k in ("state", "samples", "tested", "alarms")
                            if k in det_status}},
            "load_average_1min": os.getloadavg()[0],
        }
    finally:
        stop.set()
        th.join(timeout=2.0)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dvt-bench model", description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=30.0,
                        help="sending time [s] (30: the detector learns 20 s, then tests)")
    parser.add_argument("--params", default="physical")
    parser.add_argument("--no-detector", action="store_true",
                        help="start the node with detector.enabled:=false (comparison)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    out = run(args.rate, args.seconds, args.params, detector=not args.no_detector)
    print(json.dumps(out, indent=None if args.json else 2))
    return 0
