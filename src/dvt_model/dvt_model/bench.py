"""``dvt-bench model``: feed the model node at a fixed rate and measure it.

Starts ``dvt_model_node`` as its own process, publishes ``/dvt/joint_states`` and
``/dvt/currents`` pairs at ``--rate`` Hz for ``--seconds`` from this process, listens to
``/dvt/model/residual`` and prints JSON::

    {"rate_hz", "sent", "received", "published", "dropped",
     "latency_ms": {"p50", "p99", "p999", "max"}, "cpu_percent", "cpu_us_per_sample",
     "detector", "load_average_1min"}

``received``: samples the node processed (from its diagnostics); ``published``: residual
messages that reached the bench; ``dropped = sent - published``; latency: from just before the
bench publishes a sample's first message to the receipt of its residual (same machine clock;
both DDS hops, the node's callbacks and its residual publication; the bench's own message
building and conversion are kept out: the messages are serialised beforehand and the residual
is taken raw); ``cpu_percent``: the node process's CPU time over the run (100 = one core),
``cpu_us_per_sample`` the same per processed sample (less sensitive to the machine's load than
the latency); ``detector``: whether the node's change detector ran (default on, as in
production; ``--no-detector`` starts the node with ``detector.enabled:=false`` for a
comparison) and its last ``/diagnostics`` status (``state``, ``samples`` it tested,
``alarms``). The detector learns for ``detector.learn_s`` (20 s) before it tests; ``--seconds``
beyond that measures the testing path too. The latency is only meaningful on a machine with a
core to spare: ``load_average_1min`` says how loaded it was. A benchmark, not a test: it prints
what it measured.

``--in-process`` instead builds the node in this process (its own ROS domain, nobody
listening) and calls its per-sample callback directly on serialised messages: the CPU time
[us] of each stage per sample (``decode``, ``pairing``, ``predictor``, ``messages``,
``publish``, ``detector``, the rest of the callback as ``glue``; median, p99, max) and the
callback's total, without DDS and scheduling.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
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
    from dvt_model.node import stamp_of
    from dvt_model.recording.cdr import joint_state_cdr, restamp

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

    def on_residual(raw: Any) -> None:
        now = time.perf_counter()
        key = stamp_of(raw)
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

    node.create_subscription(JointState, MODEL_RESIDUAL, on_residual, rosutil.SENSOR_QOS,
                             raw=True)
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
        base_ns = time.time_ns()
        stamps = [base_ns + int(k * period * 1e9) for k in range(n)]
        i_m = 4.0 + 2.0 * np.sin(2 * np.pi * np.arange(n) * period)
        js = joint_state_cdr(0, SPEED_NAMES, velocity=(100.0, 20.0))
        samples = [(stamp, restamp(js, stamp),
                    joint_state_cdr(stamp, CURRENT_NAMES, effort=(float(i), 0.0, 0.0, 0.0)))
                   for stamp, i in zip(stamps, i_m.tolist(), strict=True)]
        gc.collect()
        gc.freeze()  # no full collection of this process's objects inside the measurement
        cpu0, wall0 = _cpu_seconds(proc.pid), time.monotonic()
        start = time.perf_counter()
        for k, (stamp, js_raw, cur_raw) in enumerate(samples):
            due = start + k * period
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            with lock:
                sent_at[stamp] = time.perf_counter()
            pub_js.publish(js_raw)
            pub_cur.publish(cur_raw)
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
            "cpu_us_per_sample": (1e6 * (cpu1 - cpu0) / node_samples["n"]
                                  if node_samples["n"] else None),
            "detector": {"enabled": detector,
                         **{k: det_status[k] for k in ("state", "samples", "tested", "alarms")
                            if k in det_status}},
            "load_average_1min": os.getloadavg()[0],
        }
    finally:
        gc.unfreeze()
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


STAGES = ("decode", "pairing", "predictor", "messages", "publish", "detector", "glue",
          "total")


def profile(samples: int = 30000, params: str = "physical", detector: bool = True,
            learn_s: float = 5.0) -> dict[str, Any]:
    """Per-stage CPU time [us] of the node's per-sample callback, in process (no DDS).

    The bench's stream (constant speeds, a 1 Hz motor current) as serialised messages is fed
    to :meth:`dvt_model.node.ModelNode._on_msg`; each stage's methods are timed with the
    thread's CPU clock (wrapping costs ~1 us per stage, counted in ``glue``). The first
    1000 samples (first calls) are left out. ``learn_s``: the detector's reference window
    [s], short so that the run covers the testing path.
    """
    import rclpy
    from rclpy.context import Context

    from dvt_model.contract import CURRENT_NAMES, SPEED_NAMES
    from dvt_model.node import ModelNode
    from dvt_model.recording.cdr import joint_state_cdr, restamp

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = Context()
    rclpy.init(context=ctx, domain_id=150 + os.getpid() % 50, args=[
        "dvt-bench", "--ros-args", "-p", f"params:={params}",
        "-p", f"detector.enabled:={'true' if detector else 'false'}",
        "-p", f"detector.learn_s:={learn_s}"])
    node = ModelNode(context=ctx)
    clock = time.thread_time_ns
    acc: dict[str, int] = {}

    def wrap(obj: Any, attr: str, stage: str) -> None:
        f = getattr(obj, attr)

        def timed(*args: Any) -> Any:
            t0 = clock()
            try:
                return f(*args)
            finally:
                acc[stage] = acc.get(stage, 0) + clock() - t0
        setattr(obj, attr, timed)

    try:
        js = joint_state_cdr(0, SPEED_NAMES, velocity=(100.0, 20.0))
        base = 1_700_000_000_000_000_000
        stream = [(restamp(js, base + k * 1_000_000),
                   joint_state_cdr(base + k * 1_000_000, CURRENT_NAMES,
                                   effort=(4.0 + 2.0 * math.sin(2 * math.pi * k * 1e-3),
                                           0.0, 0.0, 0.0)))
                  for k in range(samples)]
        for obj, attr, stage in ((node._speeds, "read", "decode"),
                                 (node._currents, "read", "decode"),
                                 (node.pairer, "add", "pairing"),
                                 (node.predictor, "update", "predictor"),
                                 (node._writer, "encode", "messages"),
                                 (node.pub_pred, "publish", "publish"),
                                 (node.pub_res, "publish", "publish")):
            wrap(obj, attr, stage)
        if node.blocks is not None and node.detector is not None:
            wrap(node.blocks, "add", "detector")
            wrap(node.detector, "update", "detector")
        gc.collect()
        gc.freeze()  # as the node's main() does
        rows: list[dict[str, int]] = []
        on_msg = node._on_msg
        for js_raw, cur_raw in stream:
            acc.clear()
            t0 = clock()
            on_msg(js_raw, 0)
            on_msg(cur_raw, 1)
            total = clock() - t0
            row = dict(acc)
            row["glue"] = total - sum(acc.values())
            row["total"] = total
            rows.append(row)
        gc.unfreeze()
        skip = min(1000, samples // 10)
        out: dict[str, Any] = {"samples": samples, "params": params,
                               "detector": {"enabled": detector}, "cpu_us": {}}
        for stage in STAGES:
            x = np.asarray([r.get(stage, 0) for r in rows[skip:]], dtype=float) / 1e3
            out["cpu_us"][stage] = {"median": round(float(np.median(x)), 2),
                                    "p99": round(float(np.percentile(x, 99)), 2),
                                    "max": round(float(x.max()), 1)}
        if node.detector is not None:
            out["detector"].update({k: v for k, v in node.detector.status().items()
                                    if k in ("state", "tested", "alarms")})
        out["load_average_1min"] = os.getloadavg()[0]
        return out
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dvt-bench model", description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=30.0,
                        help="sending time [s] (30: the detector learns 20 s, then tests)")
    parser.add_argument("--params", default="physical")
    parser.add_argument("--no-detector", action="store_true",
                        help="start the node with detector.enabled:=false (comparison)")
    parser.add_argument("--in-process", action="store_true",
                        help="per-stage CPU time of the node's callback in process (no DDS)")
    parser.add_argument("--samples", type=int, default=30000,
                        help="samples of --in-process")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.in_process:
        out = profile(args.samples, args.params, detector=not args.no_detector)
    else:
        out = run(args.rate, args.seconds, args.params, detector=not args.no_detector)
    print(json.dumps(out, indent=None if args.json else 2))
    return 0
