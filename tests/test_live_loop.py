"""Topic level: the self-closing loop (``docs/loop.md``) with real processes.

A recording of the simulated plant (offline runner through the driver's supervisor) holds a
clean part followed by runs of the same plant with the ``coulomb`` hidden preset, replayed at
500 Hz (every 2nd sample), stamped in host time from just before the replay (the rolling
recorder selects its windows by host time). It is replayed at rate 1 into the model node
(``physical`` prior, the plant's own parameters), a ``dvt-recorder`` in rolling mode and
``dvt_identify_node`` with the supervisor enabled (short windows, ``min_relative_gain`` 0.25).

1. ``test_detected_change_is_refitted_pushed_and_confirmed``: the model node's detector
   (reference learned on 12.5 s of neutral PRBS) raises the alarm - only the detector: the test
   publishes nothing, so a detector that misses the change fails the test - -> wait ->
   snapshot -> refit (finds the Coulomb friction) -> better on the held-out slice -> push ->
   watch -> confirmed; every step on ``/diagnostics``, the report written and published.
2. ``test_unverifiable_push_is_rolled_back``: the same, test alarm, replay stopped when the watch
   starts: no live residual, so the push is rolled back; the model node's parameters are the
   ones read before the push again (``M``, ``D`` not set, ``effects`` empty).
3. ``test_false_alarm_on_a_good_model_is_not_pushed``: a test alarm on a clean recording with
   the plant's own model in use: the refit is not better by the required margin, no push; three
   malformed alarms before it are refused and counted, the node keeps running.

A push that then makes the live residual worse is rolled back: unit tests
(``src/dvt_identify/test/test_supervisor.py``). The model node runs with
``detector.enabled:=false`` in 2 and 3, so that only the test's alarm counts.
"""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String
from test_identify_node import _get

from conftest import wait_for
from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import run_offline
from dvt_driver.run.experiment_core import Experiment, build
from dvt_model import rosutil
from dvt_model.contract import CHANGE_QOS, IDENTIFY_EPISODE, MODEL_CHANGE
from dvt_model.detect import Alarm
from dvt_model.params import load_parameters
from dvt_model.recording import write_run

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SHORT = {"neutral_prbs": 2.5, "neutral_multisine": 2.0, "steps_dwell": 0.6, "shift": 0.5,
         "excite": 1.2}
"""A shortened ``ident`` experiment (about 14.7 s), as tests/test_false_effects.py."""
KEEP_EVERY = 2
"""The plant runs at 1 kHz; every 2nd sample is replayed (500 Hz): the model node, the recorder
and the identifier are Python processes sharing 2 cores with other jobs, and at 1 kHz a loaded
model node falls tens of seconds behind (its parameter services with it)."""
LEAD_S = 1.5
"""Stamps start this long after the bag is written (the replay's start-up)."""
DETECTOR_LEARN_S = 8.0
"""The model node's reference window [s] (default 20): learned on the 14 s of neutral PRBS."""
SUPERVISOR = {"min_post_change_s": 16.0, "settle_s": 1.0, "validation_s": 5.0,
              # one refit per episode (the first stage, the structure held at the model in
              # use): its decision is the outcome; the second stage has its unit tests
              "full_post_change_s": 0.0,
              # watch and baseline span a whole repeated run: comparable operating points
              "watch_s": 15.0, "watch_settle_s": 1.0, "baseline_s": 15.0,
              "min_watch_samples": 1000, "fit_timeout_s": 90.0, "push_timeout_s": 40.0}
SNAPSHOT_MARGIN_S = 10.0
"""The recorder's ``snapshot_margin_s`` (it, too, runs behind on two loaded cores)."""
SNAPSHOT_TIMEOUT_S = 60.0
"""The identify node's ``supervisor.snapshot_timeout_s`` (its default)."""
DETECT_S = 30.0
"""Wall time after the change [s] within which the model node's alarm must arrive. Measured on
this 2-core machine (2026-11-26, quiet and with one core busy): the detector's change estimate
0.01 s from the truth, the alarm within 2 s of the change in data time; the model node's lag
behind the wall clock adds up to ~10 s when the cores are loaded. The detector's own delay is
checked in data time (``stamp_s - change``), not by this bound."""
EPISODE_S = (SUPERVISOR["min_post_change_s"] + SNAPSHOT_TIMEOUT_S + SUPERVISOR["fit_timeout_s"]
             + 2 * SUPERVISOR["push_timeout_s"] + SUPERVISOR["watch_s"] + 20.0)
"""Upper bound [s, wall] from the alarm to the episode report: every phase of the supervisor is
bounded by its own setting (waiting ``min_post_change_s`` of data, the snapshot
``snapshot_timeout_s`` after the window's end, the refit ``fit_timeout_s``, push and rollback
``push_timeout_s`` each, the watch ``watch_s``) plus 20 s for the model node's lag. Measured
typical figures (2026-11-26, 2 cores, quiet and one core busy): waiting 15.2-15.9 s, snapshot
and refit 15.5-16.4 s (the refit itself 5.3-6.2 s; a cold numba cache adds 3.5 s), push < 0.1 s,
whole episode 46-48 s. The test waits for the supervisor's verdict, not a tighter guess: a
phase that runs out ends the episode with its reason, which the assertion prints."""


def _runs(hidden: list[str], repeat: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Speeds, currents of the runs back to back (1 kHz), the changed runs (those after the
    clean ones) repeated ``repeat`` times (the replay is stopped when the episode ends: the
    data outlast a slow refit on a loaded machine), and the length of the clean part [s]."""
    def experiment(i: int, h: str) -> Experiment:
        if h == "quiet":  # neutral PRBS only: a steady residual to learn the reference on
            return build("prbs", seed=i + 1, length=12.5)
        return build("ident", seed=i + 1, **SHORT)

    runs = [run_offline(experiment(i, h), load_parameters("physical"),
                        load_hidden("none" if h == "quiet" else h), seed=100 + i)
            for i, h in enumerate(hidden)]
    dt = float(runs[0].t[1] - runs[0].t[0])
    clean = hidden.index("coulomb") if "coulomb" in hidden else 1
    order = [*runs[:clean], *(runs[clean:] * repeat)]
    return (np.concatenate([r.speeds for r in order])[::KEEP_EVERY],
            np.concatenate([r.currents for r in order])[::KEEP_EVERY],
            sum(len(r.t) for r in runs[:clean]) * dt)


def _write_now(path: Path, speeds: np.ndarray, currents: np.ndarray) -> float:
    """Write the bag stamped in host time from ``now + LEAD_S``; returns the first stamp [s]."""
    start_ns = time.time_ns() + int(LEAD_S * 1e9)
    stamps = start_ns + np.arange(len(speeds), dtype=np.int64) * (1_000_000 * KEEP_EVERY)
    write_run(path, stamps, speeds, currents)
    return start_ns * 1e-9


class _Loop:
    """The test's view of the graph: episode reports and supervisor diagnostics (no 1 kHz
    subscription: the test process must not load the two shared cores)."""

    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("test_live_loop", context=ctx)
        self.exe = SingleThreadedExecutor(context=ctx)
        self.exe.add_node(self.node)
        self.listener = self
        node = self.node
        self.episodes: list[dict[str, Any]] = []
        self.steps: list[tuple[int, str, dict[str, str]]] = []
        node.create_subscription(String, IDENTIFY_EPISODE,
                                 lambda m: self.episodes.append(json.loads(m.data)),
                                 rosutil.qos(CHANGE_QOS))
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diag, 100)
        self.alarm = node.create_publisher(String, MODEL_CHANGE, rosutil.qos(CHANGE_QOS))
        self.alarms: list[dict[str, Any]] = []
        self.source = ""
        self.early: list[dict[str, Any]] = []
        node.create_subscription(String, MODEL_CHANGE, self._alarm, rosutil.qos(CHANGE_QOS))

    def _alarm(self, msg: String) -> None:
        try:
            data = json.loads(msg.data)
        except ValueError:
            return
        if isinstance(data, dict) and isinstance(data.get("change_s"), float):
            self.alarms.append(data)

    def spin_until(self, pred: Any, timeout: float, what: str) -> Any:
        def check() -> Any:
            self.exe.spin_once(timeout_sec=0.05)
            return pred()
        return wait_for(check, timeout, what, interval=0.0)

    def _diag(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name == "dvt_identify: supervisor":
                self.steps.append((st.level[0] if isinstance(st.level, bytes) else int(st.level),
                                   st.message, {kv.key: kv.value for kv in st.values}))


def _start(procs: Any, tmp: Path, min_gain: float, detector: bool = False) -> Any:
    """Start the model node, the ring recorder and the identifier; returns the identifier's
    process."""
    procs.start("dvt_model_node", "--ros-args", "-p", "params:=physical",
                "-p", f"detector.enabled:={'true' if detector else 'false'}",
                "-p", f"detector.learn_s:={DETECTOR_LEARN_S}",
                "-p", f"detector.sample_rate_hz:={1000.0 / KEEP_EVERY}")
    procs.start("dvt-recorder", "--ros-args", "-p", f"output:={tmp / 'ring'}",
                "-p", "ring_minutes:=2.0", "-p", "ring_segment_seconds:=2.0",
                "-p", "snapshot_margin_s:=10.0",  # the recorder, too, runs behind
                "-p", "topics:=[/dvt/joint_states, /dvt/currents]")  # the refit's only
    args = ["-p", "supervisor.enabled:=true", "-p", f"output_dir:={tmp / 'out'}",
            "-p", f"supervisor.min_relative_gain:={min_gain}",
            "-p", f"supervisor.fit_decimate:={10 // KEEP_EVERY}"]  # fit at 100 Hz: bounded
    for k, v in SUPERVISOR.items():
        args += ["-p", f"supervisor.{k}:={v}"]
    return procs.start("dvt_identify_node", "--ros-args", *args)


def _episode(procs: Any, loop: _Loop, tmp: Path, hidden: list[str], repeat: int,
             timeout: float, stop_when_watching: bool = False, detector: bool = False
             ) -> tuple[dict[str, Any], float]:
    """Replay the runs; the model node's detector raises the alarm (``detector``), or the
    test publishes it 1.5 s after the change; wait for the episode (with
    ``stop_when_watching``: stop the replay as soon as the watch starts, so that no live
    residual arrives after the push). Returns the report and the true change time."""
    lst = loop.listener
    speeds, currents, first = _runs(hidden, repeat)
    lst.spin_until(lambda: lst.node.count_publishers("/dvt/model/residual") > 0, 20.0,
                   "model node")
    lst.spin_until(lambda: lst.node.count_subscribers(MODEL_CHANGE) > 0, 20.0,
                   "identify node's alarm subscription")
    lst.spin_until(lambda: lst.node.count_subscribers("/dvt/recorder/snapshot") > 0, 20.0,
                   "recorder's snapshot subscription")
    t0 = _write_now(tmp / "live", speeds, currents)
    replay = procs.start("dvt-replay", str(tmp / "live"), "--rate", "1.0",
                         "--wait-subscribers", "2", "--wait-timeout", "20")
    change = t0 + first
    if detector:
        # only the model node's detector raises the alarm: a missed change fails the test
        loop.source = "detector"
        lst.spin_until(lambda: any(a["change_s"] >= change - 1.0 for a in loop.alarms),
                       (change - time.time()) + DETECT_S, "the model node's alarm")
        # an alarm before the change (a false alarm) starts an episode early; the next alarm
        # restarts the wait from its change time: counted and printed, not hidden
        loop.early = [a for a in loop.alarms if a["change_s"] < change - 1.0]
    else:
        loop.source = "test"
        # the stamps follow the host clock (replay at rate 1 from about their start)
        lst.spin_until(lambda: time.time() > change + 1.5, 60.0, "the replay past the change")
        assert replay.poll() is None, procs.log(replay)
        _publish_alarm(loop, change)
    if stop_when_watching:
        lst.spin_until(lambda: (any(v.get("state") == "watching" for _, _, v in loop.steps)
                                or loop.episodes), timeout, "the watch (or the episode's end)")
        if not any(v.get("state") == "watching" for _, _, v in loop.steps):
            rep = loop.episodes[-1]
            pytest.fail(f"the episode ended without a watch: {rep['outcome']}: {rep['reason']}; "
                        f"timings {rep['timings']}")
        procs.stop(replay)
    lst.spin_until(lambda: loop.episodes, timeout, "the episode report")
    procs.stop(replay)
    return loop.episodes[-1], change


def _alarm(change: float) -> Alarm:
    """The alarm the tests publish for a change at ``change`` [s], as the model node would."""
    return Alarm(stamp_s=change + 1.5, change_s=change, output=1, name="carrier3",
                 direction=1, statistic=150.0, threshold=110.0, samples=1500, shift=0.05,
                 shift_sigma=1.0, level=0.0, sigma=0.05)


def _publish_alarm(loop: _Loop, change: float) -> None:
    """The alarm as the model node would publish it (and three malformed ones first)."""
    alarm = _alarm(change)
    for bad in ("not json", json.dumps({"change_s": "soon", "stamp_s": 1.0}), "[1, 2]"):
        loop.alarm.publish(String(data=bad))  # refused with a warning, never a crash
    loop.alarm.publish(String(data=alarm.to_json()))


def _check_report(rep: dict[str, Any], change: float, tmp: Path, tol: float = 1e-6,
                  output: str = "carrier3") -> None:
    for key in ("episode", "change_s", "detected_s", "outputs", "alarms", "estimation",
                "validation", "refit", "error_before", "error_after", "test", "pushed",
                "rolled_back", "outcome", "reason", "timings", "steps"):
        assert key in rep, key
    assert abs(rep["change_s"] - change) <= tol, (rep["change_s"], change)
    assert not output or output in rep["outputs"], rep["outputs"]
    est, val = rep["estimation"], rep["validation"]
    start = max(rep["change_s"] + 1.0, rep["detected_s"])  # settle_s 1, not before detection
    assert est[0] == pytest.approx(start) and est[1] == pytest.approx(val[0])
    assert val[1] - val[0] == pytest.approx(5.0)
    assert rep["refit"]["samples"]["estimation"] > 9000 // KEEP_EVERY, rep["refit"]
    written = json.loads((tmp / "out" / "episodes" / "episode-1.json").read_text())
    assert written["outcome"] == rep["outcome"]
    md = (tmp / "out" / "episodes" / "episode-1.md").read_text()
    assert md.startswith(f"# Episode 1: {rep['outcome']}")


def test_detected_change_is_refitted_pushed_and_confirmed(procs, rclpy_context, tmp_path):
    """The model node's detector (reference window ``DETECTOR_LEARN_S``, learned on 12.5 s of
    neutral PRBS of the clean plant) raises the alarm; the identifier does the rest."""
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.25, detector=True)
    rep, change = _episode(procs, loop, tmp_path, ["quiet", "coulomb", "coulomb"],
                           repeat=4, timeout=EPISODE_S, detector=True)
    # the detector's estimate of the change time: within 2 s of the true one, and the alarm
    # raised (in data time) within 3 s of the change
    _check_report(rep, change, tmp_path, tol=2.0, output="")
    assert rep["detected_s"] - change <= 3.0, (rep["detected_s"] - change)
    assert rep["outcome"] == "confirmed", (rep["outcome"], rep["reason"])
    assert rep["pushed"] and not rep["rolled_back"]
    refit = rep["refit"]
    # Coulomb friction found (on one or both outputs: the augment loop is greedy and the
    # window's position varies with the load by a second or so)
    assert any(a.startswith("coulomb_friction@") for a in refit["accepted"]), refit
    assert any(c["parameter"] == "effects" and "coulomb" in c["after"]
               for c in refit["changed"]), refit["changed"]
    # the held-out slice: the new model far better than the one in use (the Coulomb terms)
    ratios = [rep["error_after"][k] / rep["error_before"][k] for k in rep["error_before"]]
    assert max(ratios) < 0.9 and min(ratios) < 0.6, (rep["error_before"], rep["error_after"])
    assert rep["test"]["p_value"] < 0.05
    assert max(rep["live_ratio"].values()) < 1.0, rep["live_ratio"]
    # the model node runs the refitted model
    effects = json.loads(_get(loop.listener, "dvt_model", ["effects"])[0].string_value)
    assert [t["kind"] for t in effects].count("coulomb") >= 1, effects
    states = [v.get("state") for _, _, v in loop.steps]
    for state in ("waiting", "refitting", "pushing", "watching", "idle"):
        assert state in states, (state, [m for _, m, _ in loop.steps])
    assert any("confirmed" in m for _, m, _ in loop.steps)
    print(f"\nalarm from the {loop.source} ({len(loop.early)} before the change): change at "
          f"{rep['change_s'] - change:+.3f} s from the true change; timings {rep['timings']}; "
          f"validation RMS before {rep['error_before']} after {rep['error_after']}; "
          f"live ratio {rep['live_ratio']}; "
          f"refit {refit.get('refit_seconds', 0):.1f} s")


def test_unverifiable_push_is_rolled_back(procs, rclpy_context, tmp_path):
    """The live residual stops right after the push: the push cannot be verified and the
    parameters read from the model node before the push are restored (``M``/``D`` not set
    before: set back to empty, i.e. the parameter set's own values)."""
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.25)
    rep, change = _episode(procs, loop, tmp_path, ["none", "coulomb", "coulomb"], repeat=4,
                           timeout=EPISODE_S, stop_when_watching=True)
    _check_report(rep, change, tmp_path)
    assert rep["outcome"] == "rolled_back", (rep["outcome"], rep["reason"])
    assert rep["pushed"] and rep["rolled_back"] and "cannot verify" in rep["reason"]
    value = _get(loop.listener, "dvt_model", ["M", "D", "effects"])
    assert list(value[0].double_array_value) == [] and list(value[1].double_array_value) == []
    assert value[2].string_value in ("", "[]"), value[2].string_value
    states = [v.get("state") for _, _, v in loop.steps]
    assert "rolling_back" in states and any(lvl == 1 and "rolled_back" in m
                                            for lvl, m, _ in loop.steps), loop.steps[-3:]
    print(f"\nunverifiable push: timings {rep['timings']}; refit "
          f"{rep['refit'].get('refit_seconds', 0):.1f} s")


def test_false_alarm_on_a_good_model_is_not_pushed(procs, rclpy_context, tmp_path):
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.25)
    rep, change = _episode(procs, loop, tmp_path, ["none", "none"], repeat=3, timeout=EPISODE_S)
    _check_report(rep, change, tmp_path)
    assert rep["outcome"] == "not_better", (rep["outcome"], rep["reason"])
    assert not rep["pushed"] and not rep["rolled_back"]
    assert rep["test"]["relative_gain"] < 0.25, rep["test"]
    assert rep["alarms"] == [json.loads(_alarm(change).to_json())], rep["alarms"]
    loop.spin_until(lambda: any(v.get("bad_alarms") == "3" for _, _, v in loop.steps), 5.0,
                    "the count of refused alarms on /diagnostics")
    value = _get(loop.listener, "dvt_model", ["M", "effects"])
    assert list(value[0].double_array_value) == [] and value[1].string_value in ("", "[]")
    assert any("not_better" in m for _, m, _ in loop.steps)
    print(f"\nfalse alarm: test {rep['test']}; timings {rep['timings']}")


def test_crashed_refit_is_the_episodes_outcome_and_the_node_lives_on(procs, rclpy_context,
                                                                     tmp_path):
    """The refit runs in a process of its own: killed (SIGKILL, as the OOM killer would) while
    it fits, the episode ends with the outcome ``refit_crashed`` naming the signal, the
    identifier keeps running and warms a new refit process up for the next episode."""
    loop = _Loop(rclpy_context)
    ident = _start(procs, tmp_path, min_gain=0.25)
    killed: list[int] = []
    stop = threading.Event()

    def kill_the_refit() -> None:  # the refit's pid, from the identifier's own log line
        pattern = re.compile(r"handed to the refit process \(pid (\d+)\)")
        while not stop.is_set() and not killed:
            m = pattern.search(procs.log(ident))
            if m:
                killed.append(int(m.group(1)))
                os.kill(killed[0], signal.SIGKILL)
            time.sleep(0.02)

    killer = threading.Thread(target=kill_the_refit, daemon=True)
    killer.start()
    try:
        rep, _ = _episode(procs, loop, tmp_path, ["none", "coulomb", "coulomb"], repeat=4,
                          timeout=EPISODE_S)
    finally:
        stop.set()
        killer.join(timeout=5.0)
    assert killed, "the identifier never handed a refit to its process"
    assert rep["outcome"] == "refit_crashed", (rep["outcome"], rep["reason"])
    assert "SIGKILL" in rep["reason"] and f"pid {killed[0]}" in rep["reason"], rep["reason"]
    assert not rep["pushed"] and not rep["rolled_back"]
    assert ident.poll() is None, procs.log(ident)[-3000:]
    # the step is its own /diagnostics message, published with the report: it may arrive
    # after the report, so spin for it (bounded)
    loop.spin_until(lambda: any(lvl == 2 and "refit_crashed" in m for lvl, m, _ in loop.steps),
                    10.0, "the refit_crashed step (ERROR) on /diagnostics")
    # a new refit process, warm for the next episode, and the killed one reaped
    loop.spin_until(lambda: any(v.get("refit_processes_started") == "2"
                                and v.get("refit_crashes") == "1" for _, _, v in loop.steps),
                    10.0, "the new refit process on /diagnostics")
    assert not Path(f"/proc/{killed[0]}").exists(), "the killed refit process was not reaped"
    print(f"\nrefit process {killed[0]} killed: {rep['reason']}")
