"""The gravity arm's coefficients as the identifier fits them when the arm is declared, over
several recordings (the figures of ``docs/identification.md`` on the arm's cos coefficient).

Draws the ``gravity_arm`` plant with ``--draw`` (default 31, as
``tests/test_position_effects.py``), records the ``ident`` experiment offline per ``--seeds``
entry ``s`` (experiment seed ``21 + 1000 s``, noise seed ``31 + 1000 s``; validation
``121 + 1000 s`` / ``131 + 1000 s``: ``s = 0`` is the test's pair) and fits the ``dvt``
description's baseline with the arm added to its model effects at the drawn reduction (held
fixed: ``a`` and ``b`` of ``a cos(theta_c3 / N) + b sin(theta_c3 / N)`` and the baseline are
fitted, no candidate is tried), at each ``--fit-decimate`` (0: the description's ``auto``).
Prints per fit ``a`` and ``b`` against the plant's torque law (``a``: the torque at
``theta_c3 = 0``, ``b``: at ``N pi / 2``) in reported std and in N m, then the mean offset over
the seeds. ``--noise-free`` records without the tachometer's and the currents' noise (encoder
and A/D quantisation stay). ``--own-model`` then refits each fit on the identifier's own model
at the plant's ``a`` and ``b`` (the other parameters as fitted, Gaussian noise of the fit's
residual size per output, seed 5): an estimator that finds its own model's values there puts
the offset on the difference between the plant and the model. ``--structure`` also prints the
structure's masses and dampings against the plant's (``physical`` with the arm's reflected
inertia ``J_arm / N^2`` added to ``M22``): is the offset the arm's alone? About 15 s per fit at
the default step, 1 min at ``--fit-decimate 1``.

Where the offset comes from (counterfactual runs; the plant and identifier are unchanged
otherwise):

- ``--ideal-current``: the plant reports as the motor current the mean current its drive
  applies over the interval that follows the sample (what the torque integrates), noise-free,
  and the description holds it as sampled (``hold: zoh``). The measured current is the
  instantaneous value at the sample of a current that follows its reference with the drive's
  first-order lag; the description's ``hold: linear`` holds the mean of the line through two
  samples, where the lag's mean weights the later sample more (0.582 for a lag equal to the
  period).
  ``--quantise-current`` reads that mean through the plant's 12-bit motor-current A/D
  (0.0195 A steps), still without noise.
- ``--ideal-speeds``: the plant reports both speeds as their true values at the sample (no
  encoder count difference, tachometer noise or A/D quantisation), and the description reads
  the sun speed as instantaneous (no ``sampling: interval``).
- ``--hold-weight W``: the identifier's ``linear`` hold weights the interval's two samples
  ``1 - W`` and ``W`` (the description's 0.5; the plant's drive 0.582, see above), with the
  measured current: the share of the offset the hold's weight carries under noise.
- ``--bandwidths``: the reported std of ``a`` again with the Bartlett window 4 and 16 times the
  automatic one (:func:`dvt_identify.uncertainty.covariance_bandwidth`, the fit's): how much of
  the score's correlation the automatic window leaves out.

Usage::

    .venv/bin/python scripts/gravity_bias.py [--seeds 0 1 2] [--fit-decimate 0 1]
        [--draw SEED] [--noise-free] [--own-model] [--structure]
        [--ideal-current [--quantise-current]] [--ideal-speeds] [--hold-weight W]
        [--bandwidths]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
from band_lags import _refit_on_own_model, _show, drop_intersample

from dvt_driver.plant import core
from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.plant.physics import lag_mean_factor
from dvt_driver.plant.settings import SensorConfig
from dvt_driver.run.experiment_core import build
from dvt_identify import data as id_data
from dvt_identify import simulation as id_simulation
from dvt_identify.data import Segment
from dvt_identify.description import load_description
from dvt_identify.fit import OEFit
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_identify.uncertainty import covariance_bandwidth, sandwich_covariance, scores
from dvt_model.params import load_parameters

A, B = "gravity_a_carrier3", "gravity_b_carrier3"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--fit-decimate", type=int, nargs="+", default=[0])
    ap.add_argument("--draw", type=int, default=31, help="plant draw seed")
    ap.add_argument("--noise-free", action="store_true",
                    help="record with the tachometer, motor- and brake-current noise at 0")
    ap.add_argument("--own-model", action="store_true",
                    help="also refit on the identifier's own model at the plant's a and b")
    ap.add_argument("--structure", action="store_true",
                    help="also print M and D against the plant's")
    ap.add_argument("--ideal-current", action="store_true",
                    help="the plant reports the interval's mean motor current (held as sampled)")
    ap.add_argument("--quantise-current", action="store_true",
                    help="with --ideal-current: read that current through the plant's A/D")
    ap.add_argument("--ideal-speeds", action="store_true",
                    help="the plant reports both true speeds at the sample")
    ap.add_argument("--hold-weight", type=float, default=None,
                    help="the linear hold's weight of the later sample (description: 0.5)")
    ap.add_argument("--bandwidths", action="store_true",
                    help="also the std of a with 4 and 16 times the automatic Bartlett window")
    a = ap.parse_args()
    if a.hold_weight is not None and not 0.0 <= a.hold_weight <= 1.0:
        ap.error(f"--hold-weight: expected a weight in [0, 1], got {a.hold_weight}")
    if a.quantise_current and not a.ideal_current:
        ap.error("--quantise-current: needs --ideal-current")
    if a.ideal_current or a.ideal_speeds:
        ideal_sensors(a.ideal_current, a.ideal_speeds, a.quantise_current)
    if a.hold_weight is not None:
        weighted_hold(a.hold_weight)
    hidden = load_hidden("gravity_arm", draw=a.draw)
    arm = hidden.gravity_arm
    if arm is None:
        print("gravity_bias: the preset 'gravity_arm' drew no arm", file=sys.stderr)
        return 1
    n = arm.stage.reduction
    truth = {A: arm.carrier3_torque(0.0, 1.0), B: arm.carrier3_torque(0.5 * math.pi * n, 1.0)}
    params = load_parameters("physical")
    structure = structure_truth(arm.reflected_inertia)
    sensors = (dataclasses.replace(SensorConfig(), tach_noise=0.0, motor_current_noise=0.0,
                                   brake_current_noise=0.0) if a.noise_free else None)
    tmp = Path(tempfile.mkdtemp(prefix="dvt-gravity-bias-"))
    text = drop_intersample(load_description("dvt").text, a.ideal_current, a.ideal_speeds)
    desc = load_description(with_declared_arm(text, n, tmp))
    print(f"plant draw {a.draw}: reduction {n:g}, a {truth[A]:.6f}, b {truth[B]:.6f} N m")
    offsets: dict[int, list[tuple[float, float]]] = {q: [] for q in a.fit_decimate}
    for s in a.seeds:
        est = record_offline(tmp / f"est{s}", build("ident", seed=21 + 1000 * s), params,
                             hidden, seed=31 + 1000 * s, sensors=sensors)
        val = record_offline(tmp / f"val{s}", build("ident", seed=121 + 1000 * s), params,
                             hidden, seed=131 + 1000 * s, sensors=sensors)
        e, v = load_segments([est], desc), load_segments([val], desc)
        for q in a.fit_decimate:
            cfg = LoopConfig.from_options(desc.fit, q if q > 0 else desc.preprocess.fit_decimate)
            r = identify(e, v, desc, dataclasses.replace(cfg, max_effects=0))
            fit = r.baseline.fit
            p = fit.parameters()
            offsets[q].append((p[A] - truth[A], p[B] - truth[B]))
            _show(f"seed {s}, fit step {r.fit_dt * 1e3:g} ms, validation fit "
                  f"{r.baseline.val.mean_fit:.3f} %", fit, truth, ".6f", "N m")
            if a.structure:
                _show("  the structure (offset relative to the plant's)", fit, structure,
                      ".6g", relative=True)
            if a.bandwidths:
                show_bandwidths(fit, A)
            if a.own_model:
                _show("  the same fit on the identifier's own model at the plant's a, b",
                      _refit_on_own_model(fit, truth), truth, ".6f", "N m")
    for q, rows in offsets.items():
        m = np.mean(rows, axis=0)
        print(f"fit_decimate {q or 'auto'}: mean offset over {len(rows)} seeds "
              f"a {m[0]:+.6f}, b {m[1]:+.6f} N m")
    return 0


def ideal_sensors(current: bool, speeds: bool, quantise: bool = False) -> None:
    """Make every plant of this process report the interval's mean motor current (``current``;
    with ``quantise`` read by the plant's motor-current A/D) and the true speeds at the sample
    (``speeds``), noise-free (a counterfactual plant: the controller and the physics are
    unchanged, only what the samples say)."""
    measure = core.PlantSim._measure

    def ideal(self: core.PlantSim, clamped: bool) -> core.SampleValues:
        v = measure(self, clamped)
        if current:  # the mean the next sub-step applies (one sub-step per sample at 1 kHz)
            tau, i0, ref = self.drive.current_time_constant, self.physics.i_motor, self._i_ref
            mean = ref + (i0 - ref) * lag_mean_factor(self.step, tau) if tau else ref
            if quantise:
                full = self.sensors.motor_current_range
                mean = core._quantise(mean, 2.0 * full / 4096, full)
            v = dataclasses.replace(v, motor_current=mean)
        if speeds:
            v = dataclasses.replace(v, sun_speed=float(self.state.omega[0]),
                                    carrier3_speed=float(self.physics.output_speed()))
        return v

    if current and core.PlantSim(load_parameters("physical")).substeps != 1:
        raise SystemExit("gravity_bias: --ideal-current needs one physics sub-step per sample")
    core.PlantSim._measure = ideal  # type: ignore[method-assign]


def weighted_hold(weight: float) -> None:
    """Make the identifier's ``linear`` hold weight an interval's samples ``1 - weight`` and
    ``weight`` (:func:`dvt_identify.data.held_inputs` holds 0.5 and 0.5)."""

    def held(seg: Segment) -> np.ndarray:
        hold = seg.input_hold
        if hold is None or "linear" not in hold or seg.n < 2:
            return seg.u
        lin = [j for j, h in enumerate(hold) if h == "linear"]
        u = seg.u.copy()
        u[:-1, lin] = (1.0 - weight) * seg.u[:-1, lin] + weight * seg.u[1:, lin]
        return u

    id_data.held_inputs = held
    id_simulation.held_inputs = held


def show_bandwidths(fit: OEFit, name: str) -> None:
    """The std of parameter ``name`` with 1, 4 and 16 times the automatic Bartlett window."""
    if fit.jac_ is None:
        print("  (the fit did not keep its Jacobian: no bandwidth figures)")
        return
    free = [n for n, f in zip(fit.model.names, fit.model.free, strict=True) if f]
    i = free.index(name)
    sizes = [sg.n for sg in fit.segments_]
    ny = fit.segments_[0].y.shape[1]
    L = covariance_bandwidth(scores(fit.jac_, fit.residual_, ny, sizes))
    row = ", ".join(
        f"{k} x {L}: {sandwich_covariance(fit.jac_, fit.residual_, ny, sizes, k * L).std[i]:.3g}"
        for k in (1, 4, 16))
    print(f"  std of {name} with the Bartlett window {row}")


def structure_truth(arm_inertia: float) -> dict[str, float]:
    """The plant's masses and dampings as the ``dvt`` structure names them: the ``physical``
    parameters' rigid ``M`` (with ``arm_inertia`` [kg m^2] added to ``M22``) and ``D``."""
    from dvt_model.config import resolve

    rigid = resolve({"params": "physical"}).rigid
    M = np.array(rigid.M, dtype=float)
    M[1, 1] += arm_inertia
    D = np.asarray(rigid.D, dtype=float)
    out = {}
    for name, mat in (("M", M), ("D", D)):
        for i, j in ((0, 0), (0, 1), (1, 1)):
            out[f"{name}{i + 1}{j + 1}"] = float(mat[i, j])
    return out


def with_declared_arm(text: str, reduction: float, where: Path) -> Path:
    """The ``dvt`` description ``text`` with ``gravity_load@carrier3`` at the known
    ``reduction`` added to its model effects, written to ``where``."""
    key = "\ncandidates:\n"
    if text.count(key) != 1:
        raise SystemExit("gravity_bias: the dvt description's candidates line changed")
    line = f"  - {{effect: gravity_load, where: carrier3, reduction: {reduction!r}}}"
    path = where / "dvt-declared-arm.yaml"
    path.write_text(text.replace(key, f"\n{line}{key}"))
    return path


if __name__ == "__main__":
    sys.exit(main())
