"""Topic level: minutes of a clean plant raise no more alarms than the detector's design allows
(issue #11, ``docs/loop.md`` §1).

The same unattended chain as ``tests/test_launch_episode.py`` (``dvt-launch sim --supervise``:
the simulated plant at 250 Hz, the model node with the plant's own parameters and its change
detector, the ``watch`` experiment, the ring recorder and the identifier's supervisor), but the
plant never changes. After the launcher's re-arm (the detector learns its reference once the
machine moves), the detector tests the clean residual for at least ``CLEAN_S``. The alarms are
read from the ring's ``/dvt/model/change``.

A false alarm is a statistical event: one run of minutes cannot show a mean time between false
alarms of hours (that figure is the detector's offline one, ``src/dvt_model/test/
test_detect.py``, and on the simulated plant's residual ``tests/test_detector_clean_plant.py``,
``docs/loop.md`` section 1). What one run can show is that the live chain raises no more alarms
than the detector's design allows: at most the count that a Poisson process at the design rate
(``false_alarm_period_s``, 4 h) exceeds with probability below ``MISS_P`` in the tested time
(1 alarm for about 210 s: exceeding it has probability 1e-4 at the design rate), while a chain
that corrupts the residual (lost or mispaired samples, a bad re-anchor) alarms again after
every 10-s re-learning. Asserting "no alarm" instead failed 1 of 21 fresh-clone runs
(2026-11-27, one core busy: one sun-shaft alarm, statistic 32.34 against the threshold 32.22,
a borderline crossing), which the design does not promise to avoid.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import poisson

from conftest import Procs
from dvt_driver.system.bench_loop import (
    DETECTOR_SETTLE_S,
    analyse_episode,
    episode_launch_args,
    run_episode,
    true_change,
)
from dvt_model.detect import DetectorConfig

CLEAN_S = 150.0
"""Clean testing the run must reach [s] (after the re-arm, the settling and the reference)."""
LEARN_S = 10.0
"""The detector's reference window [s] (as in the episode runs)."""
RUN_S = CLEAN_S + 80.0
"""Length of the run [s]: start-up and re-arm (15-25 s; 21 s at a load average of 7-9 on the
2 cores), settling and reference (15 s), testing; the allowance covers a start-up three times
slower than measured (the run cannot end early: a clean run has no episode to wait for)."""
MISS_P = 1e-3
"""Largest probability, at the design's false-alarm rate, of more alarms than allowed."""


def allowed_false_alarms(tested_s: float,
                         period_s: float = DetectorConfig.false_alarm_period_s) -> int:
    """Most false alarms that a detector meeting its design (mean time ``period_s`` [s]
    between false alarms) exceeds in ``tested_s`` [s] with probability below ``MISS_P``."""
    return int(poisson.isf(MISS_P, tested_s / period_s))


def test_the_allowed_count_follows_the_design() -> None:
    """1 alarm in the run's few minutes at the 4-h design; none at a design 100x longer; more
    in a longer run (the bound can fail a chain that alarms repeatedly)."""
    assert allowed_false_alarms(210.0) == 1
    assert allowed_false_alarms(210.0, 400 * 3600.0) == 0
    assert allowed_false_alarms(8 * 3600.0) > 2
    assert poisson.sf(allowed_false_alarms(210.0), 210.0 / (4 * 3600.0)) < MISS_P


@pytest.mark.ros
@pytest.mark.slow
def test_minutes_of_a_clean_plant_raise_no_more_alarms_than_the_design(procs: Procs,
                                                                       tmp_path: Path) -> None:
    logdir = tmp_path / "run"
    args = episode_launch_args(logdir, rate=250.0, change_at=100000.0, learn_s=LEARN_S,
                               duration=RUN_S + 60.0)
    t0 = time.monotonic()
    rc = run_episode(logdir, args, RUN_S, env=procs.env)
    wall = time.monotonic() - t0
    log = (logdir / "launch.log").read_text(errors="replace")
    assert rc == 130, log[-2000:]  # stopped by the test at the end of the run
    assert true_change(logdir) is None, "the plant changed"
    run = analyse_episode(logdir, learn_s=LEARN_S)
    assert run.rearmed is not None, f"the launcher did not re-arm the detector:\n{log[-2000:]}"
    tested_from = run.rearmed + DETECTOR_SETTLE_S + LEARN_S
    tested_s = float(run.bins[-1] + 1.0 - tested_from)
    # the residual flowed through the tested time (no gap of more than 2 s)
    flowing = run.bins[(run.bins >= tested_from) & (run.counts > 0)]
    assert tested_s >= CLEAN_S, (tested_s, wall)
    assert flowing.size and float(np.max(np.diff(flowing), initial=1.0)) <= 2.0, flowing
    false = [a for a in run.alarms if float(a["stamp_s"]) >= tested_from]
    allowed = allowed_false_alarms(tested_s)
    assert len(false) <= allowed, (
        f"{len(false)} false alarm(s) in {tested_s:.0f} s of clean testing, more than the "
        f"{allowed} a detector meeting its design exceeds with probability {MISS_P:g}: {false}")
    print(f"\nclean testing {tested_s:.0f} s, {len(false)} alarm(s) (allowed {allowed}; "
          f"alarms before the testing: {len(run.alarms) - len(false)}); wall {wall:.0f} s")
