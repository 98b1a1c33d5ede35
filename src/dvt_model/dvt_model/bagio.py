"""Read and write DVT recordings: rosbag2 directories (MCAP storage, CDR, ROS 2 Jazzy types).

The contract (``INTERFACE.md``): a recording holds at least ``/dvt/joint_states`` (measured
speeds [rad/s] of ``("sun_shaft", "carrier3")`` in ``velocity``) and ``/dvt/currents`` (winding
currents [A] of ``("drive_motor", "brake1", "brake2", "brake3")`` in ``effort``), both
``sensor_msgs/msg/JointState``. The two messages of one controller sample carry the identical
``header.stamp``; stamps strictly increase. Unknown extra topics are ignored.

Pure module: uses ``rosbags`` (no rclpy). Every problem raises :class:`~dvt_model.errors.BagError`
naming the bag path, the topic and the field.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from dvt_model.errors import BagError

JOINT_STATES_TOPIC = "/dvt/joint_states"
CURRENTS_TOPIC = "/dvt/currents"
MODEL_JOINT_STATES_TOPIC = "/dvt/model/joint_states"
MODEL_RESIDUAL_TOPIC = "/dvt/model/residual"
DIAGNOSTICS_TOPIC = "/diagnostics"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
SPEED_NAMES: tuple[str, ...] = ("sun_shaft", "carrier3")
CURRENT_NAMES: tuple[str, ...] = ("drive_motor", "brake1", "brake2", "brake3")
TRUTH_FILE = "truth.yaml"
RECOVER_HINT = "dvt-bag recover"

#: One stream for :func:`write_bag`: (topic, msgtype, [(log_time_ns, message), ...]); a message
#: is either raw CDR bytes or a ``rosbags`` message object of ``msgtype``.
Stream = tuple[str, str, Sequence[tuple[int, Any]]]

Float2D = NDArray[np.float64]
Int1D = NDArray[np.int64]


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy type store shared by readers and writers."""
    return get_typestore(Stores.ROS2_JAZZY)


def _split_stamp(stamp_ns: int) -> tuple[int, int]:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return sec, nanosec


def joint_state(stamp_ns: int, names: Sequence[str], *, position: ArrayLike | None = None,
                velocity: ArrayLike | None = None, effort: ArrayLike | None = None) -> Any:
    """A ``sensor_msgs/msg/JointState`` (rosbags object) with ``header.stamp = stamp_ns`` [ns].

    ``position``, ``velocity``, ``effort``: 1-D arrays (any length, empty when ``None``).
    """
    ts = typestore()
    sec, nanosec = _split_stamp(stamp_ns)
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="")

    def arr(x: ArrayLike | None) -> NDArray[np.float64]:
        return np.zeros(0) if x is None else np.asarray(x, dtype=np.float64).reshape(-1)

    return ts.types[JOINT_STATE_TYPE](header=header, name=list(names), position=arr(position),
                                      velocity=arr(velocity), effort=arr(effort))


def joint_state_cdr(stamp_ns: int, names: Sequence[str], *, position: ArrayLike | None = None,
                    velocity: ArrayLike | None = None, effort: ArrayLike | None = None) -> bytes:
    """CDR bytes (little endian, as ROS 2 publishes it) of :func:`joint_state`.

    Encoded directly (about 10x faster than building and serialising the rosbags object);
    the layout is checked against ``rosbags`` in the tests.
    """
    sec, nanosec = _split_stamp(stamp_ns)
    if not -(2**31) <= sec < 2**31:
        raise BagError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 s)")
    out = bytearray(_CDR_LE)
    out += _PACK_STAMP(sec, nanosec)
    out += b"\x01\x00\x00\x00\x00\x00\x00\x00"  # frame_id "" (+ padding to 4)
    out += _PACK_U32(len(names))
    for name in names:
        data = name.encode() + b"\x00"
        out += _PACK_U32(len(data))
        out += data
        out += b"\x00" * (-len(data) % 4)
    for values in (position, velocity, effort):
        arr = (np.zeros(0) if values is None
               else np.ascontiguousarray(values, dtype="<f8").reshape(-1))
        out += _PACK_U32(arr.shape[0])
        if arr.shape[0]:
            out += b"\x00" * (-(len(out) - 4) % 8)
            out += arr.tobytes()
    return bytes(out)


_CDR_LE = b"\x00\x01\x00\x00"
_PACK_STAMP = struct.Struct("<iI").pack
_PACK_U32 = struct.Struct("<I").pack
_UNPACK_U32 = struct.Struct("<I").unpack_from
_UNPACK_STAMP = struct.Struct("<iI").unpack_from


class _JointStateFields(NamedTuple):
    stamp_ns: int
    names: tuple[str, ...]
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    effort: tuple[float, ...]


def _parse_joint_state(raw: bytes | memoryview) -> _JointStateFields:
    """Decode little-endian CDR of a JointState (fast path; any doubt falls back to rosbags)."""
    buf = bytes(raw)
    try:
        if buf[:2] != _CDR_LE[:2]:
            raise ValueError("not little-endian CDR")
        sec, nanosec = _UNPACK_STAMP(buf, 4)
        pos = 12
        (n,) = _UNPACK_U32(buf, pos)  # frame_id
        pos += 4 + n
        pos += -(pos - 4) % 4
        (count,) = _UNPACK_U32(buf, pos)
        pos += 4
        names: list[str] = []
        for _ in range(count):
            pos += -(pos - 4) % 4
            (n,) = _UNPACK_U32(buf, pos)
            if n < 1 or pos + 4 + n > len(buf):
                raise ValueError("bad string")
            names.append(buf[pos + 4:pos + 3 + n].decode())
            pos += 4 + n
        arrays: list[tuple[float, ...]] = []
        for _ in range(3):
            pos += -(pos - 4) % 4
            (count,) = _UNPACK_U32(buf, pos)
            pos += 4
            if count:
                pos += -(pos - 4) % 8
                if pos + 8 * count > len(buf):
                    raise ValueError("truncated array")
                arrays.append(struct.unpack_from(f"<{count}d", buf, pos))
                pos += 8 * count
            else:
                arrays.append(())
        return _JointStateFields(sec * 1_000_000_000 + nanosec, tuple(names), *arrays)
    except (ValueError, struct.error, UnicodeDecodeError):
        msg: Any = typestore().deserialize_cdr(buf, JOINT_STATE_TYPE)
        return _JointStateFields(_stamp_ns(msg), tuple(msg.name),
                                 tuple(float(x) for x in msg.position),
                                 tuple(float(x) for x in msg.velocity),
                                 tuple(float(x) for x in msg.effort))


def write_bag(path: str | Path, streams: Iterable[Stream]) -> Path:
    """Write a rosbag2 directory (MCAP, CDR, Jazzy types) holding ``streams``.

    Messages of all streams are written in log-time order (ties keep stream order).
    Raises :class:`BagError` if ``path`` exists or a message cannot be serialised.
    """
    path = Path(path)
    ts = typestore()
    entries: list[tuple[int, int, int, Any]] = []
    topics: list[tuple[str, str]] = []
    for k, (topic, msgtype, messages) in enumerate(streams):
        if msgtype not in ts.types:
            raise BagError(f"{path}: topic {topic}: unknown message type {msgtype!r}")
        topics.append((topic, msgtype))
        entries.extend((int(t), k, i, m) for i, (t, m) in enumerate(messages))
    entries.sort(key=lambda e: (e[0], e[1], e[2]))
    try:
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns = [writer.add_connection(topic, msgtype, typestore=ts)
                     for topic, msgtype in topics]
            for log_time, k, i, msg in entries:
                if isinstance(msg, bytes | bytearray | memoryview):
                    raw = bytes(msg)
                else:
                    try:
                        raw = bytes(ts.serialize_cdr(msg, topics[k][1]))
                    except Exception as exc:
                        raise BagError(f"{path}: topic {topics[k][0]}: message {i} cannot be "
                                       f"serialised as {topics[k][1]}: {exc}") from exc
                writer.write(conns[k], log_time, raw)
    except WriterError as exc:
        raise BagError(f"{path}: cannot write bag: {exc}") from exc
    return path


def _check_shape(name: str, a: NDArray[Any], shape: tuple[int, ...]) -> None:
    if a.shape != shape:
        raise BagError(f"{name}: expected shape {shape}, got {a.shape}")


def write_run(path: str | Path, stamps_ns: ArrayLike, speeds: ArrayLike, currents: ArrayLike,
              *, model_speeds: ArrayLike | None = None, residuals: ArrayLike | None = None,
              extra: Iterable[Stream] | None = None,
              truth: Mapping[str, Any] | None = None) -> Path:
    """Write one recording in the contract format; returns the bag directory.

    Args:
        path: bag directory to create (must not exist).
        stamps_ns: (N,) sample stamps [ns]; used as ``header.stamp`` and as log time.
        speeds: (N, 2) measured speeds [rad/s] of ``SPEED_NAMES`` -> ``/dvt/joint_states``.
        currents: (N, 4) winding currents [A] of ``CURRENT_NAMES`` -> ``/dvt/currents``.
        model_speeds: optional (N, 2) predicted speeds [rad/s] -> ``/dvt/model/joint_states``.
        residuals: optional (N, 2) measured minus predicted [rad/s] -> ``/dvt/model/residual``.
        extra: further streams ``(topic, msgtype, [(log_time_ns, msg or raw CDR), ...])``.
        truth: if given, written as ``truth.yaml`` inside the bag directory (simulation only).

    Values are written as given (no finiteness or order check) so that tests can build bad bags.
    """
    stamps = np.asarray(stamps_ns)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise BagError(f"stamps_ns: expected an integer array of shape (N,), got "
                       f"{stamps.dtype} array of shape {stamps.shape}")
    n = stamps.shape[0]
    spd = np.asarray(speeds, dtype=np.float64)
    cur = np.asarray(currents, dtype=np.float64)
    _check_shape("speeds", spd, (n, len(SPEED_NAMES)))
    _check_shape("currents", cur, (n, len(CURRENT_NAMES)))
    stamp_list = [int(s) for s in stamps]
    streams: list[Stream] = [
        (JOINT_STATES_TOPIC, JOINT_STATE_TYPE,
         [(s, joint_state_cdr(s, SPEED_NAMES, velocity=spd[i]))
          for i, s in enumerate(stamp_list)]),
        (CURRENTS_TOPIC, JOINT_STATE_TYPE,
         [(s, joint_state_cdr(s, CURRENT_NAMES, effort=cur[i]))
          for i, s in enumerate(stamp_list)]),
    ]
    for name, topic, values in (("model_speeds", MODEL_JOINT_STATES_TOPIC, model_speeds),
                                ("residuals", MODEL_RESIDUAL_TOPIC, residuals)):
        if values is None:
            continue
        v = np.asarray(values, dtype=np.float64)
        _check_shape(name, v, (n, len(SPEED_NAMES)))
        streams.append((topic, JOINT_STATE_TYPE,
                        [(s, joint_state_cdr(s, SPEED_NAMES, velocity=v[i]))
                         for i, s in enumerate(stamp_list)]))
    streams.extend(extra or ())
    out = write_bag(path, streams)
    if truth is not None:
        (out / TRUTH_FILE).write_text(yaml.safe_dump(dict(truth), sort_keys=False))
    return out


def read_truth(path: str | Path) -> dict[str, Any] | None:
    """The sidecar ``truth.yaml`` of a simulated recording, or ``None`` if there is none."""
    f = Path(path) / TRUTH_FILE
    if not f.exists():
        return None
    try:
        data = yaml.safe_load(f.read_text())
    except yaml.YAMLError as exc:
        raise BagError(f"{f}: invalid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise BagError(f"{f}: expected a mapping at top level, got {type(data).__name__}")
    return data


class TopicSeries(NamedTuple):
    """All messages of one JointState topic, in recorded order.

    ``stamps_ns`` (N,) int64 header stamps [ns]; ``names`` joint names (identical in every
    message); ``velocity`` (N, k) and ``effort`` (N, m) with k, m in {0, len(names)}.
    """

    stamps_ns: Int1D
    names: tuple[str, ...]
    velocity: Float2D
    effort: Float2D


@dataclass(frozen=True)
class Run:
    """One recording aligned by stamp.

    ``stamps_ns`` (N,) int64 sample stamps [ns]; ``t`` (N,) seconds since the first stamp;
    ``speeds`` (N, 2) [rad/s] of ``SPEED_NAMES``; ``currents`` (N, 4) [A] of ``CURRENT_NAMES``;
    ``topics`` every topic present in the bag; ``unmatched`` samples dropped because their stamp
    was present in only one of the two topics (``unmatched_by_topic`` per topic).
    """

    path: Path
    stamps_ns: Int1D
    t: NDArray[np.float64]
    speeds: Float2D
    currents: Float2D
    topics: tuple[str, ...]
    unmatched: int = 0
    unmatched_by_topic: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of aligned samples."""
        return int(self.stamps_ns.shape[0])

    @property
    def duration(self) -> float:
        """Last minus first stamp [s]."""
        return float(self.t[-1]) if self.n else 0.0


def _open_reader(path: Path) -> Reader:
    if not path.exists():
        raise BagError(f"{path}: no such bag directory")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        hint = ""
        if any(path.glob("*.mcap")):
            hint = (f" (the recording was probably killed; run `{RECOVER_HINT} {path}` "
                    "to rebuild a readable bag)")
        raise BagError(f"{path}: not a readable bag: metadata.yaml is missing{hint}")
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, OSError) as exc:
        raise BagError(f"{path}: cannot open bag: {exc} (if the recording was killed, try "
                       f"`{RECOVER_HINT} {path}`)") from exc
    return reader


def _stamp_ns(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def _read_series(reader: Reader, path: Path, topic: str) -> TopicSeries:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        present = sorted({c.topic for c in reader.connections})
        raise BagError(f"{path}: topic {topic} missing (topics present: {present})")
    for c in conns:
        if c.msgtype != JOINT_STATE_TYPE:
            raise BagError(f"{path}: topic {topic}: type is {c.msgtype}, expected "
                           f"{JOINT_STATE_TYPE}")
    stamps: list[int] = []
    vel: list[tuple[float, ...]] = []
    eff: list[tuple[float, ...]] = []
    names: tuple[str, ...] | None = None
    try:
        for i, (_, _, raw) in enumerate(reader.messages(connections=conns)):
            try:
                msg = _parse_joint_state(raw)
            except Exception as exc:
                raise BagError(f"{path}: topic {topic}: message {i} is not a valid "
                               f"{JOINT_STATE_TYPE}: {exc}") from exc
            msg_names = msg.names
            if names is None:
                names = msg_names
            elif msg_names != names:
                raise BagError(f"{path}: topic {topic}: field 'name' of message {i} is "
                               f"{list(msg_names)}, message 0 has {list(names)}")
            stamps.append(msg.stamp_ns)
            vel.append(msg.velocity)
            eff.append(msg.effort)
    except ReaderError as exc:
        raise BagError(f"{path}: topic {topic}: cannot read messages: {exc}") from exc
    if names is None:
        raise BagError(f"{path}: topic {topic} has no messages")
    return TopicSeries(np.asarray(stamps, dtype=np.int64), names,
                       _stack(path, topic, "velocity", vel, len(names)),
                       _stack(path, topic, "effort", eff, len(names)))


def _stack(path: Path, topic: str, fname: str, rows: list[tuple[float, ...]],
           width: int) -> Float2D:
    lengths = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    k = int(lengths[0])
    if k not in (0, width):
        raise BagError(f"{path}: topic {topic}: field '{fname}' of message 0 has {k} values, "
                       f"expected 0 or {width} (one per name)")
    bad = np.flatnonzero(lengths != k)
    if bad.size:
        i = int(bad[0])
        raise BagError(f"{path}: topic {topic}: field '{fname}' of message {i} has "
                       f"{int(lengths[i])} values, message 0 has {k}")
    if k == 0:
        return np.zeros((len(rows), 0))
    return np.array(rows, dtype=np.float64)


def read_topic_series(path: str | Path, topic: str) -> TopicSeries:
    """Read every message of a ``sensor_msgs/msg/JointState`` topic, in recorded order.

    Returns ``(stamps_ns, names, velocity, effort)`` (see :class:`TopicSeries`). No value
    checks beyond consistent names and array lengths.
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        return _read_series(reader, path, topic)
    finally:
        reader.close()


def _validate(path: Path, topic: str, series: TopicSeries, expected: tuple[str, ...],
              fname: str) -> Float2D:
    """Check names, the required field and stamps of one contract topic; return the field."""
    if series.names != expected:
        raise BagError(f"{path}: topic {topic}: field 'name' is {list(series.names)}, "
                       f"expected {list(expected)}")
    values = series.velocity if fname == "velocity" else series.effort
    if values.shape[1] != len(expected):
        raise BagError(f"{path}: topic {topic}: field '{fname}' is empty, expected "
                       f"{len(expected)} values per message")
    finite = np.isfinite(values)
    if not finite.all():
        i, j = (int(x) for x in np.argwhere(~finite)[0])
        raise BagError(f"{path}: topic {topic}: field '{fname}' is not finite at message {i} "
                       f"(stamp {int(series.stamps_ns[i])} ns, {expected[j]}): {values[i, j]}")
    d = np.diff(series.stamps_ns)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise BagError(f"{path}: topic {topic}: field 'header.stamp' does not strictly "
                       f"increase at message {i}: {int(series.stamps_ns[i])} ns after "
                       f"{int(series.stamps_ns[i - 1])} ns")
    return values


def read_run(path: str | Path) -> Run:
    """Read a contract recording and align ``/dvt/joint_states`` with ``/dvt/currents``.

    Samples are matched by identical ``header.stamp``; a stamp present in only one topic is
    dropped and counted in ``Run.unmatched``. Other topics are ignored.
    Raises :class:`BagError` (naming bag, topic, field) for an unreadable bag, a missing
    topic, wrong names, wrong array lengths, non-finite values or non-increasing stamps.
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        topics = tuple(sorted({c.topic for c in reader.connections}))
        js = _read_series(reader, path, JOINT_STATES_TOPIC)
        cu = _read_series(reader, path, CURRENTS_TOPIC)
    finally:
        reader.close()
    speeds = _validate(path, JOINT_STATES_TOPIC, js, SPEED_NAMES, "velocity")
    currents = _validate(path, CURRENTS_TOPIC, cu, CURRENT_NAMES, "effort")
    common, ia, ib = np.intersect1d(js.stamps_ns, cu.stamps_ns, assume_unique=True,
                                    return_indices=True)
    if common.size == 0:
        raise BagError(f"{path}: topics {JOINT_STATES_TOPIC} and {CURRENTS_TOPIC} share no "
                       "header.stamp; the contract requires both messages of a sample to carry "
                       "the identical stamp")
    by_topic = {JOINT_STATES_TOPIC: int(js.stamps_ns.size - common.size),
                CURRENTS_TOPIC: int(cu.stamps_ns.size - common.size)}
    stamps = common.astype(np.int64)
    t = (stamps - stamps[0]).astype(np.float64) * 1e-9
    return Run(path=path, stamps_ns=stamps, t=t, speeds=speeds[ia], currents=currents[ib],
               topics=topics, unmatched=sum(by_topic.values()), unmatched_by_topic=by_topic)


def sample_period(run: Run) -> float:
    """Median sample period [s] of ``run`` (``nan`` for fewer than two samples)."""
    if run.n < 2:
        return math.nan
    return float(np.median(np.diff(run.stamps_ns))) * 1e-9
