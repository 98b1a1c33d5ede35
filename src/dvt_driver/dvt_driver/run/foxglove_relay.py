"""Both names of the Foxglove WebSocket subprotocol on one port, in front of foxglove-sdk.

foxglove-sdk's WebSocket server (the one ``dvt-foxglove`` runs) accepts only the subprotocol
names ``foxglove.sdk.v1`` and ``foxglove.sdk.v1.1``; it has no option for others (0.30.3: the
name is a constant of its handshake). The open-source Foxglove Studio and Lichtblick releases
before late 2025 offer only ``foxglove.websocket.v1``, the old name of the same protocol
(Foxglove's word: so far identical), and get HTTP 400.

:class:`SubprotocolRelay` listens on the bridge's public address and relays every TCP
connection to the SDK server on a loopback port. It changes only the HTTP upgrade, and only
for a client that offers ``foxglove.websocket.v1`` and no ``foxglove.sdk.*`` name: the request
goes on offering ``foxglove.sdk.v1``, and the SDK's answer naming ``foxglove.sdk.v1`` comes
back naming ``foxglove.websocket.v1`` (``Sec-WebSocket-Accept`` depends only on the client's
key, so it stays valid). Every other request, and every byte after the upgrade, passes
unchanged; the SDK still refuses a client offering neither name. The rule is in the pure
functions :func:`rewrite_request` and :func:`rewrite_response`. No rclpy, no foxglove import.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
"""The name foxglove-sdk's server accepts (and the one current Foxglove offers)."""
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The old name of the same protocol (Foxglove Studio, Lichtblick before late 2025)."""
SUBPROTOCOLS = (SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL)
"""The names a client may offer to ``dvt-foxglove``."""

MAX_HEAD_BYTES = 16384
"""Longest HTTP upgrade request or response the relay reads [bytes]."""
HANDSHAKE_TIMEOUT_S = 10.0
"""Bound on each read and write of the upgrade, and on connecting to the SDK server [s]."""

_SDK_PREFIX = "foxglove.sdk."
_HEADER = b"sec-websocket-protocol"
_CHUNK = 65536
_POLL_S = 0.25


def _is_protocol_line(line: bytes) -> bool:
    name, sep, _ = line.partition(b":")
    return bool(sep) and name.strip().lower() == _HEADER


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocol names a WebSocket upgrade request offers, in order.

    ``head`` is the request line and header lines, CRLF-separated (every
    ``Sec-WebSocket-Protocol`` line counts; its value is comma-separated).
    """
    names: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        if _is_protocol_line(line):
            value = line.partition(b":")[2].decode("latin-1")
            names += [n.strip() for n in value.split(",") if n.strip()]
    return names


def rewrite_request(head: bytes) -> tuple[bytes, str | None]:
    """The upgrade request to forward to the SDK server, and the name to answer with.

    A request offering :data:`LEGACY_SUBPROTOCOL` and no ``foxglove.sdk.*`` name comes back
    offering only :data:`SDK_SUBPROTOCOL`, with ``LEGACY_SUBPROTOCOL`` as the name for
    :func:`rewrite_response`; any other request comes back unchanged, with ``None``.
    """
    offered = offered_subprotocols(head)
    if LEGACY_SUBPROTOCOL not in offered or any(n.startswith(_SDK_PREFIX) for n in offered):
        return head, None
    lines = [line for line in head.split(b"\r\n") if not _is_protocol_line(line)]
    lines.insert(1, b"Sec-WebSocket-Protocol: " + SDK_SUBPROTOCOL.encode())
    return b"\r\n".join(lines), LEGACY_SUBPROTOCOL


def rewrite_response(head: bytes, name: str) -> bytes:
    """The SDK server's upgrade response with its chosen :data:`SDK_SUBPROTOCOL` renamed to
    ``name`` (the name the client offered); a response choosing nothing else is unchanged
    (a refusal stays a refusal)."""
    out = []
    for line in head.split(b"\r\n"):
        key, _, value = line.partition(b":")
        if _is_protocol_line(line) and value.strip() == SDK_SUBPROTOCOL.encode():
            line = key + b": " + name.encode("latin-1")
        out.append(line)
    return b"\r\n".join(out)


def _read_head(sock: socket.socket, what: str) -> tuple[bytes, bytes]:
    """Read an HTTP head (up to and including the blank line) and what came after it.

    Raises:
        ConnectionError: ``what`` closed before the blank line or sent more than
            :data:`MAX_HEAD_BYTES` without one.
        TimeoutError: no byte for the socket's timeout.
    """
    buf = b""
    while (end := buf.find(b"\r\n\r\n")) < 0:
        if len(buf) > MAX_HEAD_BYTES:
            raise ConnectionError(f"{what}: HTTP head longer than {MAX_HEAD_BYTES} bytes")
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError(f"{what}: closed before the end of its HTTP head")
        buf += chunk
    return buf[:end + 4], buf[end + 4:]


def _pipe(src: socket.socket, dst: socket.socket) -> None:
    """Copy ``src`` to ``dst`` until either ends; then end both (unblocks the other pipe)."""
    try:
        while data := src.recv(_CHUNK):
            dst.sendall(data)
    except OSError:
        pass
    finally:
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)


class SubprotocolRelay:
    """Listens on ``host:port`` and relays each connection to ``upstream`` (module docstring).

    Args:
        host: listen address (``0.0.0.0``: every interface).
        port: listen port (0: any free port; see :attr:`port`).
        upstream: ``(host, port)`` of the foxglove-sdk server.
        warn: called (from a relay thread) with a one-line reason for each connection dropped
            before or during its upgrade.

    Raises:
        OSError: cannot listen on ``host:port`` (in use, unknown address).
    """

    def __init__(self, host: str, port: int, upstream: tuple[str, int],
                 warn: Callable[[str], None] | None = None) -> None:
        family, _, _, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        self._listener = socket.create_server(address, family=family)
        self._listener.settimeout(_POLL_S)
        self.port = int(self._listener.getsockname()[1])
        self.upstream = upstream
        self._warn = warn if warn is not None else (lambda _msg: None)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._thread = threading.Thread(target=self._accept, name="foxglove-relay", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError as exc:  # closed, or out of file descriptors
                if not self._stop.is_set():
                    self._warn(f"accept failed: {exc}")
                    self._stop.wait(_POLL_S)
                continue
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _track(self, sock: socket.socket, on: bool) -> None:
        with self._lock:
            if on:
                self._open.add(sock)
            else:
                self._open.discard(sock)

    def _serve(self, client: socket.socket) -> None:
        upstream: socket.socket | None = None
        self._track(client, True)
        try:
            host, port = client.getpeername()[:2]
            peer = f"{host}:{port}"
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            head, rest = _read_head(client, f"client {peer}")
            head, rename = rewrite_request(head)
            upstream = socket.create_connection(self.upstream, timeout=HANDSHAKE_TIMEOUT_S)
            self._track(upstream, True)
            if self._stop.is_set():
                return
            upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            upstream.sendall(head + rest)
            if rename is not None:
                reply, after = _read_head(upstream, "foxglove-sdk server")
                client.sendall(rewrite_response(reply, rename) + after)
            client.settimeout(None)
            upstream.settimeout(None)
            back = threading.Thread(target=_pipe, args=(upstream, client), daemon=True)
            back.start()
            _pipe(client, upstream)
            back.join()
        except OSError as exc:
            if not self._stop.is_set():
                self._warn(f"connection dropped during the WebSocket upgrade: {exc}")
        finally:
            for s in (client, upstream):
                if s is not None:
                    self._track(s, False)
                    s.close()

    def close(self) -> None:
        """Stop listening and end every relayed connection (bounded: about a second)."""
        self._stop.set()
        with self._lock:
            open_now = list(self._open)
        for s in open_now:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=4 * _POLL_S)
        self._listener.close()
