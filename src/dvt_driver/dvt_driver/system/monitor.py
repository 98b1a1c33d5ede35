"""The launcher's own rclpy node: counts samples, inspects the graph, re-arms the change
detector and receives the identifier's episode reports.

Not a core module: it imports rclpy (lazily, so that ``dvt-launch --help`` and the argument
checks need no ROS). :class:`Monitor` spins in a daemon thread; its sample subscriptions are
dropped once the chain is ready (:meth:`Monitor.quiet`), so the launcher costs no CPU at 1 kHz.
With ``episodes=True`` it subscribes to :data:`dvt_model.contract.IDENTIFY_EPISODE` (the
supervisor's episode records, ``std_msgs/String`` JSON, QoS
:data:`~dvt_model.contract.CHANGE_QOS`: a late subscriber still gets the last 10) for the whole
run; :meth:`Monitor.take_episodes` hands over what arrived.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable
from typing import Any

from dvt_driver.errors import LaunchError, LaunchInterruptedError
from dvt_model.contract import (
    CHANGE_QOS,
    IDENTIFY_EPISODE,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    answer_of,
    model_reset_detector_service,
)

__all__ = ["Monitor"]

RESEND_S = 2.0
"""A service request unanswered this long is sent again [s] (a reply lost while the route of a
fresh client is being matched; :func:`dvt_model.contract.answer_of`)."""


class Monitor:
    """A small rclpy node in the launcher (see the module docstring).

    Args:
        episodes: also receive the identifier's episode reports on
            :data:`~dvt_model.contract.IDENTIFY_EPISODE`.
    """

    def __init__(self, episodes: bool = False) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        from dvt_model import rosutil

        self.ctx = Context()
        rclpy.init(context=self.ctx,
                   signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node("dvt_launch", context=self.ctx)
        self.counts: dict[str, int] = {}
        self.subs: list[Any] = []
        for topic in (JOINT_STATES, MODEL_JOINT_STATES):
            self.counts[topic] = 0
            self.subs.append(self.node.create_subscription(
                JointState, topic, self._counter(topic), rosutil.SENSOR_QOS))
        self._episode_lock = threading.Lock()
        self._episodes: list[dict[str, Any]] = []
        self._bad_episodes: list[str] = []
        if episodes:
            self.node.create_subscription(String, IDENTIFY_EPISODE, self._on_episode,
                                          rosutil.qos(CHANGE_QOS))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._quit = threading.Event()
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._spin, name="dvt-launch-monitor",
                                       daemon=True)
        self.thread.start()

    def _counter(self, topic: str) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            self.counts[topic] += 1
        return cb

    def _on_episode(self, msg: Any) -> None:
        """An episode record: kept if it is a JSON object, else its text is kept as bad (never
        raises: a bad message must not stop the launcher)."""
        try:
            record = json.loads(msg.data)
        except ValueError as exc:
            bad: str | None = f"not JSON ({exc}): {msg.data[:200]!r}"
        else:
            bad = None if isinstance(record, dict) else f"not a JSON object: {msg.data[:200]!r}"
        with self._episode_lock:
            if bad is None:
                self._episodes.append(record)
            else:
                self._bad_episodes.append(bad)

    def take_episodes(self) -> tuple[list[dict[str, Any]], list[str]]:
        """The episode records received since the last call, in arrival order, and the
        messages on the topic that were not records (why, and their start)."""
        with self._episode_lock:
            out, bad = self._episodes, self._bad_episodes
            self._episodes, self._bad_episodes = [], []
        return out, bad

    def _spin(self) -> None:
        while not self._quit.is_set():
            try:
                with self._lock:
                    self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us
                return

    def subscribed(self, node_name: str, topic: str) -> bool:
        """Whether node ``node_name`` has a subscription on ``topic``."""
        with self._lock:
            infos = self.node.get_subscriptions_info_by_topic(topic)
        return any(i.node_name == node_name for i in infos)

    def published(self, node_name: str, topic: str) -> bool:
        """Whether node ``node_name`` has a publisher on ``topic``."""
        with self._lock:
            infos = self.node.get_publishers_info_by_topic(topic)
        return any(i.node_name == node_name for i in infos)

    def rearm_detector(self, model_node: str, timeout: float,
                       interrupted: Callable[[], bool] = lambda: False) -> str:
        """Make the model node's change detector learn anew: call its reset service
        (``/<model_node>/reset_detector``, std_srvs/srv/Trigger,
        :data:`dvt_model.contract.SRV_MODEL_RESET_DETECTOR`).

        Waits at most ``timeout`` [s] in all for the service to appear and answer. Returns the
        node's answer (what was reset). Raises :class:`LaunchError` naming the node and the
        service when the service does not appear or answer within ``timeout``, or refuses
        (``success=False``, e.g. the detector is off: its reason), and
        :class:`LaunchInterruptedError` as soon as ``interrupted()`` is true (a signal).
        """
        from std_srvs.srv import Trigger

        service = model_reset_detector_service(model_node)
        deadline = time.monotonic() + timeout
        with self._lock:
            client = self.node.create_client(Trigger, service)

        def ready() -> bool:
            with self._lock:
                return bool(client.service_is_ready())

        def check_interrupted() -> None:
            if interrupted():
                raise LaunchInterruptedError(f"interrupted while calling {service} of model "
                                             f"node {model_node!r}")

        try:
            while not ready():
                check_interrupted()
                if time.monotonic() > deadline:
                    raise LaunchError(f"model node {model_node!r} offers no service {service} "
                                      f"within {timeout:g} s (is it running under that name?)")
                time.sleep(0.05)
            # a reset whose reply is lost (the real-time model node's 100 ms reply wait, a
            # fresh client) is sent again: a second reset only restarts the learning just begun
            def send() -> Any:
                with self._lock:
                    return client.call_async(Trigger.Request())

            def wait(poll: float) -> None:
                check_interrupted()
                time.sleep(poll)
            try:
                answer, _ = answer_of(send, max(deadline - time.monotonic(), 1e-3), RESEND_S,
                                      poll=0.02, wait=wait)
            except TimeoutError:
                raise LaunchError(f"model node {model_node!r} did not answer {service} "
                                  f"within {timeout:g} s") from None
            except (LaunchError, LaunchInterruptedError):
                raise
            except Exception as failure:  # the call itself failed (rclpy sets it on the future)
                raise LaunchError(f"model node {model_node!r}: the call of {service} failed "
                                  f"({failure!r})") from None
            if answer is None:
                raise LaunchError(f"model node {model_node!r}: the call of {service} failed "
                                  "(no response)")
            if not answer.success:
                raise LaunchError(f"model node {model_node!r} refused {service}: "
                                  f"{answer.message}")
            return str(answer.message)
        finally:
            with self._lock:
                self.node.destroy_client(client)

    def quiet(self) -> None:
        """Drop the sample subscriptions (readiness is established); the episode
        subscription stays."""
        with self._lock:
            for sub in self.subs:
                self.node.destroy_subscription(sub)
            self.subs.clear()

    def close(self) -> None:
        """Stop the spin thread and shut the context down."""
        self._quit.set()
        self.thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self.executor.shutdown(timeout_sec=1.0)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
        with contextlib.suppress(Exception):
            self.ctx.try_shutdown()
