"""Band-brake law and engagement.

Static torque (band brake, thesis eq. 4.82 in form): the brake motor's torque ``k_b i`` is
turned by the screw/lever into a band pull ``F = G k_b i`` and the wrapped band holds

    T_static(i) = F (exp(mu theta) - 1) r_drum            [N m]

(about 1 N m at 0.125 A with the bundled data). The band's available torque follows the
static value with a first-order lag, ``T_cap' = (T_static(i) - T_cap) / tau``, so a step of
current gives ``T_cap = T_static (1 - exp(-t / tau))``. While the ring slips the band applies
``-T_cap sign(omega_ring)``; it locks the ring when the ring's speed reaches zero and the
holding torque needed is within ``static_factor * T_cap``.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dvt_model.params import BrakeParams


def static_torque(brake: BrakeParams, current: ArrayLike) -> NDArray[np.float64]:
    """Static band torque [N m] for brake-motor current(s) [A]; negative currents release.

    Shape follows ``current``.
    """
    i = np.asarray(current, dtype=float)
    return np.asarray(brake.gain * np.clip(i, 0.0, None))


def band_torques(brake: BrakeParams, current: ArrayLike) -> NDArray[np.float64]:
    """Static torque of each band [N m] for the three brake-motor currents [A], shape (3,):
    each band's own gain (:attr:`BrakeParams.gains`); negative currents release."""
    i = np.asarray(current, dtype=float).reshape(3)
    return np.asarray(brake.gains * np.clip(i, 0.0, None))


def engagement_profile(t: ArrayLike, time_constant: float) -> NDArray[np.float64]:
    """Normalised first-order engagement ``1 - exp(-t/tau)`` (0 for t < 0), shape of ``t``."""
    tt = np.asarray(t, dtype=float)
    return np.asarray(np.where(tt > 0.0, -np.expm1(-np.clip(tt, 0.0, None) / time_constant), 0.0))


@overload
def lag_mean_factor(dt: float, time_constant: float) -> float: ...


@overload
def lag_mean_factor(dt: float, time_constant: NDArray[np.float64]) -> NDArray[np.float64]: ...


def lag_mean_factor(dt: float, time_constant: float | NDArray[np.float64]
                    ) -> float | NDArray[np.float64]:
    """Mean over a step ``dt`` [s] of a first-order lag's remaining gap, as a share of the gap
    at the step start: ``(1 - exp(-dt / tau)) tau / dt`` (written with ``expm1``), a float for
    a float ``time_constant`` [s], else its shape. A lag from ``x0`` toward a held ``x``
    averages ``x + (x0 - x) lag_mean_factor(dt, tau)`` over the step: the band capacities
    (:func:`capacity_step`), the plant's motor-current lag and band release, and the
    identifier's engagement transform (``dvt_identify.effects.brakes``) hold this one mean."""
    if isinstance(time_constant, np.ndarray):
        return np.asarray(-np.expm1(-dt / time_constant) * time_constant / dt)
    tau = float(time_constant)
    return -math.expm1(-dt / tau) * tau / dt


def capacity_step(capacity: NDArray[np.float64], target: NDArray[np.float64], dt: float,
                  time_constant: float | NDArray[np.float64]
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Advance the first-order band capacity by ``dt`` exactly (``time_constant`` [s]: one for
    all bands or one per band, shape (3,)).

    Args:
        capacity: capacity at the step start [N m], shape (3,).
        target: static torque held over the step [N m], shape (3,).

    Returns:
        (capacity at the step end, mean capacity over the step), each shape (3,).
    """
    e = np.exp(-dt / time_constant)
    end = target + (capacity - target) * e
    mean = target + (capacity - target) * lag_mean_factor(dt, time_constant)
    return end, mean


class BandLaw:
    """:func:`band_torques` and :func:`capacity_step` for one band-brake data set on plain
    floats, for a per-sample loop (:meth:`dvt_model.hybrid.HybridModel.step`): the same
    operations in the same order, so the same results bit for bit, with the per-band gains
    and time constants converted once and ``exp(-dt / tau)`` kept per ``dt`` (the node's
    float-second stamps give a few distinct step lengths).
    """

    def __init__(self, brake: BrakeParams) -> None:
        self.gains: list[float] = [float(g) for g in brake.gains]
        self.time_constants = np.asarray(brake.time_constants, dtype=float)
        # exp(-dt / tau) and lag_mean_factor(dt, tau) per band, by dt
        self._decay: dict[float, tuple[list[float], list[float]]] = {}

    def targets(self, current: list[float]) -> list[float]:
        """Static torque of each band [N m] for the three brake-motor currents [A]
        (:func:`band_torques`)."""
        return [g * _clip_low(i) for g, i in zip(self.gains, current, strict=True)]

    def step(self, capacity: list[float], target: list[float], dt: float
             ) -> tuple[list[float], list[float]]:
        """(capacity at the step end, mean capacity over the step) [N m], 3 each
        (:func:`capacity_step` with these time constants)."""
        kept = self._decay.get(dt)
        if kept is None:
            kept = (np.exp(-dt / self.time_constants).tolist(),
                    lag_mean_factor(dt, self.time_constants).tolist())
            if len(self._decay) < 1024:
                self._decay[dt] = kept
        end = []
        mean = []
        for c, x, e, f in zip(capacity, target, kept[0], kept[1], strict=True):
            end.append(x + (c - x) * e)
            mean.append(x + (c - x) * f)
        return end, mean


def _clip_low(x: float) -> float:
    """``np.clip(x, 0.0, None)`` for one float (-0.0 -> 0.0, NaN stays NaN)."""
    if x > 0.0:
        return x
    return 0.0 if x <= 0.0 else x
