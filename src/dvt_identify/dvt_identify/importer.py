"""``dvt-import``: turn NPZ or CSV columns into a rosbag2/MCAP bag of JointState messages.

A mapping says which column goes to which topic, joint and field. As YAML::

    time: t                              # column of time stamps [s], strictly increasing
    derivative: {cutoff_hz: 100.0, order: 4}   # for d(...): zero-phase Butterworth, then
                                               # central difference; cutoff null = raw
    signals:
      - {topic: /emps/joint_states, joint: carriage, field: position, expr: qm}
      - {topic: /emps/joint_states, joint: carriage, field: velocity, expr: "d(qm)"}
      - {topic: /emps/drive, joint: carriage, field: effort, expr: "vir * gtau"}

or on the command line: ``--time t --signal /emps/drive carriage effort "vir*gtau"`` (repeat).

Expressions: ``COLUMN`` or ``d(COLUMN)`` (time derivative), optionally followed by ``* FACTOR`` or
``/ FACTOR`` terms, where a factor is a number or a column (a scalar column such as ``gtau``, or
one of the same length). Every message of one sample carries the identical ``header.stamp``
(``round(t * 1e9)`` ns plus ``--start-time``), so the identifier aligns topics exactly.

The derivative: the column is low-pass filtered forward and backward (zero phase, so no delay)
by a Butterworth filter of the given order and cutoff, then differentiated by central differences
(one-sided at the two ends, ``numpy.gradient`` on the time column).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from dvt_identify.data import FIELDS, JointStateSeries, write_jointstate_bag
from dvt_identify.errors import DvtIdentifyError, ImportDataError

Array = NDArray[np.float64]
_EXPR = re.compile(r"^\s*(d\(\s*([A-Za-z_][\w.]*)\s*\)|([A-Za-z_][\w.]*))\s*((?:[*/]\s*[^*/]+)*)$")


@dataclass(frozen=True)
class SignalMap:
    """One mapped signal: ``expr`` evaluated from columns lands in ``topic``/``joint``/``field``."""

    topic: str
    joint: str
    field: str
    expr: str


@dataclass(frozen=True)
class ImportMapping:
    """A full mapping (see module docstring)."""

    time: str
    signals: tuple[SignalMap, ...]
    cutoff_hz: float | None = None
    order: int = 4


def load_columns(path: str | Path) -> dict[str, Array]:
    """Columns of an ``.npz`` (arrays; 0-d arrays are scalars) or a ``.csv`` with a header row.

    Raises:
        ImportDataError: unreadable file, unknown format, non-numeric CSV cell.
    """
    p = Path(path)
    if not p.is_file():
        raise ImportDataError(f"{p}: file not found")
    if p.suffix.lower() == ".npz":
        try:
            with np.load(p, allow_pickle=False) as d:
                return {k: np.asarray(d[k], dtype=float) for k in d.files}
        except (OSError, ValueError) as exc:
            raise ImportDataError(f"{p}: cannot read NPZ: {exc}") from exc
    if p.suffix.lower() == ".csv":
        with p.open(newline="") as fh:
            rows = list(csv.reader(fh))
        if len(rows) < 2:
            raise ImportDataError(f"{p}: expected a header row and data rows")
        header = [h.strip() for h in rows[0]]
        data = np.empty((len(rows) - 1, len(header)))
        for i, row in enumerate(rows[1:], start=2):
            if len(row) != len(header):
                raise ImportDataError(f"{p}: line {i}: {len(row)} cells, header has "
                                      f"{len(header)}")
            for j, cell in enumerate(row):
                try:
                    data[i - 2, j] = float(cell)
                except ValueError:
                    raise ImportDataError(f"{p}: line {i}, column {header[j]}: not a number: "
                                          f"{cell!r}") from None
        return {h: data[:, j] for j, h in enumerate(header)}
    raise ImportDataError(f"{p}: unknown format {p.suffix!r} (expected .npz or .csv)")


def _column(cols: Mapping[str, Array], name: str, src: str, n: int | None) -> Array:
    if name not in cols:
        raise ImportDataError(f"{src}: column {name!r} not found (columns: "
                              f"{', '.join(sorted(cols))})")
    c = np.asarray(cols[name], dtype=float)
    if c.ndim > 1:
        raise ImportDataError(f"{src}: column {name!r}: expected 1-D, got shape {c.shape}")
    bad = ~np.isfinite(c)
    if np.any(bad):
        i = int(np.argmax(bad.ravel()))
        raise ImportDataError(f"{src}: column {name!r}: value {c.ravel()[i]} at row {i} "
                              f"({int(bad.sum())} non-finite values)")
    if n is not None and c.ndim == 1 and c.size != n:
        raise ImportDataError(f"{src}: column {name!r}: length {c.size}, time column has {n}")
    return c


def derivative(x: ArrayLike, t: ArrayLike, cutoff_hz: float | None, order: int = 4) -> Array:
    """Zero-phase Butterworth low-pass (if ``cutoff_hz``) then central difference on ``t``.

    Args:
        x: signal, shape (N,).
        t: time [s], shape (N,), strictly increasing.
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    if cutoff_hz is not None:
        fs = 1.0 / float(np.median(np.diff(t)))
        if not 0.0 < cutoff_hz < fs / 2:
            raise ImportDataError(f"derivative cutoff {cutoff_hz} Hz not in (0, {fs / 2:g}) Hz")
        sos = signal.butter(order, cutoff_hz, fs=fs, output="sos")
        x = signal.sosfiltfilt(sos, x)
    return np.asarray(np.gradient(x, t))


def evaluate(expr: str, cols: Mapping[str, Array], t: Array, mapping: ImportMapping,
             src: str) -> Array:
    """Value of ``expr`` (see module docstring), shape (N,)."""
    m = _EXPR.match(expr)
    if m is None:
        raise ImportDataError(f"{src}: expression {expr!r}: expected COLUMN or d(COLUMN) "
                              "followed by '* FACTOR' / '/ FACTOR' terms")
    n = t.size
    if m.group(2):
        x = derivative(_column(cols, m.group(2), src, n), t, mapping.cutoff_hz, mapping.order)
    else:
        x = _column(cols, m.group(3), src, n).copy()
    for op, term in re.findall(r"([*/])\s*([^*/]+)", m.group(4) or ""):
        term = term.strip()
        try:
            f: Array | float = float(term)
        except ValueError:
            fc = _column(cols, term, src, None)
            if fc.ndim == 1 and fc.size not in (1, n):
                raise ImportDataError(f"{src}: column {term!r}: length {fc.size}, expected 1 or "
                                      f"{n}") from None
            f = float(fc.ravel()[0]) if fc.size == 1 else fc
        if op == "*":
            x = x * f
        else:
            if np.any(np.asarray(f) == 0):
                raise ImportDataError(f"{src}: expression {expr!r}: division by zero ({term})")
            x = x / f
    return np.asarray(x, dtype=float)


def parse_mapping(data: Any, source: str) -> ImportMapping:
    """A :class:`ImportMapping` from parsed YAML; errors name ``source`` and the key."""
    if not isinstance(data, dict):
        raise ImportDataError(f"{source}: expected a mapping")
    if "time" not in data:
        raise ImportDataError(f"{source}: missing key 'time'")
    sigs = data.get("signals")
    if not isinstance(sigs, list) or not sigs:
        raise ImportDataError(f"{source}: 'signals' must be a non-empty list")
    out = []
    for i, s in enumerate(sigs):
        if not isinstance(s, dict):
            raise ImportDataError(f"{source}: signals[{i}]: expected a mapping")
        for k in ("topic", "joint", "field", "expr"):
            if k not in s:
                raise ImportDataError(f"{source}: signals[{i}]: missing key {k!r}")
        out.append(SignalMap(str(s["topic"]), str(s["joint"]), str(s["field"]), str(s["expr"])))
    der = data.get("derivative") or {}
    cutoff = der.get("cutoff_hz")
    return ImportMapping(time=str(data["time"]), signals=tuple(out),
                    cutoff_hz=None if cutoff is None else float(cutoff),
                    order=int(der.get("order", 4)))


def build_topics(cols: Mapping[str, Array], mapping: ImportMapping, src: str,
                 start_time: float = 0.0) -> dict[str, JointStateSeries]:
    """Evaluate the mapping into JointState series (one per topic).

    Raises:
        ImportDataError: missing column, NaN, time not strictly increasing, bad field, a field
            given for some joints of a topic but not for others.
    """
    t = _column(cols, mapping.time, src, None)
    if t.ndim != 1 or t.size < 2:
        raise ImportDataError(f"{src}: time column {mapping.time!r}: need at least 2 samples")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise ImportDataError(f"{src}: time column {mapping.time!r} not strictly increasing at "
                              f"row {i + 1} ({t[i]!r} -> {t[i + 1]!r})")
    stamps = np.round((t - t[0] + start_time) * 1e9).astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise ImportDataError(f"{src}: time column {mapping.time!r}: steps below 1 ns")
    by_topic: dict[str, dict[str, dict[str, Array]]] = {}
    for s in mapping.signals:
        if s.field not in FIELDS:
            raise ImportDataError(f"{src}: signal {s.topic} {s.joint}: field {s.field!r} not one "
                                  f"of {', '.join(FIELDS)}")
        joints = by_topic.setdefault(s.topic, {})
        fields = joints.setdefault(s.joint, {})
        if s.field in fields:
            raise ImportDataError(f"{src}: {s.topic} {s.joint} {s.field} mapped twice")
        fields[s.field] = evaluate(s.expr, cols, t, mapping, src)
    out: dict[str, JointStateSeries] = {}
    for topic, joints in by_topic.items():
        names = tuple(joints)
        arrays: dict[str, Array | None] = {}
        for f in FIELDS:
            have = [j for j in names if f in joints[j]]
            if have and len(have) != len(names):
                missing = [j for j in names if j not in have]
                raise ImportDataError(f"{src}: topic {topic}: field {f} given for "
                                      f"{', '.join(have)} but not for {', '.join(missing)}")
            arrays[f] = np.column_stack([joints[j][f] for j in names]) if have else None
        out[topic] = JointStateSeries(stamps_ns=stamps, names=names, **arrays)
    return out


def import_columns(source: str | Path, out: str | Path, mapping: ImportMapping,
                   start_time: float = 0.0, overwrite: bool = False) -> Path:
    """Read ``source``, evaluate ``mapping`` and write the bag ``out``; returns its path."""
    cols = load_columns(source)
    topics = build_topics(cols, mapping, str(source), start_time)
    return write_jointstate_bag(out, topics, overwrite=overwrite)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``dvt-import``; returns the exit status."""
    ap = argparse.ArgumentParser(
        prog="dvt-import",
        description="Convert NPZ/CSV columns into a rosbag2 (MCAP) bag of JointState messages.")
    ap.add_argument("source", help="input file (.npz or .csv)")
    ap.add_argument("--out", required=True, help="output bag directory (must not exist)")
    ap.add_argument("--mapping", help="YAML mapping file (see docs)")
    ap.add_argument("--time", help="time column [s] (overrides the mapping's)")
    ap.add_argument("--signal", nargs=4, action="append", default=[],
                    metavar=("TOPIC", "JOINT", "FIELD", "EXPR"),
                    help="map EXPR to TOPIC JOINT FIELD (repeatable; added to the mapping)")
    ap.add_argument("--derivative-cutoff", type=float, default=None,
                    help="cutoff [Hz] of the zero-phase Butterworth before d(...); "
                         "default: the mapping's, else raw central difference")
    ap.add_argument("--derivative-order", type=int, default=None, help="filter order (4)")
    ap.add_argument("--start-time", type=float, default=0.0,
                    help="stamp of the first sample [s] (default 0)")
    ap.add_argument("--force", action="store_true", help="replace an existing output bag")
    args = ap.parse_args(argv)
    try:
        data: dict[str, Any] = {}
        if args.mapping:
            mp = Path(args.mapping)
            if not mp.is_file():
                raise ImportDataError(f"{mp}: mapping file not found")
            try:
                data = yaml.safe_load(mp.read_text()) or {}
            except yaml.YAMLError as exc:
                raise ImportDataError(f"{mp}: not valid YAML: {exc}") from exc
            if not isinstance(data, dict):
                raise ImportDataError(f"{mp}: expected a mapping")
        if args.time:
            data["time"] = args.time
        sigs = list(data.get("signals") or [])
        sigs += [{"topic": s[0], "joint": s[1], "field": s[2], "expr": s[3]}
                 for s in args.signal]
        data["signals"] = sigs
        der = dict(data.get("derivative") or {})
        if args.derivative_cutoff is not None:
            der["cutoff_hz"] = args.derivative_cutoff
        if args.derivative_order is not None:
            der["order"] = args.derivative_order
        data["derivative"] = der
        mapping = parse_mapping(data, args.mapping or "command line")
        path = import_columns(args.source, args.out, mapping, args.start_time, args.force)
    except DvtIdentifyError as exc:
        print(f"dvt-import: error: {exc}", file=sys.stderr)
        return 2
    print(f"dvt-import: wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
