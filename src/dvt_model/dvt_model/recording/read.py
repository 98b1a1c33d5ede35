"""Reading recordings: JointState topics in bulk, and the contract's aligned run (pure).

The contract (``INTERFACE.md``, :mod:`dvt_model.contract`): a recording holds at least
``/dvt/joint_states`` (measured speeds [rad/s] of ``SPEED_NAMES`` in ``velocity``) and
``/dvt/currents`` (winding currents [A] of ``CURRENT_NAMES`` in ``effort``), both
``sensor_msgs/msg/JointState``. The two messages of one controller sample carry the identical
``header.stamp``; stamps strictly increase. Unknown extra topics are ignored.

Reading (:func:`read_topics`) is one pass over the bag for all wanted topics: an indexed MCAP file
is read through its summary and message indexes (:mod:`~dvt_model.recording.mcapindex`), any
other storage or anything unexpected through the ``rosbags`` message iterator. Each topic is then
decoded in bulk: messages with the byte layout of the topic's first message (same length, same
bytes apart from the stamp and the float arrays) are sliced with numpy, the others decoded one
by one with the same checks and errors. Every problem raises
:class:`~dvt_model.errors.BagError` naming the bag path, the topic and the field.

A killed recording (an MCAP file its writer did not finish: no summary/footer, the last chunk
cut; or no ``metadata.yaml``) is read by :func:`read_topics` up to its last complete chunk with
the salvage scan of ``dvt-bag recover`` (:class:`~dvt_model.recording.mcapindex.McapScan`) and
a :class:`~dvt_model.errors.RecordingWarning` naming the file, the messages kept and the
repair command; a file with no complete message raises :class:`BagError` naming the file.
:func:`read_run`, the strict contract reader, refuses such a recording unless asked to salvage.
Values are not checked by :func:`read_topics` (stamps, NaN: the caller decides what to keep);
:func:`read_run` refuses non-finite values and stamps that do not strictly increase.
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Channel
from numpy.typing import NDArray
from rosbags.rosbag2 import Reader, ReaderError

from dvt_model.contract import (
    CURRENT_NAMES,
    CURRENTS,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    SPEED_NAMES,
)
from dvt_model.errors import BagError, RecordingWarning
from dvt_model.recording import mcapindex
from dvt_model.recording.cdr import CdrLayout, JointStateFields, cdr_layout, parse_joint_state
from dvt_model.recording.layout import (
    MCAP_MAGIC,
    METADATA_FILE,
    RECOVER_HINT,
    recover_hint,
)
from dvt_model.recording.mcapindex import RawMessages, message_at, raw_from_list, rows, view_as
from dvt_model.recording.pairing import pair_stamps

Float2D = NDArray[np.float64]
Int1D = NDArray[np.int64]
FIELDS: tuple[str, ...] = ("position", "velocity", "effort")
"""The float-array fields of a JointState, in message order."""


@dataclass(frozen=True)
class TopicSeries:
    """All messages of one ``sensor_msgs/msg/JointState`` topic, in recorded order: the one
    series type of the suite (read by :func:`read_topics`, written by
    :func:`~dvt_model.recording.write.write_topics`).

    ``stamps_ns`` (N,) int64 header stamps [ns]; ``names`` joint names (identical in every
    message); ``position``, ``velocity`` and ``effort`` each (N, len(names)) [rad, rad/s, A or
    N m], or ``None`` when the messages carry none (an empty array in the message).
    """

    stamps_ns: Int1D
    names: tuple[str, ...]
    position: Float2D | None = None
    velocity: Float2D | None = None
    effort: Float2D | None = None

    @property
    def n(self) -> int:
        """Number of messages N."""
        return int(self.stamps_ns.shape[0])

    def field_array(self, name: str) -> Float2D | None:
        """The array of field ``name`` (one of :data:`FIELDS`), ``None`` when empty.

        Raises:
            KeyError: ``name`` is not a JointState float field.
        """
        if name not in FIELDS:
            raise KeyError(f"{name!r}: not a JointState field (expected one of {list(FIELDS)})")
        value: Float2D | None = getattr(self, name)
        return value


@dataclass(frozen=True)
class Run:
    """One recording aligned by stamp.

    ``stamps_ns`` (N,) int64 sample stamps [ns]; ``t`` (N,) seconds since the first stamp;
    ``speeds`` (N, 2) [rad/s] of ``SPEED_NAMES``; ``currents`` (N, 4) [A] of ``CURRENT_NAMES``;
    ``topics`` every topic present in the bag; ``unmatched`` samples dropped because their stamp
    was present in only one of the two topics (``unmatched_by_topic`` per topic);
    ``positions`` (N, 2) the recorded angles [rad] of ``SPEED_NAMES`` (``position`` of
    ``/dvt/joint_states``), or ``None`` when the recording has none (or a non-finite one).
    """

    path: Path
    stamps_ns: Int1D
    t: NDArray[np.float64]
    speeds: Float2D
    currents: Float2D
    topics: tuple[str, ...]
    unmatched: int = 0
    unmatched_by_topic: dict[str, int] = field(default_factory=dict)
    positions: Float2D | None = None

    @property
    def n(self) -> int:
        """Number of aligned samples."""
        return int(self.stamps_ns.shape[0])

    @property
    def duration(self) -> float:
        """Last minus first stamp [s]."""
        return float(self.t[-1]) if self.n else 0.0


def open_reader(path: Path) -> Reader:
    """An opened ``rosbags`` reader of bag directory ``path``.

    Raises :class:`BagError` naming the path (and ``dvt-bag recover`` for a killed recording).
    """
    if not path.exists():
        raise BagError(f"{path}: no such bag directory")
    if path.is_dir() and not (path / METADATA_FILE).exists():
        hint = ""
        if any(path.glob("*.mcap")):
            hint = (f" (the recording was probably killed; run `{RECOVER_HINT} {path}` "
                    "to rebuild a readable bag)")
        raise BagError(f"{path}: not a readable bag: metadata.yaml is missing{hint}")
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, OSError) as exc:
        raise BagError(f"{path}: cannot open bag: {exc}{recover_hint(path)}") from exc
    return reader


# --------------------------------------------------------------------------------------------
# One pass over the bag collects the raw CDR of every wanted topic, then each topic is decoded
# in bulk (numpy on the stacked bytes); messages that do not share the layout of the topic's
# first message are decoded one by one (same checks, same errors).


def _check_topics(path: Path, topics: Sequence[str], types: Mapping[str, Sequence[str]]
                  ) -> None:
    """Check that ``topics`` are among the bag's topics (``types``: topic -> message types of
    its connections) and are JointState topics."""
    for topic in topics:
        if topic not in types:
            raise BagError(f"{path}: topic {topic} missing (topics present: {sorted(types)})")
        for msgtype in types[topic]:
            if msgtype != JOINT_STATE_TYPE:
                raise BagError(f"{path}: topic {topic}: type is {msgtype}, expected "
                               f"{JOINT_STATE_TYPE}")


def _collect(reader: Reader, path: Path, topics: Sequence[str]) -> dict[str, RawMessages]:
    """Check that ``topics`` are JointState topics of the bag; return their raw messages."""
    types: dict[str, list[str]] = {}
    for c in reader.connections:
        types.setdefault(c.topic, []).append(c.msgtype)
    _check_topics(path, topics, types)
    conns = [c for c in reader.connections if c.topic in topics]
    files = mcapindex.mcap_files(path)
    if files is not None:
        try:
            return mcapindex.mcap_collect(files, topics)
        except (mcapindex.McapFastPathError, OSError, ValueError, struct.error,
                UnicodeDecodeError):
            pass  # rosbags reads it (and reports what is wrong with it)
    raws: dict[str, list[bytes]] = {t: [] for t in topics}
    try:
        for conn, _, raw in reader.messages(connections=conns):
            raws[conn.topic].append(raw)
    except Exception as exc:  # ReaderError, or a decompressor's error on corrupt storage
        which = ", ".join(topics)
        raise BagError(f"{path}: topic{'s' if len(topics) > 1 else ''} {which}: cannot read "
                       f"messages: {exc}") from exc
    return {t: raw_from_list(r) for t, r in raws.items()}


def _unfinished_mcaps(path: Path) -> list[Path] | None:
    """The MCAP files of bag directory ``path`` if it is a killed recording: some file was not
    finished by its writer, or ``metadata.yaml`` is missing next to ``.mcap`` files. ``None``:
    a finished bag (or not an uncompressed MCAP bag), read as usual."""
    if not path.is_dir():
        return None
    if not (path / METADATA_FILE).exists():
        return sorted(path.glob("*.mcap")) or None
    files = mcapindex.mcap_files(path)
    if files and all(f.is_file() for f in files) \
            and not all(mcapindex.mcap_finished(f) for f in files):
        return files
    return None


def _salvage_collect(path: Path, files: Sequence[Path], topics: Sequence[str]
                     ) -> tuple[dict[str, RawMessages], tuple[str, ...]]:
    """Raw messages of ``topics`` (log-time order, ties in file order) and every topic present,
    from the complete records of the unfinished MCAP ``files`` of a killed recording; warns with
    :class:`RecordingWarning`.

    Raises:
        BagError: a file is not MCAP (names the file), no file holds a complete message (names
            the files), or a topic is missing or not JointState.
    """
    wanted = set(topics)
    types: dict[str, list[str]] = {}
    found: dict[str, list[tuple[int, bytes]]] = {t: [] for t in topics}
    stops: list[str] = []
    total = 0
    for f in files:
        try:
            with f.open("rb") as fh:
                head = fh.read(len(MCAP_MAGIC))
            if head != MCAP_MAGIC:
                what = "empty" if not head else f"{len(head)} bytes" if len(head) < len(
                    MCAP_MAGIC) else "bad magic"
                raise BagError(f"{f}: not readable: not an MCAP file ({what}); no message can "
                               "be recovered from it")
            scan = mcapindex.McapScan(f)
            topic_of: dict[int, str] = {}
            for rec in scan:
                if isinstance(rec, Channel):
                    schema = scan.schemas.get(rec.schema_id)
                    types.setdefault(rec.topic, []).append(schema.name if schema else "")
                    topic_of[rec.id] = rec.topic
                else:
                    topic = topic_of.get(rec.channel_id)
                    if topic in wanted:
                        found[topic].append((rec.log_time, rec.data))
        except OSError as exc:
            raise BagError(f"{f}: cannot read: {exc.strerror or exc}") from exc
        total += scan.messages
        if scan.stopped:
            stops.append(scan.stopped)
    names = ", ".join(str(f) for f in files)
    if total == 0:
        why = f": {'; '.join(stops)}" if stops else ""
        raise BagError(f"{names}: nothing readable: no complete message in the recording{why}")
    _check_topics(path, topics, types)
    kept = ", ".join(f"{t}: {len(found[t])}" for t in topics)
    if not (path / METADATA_FILE).exists():
        what = f"{METADATA_FILE} is missing (the recording was not closed)"
    else:
        what = "the recording was not closed (no summary/footer)"
    where = f"; reading stopped at {'; '.join(stops)}" if stops else ""
    warnings.warn(RecordingWarning(
        f"{names}: {what}{where}; read up to its last complete chunk: {total} messages kept "
        f"({kept}); `{RECOVER_HINT} {path}` rewrites it as a complete bag"), stacklevel=4)
    out: dict[str, RawMessages] = {}
    for topic, msgs in found.items():
        order = sorted(range(len(msgs)), key=lambda i: msgs[i][0])  # stable: ties in file order
        out[topic] = raw_from_list([msgs[i][1] for i in order])
    return out, tuple(sorted(types))


def _read_raw(path: Path, topics: Sequence[str], salvage: bool
              ) -> tuple[dict[str, RawMessages], tuple[str, ...]]:
    """Raw messages of ``topics`` and every topic of the bag; with ``salvage`` a killed
    recording is read up to its last complete chunk (with a warning)."""
    files = _unfinished_mcaps(path) if salvage else None
    if files:
        return _salvage_collect(path, files, topics)
    reader = open_reader(path)
    try:
        present = tuple(sorted({c.topic for c in reader.connections}))
        return _collect(reader, path, topics), present
    finally:
        reader.close()


def _parse_at(path: Path, topic: str, raw: RawMessages, i: int) -> JointStateFields:
    try:
        return parse_joint_state(message_at(raw, i))
    except Exception as exc:
        raise BagError(f"{path}: topic {topic}: message {i} is not a valid "
                       f"{JOINT_STATE_TYPE}: {exc}") from exc


_SERIES_FIELDS = ("velocity", "effort", "position")  # order of the length checks


def _decode(path: Path, topic: str, raw: RawMessages) -> TopicSeries:
    """Decode the JointState messages of ``topic``.

    Messages with the byte length of message 0 and the same bytes outside the stamp and the
    float arrays (same frame_id, names, array lengths) are decoded in bulk; every other message
    by :func:`~dvt_model.recording.cdr.parse_joint_state`. Raises :class:`BagError` naming the
    message index and field for an undecodable message, changing names or a wrong array length.
    """
    n = int(raw.lengths.size)
    if n == 0:
        raise BagError(f"{path}: topic {topic} has no messages")
    first = message_at(raw, 0)
    msg0 = _parse_at(path, topic, raw, 0)
    names = msg0.names
    width = {"position": len(msg0.position), "velocity": len(msg0.velocity),
             "effort": len(msg0.effort)}
    stamps = np.empty(n, dtype=np.int64)
    values = {f: np.empty((n, k)) for f, k in width.items()}
    bulk = np.zeros(n, dtype=bool)
    try:
        layout: CdrLayout | None = cdr_layout(first)
    except (ValueError, struct.error, UnicodeDecodeError):
        layout = None  # message 0 needs rosbags: decode every message singly
    if layout is not None:
        size = len(first)
        cand = np.flatnonzero(raw.lengths == size)
        block = rows(raw.buf, raw.starts[cand], size)
        fixed = np.ones(size, dtype=bool)
        fixed[4:12] = False
        for off, count in layout.arrays:
            fixed[off:off + 8 * count] = False
        same = ~np.any((block != np.frombuffer(first, dtype=np.uint8)) & fixed, axis=1)
        cand, block = cand[same], block[same]
        bulk[cand] = True
        stamps[cand] = (view_as(block[:, 4:8], "<i4")[:, 0].astype(np.int64) * 1_000_000_000
                        + view_as(block[:, 8:12], "<u4")[:, 0])
        for fname, (off, count) in zip(("position", "velocity", "effort"), layout.arrays,
                                       strict=True):
            if count:
                values[fname][cand] = view_as(block[:, off:off + 8 * count], "<f8")
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
    return TopicSeries(stamps, names, **{f: values[f] if width[f] else None for f in FIELDS})


def read_topics(path: str | Path, topics: Sequence[str], *, salvage: bool = True
                ) -> dict[str, TopicSeries]:
    """Read every message of several ``sensor_msgs/msg/JointState`` topics in one pass.

    Returns topic -> :class:`TopicSeries` (recorded order). Other topics are ignored. No value
    checks beyond consistent names and array lengths: non-finite values and stamps that do not
    increase are returned as recorded. With ``salvage`` (the default) a killed recording (an
    unfinished MCAP file, or no ``metadata.yaml``) is read up to its last complete chunk with a
    :class:`~dvt_model.errors.RecordingWarning` naming the file, the messages kept and
    ``dvt-bag recover``; without, it is refused. Raises :class:`BagError` naming the bag, topic,
    message index and field (unreadable bag, nothing readable, missing topic, wrong type, no
    messages, undecodable message, changing names or array lengths).
    """
    path = Path(path)
    topics = list(dict.fromkeys(topics))
    raws, _ = _read_raw(path, topics, salvage)
    return {t: _decode(path, t, raws[t]) for t in topics}


def read_topic_series(path: str | Path, topic: str, *, salvage: bool = True) -> TopicSeries:
    """Read every message of a ``sensor_msgs/msg/JointState`` topic, in recorded order.

    Returns a :class:`TopicSeries`. No value checks beyond consistent names and array
    lengths; ``salvage`` as :func:`read_topics`.
    """
    return read_topics(path, [topic], salvage=salvage)[topic]


def _validate(path: Path, topic: str, series: TopicSeries, expected: tuple[str, ...],
              fname: str) -> Float2D:
    """Check names, the required field and stamps of one contract topic; return the field."""
    if series.names != expected:
        raise BagError(f"{path}: topic {topic}: field 'name' is {list(series.names)}, "
                       f"expected {list(expected)}")
    values = series.field_array(fname)
    if values is None:
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


def read_run(path: str | Path, *, salvage: bool = False) -> Run:
    """Read a contract recording and align ``/dvt/joint_states`` with ``/dvt/currents``.

    Samples are matched by identical ``header.stamp`` (the contract's rule:
    :func:`~dvt_model.recording.pairing.pair_stamps` with ``exact_only``); a stamp present in
    only one topic is dropped and counted in ``Run.unmatched``. Other topics are ignored.
    Raises :class:`BagError` (naming bag, topic, field) for an unreadable bag (also a killed
    recording, unless ``salvage``: then it is read up to its last complete chunk with a
    warning, as :func:`read_topics`), a missing topic, wrong names, wrong array lengths,
    non-finite values, non-increasing stamps or no common stamp.
    """
    path = Path(path)
    raws, topics = _read_raw(path, [JOINT_STATES, CURRENTS], salvage)
    js = _decode(path, JOINT_STATES, raws[JOINT_STATES])
    cu = _decode(path, CURRENTS, raws[CURRENTS])
    speeds = _validate(path, JOINT_STATES, js, SPEED_NAMES, "velocity")
    currents = _validate(path, CURRENTS, cu, CURRENT_NAMES, "effort")
    pairing = pair_stamps({JOINT_STATES: js.stamps_ns, CURRENTS: cu.stamps_ns}, JOINT_STATES,
                          where=str(path), exact_only=True)
    ia, ib = pairing.index[JOINT_STATES], pairing.index[CURRENTS]
    stamps = js.stamps_ns[ia].astype(np.int64)
    t = (stamps - stamps[0]).astype(np.float64) * 1e-9
    pos = js.position[ia] if js.position is not None else None
    return Run(path=path, stamps_ns=stamps, t=t, speeds=speeds[ia], currents=currents[ib],
               topics=topics, unmatched=sum(pairing.unmatched.values()),
               unmatched_by_topic=dict(pairing.unmatched),
               positions=pos if pos is not None and np.isfinite(pos).all() else None)


def sample_period(run: Run) -> float:
    """Median sample period [s] of ``run`` (``nan`` for fewer than two samples)."""
    if run.n < 2:
        return math.nan
    return float(np.median(np.diff(run.stamps_ns))) * 1e-9
