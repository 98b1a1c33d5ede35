"""The driver node's ``/diagnostics`` (:mod:`dvt_driver.link.node`): once per second (and at
once after a refusal or trip), the link, session, supervisor and clock counters, and the
problems that raise the level (link down, no session, no or too few samples, a latched FAULT,
a refused configuration, overspeed, a counter that grew)."""

from __future__ import annotations

import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.lifecycle import LifecycleNode
from rclpy.publisher import Publisher

from dvt_driver.link.node_io import _Io
from dvt_driver.link.protocol import Status
from dvt_driver.link.safety import MotorMode, Supervisor
from dvt_driver.link.serial_link import LinkState, SerialLink
from dvt_driver.link.settings import DriverSettings
from dvt_model import rosutil
from dvt_model.contract import DRIVER_NODE

_INFORMATIVE = frozenset({"frames_good"})  # counters whose growth is no problem


class DriverDiagnostics(LifecycleNode):
    """The diagnostics part of :class:`~dvt_driver.link.node.DriverNode` (its base class): reads
    the node's state, which :class:`~dvt_driver.link.node.DriverNode` sets up."""

    settings: DriverSettings | None
    supervisor: Supervisor | None
    link: SerialLink | None
    _io: _Io | None
    _lock: threading.Lock
    _active: bool
    _state_label: str
    _urgent: threading.Event
    _diag_last: float
    _diag_prev: dict[str, int]
    _diag_prev_samples: int
    _diag_prev_time: float
    _transition_errors: int
    _last_config_error: str
    _io_cycle_max: float
    pub_diag: Publisher

    def _diag_tick(self) -> None:
        now = time.monotonic()
        if not self._urgent.is_set() and now - self._diag_last < 1.0:
            return
        self._urgent.clear()
        self._diag_last = now
        try:
            self.pub_diag.publish(self._diagnostics(now))
        except Exception as exc:  # diagnostics must never take the node down
            self.get_logger().error(f"diagnostics failed: {exc!r}")

    def _diagnostics(self, now: float) -> DiagnosticArray:
        io, link, sup, s = self._io, self.link, self.supervisor, self.settings
        values: dict[str, Any] = {"lifecycle_state": self._state_label,
                                  "invalid_transition_ids": self._transition_errors}
        if io is None or link is None or sup is None or s is None:
            level = rosutil.OK if not self._last_config_error else rosutil.ERROR
            message = (self._state_label if not self._last_config_error
                       else f"configure failed: {self._last_config_error}")
            values["last_configure_error"] = self._last_config_error
            return rosutil.diagnostic(self, DRIVER_NODE, level, message, values)
        st = link.stats
        ses = io.session
        with self._lock:
            brakes = sup.brakes_at(now)
        dt = max(1e-3, now - self._diag_prev_time)
        rate = (ses.samples - self._diag_prev_samples) / dt
        self._diag_prev_time, self._diag_prev_samples = now, ses.samples
        counters = {
            "frames_good": st.frames_good, "frames_bad": st.frames_bad,
            "crc_errors": st.crc_errors, "bytes_discarded": st.bytes_discarded,
            "lost_samples": st.lost_samples, "controller_resets": st.resets,
            "reconnects": st.reconnects, "disconnects": st.disconnects,
            "write_errors": st.write_errors, "duplicates": ses.duplicates,
            "stream_timeouts": ses.stream_timeouts, "nacks": ses.nacks,
            "unanswered": ses.unanswered, "refusals": sup.refusals,
            "safety_trips": sup.trips, "watchdog_trips": sup.watchdog_trips,
        }
        prev, self._diag_prev = self._diag_prev, dict(counters)
        grew = [k for k, v in counters.items()
                if prev and k not in _INFORMATIVE and v > prev.get(k, 0)]
        values.update({
            "port": s.port, "baud": s.baud, "link_state": link.state.value,
            "last_link_error": link.last_error or "",
            "session": ses.open, "session_state": ses.state.value,
            "hello_give_ups": ses.hello_give_ups, "reopen_attempts": ses.reopen_attempts,
            "firmware_id": ses.hello_ack.firmware_id if ses.hello_ack else "",
            "protocol_version": ses.protocol_version or 0,
            "version_fallbacks": ses.version_fallbacks,
            "positions": ses.counts_per_rev is not None,
            "encoder_counts_per_rev": (list(ses.counts_per_rev) if ses.counts_per_rev
                                       else []),
            "controller_watchdog_s": (f"{ses.hello_ack.watchdog_timeout_us * 1e-6:g}"
                                      if ses.hello_ack else ""),
            "sample_rate_hz": f"{rate:.1f}", "expected_sample_rate_hz": f"{s.sample_rate_hz:g}",
            "samples": ses.samples, "samples_published": io.published,
            **counters,
            "bytes_received": st.bytes_received,
            "commands_sent": ses.commands_sent, "acks": ses.acks,
            "command_gap_max_ms": f"{ses.command_gap_max * 1e3:.1f}",
            "io_cycle_max_ms": f"{self._io_cycle_max * 1e3:.1f}",
            "nacks_by_reason": ",".join(f"{k}={v}" for k, v in ses.nacks_by_reason.items()),
            "last_refusal": sup.last_refusal, "last_trip": sup.last_trip,
            "mode": MotorMode(sup.mode).name, "setpoint": f"{sup.setpoint:g}",
            "brake_setpoints": ",".join(f"{b:g}" for b in brakes),
            "gear": "" if sup.gear is None else sup.gear,
            "shifting": sup.shift is not None,
            "overspeed": sup.overspeed,
            "controller_status": f"0x{int(io.last_status):02X}",
            "stamp_offset_ns": "" if io.clock.offset_ns is None else io.clock.offset_ns,
            "stamp_guarded": io.clock.guarded,
            "stamp_resets": io.clock.resets,
        })
        level, problems = rosutil.OK, []
        if self._active:
            if link.state is not LinkState.CONNECTED:
                level = rosutil.ERROR
                problems.append(f"link {link.state.value}: {link.last_error}")
            elif not ses.open:
                level = rosutil.ERROR
                problems.append("no session with the controller (no HELLO_ACK)" if
                                not ses.hello_refused else "controller refused our protocol")
            elif rate < 0.5:
                level = rosutil.ERROR
                problems.append("no samples")
            elif rate < 0.9 * s.sample_rate_hz:
                level = max(level, rosutil.WARN)
                problems.append(f"sample rate {rate:.0f} Hz below {s.sample_rate_hz:g} Hz")
            if io.last_status & Status.FAULT:
                level = rosutil.ERROR
                problems.append("controller FAULT latched")
        elif link.state is not LinkState.CONNECTED:
            level = rosutil.WARN
            problems.append(f"link {link.state.value}: {link.last_error}")
        if ses.config_refused:
            level = rosutil.ERROR
            problems.append(f"controller refused sample period {s.sample_period_us} µs")
        if sup.overspeed:
            level = rosutil.ERROR
            problems.append("sun overspeed")
        if grew:
            level = max(level, rosutil.WARN)
            problems.append("new " + ", ".join(grew))
            if "refusals" in grew:
                problems.append(f"last refusal: {sup.last_refusal}")
            if {"safety_trips", "watchdog_trips"} & set(grew):
                problems.append(f"last trip: {sup.last_trip}")
        message = self._state_label + (f", {rate:.0f} Hz" if self._active else "")
        if problems:
            message += ": " + "; ".join(problems)
        return rosutil.diagnostic(self, DRIVER_NODE, level, message, values)
