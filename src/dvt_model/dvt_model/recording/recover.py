"""Rebuild a readable bag from a killed recording; tell whether a bag is readable (pure).

A recording that was killed has no ``metadata.yaml`` and an MCAP file without summary/footer.
:func:`recover` (``dvt-bag recover PATH``) reads every complete chunk sequentially with
:class:`~dvt_model.recording.mcapindex.McapScan` (``mcap``'s stream reader; the reader uses the
same scan to read such a file directly, with a warning) and rewrites a proper bag through the
one writer (:class:`~dvt_model.recording.write.BagRecorder`). On a terminal it shows how far it
has read (:class:`~dvt_model.progress.ProgressLine` on stderr; nothing when stderr is not a
terminal).
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.records import Channel, Schema
from rosbags.rosbag2 import Reader, ReaderError

from dvt_model.errors import RecordingError
from dvt_model.presets import safe_load
from dvt_model.progress import ProgressLine
from dvt_model.recording.layout import MCAP_MAGIC, METADATA_FILE
from dvt_model.recording.mcapindex import McapScan
from dvt_model.recording.write import BagRecorder, fsync_dir


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
        raise RecordingError(f"{path}: no such file or directory")
    if path.is_file():
        if path.suffix != ".mcap":
            raise RecordingError(f"{path}: expected a bag directory or an .mcap file")
        return path.parent, [path]
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise RecordingError(f"{path}: no .mcap file in this directory")
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


PROGRESS_EVERY = 2000
"""Messages between two progress updates of :func:`recover` (each update is throttled too)."""


def _salvage(src: Path, out: BagRecorder, result: RecoverResult,
             progress: ProgressLine | None = None) -> None:
    """Copy every complete record of ``src`` into ``out`` (:class:`McapScan`, the one salvage
    scanner); note why reading stopped; show how far it has read on ``progress``."""
    added: dict[int, str] = {}
    scan = McapScan(src)
    size = max(src.stat().st_size, 1)
    n = 0
    for rec in scan:
        if isinstance(rec, Channel):
            _add_channel(out, rec, scan.schemas, added)
            continue
        topic = added.get(rec.channel_id)
        if topic is None:
            result.skipped += 1
            continue
        out.write(topic, rec.data, rec.log_time)
        n += 1
        if progress is not None and n % PROGRESS_EVERY == 0:
            progress.update(f"{src.name}: read {100 * min(scan.offset / size, 1.0):.0f} % "
                            f"of {size / 1e6:.3g} MB, {n} messages")
    if scan.stopped:
        result.stopped = scan.stopped


def _add_channel(out: BagRecorder, ch: Channel, schemas: Mapping[int, Schema],
                 added: dict[int, str]) -> None:
    schema = schemas.get(ch.schema_id)
    if schema is None or ch.message_encoding != "cdr":
        return
    try:
        qos = safe_load(ch.metadata.get("offered_qos_profiles", "") or "[]")
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


def recover(path: str | Path, out: str | Path | None = None, *, force: bool = False,
            progress: ProgressLine | None = None) -> RecoverResult:
    """Rebuild a readable rosbag2 directory from a killed recording.

    Reads every complete chunk/record of the ``.mcap`` file(s) in ``path`` (a bag directory or
    one ``.mcap`` file) sequentially, without the (missing) summary, and writes a proper bag:

    * ``out`` given: a new bag directory ``out`` (must not exist); sidecar files such as
      ``truth.yaml`` are copied;
    * in place otherwise: each broken ``X.mcap`` is renamed ``X.mcap.broken`` (a stale
      ``metadata.yaml`` ``metadata.yaml.broken``) and the rebuilt ``X.mcap`` plus
      ``metadata.yaml`` take their place.

    A bag that is already readable is left alone (``already_readable``) unless ``force``.
    ``progress``: where to show how far it has read (default: a
    :class:`~dvt_model.progress.ProgressLine` on stderr, silent unless stderr is a terminal);
    the line is cleared before returning.
    Raises :class:`~dvt_model.errors.RecordingError` for a missing path, no ``.mcap`` file, a
    file that is not MCAP/rosbag2, or an existing ``out``.
    """
    src = Path(path)
    bagdir, files = _bag_files(src)
    if not force and src.is_dir() and out is None and is_readable(src):
        return RecoverResult(output=src, already_readable=True)
    line = progress if progress is not None else ProgressLine.stderr("dvt-bag recover: ")
    try:
        return _recover(bagdir, files, out, line)
    finally:
        line.close()


def _recover(bagdir: Path, files: list[Path], out: str | Path | None, line: ProgressLine
             ) -> RecoverResult:
    """:func:`recover` after the checks that need no reading."""
    for f in files:
        with f.open("rb") as fh:
            if fh.read(8) != MCAP_MAGIC:
                raise RecordingError(f"{f}: not an MCAP file (bad magic)")
    if out is not None:
        target = Path(out)
        if target.exists():
            raise RecordingError(f"{target} exists already; choose a new --out directory")
        result = RecoverResult(output=target)
        try:
            with BagRecorder(target, fsync=True, flush_period=math.inf) as rec:
                for f in files:
                    _salvage(f, rec, result, line)
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
        for side in bagdir.iterdir():
            if side.is_file() and side.suffix in (".yaml", ".json") \
                    and side.name != METADATA_FILE and not side.name.endswith(".tmp"):
                shutil.copy2(side, target / side.name)
        result.counts = dict(rec.stats)
        return result

    result = RecoverResult(output=bagdir)
    tmpdir = bagdir / ".dvt-recover.tmp"
    if tmpdir.exists():
        shutil.rmtree(tmpdir)
    name = files[0].name
    try:
        with BagRecorder(tmpdir, fsync=True, flush_period=math.inf, file_name=name) as rec:
            for f in files:
                _salvage(f, rec, result, line)
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
    fsync_dir(bagdir)
    result.counts = dict(rec.stats)
    return result
