"""``dvt_driver_node``: lifecycle driver of the DVT motor/brake controller (thin rclpy layer).

A ``rclpy.lifecycle.LifecycleNode`` named ``dvt_driver`` (see ``docs/driver.md``):

* ``configure`` validates the parameters (:func:`dvt_driver.link.settings.parse_settings`),
  opens the serial link (:class:`dvt_driver.link.serial_link.SerialLink`) and starts the I/O
  thread, which runs the controller session (:class:`dvt_driver.link.session.Session`: HELLO,
  CONFIG, answers, stream timeout, reconnect), decodes samples and keeps the counters (nothing
  published);
* ``activate`` starts publishing ``/dvt/joint_states`` and ``/dvt/currents`` (one message each
  per controller sample, identical stamps: the controller clock mapped to ROS time by
  :class:`dvt_driver.link.clock.ClockMapper`) and sending COMMANDs (on every accepted command
  and as a keep-alive at ``keepalive_rate_hz``). In a protocol-version-2 session
  ``/dvt/joint_states`` also carries ``position`` [rad] of ``sun_shaft`` and ``carrier3``
  (the unwrapped encoder counts times 2 pi / counts per revolution from the HELLO_ACK; same
  message, same stamp); a version-1 controller gives speeds only;
* ``deactivate`` sends the safe state (motor off; brakes held, or released when
  ``release_brakes_on_deactivate``) and stops commanding; ``cleanup`` / ``shutdown`` stop the
  thread and close the port. Transition requests that are invalid in the current state (by
  label or by id) are answered ``success=False``; they never end the process.

Commands (``rosutil.COMMAND_QOS``), accepted while active, checked by
:class:`dvt_driver.link.safety.Supervisor` (refused, never clamped): ``/dvt/cmd/motor_current``
(std_msgs/Float64 [A]), ``/dvt/cmd/sun_speed`` (std_msgs/Float64 [rad/s]),
``/dvt/cmd/brake_currents`` (sensor_msgs/JointState, ``name`` subset of brake1..3, ``effort``
[A]), ``/dvt/cmd/gear`` (std_msgs/Int8, 0..3); services ``/dvt/driver/stop`` and
``/dvt/driver/release_brakes`` (std_srvs/Trigger). ``/diagnostics`` once per second (and at once
after a refusal or trip). All names come from :mod:`dvt_model.contract`.

The serial I/O runs in one dedicated thread: it feeds the session with time, link events and
received frames and executes the actions the session returns (reopen, HELLO/CONFIG/COMMAND
frames), decodes, stamps and publishes samples; the executor only runs command callbacks,
services, the lifecycle and the diagnostics timer. What that thread owns besides the session is
in :mod:`dvt_driver.link.node_io`, the ``/diagnostics`` in
:mod:`dvt_driver.link.node_diagnostics` (the node's base class).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Int8
from std_srvs.srv import Trigger

from dvt_driver.errors import CommandRefusedError, DvtDriverError, LinkError, ProtocolError
from dvt_driver.link.node_diagnostics import DriverDiagnostics
from dvt_driver.link.node_io import _flags, _Io
from dvt_driver.link.protocol import Command, Mode, Sample
from dvt_driver.link.safety import Supervisor
from dvt_driver.link.serial_link import LinkState, SerialLink
from dvt_driver.link.session import Actions, LogLevel
from dvt_driver.link.settings import DEFAULT_SETTINGS, DriverSettings, parse_settings
from dvt_model import rosutil
from dvt_model.contract import (
    CMD_BRAKE_CURRENTS,
    CMD_GEAR,
    CMD_MOTOR_CURRENT,
    CMD_SUN_SPEED,
    CURRENTS,
    DIAGNOSTICS,
    DRIVER_NODE,
    JOINT_STATES,
    SRV_DRIVER_RELEASE_BRAKES,
    SRV_DRIVER_STOP,
)

READ_SLICE = 0.005  # s: longest single wait for bytes (bounds command latency when idle)
READ_PERIOD = 0.004  # s: read at most this often while data flows (4 samples per wake-up at
# 1 kHz instead of one: each wake-up costs far more CPU than decoding a frame); a new command
# cuts the pause short, so command latency stays ~0
DOWN_POLL_MAX = 0.05  # s: longest sleep of the I/O thread while the link is down

_DESCRIPTIONS = {
    "port": "serial device of the controller (e.g. /dev/ttyUSB0, or the plant's pty link)",
    "baud": "line rate [bit/s]",
    "sample_rate_hz": "controller sample rate requested at connect [Hz], 1..2000",
    "max_motor_current": "drive-motor current limit [A] (<= 12 N m / 0.3732 N m/A)",
    "max_brake_current": "band-brake current limit [A] (<= 6 A)",
    "max_sun_speed": "sun-shaft speed limit [rad/s] (<= 2400 rpm = 251.33 rad/s)",
    "watchdog_timeout": "no fresh motor command for this long [s] -> motor off",
    "keepalive_rate_hz": "COMMAND re-send rate while active [Hz]",
    "gear_engage_current": "brake current that holds the band of the selected gear [A]",
    "gear_ramp_time": "duration of the release and engage ramps of a shift [s]",
    "gear_overlap": "engage starts this long before the release ends [s]; < 0 = neutral gap",
    "clock_window": "window of the controller-clock offset estimate [s]",
    "reconnect_interval": "first pause between attempts to reopen a vanished port [s] "
                          "(backs off to at most max(this, 0.04 s))",
    "release_brakes_on_deactivate": "deactivate also releases the brakes (default: hold)",
}



class DriverNode(DriverDiagnostics):
    """The lifecycle driver node (module docstring; ``docs/driver.md``)."""

    def __init__(self) -> None:
        super().__init__(DRIVER_NODE)
        dyn = {"dynamic_typing": True}
        for name, default in DEFAULT_SETTINGS.items():
            self.declare_parameter(name, default, ParameterDescriptor(
                description=_DESCRIPTIONS[name], **dyn))
        self.declare_parameter("autostart", False, ParameterDescriptor(
            description="configure and activate at start (retries configure while the port "
                        "is missing)", **dyn))
        self._lock = threading.Lock()  # supervisor and command state
        self._send_lock = threading.RLock()  # the session, sequence numbers and sends
        self.settings: DriverSettings | None = None
        self.supervisor: Supervisor | None = None
        self.link: SerialLink | None = None
        self._io: _Io | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._send_now = threading.Event()
        self._active = False
        self._state_label = "unconfigured"
        self._entities: list[Any] = []
        self._urgent = threading.Event()
        self._diag_last = time.monotonic()
        self._diag_prev: dict[str, int] = {}
        self._diag_prev_samples = 0
        self._diag_prev_time = time.monotonic()
        self._refusals_logged = 0
        self._transition_errors = 0
        self._last_config_error = ""
        self._io_cycle_max = 0.0  # [s] longest interval between two I/O cycles while active
        self.pub_js = self.create_lifecycle_publisher(JointState, JOINT_STATES,
                                                      rosutil.SENSOR_QOS)
        self.pub_cur = self.create_lifecycle_publisher(JointState, CURRENTS, rosutil.SENSOR_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, DIAGNOSTICS, 10)
        self.create_timer(0.1, self._diag_tick)
        self._guard_change_state()
        self._autostart_timer = None
        self._last_config_link_error = False
        if self._param_bool("autostart"):
            self._autostart_timer = self.create_timer(0.5, self._autostart)


    # -- helpers ---------------------------------------------------------------------------

    def _param_bool(self, name: str) -> bool:
        value = self.get_parameter(name).value
        return value is True or (isinstance(value, str) and value.lower() == "true")

    def _guard_change_state(self) -> None:
        """Answer an invalid transition *id* with success=False instead of an exception that
        would end the executor (rclpy raises inside its own service callback then)."""
        service = getattr(self, "_service_change_state", None)
        if service is None:
            return
        original = service.callback

        def guarded(req: ChangeState.Request, resp: ChangeState.Response
                    ) -> ChangeState.Response:
            try:
                result: ChangeState.Response = original(req, resp)
                return result
            except Exception as exc:  # rclpy's RCLError for an unknown transition id
                self._transition_errors += 1
                self.get_logger().warning(
                    f"change_state refused: transition id {req.transition.id} label "
                    f"{req.transition.label!r} is not valid in state "
                    f"'{self._state_label}': {exc}")
                resp.success = False
                return resp

        service.callback = guarded

    def _autostart(self) -> None:
        if self._state_label != "unconfigured":
            self._cancel_autostart()
            return
        result = self.trigger_configure()
        if result == TransitionCallbackReturn.SUCCESS:
            self._cancel_autostart()
            self.trigger_activate()
        elif not self._last_config_link_error:
            # invalid parameters: retrying cannot help (the port may still appear: retry then)
            self.get_logger().error("autostart: configure failed, not retrying")
            self._cancel_autostart()

    def _cancel_autostart(self) -> None:
        if self._autostart_timer is not None:
            self._autostart_timer.cancel()
            self.destroy_timer(self._autostart_timer)
            self._autostart_timer = None

    # -- lifecycle -------------------------------------------------------------------------

    def _read_settings(self) -> DriverSettings:
        values = {name: self.get_parameter(name).value for name in DEFAULT_SETTINGS}
        return parse_settings(values)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            settings = self._read_settings()
        except DvtDriverError as exc:
            self._last_config_error = str(exc)
            self._last_config_link_error = False
            self.get_logger().error(f"configure failed: invalid parameter: {exc}")
            return TransitionCallbackReturn.FAILURE
        link = SerialLink(settings.port, settings.baud)
        try:
            link.open()
        except LinkError as exc:
            if str(exc) != self._last_config_error:  # autostart retries: log each cause once
                self.get_logger().error(f"configure failed: {exc}")
            self._last_config_error = str(exc)
            self._last_config_link_error = True
            return TransitionCallbackReturn.FAILURE
        self.settings = settings
        self.link = link
        self.supervisor = Supervisor(settings.limits, settings.watchdog_timeout, settings.shift)
        self._io = _Io(settings, link)
        self._run(self._io.session.link_opened(time.monotonic()), time.monotonic())
        self._diag_prev = {}
        self._create_interfaces()
        self._stop.clear()
        self._thread = threading.Thread(target=self._io_main, name="dvt_driver_io", daemon=True)
        self._thread.start()
        self._state_label = "inactive"
        self._last_config_error = ""
        self.get_logger().info(
            f"configured: {settings.port} at {settings.baud} baud, {settings.sample_rate_hz:g} "
            f"Hz, limits motor {settings.limits.max_motor_current:.4g} A, brakes "
            f"{settings.limits.max_brake_current:.4g} A, sun {settings.limits.max_sun_speed:.5g} "
            f"rad/s, watchdog {settings.watchdog_timeout:g} s")
        self._urgent.set()
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        sup = self.supervisor
        if sup is None:
            return TransitionCallbackReturn.FAILURE
        with self._lock:
            sup.stop()  # activation never resumes an old motor set-point
        super().on_activate(state)
        self._active = True
        self._state_label = "active"
        self._send_now.set()
        self.get_logger().info("active: publishing samples, commands accepted")
        self._urgent.set()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._go_safe("deactivate")
        super().on_deactivate(state)
        self._state_label = "inactive"
        self._urgent.set()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._teardown()
        self._state_label = "unconfigured"
        self.get_logger().info("cleaned up: port closed")
        self._urgent.set()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._active:
            self._go_safe("shutdown")
            super().on_deactivate(state)
        self._teardown()
        self._state_label = "finalized"
        self._urgent.set()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error(f"error during a transition from '{state.label}': cleaning up")
        try:
            if self._active:
                self._go_safe("error")
            self._teardown()
        except Exception as exc:  # never let the error handler fail
            self.get_logger().error(f"cleanup after error failed: {exc!r}")
        self._state_label = "unconfigured"
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown_hook(self) -> None:
        """Called by ``rosutil.spin`` when the process stops: safe state, close the port."""
        if self._active:
            self._go_safe("process exit")
        self._teardown()

    def _go_safe(self, why: str) -> None:
        sup = self.supervisor
        if sup is not None:
            with self._lock:
                sup.stop()
                if self.settings is not None and self.settings.release_brakes_on_deactivate:
                    sup.release_brakes()
        self._active = False
        sent = self._send_command(time.monotonic())
        brakes = "released" if (self.settings is not None
                                and self.settings.release_brakes_on_deactivate) else "held"
        self.get_logger().info(f"{why}: motor off, brakes {brakes} "
                               f"({'sent' if sent else 'NOT sent: link down'})")

    def _teardown(self) -> None:
        self._active = False
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=2.0)
            if thread.is_alive():
                self.get_logger().error("I/O thread did not stop within 2 s")
        link, self.link = self.link, None
        if link is not None:
            link.close()
        for entity in self._entities:
            if isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            else:
                self.destroy_service(entity)
        self._entities = []

    def _create_interfaces(self) -> None:
        q = rosutil.COMMAND_QOS
        self._entities = [
            self.create_subscription(Float64, CMD_MOTOR_CURRENT, self._on_motor_current, q),
            self.create_subscription(Float64, CMD_SUN_SPEED, self._on_sun_speed, q),
            self.create_subscription(JointState, CMD_BRAKE_CURRENTS, self._on_brakes, q),
            self.create_subscription(Int8, CMD_GEAR, self._on_gear, q),
            self.create_service(Trigger, SRV_DRIVER_STOP, self._on_stop),
            self.create_service(Trigger, SRV_DRIVER_RELEASE_BRAKES, self._on_release_brakes),
        ]

    # -- commands (executor thread) --------------------------------------------------------

    def _command(self, what: str, apply: Callable[[Supervisor, float], Any]) -> None:
        sup = self.supervisor
        if sup is None:
            return
        now = time.monotonic()
        with self._lock:
            if not self._active:
                self._log_refusal(sup.refuse(what, "driver is not active (activate it first)"))
                return
            try:
                apply(sup, now)
            except CommandRefusedError as exc:
                self._log_refusal(exc)
        self._send_now.set()

    def _log_refusal(self, exc: CommandRefusedError) -> None:
        self._refusals_logged += 1
        n = self._refusals_logged
        if n <= 20 or n % 100 == 0:
            self.get_logger().warning(f"command refused ({n}): {exc}")
        self._urgent.set()

    def _on_motor_current(self, msg: Float64) -> None:
        self._command("motor_current", lambda s, now: s.motor_current(msg.data, now))

    def _on_sun_speed(self, msg: Float64) -> None:
        self._command("sun_speed", lambda s, now: s.sun_speed(msg.data, now))

    def _on_brakes(self, msg: JointState) -> None:
        self._command("brake_currents",
                      lambda s, now: s.brake_currents(list(msg.name), list(msg.effort), now))

    def _on_gear(self, msg: Int8) -> None:
        def apply(s: Supervisor, now: float) -> None:
            plan = s.select_gear(int(msg.data), now)
            self.get_logger().info(f"shift to gear {plan.gear}: brakes {plan.start} -> "
                                   f"{plan.target} A over {plan.t_end - plan.t_start:.3f} s")
        self._command("gear", apply)

    def _on_stop(self, req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        sup = self.supervisor
        if sup is not None:
            with self._lock:
                sup.stop()
        self._send_now.set()
        resp.success = True
        resp.message = ("motor off, brakes unchanged" if self._active
                        else "motor off (driver inactive: no motor command is being sent)")
        self.get_logger().info(f"stop service: {resp.message}")
        return resp

    def _on_release_brakes(self, req: Trigger.Request, resp: Trigger.Response
                           ) -> Trigger.Response:
        sup = self.supervisor
        if sup is None or not self._active:
            resp.success = False
            resp.message = "driver is not active: no command can be sent"
            return resp
        with self._lock:
            sup.release_brakes()
        self._send_now.set()
        resp.success = True
        resp.message = "brakes released (0 A), motor unchanged"
        self.get_logger().info(f"release_brakes service: {resp.message}")
        return resp

    # -- I/O thread ------------------------------------------------------------------------

    def _send_command(self, now: float) -> bool:
        """Send the supervisor's output now (any thread). False if not sent."""
        sup, io, link = self.supervisor, self._io, self.link
        if sup is None or io is None or link is None:
            return False
        # the output is computed under the send lock, so the last COMMAND on the wire always
        # reflects the latest supervisor state (deactivate's OFF cannot be overtaken)
        with self._send_lock:
            if not io.session.open:
                return False
            with self._lock:
                out, event = sup.output(now)
            cmd = Command(io.session.next_seq(), Mode(int(out.mode)), float(out.setpoint),
                          (float(out.brakes[0]), float(out.brakes[1]), float(out.brakes[2])))
            try:
                ok = link.send(cmd)
            except ProtocolError as exc:  # cannot happen: the supervisor output is finite
                self.get_logger().error(f"command not encodable, not sent: {exc}")
                ok = False
            if ok:
                io.session.sent(cmd, now)
        if event is not None:
            self.get_logger().warning(event)
            self._urgent.set()
        return ok

    def _run(self, acts: Actions, now: float) -> None:
        """Execute the session's actions (except ``reopen``, ``reset`` and ``duplicate``, which
        the caller handles): log, send HELLO/CONFIG frames, send a COMMAND."""
        logger = self.get_logger()
        for level, text in acts.logs:  # one call site per severity (rclpy requires it)
            if level >= LogLevel.ERROR:
                logger.error(text)
            elif level >= LogLevel.WARN:
                logger.warning(text)
            else:
                logger.info(text)
        io, link = self._io, self.link
        if acts.send and io is not None and link is not None:
            with self._send_lock:
                for frame in acts.send:
                    if link.send(frame):
                        io.session.sent(frame, now)
        if acts.command:
            self._send_command(now)
        if acts.changed:
            self._urgent.set()

    def _io_main(self) -> None:
        io = self._io
        if io is None:
            return
        try:
            self._io_loop(io)
        except Exception as exc:  # last resort: report, keep the process alive
            self.get_logger().fatal(f"I/O thread stopped by an unexpected error: {exc!r}")

    def _shifting(self) -> bool:
        sup = self.supervisor
        return sup is not None and sup.shift is not None

    def _io_loop(self, io: _Io) -> None:
        link, session = io.link, io.session
        clock = self.get_clock()
        last_cycle: float | None = None
        while not self._stop.is_set():
            now = time.monotonic()
            cycle_start = now
            active = self._active
            if not active:
                self._send_now.clear()  # nothing is sent while inactive
                last_cycle = None
            else:
                # the thread's longest absence (waits are <= READ_SLICE): a longer one is the
                # process not being run, which no keep-alive schedule can help
                if last_cycle is not None:
                    self._io_cycle_max = max(self._io_cycle_max, now - last_cycle)
                last_cycle = now
            if link.state is not LinkState.CONNECTED:
                with self._send_lock:
                    acts = session.link_lost(now, link.last_error or "")
                    due = session.poll(now, active=active)
                self._run(acts, now)
                if due.reopen:
                    ok = link.reopen()
                    now = time.monotonic()
                    with self._send_lock:
                        acts = (session.link_opened(now) if ok
                                else session.reopen_failed(now, link.last_error or ""))
                    self._run(acts, now)
                    if ok:
                        continue
                with self._send_lock:
                    pause = session.time_to_next(time.monotonic(), active=active)
                self._stop.wait(min(DOWN_POLL_MAX, pause))
                continue
            with self._send_lock:
                acts = session.poll(now, active=active, shifting=self._shifting(),
                                    urgent=self._send_now.is_set())
            if acts.command or not active or not session.open:
                self._send_now.clear()  # sent now, or nothing to send it on (the session asks
                # for a COMMAND itself once it opens)
            self._run(acts, now)
            wait = READ_SLICE
            if active and session.open:
                with self._send_lock:
                    wait = min(wait, session.time_to_next(time.monotonic(), active=True))
            messages = link.read_messages(wait)
            if messages:
                host_ns = clock.now().nanoseconds
                for msg in messages:
                    if isinstance(msg, Sample):
                        self._on_sample(io, msg, host_ns)
                    else:
                        t = time.monotonic()
                        with self._send_lock:
                            acts = session.on_message(msg, t)
                        self._run(acts, t)
                rest = cycle_start + READ_PERIOD - time.monotonic()
                if active and session.open:
                    with self._send_lock:
                        rest = min(rest, session.time_to_next(time.monotonic(), active=True))
                if rest > 0:
                    self._send_now.wait(rest)  # wakes at once for a new command

    def _on_sample(self, io: _Io, msg: Sample, host_ns: int) -> None:
        now = time.monotonic()
        with self._send_lock:
            acts = io.session.on_sample(msg, now)
        if acts.duplicate:
            return
        sup = self.supervisor
        if acts.reset:
            io.clock.reset()
            if sup is not None:
                with self._lock:
                    reason = sup.controller_reset()
                self.get_logger().warning(f"{reason} (seq {msg.seq}, t {msg.t_us} µs)")
            self._send_now.set()
        self._run(acts, now)
        stamp = io.clock.map(msg.t_us, host_ns)
        io.last_status = msg.status
        io.last_sample = msg
        pos = io.positions(msg, acts.reset)  # every sample: the unwrapping never skips one
        if sup is not None:
            with self._lock:
                trip = sup.observe(msg.sun_speed, _flags(msg.status))
            if trip is not None:
                self.get_logger().warning(f"safety trip: {trip}")
                self._send_now.set()
                self._urgent.set()
                self._urgent.set()
        if self._active:
            # the two messages are built once (rosutil.joint_state) and refilled per sample:
            # publish() serialises synchronously, so reuse is safe and saves ~30 µs per sample
            js, cur = (io.js_msg if pos is None else io.js_pos_msg), io.cur_msg
            if pos is not None:
                js.position[0], js.position[1] = pos
            sec, nanosec = divmod(stamp, 1_000_000_000)
            js.header.stamp.sec = cur.header.stamp.sec = sec
            js.header.stamp.nanosec = cur.header.stamp.nanosec = nanosec
            js.velocity[0], js.velocity[1] = msg.sun_speed, msg.carrier3_speed
            b = msg.brake_currents
            e = cur.effort
            e[0], e[1], e[2], e[3] = msg.motor_current, b[0], b[1], b[2]
            self.pub_js.publish(js)
            self.pub_cur.publish(cur)
            io.published += 1


def main(args: list[str] | None = None) -> None:
    rosutil.init(args)
    node = DriverNode()
    rosutil.spin(node)


if __name__ == "__main__":
    main()
