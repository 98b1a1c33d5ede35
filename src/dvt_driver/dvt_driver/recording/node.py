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

import functools
import importlib
import sys
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

from dvt_driver.recording.policy import DEFAULT_TOPICS, choose_qos, match_topics, needs_weaker
from dvt_driver.signals import StopFlag
from dvt_model.contract import RECORDER_NODE, SENSOR_QOS
from dvt_model.errors import RecordingError
from dvt_model.recording import DEFAULT_FLUSH_PERIOD, BagRecorder, typestore

POLL_PERIOD = 0.1  # s, timer that makes buffered messages durable when traffic stops


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
        if not output:
            raise RecordingError("parameter 'output' is required (bag directory to create), "
                                "e.g. --ros-args -p output:=runs/run1")
        if not self.patterns:
            raise RecordingError("parameter 'topics' is empty; nothing to record")
        if self.depth < 1:
            raise RecordingError(f"parameter 'depth': expected >= 1, got {self.depth}")
        if not rescan > 0:
            raise RecordingError(f"parameter 'rescan_period': expected > 0 s, got {rescan}")
        self.stop = stop
        self.recorder = BagRecorder(output, flush_period=flush_period, fsync=fsync,
                                    compression=compression)
        self.subs: dict[str, tuple[Subscription, tuple[str, str]]] = {}
        self.warned: set[str] = set()
        self.lost: dict[str, int] = {}
        self.received = 0
        self.failed: str | None = None
        self._rescan_timer = self.create_timer(rescan, self.rescan)
        self._poll_timer = self.create_timer(POLL_PERIOD, self.poll)
        self.get_logger().info(f"recording {self.patterns} to {self.recorder.path}")
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

    def poll(self) -> None:
        """Timer: make buffered messages durable when traffic pauses."""
        if self.failed or self.recorder.closed:
            return
        try:
            self.recorder.poll()
        except OSError as exc:
            self.fail(f"flushing failed: {exc}")

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
        print(f"dvt-recorder: wrote {node.recorder.path}: {counts} "
              f"({sum(stats.values())} messages in {elapsed:.1f} s, {lost} reported lost by DDS)",
              flush=True)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    return 1 if node.failed else 0


if __name__ == "__main__":
    sys.exit(main())
