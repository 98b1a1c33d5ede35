"""The subprotocol relay in front of foxglove-sdk: the rewrite rule, and a real foxglove-sdk
server behind a real relay answering clients that offer either name (no ROS graph)."""

from __future__ import annotations

import json
import socket
import struct
import time
from collections.abc import Iterator
from typing import Any

import pytest

from dvt_driver.run import foxglove_relay as fr
from dvt_driver.run.foxglove_relay import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL

pytestmark = pytest.mark.timeout(60)


def _request(*protocol_lines: str) -> bytes:
    lines = ["GET / HTTP/1.1", "Host: 127.0.0.1:8765", "Upgrade: websocket",
             "Connection: Upgrade", "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
             *protocol_lines, "Sec-WebSocket-Version: 13"]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def _response(protocol: str) -> bytes:
    return ("HTTP/1.1 101 Switching Protocols\r\nupgrade: websocket\r\n"
            f"sec-websocket-protocol: {protocol}\r\n"
            "sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n\r\n").encode()


def test_offered_names_from_every_header_line_any_case() -> None:
    head = _request("Sec-WebSocket-Protocol: a, foxglove.websocket.v1",
                    "sec-websocket-protocol:b")
    assert fr.offered_subprotocols(head) == ["a", LEGACY_SUBPROTOCOL, "b"]
    assert fr.offered_subprotocols(_request()) == []


def test_only_the_old_name_is_rewritten_to_the_sdk_name() -> None:
    head = _request("Sec-WebSocket-Protocol: x.other, foxglove.websocket.v1")
    out, name = fr.rewrite_request(head)
    assert name == LEGACY_SUBPROTOCOL
    assert fr.offered_subprotocols(out) == [SDK_SUBPROTOCOL]
    assert out.endswith(b"\r\n\r\n") and out.startswith(b"GET / HTTP/1.1\r\n")
    assert out.replace(b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n", b"") == \
        head.replace(b"Sec-WebSocket-Protocol: x.other, foxglove.websocket.v1\r\n", b"")
    # a client that offers an SDK name, or not the old one, is left to the SDK's own choice
    for offered in ("foxglove.websocket.v1, foxglove.sdk.v1", "foxglove.sdk.v1.1, "
                    "foxglove.websocket.v1", "foxglove.sdk.v1", "x.other"):
        head = _request(f"Sec-WebSocket-Protocol: {offered}")
        assert fr.rewrite_request(head) == (head, None), offered
    assert fr.rewrite_request(_request()) == (_request(), None)


def test_response_renames_only_the_sdk_choice() -> None:
    out = fr.rewrite_response(_response(SDK_SUBPROTOCOL), LEGACY_SUBPROTOCOL)
    assert out == _response(LEGACY_SUBPROTOCOL)
    other = _response("foxglove.sdk.v1.1")
    assert fr.rewrite_response(other, LEGACY_SUBPROTOCOL) == other
    refusal = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n"
    assert fr.rewrite_response(refusal, LEGACY_SUBPROTOCOL) == refusal


@pytest.fixture
def served() -> Iterator[tuple[Any, fr.SubprotocolRelay, list[str]]]:
    """A foxglove-sdk server on a loopback port with one JSON channel, behind a relay."""
    import foxglove

    ctx = foxglove.Context()
    chan = foxglove.Channel("/t", message_encoding="json", context=ctx,
                            schema=foxglove.Schema(name="T", encoding="jsonschema",
                                                   data=b'{"type": "object"}'))
    server = foxglove.start_server(host="127.0.0.1", port=0, context=ctx)
    warnings: list[str] = []
    relay = fr.SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port), warnings.append)
    try:
        yield chan, relay, warnings
    finally:
        relay.close()
        server.stop()


def _receive_one(ws: Any, chan: Any) -> dict[str, Any]:
    """Subscribe to the advertised channel and return the first message logged on it."""
    ops: list[str] = []
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        m = ws.recv(timeout=10)
        if isinstance(m, str):
            d = json.loads(m)
            ops.append(d["op"])
            if d["op"] == "advertise":
                cid = d["channels"][0]["id"]
                ws.send(json.dumps({"op": "subscribe",
                                    "subscriptions": [{"id": 7, "channelId": cid}]}))
                # the SDK adds the subscription asynchronously: log until one arrives
                break
    assert ops[:2] == ["serverInfo", "advertise"], ops
    n = 0
    while time.monotonic() < deadline:
        n += 1
        chan.log({"n": n})
        try:
            m = ws.recv(timeout=0.1)
        except TimeoutError:
            continue
        if isinstance(m, bytes) and m[0] == 0x01:
            assert struct.unpack_from("<I", m, 1)[0] == 7
            return dict(json.loads(m[13:]))
    raise AssertionError("no message within 10 s")


@pytest.mark.parametrize(("offered", "chosen"), [
    ([LEGACY_SUBPROTOCOL], LEGACY_SUBPROTOCOL),
    ([SDK_SUBPROTOCOL], SDK_SUBPROTOCOL),
    (["x.other", LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL], SDK_SUBPROTOCOL),
])
def test_relay_negotiates_either_name_and_carries_messages(
        served: tuple[Any, fr.SubprotocolRelay, list[str]], offered: list[str],
        chosen: str) -> None:
    from websockets.sync.client import connect

    chan, relay, warnings = served
    with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=offered,  # type: ignore[arg-type]
                 open_timeout=5) as ws:
        assert ws.subprotocol == chosen
        assert "n" in _receive_one(ws, chan)
    assert not warnings, warnings


def test_relay_passes_the_sdk_refusal_of_other_names(
        served: tuple[Any, fr.SubprotocolRelay, list[str]]) -> None:
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    _, relay, _ = served
    with pytest.raises(InvalidStatus) as err:
        connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["x.other"],  # type: ignore[list-item]
                open_timeout=5)
    assert err.value.response.status_code == 400


def test_relay_drops_a_client_that_never_finishes_its_request(
        served: tuple[Any, fr.SubprotocolRelay, list[str]]) -> None:
    _, relay, warnings = served
    with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as s:
        s.sendall(b"GET / HTTP/1.1\r\n" + b"X-Pad: " + b"a" * (fr.MAX_HEAD_BYTES + 10))
        s.settimeout(5)
        try:
            got = s.recv(100)
        except ConnectionResetError:  # closed with part of the request unread
            got = b""
        assert got == b""  # closed by the relay, without an answer
    deadline = time.monotonic() + 5
    while not warnings and time.monotonic() < deadline:
        time.sleep(0.02)
    assert warnings and "longer than" in warnings[0], warnings


def test_close_ends_connected_clients_and_frees_the_port(
        served: tuple[Any, fr.SubprotocolRelay, list[str]]) -> None:
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    _, relay, _ = served
    with connect(f"ws://127.0.0.1:{relay.port}",
                 subprotocols=[LEGACY_SUBPROTOCOL],  # type: ignore[list-item]
                 open_timeout=5) as ws:
        ws.recv(timeout=5)  # serverInfo
        relay.close()
        with pytest.raises(ConnectionClosed):
            while True:
                ws.recv(timeout=5)
    with socket.create_server(("127.0.0.1", relay.port)):
        pass


def test_address_in_use_is_an_oserror() -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        with pytest.raises(OSError):
            fr.SubprotocolRelay("127.0.0.1", port, ("127.0.0.1", 1))
