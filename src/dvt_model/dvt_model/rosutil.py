"""Shared node-layer helpers (rclpy): QoS profiles, JointState building, the spin loop.

Not a core module: it imports rclpy. Topic names and QoS are the interface contract's
(``../shared/INTERFACE.md``): high-rate streams use a sensor-data (best-effort) QoS with a
deep queue so bursts are absorbed; a best-effort subscription matches both best-effort and
reliable publishers.
"""

from __future__ import annotations

import hashlib
import os
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from sensor_msgs.msg import JointState

from dvt_model.contract import (
    COMMAND_QOS as _COMMAND_QOS_SPEC,
)
from dvt_model.contract import (
    FASTDDS_DEFAULT_REPLY_WAIT_S,
    FASTDDS_PROFILES_ENV,
    REPLY_WAIT_S,
    QosSpec,
    answer_of,
    reply_wait_profile,
)
from dvt_model.contract import (
    LATCHED_QOS as _LATCHED_QOS_SPEC,
)
from dvt_model.contract import (
    SENSOR_QOS as _SENSOR_QOS_SPEC,
)

__all__ = ["COMMAND_QOS", "LATCHED_QOS", "SENSOR_QOS", "qos"]

PROFILES_ENV = FASTDDS_PROFILES_ENV
"""Fast DDS's profiles-file variable (:data:`dvt_model.contract.FASTDDS_PROFILES_ENV`)."""


def qos(spec: QosSpec) -> QoSProfile:
    """The rclpy profile of a contract :class:`~dvt_model.contract.QosSpec`."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=spec.depth,
        reliability=(ReliabilityPolicy.BEST_EFFORT if spec.reliability == "best_effort"
                     else ReliabilityPolicy.RELIABLE),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if spec.durability == "transient_local"
                    else DurabilityPolicy.VOLATILE))


SENSOR_QOS = qos(_SENSOR_QOS_SPEC)
"""High-rate streams (publishers and subscribers)."""
COMMAND_QOS = qos(_COMMAND_QOS_SPEC)
"""Commands to the driver: every command counts."""
LATCHED_QOS = qos(_LATCHED_QOS_SPEC)
"""Results a late subscriber must still get."""


def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds -> ``builtin_interfaces/Time``."""
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def joint_state(stamp_ns: int, names: Sequence[str], velocity: Iterable[float] | None = None,
                effort: Iterable[float] | None = None, frame_id: str = "") -> JointState:
    """A JointState with the given stamp; ``velocity``/``effort`` optional."""
    msg = JointState()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.name = list(names)
    if velocity is not None:
        msg.velocity = [float(v) for v in velocity]
    if effort is not None:
        msg.effort = [float(v) for v in effort]
    return msg


def diagnostic(node: Node, name: str, level: int, message: str,
               values: dict[str, Any]) -> DiagnosticArray:
    """One-status DiagnosticArray stamped now; ``level`` is a DiagnosticStatus level byte."""
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    st = DiagnosticStatus()
    st.level = bytes([level]) if isinstance(level, int) else level
    st.name = name
    st.message = message
    st.hardware_id = "dvt"
    st.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
    arr.status = [st]
    return arr


OK = 0
WARN = 1
ERROR = 2
STALE = 3


def spin(node: Node, *, events: bool = True) -> None:
    """Spin ``node`` until SIGINT/SIGTERM; then destroy it and shut rclpy down.

    Uses ``rclpy.experimental.EventsExecutor`` (cheap at 1 kHz) with bounded ``spin_once``
    calls so signals are always honoured.
    """
    stop = {"flag": False}

    def _handler(signum: int, frame: object) -> None:
        stop["flag"] = True

    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)
    executor: Any
    if events and os.environ.get("DVT_EXECUTOR", "events") == "events":
        from rclpy.experimental import EventsExecutor

        executor = EventsExecutor()
    else:
        from rclpy.executors import SingleThreadedExecutor

        executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop["flag"] and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    finally:
        on_shutdown = getattr(node, "on_shutdown_hook", None)
        if callable(on_shutdown):
            on_shutdown()
        executor.remove_node(node)
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


def use_reply_wait(services: Sequence[str], wait_s: float = REPLY_WAIT_S,
                   env: dict[str, str] | None = None) -> str | None:
    """Make this process's participant use
    :func:`~dvt_model.contract.reply_wait_profile` (call before
    ``rclpy.init``): the profile is written once to a file named by its content in the
    temporary directory, and ``FASTRTPS_DEFAULT_PROFILES_FILE`` set to it in ``env``
    (default ``os.environ``). A profiles file the user has set is kept (their file decides);
    returns the file in use, or ``None`` when it is the user's."""
    target = os.environ if env is None else env
    if target.get(PROFILES_ENV):
        return None
    text = reply_wait_profile(services, wait_s)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    path = os.path.join(tempfile.gettempdir(), f"dvt-fastdds-reply-{digest}.xml")
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(prefix="dvt-fastdds-", suffix=".xml.part")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)  # atomic: a concurrent reader sees the whole file or none
    target[PROFILES_ENV] = path
    return path


def users_profile_note(services: Sequence[str], path: str) -> str:
    """What a process logs when the user's profiles file ``path`` replaces the reply-wait
    profile of ``services`` (:func:`use_reply_wait` keeps the user's file): the file, the
    services, the wait they lose and where to get the block that restores it."""
    return (f"{PROFILES_ENV}={path} is the user's own Fast DDS profiles file, kept: the "
            f"replies of {', '.join(services)} wait Fast DDS's default "
            f"{FASTDDS_DEFAULT_REPLY_WAIT_S * 1e3:g} ms for a late "
            f"client instead of {REPLY_WAIT_S:g} s (a late client then loses the reply); "
            f"add the <data_writer> block that `dvt-discovery xml` prints to that file")


def init(args: list[str] | None = None, *, reply_wait: Sequence[str] = ()) -> list[str]:
    """``rclpy.init`` without rclpy's own signal handlers; returns non-ROS args.

    ``reply_wait``: services of this (not real-time) process whose replies wait
    :data:`~dvt_model.contract.REPLY_WAIT_S` for a late client (:func:`use_reply_wait`);
    when the user's own profiles file is kept instead, a warning says so
    (:func:`users_profile_note`).
    """
    kept = None
    if reply_wait and use_reply_wait(reply_wait) is None:
        kept = users_profile_note(reply_wait, os.environ.get(PROFILES_ENV, ""))
    argv = sys.argv if args is None else args
    rclpy.init(args=argv, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    if kept is not None:
        rclpy.logging.get_logger("dvt.rosutil").warning(kept)
    return list(rclpy.utilities.remove_ros_args(argv))


def call_idempotent(executor: Any, client: Any, request: Any, timeout: float,
                    resend_s: float = 2.0) -> Any | None:
    """Call ``client`` with a ``request`` whose repetition changes nothing (a read, a refusal,
    a set of the values in use), spinning ``executor``: sent again every ``resend_s`` seconds
    while no reply came (:func:`~dvt_model.contract.answer_of`: a real-time server drops its
    reply to a client whose route it has not matched yet); the first reply, or ``None`` after
    ``timeout`` seconds. Requests left unanswered are withdrawn from the client.

    Raises:
        ValueError: ``timeout`` or ``resend_s`` not > 0.
    """
    futures: list[Any] = []

    def send() -> Any:
        futures.append(client.call_async(request))
        return futures[-1]
    try:
        reply, _ = answer_of(send, timeout, resend_s, poll=0.01,
                             wait=lambda s: executor.spin_once(timeout_sec=s))
        return reply
    except TimeoutError:
        return None
    finally:
        for f in futures:  # done ones too: their own removal runs on a later spin
            client.remove_pending_request(f)


TRANSITION_GOAL = {"configure": "inactive", "activate": "active", "deactivate": "inactive",
                   "cleanup": "unconfigured", "shutdown": "finalized"}
"""The lifecycle state each transition (by label) ends in when it succeeds."""


def change_state(executor: Any, client: Any, request: Any, timeout: float,
                 state: Callable[[], str | None], resend_s: float = 3.0) -> bool | None:
    """Request a lifecycle transition (``lifecycle_msgs/srv/ChangeState``) from a real-time
    node, spinning ``executor``; its success, or ``None`` without an answer in ``timeout``.

    A transition is not idempotent, so a lost reply (:func:`call_idempotent`) is not simply
    sent again: after ``resend_s`` without one, ``state()`` (the node's lifecycle state, from
    its ``get_state`` service or its diagnostics; ``None`` if unknown) says whether it was
    applied, which counts as success; only one not applied is asked again (a refusal changes
    nothing).
    """
    goal = TRANSITION_GOAL.get(request.transition.label)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        reply = call_idempotent(executor, client, request,
                                max(min(resend_s, end - time.monotonic()), 1e-3), resend_s)
        if reply is not None:
            return bool(reply.success)
        if goal is not None and state() == goal:
            return True
    return None
