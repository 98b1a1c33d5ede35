"""``dvt-experiment``: run a named experiment against the driver, in real time.

Usage::

    dvt-experiment NAME [--seed N] [--set NAME=VALUE ...] [--wait S] [--subscribers K]
                   [--recorder NODE] [--list] [--dry-run] [--ros-args ...]

Node ``dvt_experiment``. Builds the schedule (:mod:`dvt_driver.run.experiment_core`), waits (at
most ``--wait`` seconds) until the driver's lifecycle state is ``active`` and every command
topic has ``--subscribers`` subscriptions (the driver's, plus a recorder's when the commands
are recorded: a command published before that would be lost) and, with ``--recorder``, until
that node subscribes to the sample topics; then publishes each step at its time:

* ``MotorCurrent`` -> ``/dvt/cmd/motor_current`` (std_msgs/Float64 [A]),
* ``SunSpeed`` -> ``/dvt/cmd/sun_speed`` (std_msgs/Float64 [rad/s]),
* ``BrakeCurrents`` -> ``/dvt/cmd/brake_currents`` (sensor_msgs/JointState, brake1..3 [A]),
* ``Gear`` -> ``/dvt/cmd/gear`` (std_msgs/Int8),
* ``MotorOff`` -> service ``/dvt/driver/stop`` (std_srvs/Trigger).

Keep-alive: while the motor is on, the last motor command is re-published whenever none was
sent for ``1 / KEEPALIVE_HZ`` s (50 Hz), so the driver's watchdog (0.5 s) never trips.
Progress (phase changes, driver warnings) goes to stdout.

Exit status: 0 done as scheduled; 1 the driver never became ready; 2 bad arguments; 3 the run
completed but the driver reported refusals, safety or watchdog trips during it (see the
printed reason); 130 interrupted (SIGINT/SIGTERM: the motor is stopped through the stop service
before exiting).
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml

from dvt_driver.errors import ExperimentError
from dvt_driver.run.experiment_core import (
    BrakeCurrents,
    Command,
    Experiment,
    Gear,
    MotorCurrent,
    MotorOff,
    SunSpeed,
    available,
    build,
)
from dvt_model.contract import (
    CMD_BRAKE_CURRENTS,
    CMD_GEAR,
    CMD_MOTOR_CURRENT,
    CMD_SUN_SPEED,
    DIAGNOSTICS,
    DRIVER_NODE,
    SAMPLE_TOPICS,
    SRV_DRIVER_STOP,
)
from dvt_model.presets import safe_load

KEEPALIVE_HZ = 50.0
"""Re-publish rate of the held motor command [Hz] (>= 20 Hz; driver watchdog 0.5 s)."""

SPIN_PERIOD = 0.05
"""While running, callbacks (diagnostics) are processed at least this often [s]."""

WATCHED_COUNTERS = ("refusals", "safety_trips", "watchdog_trips")
"""Driver diagnostics counters that must not grow during a run."""


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    """Parse the non-ROS arguments of ``dvt-experiment``."""
    p = argparse.ArgumentParser(
        prog="dvt-experiment",
        description="Run a named experiment (command schedule) against the DVT driver.")
    p.add_argument("name", nargs="?", help=f"experiment, one of {available()}")
    p.add_argument("--seed", type=int, default=0, help="seed of the random signals (default 0)")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="NAME=VALUE",
                   help="builder setting (YAML value), e.g. --set amplitude=2.0 or "
                        "--set speeds_rpm=[1500,2000]; repeatable")
    p.add_argument("--wait", type=float, default=30.0,
                   help="longest wait for the driver to be active [s] (default 30)")
    p.add_argument("--subscribers", type=int, default=1,
                   help="subscribers each command topic must have before the start (default 1:"
                        " the driver; 2 when a recorder records the commands too)")
    p.add_argument("--recorder", default=None, metavar="NODE",
                   help="also wait until node NODE (e.g. dvt_recorder) subscribes to "
                        "/dvt/joint_states and /dvt/currents, so the recording holds the whole "
                        "experiment")
    p.add_argument("--driver", default=DRIVER_NODE,
                   help="driver node name, for its lifecycle state (default dvt_driver)")
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    p.add_argument("--dry-run", action="store_true",
                   help="print the experiment's summary (YAML) and exit without ROS")
    args = p.parse_args(list(argv))
    if not args.list and not args.name:
        p.error("an experiment name is required (or --list)")
    if not args.wait > 0:
        p.error(f"--wait: expected a number > 0 s, got {args.wait}")
    if args.subscribers < 1:
        p.error(f"--subscribers: expected an integer >= 1, got {args.subscribers}")
    return args


def parse_settings(items: Sequence[str]) -> dict[str, Any]:
    """``["name=value", ...]`` -> builder keyword arguments (values parsed as YAML; lists
    become tuples).

    Raises:
        ExperimentError: an item without ``=`` or with an unparsable value.
    """
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name.strip().isidentifier():
            raise ExperimentError(f"--set {item!r}: expected NAME=VALUE")
        try:
            value = safe_load(text)
        except yaml.YAMLError as exc:
            raise ExperimentError(f"--set {item!r}: value is not valid YAML: {exc}") from exc
        out[name.strip()] = tuple(value) if isinstance(value, list) else value
    return out


@dataclass
class RunStats:
    """What a run did (printed at the end)."""

    steps: int = 0
    keepalives: int = 0
    max_late: float = 0.0  # s, largest delay of a step behind its schedule
    driver_warnings: list[str] = field(default_factory=list)
    counters_start: dict[str, int] = field(default_factory=dict)
    counters_end: dict[str, int] = field(default_factory=dict)

    def grown(self) -> dict[str, int]:
        """Watched driver counters that grew during the run, by how much."""
        return {k: self.counters_end[k] - self.counters_start.get(k, 0)
                for k in WATCHED_COUNTERS
                if k in self.counters_end
                and self.counters_end[k] > self.counters_start.get(k, 0)}


class _Stop:
    def __init__(self) -> None:
        self.flag = False

    def __call__(self, signum: int, frame: object) -> None:
        self.flag = True


class Runner:
    """Publishes an experiment's steps to the driver (rclpy; see the module docstring)."""

    def __init__(self, experiment: Experiment, driver: str = DRIVER_NODE) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from lifecycle_msgs.srv import GetState
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Int8
        from std_srvs.srv import Trigger

        from dvt_model import rosutil

        self.exp = experiment
        self.node = Node("dvt_experiment")
        qos = rosutil.COMMAND_QOS
        self._Float64, self._Int8, self._JointState = Float64, Int8, JointState
        self._Trigger, self._GetState = Trigger, GetState
        self.pub_current = self.node.create_publisher(Float64, CMD_MOTOR_CURRENT, qos)
        self.pub_speed = self.node.create_publisher(Float64, CMD_SUN_SPEED, qos)
        self.pub_brakes = self.node.create_publisher(JointState, CMD_BRAKE_CURRENTS, qos)
        self.pub_gear = self.node.create_publisher(Int8, CMD_GEAR, qos)
        self.stop_client = self.node.create_client(Trigger, SRV_DRIVER_STOP)
        self.state_client = self.node.create_client(GetState, f"/{driver}/get_state")
        self.diag: dict[str, Any] = {}
        self.diag_count = 0
        self._warned: set[str] = set()
        self.stats = RunStats()
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS, self._on_diag, 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._motor: Command | None = None  # last motor command while the motor is on
        self._last_motor_pub = -1e9

    # ------------------------------------------------------------------ helpers
    def log(self, text: str) -> None:
        """Print one progress line."""
        print(f"dvt-experiment: {text}", flush=True)

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name != DRIVER_NODE:
                continue
            values = {kv.key: kv.value for kv in st.values}
            self.diag = values
            self.diag_count += 1
            level = int.from_bytes(st.level, "little") if isinstance(st.level, bytes) \
                else int(st.level)
            if level >= 1 and st.message not in self._warned and len(self._warned) < 50:
                self._warned.add(st.message)
                self.stats.driver_warnings.append(st.message)
                self.log(f"driver: {st.message}")

    def counters(self) -> dict[str, int]:
        """Watched counters from the last driver diagnostics (empty if none yet)."""
        out: dict[str, int] = {}
        for k in WATCHED_COUNTERS:
            try:
                out[k] = int(self.diag[k])
            except (KeyError, ValueError):
                continue
        return out

    def spin_for(self, seconds: float) -> None:
        """Process callbacks for about ``seconds`` (bounded)."""
        end = time.monotonic() + max(0.0, seconds)
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            self.executor.spin_once(timeout_sec=min(left, 0.05))

    def driver_state(self, timeout: float = 1.0) -> str | None:
        """The driver's lifecycle state label, ``None`` if it does not answer in ``timeout``."""
        if not self.state_client.service_is_ready():
            return None
        fut = self.state_client.call_async(self._GetState.Request())
        end = time.monotonic() + timeout
        while not fut.done() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
        if not fut.done():
            fut.cancel()
            return None
        res = fut.result()
        return None if res is None else str(res.current_state.label)

    def wait_ready(self, timeout: float, stop: _Stop, subscribers: int = 1,
                   recorder: str | None = None) -> str | None:
        """Wait until the driver is active, every command topic has ``subscribers`` and (if
        given) node ``recorder`` subscribes to the sample topics.

        Returns ``None`` when ready, else what was still missing when ``timeout`` ran out.
        """
        end = time.monotonic() + timeout
        missing = "driver lifecycle state unknown"
        next_state = 0.0
        state: str | None = None
        while not stop.flag:
            now = time.monotonic()
            if now >= next_state:
                state = self.driver_state(timeout=min(1.0, max(0.05, end - now)))
                next_state = time.monotonic() + 0.2
            unmatched = [pub.topic_name for pub in (self.pub_current, self.pub_speed,
                                                    self.pub_brakes, self.pub_gear)
                         if pub.get_subscription_count() < subscribers]
            if state != "active":
                missing = f"driver lifecycle state is {state or 'unknown (no answer)'}"
            elif unmatched:
                missing = f"fewer than {subscribers} subscriber(s) on {unmatched}"
            elif not self.stop_client.service_is_ready():
                missing = f"service {SRV_DRIVER_STOP} not available"
            elif recorder is not None and not all(
                    any(i.node_name == recorder
                        for i in self.node.get_subscriptions_info_by_topic(t))
                    for t in SAMPLE_TOPICS):
                missing = f"node {recorder} does not subscribe to {list(SAMPLE_TOPICS)}"
            else:
                return None
            if time.monotonic() >= end:
                return missing
            self.executor.spin_once(timeout_sec=0.05)
        return "interrupted"

    def call_stop(self, timeout: float = 2.0) -> bool:
        """Call the driver's stop service (motor off); True if it answered in time."""
        self._motor = None
        if not self.stop_client.wait_for_service(timeout_sec=min(timeout, 1.0)):
            return False
        fut = self.stop_client.call_async(self._Trigger.Request())
        end = time.monotonic() + timeout
        while not fut.done() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
        return fut.done() and fut.result() is not None

    def publish(self, cmd: Command, now: float) -> None:
        """Send one command to the driver."""
        if isinstance(cmd, MotorCurrent):
            self.pub_current.publish(self._Float64(data=float(cmd.amps)))
            self._motor, self._last_motor_pub = cmd, now
        elif isinstance(cmd, SunSpeed):
            self.pub_speed.publish(self._Float64(data=float(cmd.rad_s)))
            self._motor, self._last_motor_pub = cmd, now
        elif isinstance(cmd, BrakeCurrents):
            msg = self._JointState()
            msg.header.stamp = self.node.get_clock().now().to_msg()
            msg.name = ["brake1", "brake2", "brake3"]
            msg.effort = [float(a) for a in cmd.amps]
            self.pub_brakes.publish(msg)
        elif isinstance(cmd, Gear):
            self.pub_gear.publish(self._Int8(data=int(cmd.gear)))
        elif isinstance(cmd, MotorOff):
            self.motor_off()

    def motor_off(self) -> None:
        """Switch the motor off through the stop service (0 A if it does not answer)."""
        if not self.call_stop():
            self.log(f"warning: {SRV_DRIVER_STOP} did not answer; sending 0 A instead")
            self.pub_current.publish(self._Float64(data=0.0))

    # ------------------------------------------------------------------ run
    def run(self, stop: _Stop) -> bool:
        """Publish the schedule in real time; False if interrupted."""
        exp = self.exp
        steps = exp.steps
        period = 1.0 / KEEPALIVE_HZ
        k = 0
        phase = ""
        t0 = time.monotonic()
        last_spin = -1.0
        while not stop.flag:
            now = time.monotonic() - t0
            while k < len(steps) and steps[k].t <= now:
                self.stats.max_late = max(self.stats.max_late, now - steps[k].t)
                self.publish(steps[k].command, now)
                self.stats.steps += 1
                k += 1
                now = time.monotonic() - t0
            label = exp.phase_at(now)
            if label and label != phase:
                phase = label
                self.log(f"t={now:6.2f} s  phase {label}")
            if self._motor is not None and now - self._last_motor_pub >= period:
                self.publish(self._motor, now)
                self.stats.keepalives += 1
            if k >= len(steps) and now >= exp.duration:
                return True
            nxt = min(steps[k].t if k < len(steps) else exp.duration,
                      self._last_motor_pub + period if self._motor is not None else 1e9,
                      exp.duration)
            if now - last_spin >= SPIN_PERIOD:  # diagnostics, service answers
                last_spin = now
                self.executor.spin_once(timeout_sec=0.0)
            wait = min(nxt - (time.monotonic() - t0), SPIN_PERIOD)
            if wait > 0:
                time.sleep(wait)  # cheaper than a wait set per command at 200 Hz
        return False

    def close(self) -> None:
        """Destroy the node."""
        self.executor.remove_node(self.node)
        self.node.destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-experiment``; returns the exit status."""
    raw = list(sys.argv if argv is None else argv)
    try:
        from rclpy.utilities import remove_ros_args

        plain = remove_ros_args(raw)[1:]
    except ImportError:  # pragma: no cover
        plain = raw[1:]
    args = parse_args(plain)
    if args.list:
        for name in available():
            e = build(name)
            print(f"{name:18s} {e.duration:6.1f} s  {e.description}")
        return 0
    try:
        exp = build(args.name, seed=args.seed, **parse_settings(args.settings))
    except ExperimentError as exc:
        print(f"dvt-experiment: error: {exc}", file=sys.stderr)
        return 2
    if args.dry_run:
        print(yaml.safe_dump(exp.to_mapping(), sort_keys=False), end="")
        return 0

    import rclpy
    from rclpy.signals import SignalHandlerOptions

    stop = _Stop()
    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=raw, signal_handler_options=SignalHandlerOptions.NO)
    runner = Runner(exp, driver=args.driver)
    status = 0
    try:
        runner.log(f"{exp.name} (seed {exp.seed}, {exp.duration:.1f} s, {len(exp.steps)} "
                   f"steps): waiting up to {args.wait:g} s for the driver")
        missing = runner.wait_ready(args.wait, stop, args.subscribers, args.recorder)
        if missing == "interrupted":
            runner.log("interrupted while waiting for the driver")
            return 130
        if missing is not None:
            runner.log(f"error: driver not ready after {args.wait:g} s: {missing}")
            return 1
        runner.spin_for(0.3)  # matched both ways; take a first diagnostics message if due
        runner.stats.counters_start = runner.counters()
        runner.log("driver active; starting")
        done = runner.run(stop)
        if not done:
            runner.log("interrupted: stopping the motor")
            ok = runner.call_stop()
            runner.log("motor stopped" if ok else f"warning: {SRV_DRIVER_STOP} did not answer")
            return 130
        # final diagnostics (the driver publishes at least once per second)
        seen = runner.diag_count
        end = time.monotonic() + 2.5
        while runner.diag_count < seen + 1 and time.monotonic() < end and not stop.flag:
            runner.executor.spin_once(timeout_sec=0.05)
        runner.stats.counters_end = runner.counters()
        s = runner.stats
        runner.log(f"done: {s.steps} steps, {s.keepalives} keep-alives, largest step delay "
                   f"{s.max_late * 1e3:.1f} ms")
        grown = s.grown()
        if grown:
            runner.log(f"error: the driver reported {grown} during the run; last refusal "
                       f"{runner.diag.get('last_refusal', '')!r}, last trip "
                       f"{runner.diag.get('last_trip', '')!r}")
            status = 3
        return status
    finally:
        runner.close()
        rclpy.try_shutdown()
        for s_, h in old.items():
            signal.signal(s_, h)


if __name__ == "__main__":
    sys.exit(main())
