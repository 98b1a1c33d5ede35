"""Topic-level tests of ``dvt-launch sim``: the whole chain as real processes.

plant (pty) -> driver (lifecycle, autostart) -> model node, recorder; ``dvt-experiment``
drives the driver. Checks the recording end to end and that Ctrl-C leaves no process behind.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import Procs, wait_for
from dvt_model.recording import (
    changes_applied,
    read_run,
    read_run_info,
    read_truth,
    sample_period,
)


@pytest.mark.parametrize(("args", "message"), [
    (["sim", "--experiment", "nope"], "unknown experiment 'nope'"),
    (["sim", "--experiment", "thesis", "--experiment-set", "speeds_rpm=[3000]"],
     "exceeds the limit 251.327 rad/s"),
    (["sim", "--driver-param", "baud"], "--driver-param: expected NAME:=VALUE, got 'baud'"),
    (["sim", "--rate", "0"], "--rate: expected 0 < HZ <= 2000, got 0.0"),
    (["hw"], "the following arguments are required: --port"),
    (["sim", "--ring-minutes", "0"], "--ring-minutes: expected 0 < M <= 1440, got 0.0"),
    (["sim", "--ring-dir", "/tmp/x"], "--ring-dir needs --ring-minutes"),
    (["sim", "--ring-minutes", "1", "--ring-segment-seconds", "90"],
     "--ring-segment-seconds: expected 0 < S <= ring minutes * 60, got 90.0"),
    (["sim", "--change-at", "soon:coulomb"], "--change-at: expected T:SPEC"),
    (["sim", "--change-at", "5:nope"], "unknown hidden-effects preset 'nope'"),
])
def test_launch_refuses_bad_arguments(args: list[str], message: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    from dvt_driver.system.launch_args import parse_args

    with pytest.raises(SystemExit) as exc:
        parse_args(args)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_launch_refuses_an_existing_recording(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    from dvt_driver.system.launch_args import parse_args

    with pytest.raises(SystemExit):
        parse_args(["sim", "--record", str(tmp_path)])
    assert "already exists (a recording never overwrites)" in capsys.readouterr().err


def _pids(log: str) -> dict[str, int]:
    """Child pids from the launcher's ``started NAME (pid N)`` lines."""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"started (\w+) \(pid (\d+)\)", log)}


def _gone(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state == "Z"


@pytest.mark.ros
def test_launch_records_an_experiment_end_to_end(procs: Procs, tmp_path: Path) -> None:
    bag = tmp_path / "run"
    launcher = procs.start("dvt-launch", "sim", "--hidden", "coulomb", "--seed", "4",
                           "--record", str(bag), "--experiment", "smoke",
                           "--log-dir", str(tmp_path / "logs"))
    try:
        rc = launcher.wait(timeout=80)
    except subprocess.TimeoutExpired:
        pytest.fail("dvt-launch did not finish within 80 s:\n" + procs.log(launcher)[-3000:])
    log = procs.log(launcher)
    assert rc == 0, log[-3000:]
    # every child was stopped by the launcher and none is left
    pids = _pids(log)
    assert set(pids) == {"plant", "driver", "model", "recorder", "experiment"}
    for name, pid in pids.items():
        assert _gone(pid), f"{name} (pid {pid}) still running"

    run = read_run(bag)  # contract checks: names, finite values, strictly increasing stamps
    assert np.all(np.diff(run.stamps_ns) > 0)
    assert sample_period(run) == pytest.approx(1e-3, rel=0.01)  # ~1 kHz controller samples
    assert run.duration >= 5.0  # the whole 5 s experiment (plus start and stop)
    # the recording spans the 5 s experiment: at least 90 % of its 5000 samples are there
    # (the stamp-based count is not used: under load the driver's stamp mapping slews)
    assert run.n >= 4500, (run.n, run.duration)
    assert run.unmatched <= 0.01 * run.n
    for topic in ("/dvt/model/residual", "/dvt/cmd/motor_current", "/dvt/cmd/gear",
                  "/diagnostics"):
        assert topic in run.topics
    # the experiment really drove the plant: band 1 applied, motor current reversed
    assert run.currents[:, 1].max() > 0.3  # gear 1 holds its band at 0.5 A
    assert run.currents[:, 0].min() < -1.0 and run.currents[:, 0].max() > 1.0
    truth = read_truth(bag)
    assert truth is not None and truth["effects"] == ["coulomb_friction"]
    assert truth["plant"]["seed"] == 4 and truth["plant"]["sample_period_us"] == 1000
    made = read_run_info(bag)
    assert made is not None
    assert made["experiment"]["name"] == "smoke" and made["experiment_status"] == 0
    assert made["hidden"] == "coulomb"
    # the bag holds the whole experiment: its first command (t = 0) comes after the first
    # sample and its end before the last one
    assert made["check"]["experiment_inside"] is True
    start = made["experiment_start_ns"]
    assert run.stamps_ns[0] <= start <= start + 5_000_000_000 <= run.stamps_ns[-1]


@pytest.mark.ros
def test_sigint_mid_run_stops_every_child_and_closes_the_bag(procs: Procs,
                                                              tmp_path: Path) -> None:
    bag = tmp_path / "run"
    launcher = procs.start("dvt-launch", "sim", "--record", str(bag), "--experiment", "ident",
                           "--log-dir", str(tmp_path / "logs"))
    wait_for(lambda: "running experiment ident" in procs.log(launcher), 60,
             "the launcher to start the experiment")
    pids = _pids(procs.log(launcher))
    assert set(pids) == {"plant", "driver", "model", "recorder", "experiment"}
    wait_for(lambda: "phase neutral-prbs" in (tmp_path / "logs" / "experiment.log").read_text(),
             30, "the experiment to start")
    time.sleep(1.0)
    t0 = time.monotonic()
    os.kill(launcher.pid, signal.SIGINT)  # Ctrl-C reaches the launcher only (own session)
    try:
        rc = launcher.wait(timeout=45)
    except subprocess.TimeoutExpired:
        pytest.fail("dvt-launch did not exit within 45 s of SIGINT:\n"
                    + procs.log(launcher)[-3000:])
    log = procs.log(launcher)
    assert rc == 130, log[-3000:]
    assert time.monotonic() - t0 < 45
    for name, pid in pids.items():
        assert _gone(pid), f"{name} (pid {pid}) survived the launcher"
    assert "killed" not in log  # every child exited on SIGINT, none needed SIGKILL
    # the recorder closed the bag cleanly: readable, and the experiment stopped the motor
    run = read_run(bag)
    assert run.n > 500
    assert (bag / "truth.yaml").exists()
    exp_log = (tmp_path / "logs" / "experiment.log").read_text()
    assert "interrupted: stopping the motor" in exp_log and "motor stopped" in exp_log


@pytest.mark.ros
def test_launch_with_a_plant_change_and_a_ring(procs: Procs, tmp_path: Path) -> None:
    """``--change-at`` reaches the plant (its truth, copied into the bag, holds the change with
    its times) and ``--ring-minutes`` starts a rolling recorder beside the normal one."""
    bag, ring = tmp_path / "run", tmp_path / "ring"
    launcher = procs.start("dvt-launch", "sim", "--seed", "2", "--change-at", "3:coulomb",
                           "--record", str(bag), "--ring-minutes", "1",
                           "--ring-segment-seconds", "2", "--ring-dir", str(ring),
                           "--duration", "8", "--log-dir", str(tmp_path / "logs"))
    try:
        rc = launcher.wait(timeout=80)
    except subprocess.TimeoutExpired:
        pytest.fail("dvt-launch did not finish within 80 s:\n" + procs.log(launcher)[-3000:])
    log = procs.log(launcher)
    assert rc == 0, log[-3000:]
    pids = _pids(log)
    assert set(pids) == {"plant", "driver", "model", "recorder", "ring"}
    for name, pid in pids.items():
        assert _gone(pid), f"{name} (pid {pid}) still running"
    (applied,) = changes_applied(read_truth(bag))
    assert applied["at_s"] == pytest.approx(3.0, abs=0.002)
    assert applied["change"]["coulomb"] == {"sun": 0.05, "carrier3": 0.2}
    assert applied["unix_s"] > 1.6e9
    assert (read_run_info(bag) or {}).get("plant_changes") == ["3:coulomb"]
    segments = sorted(ring.glob("seg-*"))
    assert len(segments) >= 2, list(ring.iterdir())
    ring_log = (tmp_path / "logs" / "ring.log").read_text()
    assert "rolling" in ring_log, ring_log[-2000:]
