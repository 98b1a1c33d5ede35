"""One progress line on a terminal, nothing elsewhere (pure: standard library only).

A long run (the identifier's loop, ``dvt-bag recover``, the demo's stages) shows what it is doing
on one line of a terminal, rewritten in place with a carriage return; when the stream is not a
terminal (a pipe, a log file, a test) it writes nothing, so logs and captured output stay clean::

    line = ProgressLine.stderr("dvt-bag recover: ")
    for i, chunk in enumerate(chunks):
        line.update(f"chunk {i + 1}/{len(chunks)}")   # throttled to 10 redraws a second
    line.close()                                       # clears the line

:meth:`ProgressLine.note` prints a permanent line above the progress line (then redraws it).
A :class:`ProgressLine` is also a ``Callable[[str], None]`` (:meth:`update`), so it can be passed
wherever a progress callback is taken.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from types import TracebackType
from typing import Protocol

CLEAR = "\r\x1b[K"
"""Carriage return and erase to the end of the line (ANSI, every terminal emulator)."""
MIN_INTERVAL = 0.1
"""Shortest time between two redraws [s] (a faster caller costs nothing but the check)."""


class Stream(Protocol):
    """What :class:`ProgressLine` needs of its stream (``sys.stderr`` or a test's fake)."""

    def write(self, text: str, /) -> int | None: ...

    def flush(self) -> None: ...

    def isatty(self) -> bool: ...


def _columns(stream: Stream, fallback: int = 80) -> int:
    """Width of the terminal behind ``stream`` [characters] (``fallback`` if not known)."""
    try:
        fileno = getattr(stream, "fileno", None)
        if fileno is not None:
            cols = int(os.get_terminal_size(fileno()).columns)
            return cols if cols >= 20 else fallback  # 0: a pseudo-terminal without a size
    except (OSError, ValueError, TypeError, AttributeError):
        pass
    return fallback


def fraction(i: int, n: int) -> str:
    """``i/n (p %)``: a count with its share (``i/n`` alone when ``n`` is not positive)."""
    return f"{i}/{n} ({100 * i / n:.0f} %)" if n > 0 else f"{i}/{n}"


class ProgressLine:
    """A status line rewritten in place on a terminal; silent when the stream is not one.

    Args:
        stream: where to write (default ``sys.stderr`` at construction).
        prefix: text in front of every status (``"[dvt-identify] "``).
        elapsed: show the seconds since construction after the prefix.
        min_interval: shortest time between redraws [s]; :meth:`update` with ``force`` and
            :meth:`note` always draw.
        active: override the terminal test (``None``: ``stream.isatty()``).
        clock: monotonic time [s] (tests).
        width: line width [characters] (``None``: the terminal's; longer text is cut with
            ``…``).
    """

    def __init__(self, stream: Stream | None = None, prefix: str = "", *,
                 elapsed: bool = False, min_interval: float = MIN_INTERVAL,
                 active: bool | None = None, clock: Callable[[], float] = time.monotonic,
                 width: int | None = None) -> None:
        self.stream: Stream = stream if stream is not None else sys.stderr
        self.prefix = prefix
        self.elapsed = elapsed
        self.min_interval = min_interval
        self.clock = clock
        self._t0 = clock()
        self._last = -float("inf")
        self._text = ""
        self._shown = False
        self._saved: Stream | None = None
        if active is None:
            try:
                active = bool(self.stream.isatty())
            except (AttributeError, ValueError, OSError):
                active = False
        self.active = active
        self.width = width if width is not None else (_columns(self.stream) if active else 80)

    @classmethod
    def stderr(cls, prefix: str = "", *, elapsed: bool = True) -> ProgressLine:
        """A line on the current ``sys.stderr`` (shown only when it is a terminal)."""
        return cls(sys.stderr, prefix, elapsed=elapsed)

    def _format(self, text: str) -> str:
        head = self.prefix + (f"{self.clock() - self._t0:5.1f} s  " if self.elapsed else "")
        line = head + " ".join(text.split())  # one line: no newlines or runs of spaces
        room = max(self.width - 1, 10)  # the last column would wrap on some terminals
        return line if len(line) <= room else line[: room - 1] + "…"

    def _draw(self) -> None:
        self.stream.write(CLEAR + self._format(self._text))
        self.stream.flush()
        self._shown = True
        self._last = self.clock()

    def update(self, text: str, *, force: bool = False) -> None:
        """Show ``text`` as the status (at most every :attr:`min_interval` unless ``force``)."""
        self._text = text
        if not self.active:
            return
        if force or self.clock() - self._last >= self.min_interval:
            self._draw()

    __call__ = update

    def note(self, text: str) -> None:
        """Print ``text`` as a permanent line above the status line (then redraw it)."""
        if not self.active:
            return
        self.stream.write(CLEAR + text + "\n")
        self._shown = False
        if self._text:
            self._draw()
        else:
            self.stream.flush()

    def close(self) -> None:
        """Clear the status line (the terminal's cursor back at the start of an empty line)."""
        if self.active and self._shown:
            self.stream.write(CLEAR)
            self.stream.flush()
        self._shown = False
        self._text = ""

    def __enter__(self) -> ProgressLine:
        """Used as a context manager on the process's stderr, the line also guards it: other
        writes to ``sys.stderr`` (a warning, a log line) clear the status line first and it is
        redrawn under them; :meth:`close` on exit restores ``sys.stderr``."""
        if self.active and self.stream is sys.stderr and self._saved is None:
            self._saved = sys.stderr
            sys.stderr = _Guarded(self, sys.stderr)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._saved is not None:
            sys.stderr = self._saved
            self._saved = None
        self.close()


class _Guarded:
    """``sys.stderr`` while a :class:`ProgressLine` owns it: a foreign write clears the status
    line first; a write that ends a line redraws the status under it."""

    def __init__(self, line: ProgressLine, real: Stream) -> None:
        self._line = line
        self._real = real

    def write(self, text: str, /) -> int | None:
        line = self._line
        if line._shown:
            self._real.write(CLEAR)
            line._shown = False
        n = self._real.write(text)
        if text.endswith("\n") and line._text:
            line._draw()
        return n

    def flush(self) -> None:
        self._real.flush()

    def isatty(self) -> bool:
        return self._real.isatty()

    def __getattr__(self, name: str) -> object:
        return getattr(self._real, name)
