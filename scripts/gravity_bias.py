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

Usage::

    .venv/bin/python scripts/gravity_bias.py [--seeds 0 1 2] [--fit-decimate 0 1]
        [--draw SEED] [--noise-free] [--own-model] [--structure]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
from band_lags import _refit_on_own_model, _show

from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.plant.settings import SensorConfig
from dvt_driver.run.experiment_core import build
from dvt_identify.description import load_description
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.pipeline import load_segments
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
    a = ap.parse_args()
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
    desc = load_description(with_declared_arm(load_description("dvt").text, n, tmp))
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
            if a.own_model:
                _show("  the same fit on the identifier's own model at the plant's a, b",
                      _refit_on_own_model(fit, truth), truth, ".6f", "N m")
    for q, rows in offsets.items():
        m = np.mean(rows, axis=0)
        print(f"fit_decimate {q or 'auto'}: mean offset over {len(rows)} seeds "
              f"a {m[0]:+.6f}, b {m[1]:+.6f} N m")
    return 0


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
