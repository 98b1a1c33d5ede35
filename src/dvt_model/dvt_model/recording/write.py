"""The one writer of recordings: crash-safe rosbag2/MCAP bags of raw CDR messages (pure).

:class:`BagRecorder` is what ``dvt-recorder`` writes live with; :func:`write_bag`,
:func:`write_run` and :func:`write_topics` are thin offline wrappers over it (tests, demos,
simulation, importers). Every bag is a rosbag2 directory that ``rosbags``' ``Reader``, the
``mcap`` readers and :mod:`~dvt_model.recording.read` open.

Durability design
-----------------
``rosbags``' ``Writer`` keeps up to 1 MiB of messages in an in-memory chunk and writes
``metadata.yaml`` only on a clean close, with no way to flush on time. :class:`BagRecorder`
therefore writes the MCAP file with the ``mcap`` library's ``Writer`` and the exact rosbag2
conventions (profile ``ros2``, schema encoding ``ros2msg``, message encoding ``cdr``, channel
metadata ``offered_qos_profiles``, a ``rosbag2`` metadata record) and

* closes the chunk in progress, flushes and (by default) ``fsync``\\ s the file at least every
  ``flush_period`` seconds (0.5 s): a killed recorder loses at most the messages received in
  the last ``flush_period`` (plus the time between two calls of :meth:`BagRecorder.poll`);
* writes ``metadata.yaml`` (rosbag2 version 9, as ``rosbags`` writes it) atomically on close,
  so ``rosbags``' ``Reader`` and ``mcap``'s readers open the result.

A recording that was killed has no ``metadata.yaml`` and an MCAP file without summary/footer;
:func:`~dvt_model.recording.recover.recover` (``dvt-bag recover PATH``) rebuilds it.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from numpy.typing import ArrayLike, NDArray

from dvt_model.contract import (
    CURRENT_NAMES,
    CURRENTS,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    MODEL_RESIDUAL,
    SPEED_NAMES,
)
from dvt_model.errors import BagError, RecordingError
from dvt_model.recording.cdr import joint_state_cdr, message_definition, typestore
from dvt_model.recording.layout import (
    LIBRARY,
    METADATA_FILE,
    ROS_DISTRO,
    ROSBAG2_VERSION,
)
from dvt_model.recording.read import FIELDS, TopicSeries
from dvt_model.recording.sidecar import write_truth

DEFAULT_FLUSH_PERIOD = 0.5
"""Seconds after which a received message is durable on disk (:class:`BagRecorder`)."""

#: One stream for :func:`write_bag`: (topic, msgtype, [(log_time_ns, message), ...]); a message
#: is either raw CDR bytes or a ``rosbags`` message object of ``msgtype``.
Stream = tuple[str, str, Sequence[tuple[int, Any]]]


@dataclass
class _Topic:
    topic: str
    msgtype: str
    channel_id: int
    rihs01: str
    qos: list[dict[str, Any]]
    count: int = 0


class BagRecorder:
    """Write raw CDR messages to a new rosbag2 directory (MCAP storage), crash-safely.

    Args:
        path: bag directory to create (must not exist unless ``exist_ok``).
        topics: ``{topic: msgtype}`` registered at once (more with :meth:`add_topic`).
        flush_period: close the chunk, flush and fsync at least this often [s] (see
            :meth:`poll`); ``0`` flushes after every message, ``inf`` by chunk size only.
        fsync: also ``os.fsync`` the file on every flush (survives power loss, not only kills).
        compression: chunk compression, ``"none"`` or ``"zstd"``.
        chunk_size: close a chunk once it holds this many bytes [B].
        file_name: name of the ``.mcap`` file (default ``<dirname>.mcap`` as ``rosbags``).
        exist_ok: allow ``path`` to exist (it must not hold ``file_name`` or metadata.yaml).
        clock: monotonic clock [s] used to time flushes.

    Raises :class:`~dvt_model.errors.RecordingError` (naming the path, topic and value) for a
    bad setting, an existing bag, an unknown type or a write after :meth:`close`.
    Not thread-safe: call every method from one thread (the node's executor).
    """

    def __init__(self, path: str | Path, topics: Mapping[str, str] | None = None, *,
                 flush_period: float = DEFAULT_FLUSH_PERIOD, fsync: bool = True,
                 compression: str = "none", chunk_size: int = 1 << 20,
                 file_name: str | None = None, exist_ok: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        if not flush_period >= 0:
            raise RecordingError(f"{self.path}: flush_period: expected >= 0 s (inf: flush by "
                                 f"size only), got {flush_period}")
        if compression not in ("none", "zstd"):
            raise RecordingError(f"{self.path}: compression: expected 'none' or 'zstd', got "
                                 f"{compression!r}")
        if chunk_size <= 0:
            raise RecordingError(f"{self.path}: chunk_size: expected > 0 bytes, got "
                                 f"{chunk_size}")
        self.flush_period = float(flush_period)
        self._fsync = fsync
        self._clock = clock
        if self.path.exists() and not exist_ok:
            raise RecordingError(f"{self.path} exists already; not overwriting a recording")
        self.file_path = self.path / (file_name or f"{self.path.name}.mcap")
        if (self.path / METADATA_FILE).exists():
            raise RecordingError(f"{self.path / METADATA_FILE} exists already; not overwriting")
        try:
            self.path.mkdir(parents=True, exist_ok=exist_ok)
            self._file: IO[bytes] = self.file_path.open("xb")
        except OSError as exc:
            raise RecordingError(f"{self.file_path}: cannot create: {exc.strerror or exc}"
                                 ) from exc
        self._writer = McapWriter(
            self._file, chunk_size=chunk_size,
            compression=CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._start_ns: int | None = None
        self._end_ns = 0
        self._pending = 0
        self._last_flush = clock()
        self._closed = False
        self._sync()
        for topic, msgtype in (topics or {}).items():
            self.add_topic(topic, msgtype)

    # ------------------------------------------------------------------ topics
    def add_topic(self, topic: str, msgtype: str, *, msgdef: str | None = None,
                  encoding: str = "ros2msg", rihs01: str | None = None,
                  qos: Sequence[Mapping[str, Any]] = ()) -> None:
        """Register ``topic`` with ``msgtype`` (e.g. ``sensor_msgs/msg/JointState``).

        ``msgdef``/``encoding``: schema text and encoding (``ros2msg``/``ros2idl``); taken from
        the Jazzy type store when ``None``. ``rihs01``: type hash (from the store if known).
        ``qos``: offered QoS profiles in rosbag2 v9 form (recorded as metadata only).
        Registering a topic again with the same type is a no-op; another type is an error.
        """
        self._check_open()
        if topic in self._topics:
            known = self._topics[topic].msgtype
            if known != msgtype:
                raise RecordingError(f"{self.path}: topic {topic} is recorded as {known}, "
                                     f"cannot add it again as {msgtype}")
            return
        if msgdef is None:
            try:
                msgdef, rihs01 = message_definition(msgtype)
            except RecordingError as exc:
                raise RecordingError(f"{self.path}: topic {topic}: {exc}") from exc
        elif rihs01 is None:
            rihs01 = typestore().hash_rihs01(msgtype) if msgtype in typestore().types else ""
        qos_list = [dict(q) for q in qos]
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_schema(
                name=msgtype, encoding=encoding, data=msgdef.encode())
        channel_meta = {"offered_qos_profiles": _dump_qos(qos_list)}
        if rihs01:
            channel_meta["topic_type_hash"] = rihs01
        cid = self._writer.register_channel(topic=topic, message_encoding="cdr",
                                            schema_id=self._schemas[msgtype],
                                            metadata=channel_meta)
        self._topics[topic] = _Topic(topic, msgtype, cid, rihs01 or "", qos_list)

    def has_topic(self, topic: str) -> bool:
        """Whether ``topic`` is registered."""
        return topic in self._topics

    @property
    def topics(self) -> dict[str, str]:
        """``{topic: msgtype}`` of every registered topic."""
        return {t.topic: t.msgtype for t in self._topics.values()}

    # ---------------------------------------------------------------- writing
    def write(self, topic: str, raw_cdr: bytes | bytearray | memoryview, log_time_ns: int
              ) -> None:
        """Append one serialized message (CDR bytes as received) with log time [ns].

        The message is durable after the next flush (at most ``flush_period`` later if
        :meth:`write` or :meth:`poll` keeps being called).
        """
        self._check_open()
        info = self._topics.get(topic)
        if info is None:
            raise RecordingError(f"{self.path}: topic {topic} was not added; add_topic() first")
        t = int(log_time_ns)
        if t < 0:
            raise RecordingError(f"{self.path}: topic {topic}: log time must be >= 0 ns, "
                                 f"got {t}")
        self._writer.add_message(channel_id=info.channel_id, log_time=t, data=bytes(raw_cdr),
                                 publish_time=t, sequence=info.count)
        info.count += 1
        self._pending += 1
        if self._start_ns is None or t < self._start_ns:
            self._start_ns = t
        self._end_ns = max(self._end_ns, t)
        self.poll()

    def poll(self) -> bool:
        """Flush if the last flush is ``flush_period`` old and messages wait; True if flushed.

        Call this periodically (e.g. from a 10 Hz timer) so that messages become durable even
        when no further message arrives.
        """
        if self._closed or not self._pending:
            return False
        if self._clock() - self._last_flush < self.flush_period:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Close the chunk in progress, write it out and (if enabled) fsync the file."""
        self._check_open()
        self._writer.flush()
        self._sync()
        self._pending = 0
        self._last_flush = self._clock()

    def _sync(self) -> None:
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())

    # ------------------------------------------------------------------ state
    @property
    def stats(self) -> dict[str, int]:
        """Messages written per topic."""
        return {t.topic: t.count for t in self._topics.values()}

    @property
    def message_count(self) -> int:
        """Messages written in total."""
        return sum(t.count for t in self._topics.values())

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has run."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: recorder is closed")

    # ---------------------------------------------------------------- closing
    def metadata(self) -> dict[str, Any]:
        """The ``metadata.yaml`` content (rosbag2 version 9) for the messages written so far."""
        start = self._start_ns if self._start_ns is not None else 0
        duration = max(0, self._end_ns - start) if self._start_ns is not None else 0
        count = self.message_count
        return {"rosbag2_bagfile_information": {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "relative_file_paths": [self.file_path.name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": t.topic, "type": t.msgtype,
                                    "serialization_format": "cdr",
                                    "offered_qos_profiles": t.qos,
                                    "type_description_hash": t.rihs01},
                 "message_count": t.count}
                for t in self._topics.values()],
            "compression_format": "",
            "compression_mode": "",
            "files": [{"path": self.file_path.name,
                       "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration},
                       "message_count": count}],
            "custom_data": None,
            "ros_distro": ROS_DISTRO,
        }}

    def close(self) -> dict[str, int]:
        """Finish the MCAP file (summary, footer), write ``metadata.yaml``; return :attr:`stats`.

        Idempotent. Signals are best handled by setting a flag (``dvt_driver.signals.StopFlag``)
        and calling :meth:`close` after leaving the loop normally.
        """
        if self._closed:
            return self.stats
        meta = self.metadata()
        info = meta["rosbag2_bagfile_information"]
        self._writer.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(
            info, default_flow_style=False, sort_keys=False).strip()})
        self._writer.finish()
        self._sync()
        self._file.close()
        self._closed = True
        tmp = self.path / (METADATA_FILE + ".tmp")
        with tmp.open("w", encoding="utf8") as fh:
            yaml.safe_dump(meta, fh, default_flow_style=False, sort_keys=False)
            fh.flush()
            if self._fsync:
                os.fsync(fh.fileno())
        tmp.replace(self.path / METADATA_FILE)
        if self._fsync:
            fsync_dir(self.path)
        return self.stats

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        # Everything written so far is valid data: close properly even on an exception.
        self.close()


def _dump_qos(qos: list[dict[str, Any]]) -> str:
    return yaml.safe_dump(qos, default_flow_style=False, sort_keys=False).strip()


def fsync_dir(path: Path) -> None:
    """``fsync`` a directory (its entries survive a power loss); errors are ignored."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


# ------------------------------------------------------------------ offline writing
def write_bag(path: str | Path, streams: Iterable[Stream]) -> Path:
    """Write a rosbag2 directory (MCAP, CDR, Jazzy types) holding ``streams``.

    Messages of all streams are written in log-time order (ties keep stream order), through
    one :class:`BagRecorder` (no fsync, chunks closed by size). Every stream's topic is
    registered, also when it has no messages. Raises :class:`~dvt_model.errors.BagError` if
    ``path`` exists, a type is unknown or a message cannot be serialised.
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
    with BagRecorder(path, fsync=False, flush_period=math.inf) as rec:
        for topic, msgtype in topics:
            rec.add_topic(topic, msgtype)
        for log_time, k, i, msg in entries:
            if isinstance(msg, bytes | bytearray | memoryview):
                raw = bytes(msg)
            else:
                try:
                    raw = bytes(ts.serialize_cdr(msg, topics[k][1]))
                except Exception as exc:
                    raise BagError(f"{path}: topic {topics[k][0]}: message {i} cannot be "
                                   f"serialised as {topics[k][1]}: {exc}") from exc
            rec.write(topics[k][0], raw, log_time)
    return path


def _check_shape(name: str, a: NDArray[Any], shape: tuple[int, ...]) -> None:
    if a.shape != shape:
        raise BagError(f"{name}: expected shape {shape}, got {a.shape}")


def _int_stamps(where: str, stamps_ns: ArrayLike) -> NDArray[np.int64]:
    stamps = np.asarray(stamps_ns)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise BagError(f"{where}: expected an integer array of shape (N,), got "
                       f"{stamps.dtype} array of shape {stamps.shape}")
    return stamps.astype(np.int64)


def write_run(path: str | Path, stamps_ns: ArrayLike, speeds: ArrayLike, currents: ArrayLike,
              *, model_speeds: ArrayLike | None = None, residuals: ArrayLike | None = None,
              extra: Iterable[Stream] | None = None,
              truth: Mapping[str, Any] | None = None,
              positions: ArrayLike | None = None) -> Path:
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
        positions: optional (N, 2) measured angles [rad] of ``SPEED_NAMES``, written as
            ``position`` of ``/dvt/joint_states`` (docs/interface.md); ``None``: empty.

    Values are written as given (no finiteness or order check) so that tests can build bad bags.
    """
    stamps = _int_stamps("stamps_ns", stamps_ns)
    n = stamps.shape[0]
    spd = np.asarray(speeds, dtype=np.float64)
    cur = np.asarray(currents, dtype=np.float64)
    _check_shape("speeds", spd, (n, len(SPEED_NAMES)))
    _check_shape("currents", cur, (n, len(CURRENT_NAMES)))
    stamp_list = [int(s) for s in stamps]
    pos = None if positions is None else np.asarray(positions, dtype=np.float64)
    if pos is not None:
        _check_shape("positions", pos, (n, len(SPEED_NAMES)))
    streams: list[Stream] = [
        (JOINT_STATES, JOINT_STATE_TYPE,
         [(s, joint_state_cdr(s, SPEED_NAMES, velocity=spd[i],
                              position=None if pos is None else pos[i]))
          for i, s in enumerate(stamp_list)]),
        (CURRENTS, JOINT_STATE_TYPE,
         [(s, joint_state_cdr(s, CURRENT_NAMES, effort=cur[i]))
          for i, s in enumerate(stamp_list)]),
    ]
    for name, topic, values in (("model_speeds", MODEL_JOINT_STATES, model_speeds),
                                ("residuals", MODEL_RESIDUAL, residuals)):
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
        write_truth(out, truth)
    return out


def write_topics(path: str | Path, topics: Mapping[str, TopicSeries]) -> Path:
    """Write JointState topics (the inverse of :func:`~dvt_model.recording.read.read_topics`).

    Each :class:`~dvt_model.recording.read.TopicSeries` gives per message the
    ``header.stamp`` [ns] (also the log time) and the ``position``, ``velocity`` and ``effort``
    rows; a field that is ``None`` (or of shape (N, 0)) is written as an empty array, any other
    must be (N, len(names)). Raises :class:`~dvt_model.errors.BagError` naming the path, topic and
    field for a wrong shape, or if ``path`` exists.
    """
    path = Path(path)
    streams: list[Stream] = []
    for topic, ser in topics.items():
        stamps = _int_stamps(f"{path}: topic {topic}: stamps_ns", ser.stamps_ns)
        n = stamps.shape[0]
        arrays: dict[str, NDArray[np.float64] | None] = {}
        for fname in FIELDS:
            value = ser.field_array(fname)
            a = np.zeros((n, 0)) if value is None else np.asarray(value, dtype=np.float64)
            if a.shape == (n, 0):
                arrays[fname] = None
                continue
            _check_shape(f"{path}: topic {topic}: {fname}", a, (n, len(ser.names)))
            arrays[fname] = a
        streams.append((topic, JOINT_STATE_TYPE, [
            (int(s), joint_state_cdr(int(s), ser.names, **{
                f: None if a is None else a[i] for f, a in arrays.items()}))
            for i, s in enumerate(stamps)]))
    return write_bag(path, streams)
