"""Data for identification: JointState bags in and out, alignment, checks and pre-processing.

A recording is a rosbag2 directory (MCAP, CDR, ROS 2 Jazzy definitions). The identifier reads the
``sensor_msgs/msg/JointState`` topics an actuator description names (topic, field, joint), keyed by
``header.stamp`` (the controller's sample time), aligns inputs and outputs by stamp, checks them
and turns each bag into a :class:`Segment` on a uniform time grid. Topics not named are ignored.

Checks (each refusal names bag, topic and problem, see :class:`~dvt_identify.errors.DataError`):
stamps strictly increasing, no NaN/inf, at least ``min_samples`` aligned samples, no saturation
against limits the description gives, some excitation. Gaps of up to ``max_gap_samples`` missing
samples are filled by linear interpolation (and counted); a longer gap splits the recording into
segments ``<bag>#1``, ``<bag>#2``, ... (each fitted with its own initial state); a piece shorter
than ``min_samples`` is dropped with a :class:`DataWarning` (bag, time span, why), and a bag with
no piece long enough is refused with an error naming the gaps.

Pre-processing: low-pass Butterworth on inputs and outputs alike (like MATLAB ``idfilt``; optionally
zero-phase) and decimation with an anti-alias filter.
"""

from __future__ import annotations

import shutil
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from dvt_identify.errors import DataError

Array = NDArray[np.float64]
FIELDS = ("position", "velocity", "effort")
JOINT_STATE = "sensor_msgs/msg/JointState"
#: Joins a bag path and the number of one of its pieces in a segment name (``<bag>#2``).
SEGMENT_SEP = "#"


class DataWarning(UserWarning):
    """Part of a recording is not used (e.g. a piece too short between long gaps); the message
    names the bag, the time span and why."""


@dataclass(frozen=True)
class SignalSpec:
    """Where one model signal lives in a bag.

    Attributes:
        name: the model's name for the signal (an input or an output/state name).
        topic: JointState topic, e.g. ``/dvt/joint_states``.
        field: ``position``, ``velocity`` or ``effort``.
        joint: entry of the message's ``name`` list, e.g. ``sun_shaft``.
        scale: factor applied after reading (signal unit = scale * bag unit).
        saturation: optional (low, high) limits in signal units; samples at or beyond them count
            as saturated.
    """

    name: str
    topic: str
    field: str
    joint: str
    scale: float = 1.0
    saturation: tuple[float, float] | None = None


@dataclass(frozen=True)
class JointStateSeries:
    """All messages of one JointState topic.

    Attributes:
        stamps_ns: ``header.stamp`` in ns, shape (N,), int64.
        names: joint names (the ``name`` list of the messages; constant over the topic).
        position, velocity, effort: arrays of shape (N, len(names)) or ``None`` when empty.
    """

    stamps_ns: NDArray[np.int64]
    names: tuple[str, ...]
    position: Array | None = None
    velocity: Array | None = None
    effort: Array | None = None

    def field_array(self, name: str) -> Array | None:
        """The array of ``name`` (one of :data:`FIELDS`)."""
        return {"position": self.position, "velocity": self.velocity,
                "effort": self.effort}[name]


@dataclass(frozen=True, eq=False)
class Segment:
    """One contiguous record on a uniform grid.

    Attributes:
        name: source label (bag path).
        t: time [s] from the record's first sample, shape (N,), uniform step ``dt``.
        u: inputs, shape (N, nu), in the description's input units.
        y: measured outputs (= states, C = I), shape (N, ny).
        input_names, output_names: names, lengths nu and ny.
        dt: sample time [s].
        notes: what pre-processing did (filled gaps, filtering, decimation).
    """

    name: str
    t: Array
    u: Array
    y: Array
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dt: float
    notes: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        n = self.t.shape[0]
        if self.t.ndim != 1:
            raise DataError(f"{self.name}: t: expected shape (N,), got {self.t.shape}")
        if self.u.shape != (n, len(self.input_names)):
            raise DataError(f"{self.name}: u: expected shape {(n, len(self.input_names))}, "
                            f"got {self.u.shape}")
        if self.y.shape != (n, len(self.output_names)):
            raise DataError(f"{self.name}: y: expected shape {(n, len(self.output_names))}, "
                            f"got {self.y.shape}")

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])


def make_segment(name: str, t: ArrayLike, u: ArrayLike, y: ArrayLike,
                 input_names: Sequence[str], output_names: Sequence[str]) -> Segment:
    """Build a :class:`Segment` from arrays (1-D arrays are one signal), checking the grid."""
    tt = np.asarray(t, dtype=float)
    u2 = np.asarray(u, dtype=float)
    y2 = np.asarray(y, dtype=float)
    if u2.ndim == 1:
        u2 = u2[:, None]
    if y2.ndim == 1:
        y2 = y2[:, None]
    if tt.size < 2:
        raise DataError(f"{name}: too little data: {tt.size} samples")
    dt = float((tt[-1] - tt[0]) / (tt.size - 1))
    if not dt > 0:
        raise DataError(f"{name}: time not increasing")
    return Segment(name=name, t=tt - tt[0], u=u2, y=y2, input_names=tuple(input_names),
                   output_names=tuple(output_names), dt=dt)


# --------------------------------------------------------------------------------------------
# Bag I/O


def read_jointstate_topics(bag: str | Path, topics: Sequence[str]) -> dict[str, JointStateSeries]:
    """Read the JointState ``topics`` of ``bag`` in one pass; other topics are ignored.

    Uses :func:`dvt_model.bagio.read_topics` (bulk decoding of the raw CDR).

    Raises:
        DataError: the bag cannot be opened, a topic is missing, not JointState, has no
            messages, a message is undecodable, or its joint names or array lengths change
            between messages (the message names bag, topic, message index and field).
    """
    from dvt_model.bagio import read_topics
    from dvt_model.errors import BagError

    path = Path(bag)
    if not path.exists():
        raise DataError(f"{path}: bag not found")
    try:
        series = read_topics(path, topics)
    except BagError as exc:
        raise DataError(str(exc)) from exc
    return {topic: JointStateSeries(
        stamps_ns=ser.stamps_ns, names=ser.names,
        position=ser.position if ser.position.shape[1] else None,
        velocity=ser.velocity if ser.velocity.shape[1] else None,
        effort=ser.effort if ser.effort.shape[1] else None) for topic, ser in series.items()}


def write_jointstate_bag(path: str | Path, topics: Mapping[str, JointStateSeries],
                         overwrite: bool = False) -> Path:
    """Write JointState ``topics`` to a new rosbag2/MCAP bag at ``path``.

    Every message's ``header.stamp`` and the bag's log time are the series' stamp. Empty fields
    are written as empty arrays. With ``overwrite`` an existing *bag* directory (one that holds a
    ``metadata.yaml``) is replaced; any other existing path is refused.

    Raises:
        DataError: the path exists, or a series has inconsistent shapes.
    """
    from dvt_model.bagio import joint_state_cdr, write_bag
    from dvt_model.errors import BagError

    out = Path(path)
    if out.exists():
        if overwrite and (out / "metadata.yaml").exists():
            shutil.rmtree(out)
        else:
            raise DataError(f"{out}: output bag already exists"
                            + ("" if overwrite else " (pass --force to replace it)")
                            + ("" if not overwrite else " and is not a bag directory"))
    for topic, ser in topics.items():
        n = ser.stamps_ns.shape[0]
        for fname in FIELDS:
            arr = ser.field_array(fname)
            if arr is not None and arr.shape != (n, len(ser.names)):
                raise DataError(f"{out}: topic {topic}: {fname}: expected shape "
                                f"{(n, len(ser.names))}, got {arr.shape}")
    streams = [
        (topic, JOINT_STATE,
         [(int(stamp), joint_state_cdr(
             int(stamp), ser.names,
             position=None if ser.position is None else ser.position[i],
             velocity=None if ser.velocity is None else ser.velocity[i],
             effort=None if ser.effort is None else ser.effort[i]))
          for i, stamp in enumerate(ser.stamps_ns)])
        for topic, ser in topics.items()]
    try:
        return write_bag(out, streams)
    except BagError as exc:
        raise DataError(str(exc)) from exc


# --------------------------------------------------------------------------------------------
# From topics to a segment


@dataclass(frozen=True)
class Checks:
    """Data checks applied to every bag.

    Attributes:
        min_samples: fewest aligned samples a bag, and each segment cut from it, may have; a
            shorter piece between long gaps is dropped with a :class:`DataWarning`.
        max_gap_samples: longest run of missing samples filled by interpolation; a longer gap
            splits the recording into segments (see :func:`load_bag_segments`).
        max_saturated_fraction: largest fraction of samples allowed at a signal's saturation
            limits.
        min_relative_std: a signal whose std is below this times (1 + |mean|) is "constant".
    """

    min_samples: int = 100
    max_gap_samples: int = 3
    max_saturated_fraction: float = 0.01
    min_relative_std: float = 1e-9


def _signal_column(path: Path, series: JointStateSeries, spec: SignalSpec) -> Array:
    if spec.field not in FIELDS:
        raise DataError(f"{path}: topic {spec.topic}: unknown field {spec.field!r} "
                        f"(expected one of {', '.join(FIELDS)})")
    if spec.joint not in series.names:
        raise DataError(f"{path}: topic {spec.topic}: joint {spec.joint!r} not in name list "
                        f"{list(series.names)}")
    arr = series.field_array(spec.field)
    if arr is None:
        raise DataError(f"{path}: topic {spec.topic}: field {spec.field} is empty "
                        f"(needed for joint {spec.joint})")
    col = arr[:, series.names.index(spec.joint)] * spec.scale
    bad = ~np.isfinite(col)
    if np.any(bad):
        i = int(np.argmax(bad))
        t = (series.stamps_ns[i] - series.stamps_ns[0]) * 1e-9
        raise DataError(f"{path}: topic {spec.topic}: {spec.field}[{spec.joint}] is "
                        f"{col[i]} at message {i} (t = {t:.6f} s); {int(bad.sum())} "
                        "non-finite values")
    return np.asarray(col, dtype=float)


def _check_stamps(path: Path, topic: str, stamps: NDArray[np.int64]) -> None:
    d = np.diff(stamps)
    if np.any(d <= 0):
        i = int(np.argmax(d <= 0))
        raise DataError(f"{path}: topic {topic}: stamps not strictly increasing at message "
                        f"{i + 1} ({stamps[i]} ns -> {stamps[i + 1]} ns)")


def _align(path: Path, stamps: dict[str, NDArray[np.int64]], reference: str
           ) -> dict[str, NDArray[np.int64]]:
    """Index arrays into each topic's messages for the common samples (by stamp)."""
    ref = stamps[reference]
    common = ref
    for s in stamps.values():
        common = np.intersect1d(common, s, assume_unique=True)
    if common.size >= 0.99 * min(s.size for s in stamps.values()):
        return {t: np.searchsorted(s, common) for t, s in stamps.items()}
    # Not identical stamps: match each topic to the reference by nearest stamp within dt/4.
    dt = float(np.median(np.diff(ref))) if ref.size > 1 else 1.0
    keep = np.ones(ref.size, dtype=bool)
    idx: dict[str, NDArray[np.int64]] = {}
    for topic, s in stamps.items():
        j = np.clip(np.searchsorted(s, ref), 1, max(s.size - 1, 1))
        left = np.abs(ref - s[j - 1])
        right = np.abs(s[np.minimum(j, s.size - 1)] - ref)
        best = np.where(left <= right, j - 1, np.minimum(j, s.size - 1))
        ok = np.abs(s[best] - ref) <= dt / 4
        keep &= ok
        idx[topic] = best
    if keep.sum() < 0.5 * ref.size:
        others = [t for t in stamps if t != reference]
        raise DataError(f"{path}: topics {reference} and {', '.join(others)}: fewer than half "
                        "of the samples share a stamp (within a quarter sample); cannot align")
    return {t: i[keep] for t, i in idx.items()}


def check_signal(path: str | Path, topic: str, name: str, x: Array, spec: SignalSpec | None,
                 checks: Checks) -> None:
    """Saturation check of one signal against ``spec.saturation``."""
    if spec is None or spec.saturation is None:
        return
    lo, hi = spec.saturation
    tol = 1e-9 * max(abs(lo), abs(hi), 1.0)
    sat = (x <= lo + tol) | (x >= hi - tol)
    frac = float(np.mean(sat))
    if frac > checks.max_saturated_fraction:
        raise DataError(f"{path}: topic {topic}: {spec.field}[{spec.joint}] ({name}) is "
                        f"saturated at [{lo}, {hi}] in {100 * frac:.1f} % of the samples (limit "
                        f"{100 * checks.max_saturated_fraction:.1f} %)")


def _constant(x: Array, checks: Checks) -> bool:
    return bool(np.std(x) <= checks.min_relative_std * (1.0 + abs(float(np.mean(x)))))


def _fill_gaps(t: Array, cols: Array, dt: float) -> tuple[Array, Array, int]:
    """Put one gap-free piece on the uniform grid of step ``dt`` from its first sample;
    interpolate the missing samples linearly. Returns (grid, values, missing samples)."""
    steps = np.diff(t) / dt
    missing = int(np.sum(np.maximum(np.round(steps) - 1, 0)))
    n = int(np.rint((t[-1] - t[0]) / dt)) + 1
    grid = t[0] + dt * np.arange(n)
    if missing == 0 and n == t.size and np.max(np.abs(grid - t)) < 0.25 * dt:
        return t, cols, 0
    out = np.column_stack([np.interp(grid, t, cols[:, j]) for j in range(cols.shape[1])])
    return grid, out, missing


@dataclass(frozen=True)
class Gap:
    """A gap longer than ``max_gap_samples`` missing samples (where a recording is split).

    Attributes:
        before, after: times [s] (from the bag's first aligned sample) of the samples around it.
        missing: number of missing samples.
    """

    before: float
    after: float
    missing: int

    def __str__(self) -> str:
        return (f"{self.after - self.before:.6g} s ({self.missing} missing samples) after "
                f"t = {self.before:.6f} s")


def split_at_gaps(t: Array, dt: float, max_gap: int) -> tuple[list[tuple[int, int]], list[Gap]]:
    """Cut a time axis at gaps of more than ``max_gap`` missing samples.

    Args:
        t: sample times [s], shape (N,), strictly increasing.
        dt: nominal sample time [s].
        max_gap: longest run of missing samples that does not split.

    Returns:
        The pieces as index ranges ``[start, stop)`` in time order, and the gaps between them.
    """
    steps = np.diff(t) / dt
    cut = np.flatnonzero(steps > max_gap + 1.5)
    bounds = [0, *(int(i) + 1 for i in cut), int(t.size)]
    gaps = [Gap(float(t[i]), float(t[i + 1]), int(np.rint(steps[i])) - 1) for i in cut]
    return list(pairwise(bounds)), gaps


def _gap_list(gaps: Sequence[Gap], most: int = 5) -> str:
    text = "; ".join(str(g) for g in gaps[:most])
    return text + (f"; and {len(gaps) - most} more" if len(gaps) > most else "")


def load_bag_segments(bag: str | Path, inputs: Sequence[SignalSpec],
                      outputs: Sequence[SignalSpec], checks: Checks | None = None
                      ) -> list[Segment]:
    """Read, align and check one bag; return its :class:`Segment` (one per gap-free piece).

    The reference clock is the first output's topic; other topics are matched by identical stamp
    (the contract), or else by nearest stamp within a quarter sample. Gaps of up to
    ``checks.max_gap_samples`` missing samples are filled by linear interpolation; a longer gap
    splits the recording into segments named ``<bag>#1``, ``<bag>#2``, ... (in time order; a bag
    without such a gap keeps the name ``<bag>``), each with time from 0 and fitted with its own
    initial state. A piece with fewer than ``checks.min_samples`` samples is dropped with a
    :class:`DataWarning` naming the bag, its time span and why. Saturation, constant outputs and
    excitation are checked over the kept samples of the bag together.

    Raises:
        DataError: naming the bag, topic and problem (also when no piece is long enough: then
            it names the gaps).
    """
    checks = checks or Checks()
    path = Path(bag)
    specs = list(outputs) + list(inputs)
    topics = list(dict.fromkeys(s.topic for s in specs))
    series = read_jointstate_topics(path, topics)
    for topic, ser in series.items():
        _check_stamps(path, topic, ser.stamps_ns)
    cols_by_spec = [_signal_column(path, series[s.topic], s) for s in specs]
    idx = _align(path, {t: series[t].stamps_ns for t in topics}, outputs[0].topic)
    ref_topic = outputs[0].topic
    stamps = series[ref_topic].stamps_ns[idx[ref_topic]]
    cols = np.column_stack([c[idx[s.topic]] for c, s in zip(cols_by_spec, specs, strict=True)])
    if stamps.size < checks.min_samples:
        raise DataError(f"{path}: topic {ref_topic}: too little data: {stamps.size} aligned "
                        f"samples (need at least {checks.min_samples})")
    t = (stamps - stamps[0]).astype(float) * 1e-9
    dt = float(np.median(np.diff(t)))
    pieces, gaps = split_at_gaps(t, dt, checks.max_gap_samples)
    split = len(pieces) > 1
    kept: list[tuple[int, Array, Array, int]] = []
    for k, (i0, i1) in enumerate(pieces, start=1):
        if i1 - i0 < checks.min_samples:
            warnings.warn(DataWarning(
                f"{path}: topic {ref_topic}: samples at t = {t[i0]:.6f} .. {t[i1 - 1]:.6f} s "
                f"(piece {k} of {len(pieces)}, {i1 - i0} samples between gaps of more than "
                f"{checks.max_gap_samples} missing samples) dropped: fewer than min_samples = "
                f"{checks.min_samples}"), stacklevel=2)
            continue
        grid, filled, missing = _fill_gaps(t[i0:i1], cols[i0:i1], dt)
        kept.append((k, grid, filled, missing))
    if not kept:
        raise DataError(f"{path}: topic {ref_topic}: no piece of at least {checks.min_samples} "
                        f"samples between the {len(gaps)} gap(s) of more than "
                        f"{checks.max_gap_samples} missing samples: {_gap_list(gaps)} (pieces of "
                        f"{', '.join(str(b - a) for a, b in pieces)} samples)")
    every = np.concatenate([c for _, _, c, _ in kept])
    for j, s in enumerate(specs):
        check_signal(path, s.topic, s.name, every[:, j], s, checks)
    ny = len(outputs)
    for j, s in enumerate(outputs):
        if _constant(every[:, j], checks):
            raise DataError(f"{path}: topic {s.topic}: {s.field}[{s.joint}] ({s.name}) is "
                            f"constant ({every[0, j]:.6g}): no response to identify")
    if all(_constant(every[:, ny + j], checks) for j in range(len(inputs))):
        names = ", ".join(f"{s.topic} {s.field}[{s.joint}]" for s in inputs)
        raise DataError(f"{path}: no excitation: every input is constant ({names})")
    out = []
    for k, grid, filled, missing in kept:
        notes: tuple[str, ...] = ()
        if split:
            notes += (f"piece {k} of {len(pieces)} of {path}: t = {grid[0]:.6f} .. "
                      f"{grid[-1]:.6f} s of the recording (split at gaps of more than "
                      f"{checks.max_gap_samples} missing samples)",)
        if missing:
            notes += (f"{missing} missing samples filled by linear interpolation",)
        seg = make_segment(f"{path}{SEGMENT_SEP}{k}" if split else str(path), grid,
                           filled[:, ny:], filled[:, :ny], [s.name for s in inputs],
                           [s.name for s in outputs])
        out.append(replace(seg, notes=notes))
    return out


def load_segment(bag: str | Path, inputs: Sequence[SignalSpec], outputs: Sequence[SignalSpec],
                 checks: Checks | None = None) -> Segment:
    """:func:`load_bag_segments` for a bag that must give exactly one segment.

    Raises:
        DataError: as :func:`load_bag_segments`, or when long gaps split the bag into several
            segments (the message names the gaps).
    """
    segs = load_bag_segments(bag, inputs, outputs, checks)
    if len(segs) > 1:
        checks = checks or Checks()
        raise DataError(f"{bag}: topic {outputs[0].topic}: gaps of more than "
                        f"{checks.max_gap_samples} missing samples split the recording into "
                        f"{len(segs)} segments ({', '.join(s.name for s in segs)}); read it "
                        "with load_bag_segments")
    return segs[0]


def check_excitation(segments: Sequence[Segment], checks: Checks | None = None,
                     input_topics: Mapping[str, str] | None = None,
                     used: set[str] | None = None) -> None:
    """Refuse a set of estimation segments in which some (used) input never varies.

    Args:
        segments: the estimation segments (fitted jointly).
        input_topics: optional input name -> "topic field[joint]" used in the message.
        used: inputs the model uses (default: all); a constant unused input is fine.
    """
    checks = checks or Checks()
    if not segments:
        raise DataError("no estimation data")
    for j, name in enumerate(segments[0].input_names):
        if used is not None and name not in used:
            continue
        if all(_constant(s.u[:, j], checks) for s in segments):
            where = (input_topics or {}).get(name, name)
            bags = ", ".join(s.name for s in segments)
            raise DataError(f"{bags}: {where}: input {name} has no excitation (constant in every "
                            "estimation bag), so its effect cannot be identified")


# --------------------------------------------------------------------------------------------
# Pre-processing


def lowpass(seg: Segment, cutoff_hz: float, order: int = 4, zero_phase: bool = True) -> Segment:
    """Butterworth low-pass of inputs and outputs alike (MATLAB ``idfilt``).

    Args:
        cutoff_hz: -3 dB frequency [Hz], below the Nyquist frequency.
        order: filter order (doubled in effect when ``zero_phase``).
        zero_phase: forward-backward filtering (``filtfilt``), no delay.
    """
    nyq = 0.5 / seg.dt
    if not 0.0 < cutoff_hz < nyq:
        raise DataError(f"{seg.name}: lowpass cutoff {cutoff_hz} Hz not in (0, {nyq:g}) Hz")
    sos = signal.butter(order, cutoff_hz, btype="low", fs=1.0 / seg.dt, output="sos")
    filt = signal.sosfiltfilt if zero_phase else signal.sosfilt
    u = np.asarray(filt(sos, seg.u, axis=0))
    y = np.asarray(filt(sos, seg.y, axis=0))
    note = (f"low-pass Butterworth order {order} at {cutoff_hz:g} Hz"
            + (" (zero-phase)" if zero_phase else ""))
    return replace(seg, u=u, y=y, notes=(*seg.notes, note))


def decimate(seg: Segment, q: int) -> Segment:
    """Keep every ``q``-th sample after a zero-phase anti-alias filter (order-8 Chebyshev I).

    ``q == 1`` returns the segment unchanged.
    """
    if q < 1:
        raise DataError(f"{seg.name}: decimation factor must be >= 1, got {q}")
    if q == 1:
        return seg
    if seg.n // q < 10:
        raise DataError(f"{seg.name}: too little data to decimate by {q}: {seg.n} samples")
    u = np.asarray(signal.decimate(seg.u, q, axis=0, zero_phase=True))
    y = np.asarray(signal.decimate(seg.y, q, axis=0, zero_phase=True))
    t = seg.t[::q][: y.shape[0]]
    return replace(seg, t=t, u=u, y=y, dt=seg.dt * q,
                   notes=(*seg.notes, f"decimated by {q} to {1.0 / (seg.dt * q):g} Hz"))
