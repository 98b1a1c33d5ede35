"""What ``dvt-bag info`` prints: per-topic types, counts, rates and the duration (pure)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from rosbags.rosbag2 import Reader, ReaderError

from dvt_model.errors import RecordingError
from dvt_model.recording.layout import METADATA_FILE, NS, recover_hint


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
    """Summarise a readable bag directory (reads every message's log time, not its data).

    Raises :class:`~dvt_model.errors.RecordingError` naming the path (and ``dvt-bag recover``
    for a killed recording).
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such bag directory")
    if p.is_dir() and not (p / METADATA_FILE).exists():
        raise RecordingError(f"{p}: metadata.yaml is missing{recover_hint(p)}")
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
        raise RecordingError(f"{p}: cannot read bag: {exc}{recover_hint(p)}") from exc
    topics = [TopicSummary(tp, types[tp], counts[tp], first.get(tp), last.get(tp))
              for tp in sorted(types)]
    start = min(first.values(), default=0)
    end = max(last.values(), default=start)
    return BagSummary(p, topics, start, (end - start) / NS)
