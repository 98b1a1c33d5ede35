"""The refit's own process (:mod:`dvt_identify.refit_process`): real child processes, real
snapshot bags; answers, niceness, a crash reported as the outcome, cancel and reaping, and the
child's death with its parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify.errors import SupervisorError
from dvt_identify.refit import RefitSettings
from dvt_identify.refit_process import RefitWorker, outcome_from_dict, outcome_to_dict
from dvt_identify.supervisor import FitOutcome, RequestFit
from dvt_model.recording import write_run

T0 = 1_700_000_000


def _until(pred: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def _gone(pid: int) -> bool:
    """The process no longer exists (reaped; a zombie still counts as there)."""
    return not Path(f"/proc/{pid}").exists()


def _dead(pid: int) -> bool:
    """The process no longer runs (gone, or a zombie its new parent has not reaped yet)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.fixture
def snapshot(tmp_path: Path) -> Path:
    n = 3000
    stamps = T0 * 10**9 + np.arange(n, dtype=np.int64) * 1_000_000
    return write_run(tmp_path / "snap", stamps, np.zeros((n, 2)), np.zeros((n, 4)))


@pytest.fixture
def worker(tmp_path: Path) -> Iterator[RefitWorker]:
    w = RefitWorker(tmp_path / "refit-process.log", nice=0)  # prompt on a busy machine
    yield w
    w.close()


# a window of the snapshot without samples: the refit answers at once with an error
EMPTY = RequestFit(1, (T0 + 10.0, T0 + 20.0), (T0 + 20.0, T0 + 25.0), ("sun_shaft",))


def test_outcome_survives_the_pipe() -> None:
    out = FitOutcome(new_errors=np.arange(6.0).reshape(3, 2), current_errors=np.ones((3, 2)),
                     new_parameters={"M": [1.0, 0.0, 0.0, 2.0]},
                     current_parameters={"M": None}, summary={"accepted": ["x"], "n": 3},
                     error="", crashed=False)
    back = outcome_from_dict(outcome_to_dict(out))
    np.testing.assert_array_equal(np.asarray(back.new_errors), np.asarray(out.new_errors))
    assert back.new_parameters == out.new_parameters and back.summary == out.summary
    assert back.current_parameters == {"M": None} and not back.crashed
    with pytest.raises(SupervisorError, match="not a fit outcome"):
        outcome_from_dict({"new_errors": []})


def test_the_child_runs_at_the_lowest_priority_in_its_own_session(tmp_path: Path) -> None:
    worker = RefitWorker(tmp_path / "refit-process.log")  # the default: niceness 19
    try:
        worker.start()
        pid = worker.pid
        assert pid is not None and os.getpriority(os.PRIO_PROCESS, pid) == 19
        assert os.getpriority(os.PRIO_PROCESS, 0) < 19  # only the child is lowered
        assert os.getsid(pid) == pid  # a session of its own (signals reach it only from us)
        group = Path(f"/proc/{pid}/autogroup")
        if group.exists():  # its session's weight against other sessions: the same niceness
            assert group.read_text().split()[-1] == "19", group.read_text()
    finally:
        worker.close()


def test_job_answered_by_a_warm_child_which_serves_the_next_one(snapshot: Path,
                                                                tmp_path: Path) -> None:
    # niceness 0: answered promptly also on a machine busy with other jobs
    worker = RefitWorker(tmp_path / "refit-process.log", nice=0)
    try:
        worker.start()
        pid = worker.pid
        worker.submit(snapshot, EMPTY, {"params": "physical"}, tmp_path / "w1",
                      RefitSettings().to_dict())
        assert worker.busy and worker.poll() is None
        with pytest.raises(SupervisorError, match="busy"):
            worker.submit(snapshot, EMPTY, {}, tmp_path / "w2", RefitSettings().to_dict())
        out = _until(worker.poll, 60.0, "the refit's answer")
        assert not out.crashed and "0 estimation and 0 validation samples" in out.error
        assert out.summary["refit_niceness"] == 0 and out.summary["refit_cpu_seconds"] >= 0.0
        assert not worker.busy and worker.pid == pid  # the same child serves the next job
        worker.submit(tmp_path / "nope", EMPTY, {}, tmp_path / "w3", RefitSettings().to_dict())
        out2 = _until(worker.poll, 60.0, "the second answer")
        assert "nope" in out2.error and worker.started == 1
        worker.close()
        assert pid is not None and _gone(pid) and worker.pid is None
    finally:
        worker.close()


def test_crash_during_a_refit_is_its_outcome_and_the_next_job_gets_a_new_child(
        worker: RefitWorker, snapshot: Path, tmp_path: Path) -> None:
    worker.submit(snapshot, EMPTY, {}, tmp_path / "w1", RefitSettings().to_dict())
    pid = worker.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)  # as the OOM killer would, before it answers
    out = _until(worker.poll, 30.0, "the crash to be reported")
    assert out.crashed and "died during the refit" in out.error
    assert "SIGKILL" in out.error and f"pid {pid}" in out.error
    assert _gone(pid) and not worker.busy and worker.crashes == 1
    worker.submit(snapshot, EMPTY, {}, tmp_path / "w2", RefitSettings().to_dict())
    assert worker.pid not in (None, pid) and worker.started == 2
    out2 = _until(worker.poll, 60.0, "the new child's answer")
    assert not out2.crashed and "0 estimation" in out2.error


def test_cancel_kills_and_reaps_the_child(worker: RefitWorker, snapshot: Path,
                                          tmp_path: Path) -> None:
    assert not worker.cancel()  # nothing out
    worker.submit(snapshot, EMPTY, {}, tmp_path / "w1", RefitSettings().to_dict())
    pid = worker.pid
    assert pid is not None
    t0 = time.monotonic()
    assert worker.cancel()
    assert time.monotonic() - t0 < 6.0 and _gone(pid) and not worker.busy
    assert worker.poll() is None and worker.crashes == 0


def test_the_child_dies_with_its_parent(tmp_path: Path) -> None:
    code = ("import sys, time\n"
            "from dvt_identify.refit_process import RefitWorker\n"
            f"w = RefitWorker({str(tmp_path / 'log')!r}, nice=0)\n"
            "w.start()\n"
            "deadline = time.monotonic() + 120\n"
            "while not w.ready and time.monotonic() < deadline: time.sleep(0.05)\n"
            "print(w.pid if w.ready else 'not ready', flush=True)\n"
            "time.sleep(120)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                              start_new_session=True)
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())  # warm: bound to die with its parent
        parent.kill()  # SIGKILL: no clean-up of its own
        parent.wait(timeout=10)
        _until(lambda: _dead(child), 10.0, f"the child {child} to die with its parent")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(timeout=10)


def test_bad_niceness_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SupervisorError, match="-20..19"):
        RefitWorker(tmp_path / "log", nice=25)


def test_warm_up_refits_simulated_data_before_it_serves(tmp_path: Path) -> None:
    worker = RefitWorker(tmp_path / "refit-process.log", nice=0,
                         warm=RefitSettings(fit_decimate=10).to_dict())
    try:
        worker.start()
        _until(lambda: worker.ready, 180.0, "the warm-up refit")
        log = worker.log_path.read_text()
        assert "warm-up refit in" in log and "failed" not in log, log[-2000:]
    finally:
        worker.close()
