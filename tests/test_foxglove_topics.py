"""``dvt-launch sim --foxglove``: a Foxglove WebSocket client gets the advertised channels and
the messages at the configured rate, with the values of the ROS topics; the shipped layout
names only advertised channels. Clients offering only the old subprotocol name
(``foxglove.websocket.v1``: Foxglove Studio, older Lichtblick) get the same stream."""

from __future__ import annotations

import contextlib
import itertools
import json
import socket
import struct
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from conftest import ROOT, Procs, wait_for
from dvt_driver.run.foxglove_core import (
    CHANNEL_TOPICS,
    IDENTIFY,
    RESIDUAL_BAND,
    STATE,
)
from dvt_driver.run.foxglove_layout import layout_topics
from dvt_driver.run.foxglove_relay import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL
from dvt_model.contract import DIAGNOSTICS, IDENTIFY_RESULT, JOINT_STATES, MODEL_RESIDUAL

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

RATE_HZ = 50.0
SIM_RATE = 500
DISCOVERY_S = 15.0
"""Bound on the bridge's DDS subscriptions matching the chain's publishers [s] (measured
0-2.6 s; the SPDP announcements repeat, a late match takes a few periods)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class FoxgloveClient:
    """A minimal Foxglove WebSocket protocol client: offers ``subprotocols`` (only those),
    subscribes to every advertised channel and keeps the decoded JSON messages (with their log
    times) per topic; :attr:`subprotocol` is the name the server chose."""

    def __init__(self, url: str, subprotocols: list[str]) -> None:
        self.url = url
        self.offered = subprotocols
        self.subprotocol: str | None = None
        self.ws: Any = None
        self.channels: dict[int, dict[str, Any]] = {}
        self.subs: dict[int, str] = {}
        self.messages: dict[str, list[tuple[int, dict[str, Any], float]]] = defaultdict(list)
        self.errors: list[str] = []
        self._quit = threading.Event()
        self._connected = threading.Event()
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        if not self._connected.wait(timeout=10):
            raise AssertionError(f"no WebSocket connection to {url}: {self.errors}")

    def _run(self) -> None:
        from websockets.sync.client import connect

        try:
            with connect(self.url, subprotocols=self.offered,  # type: ignore[arg-type]
                         open_timeout=5) as ws:
                self.ws = ws
                self.subprotocol = ws.subprotocol
                self._connected.set()
                self._loop(ws)
        except Exception as exc:  # refused or closed
            if not self._quit.is_set():
                self.errors.append(repr(exc))

    def _loop(self, ws: Any) -> None:
        while not self._quit.is_set():
            try:
                m = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(m, str):
                d = json.loads(m)
                if d.get("op") == "advertise":
                    subs = []
                    for c in d["channels"]:
                        self.channels[c["id"]] = c
                        sid = len(self.subs) + 1
                        self.subs[sid] = c["topic"]
                        subs.append({"id": sid, "channelId": c["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif m and m[0] == 0x01:  # message data: op, subscription id, log time, payload
                sid, log_time = struct.unpack_from("<IQ", m, 1)
                with self.lock:
                    self.messages[self.subs[sid]].append(
                        (log_time, json.loads(m[13:]), time.monotonic()))

    def topics(self) -> set[str]:
        return {c["topic"] for c in self.channels.values()}

    def got(self, topic: str) -> list[tuple[int, dict[str, Any], float]]:
        with self.lock:
            return list(self.messages.get(topic, []))

    def close(self) -> None:
        self._quit.set()
        self.thread.join(timeout=5)


def _stamp(msg: dict[str, Any]) -> int:
    s = msg["header"]["stamp"]
    return int(s["sec"]) * 1_000_000_000 + int(s["nsec"])


def _launch(procs: Procs, tmp_path: Path) -> tuple[Any, int]:
    """``dvt-launch sim --foxglove`` (plant, driver, model node, bridge) up; its process and
    the bridge's port."""
    port = _free_port()
    launch = procs.start("dvt-launch", "sim", "--rate", str(SIM_RATE), "--foxglove",
                         "--foxglove-port", str(port), "--foxglove-param",
                         f"rate_hz:={RATE_HZ:g}", "--log-dir", str(tmp_path / "launch"))
    wait_for(lambda: "Foxglove: open" in procs.log(launch) or launch.poll() is not None, 60,
             "dvt-launch with --foxglove to be up")
    assert launch.poll() is None, procs.log(launch)
    return launch, port


@dataclass
class _Live:
    """A live bridge session: the client, the ROS messages of the same topics by stamp, the
    identifier summary published before the client connected, the window's start [s]."""
    launch: Any
    client: FoxgloveClient
    ros: dict[str, dict[int, list[float]]]
    summary: dict[str, Any]
    t0: float
    window: float


@contextlib.contextmanager
def _live(procs: Procs, rclpy_context: Any, tmp_path: Path) -> Iterator[_Live]:
    """``dvt-launch sim --foxglove`` with a client connected and a ROS node on the same
    topics, after a 5-s window of forwarded messages; the launch stopped (cleanly) after."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from dvt_model import rosutil

    launch, port = _launch(procs, tmp_path)

    node = rclpy.create_node("fox_check", context=rclpy_context)
    ros: dict[str, dict[int, list[float]]] = {JOINT_STATES: {}, MODEL_RESIDUAL: {}}
    def keep(topic: str) -> Any:
        def cb(m: Any) -> None:
            ros[topic][rosutil.stamp_to_ns(m.header.stamp)] = list(m.velocity)
        return cb

    for topic in ros:
        node.create_subscription(JointState, topic, keep(topic), rosutil.SENSOR_QOS)
    result_pub = node.create_publisher(String, IDENTIFY_RESULT, rosutil.LATCHED_QOS)
    ex = EventsExecutor(context=rclpy_context)  # cheap at 1 kHz: leaves the GIL to the client
    ex.add_node(node)

    # the identifier's result comes before the client connects: the client still gets it
    summary = {"baseline_fit_percent": {"sun_shaft": 97.5}, "pushed": {"node": "dvt_model"}}
    result_pub.publish(String(data=json.dumps(summary)))
    client = FoxgloveClient(f"ws://127.0.0.1:{port}", [SDK_SUBPROTOCOL])
    try:
        assert client.subprotocol == SDK_SUBPROTOCOL
        wait_for(lambda: client.topics() >= CHANNEL_TOPICS, 10, "the advertised channels")
        # the window opens at the first forwarded sample: the bridge is up once its
        # subscriptions exist, and DDS matches them with the publishers a moment later
        # (measured: up to 2.6 s after the channels were advertised, on a quiet machine)
        wait_for(lambda: bool(client.got(JOINT_STATES)), DISCOVERY_S,
                 "the first forwarded joint state (the bridge's DDS subscriptions matched)")
        window = 5.0
        t_end = time.monotonic() + window
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)
        yield _Live(launch, client, ros, summary, t_end - window, window)
    finally:
        client.close()
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
    rc = procs.stop(launch, timeout=30)
    assert rc in (0, 130), procs.log(launch)[-3000:]


@pytest.mark.flaky(reruns=2)  # timing only: on a shared 2-core machine a scheduling hiccup
# can delay one keep-alive or message; a real fault fails all three runs
def test_foxglove_bridge_live_rate(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    """The decimated 1 kHz stream comes at ``RATE_HZ``, by stamp and by arrival (the only
    timing checks of the bridge: the values are checked in a test that never reruns)."""
    with _live(procs, rclpy_context, tmp_path) as live:
        js = live.client.got(JOINT_STATES)
        inside = [m for m in js if m[2] >= live.t0]
        assert len(inside) >= 0.5 * RATE_HZ * live.window, (
            len(inside), procs.log(live.launch)[-2000:])
        stamps = [_stamp(m[1]) for m in js]
        steps = [b - a for a, b in itertools.pairwise(stamps)]
        period = 1e9 / RATE_HZ
        short = [d for d in steps if d < period - 1e9 / SIM_RATE - 1e6]
        assert steps and len(short) <= max(1, len(steps) // 20), steps[:40]
        assert sorted(steps)[len(steps) // 2] == pytest.approx(period, abs=1e9 / SIM_RATE), steps
        rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9)
        assert 0.7 * RATE_HZ <= rate <= 1.05 * RATE_HZ, rate


def test_foxglove_bridge_live(procs: Procs, rclpy_context: Any, tmp_path: Path) -> None:
    """What the client gets is what ROS has: the channels and their schemas, the values of the
    same stamps bit for bit, log time = sample stamp, the noise band, diagnostics, the driver's
    state, the identifier's latched result, and a layout naming only advertised channels."""
    with _live(procs, rclpy_context, tmp_path) as live:
        client, ros, summary = live.client, live.ros, live.summary
        assert client.topics() == set(CHANNEL_TOPICS)
        for c in client.channels.values():
            assert c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema", c
            assert json.loads(c["schema"])["type"] == "object", c
        js = client.got(JOINT_STATES)
        assert all(m[0] == _stamp(m[1]) for m in js), "log time is the sample stamp"

        # values: what the client got equals the ROS message of the same stamp
        for topic in (JOINT_STATES, MODEL_RESIDUAL):
            got = client.got(topic)
            matched = [(m[1]["velocity"], ros[topic][_stamp(m[1])]) for m in got
                       if _stamp(m[1]) in ros[topic]]
            assert len(matched) >= 20, (topic, len(got), len(ros[topic]))
            for ws_v, ros_v in matched:
                assert ws_v == pytest.approx(ros_v, rel=0, abs=0), (topic, ws_v, ros_v)
            assert got[-1][1]["name"] == ["sun_shaft", "carrier3"]

        # the noise band: stamped like the residual, lower <= mean <= upper
        band = client.got(RESIDUAL_BAND)
        res_stamps = {_stamp(m[1]) for m in client.got(MODEL_RESIDUAL)}
        assert band and all(_stamp(b[1]) in res_stamps for b in band)
        last = band[-1][1]
        assert last["samples"] > 1
        for lo, mu, hi in zip(last["lower"], last["mean"], last["upper"], strict=True):
            assert lo <= mu <= hi

        # diagnostics, the driver's state, the identifier's result
        diag = client.got(DIAGNOSTICS)
        assert any(s["name"] == "dvt_driver" for m in diag for s in m[1]["status"]), diag[:2]
        states = client.got(STATE)
        assert states and states[-1][1]["lifecycle_state"] == "active", states[-1:]
        wait_for(lambda: client.got(IDENTIFY), 5, "the identifier's result")
        assert client.got(IDENTIFY_RESULT)[-1][1]["data"] == json.dumps(summary)
        assert client.got(IDENTIFY)[-1][1] == summary

        # the shipped layout names only advertised channels
        layout = json.loads((ROOT / "docs" / "foxglove" / "dvt-layout.json").read_text())
        assert layout_topics(layout) <= client.topics()
        assert not client.errors, client.errors


def test_foxglove_bridge_live_both_subprotocol_names(procs: Procs, tmp_path: Path) -> None:
    """One bridge, two clients at once: one offering only the old name
    ``foxglove.websocket.v1``, one only the new ``foxglove.sdk.v1``; each gets its own name back
    and the joint states of the live plant/driver chain."""
    launch, port = _launch(procs, tmp_path)
    clients: dict[str, FoxgloveClient] = {}
    try:
        for name in (LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL):
            clients[name] = FoxgloveClient(f"ws://127.0.0.1:{port}", [name])
        for name, client in clients.items():
            assert client.subprotocol == name
            wait_for(lambda c=client: c.topics() >= CHANNEL_TOPICS, 10,
                     f"the advertised channels ({name})")
        wanted = int(RATE_HZ)  # about a second of the decimated stream
        for name, client in clients.items():
            wait_for(lambda c=client: len(c.got(JOINT_STATES)) >= wanted,
                     20, f"{wanted} {JOINT_STATES} messages ({name})")
            js = client.got(JOINT_STATES)
            stamps = [_stamp(m[1]) for m in js]
            assert all(b > a for a, b in itertools.pairwise(stamps)), (name, stamps[:20])
            assert all(m[0] == _stamp(m[1]) for m in js), f"{name}: log time is the sample stamp"
            assert all(m[1]["name"] == ["sun_shaft", "carrier3"] and len(m[1]["velocity"]) == 2
                       for m in js), (name, js[-1][1])
            assert not client.errors, (name, client.errors)
    finally:
        for client in clients.values():
            client.close()
    rc = procs.stop(launch, timeout=30)
    assert rc in (0, 130), procs.log(launch)[-3000:]
