"""``dvt-recorder``: record DVT topics to a crash-safe rosbag2/MCAP bag.

Node ``dvt_recorder``. Thin wrapper around :class:`dvt_model.recording.BagRecorder` (the one
writer of recordings): subscribes with ``raw=True`` and writes the CDR bytes it receives (no
re-serialisation), log time = node clock at reception [ns].

Parameters (read-only):
    output (string, required): bag directory to create; must not exist.
    topics (string[]): topic names or shell patterns; default the contract's
        ``DEFAULT_RECORD_TOPICS`` (sample and model topics, ``/dvt/cmd/*``, ``/diagnostics``).
    flush_period (double, 0.5 s): messages are durable on disk at most this long after arrival;
        a SIGKILL loses at most that much (``dvt-bag recover`` restores the rest).
    fsync (bool, true): fsync on every flush.
    compression (string, "none"): chunk compression, "none" or "zstd".
    depth (int, 1000): KEEP_LAST history depth of every subscription.
    rescan_period (double, 0.25 s): how often the graph is scanned for new topics.
    ring_minutes (double, 0 = off): rolling mode: ``output`` is a ring directory (may exist)
        holding at least the last ``ring_minutes`` of messages in segments
        (:class:`dvt_model.recording.RollingRecorder`); windows of it are written as normal bags
        on request (below).
    ring_segment_seconds (double, 10 s): log-time length of one ring segment.
    snapshot_margin_s (double, 2 s): a snapshot of ``[from, to]`` is written once the node's
        clock is ``to + snapshot_margin_s`` (samples stamped up to ``to`` have arrived), and
        segments are chosen with this much slack between stamp and reception.

Rolling mode, snapshots: a ``std_msgs/String`` JSON request ``{"from": t0, "to": t1, "out":
DIR, "id": ...}`` (ROS time [s], widened by 1 us against float rounding; ``id`` optional,
echoed) on :data:`SNAPSHOT_REQUEST` writes the
messages of ``[t0, t1]`` (by ``header.stamp`` for stamped types, else log time) as the new bag
``DIR`` (a normal recording: same contract, ``read_run`` reads it) in a worker thread; the answer
is a ``std_msgs/String`` JSON on :data:`SNAPSHOT_RESULT` (reliable, transient-local, depth 10):
``{"id", "ok", "out", "from", "to", "counts", "messages", "first", "last", "segments",
"truncated", "stopped", "error"}``. Requests are served one at a time in arrival order.

QoS: types and publishers are taken from the graph (``get_topic_names_and_types``), rescanned
periodically. A subscription is RELIABLE when every publisher of the topic offers RELIABLE
(the driver publishes ``/dvt/joint_states`` and ``/dvt/currents`` RELIABLE, KEEP_LAST 1000),
else BEST_EFFORT (a RELIABLE subscription would not match a BEST_EFFORT publisher); likewise
TRANSIENT_LOCAL/VOLATILE. History is KEEP_LAST ``depth`` (>= 1000, i.e. >= 1 s at 1 kHz) so
that a short stall of the recorder loses nothing. If a publisher that needs a weaker QoS
appears later the subscription is re-created (the rules: :mod:`dvt_driver.recording.policy`).
Samples DDS reports lost are counted.

SIGINT/SIGTERM set a flag: the node stops subscribing, drains what already arrived, closes the
bag (``metadata.yaml``) and prints one line with the message counts.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import json
import math
import queue
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from std_msgs.msg import String

from dvt_driver.recording.policy import DEFAULT_TOPICS, choose_qos, match_topics, needs_weaker
from dvt_driver.signals import StopFlag
from dvt_model.contract import (
    RECORDER_NODE,
    RECORDER_SNAPSHOT_REQUEST,
    RECORDER_SNAPSHOT_RESULT,
    SENSOR_QOS,
)
from dvt_model.errors import RecordingError
from dvt_model.recording import (
    DEFAULT_FLUSH_PERIOD,
    BagRecorder,
    RollingRecorder,
    SnapshotPlan,
    SnapshotResult,
    typestore,
    write_snapshot,
)
from dvt_model.recording.ring import seconds_to_ns, window_ns

POLL_PERIOD = 0.1  # s, timer that makes buffered messages durable when traffic stops

SNAPSHOT_REQUEST = RECORDER_SNAPSHOT_REQUEST
"""Rolling mode: JSON request (``std_msgs/String``) to write a window of the ring as a bag
(the contract's :data:`dvt_model.contract.RECORDER_SNAPSHOT_REQUEST`)."""
SNAPSHOT_RESULT = RECORDER_SNAPSHOT_RESULT
"""Rolling mode: JSON answer (``std_msgs/String``) to each snapshot request
(:data:`dvt_model.contract.RECORDER_SNAPSHOT_RESULT`)."""


def parse_snapshot_request(text: str) -> tuple[float, float, str, object]:
    """``(from_s, to_s, out, id)`` of a JSON snapshot request; :class:`RecordingError` naming
    the field and value otherwise."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise RecordingError(f"snapshot request: not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise RecordingError(f"snapshot request: expected a JSON object, got {text[:80]!r}")
    values = []
    for key in ("from", "to"):
        v = data.get(key)
        seconds_to_ns(v, f"snapshot request: '{key}'")  # type: ignore[arg-type]
        values.append(float(v))  # type: ignore[arg-type]
    if values[1] < values[0]:
        raise RecordingError(f"snapshot request: 'to' ({values[1]}) is before 'from' "
                             f"({values[0]})")
    out = data.get("out")
    if not isinstance(out, str) or not out:
        raise RecordingError(f"snapshot request: 'out': expected a bag directory to create, "
                             f"got {out!r}")
    return values[0], values[1], out, data.get("id")


def _message_class(msgtype: str) -> Any:
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


class RecorderNode(Node):
    """ROS node ``dvt_recorder`` (see the module docstring for parameters)."""

    def __init__(self, stop: StopFlag) -> None:
        super().__init__(RECORDER_NODE)
        ro = ParameterDescriptor(read_only=True)
        output = str(self.declare_parameter("output", "", ro).value)
        self.patterns = [str(p) for p in
                         self.declare_parameter("topics", list(DEFAULT_TOPICS), ro).value or []]
        flush_period = float(self.declare_parameter("flush_period", DEFAULT_FLUSH_PERIOD, ro).value)
        fsync = bool(self.declare_parameter("fsync", True, ro).value)
        compression = str(self.declare_parameter("compression", "none", ro).value)
        self.depth = int(self.declare_parameter("depth", SENSOR_QOS.depth, ro).value)
        rescan = float(self.declare_parameter("rescan_period", 0.25, ro).value)
        ring_minutes = float(self.declare_parameter("ring_minutes", 0.0, ro).value)
        segment_s = float(self.declare_parameter("ring_segment_seconds", 10.0, ro).value)
        self.margin_s = float(self.declare_parameter("snapshot_margin_s", 2.0, ro).value)
        if not output:
            raise RecordingError("parameter 'output' is required (bag directory to create), "
                                "e.g. --ros-args -p output:=runs/run1")
        if not self.patterns:
            raise RecordingError("parameter 'topics' is empty; nothing to record")
        if self.depth < 1:
            raise RecordingError(f"parameter 'depth': expected >= 1, got {self.depth}")
        if not rescan > 0:
            raise RecordingError(f"parameter 'rescan_period': expected > 0 s, got {rescan}")
        if not (math.isfinite(ring_minutes) and ring_minutes >= 0):
            raise RecordingError(f"parameter 'ring_minutes': expected >= 0 (0: off), got "
                                 f"{ring_minutes}")
        if not (math.isfinite(self.margin_s) and self.margin_s >= 0):
            raise RecordingError(f"parameter 'snapshot_margin_s': expected >= 0 s, got "
                                 f"{self.margin_s}")
        self.stop = stop
        self.recorder: BagRecorder | RollingRecorder
        if ring_minutes > 0:
            if not (math.isfinite(segment_s) and 0 < segment_s <= ring_minutes * 60):
                raise RecordingError(f"parameter 'ring_segment_seconds': expected in (0, "
                                     f"ring_minutes * 60 = {ring_minutes * 60:g}] s, got "
                                     f"{segment_s}")
            self.recorder = RollingRecorder(output, ring_s=ring_minutes * 60.0,
                                            segment_s=segment_s, flush_period=flush_period,
                                            fsync=fsync, compression=compression)
            self.out_path = self.recorder.directory
        else:
            self.recorder = BagRecorder(output, flush_period=flush_period, fsync=fsync,
                                        compression=compression)
            self.out_path = self.recorder.path
        self.rolling = isinstance(self.recorder, RollingRecorder)
        self.counts: dict[str, int] = {}
        self._pending: list[tuple[float, float, str, object]] = []
        self._busy: tuple[SnapshotPlan, object, threading.Thread] | None = None
        self._done: queue.SimpleQueue[tuple[SnapshotResult | None, str]] = queue.SimpleQueue()
        self.snapshots = 0
        self.subs: dict[str, tuple[Subscription, tuple[str, str]]] = {}
        self.warned: set[str] = set()
        self.lost: dict[str, int] = {}
        self.received = 0
        self.failed: str | None = None
        self._rescan_timer = self.create_timer(rescan, self.rescan)
        self._poll_timer = self.create_timer(POLL_PERIOD, self.poll)
        self._result_pub = self.create_publisher(
            String, SNAPSHOT_RESULT, QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=10,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self._request_sub = self.create_subscription(
            String, SNAPSHOT_REQUEST, self.on_snapshot_request, QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=10,
                reliability=ReliabilityPolicy.RELIABLE))
        mode = (f"rolling, last {ring_minutes:g} min in {segment_s:g} s segments"
                if self.rolling else "one bag")
        self.get_logger().info(f"recording {self.patterns} to {self.out_path} ({mode})")
        self.rescan()

    # ---------------------------------------------------------------- graph
    def _warn_once(self, key: str, text: str) -> None:
        if key not in self.warned:
            self.warned.add(key)
            self.get_logger().warning(text)

    def rescan(self) -> None:
        """Subscribe to new matching topics; re-create subscriptions whose QoS must weaken."""
        if self.stop or self.failed:
            return
        chosen, problems = match_topics(self.patterns, self.get_topic_names_and_types())
        for text in problems:
            self._warn_once(text, text)
        for topic, msgtype in chosen.items():
            pubs = self.get_publishers_info_by_topic(topic)
            qos = choose_qos([(p.qos_profile.reliability.name.lower(),
                               p.qos_profile.durability.name.lower()) for p in pubs])
            if qos is None:
                continue
            current = self.subs.get(topic)
            if current is not None and not needs_weaker(qos, current[1]):
                continue
            self._subscribe(topic, msgtype, qos, current[0] if current else None)

    def _subscribe(self, topic: str, msgtype: str, qos: tuple[str, str],
                   old: Subscription | None) -> None:
        if msgtype not in typestore().types:
            self._warn_once(topic, f"{topic}: type {msgtype} is not a known ROS 2 Jazzy "
                                   "message; not recorded")
            return
        if self.recorder.has_topic(topic) and self.recorder.topics[topic] != msgtype:
            self._warn_once(topic, f"{topic}: type changed to {msgtype}; not recorded")
            return
        try:
            cls = _message_class(msgtype)
        except (ImportError, AttributeError, ValueError) as exc:
            self._warn_once(topic, f"{topic}: cannot import {msgtype} ({exc}); not recorded")
            return
        self.recorder.add_topic(topic, msgtype)
        profile = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self.depth,
            reliability=(ReliabilityPolicy.RELIABLE if qos[0] == "reliable"
                         else ReliabilityPolicy.BEST_EFFORT),
            durability=(DurabilityPolicy.TRANSIENT_LOCAL if qos[1] == "transient_local"
                        else DurabilityPolicy.VOLATILE))
        events = SubscriptionEventCallbacks(
            incompatible_qos=functools.partial(self._on_incompatible, topic),
            message_lost=functools.partial(self._on_lost, topic))
        sub = self.create_subscription(cls, topic, functools.partial(self.on_message, topic),
                                       profile, raw=True, event_callbacks=events)
        if old is not None:
            self.destroy_subscription(old)
        self.subs[topic] = (sub, qos)
        self.get_logger().info(f"recording {topic} [{msgtype}] with {qos[0]}/{qos[1]} QoS, "
                               f"depth {self.depth}")

    def _on_incompatible(self, topic: str, event: Any) -> None:
        self._warn_once(f"qos:{topic}", f"{topic}: a publisher offers an incompatible QoS; "
                                        "the next graph scan re-creates the subscription")

    def _on_lost(self, topic: str, event: Any) -> None:
        self.lost[topic] = self.lost.get(topic, 0) + int(getattr(event, "total_count_change", 0))

    # ------------------------------------------------------------- messages
    def on_message(self, topic: str, raw: bytes) -> None:
        """Write one raw CDR message with the reception time as log time."""
        if self.failed or self.recorder.closed:
            return
        self.received += 1
        try:
            self.recorder.write(topic, raw, self.get_clock().now().nanoseconds)
        except (OSError, RecordingError) as exc:
            self.fail(f"writing {topic} failed: {exc}")
            return
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def poll(self) -> None:
        """Timer: make buffered messages durable when traffic pauses."""
        if self.failed or self.recorder.closed:
            return
        try:
            if isinstance(self.recorder, RollingRecorder):
                self.recorder.poll(self.get_clock().now().nanoseconds)
            else:
                self.recorder.poll()
        except (OSError, RecordingError) as exc:
            self.fail(f"flushing failed: {exc}")
            return
        self.serve_snapshots()

    # ------------------------------------------------------------ snapshots
    def _answer(self, ident: object, ok: bool, **fields: object) -> None:
        payload = {"id": ident, "ok": ok, **fields}
        self._result_pub.publish(String(data=json.dumps(payload, default=str)))

    def on_snapshot_request(self, msg: String) -> None:
        """Queue a valid request; answer an invalid one at once with the error."""
        try:
            req = parse_snapshot_request(msg.data)
            if not self.rolling:
                raise RecordingError("snapshot request: the recorder is not in rolling mode "
                                     "(parameter 'ring_minutes' is 0)")
        except RecordingError as exc:
            ident = None
            with contextlib.suppress(ValueError, AttributeError):
                ident = json.loads(msg.data).get("id")
            self.get_logger().warning(str(exc))
            self._answer(ident, False, error=str(exc))
            return
        self._pending.append(req)
        self.get_logger().info(f"snapshot request {req[3]!r}: [{req[0]:.3f}, {req[1]:.3f}] s "
                               f"-> {req[2]}")

    def serve_snapshots(self, *, now: bool = False) -> None:
        """Publish finished snapshots; start the next pending one whose window has passed
        (``now``: regardless of the clock, e.g. at shutdown)."""
        ring = self.recorder
        if not isinstance(ring, RollingRecorder):
            return
        while not self._done.empty():
            result, error = self._done.get()
            if self._busy is None:
                break
            plan, ident, thread = self._busy
            thread.join()
            ring.release(plan)
            self._busy = None
            if result is None:
                self.get_logger().error(f"snapshot {ident!r} failed: {error}")
                self._answer(ident, False, error=error)
            else:
                self.snapshots += 1
                self.get_logger().info(f"snapshot {ident!r}: {result.total} messages -> "
                                       f"{result.path}")
                self._answer(ident, True, **result.to_dict())
        if self._busy is not None or not self._pending:
            return
        t0, t1, out, ident = self._pending[0]
        clock_ns = self.get_clock().now().nanoseconds
        if not now and clock_ns < round((t1 + self.margin_s) * 1e9):
            return
        self._pending.pop(0)
        try:
            lo, hi = window_ns(t0, t1)
            plan = ring.prepare(lo, hi, round(self.margin_s * 1e9))
        except (OSError, RecordingError) as exc:
            self._answer(ident, False, error=str(exc))
            return

        def work() -> None:
            try:
                self._done.put((write_snapshot(plan, out), ""))
            except (OSError, RecordingError) as exc:
                self._done.put((None, str(exc)))
            except Exception as exc:  # never lose the answer
                self._done.put((None, f"{type(exc).__name__}: {exc}"))

        thread = threading.Thread(target=work, name="dvt-snapshot", daemon=True)
        self._busy = (plan, ident, thread)
        thread.start()

    def finish_snapshots(self, timeout: float = 60.0) -> None:
        """At shutdown: write every queued snapshot with what the ring holds, then answer."""
        deadline = time.monotonic() + timeout
        while (self._busy is not None or self._pending) and time.monotonic() < deadline:
            self.serve_snapshots(now=True)
            if self._busy is not None:
                self._busy[2].join(timeout=0.05)

    def fail(self, reason: str) -> None:
        """Stop recording after an I/O error (the bag keeps what was flushed)."""
        if self.failed is None:
            self.failed = reason
            self.get_logger().error(f"{reason}; stopping")

    # ------------------------------------------------------------- shutdown
    def drain(self, executor: Executor, timeout: float = 2.0) -> None:
        """Stop timers, then take every message that already arrived (bounded by ``timeout``)."""
        self.destroy_timer(self._rescan_timer)
        self.destroy_timer(self._poll_timer)
        self.destroy_subscription(self._request_sub)
        deadline = time.monotonic() + timeout
        idle = 0
        while idle < 2 and time.monotonic() < deadline and not self.failed:
            before = self.received
            executor.spin_once(timeout_sec=0.05)
            idle = idle + 1 if self.received == before else 0

    def finish(self) -> dict[str, int]:
        """Unsubscribe and close the bag; returns messages per topic."""
        for sub, _ in self.subs.values():
            self.destroy_subscription(sub)
        self.subs.clear()
        if isinstance(self.recorder, RollingRecorder):
            try:
                self.finish_snapshots()
            finally:
                try:
                    self.recorder.close()
                except (OSError, RecordingError) as exc:
                    self.fail(f"closing the ring failed: {exc}")
            return dict(self.counts)
        try:
            return self.recorder.close()
        except OSError as exc:
            self.fail(f"closing the bag failed: {exc}")
            return self.recorder.stats


def _make_executor() -> Executor:
    try:
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    except (ImportError, RuntimeError):  # pragma: no cover - older rclpy
        return SingleThreadedExecutor()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-recorder``; returns the exit status."""
    stop = StopFlag().install()
    args = list(sys.argv if argv is None else argv)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = RecorderNode(stop)
    except (RecordingError, OSError) as exc:
        print(f"dvt-recorder: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = _make_executor()
    executor.add_node(node)
    start = time.monotonic()
    stats: dict[str, int] = {}
    try:
        while not stop and not node.failed and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        node.drain(executor)
    finally:
        stats = node.finish()
        elapsed = time.monotonic() - start
        counts = " ".join(f"{t}={n}" for t, n in stats.items()) or "no topics"
        lost = sum(node.lost.values())
        print(f"dvt-recorder: wrote {node.out_path}: {counts} "
              f"({sum(stats.values())} messages in {elapsed:.1f} s, {lost} reported lost by DDS)",
              flush=True)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    return 1 if node.failed else 0


if __name__ == "__main__":
    sys.exit(main())
