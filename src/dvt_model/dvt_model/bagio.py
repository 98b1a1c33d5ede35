"""Read and write DVT recordings: rosbag2 directories (MCAP storage, CDR, ROS 2 Jazzy types).

The contract (``INTERFACE.md``): a recording holds at least ``/dvt/joint_states`` (measured
speeds [rad/s] of ``("sun_shaft", "carrier3")`` in ``velocity``) and ``/dvt/currents`` (winding
currents [A] of ``("drive_motor", "brake1", "brake2", "brake3")`` in ``effort``), both
``sensor_msgs/msg/JointState``. The two messages of one controller sample carry the identical
``header.stamp``; stamps strictly increase. Unknown extra topics are ignored.

Pure module: uses ``rosbags`` (no rclpy). Every problem raises :class:`~dvt_model.errors.BagError`
naming the bag path, the topic and the field.

Reading (:func:`read_topics`) is one pass over the bag for all wanted topics: an indexed MCAP file
is read through its summary and message indexes (numpy, no per-message loop; rosbags' chunk
decompression and checksum check), any other storage or anything unexpected through the rosbags
message iterator. Each topic is then decoded in bulk: messages with the byte layout of the
topic's first message (same length, same bytes apart from the stamp and the float arrays) are
sliced with numpy, the others decoded one by one with the same checks and errors.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

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


class _CdrLayout(NamedTuple):
    """Where the parts of one little-endian CDR JointState lie (byte offsets into the message).

    ``arrays``: ``(offset, count)`` of ``position``, ``velocity`` and ``effort`` (float64).
    The stamp is always at bytes 4..12 (int32 sec, uint32 nanosec).
    """

    names: tuple[str, ...]
    arrays: tuple[tuple[int, int], ...]


def _cdr_layout(buf: bytes) -> _CdrLayout:
    """Layout of little-endian CDR ``buf``; raises ValueError/struct.error/UnicodeDecodeError."""
    if buf[:2] != _CDR_LE[:2]:
        raise ValueError("not little-endian CDR")
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
    arrays: list[tuple[int, int]] = []
    for _ in range(3):
        pos += -(pos - 4) % 4
        (count,) = _UNPACK_U32(buf, pos)
        pos += 4
        if count:
            pos += -(pos - 4) % 8
            if pos + 8 * count > len(buf):
                raise ValueError("truncated array")
        arrays.append((pos, count))
        pos += 8 * count
    return _CdrLayout(tuple(names), tuple(arrays))


def _parse_joint_state(raw: bytes | memoryview) -> _JointStateFields:
    """Decode CDR of a JointState (fast path for little endian; any doubt falls back to rosbags)."""
    buf = bytes(raw)
    try:
        lay = _cdr_layout(buf)
        sec, nanosec = _UNPACK_STAMP(buf, 4)
        pos, vel, eff = (struct.unpack_from(f"<{c}d", buf, o) if c else ()
                         for o, c in lay.arrays)
        return _JointStateFields(sec * 1_000_000_000 + nanosec, lay.names, pos, vel, eff)
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
    message); ``velocity`` (N, k), ``effort`` (N, m) and ``position`` (N, p) with k, m, p in
    {0, len(names)}.
    """

    stamps_ns: Int1D
    names: tuple[str, ...]
    velocity: Float2D
    effort: Float2D
    position: Float2D


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


# --------------------------------------------------------------------------------------------
# Reading: one pass over the bag collects the raw CDR of every wanted topic, then each topic is
# decoded in bulk (numpy on the stacked bytes); messages that do not share the layout of the
# topic's first message are decoded one by one (same checks, same errors).


class _RawMessages(NamedTuple):
    """Raw CDR messages of one topic in recorded order.

    Message ``i`` is ``buf[starts[i]:starts[i] + lengths[i]]``; ``buf`` (B,) uint8, ``starts``
    and ``lengths`` (N,) int64.
    """

    buf: NDArray[np.uint8]
    starts: Int1D
    lengths: Int1D


def _raw_from_list(raws: Sequence[bytes]) -> _RawMessages:
    lengths = np.fromiter(map(len, raws), dtype=np.int64, count=len(raws))
    starts = np.zeros_like(lengths)
    np.cumsum(lengths[:-1], out=starts[1:])
    return _RawMessages(np.frombuffer(b"".join(raws), dtype=np.uint8), starts, lengths)


def _rows(buf: NDArray[np.uint8], starts: Int1D, width: int) -> NDArray[np.uint8]:
    """(len(starts), width) copy of the bytes ``buf[s:s + width]`` for every ``s`` in ``starts``."""
    if starts.size == 0:
        return np.zeros((0, width), dtype=np.uint8)
    windows = np.lib.stride_tricks.sliding_window_view(buf, width)
    return np.asarray(windows[starts])


def _as(rows: NDArray[np.uint8], dtype: str) -> NDArray[Any]:
    """Reinterpret each row of ``rows`` (n, k * itemsize) bytes as k values of ``dtype``."""
    return np.ascontiguousarray(rows).view(dtype)


class _McapFastPathError(Exception):
    """The MCAP fast path does not apply (no summary or index, odd record); rosbags reads."""


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_UNPACK_Q = struct.Struct("<Q").unpack_from
_UNPACK_H = struct.Struct("<H").unpack_from


class _McapChunk(NamedTuple):
    start: int  # file offset of the chunk record
    length: int  # chunk record length (with opcode and length prefix)
    index_offsets: dict[int, int]  # channel id -> file offset of its message index record
    index_length: int  # bytes of message index records after the chunk


class _McapSummary(NamedTuple):
    topics: dict[int, str]  # channel id -> topic
    chunks: list[_McapChunk]
    counts: dict[int, int]  # channel id -> message count (statistics record)


def _mcap_string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = _UNPACK_U32(buf, pos)
    return buf[pos + 4:pos + 4 + n].decode(), pos + 4 + n


def _mcap_summary(fh: BinaryIO) -> _McapSummary:
    """Channels, chunk indexes and message counts from the summary section of an MCAP file."""
    size = fh.seek(0, 2)
    if size < 45:
        raise _McapFastPathError("file too short")
    fh.seek(size - 37)
    tail = fh.read(37)
    if tail[-8:] != _MCAP_MAGIC or tail[0] != 0x02:
        raise _McapFastPathError("no footer")
    summary_start, offsets_start = struct.unpack_from("<QQ", tail, 9)
    if summary_start == 0:
        raise _McapFastPathError("no summary")
    end = offsets_start or size - 37
    fh.seek(summary_start)
    blob = fh.read(end - summary_start)
    topics: dict[int, str] = {}
    chunks: list[_McapChunk] = []
    counts: dict[int, int] | None = None
    pos = 0
    while pos < len(blob):
        op = blob[pos]
        (n,) = _UNPACK_Q(blob, pos + 1)
        body = pos + 9
        pos = body + n
        if op == 0x04:  # channel: id, schema id, topic, ...
            (cid,) = _UNPACK_H(blob, body)
            topics[cid], _ = _mcap_string(blob, body + 4)
        elif op == 0x08:  # chunk index
            start, length = struct.unpack_from("<QQ", blob, body + 16)
            (maplen,) = _UNPACK_U32(blob, body + 32)
            idx = dict(struct.iter_unpack("<HQ", blob[body + 36:body + 36 + maplen]))
            (index_length,) = _UNPACK_Q(blob, body + 36 + maplen)
            chunks.append(_McapChunk(start, length, idx, index_length))
        elif op == 0x0B:  # statistics: ..., channel message counts
            (maplen,) = _UNPACK_U32(blob, body + 42)
            counts = dict(struct.iter_unpack("<HQ", blob[body + 46:body + 46 + maplen]))
    if counts is None or not chunks:
        raise _McapFastPathError("no statistics or no chunk index")
    return _McapSummary(topics, chunks, counts)


def _mcap_collect(files: Sequence[Path], topics: Sequence[str]) -> dict[str, _RawMessages]:
    """Raw messages of ``topics`` from indexed MCAP ``files`` without a per-message loop.

    Uses the summary (chunk indexes, statistics) and each chunk's message index; every record
    found is checked (opcode, channel, bounds) and the counts must equal the statistics, else
    :class:`_McapFastPathError` is raised and the caller reads with rosbags instead.
    """
    from rosbags.rosbag2.storage_mcap import decompress

    pieces: list[NDArray[np.uint8]] = []
    base = 0
    found: dict[str, list[tuple[Int1D, Int1D, Int1D]]] = {t: [] for t in topics}
    for f in files:
        with f.open("rb") as fh:
            summary = _mcap_summary(fh)
            wanted = {cid: t for cid, t in summary.topics.items() if t in found}
            seen = dict.fromkeys(wanted, 0)
            for chunk in summary.chunks:
                ids = [cid for cid in chunk.index_offsets if cid in wanted]
                if not ids:
                    continue
                fh.seek(chunk.start)
                blob = fh.read(chunk.length + chunk.index_length)
                if len(blob) != chunk.length + chunk.index_length or blob[0] != 0x06:
                    raise _McapFastPathError("bad chunk record")
                usize, crc, clen = struct.unpack_from("<QII", blob, 25)
                compression = blob[41:41 + clen].decode()
                (rlen,) = _UNPACK_Q(blob, 41 + clen)
                rstart = 49 + clen
                if rstart + rlen > chunk.length:
                    raise _McapFastPathError("chunk records exceed the chunk")
                data = blob[rstart:rstart + rlen]
                try:
                    records = np.frombuffer(decompress(data, compression, usize, crc),
                                            dtype=np.uint8)
                except ReaderError as exc:
                    raise _McapFastPathError(str(exc)) from exc
                for cid in ids:
                    ipos = chunk.index_offsets[cid] - chunk.start
                    if not 0 <= ipos <= len(blob) - 15 or blob[ipos] != 0x07 or \
                            _UNPACK_H(blob, ipos + 9)[0] != cid:
                        raise _McapFastPathError("bad message index")
                    (ilen,) = _UNPACK_U32(blob, ipos + 11)
                    if ilen % 16 or ipos + 15 + ilen > len(blob):
                        raise _McapFastPathError("bad message index length")
                    entries = np.frombuffer(blob, dtype="<u8", count=ilen // 8,
                                            offset=ipos + 15).reshape(-1, 2)
                    offs = entries[:, 1].astype(np.int64)
                    if offs.size and (offs.min() < 0 or offs.max() + 31 > records.size):
                        raise _McapFastPathError("message index offset out of range")
                    head = _rows(records, offs, 31)  # opcode, length, channel, seq, times
                    reclen = _as(head[:, 1:9], "<u8")[:, 0].astype(np.int64)
                    if (np.any(head[:, 0] != 0x05) or np.any(_as(head[:, 9:11], "<u2") != cid)
                            or np.any(reclen < 22) or np.any(offs + 9 + reclen > records.size)):
                        raise _McapFastPathError("message index does not point at messages")
                    log_time = _as(head[:, 15:23], "<u8")[:, 0].astype(np.int64)
                    found[wanted[cid]].append((log_time, base + offs + 31, reclen - 22))
                    seen[cid] += offs.size
                pieces.append(records)
                base += records.size
            if any(seen[cid] != summary.counts.get(cid, 0) for cid in wanted):
                raise _McapFastPathError("message indexes disagree with the statistics")
    buf = np.concatenate(pieces) if pieces else np.zeros(0, dtype=np.uint8)
    out: dict[str, _RawMessages] = {}
    for topic, parts in found.items():
        if not parts:
            out[topic] = _RawMessages(buf, np.zeros(0, np.int64), np.zeros(0, np.int64))
            continue
        log_time, starts, lengths = (np.concatenate(x) for x in zip(*parts, strict=True))
        order = np.lexsort((starts, log_time))  # log time, ties in file order (as rosbags)
        out[topic] = _RawMessages(buf, starts[order], lengths[order])
    return out


def _mcap_files(path: Path) -> list[Path] | None:
    """The MCAP files of a bag directory (``None``: other storage, or compressed files)."""
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        if meta.get("storage_identifier") != "mcap" or \
                str(meta.get("compression_mode") or "").lower() not in ("", "none"):
            return None
        return [path / Path(str(x)).name for x in meta["relative_file_paths"]]
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return None


def _collect(reader: Reader, path: Path, topics: Sequence[str]) -> dict[str, _RawMessages]:
    """Check that ``topics`` are JointState topics of the bag; return their raw messages."""
    conns = [c for c in reader.connections if c.topic in topics]
    for topic in topics:
        mine = [c for c in conns if c.topic == topic]
        if not mine:
            listed = sorted({c.topic for c in reader.connections})
            raise BagError(f"{path}: topic {topic} missing (topics present: {listed})")
        for c in mine:
            if c.msgtype != JOINT_STATE_TYPE:
                raise BagError(f"{path}: topic {topic}: type is {c.msgtype}, expected "
                               f"{JOINT_STATE_TYPE}")
    files = _mcap_files(path)
    if files is not None:
        try:
            return _mcap_collect(files, topics)
        except (_McapFastPathError, OSError, ValueError, struct.error, UnicodeDecodeError):
            pass  # rosbags reads it (and reports what is wrong with it)
    raws: dict[str, list[bytes]] = {t: [] for t in topics}
    try:
        for conn, _, raw in reader.messages(connections=conns):
            raws[conn.topic].append(raw)
    except Exception as exc:  # ReaderError, or a decompressor's error on corrupt storage
        which = ", ".join(topics)
        raise BagError(f"{path}: topic{'s' if len(topics) > 1 else ''} {which}: cannot read "
                       f"messages: {exc}") from exc
    return {t: _raw_from_list(r) for t, r in raws.items()}


def _message(raw: _RawMessages, i: int) -> bytes:
    s = int(raw.starts[i])
    return raw.buf[s:s + int(raw.lengths[i])].tobytes()


def _parse_at(path: Path, topic: str, raw: _RawMessages, i: int) -> _JointStateFields:
    try:
        return _parse_joint_state(_message(raw, i))
    except Exception as exc:
        raise BagError(f"{path}: topic {topic}: message {i} is not a valid "
                       f"{JOINT_STATE_TYPE}: {exc}") from exc


_SERIES_FIELDS = ("velocity", "effort", "position")  # order of the length checks


def _decode(path: Path, topic: str, raw: _RawMessages) -> TopicSeries:
    """Decode the JointState messages of ``topic``.

    Messages with the byte length of message 0 and the same bytes outside the stamp and the
    float arrays (same frame_id, names, array lengths) are decoded in bulk; every other message
    by :func:`_parse_joint_state`. Raises :class:`BagError` naming the message index and field
    for an undecodable message, changing names or a wrong array length.
    """
    n = int(raw.lengths.size)
    if n == 0:
        raise BagError(f"{path}: topic {topic} has no messages")
    first = _message(raw, 0)
    msg0 = _parse_at(path, topic, raw, 0)
    names = msg0.names
    width = {"position": len(msg0.position), "velocity": len(msg0.velocity),
             "effort": len(msg0.effort)}
    stamps = np.empty(n, dtype=np.int64)
    values = {f: np.empty((n, k)) for f, k in width.items()}
    bulk = np.zeros(n, dtype=bool)
    try:
        layout: _CdrLayout | None = _cdr_layout(first)
    except (ValueError, struct.error, UnicodeDecodeError):
        layout = None  # message 0 needs rosbags: decode every message singly
    if layout is not None:
        size = len(first)
        cand = np.flatnonzero(raw.lengths == size)
        rows = _rows(raw.buf, raw.starts[cand], size)
        fixed = np.ones(size, dtype=bool)
        fixed[4:12] = False
        for off, count in layout.arrays:
            fixed[off:off + 8 * count] = False
        same = ~np.any((rows != np.frombuffer(first, dtype=np.uint8)) & fixed, axis=1)
        cand, rows = cand[same], rows[same]
        bulk[cand] = True
        stamps[cand] = (_as(rows[:, 4:8], "<i4")[:, 0].astype(np.int64) * 1_000_000_000
                        + _as(rows[:, 8:12], "<u4")[:, 0])
        for fname, (off, count) in zip(("position", "velocity", "effort"), layout.arrays,
                                       strict=True):
            if count:
                values[fname][cand] = _as(rows[:, off:off + 8 * count], "<f8")
    lengths = {f: np.full(n, k, dtype=np.int64) for f, k in width.items()}
    for i in np.flatnonzero(~bulk).tolist():
        msg = _parse_at(path, topic, raw, i)
        if msg.names != names:
            raise BagError(f"{path}: topic {topic}: field 'name' of message {i} is "
                           f"{list(msg.names)}, message 0 has {list(names)}")
        stamps[i] = msg.stamp_ns
        for fname in width:
            row = getattr(msg, fname)
            lengths[fname][i] = len(row)
            if len(row) == width[fname]:
                values[fname][i] = row
    for fname in _SERIES_FIELDS:
        k = width[fname]
        if k not in (0, len(names)):
            raise BagError(f"{path}: topic {topic}: field '{fname}' of message 0 has {k} "
                           f"values, expected 0 or {len(names)} (one per name)")
        bad = np.flatnonzero(lengths[fname] != k)
        if bad.size:
            i = int(bad[0])
            raise BagError(f"{path}: topic {topic}: field '{fname}' of message {i} has "
                           f"{int(lengths[fname][i])} values, message 0 has {k}")
    return TopicSeries(stamps, names, values["velocity"], values["effort"], values["position"])


def read_topics(path: str | Path, topics: Sequence[str]) -> dict[str, TopicSeries]:
    """Read every message of several ``sensor_msgs/msg/JointState`` topics in one pass.

    Returns topic -> :class:`TopicSeries` (recorded order). Other topics are ignored. No value
    checks beyond consistent names and array lengths. Raises :class:`BagError` naming the bag,
    topic, message index and field (unreadable bag, missing topic, wrong type, no messages,
    undecodable message, changing names or array lengths).
    """
    path = Path(path)
    topics = list(dict.fromkeys(topics))
    reader = _open_reader(path)
    try:
        raws = _collect(reader, path, topics)
    finally:
        reader.close()
    return {t: _decode(path, t, raws[t]) for t in topics}


def read_topic_series(path: str | Path, topic: str) -> TopicSeries:
    """Read every message of a ``sensor_msgs/msg/JointState`` topic, in recorded order.

    Returns ``(stamps_ns, names, velocity, effort, position)`` (see :class:`TopicSeries`). No
    value checks beyond consistent names and array lengths.
    """
    return read_topics(path, [topic])[topic]


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
        raws = _collect(reader, path, [JOINT_STATES_TOPIC, CURRENTS_TOPIC])
    finally:
        reader.close()
    js = _decode(path, JOINT_STATES_TOPIC, raws[JOINT_STATES_TOPIC])
    cu = _decode(path, CURRENTS_TOPIC, raws[CURRENTS_TOPIC])
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
