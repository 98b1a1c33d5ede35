"""What the driver node's I/O thread owns besides the session (:mod:`dvt_driver.link.node`):
the serial link, the controller-clock mapping, the reusable JointState messages and the
unwrapped encoder counts; the session timing for the driver's settings."""

from __future__ import annotations

import math

from dvt_driver.link.clock import ClockMapper
from dvt_driver.link.protocol import Sample, Status, unwrap_count
from dvt_driver.link.serial_link import SerialLink
from dvt_driver.link.session import Session, SessionTiming
from dvt_driver.link.settings import DriverSettings
from dvt_model import rosutil
from dvt_model.contract import CURRENT_NAMES, SPEED_NAMES

_TWO_PI = 2.0 * math.pi


def _flags(status: Status) -> frozenset[str]:
    out = []
    if status & Status.FAULT:
        out.append("FAULT")
    if status & Status.OVERSPEED:
        out.append("OVERSPEED")
    if status & Status.WATCHDOG:
        out.append("WATCHDOG")
    return frozenset(out)


class _Io:
    """What the I/O thread owns besides the session: link, clock mapping, reusable messages."""

    def __init__(self, settings: DriverSettings, link: SerialLink) -> None:
        self.settings = settings
        self.link = link
        self.session = Session(session_timing(settings), name=settings.port)
        self.clock = ClockMapper(settings.clock_window)
        self.published = 0
        self.last_status = Status(0)
        self.last_sample: Sample | None = None
        self.js_msg = rosutil.joint_state(0, SPEED_NAMES, velocity=(0.0, 0.0))
        # with positions (protocol version 2): the same names, position [rad] and velocity
        self.js_pos_msg = rosutil.joint_state(0, SPEED_NAMES, velocity=(0.0, 0.0))
        self.js_pos_msg.position = [0.0, 0.0]
        self.cur_msg = rosutil.joint_state(0, CURRENT_NAMES, effort=(0.0,) * 4)
        self.counts: list[int] | None = None  # unwrapped encoder counts (sun, output)
        self.counts_cpr: tuple[int, int] | None = None  # resolution they were counted with

    def positions(self, msg: Sample, reset: bool) -> tuple[float, float] | None:
        """``(sun_shaft, carrier3)`` angles [rad] of a sample, or ``None`` when the session
        carries no counts (version 1, or no HELLO_ACK seen yet).

        The i32 counts are unwrapped against the previous sample (exact while an encoder moves
        less than 2**31 counts between samples); a controller reset or a change of resolution
        restarts from the raw counts. An encoder with 0 counts/rev (absent) gives NaN.
        """
        cpr = self.session.counts_per_rev
        if cpr is None or msg.counts is None:
            self.counts = None
            return None
        if self.counts is None or reset or cpr != self.counts_cpr:
            self.counts = [msg.counts[0], msg.counts[1]]
            self.counts_cpr = cpr
        else:
            c = self.counts
            c[0] = unwrap_count(c[0], msg.counts[0])
            c[1] = unwrap_count(c[1], msg.counts[1])
        c = self.counts
        return (_TWO_PI * c[0] / cpr[0] if cpr[0] else math.nan,
                _TWO_PI * c[1] / cpr[1] if cpr[1] else math.nan)


def session_timing(settings: DriverSettings) -> SessionTiming:
    """The session timing for the driver's settings."""
    return SessionTiming(sample_period_us=settings.sample_period_us,
                         keepalive_period=1.0 / settings.keepalive_rate_hz,
                         reconnect_interval=settings.reconnect_interval)
