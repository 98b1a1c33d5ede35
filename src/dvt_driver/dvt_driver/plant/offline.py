"""Run an experiment through the driver's supervisor into the plant core, offline (pure).

No ROS, no serial line, no wall clock: the same command path as the live chain
(:class:`~dvt_driver.link.safety.Supervisor` -> protocol ``Command`` -> :class:`PlantSim`) advanced
one controller sample at a time, as fast as the CPU allows. Used for validation recordings in
tests, Monte Carlo studies and benchmarks; the committed ``bags/`` are made by the real chain
(``scripts/make_bags.sh``).

The runner's keep-alive is modelled by refreshing the supervisor's motor command every sample;
commands take effect at the sample at or after their time, as on the link.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dvt_driver.link.protocol import Ack, Command, Hello, HelloAck, Mode, unwrap_count
from dvt_driver.link.safety import Limits, MotorMode, ShiftSettings, Supervisor
from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.hidden import HiddenEffects
from dvt_driver.plant.settings import SampleValues, SensorConfig
from dvt_driver.run.experiment_core import (
    BrakeCurrents,
    Experiment,
    Gear,
    MotorCurrent,
    SunSpeed,
)
from dvt_model.hybrid import HybridModel
from dvt_model.load import JointLoad
from dvt_model.params import TransmissionParams
from dvt_model.predictor import Prediction, Predictor
from dvt_model.recording import parse_truth, write_run

Array = NDArray[np.float64]


@dataclass(frozen=True)
class OfflineRun:
    """Samples of an offline run.

    Attributes:
        t: controller time of each sample [s], shape (N,).
        speeds: measured (sun, carrier3) [rad/s], shape (N, 2).
        currents: measured (motor, brake1..3) [A], shape (N, 4).
        omega_true: true (sun, carrier3) [rad/s], shape (N, 2).
        positions: measured (sun, carrier3) angles from the encoder counts [rad], shape (N, 2)
            (the counts' zero: controller start for the sun, plant start for carrier 3).
        theta_true: true (sun, carrier3) angles from the plant's start [rad], shape (N, 2).
        gear: model gear state per sample, shape (N,).
        trips: safety events of the supervisor.
        nacks: commands the plant refused.
        truth: the plant's ``truth.yaml`` text.
    """

    t: Array
    speeds: Array
    currents: Array
    omega_true: Array
    gear: NDArray[np.int64]
    positions: Array
    theta_true: Array
    trips: list[str]
    nacks: int
    truth: str


def run_offline(experiment: Experiment, params: TransmissionParams,
                hidden: HiddenEffects | None = None, seed: int = 1,
                limits: Limits | None = None, load: JointLoad | None = None,
                sensors: SensorConfig | None = None) -> OfflineRun:
    """Run ``experiment`` on a :class:`PlantSim` with ``hidden`` effects, an optional
    declared joint ``load`` and the bench's ``sensors`` (default :class:`SensorConfig`: their
    noise levels and resolutions; see module doc); the session speaks protocol version 2."""
    period_s = experiment.sample_period_us * 1e-6
    plant = PlantSim(params, hidden, experiment.sample_period_us, seed=seed, load=load,
                     sensors=sensors)
    hello = plant.handle(Hello())[0]
    cpr = ((hello.sun_counts_per_rev, hello.output_counts_per_rev)
           if isinstance(hello, HelloAck) else (0, 0))
    unwrapped: list[int] | None = None
    sup = Supervisor(limits or Limits(), 0.5, ShiftSettings())
    n = round(experiment.duration / period_s)
    steps, k = list(experiment.steps), 0
    trips: list[str] = []
    nacks = 0
    t = np.empty(n)
    speeds = np.empty((n, 2))
    currents = np.empty((n, 4))
    true = np.empty((n, 2))
    gear = np.empty(n, dtype=np.int64)
    pos = np.full((n, 2), np.nan)
    theta = np.empty((n, 2))
    for i in range(n):
        now = i * period_s
        while k < len(steps) and steps[k].t <= now + 1e-9:
            c = steps[k].command
            if isinstance(c, MotorCurrent):
                sup.motor_current(c.amps, now)
            elif isinstance(c, SunSpeed):
                sup.sun_speed(c.rad_s, now)
            elif isinstance(c, BrakeCurrents):
                sup.brake_currents(["brake1", "brake2", "brake3"], list(c.amps), now)
            elif isinstance(c, Gear):
                sup.select_gear(c.gear, now)
            else:
                sup.stop()
            k += 1
        if sup.mode is not MotorMode.OFF:
            sup.last_motor_command = now  # the runner's keep-alive
        out, event = sup.output(now)
        if event:
            trips.append(str(event))
        reply = plant.handle(Command(i & 0xFFFF, Mode(int(out.mode)), out.setpoint, out.brakes))
        nacks += not isinstance(reply[0], Ack)
        v = plant.tick()
        trip = sup.observe(v.sun_speed)
        if trip:
            trips.append(str(trip))
        t[i] = v.t_us * 1e-6
        speeds[i] = (v.sun_speed, v.carrier3_speed)
        currents[i] = (v.motor_current, *v.brake_currents)
        true[i] = v.omega_true
        gear[i] = v.gear
        theta[i] = v.theta_true
        if v.counts is not None:
            unwrapped = (list(v.counts) if unwrapped is None else
                         [unwrap_count(unwrapped[j], v.counts[j]) for j in (0, 1)])
            pos[i] = [2.0 * np.pi * unwrapped[j] / cpr[j] if cpr[j] else np.nan for j in (0, 1)]
    return OfflineRun(t=t, speeds=speeds, currents=currents, omega_true=true, gear=gear,
                      positions=pos, theta_true=theta, trips=trips, nacks=nacks,
                      truth=plant.truth_yaml())


def record_offline(path: str | Path, experiment: Experiment, params: TransmissionParams,
                   hidden: HiddenEffects | None = None, seed: int = 1,
                   start_ns: int = 1_700_000_000_000_000_000,
                   load: JointLoad | None = None, sensors: SensorConfig | None = None) -> Path:
    """Run offline and write a contract bag at ``path`` with its ``truth.yaml``; the
    ``/dvt/joint_states`` messages carry the encoder positions (protocol version 2)."""
    run = run_offline(experiment, params, hidden, seed, load=load, sensors=sensors)
    stamps = start_ns + np.round(run.t * 1e9).astype(np.int64)
    truth = parse_truth(run.truth, "the plant's truth")
    truth["made_by"] = f"dvt_driver.plant.offline.record_offline (experiment {experiment.name})"
    return write_run(path, stamps, run.speeds, run.currents, truth=truth,
                     positions=run.positions)


KEEP_ALIVE_SAMPLES = 50
"""Samples between two set-points of :func:`held_current` (20 Hz at 1 kHz: within the
controller's watchdog)."""


def held_current(plant: PlantSim, current_a: float, until_s: float) -> Iterator[SampleValues]:
    """The samples of ``plant`` (a session open) with the
    motor at ``current_a`` [A] in current mode and every band released, the set-point sent
    again every :data:`KEEP_ALIVE_SAMPLES` samples, until the controller clock passes
    ``until_s`` [s] (that sample not yielded). The clean-plant scenario of the change
    detector's offline tests and of ``scripts/detector_residual.py``."""
    i = 0
    while True:
        if i % KEEP_ALIVE_SAMPLES == 0:
            plant.handle(Command(i & 0xFFFF, Mode.CURRENT, float(current_a), (0.0, 0.0, 0.0)))
        v = plant.tick()
        i += 1
        if v.t_us * 1e-6 > until_s:
            return
        yield v


def predicted_held_current(plant: PlantSim, params: TransmissionParams, current_a: float,
                           until_s: float, lead_s: float) -> Iterator[tuple[float, Prediction]]:
    """The model node's path without ROS on a plant held at a constant current: ``plant`` (a
    session opened if none is) driven by :func:`held_current`, and from ``lead_s`` [s] on (the
    node started after the motor) a :class:`~dvt_model.predictor.Predictor` with ``params``
    (the plant's own for a clean plant) fed each sample: ``(plant time [s], prediction)`` until
    ``until_s`` [s]."""
    if not plant.session_open:
        plant.handle(Hello())
    pred = Predictor(HybridModel.from_params(params), params.brake)
    for v in held_current(plant, current_a, until_s):
        t = v.t_us * 1e-6
        if t >= lead_s:
            yield t, pred.update(t, v.motor_current, v.brake_currents,
                                 (v.sun_speed, v.carrier3_speed))
