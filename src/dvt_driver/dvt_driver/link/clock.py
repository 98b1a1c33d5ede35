"""Controller clock -> host (ROS) time mapping for sample stamps (pure, no I/O, no ROS).

The controller stamps every sample with its own microsecond clock ``t_us`` (time since the
controller started). The host sees each sample some latency ``L >= 0`` after the controller
took it: ``host_ns = t_us * 1000 + offset + L`` where ``offset`` is the (unknown) difference of
the two clocks. The smallest observed ``host_ns - t_us * 1000`` over a sliding window is the
offset plus the smallest latency in that window - a serial link has a sharp lower latency bound
and only positive spikes (scheduling, USB polling, bursts), so the minimum is robust where a mean
would be dragged by every spike. A sample's stamp is ``t_us * 1000 + offset_estimate``: the
controller's sample instant expressed in host time (within the minimum latency, typically a few
hundred microseconds on a 921600 baud line).

Drift: the two crystals run at slightly different rates (typically < 100 ppm). The window is a
span of *controller* time (default 2 s), so the estimate follows drift: a controller clock that
runs fast makes the offset fall and the newest samples carry the minimum (no lag); one that runs
slow makes the offset rise and the estimate lags by at most ``window * drift`` (0.2 ms for 2 s
at 100 ppm). Downward corrections (a better minimum found, drift) are slewed: the offset may
fall by at most ``max_slew`` times the controller time that passed, so stamps keep advancing at
no less than ``1 - max_slew`` of the controller's rate and never step backwards; upward
corrections are applied at once (a forward step is harmless).

Controller reset (the controller restarted, its clock begins again near zero): call
:meth:`ClockMapper.reset`; the window is cleared and the offset is estimated afresh from the
new run. Stamps still strictly increase across the reset: a stamp is never less than the last
one plus 1 ns. A clock that does not advance (``t_us`` not greater than the previous one) is
treated as a reset as well (the caller should drop exact duplicates before mapping).

All times are integers: ``t_us`` in microseconds, ``host_ns`` and stamps in nanoseconds.
"""

from __future__ import annotations

import math
from collections import deque

from dvt_driver.errors import ClockError

__all__ = ["ClockError", "ClockMapper"]


class ClockMapper:
    """Maps controller sample times to strictly increasing host-time stamps.

    Args:
        window: span of controller time over which the minimum offset is taken [s], > 0.
        max_slew: largest downward offset correction per unit of controller time
            (dimensionless, 0 <= max_slew < 1); 0.5 lets stamps advance at half speed
            while a correction is absorbed.

    Attributes:
        offset_ns: offset in use (``stamp - t_us * 1000``) [ns], ``None`` before the first sample.
        samples: samples mapped.
        resets: times the estimate was restarted (explicit :meth:`reset` or clock going back).
        guarded: stamps raised to ``last + 1 ns`` to keep them strictly increasing (after a
            reset whose new offset would map into the past).
    """

    def __init__(self, window: float = 2.0, max_slew: float = 0.5) -> None:
        if not (isinstance(window, int | float) and not isinstance(window, bool)
                and math.isfinite(window) and window > 0):
            raise ClockError(f"window: expected a finite number > 0 s, got {window!r}")
        if not (isinstance(max_slew, int | float) and not isinstance(max_slew, bool)
                and math.isfinite(max_slew) and 0 <= max_slew < 1):
            raise ClockError(f"max_slew: expected a number in [0, 1), got {max_slew!r}")
        self.window = float(window)
        self.max_slew = float(max_slew)
        self._window_us = max(1, round(window * 1e6))
        # monotonic deque of (t_us, raw offset ns): raw offsets strictly increase front->back,
        # the front is the window minimum
        self._mins: deque[tuple[int, int]] = deque()
        self._last_t_us: int | None = None
        self._last_stamp: int | None = None
        self.offset_ns: int | None = None
        self.samples = 0
        self.resets = 0
        self.guarded = 0

    @property
    def last_stamp_ns(self) -> int | None:
        """The last stamp returned by :meth:`map` [ns], ``None`` before the first."""
        return self._last_stamp

    @property
    def window_min_ns(self) -> int | None:
        """Current minimum of ``host_ns - t_us * 1000`` over the window [ns] (unslewed)."""
        return self._mins[0][1] if self._mins else None

    def reset(self) -> None:
        """Start a new run (controller reset): forget the window and the offset.

        The strict-increase guard on stamps is kept, so stamps keep increasing across resets.
        """
        self._mins.clear()
        self._last_t_us = None
        self.offset_ns = None
        self.resets += 1

    def map(self, t_us: int, host_ns: int) -> int:
        """Stamp [ns] of the sample taken at controller time ``t_us`` [µs] and received by the
        host at ``host_ns`` [ns] (host clock, e.g. ROS time).

        Raises:
            ClockError: ``t_us`` or ``host_ns`` is not an integer (``t_us`` must be >= 0).
        """
        if isinstance(t_us, bool) or not isinstance(t_us, int) or t_us < 0:
            raise ClockError(f"t_us: expected an integer >= 0 µs, got {t_us!r}")
        if isinstance(host_ns, bool) or not isinstance(host_ns, int):
            raise ClockError(f"host_ns: expected an integer ns, got {host_ns!r}")
        last_t = self._last_t_us
        if last_t is not None and t_us <= last_t:
            self.reset()
            last_t = None
        raw = host_ns - t_us * 1000
        mins = self._mins
        while mins and mins[-1][1] >= raw:
            mins.pop()
        mins.append((t_us, raw))
        horizon = t_us - self._window_us
        while mins[0][0] < horizon:
            mins.popleft()
        window_min = mins[0][1]
        if self.offset_ns is None or last_t is None:
            offset = window_min
        else:
            floor = self.offset_ns - int(self.max_slew * (t_us - last_t) * 1000)
            offset = max(window_min, floor)
        self.offset_ns = offset
        self._last_t_us = t_us
        stamp = t_us * 1000 + offset
        if self._last_stamp is not None and stamp <= self._last_stamp:
            stamp = self._last_stamp + 1
            self.guarded += 1
        self._last_stamp = stamp
        self.samples += 1
        return stamp
