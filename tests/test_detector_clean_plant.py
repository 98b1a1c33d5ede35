"""The change detector on the simulated plant's own residual, offline (slow): its false-alarm
rate, and its change-time estimate for the step of ``tests/test_change_detection.py``.

``src/dvt_model/test/test_false_alarm_rate.py`` checks the design (one false alarm per 4 h) on
simulated AR(1) residuals. This test checks it where the model node meets it: the node's path
without ROS, sample by sample (:class:`~dvt_driver.plant.core.PlantSim`, clean, 1 kHz, the
drive motor at 4 A in neutral as in ``tests/test_change_detection.py`` -> the model node's
:class:`~dvt_model.predictor.Predictor` with the plant's own parameters (``physical``) ->
:class:`~dvt_model.predictor.ResidualBlocks` -> :class:`~dvt_model.detect.ChangeDetector` with
the node's default settings (10-ms blocks, a 20-s reference window, ``settle_s`` after the
first anchor; re-learning after every alarm, as the node does). ``RUNS`` independent plants
(seeds fixed before the first run), each tested for ``TEST_S`` after its first reference
window; the alarm count over the tested time is Poisson.

Measured (this test, seeds 3100-3115): 5 false alarms, all on carrier 3, in 14.9 min of
testing (4 of 16 runs), 20/h (one-sided 95 %: 7.9 to 42/h) against the design's 0.25/h; in
another 4 runs with other seeds 3 alarms in 3.3 min. The likely cause, from the alarms: carrier
3's 10-ms residual has a slow component (the open-loop response of the slow mode, tau 0.58 s,
about 0.98 per block) beside a faster one, and the ARMA(1,1) learned on 20 s takes phi
0.8-0.9; the whitened residual keeps the slow wander, which the CUSUM's small reference value
accumulates (in one run carrier 3's learned level moved by 0.012 rad/s, 0.3 residual sigmas,
between consecutive windows: six times the standard error the learned ARMA(1,1) gives a 20-s
mean). ``scripts/detector_residual.py --trial`` measures it on 4 longer runs (docs/loop.md,
"Limits"): the whitened 20-s window means scatter twice as far as the design allows, a longer
reference does not help, and a design that widens ``h`` for the whitened residual's long-run
variance meets the rate here only by being 350 times too cautious on a white residual. Hence
the expected failure: the test passes, and the mark must go, when the detector meets its
design on this residual.

The change-time estimate (``test_change_time_estimate_of_a_friction_step``: the topic-level
test's scenario, ``learn_s`` 10, the step 8-12 s after the testing began, 40 plants): measured
before on 185 plants (seeds 1-185) with the same path, 6 false alarms before the step; of the
179 others all detected within 0.39 s, none estimated later than the truth, within [-3, 0] s
in 159 (0.89, 95 % 0.83-0.93), earliest -10.7 s.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import pytest
from scipy.stats import beta, chi2

from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import predicted_held_current
from dvt_model.config import detector_config
from dvt_model.contract import DETECTOR_PREFIX
from dvt_model.detect import ChangeDetector
from dvt_model.params import load_parameters
from dvt_model.predictor import ResidualBlocks

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

RUNS = 16
TEST_S = 60.0  # tested time per run after the first reference window [s]
LEAD_S = 2.0  # the model node starts this long after the motor [s] (as the topic-level test)
CURRENT_A = 4.0
SEED = 3100  # first plant seed; fixed before the first run
STEP = {"sun": 0.05, "carrier3": 0.2}  # N m: the friction step of test_change_detection.py
STEP_RUNS = 40
STEP_SEED = 4000  # first plant seed of the step runs; fixed before the first run
MAX_DELAY = 3.0  # detection stamp - true step [s] (as tests/test_change_detection.py)
LATE_TOL = 0.25  # latest estimated change time after the true one [s] (the same)
WITHIN = (-3.0, LATE_TOL)  # the window the estimate falls in in most runs [s]
WITHIN_AT_LEAST = 0.80  # ... the fraction the data must be consistent with


def node_path(seed: int, learn_s: float | None, test_s: float, step_after_s: float | None = None
              ) -> tuple[list[dict[str, Any]], float, float | None]:
    """One clean plant through the node's path, tested ``test_s`` after the first reference
    window (``learn_s``: ``None`` the node's default); with ``step_after_s`` the plant's Coulomb
    friction steps to ``STEP`` that long after the testing began (the run then ends
    ``test_s`` after the step, or at the first alarm after it). Returns the alarms (dicts), the
    tested seconds and the plant time of the step (``None`` without one)."""
    params = load_parameters("physical")
    setup = detector_config({} if learn_s is None else {f"{DETECTOR_PREFIX}.learn_s": learn_s})
    assert setup is not None
    cfg = setup.config
    tested_from = LEAD_S + setup.settle_s + cfg.learn_s
    step_at = None if step_after_s is None else tested_from + step_after_s
    hidden = None if step_at is None else parse_hidden(
        {"changes": [{"at": step_at, "coulomb": STEP}]}, source="test")
    blocks = ResidualBlocks(setup.block, 2, cfg.max_gap_s)
    det = ChangeDetector(cfg)
    end = (tested_from if step_at is None else step_at) + test_s
    settle_until = float("inf")
    alarms: list[dict[str, Any]] = []
    sim = PlantSim(params, hidden, seed=seed)
    for t, p in predicted_held_current(sim, params, CURRENT_A, end, LEAD_S):
        if p.anchored:
            det.reset()
            blocks.clear()
            settle_until = t + setup.settle_s
        if t < settle_until:
            continue
        block = blocks.add(t, p.residual.tolist())
        if block is not None:
            alarm = det.update(block[0], block[1])
            if alarm is not None:
                alarms.append(alarm.to_dict())
                if step_at is not None and alarm.stamp_s >= step_at:
                    break
    true_step = (float(sim.changes_applied[0]["at_s"]) if sim.changes_applied else None)
    return alarms, det.counters.tested / cfg.sample_rate_hz, true_step


def clean_run(seed: int) -> tuple[int, float, list[tuple[float, str]]]:
    """:func:`node_path` of a clean plant with the node's defaults: (alarms, tested seconds,
    [(stamp, output)])."""
    alarms, tested, _ = node_path(seed, None, TEST_S)
    return len(alarms), tested, [(a["stamp_s"], a["name"]) for a in alarms]


def step_run(seed: int) -> tuple[list[dict[str, Any]], float, float | None]:
    """:func:`node_path` of the scenario of tests/test_change_detection.py: ``learn_s`` 10, the
    step 8-12 s after the testing began."""
    return node_path(seed, 10.0, 8.0, step_after_s=8.0 + (seed % 5))


@pytest.mark.xfail(strict=True, reason=(
    "library (dvt_model.detect): on the simulated plant's own residual the detector raises "
    "false alarms on carrier 3 far above its design of one per 4 h (the ARMA(1,1) whitening "
    "misses the residual's slow component); see the module docstring and the printed figures"))
def test_false_alarm_rate_on_the_clean_simulated_plant_meets_the_design() -> None:
    gc.freeze()  # a forked worker never finalises what it inherited (a ROS
    # context left by an earlier test segfaulted one in its destructor)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(clean_run, range(SEED, SEED + RUNS)))
    gc.unfreeze()
    alarms = sum(n for n, _, _ in out)
    hours = sum(s for _, s, _ in out) / 3600.0
    setup = detector_config({})
    assert setup is not None
    design = 3600.0 / setup.config.false_alarm_period_s
    lower = 0.0 if alarms == 0 else float(chi2.ppf(0.05, 2 * alarms)) / (2 * hours)
    upper = float(chi2.ppf(0.95, 2 * alarms + 2)) / (2 * hours)
    print(f"\nclean simulated plant, node path: {alarms} false alarms in {hours * 60:.1f} min of "
          f"testing ({RUNS} runs): {alarms / hours:.1f}/h (one-sided 95 %: {lower:.2f} to "
          f"{upper:.2f}/h); design {design:.2f}/h; runs with an alarm: "
          f"{sum(n > 0 for n, _, _ in out)}/{RUNS}")
    for seed, (n, tested, where) in zip(range(SEED, SEED + RUNS), out, strict=True):
        if n:
            print(f"  seed {seed}: {n} in {tested:.0f} s: "
                  + ", ".join(f"{name} at {stamp:.2f} s" for stamp, name in where))
    assert lower <= design, (alarms, hours)


def test_change_time_estimate_of_a_friction_step() -> None:
    """The scenario of tests/test_change_detection.py, ``STEP_RUNS`` plants offline: every run
    without a false alarm before the step detects it within ``MAX_DELAY``, braking
    (direction -1), never estimating the change later than ``LATE_TOL``; the estimate is within
    ``WITHIN`` of the truth in a fraction of the runs consistent with ``WITHIN_AT_LEAST``
    (two-sided 95 % Clopper-Pearson upper bound): earlier estimates come from a CUSUM that had
    wandered above zero before the step."""
    gc.freeze()  # a forked worker never finalises what it inherited (a ROS
    # context left by an earlier test segfaulted one in its destructor)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(step_run, range(STEP_SEED, STEP_SEED + STEP_RUNS)))
    gc.unfreeze()
    false_runs, offsets, problems = 0, [], []
    for seed, (alarms, _, step) in zip(range(STEP_SEED, STEP_SEED + STEP_RUNS), out,
                                       strict=True):
        assert step is not None, seed
        if any(a["stamp_s"] < step for a in alarms):
            false_runs += 1  # the false-alarm rate is the test above's
            continue
        after = [a for a in alarms if a["stamp_s"] >= step]
        if not after:
            problems.append(f"seed {seed}: no alarm within 8 s of the step")
            continue
        a = after[0]
        offsets.append(a["change_s"] - step)
        if not (a["stamp_s"] - step <= MAX_DELAY and a["direction"] == -1
                and a["change_s"] - step <= LATE_TOL):
            problems.append(f"seed {seed}: {a}")
    off = np.asarray(offsets)
    k = int(np.sum((off >= WITHIN[0]) & (off <= WITHIN[1])))
    n = off.size
    lo = float(beta.ppf(0.025, k, n - k + 1)) if k else 0.0
    hi = float(beta.ppf(0.975, k + 1, n - k)) if k < n else 1.0
    print(f"\nfriction step, node path offline: {STEP_RUNS} plants, {false_runs} with a false "
          f"alarm before the step; of the {n} others: estimated - true change time quantiles "
          f"(0/5/50/95/100 %) {np.round(np.percentile(off, [0, 5, 50, 95, 100]), 2).tolist()} s; "
          f"within {WITHIN} s in {k}/{n} (95 % {lo:.2f}-{hi:.2f})")
    assert not problems, "\n".join(problems)
    assert n >= STEP_RUNS // 2, (n, false_runs)
    assert hi >= WITHIN_AT_LEAST, (k, n, lo, hi)
