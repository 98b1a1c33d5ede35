"""Any topic of a recording as raw messages in log-time order (pure).

:func:`read_topics` and :func:`read_run` (:mod:`~dvt_model.recording.read`) decode JointState
topics in bulk; what needs the messages themselves (a replay publishes the raw CDR, a benchmark
times the reception of each sample, the launcher finds the first command) reads them here:
:class:`BagMessages` opens a bag (errors as :func:`~dvt_model.recording.read.open_reader`'s),
tells its topics and types and iterates :class:`BagMessage` records; :func:`decode` turns one into
a message object (the one type store), :func:`first_log_time` is the log time of the first
message on matching topics.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

from dvt_model.errors import BagError
from dvt_model.recording.cdr import typestore
from dvt_model.recording.read import open_reader

__all__ = ["BagMessage", "BagMessages", "decode", "first_log_time"]


class BagMessage(NamedTuple):
    """One recorded message: ``topic``, ``msgtype`` (e.g. ``std_msgs/msg/String``),
    ``log_time_ns`` (when the recorder received it) [ns] and ``data`` (its serialised CDR)."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes


class BagMessages:
    """An open bag read as raw messages (a context manager; :meth:`close` when done).

    Raises:
        BagError: the bag cannot be opened (names the path; a killed recording names
            ``dvt-bag recover``).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader = open_reader(self.path)

    @property
    def types(self) -> dict[str, str]:
        """Topic -> message type of every topic in the bag."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    def messages(self, topics: Iterable[str] | None = None, *, pattern: str | None = None
                 ) -> Iterator[BagMessage]:
        """The messages on ``topics`` (``None``: every topic) whose topic also matches the
        shell ``pattern`` (``None``: any), in log-time order.

        Raises:
            BagError: a topic in ``topics`` is not in the bag, or the storage cannot be read
                (names the bag and the topics).
        """
        wanted = None if topics is None else list(dict.fromkeys(topics))
        if wanted is not None:
            missing = sorted(set(wanted) - set(self.types))
            if missing:
                raise BagError(f"{self.path}: topic(s) {missing} not in the bag (topics "
                               f"present: {sorted(self.types)})")
        conns = [c for c in self._reader.connections
                 if (wanted is None or c.topic in wanted)
                 and (pattern is None or fnmatch.fnmatchcase(c.topic, pattern))]
        if not conns:
            return
        try:
            for conn, log_time, raw in self._reader.messages(connections=conns):
                yield BagMessage(conn.topic, conn.msgtype, int(log_time), bytes(raw))
        except Exception as exc:  # ReaderError, or a decompressor's error on corrupt storage
            which = ", ".join(sorted({c.topic for c in conns}))
            raise BagError(f"{self.path}: {which}: cannot read messages: {exc}") from exc

    def close(self) -> None:
        """Close the bag."""
        self._reader.close()

    def __enter__(self) -> BagMessages:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def decode(msg: BagMessage) -> Any:
    """The message object (``rosbags``, ROS 2 Jazzy types) of a recorded message.

    Raises:
        BagError: the type is unknown or the bytes do not decode (names the topic).
    """
    try:
        return typestore().deserialize_cdr(msg.data, msg.msgtype)
    except Exception as exc:
        raise BagError(f"topic {msg.topic}: message at log time {msg.log_time_ns} ns is not a "
                       f"valid {msg.msgtype}: {exc}") from exc


def first_log_time(path: str | Path, pattern: str) -> int | None:
    """Log time [ns] of the first message on a topic matching the shell ``pattern`` (e.g.
    ``/dvt/cmd/*``), ``None`` if the bag has none.

    Raises:
        BagError: the bag or its messages cannot be read.
    """
    with BagMessages(path) as bag:
        for msg in bag.messages(pattern=pattern):
            return msg.log_time_ns
    return None
