"""What ``dvt-foxglove`` serves, as data and pure functions (no rclpy, no foxglove import).

The bridge (:mod:`dvt_driver.run.foxglove`) advertises one Foxglove channel per entry of
:data:`CHANNELS`, all JSON-encoded with a JSON schema:

* the suite's ROS topics under their own names and with their ROS field layout
  (``/dvt/joint_states``, ``/dvt/currents``, ``/dvt/model/joint_states``,
  ``/dvt/model/residual``, ``/diagnostics``, the ``/dvt/cmd/*`` commands and
  ``/dvt/identify/result``), so that a Foxglove message path such as
  ``/dvt/joint_states.velocity[0]`` means the same live and in a recorded bag opened as a file.
  Times are ``{"sec", "nsec"}`` (how Foxglove shows a ROS 2 ``builtin_interfaces/Time``);
  angles (``position``) are forwarded when the driver fills them;
* derived channels under ``/dvt/foxglove/``: the residual's noise band
  (:class:`ResidualBand`), the gear and band (brake) states (:class:`StateTracker`), alarms as
  ``foxglove.Log`` (:class:`AlarmTracker`) and the identifier's result parsed into numbers.

The high-rate streams (1 kHz) are decimated to ``rate_hz`` (:class:`Decimator`) by sample
stamp: the first sample of every ``1/rate_hz`` interval is forwarded, so the measured,
predicted and residual messages the bridge forwards carry the same stamps.

:func:`dvt_driver.run.foxglove_layout.build_layout` makes the shipped layout
``docs/foxglove/dvt-layout.json``; :func:`~dvt_driver.run.foxglove_layout.layout_topics` lists the
channels a layout names (the test checks they are all
advertised).
"""

from __future__ import annotations

import json
import math
import struct
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dvt_driver.link.settings import DEFAULT_SETTINGS
from dvt_model.contract import (
    BRAKE_NAMES,
    CMD_BRAKE_CURRENTS,
    CMD_GEAR,
    CMD_MOTOR_CURRENT,
    CMD_SUN_SPEED,
    CURRENT_NAMES,
    CURRENTS,
    DIAGNOSTICS,
    DRIVER_NODE,
    IDENTIFY_RESULT,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    MODEL_RESIDUAL,
    SPEED_NAMES,
)

FOXGLOVE_NODE = "dvt_foxglove"
"""Node name of the bridge."""

ENGAGED_FRACTION = 0.8
"""The default engaged threshold as a fraction of the driver's ``gear_engage_current``: a band
is held at that current, so a threshold equal to it flickers with the current's noise."""

STATE = "/dvt/foxglove/state"
"""Gear and band (brake) states: the driver's gear/shift/mode from ``/diagnostics``, each
band engaged when its measured current exceeds ``band_engaged_current``."""
RESIDUAL_BAND = "/dvt/foxglove/residual_band"
"""The residual's noise band: mean +- ``band_sigmas`` standard deviations over the last
``band_window_s`` seconds of forwarded residual samples, stamped like the residual."""
ALARMS = "/dvt/foxglove/alarms"
"""``foxglove.Log`` entries: a status of ``/diagnostics`` entering or changing at WARN or
above (WARNING/ERROR), or returning to OK (INFO)."""
IDENTIFY = "/dvt/foxglove/identify"
"""The identifier's result (``/dvt/identify/result`` JSON text) as an object."""

SETTINGS_DEFAULTS: dict[str, Any] = {
    "host": "127.0.0.1",
    "port": 8765,
    "rate_hz": 100.0,
    "band_window_s": 2.0,
    "band_sigmas": 3.0,
    "band_engaged_current": round(ENGAGED_FRACTION * DEFAULT_SETTINGS["gear_engage_current"], 6),
    "state_period_s": 0.5,
    "mcap": "",
}
"""The bridge's parameters and their defaults."""

SETTINGS_DOC: dict[str, str] = {
    "host": "address the WebSocket server binds to (0.0.0.0: every interface)",
    "port": "WebSocket port (0: any free port)",
    "rate_hz": "forwarding rate of the 1 kHz streams [Hz], by sample stamp (0 < rate <= 10000)",
    "band_window_s": "window of the residual's noise band [s]",
    "band_sigmas": "half-width of the noise band in standard deviations",
    "band_engaged_current": "a band (brake) counts as engaged above this current [A] (default "
                            "0.8 x the driver's gear_engage_current: a held band's current "
                            "noise must not flicker the flag)",
    "state_period_s": "the state channel is re-sent at least this often [s]",
    "mcap": "also write everything served to this MCAP file ('' = no)",
}


class BridgeSettingsError(ValueError):
    """A bridge parameter is not admissible (the message names it and the value)."""


@dataclass(frozen=True)
class BridgeSettings:
    """The bridge's parameters, validated (see :data:`SETTINGS_DOC`)."""

    host: str
    port: int
    rate_hz: float
    band_window_s: float
    band_sigmas: float
    band_engaged_current: float
    state_period_s: float
    mcap: str


def _number(name: str, value: Any, lo: float, hi: float, lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise BridgeSettingsError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if (v <= lo if lo_open else v < lo) or v > hi:
        raise BridgeSettingsError(f"{name}: {v!r} is not admissible: expected "
                                  f"{'(' if lo_open else '['}{lo:g}, {hi:g}]")
    return v


def parse_settings(values: Mapping[str, Any]) -> BridgeSettings:
    """Validate parameter values (missing ones take :data:`SETTINGS_DEFAULTS`).

    Raises:
        BridgeSettingsError: naming the first bad parameter and its value.
    """
    unknown = sorted(set(values) - set(SETTINGS_DEFAULTS))
    if unknown:
        raise BridgeSettingsError(f"unknown parameter(s) {unknown}; expected some of "
                                  f"{sorted(SETTINGS_DEFAULTS)}")
    v = {**SETTINGS_DEFAULTS, **values}
    host = v["host"]
    if not isinstance(host, str) or not host.strip():
        raise BridgeSettingsError(f"host: expected an address such as 127.0.0.1 or 0.0.0.0, "
                                  f"got {host!r}")
    port = v["port"]
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise BridgeSettingsError(f"port: expected an integer 0..65535, got {port!r}")
    mcap = v["mcap"]
    if not isinstance(mcap, str):
        raise BridgeSettingsError(f"mcap: expected a file path or '', got {mcap!r}")
    return BridgeSettings(
        host=host.strip(), port=port,
        rate_hz=_number("rate_hz", v["rate_hz"], 0.0, 10000.0, lo_open=True),
        band_window_s=_number("band_window_s", v["band_window_s"], 0.0, 3600.0, lo_open=True),
        band_sigmas=_number("band_sigmas", v["band_sigmas"], 0.0, 100.0, lo_open=True),
        band_engaged_current=_number("band_engaged_current", v["band_engaged_current"],
                                     0.0, 1000.0),
        state_period_s=_number("state_period_s", v["state_period_s"], 0.0, 3600.0,
                               lo_open=True),
        mcap=mcap)


# ----------------------------------------------------------------------------- JSON schemas
def _array(items: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": items}}


TIME_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "time",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
HEADER_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {"stamp": TIME_SCHEMA, "frame_id": {"type": "string"}}}
JOINT_STATE_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "sensor_msgs/msg/JointState",
    "properties": {"header": HEADER_SCHEMA, "name": _array("string"),
                   "position": _array("number"), "velocity": _array("number"),
                   "effort": _array("number")}}
DIAGNOSTIC_ARRAY_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "diagnostic_msgs/msg/DiagnosticArray",
    "properties": {"header": HEADER_SCHEMA, "status": {"type": "array", "items": {
        "type": "object", "properties": {
            "level": {"type": "integer", "description": "0 OK, 1 WARN, 2 ERROR, 3 STALE"},
            "name": {"type": "string"}, "message": {"type": "string"},
            "hardware_id": {"type": "string"},
            "values": {"type": "array", "items": {"type": "object", "properties": {
                "key": {"type": "string"}, "value": {"type": "string"}}}}}}}}}
FLOAT64_SCHEMA: dict[str, Any] = {"type": "object", "title": "std_msgs/msg/Float64",
                                  "properties": {"data": {"type": "number"}}}
INT8_SCHEMA: dict[str, Any] = {"type": "object", "title": "std_msgs/msg/Int8",
                               "properties": {"data": {"type": "integer"}}}
STRING_SCHEMA: dict[str, Any] = {"type": "object", "title": "std_msgs/msg/String",
                                 "properties": {"data": {"type": "string"}}}
STATE_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "dvt/FoxgloveState",
    "properties": {
        "header": HEADER_SCHEMA,
        "gear": {"type": "integer", "description": "gear reported by the driver, -1 unknown"},
        "shifting": {"type": "boolean"},
        "mode": {"type": "string", "description": "motor mode reported by the driver"},
        "lifecycle_state": {"type": "string"},
        "controller_status": {"type": "integer", "description": "status bits of the controller"},
        "driver_level": {"type": "integer", "description": "driver diagnostics level, -1 none"},
        "band_names": _array("string"),
        "band_currents": _array("number"),
        "bands_engaged": {"type": "array", "items": {"type": "integer"},
                          "description": "1 when the band's current exceeds the threshold"},
        "engaged_count": {"type": "integer"}}}
BAND_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "dvt/ResidualBand",
    "properties": {"header": HEADER_SCHEMA, "name": _array("string"),
                   "mean": _array("number"), "sigma": _array("number"),
                   "lower": _array("number"), "upper": _array("number"),
                   "samples": {"type": "integer"}, "window_s": {"type": "number"},
                   "sigmas": {"type": "number"}}}
LOG_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "foxglove.Log",
    "properties": {"timestamp": TIME_SCHEMA,
                   "level": {"type": "integer",
                             "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, "
                                            "5 FATAL"},
                   "message": {"type": "string"}, "name": {"type": "string"},
                   "file": {"type": "string"}, "line": {"type": "integer"}}}
IDENTIFY_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "dvt/IdentifyResult",
    "description": "the identifier's JSON summary (fit percentages per output, accepted "
                   "terms, pushed parameters, error)",
    "additionalProperties": True, "properties": {}}


@dataclass(frozen=True)
class ChannelSpec:
    """One channel the bridge advertises."""

    topic: str
    schema_name: str
    schema: dict[str, Any]
    source: str | None
    """The ROS topic it comes from (``None``: derived by the bridge)."""
    decimated: bool = False
    """Forwarded at ``rate_hz`` instead of every message."""
    doc: str = ""


CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec(JOINT_STATES, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA, JOINT_STATES,
                True, f"measured speeds [rad/s] {list(SPEED_NAMES)} (angles [rad] when present)"),
    ChannelSpec(CURRENTS, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA, CURRENTS, True,
                f"measured currents [A] (effort) {list(CURRENT_NAMES)}"),
    ChannelSpec(MODEL_JOINT_STATES, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA,
                MODEL_JOINT_STATES, True, "predicted speeds [rad/s]"),
    ChannelSpec(MODEL_RESIDUAL, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA, MODEL_RESIDUAL,
                True, "measured - predicted speeds [rad/s]"),
    ChannelSpec(DIAGNOSTICS, "diagnostic_msgs/msg/DiagnosticArray", DIAGNOSTIC_ARRAY_SCHEMA,
                DIAGNOSTICS, False, "every node's status"),
    ChannelSpec(CMD_MOTOR_CURRENT, "std_msgs/msg/Float64", FLOAT64_SCHEMA, CMD_MOTOR_CURRENT,
                False, "commanded motor current [A]"),
    ChannelSpec(CMD_SUN_SPEED, "std_msgs/msg/Float64", FLOAT64_SCHEMA, CMD_SUN_SPEED, False,
                "commanded sun speed [rad/s]"),
    ChannelSpec(CMD_BRAKE_CURRENTS, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA,
                CMD_BRAKE_CURRENTS, False, "commanded band currents [A] (effort)"),
    ChannelSpec(CMD_GEAR, "std_msgs/msg/Int8", INT8_SCHEMA, CMD_GEAR, False, "commanded gear"),
    ChannelSpec(IDENTIFY_RESULT, "std_msgs/msg/String", STRING_SCHEMA, IDENTIFY_RESULT, False,
                "the identifier's result (JSON text)"),
    ChannelSpec(STATE, "dvt/FoxgloveState", STATE_SCHEMA, None, False,
                "gear and band states"),
    ChannelSpec(RESIDUAL_BAND, "dvt/ResidualBand", BAND_SCHEMA, None, False,
                "the residual's noise band"),
    ChannelSpec(ALARMS, "foxglove.Log", LOG_SCHEMA, None, False, "alarms from /diagnostics"),
    ChannelSpec(IDENTIFY, "dvt/IdentifyResult", IDENTIFY_SCHEMA, None, False,
                "the identifier's result as an object"),
)
"""Every channel the bridge advertises, in advertising order."""

CHANNEL_TOPICS: frozenset[str] = frozenset(c.topic for c in CHANNELS)

LATCHED_CHANNELS: frozenset[str] = frozenset({IDENTIFY_RESULT, IDENTIFY})
"""Channels whose last message a client gets when it subscribes (the identifier's result is
latched on the ROS side too: it comes once per run)."""


def channel(topic: str) -> ChannelSpec:
    """The spec of channel ``topic`` (``KeyError`` naming it if the bridge has none)."""
    for c in CHANNELS:
        if c.topic == topic:
            return c
    raise KeyError(f"the bridge advertises no channel {topic!r}")


# ---------------------------------------------------------------------- message conversion
def stamp_ns(stamp: Any) -> int:
    """Nanoseconds of a ROS time (``sec``/``nanosec`` attributes)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_json(ns: int) -> dict[str, int]:
    """A time as Foxglove shows it: ``{"sec", "nsec"}``."""
    return {"sec": int(ns // 1_000_000_000), "nsec": int(ns % 1_000_000_000)}


def header_json(header: Any) -> dict[str, Any]:
    return {"stamp": time_json(stamp_ns(header.stamp)), "frame_id": str(header.frame_id)}


def _floats(values: Iterable[Any]) -> list[float | None]:
    # JSON has no NaN/inf: a non-finite value becomes null (Foxglove leaves a gap)
    out: list[float | None] = []
    for v in values:
        f = float(v)
        out.append(f if math.isfinite(f) else None)
    return out


def joint_state_json(msg: Any) -> dict[str, Any]:
    """A ``sensor_msgs/JointState`` (rclpy or rosbags message) as JSON-ready data."""
    return {"header": header_json(msg.header), "name": [str(n) for n in msg.name],
            "position": _floats(msg.position), "velocity": _floats(msg.velocity),
            "effort": _floats(msg.effort)}


def _level(value: Any) -> int:
    if isinstance(value, bytes | bytearray):
        return value[0] if value else 0
    return int(value)


def diagnostic_array_json(msg: Any) -> dict[str, Any]:
    """A ``diagnostic_msgs/DiagnosticArray`` as JSON-ready data (``level`` as a number)."""
    return {"header": header_json(msg.header), "status": [
        {"level": _level(s.level), "name": str(s.name), "message": str(s.message),
         "hardware_id": str(s.hardware_id),
         "values": [{"key": str(kv.key), "value": str(kv.value)} for kv in s.values]}
        for s in msg.status]}


def float64_json(msg: Any) -> dict[str, Any]:
    f = float(msg.data)
    return {"data": f if math.isfinite(f) else None}


def int8_json(msg: Any) -> dict[str, Any]:
    return {"data": int(msg.data)}


def string_json(msg: Any) -> dict[str, Any]:
    return {"data": str(msg.data)}


CONVERTERS = {
    "sensor_msgs/msg/JointState": joint_state_json,
    "diagnostic_msgs/msg/DiagnosticArray": diagnostic_array_json,
    "std_msgs/msg/Float64": float64_json,
    "std_msgs/msg/Int8": int8_json,
    "std_msgs/msg/String": string_json,
}
"""ROS type name -> converter, for every forwarded channel's ``schema_name``."""


def identify_json(text: str) -> dict[str, Any]:
    """The identifier's result text as an object (``{"error": ...}`` if it is not one)."""
    try:
        data = json.loads(text)
    except ValueError as exc:
        return {"error": f"result is not JSON: {exc}", "text": text[:200]}
    if not isinstance(data, dict):
        return {"error": f"result is not a JSON object: {type(data).__name__}"}
    return _finite(data)


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def peek_stamp_ns(cdr: bytes) -> int:
    """``header.stamp`` [ns] of a serialized message that starts with a ``std_msgs/Header``
    (CDR: 4-byte encapsulation, then ``int32 sec``, ``uint32 nanosec``), without decoding it.

    Raises:
        ValueError: the buffer is too short or its encapsulation is not plain CDR.
    """
    if len(cdr) < 12:
        raise ValueError(f"serialized message of {len(cdr)} bytes is too short for a header")
    kind = cdr[1]
    if cdr[0] != 0 or kind not in (0, 1):
        raise ValueError(f"unknown CDR encapsulation 0x{cdr[0]:02x}{kind:02x}")
    sec, nsec = struct.unpack_from("<iI" if kind == 1 else ">iI", cdr, 4)
    return sec * 1_000_000_000 + nsec


# ------------------------------------------------------------------------------ decimation
class Decimator:
    """Forwards the first message of every ``1/rate_hz`` interval of sample stamps, per topic.

    Deterministic in the stamps: topics that carry the same stamps (measured, predicted,
    residual) forward the same samples. A stamp that goes back (clock reset) starts anew.
    """

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz: expected > 0, got {rate_hz!r}")
        self.period_ns = max(1, round(1e9 / rate_hz))
        self._last: dict[str, int] = {}

    def due(self, topic: str, stamp: int) -> bool:
        """Whether the message of ``topic`` stamped ``stamp`` [ns] is forwarded."""
        bucket = stamp // self.period_ns
        if self._last.get(topic) == bucket:
            return False
        self._last[topic] = bucket
        return True


# ---------------------------------------------------------------------------- noise band
class ResidualBand:
    """Mean +- k standard deviations of the residual over a sliding window of stamps."""

    def __init__(self, window_s: float, sigmas: float) -> None:
        self.window_ns = round(window_s * 1e9)
        self.window_s = window_s
        self.sigmas = sigmas
        self.samples: deque[tuple[int, list[float]]] = deque()

    def add(self, stamp: int, names: Sequence[str], values: Sequence[float | None]
            ) -> dict[str, Any]:
        """Add a residual sample; returns the band message (stamped ``stamp``)."""
        if self.samples and stamp < self.samples[-1][0]:
            self.samples.clear()  # the clock went back
        clean = [math.nan if v is None else float(v) for v in values]
        self.samples.append((stamp, clean))
        while self.samples and self.samples[0][0] <= stamp - self.window_ns:
            self.samples.popleft()
        n_out = len(clean)
        mean: list[float | None] = []
        sigma: list[float | None] = []
        lower: list[float | None] = []
        upper: list[float | None] = []
        for i in range(n_out):
            xs = [s[1][i] for s in self.samples if i < len(s[1]) and math.isfinite(s[1][i])]
            if not xs:
                mean.append(None)
                sigma.append(None)
                lower.append(None)
                upper.append(None)
                continue
            m = math.fsum(xs) / len(xs)
            sd = math.sqrt(math.fsum((x - m) ** 2 for x in xs) / len(xs))
            mean.append(m)
            sigma.append(sd)
            lower.append(m - self.sigmas * sd)
            upper.append(m + self.sigmas * sd)
        return {"header": {"stamp": time_json(stamp), "frame_id": ""}, "name": list(names),
                "mean": mean, "sigma": sigma, "lower": lower, "upper": upper,
                "samples": len(self.samples), "window_s": self.window_s,
                "sigmas": self.sigmas}


# ----------------------------------------------------------------------- gear/band states
def _int(text: str, default: int) -> int:
    try:
        return int(text, 0)
    except ValueError:
        return default


class StateTracker:
    """Gear and band states from the driver's ``/diagnostics`` and the measured currents.

    :meth:`update_currents` / :meth:`update_diagnostics` return the state message when it
    changed or ``period_s`` passed since the last one (by stamp), else ``None``.
    """

    def __init__(self, engaged_current: float, period_s: float,
                 driver_name: str = DRIVER_NODE) -> None:
        self.engaged_current = engaged_current
        self.period_ns = round(period_s * 1e9)
        self.driver_name = driver_name
        self.gear = -1
        self.shifting = False
        self.mode = ""
        self.lifecycle_state = ""
        self.controller_status = 0
        self.driver_level = -1
        self.band_currents: list[float] = [0.0] * len(BRAKE_NAMES)
        self._last_key: tuple[Any, ...] | None = None
        self._last_sent: int | None = None

    def _key(self) -> tuple[Any, ...]:
        return (self.gear, self.shifting, self.mode, self.lifecycle_state,
                self.controller_status, self.driver_level, tuple(self.engaged()))

    def engaged(self) -> list[int]:
        return [int(abs(c) > self.engaged_current) for c in self.band_currents]

    def message(self, stamp: int) -> dict[str, Any]:
        engaged = self.engaged()
        return {"header": {"stamp": time_json(stamp), "frame_id": ""}, "gear": self.gear,
                "shifting": self.shifting, "mode": self.mode,
                "lifecycle_state": self.lifecycle_state,
                "controller_status": self.controller_status, "driver_level": self.driver_level,
                "band_names": list(BRAKE_NAMES), "band_currents": list(self.band_currents),
                "bands_engaged": engaged, "engaged_count": sum(engaged)}

    def _emit(self, stamp: int) -> dict[str, Any] | None:
        key = self._key()
        due = (self._last_sent is None or key != self._last_key
               or stamp - self._last_sent >= self.period_ns or stamp < self._last_sent)
        if not due:
            return None
        self._last_key, self._last_sent = key, stamp
        return self.message(stamp)

    def update_currents(self, stamp: int, names: Sequence[str],
                        effort: Sequence[float | None]) -> dict[str, Any] | None:
        by_name = dict(zip(names, effort, strict=False))
        self.band_currents = [float(by_name.get(n) or 0.0) for n in BRAKE_NAMES]
        return self._emit(stamp)

    def update_diagnostics(self, stamp: int, diag: Mapping[str, Any]) -> dict[str, Any] | None:
        """Take the driver's status from a converted DiagnosticArray (others are ignored)."""
        found = False
        for st in diag.get("status", []):
            if st.get("name") != self.driver_name:
                continue
            found = True
            values = {kv["key"]: kv["value"] for kv in st.get("values", [])}
            self.driver_level = int(st.get("level", -1))
            gear = values.get("gear", "")
            self.gear = _int(gear, -1) if gear != "" else -1
            self.shifting = values.get("shifting", "False") == "True"
            self.mode = values.get("mode", "")
            self.lifecycle_state = values.get("lifecycle_state", "")
            self.controller_status = _int(values.get("controller_status", "0"), 0)
        return self._emit(stamp) if found else None


# ----------------------------------------------------------------------------------- alarms
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
_DIAG_TO_LOG = {1: LOG_WARNING, 2: LOG_ERROR, 3: LOG_WARNING}


class AlarmTracker:
    """Turns ``/diagnostics`` statuses into ``foxglove.Log`` alarms (on change only)."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[int, str]] = {}

    def update(self, diag: Mapping[str, Any]) -> list[dict[str, Any]]:
        """The alarms raised by a converted DiagnosticArray (possibly none)."""
        stamp = diag.get("header", {}).get("stamp", {"sec": 0, "nsec": 0})
        out: list[dict[str, Any]] = []
        for st in diag.get("status", []):
            name, level, message = str(st.get("name", "")), int(st.get("level", 0)), \
                str(st.get("message", ""))
            prev = self._last.get(name)
            self._last[name] = (level, message)
            if level > 0 and (prev is None or prev != (level, message)):
                out.append({"timestamp": dict(stamp), "level": _DIAG_TO_LOG.get(level, LOG_ERROR),
                            "message": message, "name": name, "file": "", "line": 0})
            elif level == 0 and prev is not None and prev[0] > 0:
                out.append({"timestamp": dict(stamp), "level": LOG_INFO,
                            "message": f"recovered: {message}", "name": name, "file": "",
                            "line": 0})
        return out


# ---------------------------------------------------------------------------------- bridge
Output = tuple[str, dict[str, Any], int]
"""(channel topic, JSON-ready message, log time [ns])."""


class Bridge:
    """The bridge's logic between ROS messages and Foxglove channels (no I/O).

    For a decimated topic ask :meth:`wants` with the sample stamp first (the node peeks it in
    the raw message, :func:`peek_stamp_ns`) and convert only what is wanted; :meth:`handle`
    turns one ROS message (rclpy or rosbags) into the messages to log on the channels.
    """

    def __init__(self, settings: BridgeSettings) -> None:
        self.settings = settings
        self.decimator = Decimator(settings.rate_hz)
        self.band = ResidualBand(settings.band_window_s, settings.band_sigmas)
        self.state = StateTracker(settings.band_engaged_current, settings.state_period_s)
        self.alarms = AlarmTracker()
        self.forwarded: dict[str, int] = {c.topic: 0 for c in CHANNELS}
        self.last: dict[str, Output] = {}
        """The last message of each of :data:`LATCHED_CHANNELS` (re-sent to new subscribers)."""
        self._specs = {c.source: c for c in CHANNELS if c.source is not None}

    @property
    def sources(self) -> tuple[ChannelSpec, ...]:
        """The channels forwarded from ROS topics."""
        return tuple(self._specs.values())

    @property
    def by_source(self) -> dict[str, ChannelSpec]:
        """The channels forwarded from ROS topics, by source topic."""
        return dict(self._specs)

    def wants(self, topic: str, stamp: int) -> bool:
        """Whether a sample of ``topic`` stamped ``stamp`` [ns] is forwarded (decimation)."""
        spec = self._specs.get(topic)
        if spec is None:
            return False
        return not spec.decimated or self.decimator.due(topic, stamp)

    def handle(self, topic: str, msg: Any, now_ns: int) -> list[Output]:
        """The channel messages for one ROS message of ``topic`` (already decimated)."""
        spec = self._specs.get(topic)
        if spec is None:
            raise KeyError(f"the bridge forwards no topic {topic!r}")
        data = CONVERTERS[spec.schema_name](msg)
        header = data.get("header")
        t = (header["stamp"]["sec"] * 1_000_000_000 + header["stamp"]["nsec"]
             if isinstance(header, dict) else now_ns)
        out: list[Output] = [(topic, data, t)]
        if topic == MODEL_RESIDUAL:
            out.append((RESIDUAL_BAND, self.band.add(t, data["name"], data["velocity"]), t))
        elif topic == CURRENTS:
            st = self.state.update_currents(t, data["name"], data["effort"])
            if st is not None:
                out.append((STATE, st, t))
        elif topic == DIAGNOSTICS:
            st = self.state.update_diagnostics(t, data)
            if st is not None:
                out.append((STATE, st, t))
            out.extend((ALARMS, a, t) for a in self.alarms.update(data))
        elif topic == IDENTIFY_RESULT:
            out.append((IDENTIFY, identify_json(data["data"]), t))
        for o in out:
            self.forwarded[o[0]] += 1
            if o[0] in LATCHED_CHANNELS:
                self.last[o[0]] = o
        return out
