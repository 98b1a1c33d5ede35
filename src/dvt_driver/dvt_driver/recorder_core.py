"""Crash-safe rosbag2/MCAP recording of raw CDR messages, bag recovery and bag summaries.

Pure core of ``dvt-recorder`` and ``dvt-bag`` (no rclpy).

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
:func:`recover` (``dvt-bag recover PATH``) reads every complete chunk sequentially with
``mcap``'s stream reader and rewrites a proper bag.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import struct
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from functools import lru_cache
from pathlib import Path
from types import FrameType
from typing import IO, Any

import yaml
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from dvt_driver.errors import DvtDriverError

ROSBAG2_VERSION = 9
ROS_DISTRO = "jazzy"
LIBRARY = "dvt-recorder"
METADATA_FILE = "metadata.yaml"
DEFAULT_FLUSH_PERIOD = 0.5
NS = 1_000_000_000


class RecorderError(DvtDriverError):
    """Recording or recovering a bag failed; the message names the path and the reason."""


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The ROS 2 Jazzy type store (message definitions and RIHS01 hashes)."""
    return get_typestore(Stores.ROS2_JAZZY)


def message_definition(msgtype: str) -> tuple[str, str]:
    """``(ros2msg definition text, RIHS01 hash)`` of a Jazzy message type.

    Raises :class:`RecorderError` if the type is not a known Jazzy message.
    """
    ts = typestore()
    if msgtype not in ts.types:
        raise RecorderError(f"message type {msgtype!r} is not a known ROS 2 Jazzy message")
    msgdef, _ = ts.generate_msgdef(msgtype, ros_version=2)
    return msgdef, ts.hash_rihs01(msgtype)


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
            :meth:`poll`); ``0`` flushes after every message.
        fsync: also ``os.fsync`` the file on every flush (survives power loss, not only kills).
        compression: chunk compression, ``"none"`` or ``"zstd"``.
        chunk_size: close a chunk once it holds this many bytes [B].
        file_name: name of the ``.mcap`` file (default ``<dirname>.mcap`` as ``rosbags``).
        exist_ok: allow ``path`` to exist (it must not hold ``file_name`` or metadata.yaml).
        clock: monotonic clock [s] used to time flushes.

    Not thread-safe: call every method from one thread (the node's executor).
    """

    def __init__(self, path: str | Path, topics: Mapping[str, str] | None = None, *,
                 flush_period: float = DEFAULT_FLUSH_PERIOD, fsync: bool = True,
                 compression: str = "none", chunk_size: int = 1 << 20,
                 file_name: str | None = None, exist_ok: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        if not flush_period >= 0:
            raise RecorderError(f"flush_period: expected >= 0 s (inf: flush by size only), "
                                f"got {flush_period}")
        if compression not in ("none", "zstd"):
            raise RecorderError(f"compression: expected 'none' or 'zstd', got {compression!r}")
        if chunk_size <= 0:
            raise RecorderError(f"chunk_size: expected > 0 bytes, got {chunk_size}")
        self.flush_period = float(flush_period)
        self._fsync = fsync
        self._clock = clock
        if self.path.exists() and not exist_ok:
            raise RecorderError(f"{self.path} exists already; not overwriting a recording")
        self.file_path = self.path / (file_name or f"{self.path.name}.mcap")
        if (self.path / METADATA_FILE).exists():
            raise RecorderError(f"{self.path / METADATA_FILE} exists already; not overwriting")
        try:
            self.path.mkdir(parents=True, exist_ok=exist_ok)
            self._file: IO[bytes] = self.file_path.open("xb")
        except OSError as exc:
            raise RecorderError(f"{self.file_path}: cannot create: {exc.strerror or exc}"
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
                raise RecorderError(f"{self.path}: topic {topic} is recorded as {known}, "
                                    f"cannot add it again as {msgtype}")
            return
        if msgdef is None:
            msgdef, rihs01 = message_definition(msgtype)
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
            raise RecorderError(f"{self.path}: topic {topic} was not added; add_topic() first")
        t = int(log_time_ns)
        if t < 0:
            raise RecorderError(f"{self.path}: topic {topic}: log time must be >= 0 ns, got {t}")
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
            raise RecorderError(f"{self.path}: recorder is closed")

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

        Idempotent. Signals are best handled by setting a flag (see :class:`StopFlag`) and
        calling :meth:`close` after leaving the loop normally.
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
            _fsync_dir(self.path)
        return self.stats

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        # Everything written so far is valid data: close properly even on an exception.
        self.close()


def _dump_qos(qos: list[dict[str, Any]]) -> str:
    return yaml.safe_dump(qos, default_flow_style=False, sort_keys=False).strip()


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


# --------------------------------------------------------------------- signals
class StopFlag:
    """A flag set by SIGINT/SIGTERM instead of raising ``KeyboardInterrupt``.

    ``install()`` replaces the handlers (main thread only) and ``restore()`` puts the previous
    ones back. A second signal while the flag is set restores the previous handlers, so a
    third one falls through to the default action (an escape hatch for a hung shutdown).
    """

    def __init__(self, signals: Iterable[int] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.signals = tuple(signals)
        self.received: int | None = None
        self._previous: dict[int, Any] = {}

    def __bool__(self) -> bool:
        return self.received is not None

    @property
    def is_set(self) -> bool:
        """Whether a stop signal arrived."""
        return self.received is not None

    def set(self, signum: int = 0) -> None:
        """Request a stop (as if signal ``signum`` arrived)."""
        self.received = signum

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            self.restore()
        self.received = signum

    def install(self) -> StopFlag:
        """Install the handlers; returns self."""
        for s in self.signals:
            self._previous[s] = signal.signal(s, self._handler)
        return self

    def restore(self) -> None:
        """Restore the handlers that were active before :meth:`install`."""
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()


# -------------------------------------------------------------- topic choice
def match_topics(patterns: Sequence[str], graph: Iterable[tuple[str, Sequence[str]]]
                 ) -> tuple[dict[str, str], list[str]]:
    """Select topics of the ROS graph to record.

    Args:
        patterns: topic names or shell-style patterns (``/dvt/cmd/*``).
        graph: ``(topic, [msgtype, ...])`` as ``Node.get_topic_names_and_types()`` returns.

    Returns:
        ``({topic: msgtype}, problems)``: every matching topic with exactly one type, and a
        message for each matching topic that has several types (not recorded).
    """
    chosen: dict[str, str] = {}
    problems: list[str] = []
    for topic, types in graph:
        if not any(fnmatchcase(topic, p) for p in patterns):
            continue
        if len(types) != 1:
            problems.append(f"topic {topic} has {len(types)} types {list(types)}; not recorded")
            continue
        chosen[topic] = types[0]
    return chosen, problems


def choose_qos(offered: Sequence[tuple[str, str]]) -> tuple[str, str] | None:
    """Subscription ``(reliability, durability)`` that matches every offered publisher.

    ``offered``: ``(reliability, durability)`` of each publisher, lower-case names
    (``reliable``/``best_effort``, ``volatile``/``transient_local``). A RELIABLE subscription
    does not match a BEST_EFFORT publisher, so RELIABLE is chosen only if every publisher
    offers it (the same rule as ``ros2 bag record``); likewise TRANSIENT_LOCAL. ``None`` when
    there is no publisher yet.
    """
    if not offered:
        return None
    reliability = "reliable" if all(r == "reliable" for r, _ in offered) else "best_effort"
    durability = ("transient_local" if all(d == "transient_local" for _, d in offered)
                  else "volatile")
    return reliability, durability


# ------------------------------------------------------------------- recover
@dataclass
class RecoverResult:
    """Outcome of :func:`recover`.

    ``counts``: messages recovered per topic; ``output``: the readable bag directory;
    ``moved``: broken files renamed aside; ``stopped``: why reading stopped early (``""`` if
    the input ended cleanly); ``skipped``: messages that could not be kept (unknown channel).
    """

    output: Path
    counts: dict[str, int] = field(default_factory=dict)
    moved: list[Path] = field(default_factory=list)
    stopped: str = ""
    skipped: int = 0
    already_readable: bool = False

    @property
    def total(self) -> int:
        """Messages recovered in total."""
        return sum(self.counts.values())


def _bag_files(path: Path) -> tuple[Path, list[Path]]:
    if not path.exists():
        raise RecorderError(f"{path}: no such file or directory")
    if path.is_file():
        if path.suffix != ".mcap":
            raise RecorderError(f"{path}: expected a bag directory or an .mcap file")
        return path.parent, [path]
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise RecorderError(f"{path}: no .mcap file in this directory")
    return path, files


def is_readable(path: str | Path) -> bool:
    """Whether ``rosbags`` opens the bag directory and all of its messages are reachable."""
    p = Path(path)
    if not (p.is_dir() and (p / METADATA_FILE).exists()):
        return False
    try:
        with Reader(p) as reader:
            for _ in reader.messages():
                pass
    except (ReaderError, OSError, ValueError, KeyError):
        return False
    return True


def _salvage(src: Path, out: BagRecorder, result: RecoverResult) -> None:
    """Copy every complete record of ``src`` into ``out``; note why reading stopped."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    added: dict[int, str] = {}
    with src.open("rb") as fh:
        reader = StreamReader(fh, validate_crcs=True, record_size_limit=1 << 31)
        try:
            for rec in reader.records:
                if isinstance(rec, Header):
                    if rec.profile != "ros2":
                        raise RecorderError(f"{src}: MCAP profile is {rec.profile!r}, "
                                            "expected 'ros2' (not a rosbag2 recording)")
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                    _add_channel(out, rec, schemas, added)
                elif isinstance(rec, Message):
                    topic = added.get(rec.channel_id)
                    if topic is None:
                        result.skipped += 1
                        continue
                    out.write(topic, rec.data, rec.log_time)
                elif isinstance(rec, Metadata):
                    continue
        except RecorderError:
            raise
        except Exception as exc:
            # A truncated last record (EndOfFile, short struct) is the normal end of a killed
            # recording; anything else is reported as it is.
            if isinstance(exc, EndOfFile | struct.error):
                result.stopped = f"{src.name}: truncated record after offset {fh.tell()}"
            else:
                result.stopped = (f"{src.name}: {type(exc).__name__}: {exc} after offset "
                                  f"{fh.tell()}")


def _add_channel(out: BagRecorder, ch: Channel, schemas: Mapping[int, Schema],
                 added: dict[int, str]) -> None:
    schema = schemas.get(ch.schema_id)
    if schema is None or ch.message_encoding != "cdr":
        return
    try:
        qos = yaml.safe_load(ch.metadata.get("offered_qos_profiles", "") or "[]")
    except yaml.YAMLError:
        qos = []
    if not isinstance(qos, list) or not all(isinstance(q, dict) for q in qos):
        qos = []
    out.add_topic(ch.topic, schema.name, msgdef=schema.data.decode("utf8", "replace"),
                  encoding=schema.encoding or "ros2msg",
                  rihs01=ch.metadata.get("topic_type_hash") or None, qos=qos)
    added[ch.id] = ch.topic


def _unique_aside(p: Path, suffix: str) -> Path:
    target = p.with_name(p.name + suffix)
    k = 1
    while target.exists():
        target = p.with_name(f"{p.name}{suffix}.{k}")
        k += 1
    return target


def recover(path: str | Path, out: str | Path | None = None, *, force: bool = False
            ) -> RecoverResult:
    """Rebuild a readable rosbag2 directory from a killed recording.

    Reads every complete chunk/record of the ``.mcap`` file(s) in ``path`` (a bag directory or
    one ``.mcap`` file) sequentially, without the (missing) summary, and writes a proper bag:

    * ``out`` given: a new bag directory ``out`` (must not exist); sidecar files such as
      ``truth.yaml`` are copied;
    * in place otherwise: each broken ``X.mcap`` is renamed ``X.mcap.broken`` (a stale
      ``metadata.yaml`` ``metadata.yaml.broken``) and the rebuilt ``X.mcap`` plus
      ``metadata.yaml`` take their place.

    A bag that is already readable is left alone (``already_readable``) unless ``force``.
    Raises :class:`RecorderError` for a missing path, no ``.mcap`` file, a file that is not
    MCAP/rosbag2, or an existing ``out``.
    """
    src = Path(path)
    bagdir, files = _bag_files(src)
    if not force and src.is_dir() and out is None and is_readable(src):
        return RecoverResult(output=src, already_readable=True)
    for f in files:
        with f.open("rb") as fh:
            if fh.read(8) != b"\x89MCAP0\r\n":
                raise RecorderError(f"{f}: not an MCAP file (bad magic)")
    if out is not None:
        target = Path(out)
        if target.exists():
            raise RecorderError(f"{target} exists already; choose a new --out directory")
        result = RecoverResult(output=target)
        try:
            with BagRecorder(target, fsync=True, flush_period=math.inf) as rec:
                for f in files:
                    _salvage(f, rec, result)
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
        for side in bagdir.iterdir():
            if side.is_file() and side.suffix in (".yaml", ".json") \
                    and side.name != METADATA_FILE and not side.name.endswith(".tmp"):
                shutil.copy2(side, target / side.name)
        result.counts = _counts(rec)
        return result

    result = RecoverResult(output=bagdir)
    tmpdir = bagdir / ".dvt-recover.tmp"
    if tmpdir.exists():
        shutil.rmtree(tmpdir)
    name = files[0].name
    try:
        with BagRecorder(tmpdir, fsync=True, flush_period=math.inf, file_name=name) as rec:
            for f in files:
                _salvage(f, rec, result)
    except BaseException:
        shutil.rmtree(tmpdir, ignore_errors=True)
        raise
    for f in files:
        aside = _unique_aside(f, ".broken")
        f.rename(aside)
        result.moved.append(aside)
    meta = bagdir / METADATA_FILE
    if meta.exists():
        aside = _unique_aside(meta, ".broken")
        meta.rename(aside)
        result.moved.append(aside)
    (tmpdir / name).rename(bagdir / name)
    (tmpdir / METADATA_FILE).rename(meta)
    tmpdir.rmdir()
    _fsync_dir(bagdir)
    result.counts = _counts(rec)
    return result


def _counts(rec: BagRecorder) -> dict[str, int]:
    return dict(rec.stats)


# ---------------------------------------------------------------------- info
@dataclass
class TopicSummary:
    """One topic of a bag: type, message count, first/last log time [ns]."""

    topic: str
    msgtype: str
    count: int
    first_ns: int | None
    last_ns: int | None

    @property
    def rate(self) -> float:
        """Mean message rate [Hz] over the topic's own span (``nan`` below two messages)."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None \
                or self.last_ns <= self.first_ns:
            return math.nan
        return (self.count - 1) * NS / (self.last_ns - self.first_ns)


@dataclass
class BagSummary:
    """What ``dvt-bag info`` prints: per-topic counts, duration [s], start [ns]."""

    path: Path
    topics: list[TopicSummary]
    start_ns: int
    duration: float

    @property
    def message_count(self) -> int:
        """Messages in total."""
        return sum(t.count for t in self.topics)

    def format(self) -> str:
        """Human-readable multi-line summary."""
        lines = [f"bag:       {self.path}",
                 f"duration:  {self.duration:.3f} s",
                 f"start:     {self.start_ns / NS:.6f} s (log time)",
                 f"messages:  {self.message_count}",
                 "topics:"]
        width = max((len(t.topic) for t in self.topics), default=0)
        for t in self.topics:
            rate = "" if math.isnan(t.rate) else f"  {t.rate:9.2f} Hz"
            lines.append(f"  {t.topic:<{width}}  {t.count:8d} msgs{rate}  [{t.msgtype}]")
        return "\n".join(lines)


def bag_summary(path: str | Path) -> BagSummary:
    """Summarise a readable bag directory (reads every message's log time, not its data)."""
    p = Path(path)
    if not p.exists():
        raise RecorderError(f"{p}: no such bag directory")
    if p.is_dir() and not (p / METADATA_FILE).exists():
        raise RecorderError(f"{p}: metadata.yaml is missing (killed recording?); run "
                            f"`dvt-bag recover {p}`")
    try:
        with Reader(p) as reader:
            first: dict[str, int] = {}
            last: dict[str, int] = {}
            counts: dict[str, int] = {}
            types: dict[str, str] = {}
            for c in reader.connections:
                types.setdefault(c.topic, c.msgtype)
                counts.setdefault(c.topic, 0)
            for conn, t, _ in reader.messages():
                counts[conn.topic] += 1
                first.setdefault(conn.topic, t)
                first[conn.topic] = min(first[conn.topic], t)
                last[conn.topic] = max(last.get(conn.topic, t), t)
    except (ReaderError, OSError, ValueError, KeyError) as exc:
        raise RecorderError(f"{p}: cannot read bag: {exc} (if the recording was killed, run "
                            f"`dvt-bag recover {p}`)") from exc
    topics = [TopicSummary(tp, types[tp], counts[tp], first.get(tp), last.get(tp))
              for tp in sorted(types)]
    start = min(first.values(), default=0)
    end = max(last.values(), default=start)
    return BagSummary(p, topics, start, (end - start) / NS)
