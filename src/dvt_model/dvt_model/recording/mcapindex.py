"""MCAP files read without ``rosbags``: the fast indexed reader and the sequential salvage scan.

* :func:`mcap_collect` - raw messages of chosen channels of an indexed (finished) MCAP file
  without a per-message loop. Uses the summary section (channels, chunk indexes, statistics) and
  each chunk's message index records, with ``numpy`` on the decompressed chunk records
  (``rosbags``' chunk decompression and checksum check). Every record found is checked (opcode,
  channel, bounds) and the counts must equal the statistics; anything unexpected raises
  :class:`McapFastPathError` and the caller reads the bag with the ``rosbags`` message iterator
  instead.
* :class:`McapScan` - every complete record of a possibly unfinished MCAP file (a killed
  recording: no summary/footer, last chunk cut), in file order; the one salvage scanner, used by
  :func:`~dvt_model.recording.recover.recover` and by the reader
  (:func:`~dvt_model.recording.read.read_topics`).

Pure module.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Footer, Header, Message, Schema
from mcap.stream_reader import StreamReader
from numpy.typing import NDArray
from rosbags.rosbag2 import ReaderError

from dvt_model.errors import BagError, RecordingError
from dvt_model.recording.cdr import UNPACK_U32
from dvt_model.recording.layout import MCAP_MAGIC
from dvt_model.recording.sidecar import read_metadata

Int1D = NDArray[np.int64]


class RawMessages(NamedTuple):
    """Raw CDR messages of one topic in recorded order.

    Message ``i`` is ``buf[starts[i]:starts[i] + lengths[i]]``; ``buf`` (B,) uint8, ``starts``
    and ``lengths`` (N,) int64.
    """

    buf: NDArray[np.uint8]
    starts: Int1D
    lengths: Int1D


def raw_from_list(raws: Sequence[bytes]) -> RawMessages:
    """:class:`RawMessages` of a list of byte strings."""
    lengths = np.fromiter(map(len, raws), dtype=np.int64, count=len(raws))
    starts = np.zeros_like(lengths)
    np.cumsum(lengths[:-1], out=starts[1:])
    return RawMessages(np.frombuffer(b"".join(raws), dtype=np.uint8), starts, lengths)


def message_at(raw: RawMessages, i: int) -> bytes:
    """The bytes of message ``i``."""
    s = int(raw.starts[i])
    return raw.buf[s:s + int(raw.lengths[i])].tobytes()


def rows(buf: NDArray[np.uint8], starts: Int1D, width: int) -> NDArray[np.uint8]:
    """(len(starts), width) copy of the bytes ``buf[s:s + width]`` for every ``s`` in ``starts``."""
    if starts.size == 0:
        return np.zeros((0, width), dtype=np.uint8)
    windows = np.lib.stride_tricks.sliding_window_view(buf, width)
    return np.asarray(windows[starts])


def view_as(rows: NDArray[np.uint8], dtype: str) -> NDArray[Any]:
    """Reinterpret each row of ``rows`` (n, k * itemsize) bytes as k values of ``dtype``."""
    return np.ascontiguousarray(rows).view(dtype)


class McapFastPathError(Exception):
    """The MCAP fast path does not apply (no summary or index, odd record); rosbags reads."""


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
    (n,) = UNPACK_U32(buf, pos)
    return buf[pos + 4:pos + 4 + n].decode(), pos + 4 + n


def _mcap_summary(fh: BinaryIO) -> _McapSummary:
    """Channels, chunk indexes and message counts from the summary section of an MCAP file."""
    size = fh.seek(0, 2)
    if size < 45:
        raise McapFastPathError("file too short")
    fh.seek(size - 37)
    tail = fh.read(37)
    if tail[-8:] != MCAP_MAGIC or tail[0] != 0x02:
        raise McapFastPathError("no footer")
    summary_start, offsets_start = struct.unpack_from("<QQ", tail, 9)
    if summary_start == 0:
        raise McapFastPathError("no summary")
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
            (maplen,) = UNPACK_U32(blob, body + 32)
            idx = dict(struct.iter_unpack("<HQ", blob[body + 36:body + 36 + maplen]))
            (index_length,) = _UNPACK_Q(blob, body + 36 + maplen)
            chunks.append(_McapChunk(start, length, idx, index_length))
        elif op == 0x0B:  # statistics: ..., channel message counts
            (maplen,) = UNPACK_U32(blob, body + 42)
            counts = dict(struct.iter_unpack("<HQ", blob[body + 46:body + 46 + maplen]))
    if counts is None or not chunks:
        raise McapFastPathError("no statistics or no chunk index")
    return _McapSummary(topics, chunks, counts)


def mcap_collect(files: Sequence[Path], topics: Sequence[str]) -> dict[str, RawMessages]:
    """Raw messages of ``topics`` from indexed MCAP ``files`` without a per-message loop.

    Uses the summary (chunk indexes, statistics) and each chunk's message index; every record
    found is checked (opcode, channel, bounds) and the counts must equal the statistics, else
    :class:`McapFastPathError` is raised and the caller reads with rosbags instead. Messages
    come in log-time order, ties in file order (as rosbags returns them).
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
                    raise McapFastPathError("bad chunk record")
                usize, crc, clen = struct.unpack_from("<QII", blob, 25)
                compression = blob[41:41 + clen].decode()
                (rlen,) = _UNPACK_Q(blob, 41 + clen)
                rstart = 49 + clen
                if rstart + rlen > chunk.length:
                    raise McapFastPathError("chunk records exceed the chunk")
                data = blob[rstart:rstart + rlen]
                try:
                    records = np.frombuffer(decompress(data, compression, usize, crc),
                                            dtype=np.uint8)
                except ReaderError as exc:
                    raise McapFastPathError(str(exc)) from exc
                for cid in ids:
                    ipos = chunk.index_offsets[cid] - chunk.start
                    if not 0 <= ipos <= len(blob) - 15 or blob[ipos] != 0x07 or \
                            _UNPACK_H(blob, ipos + 9)[0] != cid:
                        raise McapFastPathError("bad message index")
                    (ilen,) = UNPACK_U32(blob, ipos + 11)
                    if ilen % 16 or ipos + 15 + ilen > len(blob):
                        raise McapFastPathError("bad message index length")
                    entries = np.frombuffer(blob, dtype="<u8", count=ilen // 8,
                                            offset=ipos + 15).reshape(-1, 2)
                    offs = entries[:, 1].astype(np.int64)
                    if offs.size and (offs.min() < 0 or offs.max() + 31 > records.size):
                        raise McapFastPathError("message index offset out of range")
                    head = rows(records, offs, 31)  # opcode, length, channel, seq, times
                    reclen = view_as(head[:, 1:9], "<u8")[:, 0].astype(np.int64)
                    if (np.any(head[:, 0] != 0x05)
                            or np.any(view_as(head[:, 9:11], "<u2") != cid)
                            or np.any(reclen < 22) or np.any(offs + 9 + reclen > records.size)):
                        raise McapFastPathError("message index does not point at messages")
                    log_time = view_as(head[:, 15:23], "<u8")[:, 0].astype(np.int64)
                    found[wanted[cid]].append((log_time, base + offs + 31, reclen - 22))
                    seen[cid] += offs.size
                pieces.append(records)
                base += records.size
            if any(seen[cid] != summary.counts.get(cid, 0) for cid in wanted):
                raise McapFastPathError("message indexes disagree with the statistics")
    buf = np.concatenate(pieces) if pieces else np.zeros(0, dtype=np.uint8)
    out: dict[str, RawMessages] = {}
    for topic, parts in found.items():
        if not parts:
            out[topic] = RawMessages(buf, np.zeros(0, np.int64), np.zeros(0, np.int64))
            continue
        log_time, starts, lengths = (np.concatenate(x) for x in zip(*parts, strict=True))
        order = np.lexsort((starts, log_time))  # log time, ties in file order (as rosbags)
        out[topic] = RawMessages(buf, starts[order], lengths[order])
    return out


def mcap_files(path: Path) -> list[Path] | None:
    """The MCAP files of a bag directory (``None``: other storage, or compressed files)."""
    try:
        meta = read_metadata(path)
        if meta.get("storage_identifier") != "mcap" or \
                str(meta.get("compression_mode") or "").lower() not in ("", "none"):
            return None
        return [path / Path(str(x)).name for x in meta["relative_file_paths"]]
    except (BagError, KeyError, TypeError):
        return None


def mcap_finished(path: Path) -> bool:
    """Whether the MCAP file ``path`` ends with the closing magic (its writer finished it).

    A missing or unreadable file counts as finished (the caller's reader reports it).
    """
    try:
        with path.open("rb") as fh:
            size = fh.seek(0, 2)
            if size < 2 * len(MCAP_MAGIC):
                return False
            fh.seek(size - len(MCAP_MAGIC))
            return fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return True


class McapScan:
    """Sequential scan of every complete record of one MCAP file, without its summary.

    Iterating yields, in file order, the :class:`~mcap.records.Channel` and
    :class:`~mcap.records.Message` records of every complete record and chunk (chunk checksums
    are checked); schemas and channels seen are kept in :attr:`schemas` and :attr:`channels`.
    A truncated or corrupt record ends the scan without an exception: :attr:`stopped` then says
    why and where (``""`` when the file ended cleanly with its footer, :attr:`finished`).

    Raises:
        RecordingError: the file is not a ``ros2`` profile MCAP file (names the file).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.messages = 0
        self.stopped = ""
        self.finished = False
        self.offset = 0  # end of the last complete record read [bytes]

    def __iter__(self) -> Iterator[Channel | Message]:
        with self.path.open("rb") as fh:
            records = StreamReader(fh, validate_crcs=True, record_size_limit=1 << 31).records
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    return
                except Exception as exc:
                    # A truncated last record (EndOfFile, short struct) is the normal end of a
                    # killed recording; anything else is reported as it is.
                    size = fh.seek(0, 2)
                    if isinstance(exc, EndOfFile | struct.error):
                        self.stopped = (f"{self.path.name}: truncated record after offset "
                                        f"{self.offset} (file size {size} bytes)")
                    else:
                        self.stopped = (f"{self.path.name}: {type(exc).__name__}: {exc} after "
                                        f"offset {self.offset} (file size {size} bytes)")
                    return
                self.offset = fh.tell()  # end of the last complete record (or chunk)
                if isinstance(rec, Header):
                    if rec.profile != "ros2":
                        raise RecordingError(f"{self.path}: MCAP profile is {rec.profile!r}, "
                                             "expected 'ros2' (not a rosbag2 recording)")
                elif isinstance(rec, Schema):
                    self.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                    yield rec
                elif isinstance(rec, Message):
                    self.messages += 1
                    yield rec
                elif isinstance(rec, Footer):
                    self.finished = True
