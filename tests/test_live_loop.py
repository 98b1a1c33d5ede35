"""Topic level: the self-closing loop (``docs/loop.md``) with real processes.

A recording of the simulated plant (offline runner through the driver's supervisor) holds a
clean run followed by runs of the same plant with the ``coulomb`` hidden preset, stamped in host
time from just before the replay (the rolling recorder selects its windows by host time). It is
replayed at rate 1 into the model node (``physical`` prior, the plant's own parameters), a
``dvt-recorder`` in rolling mode and ``dvt_identify_node`` with the supervisor enabled.

The change alarm is published by the test, as the model node would publish it
(``dvt_model.detect.Alarm.to_json()`` on ``/dvt/model/change``) when the residual passes the
change: the model node's detector is not wired yet, and it could not alarm here anyway (its
reference window is 20 s, the clean part 15 s). The model node runs with
``detector.enabled:=false`` so that only the test's alarm counts once it is wired.

Case 1: alarm -> wait -> snapshot -> refit (finds the Coulomb friction) -> better on the held-out
slice -> push -> watch -> confirmed; every step on ``/diagnostics``, the episode report written
and published. Case 2: a false alarm on a clean recording with the plant's own model in use:
the refit is not better by the required margin and is not pushed (the model node's parameters
stay as they were). A push that then makes the live residual worse is rolled back: unit tests
(``src/dvt_identify/test/test_supervisor.py``).
"""

from __future__ import annotations

import json
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
from dvt_driver.run.experiment_core import build
from dvt_model import rosutil
from dvt_model.contract import CHANGE_QOS, IDENTIFY_EPISODE, MODEL_CHANGE
from dvt_model.detect import Alarm
from dvt_model.params import load_parameters
from dvt_model.recording import write_run

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SHORT = {"neutral_prbs": 2.5, "neutral_multisine": 2.0, "steps_dwell": 0.6, "shift": 0.5,
         "excite": 1.2}
"""A shortened ``ident`` experiment (about 14.7 s at 1 kHz), as tests/test_false_effects.py."""
LEAD_S = 1.5
"""Stamps start this long after the bag is written (the replay's start-up)."""
SUPERVISOR = {"min_post_change_s": 16.0, "settle_s": 1.0, "validation_s": 5.0,
              "watch_s": 8.0, "watch_settle_s": 1.0, "baseline_s": 8.0,
              "min_watch_samples": 1000, "fit_timeout_s": 90.0, "push_timeout_s": 40.0}


def _runs(hidden: list[str], repeat: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Speeds, currents of the runs back to back (1 kHz), the changed runs (those after the
    clean ones) repeated ``repeat`` times (the replay is stopped when the episode ends: the
    data outlast a slow refit on a loaded machine), and the length of the clean part [s]."""
    runs = [run_offline(build("ident", seed=i + 1, **SHORT), load_parameters("physical"),
                        load_hidden(h), seed=100 + i) for i, h in enumerate(hidden)]
    dt = float(runs[0].t[1] - runs[0].t[0])
    clean = hidden.index("coulomb") if "coulomb" in hidden else 1
    order = [*runs[:clean], *(runs[clean:] * repeat)]
    return (np.concatenate([r.speeds for r in order]),
            np.concatenate([r.currents for r in order]),
            sum(len(r.t) for r in runs[:clean]) * dt)


def _write_now(path: Path, speeds: np.ndarray, currents: np.ndarray) -> float:
    """Write the bag stamped in host time from ``now + LEAD_S``; returns the first stamp [s]."""
    start_ns = time.time_ns() + int(LEAD_S * 1e9)
    stamps = start_ns + np.arange(len(speeds), dtype=np.int64) * 1_000_000
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


def _start(procs: Any, tmp: Path, min_gain: float, detector: bool = False) -> None:
    procs.start("dvt_model_node", "--ros-args", "-p", "params:=physical",
                "-p", f"detector.enabled:={'true' if detector else 'false'}")
    procs.start("dvt-recorder", "--ros-args", "-p", f"output:={tmp / 'ring'}",
                "-p", "ring_minutes:=2.0", "-p", "ring_segment_seconds:=2.0",
                "-p", "snapshot_margin_s:=3.0")
    args = ["-p", "supervisor.enabled:=true", "-p", f"output_dir:={tmp / 'out'}",
            "-p", f"supervisor.min_relative_gain:={min_gain}"]
    for k, v in SUPERVISOR.items():
        args += ["-p", f"supervisor.{k}:={v}"]
    procs.start("dvt_identify_node", "--ros-args", *args)


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
        lst.spin_until(lambda: loop.alarms, change - time.time() + 15.0,
                       "the model node's change alarm")
        assert not [a for a in loop.alarms if a["change_s"] < change - 1.0], loop.alarms
    else:
        # the stamps follow the host clock (replay at rate 1 from about their start)
        lst.spin_until(lambda: time.time() > change + 1.5, 60.0, "the replay past the change")
        assert replay.poll() is None, procs.log(replay)
        _publish_alarm(loop, change)
    if stop_when_watching:
        lst.spin_until(lambda: any(v.get("state") == "watching" for _, _, v in loop.steps),
                       timeout, "the watch")
        procs.stop(replay)
    lst.spin_until(lambda: loop.episodes, timeout, "the episode report")
    procs.stop(replay)
    return loop.episodes[-1], change


def _publish_alarm(loop: _Loop, change: float) -> None:
    """The alarm as the model node would publish it (and three malformed ones first)."""
    alarm = Alarm(stamp_s=change + 1.5, change_s=change, output=1, name="carrier3",
                  direction=1, statistic=150.0, threshold=110.0, samples=1500, shift=0.05,
                  shift_sigma=1.0, level=0.0, sigma=0.05)
    for bad in ("not json", json.dumps({"change_s": "soon", "stamp_s": 1.0}), "[1, 2]"):
        loop.alarm.publish(String(data=bad))  # refused with a warning, never a crash
    loop.alarm.publish(String(data=alarm.to_json()))


def _check_report(rep: dict[str, Any], change: float, tmp: Path, tol: float = 1e-6,
                  output: str = "carrier3") -> None:
    for key in ("episode", "change_s", "detected_s", "outputs", "alarms", "estimation",
                "validation", "refit", "error_before", "error_after", "test", "pushed",
                "rolled_back", "outcome", "reason", "timings", "steps"):
        assert key in rep, key
    assert abs(rep["change_s"] - change) <= tol and output in rep["outputs"], rep["outputs"]
    est, val = rep["estimation"], rep["validation"]
    assert est[0] == pytest.approx(rep["change_s"] + 1.0) and est[1] == pytest.approx(val[0])
    assert val[1] - val[0] == pytest.approx(5.0)
    assert rep["refit"]["samples"]["estimation"] > 9000, rep["refit"]
    written = json.loads((tmp / "out" / "episodes" / "episode-1.json").read_text())
    assert written["outcome"] == rep["outcome"]
    md = (tmp / "out" / "episodes" / "episode-1.md").read_text()
    assert md.startswith(f"# Episode 1: {rep['outcome']}")


def test_detected_change_is_refitted_pushed_and_confirmed(procs, rclpy_context, tmp_path):
    """The model node's detector (default settings: 20 s reference window, so two clean runs)
    raises the alarm; the identifier does the rest."""
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.1, detector=True)
    rep, change = _episode(procs, loop, tmp_path, ["none", "none", "coulomb", "coulomb"],
                           repeat=4, timeout=100.0, detector=True)
    # the detector's estimate of the change time: within 2 s of the true one
    _check_report(rep, change, tmp_path, tol=2.0, output="")
    assert rep["outcome"] == "confirmed", (rep["outcome"], rep["reason"])
    assert rep["pushed"] and not rep["rolled_back"]
    refit = rep["refit"]
    assert "coulomb_friction@carrier3" in refit["accepted"], refit
    assert any(c["parameter"] == "effects" and "coulomb" in c["after"]
               for c in refit["changed"]), refit["changed"]
    # the held-out slice: the new model far better than the one in use (the Coulomb terms)
    assert rep["error_after"]["carrier3"] < 0.5 * rep["error_before"]["carrier3"], rep
    assert rep["test"]["p_value"] < 0.05
    assert max(rep["live_ratio"].values()) < 1.0, rep["live_ratio"]
    # the model node runs the refitted model
    effects = json.loads(_get(loop.listener, "dvt_model", ["effects"])[0].string_value)
    assert [t["kind"] for t in effects].count("coulomb") >= 1, effects
    states = [v.get("state") for _, _, v in loop.steps]
    for state in ("waiting", "refitting", "pushing", "watching", "idle"):
        assert state in states, (state, [m for _, m, _ in loop.steps])
    assert any("confirmed" in m for _, m, _ in loop.steps)
    print(f"\nepisode: timings {rep['timings']}; validation RMS before {rep['error_before']} "
          f"after {rep['error_after']}; live ratio {rep['live_ratio']}; "
          f"refit {refit.get('refit_seconds', 0):.1f} s")


def test_unverifiable_push_is_rolled_back(procs, rclpy_context, tmp_path):
    """The live residual stops right after the push: the push cannot be verified and the
    parameters read from the model node before the push are restored (``M``/``D`` not set
    before: set back to empty, i.e. the parameter set's own values)."""
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.1)
    rep, change = _episode(procs, loop, tmp_path, ["none", "coulomb", "coulomb"], repeat=4,
                           timeout=100.0, stop_when_watching=True)
    _check_report(rep, change, tmp_path)
    assert rep["outcome"] == "rolled_back", (rep["outcome"], rep["reason"])
    assert rep["pushed"] and rep["rolled_back"] and "cannot verify" in rep["reason"]
    value = _get(loop.listener, "dvt_model", ["M", "D", "effects"])
    assert list(value[0].double_array_value) == [] and list(value[1].double_array_value) == []
    assert value[2].string_value in ("", "[]"), value[2].string_value
    states = [v.get("state") for _, _, v in loop.steps]
    assert "rolling_back" in states and any(lvl == 1 and "rolled_back" in m
                                            for lvl, m, _ in loop.steps), loop.steps[-3:]


def test_false_alarm_on_a_good_model_is_not_pushed(procs, rclpy_context, tmp_path):
    loop = _Loop(rclpy_context)
    _start(procs, tmp_path, min_gain=0.1)
    rep, change = _episode(procs, loop, tmp_path, ["none", "none"], repeat=3, timeout=80.0)
    _check_report(rep, change, tmp_path)
    assert rep["outcome"] == "not_better", (rep["outcome"], rep["reason"])
    assert not rep["pushed"] and not rep["rolled_back"]
    assert rep["test"]["relative_gain"] < 0.1, rep["test"]
    assert rep["alarms"] == [json.loads(rep["alarms"][0] and json.dumps(rep["alarms"][0]))]
    loop.spin_until(lambda: any(v.get("bad_alarms") == "3" for _, _, v in loop.steps), 5.0,
                    "the count of refused alarms on /diagnostics")
    value = _get(loop.listener, "dvt_model", ["M", "effects"])
    assert list(value[0].double_array_value) == [] and value[1].string_value in ("", "[]")
    assert any("not_better" in m for _, m, _ in loop.steps)
    print(f"\nfalse alarm: test {rep['test']}; timings {rep['timings']}")
