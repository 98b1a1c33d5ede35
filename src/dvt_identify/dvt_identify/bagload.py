"""From JointState bags to segments: read, align, check and split one bag
(:func:`load_bag_segments`); the excitation check of a set of estimation segments.

A recording is a rosbag2 directory (MCAP, CDR, ROS 2 Jazzy definitions). The identifier reads the
``sensor_msgs/msg/JointState`` topics an actuator description names (topic, field, joint), keyed by
``header.stamp`` (the controller's sample time), aligns inputs and outputs by stamp, checks them
and turns each bag into a :class:`Segment` on a uniform time grid. Topics not named are ignored.

Checks (each refusal names bag, topic and problem, see :class:`~dvt_identify.errors.DataError`):
at least ``min_samples`` aligned samples, no saturation against limits the description gives,
some excitation. What is sound is salvaged, with a :class:`DataWarning` naming bag, topic and
problem: a stamp that goes backwards or repeats splits the recording there; an aligned sample
with a NaN/inf in a used signal is dropped and splits the recording there; gaps of up to
``max_gap_samples`` missing samples are filled by linear interpolation (and counted), a longer
gap splits the recording. The pieces become segments ``<bag>#1``, ``<bag>#2``, ... (each fitted
with its own initial state); a piece shorter than ``min_samples`` is dropped with a
:class:`DataWarning` (bag, time span, why), and a bag with no piece long enough is refused with
an error naming the splits. A killed recording (unfinished MCAP file) is read up to its last
complete chunk (:func:`dvt_model.recording.read_topics`), with a :class:`DataWarning`.

Measured angles: when the outputs' topics carry ``position``, each output that is the
``velocity`` of a joint gets the recorded ``position`` of the same joint (same topic, same
scale) as its angle (:attr:`Segment.angles`); the position-dependent effects then take member
angles from it instead of integrating the speed from the first sample
(:func:`dvt_identify.effects.position.angle_of`). A recording without positions (or with a
non-finite position) gives no angles (``None``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import (
    FIELDS,
    SEGMENT_SEP,
    Array,
    Checks,
    DataWarning,
    JointStateSeries,
    Segment,
    SignalSpec,
    _constant,
    intersample,
    make_segment,
    read_jointstate_topics,
)
from dvt_identify.errors import DataError
from dvt_model.errors import BagError


def _signal_column(path: Path, series: JointStateSeries, spec: SignalSpec) -> Array:
    """The scaled values of ``spec`` in every message of its topic (non-finite values kept)."""
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
    with np.errstate(invalid="ignore", over="ignore"):
        col = arr[:, series.names.index(spec.joint)] * spec.scale
    return np.asarray(col, dtype=float)


def _angle_columns(path: Path, series: Mapping[str, JointStateSeries],
                   outputs: Sequence[SignalSpec]) -> list[Array] | None:
    """The measured angle of each output, per message of its topic: the recorded ``position``
    of the joint of a ``velocity`` output (times the output's scale), zeros for another
    output; ``None`` when an output's topic records no positions, or a joint's position is
    NaN throughout (not measured): no angles for the bag.

    Raises:
        DataError: a topic's ``position`` array does not have one column per joint name
            (naming the bag, topic and field).
    """
    cols: list[Array] = []
    for spec in outputs:
        ser = series[spec.topic]
        n = int(ser.stamps_ns.shape[0])
        if spec.field != "velocity":
            cols.append(np.zeros(n))
            continue
        pos = ser.position
        if pos is None:
            return None
        if pos.shape != (n, len(ser.names)):
            raise DataError(f"{path}: topic {spec.topic}: field position: expected shape "
                            f"({n}, {len(ser.names)}) (messages, joints {list(ser.names)}), "
                            f"got {pos.shape}")
        with np.errstate(invalid="ignore", over="ignore"):
            col = np.asarray(pos[:, ser.names.index(spec.joint)] * spec.scale, float)
        if not np.any(np.isfinite(col)):  # NaN throughout: the joint's angle is not measured
            return None
        cols.append(col)
    return cols


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` of the runs of True in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(),
                    strict=True))


def _stamp_breaks(stamps: NDArray[np.int64]) -> NDArray[np.int64]:
    """Indices of the messages whose stamp does not exceed the previous message's."""
    return np.flatnonzero(np.diff(stamps) <= 0).astype(np.int64) + 1


def _pair_pieces(path: Path, stamps: Mapping[str, NDArray[np.int64]],
                 breaks: Mapping[str, NDArray[np.int64]], reference: str
                 ) -> tuple[list[dict[str, NDArray[np.int64]]], list[str]]:
    """Pair the topics' messages by stamp within runs of strictly increasing stamps.

    Each topic's messages (recorded order) are cut at its ``breaks`` (stamps that go backwards
    or repeat) into runs. Walking through the recording, the current run of every topic is
    trimmed to the stamp span all of them cover (within a quarter sample) and paired by
    :func:`dvt_model.recording.pair_stamps` (identical stamps, else nearest within a quarter
    sample); the run that ends first is then left for the next. Without a break this is one
    pairing of the whole recording.

    Returns:
        The paired pieces in recording order (per topic, indices into its messages), and the
        messages of the pairings that failed (each names the bag and the topics).
    """
    from dvt_model.recording import pair_stamps

    runs = {t: list(pairwise([0, *breaks[t].tolist(), int(st.size)]))
            for t, st in stamps.items()}
    steps = np.diff(stamps[reference])
    steps = steps[steps > 0]
    tol = int(0.25 * float(np.median(steps))) if steps.size else 0  # [ns]
    run_no = dict.fromkeys(stamps, 0)
    cursor = dict.fromkeys(stamps, 0)
    pieces: list[dict[str, NDArray[np.int64]]] = []
    failed: list[str] = []
    while all(run_no[t] < len(runs[t]) for t in stamps):
        window = {t: (max(runs[t][run_no[t]][0], cursor[t]), runs[t][run_no[t]][1])
                  for t in stamps}
        lo = np.int64(max(int(stamps[t][a]) for t, (a, _) in window.items()) - tol)
        hi = np.int64(min(int(stamps[t][b - 1]) for t, (_, b) in window.items()) + tol)
        sub: dict[str, tuple[int, int]] = {}
        for t, (a, b) in window.items():
            st = stamps[t][a:b]
            sub[t] = (a + int(np.searchsorted(st, lo, side="left")),
                      a + int(np.searchsorted(st, hi, side="right")))
        if all(i1 > i0 for i0, i1 in sub.values()):
            try:
                pairing = pair_stamps({t: stamps[t][i0:i1] for t, (i0, i1) in sub.items()},
                                      reference, where=str(path))
            except BagError as exc:
                failed.append(str(exc))
            else:
                if pairing.n:
                    pieces.append({t: (pairing.index[t] + sub[t][0]).astype(np.int64)
                                   for t in stamps})
        for t, (_, i1) in sub.items():
            cursor[t] = i1
            if i1 >= window[t][1]:
                run_no[t] += 1
    return pieces, failed


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


_MOST_WARNED = 5
"""Dropped pieces warned about one by one; the rest of a bag's in one summary warning."""


def _gap_list(gaps: Sequence[Gap], most: int = 5) -> str:
    text = "; ".join(str(g) for g in gaps[:most])
    return text + (f"; and {len(gaps) - most} more" if len(gaps) > most else "")


def _warn_stamp_breaks(path: Path, topic: str, stamps: NDArray[np.int64],
                       breaks: NDArray[np.int64], t0: int) -> str:
    """Warn (one :class:`DataWarning` per topic) about stamps that go backwards or repeat;
    return a short description for an error message."""
    def one(i: int) -> str:
        kind = "repeats" if stamps[i] == stamps[i - 1] else "goes backwards"
        return (f"message {i} ({kind}: {int(stamps[i])} ns after {int(stamps[i - 1])} ns, "
                f"t = {(int(stamps[i - 1]) - t0) * 1e-9:.6f} s)")

    listed = [one(int(i)) for i in breaks[:5]]
    more = f"; and {breaks.size - 5} more" if breaks.size > 5 else ""
    count = ("a stamp that does not increase" if breaks.size == 1
             else f"{breaks.size} stamps that do not increase")
    warnings.warn(DataWarning(
        f"{path}: topic {topic}: header.stamp does not strictly increase at "
        f"{'; '.join(listed)}{more}: the recording is split there ({count})"), stacklevel=3)
    return f"topic {topic}: {count} (first at {listed[0]})"


def _warn_non_finite(path: Path, spec: SignalSpec, first_row: tuple[float, int, int, float],
                     n: int) -> str:
    """Warn (one :class:`DataWarning` per signal) about the ``n`` aligned samples with a
    non-finite value of ``spec`` (``first_row``: time [s], stamp [ns], message index and value
    of the first); return a short description."""
    t, stamp, msg, value = first_row
    first = f"t = {t:.6f} s (stamp {stamp} ns, message {msg})"
    count = "1 sample" if n == 1 else f"{n} samples"
    warnings.warn(DataWarning(
        f"{path}: topic {spec.topic}: {spec.field}[{spec.joint}] ({spec.name}) is {value} at "
        f"{first}{'' if n == 1 else ' and in ' + str(n - 1) + ' more samples'}: {count} with a "
        f"non-finite value dropped, the recording is split there"), stacklevel=3)
    return (f"topic {spec.topic}: {spec.field}[{spec.joint}] non-finite in {count} (first at "
            f"{first})")


def load_bag_segments(bag: str | Path, inputs: Sequence[SignalSpec],
                      outputs: Sequence[SignalSpec], checks: Checks | None = None
                      ) -> list[Segment]:
    """Read, align and check one bag; return its :class:`Segment` (one per sound piece).

    The reference clock is the first output's topic; other topics are matched by identical stamp
    (the contract), or else by nearest stamp within a quarter sample. What is sound is kept and
    the recording is split around the rest, each time with a :class:`DataWarning` naming the
    bag, the topic and the problem:

    * a stamp that goes backwards or repeats (on any topic read) splits the recording there
      (the warning names the message and the two stamps);
    * an aligned sample with a NaN or inf in a used input or output is dropped and splits the
      recording there (the warning names the topic, field, joint, time and how many samples);
    * gaps of up to ``checks.max_gap_samples`` missing samples are filled by linear
      interpolation (noted in the segment); a longer gap splits the recording (no warning:
      nothing is lost);
    * a killed recording is read up to its last complete chunk.

    Each segment carries the measured angles (:attr:`Segment.angles`, gaps filled alike) when
    the outputs' topics record positions; a non-finite position among the kept samples drops
    the bag's angles with a :class:`DataWarning` (the fit still runs on the speeds).

    The pieces become segments named ``<bag>#1``, ``<bag>#2``, ... (in recording order; a bag
    without a split keeps the name ``<bag>``), each with time from 0 and fitted with its own
    initial state. A piece with fewer than ``checks.min_samples`` samples is dropped with a
    :class:`DataWarning` naming the bag, its time span and why. Saturation, constant outputs and
    excitation are checked over the kept samples of the bag together.

    Raises:
        DataError: naming the bag, topic and problem (also when no piece is long enough: then
            it names the gaps and the other splits).
    """
    checks = checks or Checks()
    path = Path(bag)
    specs = list(outputs) + list(inputs)
    topics = list(dict.fromkeys(s.topic for s in specs))
    ref_topic = outputs[0].topic
    series = read_jointstate_topics(path, topics)
    cols_by_spec = [_signal_column(path, series[s.topic], s) for s in specs]
    angle_cols = _angle_columns(path, series, outputs)
    n_ang = 0 if angle_cols is None else len(angle_cols)
    # angle columns ride after the signals (gap filling alike); they do not split a recording
    ang_specs = [] if angle_cols is None else list(outputs)
    cols_by_spec += angle_cols or []
    stamps_of = {t: series[t].stamps_ns for t in topics}
    breaks = {t: _stamp_breaks(st) for t, st in stamps_of.items()}
    paired, failed = _pair_pieces(path, stamps_of, breaks, ref_topic)
    if not paired:
        raise DataError(failed[0] if failed else
                        f"{path}: topics {', '.join(topics)}: no samples to pair")
    if failed:
        warnings.warn(DataWarning(
            f"{failed[0]}: {len(failed)} of the pieces between stamps that do not increase "
            "could not be paired and are dropped"), stacklevel=2)
    ref_stamps = stamps_of[ref_topic]
    t0 = int(ref_stamps[paired[0][ref_topic][0]])
    problems: list[str] = []
    reasons: list[str] = []
    for topic in topics:
        if breaks[topic].size:
            problems.append(_warn_stamp_breaks(path, topic, stamps_of[topic], breaks[topic], t0))
    if any(breaks[t].size for t in topics):
        reasons.append("stamps that do not increase")
    n_aligned = sum(int(pc[ref_topic].size) for pc in paired)
    if n_aligned < checks.min_samples:
        raise DataError(f"{path}: topic {ref_topic}: too little data: {n_aligned} aligned "
                        f"samples (need at least {checks.min_samples})"
                        + (f"; {'; '.join(problems)}" if problems else ""))
    # Drop the aligned samples with a non-finite value; split there.
    blocks: list[tuple[Array, Array]] = []
    bad_count = [0] * len(specs)
    bad_first: list[tuple[float, int, int, float] | None] = [None] * len(specs)
    for pc in paired:
        stamps = ref_stamps[pc[ref_topic]]
        cols = np.column_stack([c[pc[s.topic]] for c, s in zip(
            cols_by_spec, specs + ang_specs, strict=True)])
        finite = np.isfinite(cols[:, :len(specs)])
        for j, s in enumerate(specs):
            bad = np.flatnonzero(~finite[:, j])
            if bad.size and bad_first[j] is None:
                i = int(bad[0])
                bad_first[j] = ((int(stamps[i]) - t0) * 1e-9, int(stamps[i]),
                                int(pc[s.topic][i]), float(cols[i, j]))
            bad_count[j] += int(bad.size)
        t = (stamps - t0).astype(float) * 1e-9
        good = np.asarray(finite.all(axis=1), dtype=bool)
        blocks += [(t[a:b], cols[a:b]) for a, b in _runs(good)]
    for s, first, count in zip(specs, bad_first, bad_count, strict=True):
        if first is not None:
            problems.append(_warn_non_finite(path, s, first, count))
    if any(bad_count):
        reasons.append("non-finite samples")
    steps = np.concatenate([np.diff(t) for t, _ in blocks] or [np.zeros(0)])
    dt = float(np.median(steps)) if steps.size else math.nan
    if not dt > 0:
        raise DataError(f"{path}: topic {ref_topic}: no two consecutive usable samples"
                        + (f"; {'; '.join(problems)}" if problems else ""))
    pieces: list[tuple[Array, Array]] = []
    gaps: list[Gap] = []
    for t, cols in blocks:
        cuts, found = split_at_gaps(t, dt, checks.max_gap_samples)
        pieces += [(t[a:b], cols[a:b]) for a, b in cuts]
        gaps += found
    if gaps:
        reasons.insert(0, f"gaps of more than {checks.max_gap_samples} missing samples")
    between = " or ".join(reasons)
    split = len(pieces) > 1
    kept: list[tuple[int, Array, Array, int]] = []
    short = [k for k, (t, _) in enumerate(pieces, start=1) if t.size < checks.min_samples]
    for k, (t, cols) in enumerate(pieces, start=1):
        if t.size >= checks.min_samples:
            kept.append((k, *_fill_gaps(t, cols, dt)))
        elif k in short[:_MOST_WARNED]:
            warnings.warn(DataWarning(
                f"{path}: topic {ref_topic}: samples at t = {t[0]:.6f} .. {t[-1]:.6f} s "
                f"(piece {k} of {len(pieces)}, {t.size} samples between {between}) dropped: "
                f"fewer than min_samples = {checks.min_samples}"), stacklevel=2)
    if len(short) > _MOST_WARNED:
        rest = [pieces[k - 1][0] for k in short[_MOST_WARNED:]]
        warnings.warn(DataWarning(
            f"{path}: topic {ref_topic}: {len(rest)} more pieces (pieces "
            f"{short[_MOST_WARNED]} .. {short[-1]} of {len(pieces)}, "
            f"{sum(t.size for t in rest)} samples at t = {rest[0][0]:.6f} .. {rest[-1][-1]:.6f} "
            f"s, between {between}) dropped: fewer than min_samples = {checks.min_samples} "
            "each"), stacklevel=2)
    if not kept:
        sizes = ", ".join(str(t.size) for t, _ in pieces)
        if problems:
            if gaps:
                problems.insert(0, f"{len(gaps)} gap(s) of more than {checks.max_gap_samples} "
                                   f"missing samples: {_gap_list(gaps)}")
            raise DataError(f"{path}: topic {ref_topic}: no piece of at least "
                            f"{checks.min_samples} samples between the splits of the "
                            f"recording: {'; '.join(problems)} (pieces of {sizes} samples)")
        raise DataError(f"{path}: topic {ref_topic}: no piece of at least {checks.min_samples} "
                        f"samples between the {len(gaps)} gap(s) of more than "
                        f"{checks.max_gap_samples} missing samples: {_gap_list(gaps)} (pieces of "
                        f"{sizes} samples)")
    every = np.concatenate([c for _, _, c, _ in kept])
    if n_ang and not np.all(np.isfinite(every[:, len(specs):])):
        bad = ~np.isfinite(every[:, len(specs):])
        j = int(np.flatnonzero(bad.any(axis=0))[0])
        warnings.warn(DataWarning(
            f"{path}: topic {outputs[j].topic}: position[{outputs[j].joint}] is not finite in "
            f"{int(bad[:, j].sum())} of {every.shape[0]} kept samples: no measured angles for "
            "this bag (member angles integrate the measured speed)"), stacklevel=2)
        n_ang = 0
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
                      f"{grid[-1]:.6f} s of the recording (split at {between})",)
        if missing:
            notes += (f"{missing} missing samples filled by linear interpolation",)
        if n_ang:
            notes += ("angles: recorded position of " + ", ".join(
                f"{s.topic} {s.joint}" for s in outputs if s.field == "velocity"),)
        nsig = len(specs)
        seg = make_segment(f"{path}{SEGMENT_SEP}{k}" if split else str(path), grid,
                           filled[:, ny:nsig], filled[:, :ny], [s.name for s in inputs],
                           [s.name for s in outputs],
                           angles=filled[:, nsig:nsig + n_ang] if n_ang else None)
        out.append(intersample(replace(seg, notes=notes), inputs, outputs))
    return out


def load_segment(bag: str | Path, inputs: Sequence[SignalSpec], outputs: Sequence[SignalSpec],
                 checks: Checks | None = None) -> Segment:
    """:func:`load_bag_segments` for a bag that must give exactly one segment.

    Raises:
        DataError: as :func:`load_bag_segments`, or when the bag is split into several
            segments (long gaps, non-finite samples, stamps that do not increase; the message
            names the segments).
    """
    segs = load_bag_segments(bag, inputs, outputs, checks)
    if len(segs) > 1:
        why = segs[0].notes[0].rsplit("(split at ", 1)[-1].rstrip(")")
        raise DataError(f"{bag}: topic {outputs[0].topic}: {why} split the recording into "
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

