"""``dvt-import``: turn NPZ, MATLAB or CSV columns into a rosbag2/MCAP bag of JointState messages.

A mapping says which column goes to which topic, joint and field. As YAML::

    time: t                              # column of time stamps [s], strictly increasing
    # dt: 0.001                          # ... or a fixed sample period [s] (no time column)
    range: [0, 20000]                    # optional: samples [start, stop) to keep
    derivative: {cutoff_hz: 100.0, order: 4}   # for d(...): zero-phase Butterworth, then
                                               # central difference; cutoff null = raw
    signals:
      - {topic: /emps/joint_states, joint: carriage, field: position, expr: qm}
      - {topic: /emps/joint_states, joint: carriage, field: velocity, expr: "d(qm)"}
      - {topic: /emps/drive, joint: carriage, field: effort, expr: "vir * gtau"}

or on the command line: ``--time t --signal /emps/drive carriage effort "vir*gtau"`` (repeat),
``--dt 0.001`` instead of ``--time`` for a file without a time column, ``--range 100:20100``.
``dvt-import FILE --list`` shows the columns a file has (name, length, range; a strictly
increasing one is flagged as a time column) and writes nothing.

Expressions: ``COLUMN``, ``d(COLUMN)`` (time derivative) or ``dN(COLUMN)`` (the N-th derivative,
e.g. ``d2(qm)`` for an acceleration), optionally followed by ``* FACTOR`` or
``/ FACTOR`` terms, where a factor is a number or a column (a scalar column such as ``gtau``, or
one of the same length). Every message of one sample carries the identical ``header.stamp``
(``round(t * 1e9)`` ns plus ``--start-time``), so the identifier aligns topics exactly.

The derivative: the column is low-pass filtered forward and backward (zero phase, so no delay)
by a Butterworth filter of the given order and cutoff, then differentiated N times by central
differences (one-sided at the two ends, ``numpy.gradient`` on the time column). Derivatives are
taken on the whole record before a ``range`` is cut out, so the cut has no end effects.

CSV files: a header row, then numbers. Empty trailing cells (lines ending in a comma, as many
loggers write them) and columns with an empty header and no values are ignored.

NPZ and MATLAB files (``.mat``: v5/v7 as MATLAB's ``save`` writes by default, read by
``scipy.io.loadmat``; v7.3, MATLAB's HDF5 format for large variables, read by ``h5py``): every
real numeric variable is a column. A vector of either orientation (MATLAB's ``N x 1`` or
``1 x N``) is one column of its name, a ``1 x 1`` a scalar; a matrix is one column per channel,
named ``NAME.1`` ... ``NAME.K`` (MATLAB's ``NAME(:, 1)`` ...; the samples run along its longer
side); a struct's fields are ``NAME.FIELD`` (nested alike). Text, cell arrays, objects, complex,
empty and higher-dimensional arrays are not columns (an error naming a missing column lists
those that are).
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

from dvt_identify.data import write_jointstate_bag
from dvt_identify.errors import DvtIdentifyError, ImportDataError
from dvt_model.presets import safe_load
from dvt_model.recording import FIELDS, TopicSeries

Array = NDArray[np.float64]
_EXPR = re.compile(r"^\s*(d(\d*)\(\s*([A-Za-z_][\w.]*)\s*\)|([A-Za-z_][\w.]*))\s*"
                   r"((?:[*/]\s*[^*/]+)*)$")
MAX_DERIVATIVE = 4
"""Highest derivative order an expression may ask for (noise grows with every order)."""


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

    time: str | None
    signals: tuple[SignalMap, ...]
    cutoff_hz: float | None = None
    order: int = 4
    dt: float | None = None
    """Sample period [s] when there is no time column (exactly one of ``time`` and ``dt``)."""
    sample_range: tuple[int, int | None] | None = None
    """Samples ``[start, stop)`` to keep (``stop`` None: to the end)."""


def load_columns(path: str | Path) -> dict[str, Array]:
    """Columns of an ``.npz``, a MATLAB ``.mat`` or a ``.csv`` with a header row (see the module
    docstring); each 1-D [samples] or 0-d (a scalar).

    Raises:
        ImportDataError: unreadable file, unknown format, non-numeric CSV cell.
    """
    p = Path(path)
    if not p.is_file():
        raise ImportDataError(f"{p}: file not found")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(p, allow_pickle=False) as d:
                return _numeric_columns({k: d[k] for k in d.files})
        except (OSError, ValueError) as exc:
            raise ImportDataError(f"{p}: cannot read NPZ: {exc}") from exc
    if suffix == ".mat":
        return _numeric_columns(_mat_variables(p))
    if suffix == ".csv":
        with p.open(newline="") as fh:
            rows = list(csv.reader(fh))
        if len(rows) < 2:
            raise ImportDataError(f"{p}: expected a header row and data rows")
        return _csv_columns(p, rows)
    raise ImportDataError(f"{p}: unknown format {p.suffix!r} (expected .npz, .mat or .csv)")


def describe_columns(cols: Mapping[str, Array]) -> list[str]:
    """One line per column of :func:`load_columns` (``dvt-import FILE --list``): its name, then
    a scalar's value, or a column's length, range and, when it strictly increases (a time
    column), its mean step."""
    width = max((len(k) for k in cols), default=0)
    lines = []
    for name in sorted(cols):
        c = np.asarray(cols[name], dtype=float)
        if c.ndim == 0:
            lines.append(f"{name:<{width}}  scalar {float(c):.6g}")
            continue
        ok = c[np.isfinite(c)]
        line = f"{name:<{width}}  {c.size} samples"
        if ok.size:
            line += f", {float(ok.min()):.6g} .. {float(ok.max()):.6g}"
        if ok.size < c.size:
            line += f", {c.size - ok.size} non-finite"
        d = np.diff(c)
        if c.size > 1 and ok.size == c.size and np.all(d > 0):
            line += f", increasing: mean step {float(d.mean()):.6g} (a time column?)"
        lines.append(line)
    return lines


def _mat_variables(p: Path) -> dict[str, Any]:
    """The variables of MATLAB file ``p`` (structs as dicts; cell arrays, text and other
    classes as values :func:`_numeric_columns` skips)."""
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    try:
        data = loadmat(p, simplify_cells=True)
    except NotImplementedError:  # scipy's answer to the HDF5-based v7.3 format
        return _mat73_variables(p)
    except (MatReadError, OSError, ValueError, TypeError) as exc:
        raise ImportDataError(f"{p}: cannot read MATLAB file: {exc}") from exc
    return {k: v for k, v in data.items() if not k.startswith("__")}


def _mat73_variables(p: Path) -> dict[str, Any]:
    """The numeric variables of MATLAB v7.3 (HDF5) file ``p``, in MATLAB's orientation (HDF5
    stores MATLAB's column-major arrays with their dimensions reversed); structs as dicts."""
    import h5py

    def matlab_class(node: Any) -> str:
        c = node.attrs.get("MATLAB_class", b"")
        return c.decode() if isinstance(c, bytes) else str(c)

    def read(group: Any) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, node in group.items():
            if key.startswith("#"):  # MATLAB's reference and subsystem stores
                continue
            if isinstance(node, h5py.Group):
                if matlab_class(node) == "struct" and "MATLAB_sparse" not in node.attrs:
                    out[key] = read(node)
            elif (matlab_class(node) not in ("char", "cell")
                  and not node.attrs.get("MATLAB_empty", 0) and node.dtype.kind in "biuf"):
                out[key] = np.asarray(node[()]).T
        return out

    try:
        with h5py.File(p, "r") as f:
            return read(f)
    except OSError as exc:
        raise ImportDataError(f"{p}: cannot read MATLAB v7.3 (HDF5) file: {exc}") from exc


def _numeric_columns(items: Mapping[str, Any], prefix: str = "") -> dict[str, Array]:
    """The columns of NPZ arrays or MATLAB variables ``items`` (see the module docstring)."""
    out: dict[str, Array] = {}
    for key, value in items.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_numeric_columns(value, f"{name}."))
            continue
        a = np.asarray(value) if isinstance(value, (np.ndarray, np.generic, int, float)) \
            else None
        if a is None or a.dtype.kind not in "biuf" or a.size == 0:
            continue  # text, cells, objects, complex, empty: not columns
        a = a.astype(float)
        if a.ndim > 1 and sum(d > 1 for d in a.shape) <= 1:
            a = a.reshape(-1) if a.size > 1 else a.reshape(())
        if a.ndim <= 1:
            out[name] = a
        elif a.ndim == 2:
            if a.shape[0] < a.shape[1]:
                a = a.T  # channels x samples: the samples run along the longer side
            for j in range(a.shape[1]):
                out[f"{name}.{j + 1}"] = a[:, j]
    return out


def _trim(row: list[str]) -> list[str]:
    """``row`` without its empty trailing cells."""
    end = len(row)
    while end and not row[end - 1].strip():
        end -= 1
    return row[:end]


def _csv_columns(p: Path, rows: list[list[str]]) -> dict[str, Array]:
    """Numeric columns of CSV ``rows`` (header first); see the module docstring's tolerance."""
    header = [h.strip() for h in _trim(rows[0])]
    if not header:
        raise ImportDataError(f"{p}: line 1: empty header row")
    for j, h in enumerate(header):
        if not h:
            raise ImportDataError(f"{p}: line 1: column {j + 1} has an empty name")
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise ImportDataError(f"{p}: line 1: duplicate column name(s) {', '.join(dupes)}")
    body = [(i, _trim(row)) for i, row in enumerate(rows[1:], start=2)]
    body = [(i, row) for i, row in body if row]  # blank lines
    if not body:
        raise ImportDataError(f"{p}: expected data rows after the header")
    data = np.empty((len(body), len(header)))
    for k, (i, row) in enumerate(body):
        if len(row) != len(header):
            raise ImportDataError(f"{p}: line {i}: {len(row)} cells, header has "
                                  f"{len(header)} ({', '.join(header)})")
        for j, cell in enumerate(row):
            try:
                data[k, j] = float(cell)
            except ValueError:
                raise ImportDataError(f"{p}: line {i}, column {header[j]!r} (column {j + 1}): "
                                      f"not a number: {cell!r}") from None
    return {h: data[:, j] for j, h in enumerate(header)}


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


def derivative(x: ArrayLike, t: ArrayLike, cutoff_hz: float | None, order: int = 4,
               n: int = 1) -> Array:
    """Zero-phase Butterworth low-pass (if ``cutoff_hz``) then ``n`` central differences on ``t``.

    Args:
        x: signal, shape (N,).
        t: time [s], shape (N,), strictly increasing.
        n: derivative order, 1..:data:`MAX_DERIVATIVE` (result in [x]/s^n).
    """
    if not 1 <= n <= MAX_DERIVATIVE:
        raise ImportDataError(f"derivative order {n}: expected 1..{MAX_DERIVATIVE}")
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    if cutoff_hz is not None:
        fs = 1.0 / float(np.median(np.diff(t)))
        if not 0.0 < cutoff_hz < fs / 2:
            raise ImportDataError(f"derivative cutoff {cutoff_hz} Hz not in (0, {fs / 2:g}) Hz")
        sos = signal.butter(order, cutoff_hz, fs=fs, output="sos")
        x = signal.sosfiltfilt(sos, x)
    for _ in range(n):
        x = np.gradient(x, t)
    return np.asarray(x, dtype=float)


def evaluate(expr: str, cols: Mapping[str, Array], t: Array, mapping: ImportMapping,
             src: str) -> Array:
    """Value of ``expr`` (see module docstring), shape (N,)."""
    m = _EXPR.match(expr)
    if m is None:
        raise ImportDataError(f"{src}: expression {expr!r}: expected COLUMN, d(COLUMN) or "
                              "dN(COLUMN), followed by '* FACTOR' / '/ FACTOR' terms")
    n = t.size
    if m.group(3):
        k = int(m.group(2)) if m.group(2) else 1
        if not 1 <= k <= MAX_DERIVATIVE:
            raise ImportDataError(f"{src}: expression {expr!r}: derivative order {k}, expected "
                                  f"1..{MAX_DERIVATIVE}")
        x = derivative(_column(cols, m.group(3), src, n), t, mapping.cutoff_hz, mapping.order,
                       n=k)
    else:
        x = _column(cols, m.group(4), src, n).copy()
    for op, term in re.findall(r"([*/])\s*([^*/]+)", m.group(5) or ""):
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
    has_time = data.get("time") is not None
    has_dt = data.get("dt") is not None
    if has_time == has_dt:
        raise ImportDataError(f"{source}: give exactly one of 'time' (a time column) and 'dt' "
                              f"(a sample period [s]); got time={data.get('time')!r}, "
                              f"dt={data.get('dt')!r}")
    dt: float | None = None
    if has_dt:
        try:
            dt = float(data["dt"])
        except (TypeError, ValueError):
            raise ImportDataError(f"{source}: dt: expected a number of seconds, got "
                                  f"{data['dt']!r}") from None
        if not (np.isfinite(dt) and dt > 0):
            raise ImportDataError(f"{source}: dt: expected a finite period > 0 s, got {dt!r}")
    rng = _parse_range(data.get("range"), source)
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
    return ImportMapping(time=str(data["time"]) if has_time else None, signals=tuple(out),
                         cutoff_hz=None if cutoff is None else float(cutoff),
                         order=int(der.get("order", 4)), dt=dt, sample_range=rng)


def _parse_range(raw: Any, source: str) -> tuple[int, int | None] | None:
    """``[start, stop]`` / ``"start:stop"`` (stop may be empty or null) -> a sample range."""
    if raw is None:
        return None
    parts: list[Any]
    if isinstance(raw, str):
        parts = [p.strip() or None for p in raw.split(":")]
    elif isinstance(raw, list | tuple):
        parts = list(raw)
    else:
        parts = []
    if len(parts) != 2:
        raise ImportDataError(f"{source}: range: expected START:STOP or [start, stop] (sample "
                              f"indices), got {raw!r}")
    try:
        start = 0 if parts[0] is None else int(parts[0])
        stop = None if parts[1] is None else int(parts[1])
    except (TypeError, ValueError):
        raise ImportDataError(f"{source}: range: expected whole sample indices, got "
                              f"{raw!r}") from None
    if start < 0 or (stop is not None and stop <= start):
        raise ImportDataError(f"{source}: range: expected 0 <= start < stop, got {raw!r}")
    return start, stop


def build_topics(cols: Mapping[str, Array], mapping: ImportMapping, src: str,
                 start_time: float = 0.0) -> dict[str, TopicSeries]:
    """Evaluate the mapping into JointState series (one per topic).

    Raises:
        ImportDataError: missing column, NaN, time not strictly increasing, bad field, a field
            given for some joints of a topic but not for others.
    """
    if mapping.time is not None:
        t = _column(cols, mapping.time, src, None)
        what = f"time column {mapping.time!r}"
    else:
        lengths = {k: np.asarray(v).size for k, v in cols.items() if np.asarray(v).ndim == 1
                   and np.asarray(v).size > 1}
        if not lengths:
            raise ImportDataError(f"{src}: no column with more than one sample")
        n_rows = max(lengths.values())
        t = np.arange(n_rows, dtype=float) * float(mapping.dt or 0.0)
        what = f"dt {mapping.dt!r} s"
    if t.ndim != 1 or t.size < 2:
        raise ImportDataError(f"{src}: {what}: need at least 2 samples")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise ImportDataError(f"{src}: {what} not strictly increasing at "
                              f"row {i + 1} ({t[i]!r} -> {t[i + 1]!r})")
    keep = slice(None)
    if mapping.sample_range is not None:
        start, stop = mapping.sample_range
        if start >= t.size - 1 or (stop is not None and stop > t.size):
            raise ImportDataError(f"{src}: range {start}:{'' if stop is None else stop} outside "
                                  f"the {t.size} samples")
        keep = slice(start, stop)
    t_all = t
    t = t_all[keep]
    stamps = np.round((t - t[0] + start_time) * 1e9).astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise ImportDataError(f"{src}: {what}: steps below 1 ns")
    by_topic: dict[str, dict[str, dict[str, Array]]] = {}
    for s in mapping.signals:
        if s.field not in FIELDS:
            raise ImportDataError(f"{src}: signal {s.topic} {s.joint}: field {s.field!r} not one "
                                  f"of {', '.join(FIELDS)}")
        joints = by_topic.setdefault(s.topic, {})
        fields = joints.setdefault(s.joint, {})
        if s.field in fields:
            raise ImportDataError(f"{src}: {s.topic} {s.joint} {s.field} mapped twice")
        fields[s.field] = evaluate(s.expr, cols, t_all, mapping, src)[keep]
    out: dict[str, TopicSeries] = {}
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
        out[topic] = TopicSeries(stamps_ns=stamps, names=names, **arrays)
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
        description="Convert NPZ, MATLAB or CSV columns into a rosbag2 (MCAP) bag of "
                    "JointState messages.")
    ap.add_argument("source", help="input file (.npz, .mat or .csv)")
    ap.add_argument("--out", help="output bag directory (must not exist; required unless --list)")
    ap.add_argument("--list", action="store_true",
                    help="only list the file's columns (name, length, range) and exit")
    ap.add_argument("--mapping", help="YAML mapping file (see docs)")
    ap.add_argument("--time", help="time column [s] (overrides the mapping's)")
    ap.add_argument("--dt", type=float, default=None,
                    help="sample period [s] for a file without a time column")
    ap.add_argument("--range", default=None, metavar="START:STOP",
                    help="keep samples START..STOP-1 (derivatives use the whole record)")
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
    if args.list:
        try:
            cols = load_columns(args.source)
        except DvtIdentifyError as exc:
            print(f"dvt-import: error: {exc}", file=sys.stderr)
            return 2
        print(f"{args.source}: {len(cols)} columns")
        for line in describe_columns(cols):
            print(f"  {line}")
        return 0
    if not args.out:
        ap.error("--out is required (or --list to see the file's columns)")
    try:
        data: dict[str, Any] = {}
        if args.mapping:
            mp = Path(args.mapping)
            if not mp.is_file():
                raise ImportDataError(f"{mp}: mapping file not found")
            try:
                data = safe_load(mp.read_text()) or {}
            except yaml.YAMLError as exc:
                raise ImportDataError(f"{mp}: not valid YAML: {exc}") from exc
            if not isinstance(data, dict):
                raise ImportDataError(f"{mp}: expected a mapping")
        if args.time:
            data["time"] = args.time
            data.pop("dt", None)
        if args.dt is not None:
            data["dt"] = args.dt
            data.pop("time", None)
        if args.range is not None:
            data["range"] = args.range
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
