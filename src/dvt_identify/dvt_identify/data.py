"""Data for identification: the :class:`Segment` (a recording on a uniform time grid), JointState
bags in and out, the data checks' settings (:class:`Checks`) and pre-processing. Reading a bag
into segments (alignment, checks, splits): :mod:`dvt_identify.bagload`.

Pre-processing: low-pass Butterworth on inputs and outputs alike (like MATLAB ``idfilt``; optionally
zero-phase; the angles with the same filter) and decimation with an anti-alias filter (the angles
are sampled at the kept samples).
"""

from __future__ import annotations

import shutil
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import signal

from dvt_identify.errors import DataError
from dvt_model.errors import BagError, RecordingWarning
from dvt_model.recording import TopicSeries, is_bag, read_topics, write_topics

Array = NDArray[np.float64]
FIELDS = ("position", "velocity", "effort")
#: Joins a bag path and the number of one of its pieces in a segment name (``<bag>#2``).
SEGMENT_SEP = "#"


class DataWarning(UserWarning):
    """Part of a recording is not used (a piece too short between long gaps, a non-finite
    sample, a stamp that does not increase, the cut end of a killed recording); the message
    names the bag, the topic, the time or stamps and why."""


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
        hold: an input's behaviour between its samples (:data:`HOLDS`): ``zoh``, a command the
            actuator holds over the interval that follows the sample (a set-point, a DAC
            output); ``linear``, a sampled continuous signal (a measured motor current, which
            moves during the interval): the simulation holds the interval's mean of the line
            through the two samples (:func:`intersample`).
        sampling: what an output's sample measures (:data:`SAMPLINGS`): ``instant``, the value
            at the sample time (a tachometer read by an A/D converter, an encoder position);
            ``interval``, the mean over the period that ends at the sample (a speed from an
            encoder's count difference, centred half a period early): compared with the
            model's output half a period earlier (:func:`intersample`).
    """

    name: str
    topic: str
    field: str
    joint: str
    scale: float = 1.0
    saturation: tuple[float, float] | None = None
    hold: str = "zoh"
    sampling: str = "instant"


HOLDS: tuple[str, ...] = ("zoh", "linear")
"""An input's behaviour between samples (:attr:`SignalSpec.hold`)."""
SAMPLINGS: tuple[str, ...] = ("instant", "interval")
"""What an output's sample measures (:attr:`SignalSpec.sampling`)."""


JointStateSeries = TopicSeries
"""All messages of one JointState topic: :class:`dvt_model.recording.TopicSeries`, the one series
type (``stamps_ns``, ``names``, ``position``/``velocity``/``effort`` or ``None`` when empty)."""


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
        angles: measured angles, shape (N, ny), or ``None``: column ``j`` is the recorded
            ``position`` of the joint whose ``velocity`` output ``j`` is (in that output's
            scale, e.g. rad for rad/s), 0 for an output that is not a joint's velocity; finite.
            ``None`` when the recording has no positions (the effects then integrate the
            measured speed). Rebuild a segment over some of its samples with :meth:`rows`,
            which keeps them aligned; a ``dataclasses.replace`` of ``t``/``u``/``y`` alone with
            another number of samples drops them (with a note), it cannot know which rows
            are kept.
        output_lag: how far each output's samples lag their sample times [s], length ny, or
            ``None`` (none lags): half the recording's period for an output that is a mean
            over the period ending at the sample (``sampling: interval``,
            :func:`intersample`). The simulation compares such an output with the model's
            output that much earlier (:func:`dvt_identify.simulation.lag_outputs`);
            decimation keeps it (a centred mean of lagged samples lags as much).
        input_hold: each input's behaviour between its samples (:data:`HOLDS`), length nu,
            or ``None`` (all ``zoh``): the samples stay as measured; the simulation holds a
            ``linear`` input's interval mean (:func:`held_inputs`).
    """

    name: str
    t: Array
    u: Array
    y: Array
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dt: float
    notes: tuple[str, ...] = field(default_factory=tuple)
    angles: Array | None = None
    output_lag: tuple[float, ...] | None = None
    input_hold: tuple[str, ...] | None = None

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
        if self.input_hold is not None and (
                len(self.input_hold) != len(self.input_names)
                or any(h not in HOLDS for h in self.input_hold)):
            raise DataError(f"{self.name}: input_hold: expected {len(self.input_names)} of "
                            f"{list(HOLDS)} (one per input), got {self.input_hold!r}")
        if self.output_lag is not None and (
                len(self.output_lag) != len(self.output_names)
                or not all(0.0 <= v < float("inf") for v in self.output_lag)):
            raise DataError(f"{self.name}: output_lag: expected {len(self.output_names)} "
                            f"lags >= 0 [s] (one per output), got {self.output_lag!r}")
        a = self.angles
        if a is None:
            return
        ny = len(self.output_names)
        if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[1] != ny:
            raise DataError(f"{self.name}: angles: expected shape (N, {ny}) (one column per "
                            f"output), got {np.shape(a)}")
        if a.shape[0] != n:  # rebuilt by replace() on t/u/y only: the rows kept are unknown
            object.__setattr__(self, "angles", None)
            object.__setattr__(self, "notes", (
                *self.notes, f"measured angles dropped: the segment was rebuilt with {n} of "
                f"{a.shape[0]} samples without them (member angles integrate the speed)"))
            return
        if not np.all(np.isfinite(a)):
            bad = np.argwhere(~np.isfinite(a))[0]
            raise DataError(f"{self.name}: angles: non-finite value {a[bad[0], bad[1]]} at "
                            f"sample {int(bad[0])}, column {self.output_names[int(bad[1])]}")

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])

    def rows(self, start: int, stop: int | None = None, name: str | None = None,
             from_zero: bool = False) -> Segment:
        """The samples ``[start, stop)`` (``stop`` ``None``: to the end) as a segment: time,
        inputs, outputs and angles cut alike.

        Args:
            name: the new segment's name (default: this one's).
            from_zero: time from 0 at the first kept sample (else the times are kept).
        """
        t = self.t[start:stop]
        return replace(self, name=self.name if name is None else name,
                       t=t - t[0] if from_zero and t.size else t, u=self.u[start:stop],
                       y=self.y[start:stop],
                       angles=None if self.angles is None else self.angles[start:stop])


def make_segment(name: str, t: ArrayLike, u: ArrayLike, y: ArrayLike,
                 input_names: Sequence[str], output_names: Sequence[str],
                 angles: ArrayLike | None = None) -> Segment:
    """Build a :class:`Segment` from arrays (1-D arrays are one signal), checking the grid.

    Args:
        angles: optional measured angles, shape (N, ny) (see :attr:`Segment.angles`).

    Raises:
        DataError: too few samples, time not increasing, or an array of the wrong shape
            (naming ``name`` and the field).
    """
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
    a2: Array | None = None
    if angles is not None:
        a2 = np.asarray(angles, dtype=float)
        if a2.ndim == 1:
            a2 = a2[:, None]
        if a2.shape != y2.shape:
            raise DataError(f"{name}: angles: expected shape {y2.shape} (as the outputs), "
                            f"got {a2.shape}")
    return Segment(name=name, t=tt - tt[0], u=u2, y=y2, input_names=tuple(input_names),
                   output_names=tuple(output_names), dt=dt, angles=a2)


def intersample(seg: Segment, inputs: Sequence[SignalSpec], outputs: Sequence[SignalSpec]
                ) -> Segment:
    """``seg`` with its signals put on the simulation's timing, at the recording's own rate
    (before any decimation, which then averages the result exactly).

    The simulation holds input sample ``k`` over ``[t_k, t_k+1)`` and compares its output at
    ``t_k`` with output sample ``k``. An input with ``hold: linear`` (a sampled continuous
    signal) is held at ``(u_k + u_k+1) / 2``, the mean of the line through the two samples
    over that interval (:func:`held_inputs`; :attr:`Segment.input_hold`): held as sampled, it
    would act half a period late (measured on the simulated plant, whose motor current
    follows its reference with a 1-ms lag: band lags 4 % long at the 5-ms fit step, band
    gains 1.6-2.4 % high at 1 ms). An output with ``sampling: interval`` (the mean over the
    period ending at ``t_k``, centred at ``t_k - T/2``) would show a delay of half a period
    against an instantaneous model output: :attr:`Segment.output_lag` says ``T/2`` for it,
    and the simulation compares it with the model's output ``T/2`` earlier. The samples
    themselves stay as measured: averaging neighbours would correlate their noise, and the
    noise floors the loop stops at are estimated from them. A note names what was done.

    Args:
        seg: a segment at the recording's rate, columns in the order of ``inputs`` and
            ``outputs``.
        inputs, outputs: the signal specs of its columns.

    Raises:
        DataError: the specs do not match the segment's columns (naming both).
    """
    if (tuple(s.name for s in inputs) != seg.input_names
            or tuple(s.name for s in outputs) != seg.output_names):
        raise DataError(f"{seg.name}: intersample: signal specs "
                        f"{[s.name for s in inputs]} / {[s.name for s in outputs]} do not "
                        f"match the segment's columns {list(seg.input_names)} / "
                        f"{list(seg.output_names)}")
    lin = [j for j, s in enumerate(inputs) if s.hold == "linear"]
    itv = [j for j, s in enumerate(outputs) if s.sampling == "interval"]
    if seg.n < 2 or not (lin or itv):
        return seg
    notes = list(seg.notes)
    hold = None
    if lin:
        hold = tuple(s.hold for s in inputs)
        notes.append("inputs held linear between samples (each interval holds its mean): "
                     + ", ".join(inputs[j].name for j in lin))
    lag = None
    if itv:
        lag = tuple(0.5 * seg.dt if j in itv else 0.0 for j in range(len(outputs)))
        notes.append(f"interval-mean outputs compared with the model {0.5 * seg.dt:.6g} s "
                     "(half a period) earlier: " + ", ".join(outputs[j].name for j in itv))
    return replace(seg, notes=tuple(notes), output_lag=lag, input_hold=hold)


def held_inputs(seg: Segment) -> Array:
    """The inputs (N, nu) the simulation holds over each interval: ``u`` itself, a
    ``linear`` input (:attr:`Segment.input_hold`) replaced by its interval means
    ``(u_k + u_k+1) / 2`` (the last sample, without a successor, as measured)."""
    hold = seg.input_hold
    if hold is None or "linear" not in hold or seg.n < 2:
        return seg.u
    lin = [j for j, h in enumerate(hold) if h == "linear"]
    u = seg.u.copy()
    u[:-1, lin] = 0.5 * (seg.u[:-1, lin] + seg.u[1:, lin])
    return u


# --------------------------------------------------------------------------------------------
# Bag I/O


def read_jointstate_topics(bag: str | Path, topics: Sequence[str]) -> dict[str, TopicSeries]:
    """Read the JointState ``topics`` of ``bag`` in one pass; other topics are ignored.

    :func:`dvt_model.recording.read_topics` (bulk decoding of the raw CDR; empty fields are
    ``None``). Values are returned as recorded (no stamp or NaN checks). A killed recording
    (unfinished MCAP file) is read up to its last complete chunk: its
    :class:`~dvt_model.errors.RecordingWarning` is passed on as a :class:`DataWarning`.

    Raises:
        DataError: the bag cannot be opened or holds no complete message, a topic is missing,
            not JointState, has no messages, a message is undecodable, or its joint names or
            array lengths change between messages (the message names bag, topic, message index
            and field).
    """
    path = Path(bag)
    if not path.exists():
        raise DataError(f"{path}: bag not found")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RecordingWarning)
            series = read_topics(path, topics)
    except BagError as exc:
        raise DataError(str(exc)) from exc
    for w in caught:
        if issubclass(w.category, RecordingWarning):
            warnings.warn(DataWarning(str(w.message)), stacklevel=2)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return series


def write_jointstate_bag(path: str | Path, topics: Mapping[str, TopicSeries],
                         overwrite: bool = False) -> Path:
    """Write JointState ``topics`` to a new rosbag2/MCAP bag at ``path``.

    Every message's ``header.stamp`` and the bag's log time are the series' stamp. Empty fields
    are written as empty arrays. With ``overwrite`` an existing *bag* directory (one that holds a
    ``metadata.yaml``) is replaced; any other existing path is refused. Uses
    :func:`dvt_model.recording.write_topics` (the one writer).

    Raises:
        DataError: the path exists, or a series has inconsistent shapes (names bag, topic and
            field).
    """
    out = Path(path)
    if out.exists():
        if overwrite and is_bag(out):
            shutil.rmtree(out)
        else:
            raise DataError(f"{out}: output bag already exists"
                            + ("" if overwrite else " (pass --force to replace it)")
                            + ("" if not overwrite else " and is not a bag directory"))
    try:
        return write_topics(out, topics)
    except BagError as exc:
        raise DataError(str(exc)) from exc


# --------------------------------------------------------------------------------------------
# Data checks


@dataclass(frozen=True)
class Checks:
    """Data checks applied to every bag.

    Attributes:
        min_samples: fewest aligned samples a bag, and each segment cut from it, may have; a
            shorter piece (between long gaps, non-finite samples or stamps that do not
            increase) is dropped with a :class:`DataWarning`.
        max_gap_samples: longest run of missing samples filled by interpolation; a longer gap
            splits the recording into segments (see
            :func:`~dvt_identify.bagload.load_bag_segments`).
        max_saturated_fraction: largest fraction of samples allowed at a signal's saturation
            limits.
        min_relative_std: a signal whose std is below this times (1 + |mean|) is "constant".
    """

    min_samples: int = 100
    max_gap_samples: int = 3
    max_saturated_fraction: float = 0.01
    min_relative_std: float = 1e-9


def _constant(x: Array, checks: Checks) -> bool:
    return bool(np.std(x) <= checks.min_relative_std * (1.0 + abs(float(np.mean(x)))))


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
    ang = None if seg.angles is None else np.asarray(filt(sos, seg.angles, axis=0))
    note = (f"low-pass Butterworth order {order} at {cutoff_hz:g} Hz"
            + (" (zero-phase)" if zero_phase else "")
            + (", angles alike" if ang is not None else ""))
    return replace(seg, u=u, y=y, angles=ang, notes=(*seg.notes, note))


def decimate(seg: Segment, q: int) -> Segment:
    """Keep every ``q``-th sample after a zero-phase anti-alias filter (order-8 Chebyshev I);
    the measured angles are sampled at the kept samples (the filter is zero-phase: the
    filtered speeds stay aligned with the sampled angles).

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
    ang = None if seg.angles is None else seg.angles[::q][: y.shape[0]]
    return replace(seg, t=t, u=u, y=y, dt=seg.dt * q, angles=ang,
                   notes=(*seg.notes, f"decimated by {q} to {1.0 / (seg.dt * q):g} Hz"))
