"""Serial link to the DVT controller: a pyserial port speaking :mod:`dvt_driver.link.protocol`.

:class:`SerialLink` opens a port (a real UART or a pseudo-terminal), decodes the incoming byte
stream into messages with :class:`~dvt_driver.link.protocol.FrameDecoder`, tracks sample sequence
numbers with :class:`~dvt_driver.link.protocol.SequenceTracker`, and sends encoded messages. Every
wait is bounded. Runtime failures (device unplugged, pty closed, write error) never raise: the
link goes to :attr:`LinkState.DISCONNECTED`, the failure is counted and kept in
:attr:`SerialLink.last_error`, and :meth:`SerialLink.reopen` brings it back once the device is
there again. No ROS here.

Threading: one thread may call :meth:`SerialLink.read_messages` while another calls
:meth:`SerialLink.send`; call :meth:`open`, :meth:`close` and :meth:`reopen` from one thread.
"""

from __future__ import annotations

import contextlib
import enum
import math
import select
import threading
import time
from dataclasses import dataclass
from types import TracebackType

import serial

from dvt_driver.errors import LinkError
from dvt_driver.link.protocol import (
    DEFAULT_BAUD,
    MAX_FRAME_LEN,
    FrameDecoder,
    Message,
    Sample,
    SequenceTracker,
    encode,
)

__all__ = ["LinkState", "LinkStats", "SerialLink"]

_READ_CHUNK = 4096


class LinkState(enum.Enum):
    """State of a :class:`SerialLink`."""

    CLOSED = "closed"  #: never opened, or closed by the user
    CONNECTED = "connected"  #: port open, bytes flow
    DISCONNECTED = "disconnected"  #: the port failed or could not be reopened; try reopen()


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Snapshot of a link's counters (cumulative over the link's life, across reconnects).

    Attributes:
        frames_good: frames decoded into messages.
        frames_bad: malformed frames dropped (bad CRC, COBS, length, oversize, ...).
        crc_errors: the subset of ``frames_bad`` that failed the CRC.
        bytes_discarded: received bytes thrown away (bad frames, unsynchronised fragments).
        lost_samples: samples missing according to sequence-number gaps (a gap spanning a
            disconnection counts as lost).
        resets: controller resets detected (sequence or clock went backwards).
        reconnects: successful :meth:`SerialLink.reopen` calls.
        write_errors: frames not written (link not connected, write timeout or I/O error).
        disconnects: times the open port failed and the link went to ``DISCONNECTED``.
        bytes_received: raw bytes read from the port.
    """

    frames_good: int = 0
    frames_bad: int = 0
    crc_errors: int = 0
    bytes_discarded: int = 0
    lost_samples: int = 0
    resets: int = 0
    reconnects: int = 0
    write_errors: int = 0
    disconnects: int = 0
    bytes_received: int = 0


class SerialLink:
    """Framed, counted, reconnectable serial link to the controller.

    Args:
        port: device path (``/dev/ttyUSB0``, a pty slave or a symlink to one).
        baud: line rate [bit/s], default 921600.
        write_timeout: longest a :meth:`send` may block [s], > 0.
        max_frame_len: longest accepted encoded frame [bytes].

    The constructor does not touch the port; call :meth:`open` (or use ``with``).
    """

    def __init__(self, port: str, baud: int = DEFAULT_BAUD, *, write_timeout: float = 0.1,
                 max_frame_len: int = MAX_FRAME_LEN) -> None:
        if not isinstance(port, str) or not port:
            raise LinkError(f"port: expected a non-empty device path, got {port!r}")
        if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
            raise LinkError(f"baud: expected a positive integer, got {baud!r}")
        if not (isinstance(write_timeout, int | float) and math.isfinite(write_timeout)
                and write_timeout > 0):
            raise LinkError(f"write_timeout: expected a finite number > 0 s, got {write_timeout!r}")
        self.port = port
        self.baud = baud
        self.write_timeout = float(write_timeout)
        self.last_error: str | None = None
        self._serial: serial.Serial | None = None
        self._state = LinkState.CLOSED
        self._decoder = FrameDecoder(max_frame_len, synced=False)
        self._tracker = SequenceTracker()
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._reconnects = 0
        self._write_errors = 0
        self._disconnects = 0
        self._bytes_received = 0

    # -- state -----------------------------------------------------------------------------

    @property
    def state(self) -> LinkState:
        """Current :class:`LinkState`."""
        return self._state

    @property
    def connected(self) -> bool:
        """``state is LinkState.CONNECTED``."""
        return self._state is LinkState.CONNECTED

    @property
    def stats(self) -> LinkStats:
        """Snapshot of the counters."""
        d, t = self._decoder, self._tracker
        return LinkStats(frames_good=d.frames_good, frames_bad=d.frames_bad,
                         crc_errors=d.crc_errors, bytes_discarded=d.bytes_discarded,
                         lost_samples=t.lost, resets=t.resets, reconnects=self._reconnects,
                         write_errors=self._write_errors, disconnects=self._disconnects,
                         bytes_received=self._bytes_received)

    # -- open / close ----------------------------------------------------------------------

    def open(self) -> None:
        """Open the port (no-op when already connected).

        Stale bytes waiting in the port are dropped and a lone 0x00 delimiter is sent so the
        device's decoder starts the next frame cleanly.

        Raises:
            LinkError: the port cannot be opened or configured; the message names the port and
                the OS error. The link is then ``DISCONNECTED`` (``CLOSED`` if it was never
                connected before).
        """
        with self._lock:
            if self._state is LinkState.CONNECTED:
                return
            try:
                port = serial.Serial(port=self.port, baudrate=self.baud, timeout=0,
                                     write_timeout=self.write_timeout)
            except (serial.SerialException, OSError, ValueError) as exc:
                self.last_error = f"cannot open {self.port} at {self.baud} baud: {exc}"
                if self._state is not LinkState.CLOSED:
                    self._state = LinkState.DISCONNECTED
                raise LinkError(self.last_error) from exc
            try:
                port.reset_input_buffer()
                port.write(b"\x00")
            except (serial.SerialException, OSError) as exc:
                _quiet_close(port)
                self.last_error = f"cannot use {self.port} after opening it: {exc}"
                if self._state is not LinkState.CLOSED:
                    self._state = LinkState.DISCONNECTED
                raise LinkError(self.last_error) from exc
            self._serial = port
            self._decoder.reset(synced=False)
            self._state = LinkState.CONNECTED

    def close(self) -> None:
        """Close the port; the link becomes ``CLOSED``. Safe to call in any state."""
        with self._lock:
            port, self._serial = self._serial, None
            self._state = LinkState.CLOSED
        if port is not None:
            _quiet_close(port)

    def reopen(self) -> bool:
        """Close and open the port again; never raises.

        Returns:
            ``True`` if the link is connected afterwards (counted in ``reconnects``); ``False``
            if the port could not be opened (link ``DISCONNECTED``, reason in
            :attr:`last_error`).
        """
        with self._lock:
            port, self._serial = self._serial, None
            self._state = LinkState.DISCONNECTED
        if port is not None:
            _quiet_close(port)
        try:
            self.open()
        except LinkError:
            return False
        self._reconnects += 1
        return True

    def __enter__(self) -> SerialLink:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _fail(self, port: serial.Serial, what: str, exc: BaseException) -> None:
        """The open port failed: go DISCONNECTED (once per failure), close it, remember why."""
        with self._lock:
            if self._serial is not port:  # already handled (or reopened) by another thread
                return
            self._serial = None
            self._state = LinkState.DISCONNECTED
            self._disconnects += 1
            self.last_error = f"{self.port}: {what} failed: {exc}"
        _quiet_close(port)

    # -- I/O -------------------------------------------------------------------------------

    def read_messages(self, timeout: float) -> list[Message]:
        """Messages received within ``timeout`` seconds.

        Returns as soon as at least one complete message has arrived (with every complete
        message already buffered), or an empty list after ``timeout``. When the link is not
        connected it waits ``timeout`` and returns an empty list (so a polling loop does not
        spin). A failing port moves the link to ``DISCONNECTED`` and returns what was decoded.

        Args:
            timeout: longest wait [s], finite and >= 0 (0 polls).

        Raises:
            LinkError: ``timeout`` is negative, NaN or infinite.
        """
        if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout >= 0):
            raise LinkError(f"timeout: expected a finite number >= 0 s, got {timeout!r}")
        deadline = time.monotonic() + timeout
        port = self._serial
        if port is None or self._state is not LinkState.CONNECTED:
            if timeout > 0:
                time.sleep(timeout)
            return []
        messages: list[Message] = []
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([port.fileno()], [], [], remaining)
                if ready:
                    data = port.read(max(1, min(port.in_waiting, _READ_CHUNK)))
                    self._bytes_received += len(data)
                    messages.extend(self._decoder.feed(data))
            except (serial.SerialException, OSError, ValueError, TypeError) as exc:
                # ValueError/TypeError: the port was closed by another thread during the wait
                self._fail(port, "read", exc)
                break
            if messages or remaining <= 0.0:
                break
        for msg in messages:
            if isinstance(msg, Sample):
                self._tracker.update(msg.seq, msg.t_us)
        return messages

    def send(self, msg: Message) -> bool:
        """Encode ``msg`` and write it (blocking at most ``write_timeout``).

        Returns:
            ``True`` if the whole frame was written. ``False`` if the link is not connected or
            the write failed; both are counted in ``write_errors``. An I/O error also moves the
            link to ``DISCONNECTED``; a write timeout (device not reading) does not.

        Raises:
            ProtocolError: ``msg`` cannot be encoded (see :func:`dvt_driver.link.protocol.encode`);
                nothing is written then.
        """
        frame = encode(msg)
        port = self._serial
        if port is None or self._state is not LinkState.CONNECTED:
            self._write_errors += 1
            return False
        with self._write_lock:
            try:
                written = port.write(frame)
            except serial.SerialTimeoutException as exc:
                self._write_errors += 1
                self.last_error = (f"{self.port}: write timed out after "
                                   f"{self.write_timeout} s: {exc}")
                return False
            except (serial.SerialException, OSError, ValueError, TypeError) as exc:
                self._write_errors += 1
                self._fail(port, "write", exc)
                return False
        if written != len(frame):
            self._write_errors += 1
            self.last_error = f"{self.port}: wrote {written} of {len(frame)} bytes"
            return False
        return True


def _quiet_close(port: serial.Serial) -> None:
    with contextlib.suppress(serial.SerialException, OSError):
        port.close()
