"""The change detector's false-alarm rate, measured statistically (the measurement: slow tier).

The claim (``detector.false_alarm_period_s``, default 4 h; :mod:`dvt_model.detect`): on a clean
plant the model node's detector raises on average at most one false alarm per 4 h. Checked here
on the node's own configuration (:func:`dvt_model.config.detector_config` of the defaults: the
mean of 10-ms residual blocks at 100 Hz, a 20-s reference window, re-learning after every
alarm) over hundreds of simulated hours of clean residual, two outputs, for residual colours
that bracket the live plant's (docs/loop.md section 6: sun shaft phi 0.81, theta -0.32; carrier
3 phi 0.98, theta -0.67): white, AR(0.5), AR(0.8) and AR(0.98) with white sensor noise, AR(0.9).

The simulation is the detector's exact algorithm, vectorised
(:func:`dvt_model.detect_sim.simulate_clean`; that it raises the class's alarms at the same samples
is ``test_detect.py::test_class_and_vectorised_simulation_agree``). Alarms in ``T`` tested
hours are a Poisson count: the test prints the rate per hour with its exact two-sided 95 %
interval (chi-square) for every colour and pooled, and fails

- when the data show the rate above the design (a colour's one-sided 95 % *lower* bound above
  1 per 4 h = 0.25 per hour): a threshold 1.5 times too permissive fails it;
- when the data do not show the requirement (docs/loop.md section 1: a mean time between false
  alarms of at least 1 h, i.e. a colour's one-sided 95 % *upper* bound above 1 per hour).

Fixed seeds: the outcome is reproducible. Measured (300 h per colour, seed 20260): white
residual 62 alarms, 0.207/h (95 % 0.158-0.265), the design's level; AR(0.5) 0.050/h, AR(0.8) +
white 0.053/h, AR(0.9) and AR(0.98) + white none (upper bound 0.010/h): for a coloured residual
the threshold, averaged over the estimation error of a 2000-sample reference window, is
conservative. Pooled 93 in 1500 h, 0.062/h (0.050-0.076).
"""

from __future__ import annotations

import gc
import math
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import pytest
from scipy.stats import chi2

from dvt_model.config import detector_config
from dvt_model.detect import DetectorConfig
from dvt_model.detect_sim import rate_bounds, simulate_clean

pytestmark = pytest.mark.timeout(600)

HOURS = 300.0
"""Tested hours per residual colour (split into two independent halves, one per worker)."""
COLOURS = (  # (label, AR(1) coefficient per detector sample, white noise std relative)
    ("white", 0.0, 0.0),
    ("AR(0.5)", 0.5, 0.0),
    ("AR(0.8) + white 0.5", 0.8, 0.5),
    ("AR(0.9)", 0.9, 0.0),
    ("AR(0.98) + white 0.5", 0.98, 0.5),
)
SEED = 20260  # fixed before the first run; never tuned to pass
REQUIRED_MTBFA_H = 1.0
"""The requirement on the mean time between false alarms [h] (docs/loop.md section 1)."""


def poisson_interval(count: int, exposure: float, conf: float = 0.95) -> tuple[float, float]:
    """Exact two-sided ``conf`` interval of a Poisson rate with ``count`` events in
    ``exposure`` (chi-square / Garwood)."""
    a = 1.0 - conf
    lo = 0.0 if count == 0 else float(chi2.ppf(a / 2, 2 * count)) / (2 * exposure)
    hi = float(chi2.ppf(1 - a / 2, 2 * count + 2)) / (2 * exposure)
    return lo, hi


def poisson_upper(count: int, exposure: float, conf: float = 0.95) -> float:
    """One-sided ``conf`` upper bound of a Poisson rate (:func:`rate_bounds`)."""
    return rate_bounds(count, exposure, conf)[1]


def poisson_lower(count: int, exposure: float, conf: float = 0.95) -> float:
    """One-sided ``conf`` lower bound of a Poisson rate (0 with no event)."""
    return rate_bounds(count, exposure, conf)[0]


def _run(job: tuple[DetectorConfig, float, float, float, int]) -> tuple[int, float]:
    cfg, hours, phi, white, seed = job
    sim = simulate_clean(cfg, hours=hours, phi=phi, white=white, seed=seed)
    return sim.alarms, sim.hours


def test_poisson_bounds_are_the_textbook_ones() -> None:
    # 0 events in T: one-sided 95 % upper bound 3.0 / T; 10 events: two-sided (4.80, 18.39) / T,
    # one-sided 95 % lower 5.43 / T
    assert poisson_upper(0, 1.0) == pytest.approx(2.9957, abs=1e-3)
    assert poisson_lower(0, 1.0) == 0.0
    assert poisson_lower(10, 1.0) == pytest.approx(5.4254, abs=1e-3)
    lo, hi = poisson_interval(10, 1.0)
    assert (lo, hi) == (pytest.approx(4.7954, abs=1e-3), pytest.approx(18.390, abs=1e-3))


@pytest.mark.slow  # 1500 simulated hours on two worker processes
def test_false_alarm_rate_of_the_node_detector_is_at_most_its_design() -> None:
    setup = detector_config({})
    assert setup is not None
    cfg = setup.config
    design_per_h = 3600.0 / cfg.false_alarm_period_s
    jobs = [(cfg, HOURS / 2, phi, white, SEED + 10 * i + half)
            for i, (_, phi, white) in enumerate(COLOURS) for half in (0, 1)]
    gc.freeze()  # a forked worker never finalises what it inherited (a ROS
    # context left by an earlier test segfaulted one in its destructor)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        out = list(pool.map(_run, jobs))
    gc.unfreeze()
    print(f"\nnode detector: {cfg.sample_rate_hz:g} Hz blocks, learn {cfg.learn_s:g} s, design "
          f"{design_per_h:.3f} false alarms per hour (one per {cfg.false_alarm_period_s:g} s)")
    failures = []
    total_alarms, total_hours = 0, 0.0
    for i, (label, _, _) in enumerate(COLOURS):
        alarms = out[2 * i][0] + out[2 * i + 1][0]
        hours = out[2 * i][1] + out[2 * i + 1][1]
        total_alarms += alarms
        total_hours += hours
        lo, hi = poisson_interval(alarms, hours)
        lower, upper = poisson_lower(alarms, hours), poisson_upper(alarms, hours)
        print(f"  {label:22s} {alarms:4d} alarms in {hours:6.1f} h: {alarms / hours:.3f}/h "
              f"(95 % {lo:.3f}-{hi:.3f}; one-sided {lower:.3f} / {upper:.3f}); MTBFA "
              f"{hours / alarms if alarms else math.inf:.1f} h")
        if lower > design_per_h:
            failures.append(f"{label}: {alarms} alarms in {hours:.1f} h, one-sided 95 % lower "
                            f"bound {lower:.3f}/h above the design {design_per_h:.3f}/h")
        if upper > 1.0 / REQUIRED_MTBFA_H:
            failures.append(f"{label}: {alarms} alarms in {hours:.1f} h, one-sided 95 % upper "
                            f"bound {upper:.3f}/h: a mean time between false alarms of "
                            f"{REQUIRED_MTBFA_H:g} h not shown")
    lo, hi = poisson_interval(total_alarms, total_hours)
    print(f"  {'pooled':22s} {total_alarms:4d} alarms in {total_hours:6.1f} h: "
          f"{total_alarms / total_hours:.3f}/h (95 % {lo:.3f}-{hi:.3f})")
    assert not failures, "\n".join(failures)


def test_the_rate_check_fails_on_a_detector_designed_for_a_shorter_period() -> None:
    # The check above can fail: a detector whose threshold is designed for one false alarm per
    # 20 min, checked against the node's design (one per 4 h), is shown above it ...
    setup = detector_config({})
    assert setup is not None
    cfg = replace(setup.config, false_alarm_period_s=1200.0)
    alarms, hours = _run((cfg, 10.0, 0.0, 0.0, SEED))
    print(f"\nthreshold for one per 1200 s, white residual: {alarms} alarms in {hours:.1f} h")
    assert poisson_lower(alarms, hours) > 3600.0 / setup.config.false_alarm_period_s
    # ... while its own design (3 per hour) is met within the Poisson uncertainty
    assert poisson_lower(alarms, hours) <= 3600.0 / cfg.false_alarm_period_s
