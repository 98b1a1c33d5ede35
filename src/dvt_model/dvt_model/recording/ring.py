"""Rolling recording: the last N minutes in a ring of crash-safe segments, and snapshots (pure).

:class:`RollingRecorder` writes what it is given (raw CDR + log time, like
:class:`~dvt_model.recording.write.BagRecorder`) into a directory of *segments*, each a normal
rosbag2/MCAP bag ``seg-<start_ns>`` written by the one writer (:class:`BagRecorder`, so each
segment is as crash-safe as a recording: durable within ``flush_period``). A segment is closed
after ``segment_s`` seconds of log time and a new one opened with the next message; segments
whose whole content is older than ``ring_s`` before the newest message are deleted (never one a
snapshot in progress reads). Every message goes to exactly one segment, so a window that spans
segment boundaries loses nothing.

:meth:`RollingRecorder.snapshot` (or :meth:`~RollingRecorder.prepare` + :func:`write_snapshot`
+ :meth:`~RollingRecorder.release`, so that the copy can run in another thread) writes the
messages of a time window as a normal bag through :class:`BagRecorder`: same topics, types,
schemas, QoS metadata and log times as the segments (same contract as any recording, read with
:func:`~dvt_model.recording.read.read_run`). The segments are read with the one salvage scanner
(:class:`~dvt_model.recording.mcapindex.McapScan`), so a segment left by a killed recorder is
read up to its last complete chunk.

Window: a message is in ``[t_from, t_to]`` by its ``header.stamp`` when its type starts with a
``std_msgs/Header`` (JointState, DiagnosticArray, ...: the two messages of one controller sample
carry the same stamp, so a sample is never cut in half at the window's edge), else by its log
time. Times are ROS time [ns] here; the snapshot API takes seconds.

Segments of an earlier run found in the directory are adopted (read by snapshots, deleted when
they age out).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Channel, Schema

from dvt_model.errors import RecordingError
from dvt_model.recording.cdr import raw_stamp_ns
from dvt_model.recording.mcapindex import McapScan
from dvt_model.recording.recover import _add_channel
from dvt_model.recording.write import DEFAULT_FLUSH_PERIOD, BagRecorder, fsync_dir

SEGMENT_PREFIX = "seg-"
"""Name prefix of a segment directory: ``seg-<start log time, ns, 20 digits>``."""
_HEADER_TYPES = ("std_msgs/Header", "std_msgs/msg/Header", "Header")


@dataclass
class Segment:
    """One segment of the ring: bag directory ``path``, first log time ``start_ns`` [ns], last
    log time written ``end_ns`` [ns] (``None``: unknown, an adopted segment), ``messages``
    written by this process, ``closed`` (finished, immutable)."""

    path: Path
    start_ns: int
    end_ns: int | None = None
    messages: int = 0
    closed: bool = False

    @property
    def mcap_files(self) -> list[Path]:
        """The segment's ``.mcap`` file(s)."""
        return sorted(self.path.glob("*.mcap"))


@dataclass(frozen=True)
class SnapshotPlan:
    """What :func:`write_snapshot` reads: closed ``segments`` (in time order) and the window
    ``[from_ns, to_ns]`` [ns]; ``truncated`` if the ring's oldest segment starts more than the
    margin after ``from_ns`` (the start of the window is no longer, or never was, in the ring)."""

    from_ns: int
    to_ns: int
    segments: tuple[Segment, ...]
    truncated: bool


@dataclass
class SnapshotResult:
    """Outcome of a snapshot: the bag ``path``, messages per topic ``counts``, the first and
    last stamp written [ns] (``None`` if empty), segments read, ``truncated`` (window older
    than the ring), ``stopped`` notes of segments read only up to a damaged end."""

    path: Path
    from_ns: int
    to_ns: int
    counts: dict[str, int] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    segments: int = 0
    truncated: bool = False
    stopped: list[str] = field(default_factory=list)

    @property
    def total(self) -> int:
        """Messages written in total."""
        return sum(self.counts.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (times in seconds)."""
        return {"out": str(self.path), "from": self.from_ns * 1e-9, "to": self.to_ns * 1e-9,
                "counts": dict(self.counts), "messages": self.total,
                "first": None if self.first_ns is None else self.first_ns * 1e-9,
                "last": None if self.last_ns is None else self.last_ns * 1e-9,
                "segments": self.segments, "truncated": self.truncated,
                "stopped": list(self.stopped)}


def seconds_to_ns(value: float, name: str) -> int:
    """ROS time [s] -> [ns]; :class:`RecordingError` naming ``name`` if not finite/negative."""
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not math.isfinite(value) or value < 0:
        raise RecordingError(f"{name}: expected a time >= 0 s, got {value!r}")
    return round(float(value) * 1e9)


WINDOW_TOLERANCE_NS = 1000
"""A window given in float seconds is widened by this much on both sides [ns]: a float64 ROS
time (~1.8e9 s) resolves only ~0.24 us, so a sample stamped exactly at an edge could fall out."""


def window_ns(from_s: float, to_s: float) -> tuple[int, int]:
    """``[from_s, to_s]`` (ROS time [s], floats) as ``[from_ns, to_ns]`` widened by
    :data:`WINDOW_TOLERANCE_NS`; :class:`RecordingError` naming ``from``/``to`` if invalid."""
    lo = seconds_to_ns(from_s, "from")
    hi = seconds_to_ns(to_s, "to")
    return max(lo - WINDOW_TOLERANCE_NS, 0), hi + WINDOW_TOLERANCE_NS


class RollingRecorder:
    """The last ``ring_s`` seconds of messages in segments of ``segment_s`` seconds.

    Args:
        directory: ring directory (created if missing; segments of an earlier run are adopted).
        ring_s: keep at least this much log time [s] (older whole segments are deleted).
        segment_s: log-time length of one segment [s] (``<= ring_s``).
        flush_period, fsync, compression: as :class:`BagRecorder` (every segment).
        clock: monotonic clock [s] for the writer's flush timing.

    Raises :class:`RecordingError` naming the parameter for a bad setting. Not thread-safe:
    call every method from one thread; only :func:`write_snapshot` may run in another.
    """

    def __init__(self, directory: str | Path, *, ring_s: float, segment_s: float = 10.0,
                 flush_period: float = DEFAULT_FLUSH_PERIOD, fsync: bool = True,
                 compression: str = "none",
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.directory = Path(directory)
        if isinstance(ring_s, bool) or not isinstance(ring_s, int | float) \
                or not math.isfinite(ring_s) or ring_s <= 0:
            raise RecordingError(f"ring_s: expected a finite length > 0 s, got {ring_s!r}")
        if isinstance(segment_s, bool) or not isinstance(segment_s, int | float) \
                or not math.isfinite(segment_s) or not 0 < segment_s <= ring_s:
            raise RecordingError(f"segment_s: expected a length in (0, ring_s = {ring_s:g}] s, "
                                 f"got {segment_s!r}")
        if self.directory.exists() and not self.directory.is_dir():
            raise RecordingError(f"{self.directory}: exists and is not a directory")
        self.ring_ns = round(ring_s * 1e9)
        self.segment_ns = round(segment_s * 1e9)
        self._writer_args: dict[str, Any] = {"flush_period": flush_period, "fsync": fsync,
                                             "compression": compression, "clock": clock}
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.directory}: cannot create: {exc.strerror or exc}"
                                 ) from exc
        self.segments: list[Segment] = self._adopt()
        self._topics: dict[str, tuple[str, dict[str, Any]]] = {}
        self._current: BagRecorder | None = None
        self._pins: dict[int, int] = {}  # id(segment) -> snapshots reading it
        self.newest_ns: int | None = None
        self.deleted = 0
        self._closed = False

    def _adopt(self) -> list[Segment]:
        found: list[Segment] = []
        for p in self.directory.iterdir():
            if not (p.is_dir() and p.name.startswith(SEGMENT_PREFIX)):
                continue
            try:
                start = int(p.name[len(SEGMENT_PREFIX):].split("-")[0])
            except ValueError:
                continue
            found.append(Segment(p, start, closed=True))
        found.sort(key=lambda s: (s.start_ns, s.path.name))
        for a, b in itertools.pairwise(found):
            a.end_ns = b.start_ns
        return found

    # ------------------------------------------------------------------ topics
    def add_topic(self, topic: str, msgtype: str, **kwargs: Any) -> None:
        """Register ``topic`` (arguments as :meth:`BagRecorder.add_topic`) in the current and
        every later segment. Another type for a known topic is a :class:`RecordingError`."""
        known = self._topics.get(topic)
        if known is not None and known[0] != msgtype:
            raise RecordingError(f"{self.directory}: topic {topic} is recorded as {known[0]}, "
                                 f"cannot add it again as {msgtype}")
        self._topics[topic] = (msgtype, dict(kwargs))
        if self._current is not None:
            self._current.add_topic(topic, msgtype, **kwargs)

    def has_topic(self, topic: str) -> bool:
        """Whether ``topic`` is registered."""
        return topic in self._topics

    @property
    def topics(self) -> dict[str, str]:
        """``{topic: msgtype}`` of every registered topic."""
        return {t: v[0] for t, v in self._topics.items()}

    # ----------------------------------------------------------------- writing
    def write(self, topic: str, raw_cdr: bytes | bytearray | memoryview, log_time_ns: int
              ) -> None:
        """Append one message (raw CDR, log time [ns]); rotates and prunes segments."""
        if self._closed:
            raise RecordingError(f"{self.directory}: rolling recorder is closed")
        if topic not in self._topics:
            raise RecordingError(f"{self.directory}: topic {topic} was not added; "
                                 "add_topic() first")
        t = int(log_time_ns)
        seg = self.segments[-1] if self._current is not None else None
        if seg is not None and t >= seg.start_ns + self.segment_ns:
            self._close_current()
            seg = None
        writer = self._current
        if seg is None or writer is None:
            seg, writer = self._open(t)
        writer.write(topic, raw_cdr, t)
        seg.messages += 1
        seg.end_ns = t if seg.end_ns is None else max(seg.end_ns, t)
        if self.newest_ns is None or t > self.newest_ns:
            self.newest_ns = t
            self._prune()

    def _open(self, start_ns: int) -> tuple[Segment, BagRecorder]:
        name = f"{SEGMENT_PREFIX}{max(start_ns, 0):020d}"
        path = self.directory / name
        k = 1
        while path.exists():
            path = self.directory / f"{name}-{k}"
            k += 1
        writer = BagRecorder(path, **self._writer_args)
        for topic, (msgtype, kwargs) in self._topics.items():
            writer.add_topic(topic, msgtype, **kwargs)
        self._current = writer
        if self.segments and self.segments[-1].end_ns is None:
            self.segments[-1].end_ns = start_ns
        seg = Segment(path, start_ns)
        self.segments.append(seg)
        return seg, writer

    def _close_current(self) -> None:
        if self._current is None:
            return
        self._current.close()
        self._current = None
        self.segments[-1].closed = True
        fsync_dir(self.directory)

    def poll(self, now_ns: int | None = None) -> None:
        """Make buffered messages durable (:meth:`BagRecorder.poll`); with ``now_ns`` (ROS time
        [ns]) also close the current segment once its ``segment_s`` are over, so that a pause
        in the traffic does not keep a segment open."""
        if self._current is None:
            return
        self._current.poll()
        if now_ns is not None and now_ns >= self.segments[-1].start_ns + self.segment_ns:
            self._close_current()

    def _prune(self) -> None:
        if self.newest_ns is None:
            return
        horizon = self.newest_ns - self.ring_ns
        while len(self.segments) > 1:
            seg = self.segments[0]
            end = self.segments[1].start_ns  # everything in seg is older than its successor
            if end >= horizon or self._pins.get(id(seg)):
                return
            shutil.rmtree(seg.path, ignore_errors=True)
            self.segments.pop(0)
            self.deleted += 1

    @property
    def oldest_ns(self) -> int | None:
        """Start [ns] of the oldest segment held (``None``: empty ring)."""
        return self.segments[0].start_ns if self.segments else None

    # --------------------------------------------------------------- snapshots
    def prepare(self, from_ns: int, to_ns: int, margin_ns: int = 2 * 10**9) -> SnapshotPlan:
        """Choose and pin the segments a snapshot of ``[from_ns, to_ns]`` reads.

        Segments whose log-time span overlaps the window widened by ``margin_ns`` (the time
        between a sample's stamp and its reception) are chosen; the current segment is closed
        first if it is among them, so that every chosen segment is immutable. Pinned segments
        are not deleted until :meth:`release`.
        """
        if to_ns < from_ns:
            raise RecordingError(f"snapshot window: 'to' ({to_ns * 1e-9:.9f} s) is before "
                                 f"'from' ({from_ns * 1e-9:.9f} s)")
        lo, hi = from_ns - margin_ns, to_ns + margin_ns
        chosen: list[Segment] = []
        for i, seg in enumerate(self.segments):
            end = seg.end_ns
            if end is None:
                end = self.segments[i + 1].start_ns if i + 1 < len(self.segments) else hi
            if seg.start_ns <= hi and end >= lo:
                chosen.append(seg)
        if chosen and chosen[-1] is self.segments[-1] and self._current is not None:
            self._close_current()
        for seg in chosen:
            self._pins[id(seg)] = self._pins.get(id(seg), 0) + 1
        truncated = not self.segments or self.segments[0].start_ns > from_ns + margin_ns
        return SnapshotPlan(from_ns, to_ns, tuple(chosen), truncated)

    def release(self, plan: SnapshotPlan) -> None:
        """Unpin the segments of ``plan`` (they may be deleted again)."""
        for seg in plan.segments:
            n = self._pins.get(id(seg), 0) - 1
            if n > 0:
                self._pins[id(seg)] = n
            else:
                self._pins.pop(id(seg), None)
        self._prune()

    def snapshot(self, from_s: float, to_s: float, out_dir: str | Path,
                 margin_s: float = 2.0) -> SnapshotResult:
        """Write the messages of ``[from_s, to_s]`` (ROS time [s], widened by 1 us for float
        rounding: :func:`window_ns`) as a new bag ``out_dir``."""
        lo, hi = window_ns(from_s, to_s)
        plan = self.prepare(lo, hi, round(margin_s * 1e9))
        try:
            return write_snapshot(plan, out_dir)
        finally:
            self.release(plan)

    # ----------------------------------------------------------------- closing
    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has run."""
        return self._closed

    @property
    def message_count(self) -> int:
        """Messages written by this process (all segments, also deleted ones not counted)."""
        return sum(s.messages for s in self.segments)

    def close(self) -> None:
        """Close the current segment (idempotent)."""
        if not self._closed:
            self._close_current()
            self._closed = True

    def __enter__(self) -> RollingRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def has_header(schema: Schema | None) -> bool:
    """Whether a ``ros2msg`` schema's first field is a ``std_msgs/Header header``."""
    if schema is None:
        return False
    for line in schema.data.decode("utf8", "replace").splitlines():
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = s.split()
        return len(parts) >= 2 and parts[0] in _HEADER_TYPES and parts[1] == "header"
    return False


def write_snapshot(plan: SnapshotPlan, out_dir: str | Path) -> SnapshotResult:
    """Copy the messages of ``plan``'s window from its (closed) segments into a new bag.

    Runs in any thread (reads only immutable files). Raises :class:`RecordingError` if
    ``out_dir`` exists or cannot be written; a partial output is removed.
    """
    out = Path(out_dir)
    if out.exists():
        raise RecordingError(f"{out} exists already; choose a new snapshot directory")
    result = SnapshotResult(path=out, from_ns=plan.from_ns, to_ns=plan.to_ns,
                            truncated=plan.truncated)
    lo, hi = plan.from_ns, plan.to_ns
    try:
        with BagRecorder(out, fsync=True, flush_period=math.inf) as rec:
            for seg in plan.segments:
                files = seg.mcap_files
                if not files:
                    continue
                result.segments += 1
                for f in files:
                    _copy_window(f, rec, lo, hi, result)
        result.counts = {t: n for t, n in rec.stats.items()}
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return result


def _copy_window(src: Path, rec: BagRecorder, lo: int, hi: int, result: SnapshotResult
                 ) -> None:
    scan = McapScan(src)
    topic_of: dict[int, str] = {}
    stamped: dict[int, bool] = {}
    for r in scan:
        if isinstance(r, Channel):
            _add_channel(rec, r, scan.schemas, topic_of)
            stamped[r.id] = has_header(scan.schemas.get(r.schema_id))
            continue
        topic = topic_of.get(r.channel_id)
        if topic is None:
            continue
        t = r.log_time
        if stamped.get(r.channel_id):
            with contextlib.suppress(ValueError):  # not CDR: the log time stands in
                t = raw_stamp_ns(r.data)
        if lo <= t <= hi:
            rec.write(topic, r.data, r.log_time)
            if result.first_ns is None or t < result.first_ns:
                result.first_ns = t
            if result.last_ns is None or t > result.last_ns:
                result.last_ns = t
    if scan.stopped:
        result.stopped.append(scan.stopped)


def segment_paths(directory: str | Path) -> list[Path]:
    """Segment directories of a ring directory, oldest first."""
    d = Path(directory)
    return sorted((p for p in d.iterdir() if p.is_dir() and p.name.startswith(SEGMENT_PREFIX)),
                  key=lambda p: p.name)
