"""The change detector on the simulated plant's own residual, offline (slow): its false-alarm
rate once the residual's colour is learned and before it (the first minute after a start), and
its change-time estimate for the step of ``tests/test_change_detection.py``.

``src/dvt_model/test/test_false_alarm_rate.py`` and ``test_detect_colour.py`` check the design
(one false alarm per 4 h) on simulated coloured residuals. This test checks it where the model
node meets it: the node's path without ROS, sample by sample
(:class:`~dvt_driver.plant.core.PlantSim`, clean, 1 kHz, the drive motor at 4 A in neutral as
in ``tests/test_change_detection.py`` -> the model node's
:class:`~dvt_model.predictor.Predictor` with the plant's own parameters (``physical``) ->
:class:`~dvt_model.predictor.ResidualBlocks` -> :class:`~dvt_model.detect.ChangeDetector` with
the node's default settings (10-ms blocks, a 20-s reference window, ``settle_s`` after the
first anchor, re-learning after every alarm, the colour learned on ``detector.colour_s`` =
300 s of residual). ``RUNS`` independent plants (seeds fixed before the first run), each tested
for ``TEST_S`` once the colour whitens it; the alarm count over the tested time is Poisson,
and the test fails when its one-sided 95 % lower bound is above the design, i.e. on 2 or more
alarms in the 40 min: with probability 0.99 at the 10/h that the ARMA(1, 1) of each window
gives on this residual, 0.80 at 4.5/h, 0.26 at 1.5/h and 0.01 at the design (a weak check of
the design itself: ``scripts/detector_residual.py`` measures it on longer records,
docs/loop.md "Colour").

Measured (this test, seeds 3100-3107): 0 false alarms in 40 min with the full colour; before
it (the detector's first 5 minutes: each window's ARMA(1, 1) in the first, then a colour on
60-240 s of history) 1 in 35 min (2026-12-05; 6 in 39 min, all but one on carrier 3, when the
first 5 minutes ran on the ARMA(1, 1) alone). Since the growing colour rewhitens and allows
for what it leaves (2026-12-06, 9419efd): 1 in 40 min with the full colour, 3 in 35 min
before it, on these 8 starts (``pytest -s`` prints them); over 150 starts the minutes 1-5
fell from 7.4/h to 0.98/h (``scripts/results.sh detector_starts``, docs/loop.md "Limits").
Carrier 3's 10-ms residual has at least three time scales (about 0.2, 0.6 and 1.4 s) beside
the sensor noise, and the ARMA(1, 1) learned on 20 s leaves the slow ones in the whitened
residual, which the CUSUM's small reference value accumulates.

The change-time estimate (``test_change_time_estimate_of_a_friction_step``: the topic-level
test's scenario, ``learn_s`` 10, the step 8-12 s after the testing began, 40 plants, so before
the colour): measured before on 185 plants (seeds 1-185) with the same path, 6 false alarms
before the step; of the 179 others all detected within 0.39 s, none estimated later than the
truth, within [-3, 0] s in 159 (0.89, 95 % 0.83-0.93), earliest -10.7 s.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import pytest
from scipy.stats import beta

from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import predicted_held_current
from dvt_model.config import DetectorSetup, detector_config
from dvt_model.contract import DETECTOR_PREFIX
from dvt_model.detect import COLOUR_CHUNK_S, ChangeDetector
from dvt_model.detect_sim import rate_bounds
from dvt_model.params import TransmissionParams, load_parameters
from dvt_model.predictor import ResidualBlocks

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

RUNS = 8
TEST_S = 300.0  # tested time per run with the full colour in use [s]
LEAD_S = 2.0  # the model node starts this long after the motor [s] (as the topic-level test)
CURRENT_A = 4.0
SEED = 3100  # first plant seed; fixed before the first run
STEP = {"sun": 0.05, "carrier3": 0.2}  # N m: the friction step of test_change_detection.py
STEP_RUNS = 40
MAX_FALSE_RUNS = 4
"""Runs of the step scenario allowed a false alarm before the step: 5 or more of 40 fail, with
probability 0.009 at the rate measured on 185 plants (6 of 185, 3.2 %), 0.37 at 10 %, 0.74 at
15 % and 0.92 at 20 % (binomial)."""
STEP_SEED = 4000  # first plant seed of the step runs; fixed before the first run
FIRST_SEED = 6000  # first plant seed of the starts before the colour; fixed before the first run
FIRST_STARTS = 90  # node starts, each tested until just before its first colour
FIRST_TEST_S = 39.0  # tested per start [s]: the first colour comes 60 s into the history
FIRST_MAX_ALARMS = 5
"""Most false alarms allowed in the ``FIRST_STARTS`` starts before the colour (about 1 h of
testing): 6 or more fail, with probability 0.001 at the 1.14/h measured on 400 starts of other
plants (``scripts/results.sh detector_first``, docs/loop.md "Limits"), 0.03 at its one-sided
95 % bound 2.39/h, and 0.95 at the 10.8/h of the ARMA's own design before (Poisson)."""
CARRY_SEED = 6500  # first plant seed of the starts with a carried colour; fixed before the run
CARRY_PLANTS = 10
CARRY_S = 360.0  # residual [s] of each plant's earlier run, whose colour the starts carry in
CARRY_STARTS = 10  # node starts per plant after it, one a minute
CARRY_MAX_ALARMS = 2
"""Most false alarms allowed in the first minutes of the ``CARRY_PLANTS x CARRY_STARTS``
starts with a carried colour (40 s tested in each, 1.1 h): 3 or more fail, with probability
0.003 at the design (0.25/h), 0.14 at the 1.14/h of the first minute without it (400 starts,
``scripts/results.sh detector_first``), 0.50 at 2.39/h, its one-sided 95 % bound, and 1.00 at
the 10.8/h of each window's ARMA(1, 1) alone (Poisson): a weak check against the first
minute without it (the plant is slow: about 5 minutes on two cores); the rate itself is
measured on 560 starts (``scripts/results.sh detector_carried``, docs/loop.md "Limits")."""
MAX_DELAY = 3.0  # detection stamp - true step [s] (as tests/test_change_detection.py)
LATE_TOL = 0.25  # latest estimated change time after the true one [s] (the same)
WITHIN = (-3.0, LATE_TOL)  # the window the estimate falls in in most runs [s]
WITHIN_AT_LEAST = 0.80  # ... the fraction the data must be consistent with


def node_blocks(sim: PlantSim, params: TransmissionParams, setup: DetectorSetup,
                end: float) -> Iterator[tuple[float, float, list[float]]]:
    """The residual the model node's detector sees on ``sim`` until plant time ``end`` [s]: the
    prediction of the drive at ``CURRENT_A`` with ``params`` (the node starting ``LEAD_S``
    after the motor), nothing for ``setup.settle_s`` after each anchor, then the node's
    residual blocks (:class:`~dvt_model.predictor.ResidualBlocks`). Yields (the plant time [s]
    the settling after the latest anchor ended, the block's stamp [s], its residual, one value
    per output)."""
    blocks = ResidualBlocks(setup.block, 2, setup.config.max_gap_s)
    settle_until = float("inf")
    for t, p in predicted_held_current(sim, params, CURRENT_A, end, LEAD_S):
        if p.anchored:
            blocks.clear()
            settle_until = t + setup.settle_s
        if t < settle_until:
            continue
        block = blocks.add(t, p.residual.tolist())
        if block is not None:
            yield settle_until, block[0], block[1]


def node_path(seed: int, learn_s: float | None, test_s: float, step_after_s: float | None = None,
              colour: bool = False) -> tuple[list[dict[str, Any]], float, float | None, float]:
    """One clean plant through the node's path, tested ``test_s`` after the first reference
    window (``learn_s``: ``None`` the node's default); with ``colour`` ``test_s`` after the
    first reference window that uses the long-window whitening fitted on its full history
    (``detector.colour_s``); with
    ``step_after_s`` the plant's Coulomb friction steps to ``STEP`` that long after the testing
    began (the run then ends ``test_s`` after the step, or at the first alarm after it).
    Returns the alarms (dicts, each with ``"colour"``: whether the full colour was in use),
    the tested seconds (with ``colour``: with the full colour in use), the plant time of the
    step (``None`` without one) and the tested seconds before the full colour."""
    params = load_parameters("physical")
    setup = detector_config({} if learn_s is None else {f"{DETECTOR_PREFIX}.learn_s": learn_s})
    assert setup is not None
    cfg = setup.config
    tested_from = LEAD_S + setup.settle_s + cfg.learn_s
    step_at = None if step_after_s is None else tested_from + step_after_s
    hidden = None if step_at is None else parse_hidden(
        {"changes": [{"at": step_at, "coulomb": STEP}]}, source="test")
    det = ChangeDetector(cfg)
    end = (tested_from if step_at is None else step_at) + test_s
    if colour:  # the colour's history, a chunk's slack and the new reference window
        end += cfg.colour_s + COLOUR_CHUNK_S + cfg.learn_s
    alarms: list[dict[str, Any]] = []
    tested = [0, 0]  # samples tested before the full colour, with it
    settled = float("nan")
    sim = PlantSim(params, hidden, seed=seed)
    for since, stamp, values in node_blocks(sim, params, setup, end):
        if since != settled:  # anchored again
            det.reset()
            settled = since
        phase = int(det.colour_complete)
        before = det.counters.tested
        alarm = det.update(stamp, values)
        tested[phase] += det.counters.tested - before
        if alarm is not None:
            alarms.append({**alarm.to_dict(), "colour": bool(phase)})
            if step_at is not None and alarm.stamp_s >= step_at:
                break
        if colour and tested[1] >= test_s * cfg.sample_rate_hz:
            break
    true_step = (float(sim.changes_applied[0]["at_s"]) if sim.changes_applied else None)
    rate = cfg.sample_rate_hz
    return (alarms, tested[int(colour)] / rate, true_step,
            tested[0] / rate)


def clean_run(seed: int) -> tuple[list[tuple[float, str, bool]], float, float]:
    """:func:`node_path` of a clean plant with the node's defaults, tested ``TEST_S`` with the
    full colour in use: ([(stamp, output, with the full colour)], tested seconds with it,
    before it)."""
    alarms, tested, _, before = node_path(seed, None, TEST_S, colour=True)
    return [(a["stamp_s"], a["name"], a["colour"]) for a in alarms], tested, before


def step_run(seed: int) -> tuple[list[dict[str, Any]], float, float | None, float]:
    """:func:`node_path` of the scenario of tests/test_change_detection.py: ``learn_s`` 10, the
    step 8-12 s after the testing began."""
    return node_path(seed, 10.0, 8.0, step_after_s=8.0 + (seed % 5))


def test_false_alarm_rate_on_the_clean_simulated_plant_meets_the_design() -> None:
    gc.freeze()  # a forked worker never finalises what it inherited (a ROS
    # context left by an earlier test segfaulted one in its destructor)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(clean_run, range(SEED, SEED + RUNS)))
    gc.unfreeze()
    alarms = sum(sum(c for _, _, c in where) for where, _, _ in out)
    hours = sum(s for _, s, _ in out) / 3600.0
    early = sum(sum(not c for _, _, c in where) for where, _, _ in out)
    early_h = sum(b for _, _, b in out) / 3600.0
    setup = detector_config({})
    assert setup is not None
    design = 3600.0 / setup.config.false_alarm_period_s
    lower, upper = rate_bounds(alarms, hours)
    print(f"\nclean simulated plant, node path, the colour in use: {alarms} false alarms in "
          f"{hours * 60:.1f} min of testing ({RUNS} runs): {alarms / hours:.1f}/h (one-sided "
          f"95 %: {lower:.2f} to {upper:.2f}/h); design {design:.2f}/h; before the full "
          f"colour (ARMA(1, 1) per window, then a colour on a shorter history): {early} in "
          f"{early_h * 60:.1f} min")
    for seed, (where, tested, _) in zip(range(SEED, SEED + RUNS), out, strict=True):
        if where:
            print(f"  seed {seed} ({tested:.0f} s with the full colour): " + ", ".join(
                f"{name} at {stamp:.2f} s{'' if c else ' (before the full colour)'}"
                for stamp, name, c in where))
    assert lower <= design, (alarms, hours)


def first_minute(seed: int) -> tuple[int, float]:
    """A node start with the defaults, tested ``FIRST_TEST_S`` before its first colour:
    (false alarms, tested seconds)."""
    alarms, _, _, before = node_path(seed, None, FIRST_TEST_S)
    return len(alarms), before


def test_false_alarm_rate_before_the_colour_allows_for_what_the_window_cannot_see() -> None:
    """The detector's first minute after a start (each reference window whitened by its own
    ARMA(1, 1), the threshold designed over the long-run variance ratio the window measures and
    its uncertainty, ``dvt_model.detect.long_run_spread``): at most ``FIRST_MAX_ALARMS`` false
    alarms in ``FIRST_STARTS`` starts of independent plants. Without the allowance (the
    ARMA's design alone) this residual raised 10.8/h (``docs/results/detector_starts.json`` at
    9419efd): the test fails on it with probability 0.95. The design (0.25/h) is not met before
    the colour (docs/loop.md "Limits")."""
    gc.freeze()  # a forked worker never finalises what it inherited
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(first_minute, range(FIRST_SEED, FIRST_SEED + FIRST_STARTS)))
    gc.unfreeze()
    alarms = sum(a for a, _ in out)
    hours = sum(t for _, t in out) / 3600.0
    lower, upper = rate_bounds(alarms, hours)
    print(f"\nbefore the colour: {alarms} false alarms in {hours:.2f} h ({FIRST_STARTS} starts): "
          f"{alarms / hours:.2f}/h (one-sided 95 %: {lower:.2f} to {upper:.2f}/h)")
    assert hours >= 0.9 * FIRST_STARTS * FIRST_TEST_S / 3600.0, hours  # tested, not learning
    assert alarms <= FIRST_MAX_ALARMS, (alarms, hours)


def carried_starts(seed: int) -> tuple[int, float, int]:
    """One clean plant through the node's path: its first ``CARRY_S`` of residual teach a
    detector the colour (an earlier run, ``ChangeDetector.carry``), then a node start every
    minute carries it in (``detector.colour_file``); (false alarms in the first minutes,
    tested seconds there, starts that tested with the carried colour)."""
    params = load_parameters("physical")
    setup = detector_config({})
    assert setup is not None
    cfg = setup.config
    earlier = ChangeDetector(cfg)
    det: ChangeDetector | None = None
    carried = None
    alarms, tested, used, started = 0, 0, 0, 0.0
    end = LEAD_S + setup.settle_s + CARRY_S + 60.0 * CARRY_STARTS
    sim = PlantSim(params, None, seed=seed)
    for since, stamp, values in node_blocks(sim, params, setup, end):
        if det is None and carried is None:
            earlier.update(stamp, values)
            if stamp - since >= CARRY_S:
                carried = earlier.carry()
                assert carried is not None, f"seed {seed}: no full colour in {CARRY_S:g} s"
        if carried is not None and (det is None or stamp - started >= 60.0):
            det, started = ChangeDetector(cfg, carried), stamp
        if det is not None and stamp - started < 60.0:
            before = det.counters.tested
            alarms += det.update(stamp, values) is not None
            tested += det.counters.tested - before
            if det.colour_carried and det.references and all(
                    r.order > 0 for r in det.references) and det.counters.tested == 1:
                used += 1
    return alarms, tested / cfg.sample_rate_hz, used


@pytest.mark.timeout(1800)
def test_false_alarm_rate_of_the_first_minute_with_a_carried_colour() -> None:
    """The first minute after a start whose detector carries the colour of an earlier run of
    the same plant and model in (``detector.colour_file``: the first reference window whitened
    by it, ``h`` over that window's long-run ratio with its uncertainty): at most
    ``CARRY_MAX_ALARMS`` false alarms in ``CARRY_PLANTS x CARRY_STARTS`` starts, each of
    which tested with the carried colour."""
    gc.freeze()  # a forked worker never finalises what it inherited
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(carried_starts, range(CARRY_SEED, CARRY_SEED + CARRY_PLANTS)))
    gc.unfreeze()
    alarms = sum(a for a, _, _ in out)
    hours = sum(t for _, t, _ in out) / 3600.0
    lower, upper = rate_bounds(alarms, hours)
    print(f"\nfirst minute with a carried colour: {alarms} false alarms in {hours:.2f} h "
          f"({CARRY_PLANTS * CARRY_STARTS} starts): {alarms / hours:.2f}/h (one-sided 95 %: "
          f"{lower:.2f} to {upper:.2f}/h)")
    assert [u for _, _, u in out] == [CARRY_STARTS] * CARRY_PLANTS, out  # every start carried
    assert hours >= 0.9 * CARRY_PLANTS * CARRY_STARTS * 40.0 / 3600.0, hours  # tested
    assert alarms <= CARRY_MAX_ALARMS, (alarms, hours)


def test_change_time_estimate_of_a_friction_step() -> None:
    """The scenario of tests/test_change_detection.py, ``STEP_RUNS`` plants offline: at most
    ``MAX_FALSE_RUNS`` of them raise a false alarm before the step; every other run detects it
    within ``MAX_DELAY``, braking
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
    for seed, (alarms, _, step, _) in zip(range(STEP_SEED, STEP_SEED + STEP_RUNS), out,
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
    assert false_runs <= MAX_FALSE_RUNS, (false_runs, STEP_RUNS)
    assert hi >= WITHIN_AT_LEAST, (k, n, lo, hi)
