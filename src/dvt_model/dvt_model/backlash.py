"""Lost motion, written once (pure; numpy; the scalar laws compile with ``numba.njit``).

Three forms of backlash, shared by the identifier's ``backlash`` candidates
(``dvt_identify.effects.backlash``) and the model node's ``dead_zone``, ``play`` and
``spline_play`` terms (:mod:`dvt_model.terms`, :class:`OutputPlay`, :class:`OutputSpline`):

- :func:`dead_zone`: lost motion seen from an input, ``u -> u - clip(u, -delta, delta)``
  (stateless);
- :func:`play`: the play (backlash) operator between a member's angle and the angle its sensor
  reads: the sensed angle stays where it is while the member moves within ``+-delta`` of it,
  and is dragged along at the edge;
- :func:`spline_substep`: a load shaft driven through a compliant spline with play: the contact
  (stiffness ``a = wn^2``, damping ``b = 2 zeta wn`` per unit load inertia) acts only outside the
  gap ``+-half`` and never pulls; one semi-implicit Euler sub-step of the load speed and the
  twist.

The scalar laws spell everything out in plain arithmetic so that ``numba.njit(law)`` compiles
them unchanged (the identifier's kernels do).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

SPLINE_SUBSTEP_PHASE = 0.2
"""Largest contact phase ``wn h`` [rad] per explicit sub-step of the spline contact (the
explicit contact stays accurate below it)."""


def dead_zone(u: Any, delta: Any) -> Any:
    """``u - clip(u, -delta, delta)``: 0 within ``+-delta``, shifted by ``delta`` outside;
    ``delta >= 0`` [unit of ``u``]; scalars and arrays alike (``delta`` broadcast)."""
    return np.sign(u) * np.maximum(np.abs(u) - delta, 0.0)


def play(sensed: float, theta: float, delta: float) -> float:
    """One step of the play operator: the sensed angle after the member moved to ``theta``
    [rad], when the sensed angle was ``sensed`` and the half-width of the play is ``delta``
    (>= 0): ``sensed`` clamped into ``[theta - delta, theta + delta]``."""
    if theta - sensed > delta:
        return theta - delta
    if sensed - theta > delta:
        return theta + delta
    return sensed


def spline_substep(wl: float, z: float, w: float, h: float, half: float, a: float, b: float
                   ) -> tuple[float, float]:
    """One sub-step of length ``h`` [s] of a load behind a compliant spline with play.

    Args:
        wl: load speed [rad/s] at the sub-step start.
        z: twist ``theta_member - theta_load`` [rad] at the sub-step start.
        w: the member's speed over the sub-step [rad/s].
        h: sub-step [s].
        half: half the total play [rad] (>= 0).
        a: contact stiffness per unit load inertia, ``wn^2`` [1/s^2].
        b: contact damping per unit load inertia, ``2 zeta wn`` [1/s].

    Returns:
        ``(wl, z)`` at the sub-step end (load speed first, then the twist with the new speed).
    """
    if z > half:
        t = a * (z - half) + b * (w - wl)
        t = t if t > 0.0 else 0.0
    elif z < -half:
        t = a * (z + half) + b * (w - wl)
        t = t if t < 0.0 else 0.0
    else:
        t = 0.0
    wl_new = wl + h * t
    return wl_new, z + h * (w - wl_new)


def spline_substeps(dt: float, wn: float) -> int:
    """Sub-steps of a sample interval ``dt`` [s] for a contact frequency ``wn`` [rad/s]: the
    smallest even count (at least 2) with ``wn h <= SPLINE_SUBSTEP_PHASE``."""
    sub = max(2, math.ceil(dt * wn / SPLINE_SUBSTEP_PHASE))
    return sub + sub % 2


class OutputMap(Protocol):
    """A sensor reading a member's speed through lost motion, sample by sample (state
    inside)."""

    def reset(self) -> None:
        """Start again at the next sample (an anchor of the model)."""

    def sensed_speed(self, w: float, dt: float) -> float:
        """The speed the sensor reads [rad/s] for the member speed ``w`` [rad/s] at this
        sample, ``dt`` [s] the interval since the previous one (``<= 0``: right after a
        reset)."""


@dataclass
class OutputPlay:
    """The sensed speed of a member seen through rigid play, sample by sample (the model
    node's ``play`` term).

    The member's angle is integrated from its speed, ``theta_{k+1} = theta_k + w_k dt``, the
    sensed angle follows it through :func:`play`, and the sensed speed at sample ``k`` is the
    sensed angle's rate over the interval that starts there, ``(s_{k+1} - s_k) / dt`` (the
    identifier's output map on evenly sampled data; live, ``dt`` is the interval that ended at
    the sample). :meth:`reset` starts with the sensed angle on the member's (the gap centred).

    Attributes:
        delta: half-width of the play [rad].
    """

    delta: float
    _theta: float = field(default=0.0, repr=False)
    _sensed: float = field(default=0.0, repr=False)

    def reset(self) -> None:
        """Start again: member and sensed angle together (at an anchor)."""
        self._theta = 0.0
        self._sensed = 0.0

    def sensed_speed(self, w: float, dt: float) -> float:
        """The sensed speed [rad/s] for the member speed ``w`` [rad/s] at this sample, ``dt``
        [s] the sample interval (``<= 0``: ``w``, the state unchanged)."""
        if not dt > 0.0:
            return w
        theta = self._theta + w * dt
        sensed = play(self._sensed, theta, self.delta)
        speed = (sensed - self._sensed) / dt
        self._theta, self._sensed = theta, sensed
        return speed


@dataclass
class OutputSpline:
    """The speed of a load shaft driven by a member through a compliant spline with play,
    sample by sample (the model node's ``spline_play`` term).

    Over each sample interval the member speed is interpolated linearly between the two
    samples and the contact advanced in :func:`spline_substeps` sub-steps of
    :func:`spline_substep`; the result is the load speed at the sample instant. (The
    identifier averages it over the sample interval centred on the sample, the anti-alias
    filter of its decimated data; at the node's raw rate the contact transients it averages
    are a fraction of a sample.) :meth:`reset` starts with the load moving with the member and
    the gap centred.

    Attributes:
        gap: total play [rad] (``half = gap / 2``).
        wn: contact frequency ``sqrt(k / J_load)`` [rad/s].
        zeta: contact damping ratio [1].
    """

    gap: float
    wn: float
    zeta: float
    _wl: float = field(default=0.0, repr=False)
    _z: float = field(default=0.0, repr=False)
    _w: float | None = field(default=None, repr=False)

    def reset(self) -> None:
        """Start again at the next sample: load with the member, gap centred."""
        self._w = None
        self._z = 0.0

    def sensed_speed(self, w: float, dt: float) -> float:
        """The load speed [rad/s] at this sample for the member speed ``w`` [rad/s]; ``dt``
        [s] the interval since the previous sample (the first sample after :meth:`reset`, or
        ``dt <= 0``: the load moves with the member)."""
        if self._w is None or not dt > 0.0:
            self._w, self._wl = w, w
            return w
        sub = spline_substeps(dt, self.wn)
        h = dt / sub
        half, a, b = 0.5 * self.gap, self.wn * self.wn, 2.0 * self.zeta * self.wn
        w0, dw = self._w, (w - self._w) / sub
        wl, z = self._wl, self._z
        for i in range(sub):
            wl, z = spline_substep(wl, z, w0 + dw * (i + 0.5), h, half, a, b)
        self._w, self._wl, self._z = w, wl, z
        return wl
