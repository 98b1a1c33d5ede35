"""The rate an output-error fit runs at (:func:`fit_segments`, :func:`fit_decimation`): each
segment's own rate, decimated as far as the model's fastest pole and shortest lag allow
(:class:`~dvt_identify.fit.OEFit` fits what this returns). Pure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment
from dvt_identify.simulation import OEModel, zoh_decimate

Array = NDArray[np.float64]

POLE_STEP = 0.2
"""Largest ``|lambda_max| dt`` of the fit step (the fastest pole of the linear part)."""
LAG_STEPS = 4.0
"""Fewest fit steps per effect time constant (a band's engagement lag)."""
MIN_FIT_SAMPLES = 1000
"""Fewest samples a segment keeps after the fit decimation."""


def fit_decimation(dt: float, fastest_pole: float, time_constants: Sequence[float] = (),
                   n: int | None = None) -> int:
    """Decimation factor of one segment for fitting: the largest ``q`` whose fit step
    ``q dt`` resolves the dynamics, ``|lambda_max| q dt <= POLE_STEP`` and at least
    ``LAG_STEPS`` steps per effect time constant, keeping ``MIN_FIT_SAMPLES`` samples (``n``:
    the segment's length). 1 when the data are not faster than that (e.g. 62.5 Hz).

    Args:
        dt: the segment's sample time [s].
        fastest_pole: ``max |eig(A)|`` [1/s] of the model's linear part (0: unknown).
        time_constants: the effects' time constants [s] (non-positive ones are ignored).
        n: samples of the segment (``None``: no length limit).
    """
    if not (dt > 0 and math.isfinite(dt)):
        return 1
    step = math.inf
    if fastest_pole > 0 and math.isfinite(fastest_pole):
        step = POLE_STEP / fastest_pole
    taus = [float(t) for t in time_constants if t > 0 and math.isfinite(t)]
    if taus:
        step = min(step, min(taus) / LAG_STEPS)
    if not math.isfinite(step):
        return 1
    q = max(1, math.floor(step / dt * (1 + 1e-3)))
    if n is not None:
        q = max(1, min(q, n // MIN_FIT_SAMPLES))
    return q


def resolves_intersample(dt: float, fastest_pole: float, time_constants: Sequence[float] = ()
                         ) -> bool:
    """Whether samples ``dt`` [s] apart resolve the model's dynamics finely enough for a
    statement about the signals *between* them (:func:`dvt_identify.data.intersample`: a
    current linear between samples, an encoder's interval mean half a period back): the fit
    step those dynamics need (:func:`fit_decimation`) is at least two sample periods. A
    coarser recording (62.5 Hz for the DVT: its bands' 20-ms lags span about one period)
    says nothing about the signal between its samples, and the simulation's own convention
    (inputs held, outputs at the sample) stays."""
    return fit_decimation(dt, fastest_pole, time_constants) >= 2


def model_time_scales(model: OEModel, theta: Array | None = None) -> tuple[float, list[float]]:
    """``max |eig(A)|`` [1/s] (0 if it cannot be computed) and the effects' time constants [s]
    of ``model`` at ``theta`` (default: the specs' initial values)."""
    th = model.initial() if theta is None else theta
    try:
        A, _, _ = model.structure.matrices(th[: model.n_struct])
        eig = np.linalg.eigvals(A)
        pole = float(np.max(np.abs(eig))) if A.size and np.all(np.isfinite(eig)) else 0.0
    except (np.linalg.LinAlgError, ValueError):
        pole = 0.0
    taus = [t for e, p in zip(model.effects, model.effect_params(th), strict=True)
            for t in e.time_constants(p)]
    return pole, taus


def fit_segments(segments: Sequence[Segment], model: OEModel, fit_decimate: int = 0
                 ) -> tuple[list[Segment], list[str]]:
    """The estimation segments at their fit rates, and notes saying what was done.

    ``fit_decimate`` >= 1 decimates every segment by that factor (less where a segment would
    keep fewer than 10 samples); 0 chooses each segment's factor from its rate and the model's
    dynamics at its initial values (:func:`fit_decimation`), so recordings of different rates
    get a similar fit step. The decimation is consistent with the simulation's zero-order hold
    (:func:`~dvt_identify.simulation.zoh_decimate`)."""
    pole, taus = model_time_scales(model)
    out: list[Segment] = []
    notes: list[str] = []
    for seg in segments:
        if fit_decimate >= 1:
            q = max(1, min(int(fit_decimate), seg.n // 10))
        else:
            q = fit_decimation(seg.dt, pole, taus, seg.n)
        out.append(zoh_decimate(seg, q) if q > 1 else seg)
        if q > 1:
            notes.append(f"{seg.name}: estimation data decimated by {q} for fitting and "
                         f"scoring ({1.0 / seg.dt:g} -> {1.0 / (seg.dt * q):g} Hz"
                         + (", chosen from the dynamics: fastest pole "
                            f"{pole:.3g} 1/s, shortest time constant "
                            f"{min(taus) if taus else math.inf:.3g} s" if fit_decimate < 1
                            else "") + "); figures at the full rate")
    rates = sorted({round(1.0 / s.dt, 6) for s in out})
    if len(rates) > 1:
        notes.append("segments fitted jointly at different rates: "
                     + ", ".join(f"{r:g} Hz" for r in rates))
    return out, notes
