"""``dvt-foxglove``: serve the live suite to the Foxglove app over WebSocket (foxglove-sdk).

Usage::

    dvt-foxglove [--ros-args -p port:=8765 -p host:=0.0.0.0 -p rate_hz:=100.0 ...]
    dvt-foxglove --ros-args --params-file docs/params/dvt_foxglove.yaml
    dvt-foxglove --bag BAG_DIR --out FILE.mcap     # a recorded bag -> MCAP with every channel

Live: node ``dvt_foxglove`` subscribes the suite's topics with the contract's QoS (sensor QoS
for the 1 kHz streams, reliable for commands and diagnostics, latched for the identifier's
result), decimates the 1 kHz streams to ``rate_hz`` by sample stamp and serves the channels of
:data:`dvt_driver.run.foxglove_core.CHANNELS` (JSON with JSON schemas) on
``ws://host:port`` (Foxglove: *Open connection* -> *Foxglove WebSocket*), to clients offering
either subprotocol name, ``foxglove.sdk.v1`` or the older ``foxglove.websocket.v1`` (see
:mod:`dvt_driver.run.foxglove_relay`). See ``docs/foxglove.md``. The 1 kHz streams are
subscribed raw: only the forwarded samples are deserialized, nothing at all while no client is
connected (and no ``mcap`` file is written).

Offline (``--bag``): reads a recorded bag and writes an MCAP file with the same channels
(decimated the same way, noise band, states and alarms included), to open in Foxglove with the
shipped layout.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from foxglove.websocket import ServerListener

from dvt_driver.run.foxglove_core import (
    CHANNELS,
    FOXGLOVE_NODE,
    LATCHED_CHANNELS,
    SETTINGS_DEFAULTS,
    SETTINGS_DOC,
    Bridge,
    BridgeSettings,
    BridgeSettingsError,
    ChannelSpec,
    Output,
    parse_settings,
    peek_stamp_ns,
)
from dvt_driver.run.foxglove_relay import SubprotocolRelay

_SDK_HOST = "127.0.0.1"
"""Where the foxglove-sdk server listens (any free port); the public address is the relay's."""

_ROS_TYPES = {
    "sensor_msgs/msg/JointState": ("sensor_msgs.msg", "JointState"),
    "diagnostic_msgs/msg/DiagnosticArray": ("diagnostic_msgs.msg", "DiagnosticArray"),
    "std_msgs/msg/Float64": ("std_msgs.msg", "Float64"),
    "std_msgs/msg/Int8": ("std_msgs.msg", "Int8"),
    "std_msgs/msg/String": ("std_msgs.msg", "String"),
}


class Channels:
    """The foxglove-sdk channels of :data:`CHANNELS` in one context, with optional MCAP."""

    def __init__(self, mcap: str = "") -> None:
        import foxglove

        self.context = foxglove.Context()
        self.channels = {c.topic: foxglove.Channel(
            c.topic, schema=_schema(c), message_encoding="json", context=self.context,
            metadata={"source": c.source or "dvt-foxglove", "doc": c.doc})
            for c in CHANNELS}
        self.writer: Any = None
        if mcap:
            path = Path(mcap)
            if path.exists():
                raise BridgeSettingsError(f"mcap: {path} exists; will not overwrite it")
            self.writer = foxglove.open_mcap(path, context=self.context)

    def active(self, topic: str) -> bool:
        """Whether anything (a client, the MCAP file) takes messages of ``topic``."""
        return self.writer is not None or self.channels[topic].has_sinks()

    def log(self, outputs: list[Output]) -> None:
        for topic, data, t in outputs:
            self.channels[topic].log(data, log_time=t)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class _Subscriptions(ServerListener):
    """foxglove-sdk server listener: notes which latched channels got a new subscriber (the
    node re-sends their last message from its executor, not from the server's thread)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pending: set[str] = set()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        if channel.topic in LATCHED_CHANNELS:
            with self.lock:
                self.pending.add(channel.topic)

    def take(self) -> set[str]:
        with self.lock:
            out, self.pending = self.pending, set()
        return out


def _schema(spec: ChannelSpec) -> Any:
    import json

    import foxglove

    return foxglove.Schema(name=spec.schema_name, encoding="jsonschema",
                           data=json.dumps(spec.schema).encode())


def _node_class() -> type:
    import importlib

    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node
    from rclpy.serialization import deserialize_message

    from dvt_model import rosutil
    from dvt_model.contract import DIAGNOSTICS_QOS

    class FoxgloveNode(Node):
        """Node ``dvt_foxglove`` (see the module docstring)."""

        def __init__(self) -> None:
            super().__init__(FOXGLOVE_NODE)
            ro = {"read_only": True, "dynamic_typing": True}
            values = {name: self.declare_parameter(name, default, ParameterDescriptor(
                description=SETTINGS_DOC[name], **ro)).value
                for name, default in SETTINGS_DEFAULTS.items()}
            self.settings: BridgeSettings = parse_settings(values)
            self.bridge = Bridge(self.settings)
            self.out = Channels(self.settings.mcap)
            import foxglove

            foxglove.set_log_level("WARN")
            self.listener = _Subscriptions()
            where = f"{self.settings.host}:{self.settings.port}"
            try:  # the SDK server on a loopback port; clients reach it through the relay
                self.server = foxglove.start_server(
                    name="dvt", host=_SDK_HOST, port=0, context=self.out.context,
                    server_listener=self.listener)
            except Exception as exc:  # FoxgloveError
                self.out.close()
                raise BridgeSettingsError(f"host/port: cannot serve on {where}: "
                                          f"foxglove-sdk server: {exc}") from exc
            try:
                self.relay = SubprotocolRelay(self.settings.host, self.settings.port,
                                              (_SDK_HOST, self.server.port), self._relay_warning)
            except OSError as exc:  # address in use, unknown host, ...
                self.server.stop()
                self.out.close()
                raise BridgeSettingsError(f"host/port: cannot serve on {where}: {exc}") from exc
            self.port = self.relay.port
            self.received = 0
            qos = {"sensor": rosutil.SENSOR_QOS, "command": rosutil.COMMAND_QOS,
                   "latched": rosutil.LATCHED_QOS, "diag": rosutil.qos(DIAGNOSTICS_QOS)}
            from dvt_model.contract import COMMAND_TOPICS, DIAGNOSTICS, IDENTIFY_RESULT

            for source, spec in self.bridge.by_source.items():
                module, name = _ROS_TYPES[spec.schema_name]
                cls = getattr(importlib.import_module(module), name)
                if spec.decimated:
                    self.create_subscription(cls, source, self._raw_cb(source, cls),
                                             qos["sensor"], raw=True)
                    continue
                profile = (qos["diag"] if source == DIAGNOSTICS else
                           qos["latched"] if source == IDENTIFY_RESULT else
                           qos["command"] if source in COMMAND_TOPICS else qos["sensor"])
                self.create_subscription(cls, source, self._msg_cb(source), profile)
            self.create_timer(0.1, self._resend_latched)
            self.get_logger().info(
                f"serving {len(CHANNELS)} channels on ws://{self.settings.host}:{self.port} "
                f"(1 kHz streams at {self.settings.rate_hz:g} Hz)"
                + (f", writing {self.settings.mcap}" if self.settings.mcap else ""))
            print(f"READY ws://{self.settings.host}:{self.port}", flush=True)

        def _raw_cb(self, topic: str, cls: type) -> Any:
            def cb(raw: bytes) -> None:
                self.received += 1
                try:
                    stamp = peek_stamp_ns(raw)
                except ValueError as exc:
                    self.get_logger().warning(f"{topic}: {exc}", throttle_duration_sec=10.0)
                    return
                if not self.bridge.wants(topic, stamp) or not self.out.active(topic):
                    return
                msg = deserialize_message(raw, cls)
                self.out.log(self.bridge.handle(topic, msg, time.time_ns()))
            return cb

        def _msg_cb(self, topic: str) -> Any:
            def cb(msg: Any) -> None:
                self.received += 1
                self.out.log(self.bridge.handle(topic, msg, self.get_clock().now().nanoseconds))
            return cb

        def _resend_latched(self) -> None:
            # a client that subscribes after the identifier's result still gets it (a message
            # that came between the subscription and this timer arrives twice)
            for topic in self.listener.take():
                last = self.bridge.last.get(topic)
                if last is not None:
                    self.out.log([last])

        def _relay_warning(self, text: str) -> None:
            self.get_logger().warning(f"WebSocket: {text}", throttle_duration_sec=10.0)

        def on_shutdown_hook(self) -> None:
            self.relay.close()
            self.server.stop()
            self.out.close()

    return FoxgloveNode


def convert_bag(bag: Path, out: Path, settings: BridgeSettings) -> dict[str, int]:
    """Write the bridge's channels for recorded ``bag`` into the MCAP file ``out``.

    Returns the number of messages per channel.

    Raises:
        BridgeSettingsError: ``out`` exists, ``bag`` is not a bag directory or cannot be read
            (the recording's reader's error, naming the bag and topic).
    """
    from dvt_model.errors import BagError
    from dvt_model.recording.messages import BagMessages, decode

    if out.exists():
        raise BridgeSettingsError(f"--out: {out} exists; will not overwrite it")
    if not (bag / "metadata.yaml").exists():
        raise BridgeSettingsError(f"--bag: {bag} is not a bag directory (no metadata.yaml)")
    bridge = Bridge(settings)
    sources = {s.source: s for s in bridge.sources}
    try:
        with BagMessages(bag) as reader:
            wanted = [t for t in reader.types if t in sources]
            chans = Channels(str(out))
            try:
                for m in reader.messages(wanted):
                    if (sources[m.topic].decimated
                            and not bridge.decimator.due(m.topic, peek_stamp_ns(m.data))):
                        continue
                    chans.log(bridge.handle(m.topic, decode(m), m.log_time_ns))
            finally:
                chans.close()
    except BagError as exc:
        raise BridgeSettingsError(f"--bag: {exc}") from exc
    return {k: v for k, v in bridge.forwarded.items() if v}


def _settings_from_args(args: argparse.Namespace) -> BridgeSettings:
    return parse_settings({"rate_hz": args.rate})


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-foxglove``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--bag" in argv or "--out" in argv or "-h" in argv or "--help" in argv:
        p = argparse.ArgumentParser(prog="dvt-foxglove", description=__doc__.split("\n\n")[0])
        p.add_argument("--bag", type=Path, required=True, help="recorded bag directory")
        p.add_argument("--out", type=Path, required=True, help="MCAP file to write")
        p.add_argument("--rate", type=float, default=SETTINGS_DEFAULTS["rate_hz"],
                       help="forwarding rate of the 1 kHz streams [Hz] (default %(default)s)")
        args = p.parse_args(argv)
        try:
            counts = convert_bag(args.bag, args.out, _settings_from_args(args))
        except BridgeSettingsError as exc:
            print(f"dvt-foxglove: error: {exc}", file=sys.stderr)
            return 2
        print(f"dvt-foxglove: wrote {args.out}: " +
              ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
        return 0
    from dvt_model import rosutil

    rosutil.init([sys.argv[0], *argv])
    try:
        node = _node_class()()
    except (BridgeSettingsError, RuntimeError) as exc:
        print(f"dvt-foxglove: error: {exc}", file=sys.stderr)
        import rclpy

        rclpy.try_shutdown()
        return 2
    rosutil.spin(node)
    return 0


if __name__ == "__main__":
    sys.exit(main())
