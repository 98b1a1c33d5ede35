"""Sample-by-sample prediction of the measured speeds (the model node's core; no rclpy).

The predictor is fed each measured sample ``(stamp, motor current, brake currents, speeds)``.
It advances its model from the previous sample's stamp to this one with the previous sample's
inputs held (zero-order hold, as the controller applies them) and returns the prediction for
this stamp and the residual ``measured - predicted``.

Initialisation and re-anchoring:

- The first sample anchors the model state to the measured speeds (the model starts where the
  machine is; the band capacities start at their static value for the measured currents if
  the ring is still, else at zero).
- ``mode="simulate"`` (default): afterwards the model runs free on the measured inputs, so the
  residual is the output-error (simulation) residual that the identifier fits and judges. It
  re-anchors only when the stream restarts: a stamp that goes backwards or a gap longer than
  ``gap_reset`` seconds (a new recording, a controller reset).
- ``mode="reanchor"``: additionally re-anchors every ``reanchor_period`` seconds, so the
  residual shows the model's short-horizon prediction error and never drifts; useful to watch
  a live machine for hours.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dvt_model.brake import band_torques, capacity_step
from dvt_model.errors import SimulationError
from dvt_model.hybrid import HybridModel, HybridState
from dvt_model.linear import LinearModel
from dvt_model.params import BrakeParams

Array = NDArray[np.float64]
Mode = Literal["simulate", "reanchor"]


@dataclass(frozen=True)
class Prediction:
    """Prediction for one sample: speeds and residual [rad/s], shape (2,) each; gear state."""

    stamp: float
    predicted: Array
    residual: Array
    gear: int
    anchored: bool


class Predictor:
    """Runs a :class:`HybridModel` or :class:`LinearModel` on measured samples.

    Args:
        model: the model to run.
        brake: band data (for the band torque profile of a linear model).
        mode: ``"simulate"`` or ``"reanchor"`` (see module docstring).
        reanchor_period: seconds between re-anchors in ``"reanchor"`` mode.
        gap_reset: a stamp gap [s] longer than this re-anchors (stream restart).
        rms_window: number of samples in the running residual RMS.
    """

    def __init__(self, model: HybridModel | LinearModel, brake: BrakeParams,
                 mode: Mode = "simulate", reanchor_period: float = 1.0,
                 gap_reset: float = 0.5, rms_window: int = 1000,
                 output_delay: float = 0.0, output_gain: tuple[float, float] = (0.0, 0.0)
                 ) -> None:
        if mode not in ("simulate", "reanchor"):
            raise SimulationError(f"mode: expected 'simulate' or 'reanchor', got {mode!r}")
        if not reanchor_period > 0.0:
            raise SimulationError(f"reanchor_period: expected > 0 s, got {reanchor_period!r}")
        self.model = model
        self.brake = brake
        self.mode: Mode = mode
        self.reanchor_period = reanchor_period
        self.gap_reset = gap_reset
        self.output_delay = float(output_delay)
        self.output_gain = np.asarray(output_gain, dtype=float) + 1.0
        self._history: deque[tuple[float, Array]] = deque()
        self._state: HybridState | None = None
        self._omega = np.zeros(2)
        self._cap = np.zeros(3)
        self._last_stamp: float | None = None
        self._last_inputs: tuple[float, Array] = (0.0, np.zeros(3))
        self._anchor_stamp = 0.0
        self._sq: deque[Array] = deque(maxlen=max(1, rms_window))
        self.samples = 0
        self.anchors = 0

    @property
    def residual_rms(self) -> Array:
        """RMS of the residual over the window [rad/s], shape (2,)."""
        if not self._sq:
            return np.zeros(2)
        return np.asarray(np.sqrt(np.mean(np.asarray(self._sq), axis=0)))

    def _anchor(self, stamp: float, omega: Array, i_brake: Array) -> None:
        if isinstance(self.model, HybridModel):
            prev = self._state
            rings = self.model.ring_speeds(omega)
            target = band_torques(self.brake, i_brake)
            still = np.abs(rings) < 0.5
            cap = np.where(still, target, prev.capacity if prev is not None else 0.0)
            self._state = self.model.initial_state(omega, t=stamp, capacity=cap)
        else:
            self._omega = omega.copy()
        self._anchor_stamp = stamp
        self.anchors += 1

    def update(self, stamp: float, i_motor: float, i_brake: ArrayLike,
               omega_measured: ArrayLike) -> Prediction:
        """Feed one measured sample; return the prediction at ``stamp`` [s].

        Raises:
            SimulationError: non-finite inputs or measurements (the sample is not used).
        """
        ib = np.asarray(i_brake, dtype=float).reshape(3)
        meas = np.asarray(omega_measured, dtype=float).reshape(2)
        if not (np.isfinite(i_motor) and np.all(np.isfinite(ib)) and np.all(np.isfinite(meas))
                and np.isfinite(stamp)):
            raise SimulationError(f"sample at stamp {stamp!r}: non-finite value")
        anchored = False
        last = self._last_stamp
        if last is None or stamp <= last or stamp - last > self.gap_reset or (
                self.mode == "reanchor" and stamp - self._anchor_stamp >= self.reanchor_period):
            self._anchor(stamp, meas, ib)
            anchored = True
        else:
            dt = stamp - last
            im_prev, ib_prev = self._last_inputs
            if isinstance(self.model, HybridModel):
                assert self._state is not None
                self._state = self.model.step(self._state, dt, im_prev, ib_prev)
            else:
                target = band_torques(self.brake, ib_prev)
                cap_end, cap_mean = capacity_step(self._cap, target, dt,
                                                  self.brake.time_constants)
                u = np.concatenate([[im_prev], cap_mean])
                self._omega = self.model.step(self._omega, dt, u)
                self._cap = cap_end
        if isinstance(self.model, HybridModel):
            assert self._state is not None
            predicted = self._state.omega.copy()
            gear = self._state.gear
        else:
            predicted = self._omega.copy()
            gear = 0
        if anchored:
            self._history.clear()
        if self.output_delay > 0.0:
            # measured output at t is the machine's state at t - delay (sensor delay)
            self._history.append((stamp, predicted))
            while (len(self._history) > 1
                   and self._history[1][0] <= stamp - self.output_delay + 1e-9):
                self._history.popleft()
            predicted = self._history[0][1].copy()
        predicted = predicted * self.output_gain
        self._last_stamp = stamp
        self._last_inputs = (float(i_motor), ib)
        residual = meas - predicted
        self._sq.append(residual**2)
        self.samples += 1
        return Prediction(stamp=stamp, predicted=predicted, residual=residual, gear=gear,
                          anchored=anchored)
