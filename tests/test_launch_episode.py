"""Topic level: ``dvt-launch sim --supervise`` closes the loop by itself (``docs/loop.md`` §4).

One launcher as a subprocess (its own process group, this test's ``ROS_DOMAIN_ID``): the clean
simulated plant at 250 Hz, the model node with the plant's own parameters as its prior, the
``watch`` experiment, the ring recorder and the identifier with its supervisor
(:func:`dvt_driver.system.bench_loop.episode_launch_args`); at plant time ``CHANGE_AT_S`` the
plant's Coulomb friction steps (``friction_step``). The test waits (at most ``DEADLINE_S``)
for the episode report of that change, stops the launcher (SIGINT: it stops its children in
order; SIGKILL of the group as the fallback) and checks: the change detected after the
injection, a refit, a push, and the live residual after the push lower than during the change.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from conftest import Procs
from dvt_driver.system.bench_loop import (
    LIVE_SUPERVISOR,
    analyse_episode,
    change_episode,
    episode_launch_args,
    run_episode,
    true_change,
)

CHANGE_AT_S = 45.0
"""Plant time of the change [s]: after the start-up, the re-arm and the detector's 15 s."""
SNAPSHOT_TIMEOUT_S = 60.0
"""The identify node's ``supervisor.snapshot_timeout_s`` (its default)."""
_SUP = LIVE_SUPERVISOR
DEADLINE_S = (CHANGE_AT_S + 30.0
              + _SUP["min_post_change_s"] + SNAPSHOT_TIMEOUT_S + _SUP["fit_timeout_s"]
              + _SUP["full_post_change_s"] + SNAPSHOT_TIMEOUT_S + _SUP["fit_timeout_s"]
              + 2 * _SUP["push_timeout_s"] + _SUP["watch_s"] + 20.0)
"""Longest run [s] from the supervisor's own bounds (not a guess of the typical time, which is
about 100-150 s): the change, 30 s for the detection and the model node's lag, each stage's
post-change data, snapshot and refit (``snapshot_timeout_s``, ``fit_timeout_s``; the full
stage only when the first is not pushed), push and rollback (``push_timeout_s`` each), the
watch, and 20 s of lag. A phase that runs out ends the episode with its reason, which the
assertions print; the run stops as soon as the episode is reported."""

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(DEADLINE_S + 200.0)]


def test_launch_supervise_detects_refits_pushes_and_restores(procs: Procs,
                                                             tmp_path: Path) -> None:
    logdir = tmp_path / "run"
    args = episode_launch_args(logdir, rate=250.0, change_at=CHANGE_AT_S,
                               duration=DEADLINE_S + 30.0)
    t0 = time.monotonic()
    rc = run_episode(logdir, args, DEADLINE_S, env=procs.env)
    wall = time.monotonic() - t0
    log = (logdir / "launch.log").read_text(errors="replace")
    change = true_change(logdir)
    assert change is not None, f"the plant applied no change:\n{log[-3000:]}"
    rec = change_episode(logdir)
    reports = sorted((logdir / "identify" / "episodes").glob("episode-*.json"))
    assert rec is not None, (f"no episode of the change within {DEADLINE_S:g} s (status {rc}); "
                             f"reports {[json.loads(p.read_text())['outcome'] for p in reports]}"
                             f":\n{log[-3000:]}")
    assert rc == 130, log[-2000:]  # stopped by the test once the episode was reported
    assert "episode-" in log and "re-armed" in log, log[-2000:]
    # detected after the injection
    after = [a for a in rec["alarms"] if a["stamp_s"] >= change]
    assert after, (change, rec["alarms"])
    # refitted and pushed (better on the held-out slice); the watch's verdict is the
    # supervisor's (confirmed, or rolled back when an output got worse live)
    assert rec["refit"] and rec["refit"].get("accepted"), rec["refit"]
    assert rec["pushed"] and rec["outcome"] in ("confirmed", "rolled_back"), \
        (rec["outcome"], rec["reason"])
    # the live residual after the push lower than during the change on the output that
    # alarmed (the supervisor's watch and, independently, the ring's /dvt/model/residual)
    name = after[0]["name"]
    assert rec["live_ratio"][name] < 0.8, (name, rec["live_before"], rec["live_after"],
                                           rec["refit"].get("accepted"),
                                           rec["refit"].get("changed"))
    f = analyse_episode(logdir).figures
    assert f["residual_rms_restored"][name] < f["residual_rms_changed"][name], f
    assert (logdir / "identify" / "episodes" / f"episode-{rec['episode']}.md").exists()
    print(f"\nwall {wall:.0f} s; detection delay {f['detection_delay_s']} s, push "
          f"+{f['push_after_change_s']} s, restored +{f['restored_s']} s; residual RMS clean "
          f"{f['residual_rms_clean']}, changed {f['residual_rms_changed']}, restored "
          f"{f['residual_rms_restored']}; false alarms {f['false_alarms']} in "
          f"{f['clean_tested_s']} s; timings {rec['timings']}")
