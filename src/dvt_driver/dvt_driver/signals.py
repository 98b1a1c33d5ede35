"""One stop flag for every long-running process of the driver package (pure; no rclpy)."""

from __future__ import annotations

import signal
from collections.abc import Iterable
from types import FrameType
from typing import Any


class StopFlag:
    """A flag set by SIGINT/SIGTERM instead of raising ``KeyboardInterrupt``.

    ``install()`` replaces the handlers (main thread only) and ``restore()`` puts the previous
    ones back. Every signal is counted (:attr:`count`, :attr:`signals`); a second one sets
    :attr:`hurry` (shorten the shutdown waits). With ``escalate=True`` a second signal while the
    flag is set also restores the previous handlers, so a third one falls through to the default
    action (an escape hatch for a hung shutdown). The flag is also a signal handler itself
    (``signal.signal(SIGINT, flag)``).
    """

    def __init__(self, signals: Iterable[int] = (signal.SIGINT, signal.SIGTERM), *,
                 escalate: bool = True) -> None:
        self.watched = tuple(signals)
        self.escalate = escalate
        self.signals: list[int] = []
        self._previous: dict[int, Any] = {}

    def __bool__(self) -> bool:
        return bool(self.signals)

    @property
    def count(self) -> int:
        """How many stop requests arrived."""
        return len(self.signals)

    @property
    def received(self) -> int | None:
        """The first signal number received (0 for :meth:`set`), or ``None``."""
        return self.signals[0] if self.signals else None

    @property
    def is_set(self) -> bool:
        """Whether a stop was requested."""
        return bool(self.signals)

    @property
    def hurry(self) -> bool:
        """A second request arrived: shorten the shutdown waits."""
        return len(self.signals) > 1

    def set(self, signum: int = 0) -> None:
        """Request a stop (as if signal ``signum`` arrived)."""
        self.signals.append(signum)

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        if self.signals and self.escalate:
            self.restore()
        self.signals.append(signum)

    def install(self) -> StopFlag:
        """Install the handlers; returns self."""
        for s in self.watched:
            self._previous[s] = signal.signal(s, self)
        return self

    def restore(self) -> None:
        """Restore the handlers that were active before :meth:`install`."""
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()
