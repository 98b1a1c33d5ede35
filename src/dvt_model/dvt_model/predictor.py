"""Sample-by-sample prediction of the measured speeds and angles (the model node's core; no rclpy).

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
  re-anchors only when the stream restarts (a stamp that goes backwards or a gap longer than
  ``gap_reset`` seconds: a new recording, a controller reset; :attr:`Prediction.restarted`)
  or loses its inputs: a gap longer than ``gap_reanchor`` seconds and than
  :data:`GAP_PERIODS` times the previous stamp step (samples lost in transport: the inputs
  held across a lost burst would leave the free run off for good; the second bound keeps a
  stream slower than ``gap_reanchor``, e.g. 62.5 Hz, running free; the first step, with no
  previous one to compare, is run through).
- ``mode="reanchor"``: additionally re-anchors every ``reanchor_period`` seconds, so the
  residual shows the model's short-horizon prediction error and never drifts; useful to watch
  a live machine for hours.

Angles: the model carries ``theta = (theta_sun, theta_carrier3)`` [rad] (the hybrid model
integrates them exactly with the speeds; the linear model by the trapezoidal rule). When a
sample carries measured angles (``theta_measured``, the driver's ``position`` from the encoder
counts) the model's angles are anchored to them at every anchor (and at the first sample that
carries them), and the prediction includes the predicted angles and the angle residual
``measured - predicted`` [rad]. Without measured angles the model's angles continue from the
last anchor (0 at the start), and the prediction carries no angle residual. A joint load's
gravity torque depends on the carrier-3 angle, so a load is predicted right only from the
measured angles.

Lost motion (the ``dead_zone``, ``play`` and ``spline_play`` terms, :mod:`dvt_model.backlash`):
a dead zone is applied to the measured current as it arrives, so the model (band torques and
input terms included) sees the transformed current; an output's sensor map turns the model's
speed of that output into what its sensor reads (rigid play or a compliant spline to a load),
and starts again at every anchor. The angles are the model's, not mapped.

The guard: a prediction is never non-finite or implausibly large. If a model step fails or
leaves a speed that is not finite or exceeds :data:`OMEGA_GUARD` in magnitude (a diverging
model, e.g. an identified model that is wrong far from its data), the model is re-anchored to
the measured sample instead, the event is counted in :attr:`Predictor.guard_reanchors` (the
node reports it in ``/diagnostics`` with level WARN) and the prediction is the anchored state.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dvt_model.backlash import OutputMap, dead_zone
from dvt_model.brake import band_torques, capacity_step
from dvt_model.contract import GAP_REANCHOR_S, GAP_RESET_S
from dvt_model.errors import DvtModelError, SimulationError
from dvt_model.hybrid import HybridModel, HybridState
from dvt_model.linear import LinearModel
from dvt_model.params import BrakeParams

Array = NDArray[np.float64]
Mode = Literal["simulate", "reanchor"]
GAP_PERIODS = 2.5
"""A stamp step longer than ``gap_reanchor`` re-anchors only if it is also longer than this
many times the previous step: more than one lost sample at the stream's own rate."""

SUN_SPEED_LIMIT = 2400.0 * 2.0 * np.pi / 60.0
"""The machine's safe maximum sun speed, 2400 rpm, in rad/s (the driver refuses faster
set-points)."""
OMEGA_GUARD = 100.0 * SUN_SPEED_LIMIT
"""Largest plausible predicted speed [rad/s], about 25 133 rad/s: 100 times the safe sun speed.
The carrier-3 speed is a fraction of the sun's, so a real prediction stays far below; a model
state beyond it has diverged and is re-anchored (see the module docstring)."""


@dataclass(frozen=True)
class Prediction:
    """Prediction for one sample: speeds and residual [rad/s], shape (2,) each; gear state;
    whether the model was anchored at this sample, whether that was a stream (re)start
    (``restarted``) or samples lost in transport (``lost``: the same stream goes on);
    predicted angles [rad] (2,) always, and the angle residual [rad] (2,) when the sample
    carried measured angles (else ``None``)."""

    stamp: float
    predicted: Array
    residual: Array
    gear: int
    anchored: bool
    restarted: bool = False
    lost: bool = False
    predicted_position: Array = field(default_factory=lambda: np.zeros(2))
    position_residual: Array | None = None


class Predictor:
    """Runs a :class:`HybridModel` or :class:`LinearModel` on measured samples.

    Args:
        model: the model to run.
        brake: band data (for the band torque profile of a linear model).
        mode: ``"simulate"`` or ``"reanchor"`` (see module docstring).
        reanchor_period: seconds between re-anchors in ``"reanchor"`` mode.
        gap_reset: a stamp gap [s] longer than this re-anchors (stream restart).
        gap_reanchor: a stamp gap [s] longer than this and than :data:`GAP_PERIODS` times
            the previous step re-anchors (samples lost; not a restart).
        rms_window: number of samples in the running residual RMS.
        output_delay: the outputs' measurement delay [s] (whole samples).
        output_gain: each output's relative scale error (output scaled by ``1 + gain``).
        input_dead_zone: half-width of a dead zone on each current (drive motor, brakes 1-3)
            [A], 0 for none; shape (4,).
        output_maps: each output's sensor map through lost motion, or ``None``; (2,).
    """

    def __init__(self, model: HybridModel | LinearModel, brake: BrakeParams,
                 mode: Mode = "simulate", reanchor_period: float = 1.0,
                 gap_reset: float = GAP_RESET_S, gap_reanchor: float = GAP_REANCHOR_S,
                 rms_window: int = 1000,
                 output_delay: float = 0.0, output_gain: tuple[float, float] = (0.0, 0.0),
                 input_dead_zone: ArrayLike = (0.0, 0.0, 0.0, 0.0),
                 output_maps: tuple[OutputMap | None, OutputMap | None] = (None, None)
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
        self.gap_reanchor = gap_reanchor
        self.gap_anchors = 0
        """Re-anchors after lost samples (a gap beyond ``gap_reanchor``, not a restart)."""
        self.output_delay = float(output_delay)
        self.output_gain = np.asarray(output_gain, dtype=float) + 1.0
        zones = np.asarray(input_dead_zone, dtype=float).reshape(-1)
        if zones.shape != (4,) or not np.all(np.isfinite(zones)) or np.any(zones < 0.0):
            raise SimulationError(f"input_dead_zone: expected 4 finite numbers >= 0 [A], got "
                                  f"{zones.tolist()}")
        self._zones: tuple[float, ...] | None = (tuple(float(z) for z in zones)
                                                  if np.any(zones > 0.0) else None)
        if len(output_maps) != 2:
            raise SimulationError(f"output_maps: expected one per output (2), got "
                                  f"{len(output_maps)}")
        self._maps = output_maps if any(m is not None for m in output_maps) else None
        self._history: deque[tuple[float, Array]] = deque()
        self._state: HybridState | None = None
        self._omega = np.zeros(2)
        self._theta = np.zeros(2)  # linear model's angles [rad]
        self._theta_known = False  # the angles are anchored to measured ones
        self._sq_pos: deque[Array] = deque(maxlen=max(1, rms_window))
        self._cap = np.zeros(3)
        self._last_stamp: float | None = None
        self._last_step = 0.0  # the previous forward stamp step [s] (0: none yet)
        self._last_inputs: tuple[float, Array] = (0.0, np.zeros(3))
        self._anchor_stamp = 0.0
        self._sq: deque[Array] = deque(maxlen=max(1, rms_window))
        self.samples = 0
        self.anchors = 0
        self.guard_reanchors = 0
        """Re-anchors forced by the guard (non-finite or diverging model state)."""

    @property
    def position_residual_rms(self) -> Array | None:
        """RMS of the angle residual over the window [rad], shape (2,); ``None`` before any
        sample with measured angles."""
        if not self._sq_pos:
            return None
        return np.asarray(np.sqrt(np.mean(np.asarray(self._sq_pos), axis=0)))

    @property
    def theta(self) -> Array:
        """The model's angles (theta_sun, theta_carrier3) [rad] now, shape (2,)."""
        if isinstance(self.model, HybridModel):
            return self._state.theta.copy() if self._state is not None else np.zeros(2)
        return self._theta.copy()

    def _set_theta(self, theta: Array) -> None:
        if isinstance(self.model, HybridModel):
            if self._state is not None:
                self._state = dataclasses.replace(self._state, theta=theta.copy())
        else:
            self._theta = theta.copy()

    @property
    def residual_rms(self) -> Array:
        """RMS of the residual over the window [rad/s], shape (2,)."""
        if not self._sq:
            return np.zeros(2)
        return np.asarray(np.sqrt(np.mean(np.asarray(self._sq), axis=0)))

    def _anchor(self, stamp: float, omega: Array, i_brake: Array,
                theta: Array | None = None) -> None:
        """Anchor the model to the measured speeds (and angles, if measured; else the angles
        continue from the model's present ones)."""
        th = theta if theta is not None else self.theta
        if not np.all(np.isfinite(th)):  # a diverged model's angles: start again from 0
            th = np.zeros(2)
        self._theta_known = theta is not None
        if isinstance(self.model, HybridModel):
            prev = self._state
            rings = self.model.ring_speeds(omega)
            target = band_torques(self.brake, i_brake)
            still = np.abs(rings) < 0.5
            prev_cap = (prev.capacity if prev is not None
                        and np.all(np.isfinite(prev.capacity)) else 0.0)
            cap = np.where(still, target, prev_cap)
            self._state = self.model.initial_state(omega, t=stamp, capacity=cap, theta=th)
        else:
            self._omega = omega.copy()
            self._theta = th.copy()
        self._anchor_stamp = stamp
        self.anchors += 1

    def _advance(self, dt: float) -> bool:
        """Advance the model by ``dt`` [s] with the previous inputs held; False (state left
        unusable) if the step failed or left a speed non-finite or beyond :data:`OMEGA_GUARD`."""
        im_prev, ib_prev = self._last_inputs
        try:
            with np.errstate(all="ignore"):
                if isinstance(self.model, HybridModel):
                    if self._state is None:
                        return False
                    self._state = self.model.step(self._state, dt, im_prev, ib_prev)
                    omega = self._state.omega
                    theta = self._state.theta
                else:
                    target = band_torques(self.brake, ib_prev)
                    cap_end, cap_mean = capacity_step(self._cap, target, dt,
                                                      self.brake.time_constants)
                    u = np.concatenate([[im_prev], cap_mean])
                    w0 = self._omega
                    self._omega = self.model.step(self._omega, dt, u)
                    self._theta = self._theta + 0.5 * dt * (w0 + self._omega)
                    self._cap = cap_end
                    omega = self._omega
                    theta = self._theta
        except (DvtModelError, ArithmeticError, np.linalg.LinAlgError):
            return False
        # plain floats: a few small-array numpy reductions cost more than the checks
        speeds = omega.tolist()
        return (_all_finite(speeds) and max(map(abs, speeds)) <= OMEGA_GUARD
                and _all_finite(theta.tolist()))

    def update(self, stamp: float, i_motor: float, i_brake: ArrayLike,
               omega_measured: ArrayLike, theta_measured: ArrayLike | None = None
               ) -> Prediction:
        """Feed one measured sample; return the prediction at ``stamp`` [s].

        Args:
            stamp: sample time [s].
            i_motor: drive-motor current [A].
            i_brake: brake-motor currents [A], shape (3,).
            omega_measured: measured (sun, carrier3) speeds [rad/s], shape (2,).
            theta_measured: measured (sun, carrier3) angles [rad], shape (2,), or ``None``
                (a sample without positions; a non-finite angle counts as not measured).

        Raises:
            SimulationError: non-finite inputs or speeds (the sample is not used).
        """
        ib = np.asarray(i_brake, dtype=float).reshape(3)
        meas = np.asarray(omega_measured, dtype=float).reshape(2)
        if not (math.isfinite(i_motor) and _all_finite(ib.tolist())
                and _all_finite(meas.tolist()) and math.isfinite(stamp)):
            raise SimulationError(f"sample at stamp {stamp!r}: non-finite value")
        if self._zones is not None:  # lost motion on the inputs: what the model sees
            i_motor = float(dead_zone(i_motor, self._zones[0]))
            ib = np.asarray(dead_zone(ib, np.asarray(self._zones[1:])), dtype=float)
        th_meas: Array | None = None
        if theta_measured is not None:
            th_meas = np.asarray(theta_measured, dtype=float).reshape(2)
            if not _all_finite(th_meas.tolist()):
                th_meas = None
        anchored = False
        last = self._last_stamp
        step_s = 0.0 if last is None else stamp - last
        restarted = last is None or stamp <= last or step_s > self.gap_reset
        lost = (not restarted and self._last_step > 0.0 and step_s > self.gap_reanchor
                and step_s > GAP_PERIODS * self._last_step)
        if restarted or lost or (
                self.mode == "reanchor" and stamp - self._anchor_stamp >= self.reanchor_period):
            self._anchor(stamp, meas, ib, th_meas)
            anchored = True
            self.gap_anchors += lost
        else:
            if last is None or not self._advance(stamp - last):  # (last is set here)
                self._anchor(stamp, meas, ib, th_meas)
                self.guard_reanchors += 1
                anchored = True
        if th_meas is not None and not self._theta_known:
            self._set_theta(th_meas)  # positions appeared: anchor the angles to them
            self._theta_known = True
            anchored = True
        # ``predicted`` is a new array below (``* output_gain``): no copy of the state's
        if isinstance(self.model, HybridModel):
            if self._state is None:
                raise SimulationError("predictor: no model state after anchoring")
            predicted = self._state.omega
            gear = self._state.gear
            position = self._state.theta.copy()
        else:
            predicted = self._omega
            gear = 0
            position = self._theta.copy()
        if anchored:
            self._history.clear()
        if self._maps is not None:  # the sensors read the speeds through lost motion
            step = 0.0 if anchored or last is None else stamp - last
            sensed = []
            for j, m in enumerate(self._maps):
                if m is None:
                    sensed.append(float(predicted[j]))
                    continue
                if anchored:
                    m.reset()
                sensed.append(m.sensed_speed(float(predicted[j]), step))
            predicted = np.array(sensed)
        if self.output_delay > 0.0:
            # measured output at t is the machine's state at t - delay (sensor delay)
            self._history.append((stamp, np.concatenate([predicted, position])))
            while (len(self._history) > 1
                   and self._history[1][0] <= stamp - self.output_delay + 1e-9):
                self._history.popleft()
            delayed = self._history[0][1]
            predicted, position = delayed[:2].copy(), delayed[2:].copy()
        predicted = predicted * self.output_gain
        self._last_stamp = stamp
        if step_s > 0.0:
            self._last_step = step_s
        self._last_inputs = (float(i_motor), ib)
        residual = meas - predicted
        self._sq.append(residual**2)
        pos_res: Array | None = None
        if th_meas is not None:
            pos_res = th_meas - position
            self._sq_pos.append(pos_res**2)
        self.samples += 1
        return Prediction(stamp=stamp, predicted=predicted, residual=residual, gear=gear,
                          anchored=anchored, restarted=restarted, lost=lost,
                          predicted_position=position,
                          position_residual=pos_res)


def _all_finite(values: list[float]) -> bool:
    """Whether every value of a short list of floats is finite (cheaper than numpy for a
    handful of values)."""
    return all(map(math.isfinite, values))


class ResidualBlocks:
    """Means of consecutive blocks of ``size`` residual samples (the change detector's input).

    :meth:`add` takes one sample (stamp [s], residual per output) and returns
    ``(stamp of the block's first sample, means)`` when a block is complete, else ``None``.
    A stamp step that is not in ``(0, max_gap_s]`` drops the unfinished block (a block never
    spans a gap or a restart). Plain floats, O(outputs) per sample.
    """

    def __init__(self, size: int, outputs: int = 2, max_gap_s: float = 0.05) -> None:
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise SimulationError(f"block size: expected an integer >= 1, got {size!r}")
        self.size = size
        self.max_gap_s = float(max_gap_s)
        self._sum = [0.0] * outputs
        self._n = 0
        self._first = 0.0
        self._last = -float("inf")
        self.dropped = 0
        """Unfinished blocks dropped at a gap."""

    def clear(self) -> None:
        """Drop the unfinished block (the next sample starts a new one)."""
        self._n = 0

    def add(self, stamp: float, residual: list[float]) -> tuple[float, list[float]] | None:
        """Add one sample; the completed block's ``(first stamp, means)`` or ``None``."""
        step = stamp - self._last
        self._last = stamp
        if self._n and not 0.0 < step <= self.max_gap_s:
            self._n = 0
            self.dropped += 1
        acc = self._sum
        if self._n == 0:
            self._first = stamp
            for i, r in enumerate(residual):
                acc[i] = r
        else:
            for i, r in enumerate(residual):
                acc[i] += r
        self._n += 1
        if self._n < self.size:
            return None
        self._n = 0
        inv = 1.0 / self.size
        return self._first, [a * inv for a in acc]
