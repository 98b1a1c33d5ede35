"""Advice for a parameter the identifiability check (:mod:`dvt_identify.identifiability`) finds
undetermined: the description's own experiment for it (:func:`experiment_for`), else generic
advice from the data and the model (:func:`generic_advice`: the mode or pole of the linear
structure it moves most and the share of the input power there, a longer record, or the
parameters it moves only together with)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.description import ExperimentSpec
from dvt_identify.fisher import MAX_RELATIVE_STD
from dvt_identify.structures import ModelStructure

Array = NDArray[np.float64]


def experiment_for(name: str, table: Sequence[ExperimentSpec]) -> tuple[str, str] | None:
    """The experiment (command or procedure) and what it excites for parameter ``name``: the
    first row of ``table`` (a description's ``experiments``) whose pattern matches, its named
    groups filled into ``excites``; ``None`` when no row matches."""
    for row in table:
        m = re.search(row.parameters, name)
        if m:
            groups = {k: (v or "") for k, v in m.groupdict().items()}
            try:
                return row.run, row.excites.format(**groups)
            except (KeyError, IndexError, ValueError):
                return row.run, row.excites
    return None


@dataclass(frozen=True)
class _Pole:
    """The eigenvalue of the linear part a parameter moves most (relative to its size)."""

    lam: complex
    mode: int  # 1-based index among the oscillating modes (slowest first); 0 for a real pole

    def where(self) -> str:
        f = abs(self.lam) / (2 * math.pi)
        if self.mode:
            zeta = -self.lam.real / abs(self.lam)
            return f"mode {self.mode} near {f:.3g} Hz (damping ratio {zeta:.2g})"
        return f"the pole at {f:.3g} Hz (time constant {1 / abs(self.lam):.3g} s)"

    def band(self) -> tuple[float, float]:
        """Frequency band [Hz] that excites it: around a mode, below twice a real pole."""
        f = abs(self.lam) / (2 * math.pi)
        return (f / 1.5, 1.5 * f) if self.mode else (0.0, 2.0 * f)

    def band_words(self) -> str:
        lo, hi = self.band()
        if self.mode:
            return f"between {lo:.3g} and {hi:.3g} Hz"
        return f"below {hi:.3g} Hz (inputs held longer than {1 / abs(self.lam):.3g} s)"


def _poles_moved(structure: ModelStructure, theta: Array) -> list[_Pole | None]:
    """For each structure parameter, the eigenvalue of ``A`` it moves most relative to the
    eigenvalue's size (first-order eigenvalue sensitivity ``(V^-1 dA V)_kk`` to a relative
    change), ignoring zero eigenvalues (a free angle); ``None`` when it moves none or ``A`` is
    not diagonalisable."""
    none: list[_Pole | None] = [None] * theta.size
    try:
        A = np.asarray(structure.matrices(theta)[0], dtype=float)
        lam, V = np.linalg.eig(A)
        if not np.all(np.isfinite(lam)) or np.linalg.cond(V) > 1e10:
            return none
        Vinv = np.linalg.inv(V)
    except (np.linalg.LinAlgError, ValueError):
        return none
    size = np.abs(lam)
    live = (size > 1e-9 * max(float(size.max(initial=0.0)), 1e-300)) & (lam.imag >= 0)
    oscill = sorted((k for k in range(lam.size) if live[k] and lam[k].imag > 1e-9),
                    key=lambda k: size[k])
    out: list[_Pole | None] = []
    for i in range(theta.size):
        scale = abs(float(theta[i])) or 1.0
        h = 1e-6 * scale
        tp = theta.copy()
        tp[i] += h
        try:
            dA = (np.asarray(structure.matrices(tp)[0], dtype=float) - A) / h * scale
        except (np.linalg.LinAlgError, ValueError):
            out.append(None)
            continue
        d = np.abs(np.einsum("ij,jk,ki->i", Vinv, dA, V)) / np.maximum(size, 1e-300)
        d = np.where(live, d, 0.0)
        k = int(np.argmax(d)) if d.size else 0
        if not d.size or d[k] <= 1e-9:
            out.append(None)
            continue
        out.append(_Pole(complex(lam[k]), oscill.index(k) + 1 if k in oscill else 0))
    return out


def _band_share(segments: Sequence[Segment], lo: float, hi: float) -> float:
    """Share of the inputs' power (each varying input's own, averaged) within ``[lo, hi]`` Hz
    in ``segments`` (their periodograms pooled); 0 when no input varies."""
    if not segments:
        return 0.0
    shares = []
    for j in range(segments[0].u.shape[1]):
        inside = total = 0.0
        for s in segments:
            u = s.u[:, j] - float(np.mean(s.u[:, j]))
            p = np.abs(np.fft.rfft(u)) ** 2
            f = np.fft.rfftfreq(u.size, s.dt)
            inside += float(np.sum(p[(f >= lo) & (f <= hi) & (f > 0)]))
            total += float(np.sum(p[f > 0]))
        if total > 0:
            shares.append(inside / total)
    return float(np.mean(shares)) if shares else 0.0


def generic_advice(name: str, kind: str, rel_std: float, *, partners: Sequence[str] = (),
                   effect: str = "", pole: _Pole | None = None, share: float = 0.0,
                   seconds: float = 0.0, input_name: str = "", influence: float = 0.0,
                   probe: float | None = None) -> tuple[str, str]:
    """What would determine parameter ``name``, from the data and the model, when the
    description names no experiment for it: ``(what to record, why)``.

    Args:
        name: the parameter.
        kind: why it is not determined: ``unused`` (its effect's input never varies),
            ``quiet`` (its effect is never engaged), ``null`` (in a null direction), ``weak``
            (a finite predicted relative std above :data:`MAX_RELATIVE_STD`).
        rel_std: its predicted relative std.
        partners: the parameters it moves the outputs only together with (``null``).
        effect: label of its effect ("" for the structure).
        pole: the mode or pole of the linear part it moves most (structure parameters).
        share: share of the input power that excites that pole in this recording.
        seconds: length of this recording [s].
        input_name: its effect's input (``unused``).
        influence: its effect's influence at the probe [output std] (``quiet``, ``null``).
        probe: the probe value of the parameter (``quiet``, ``null``).
    """
    if kind == "unused":
        return (f"a record that uses input {input_name}",
                f"{effect} acts only when {input_name} varies")
    if kind == "quiet":
        at = f"{name} = {probe:.3g}" if probe is not None else "its prior"
        return (f"a record in which {effect} acts",
                f"at {at} it changes the outputs of this one by {influence:.2g} output std")
    if kind == "null":
        if partners:
            return (f"an experiment that moves {name} differently from "
                    f"{', '.join(partners)}: a further sensor or input (a longer record does "
                    "not help)", f"the outputs see {name} only together with them")
        if effect and probe is not None:
            return (f"a prior where {effect} acts (e.g. {name} {probe:.3g} in its `initial`)",
                    f"at its prior no output responds to it, at {probe:.3g} the outputs "
                    f"change by {influence:.2g} output std")
        return (f"an input or sensor that {name} acts on",
                "no output of this recording responds to it")
    factor = (rel_std / MAX_RELATIVE_STD) ** 2 if math.isfinite(rel_std) else math.inf
    longer = f"a record about {factor:.2g} x as long ({factor * seconds:.3g} s)"
    if pole is not None:
        return (f"more excitation {pole.band_words()}: a richer input there, or {longer}",
                f"{name} moves {pole.where()} most; this recording puts {100 * share:.2g} % "
                "of its input power there")
    what = f"{effect} engaged more often" if effect else "a richer input"
    return (f"{what}, or {longer}",
            f"the predicted std of {name} falls as one over the root of the record length")

