"""Independent pieces on both cores (:mod:`dvt_identify.parallel`): forked workers give the
serial loop's results in its order, hand exceptions back, and never fork again."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dvt_identify import parallel
from dvt_identify.errors import FitError
from dvt_identify.parallel import fork_map, workers


def test_results_come_back_in_order_from_both_processes() -> None:
    parent = os.getpid()
    out = fork_map(lambda k: (k, os.getpid(), np.arange(k)), range(7), 2)
    assert [k for k, _, _ in out] == list(range(7))
    assert all(np.array_equal(a, np.arange(k)) for k, _, a in out)
    pids = {pid for _, pid, _ in out}
    assert parent in pids and len(pids) == 2  # one share here, the other in a child


def test_with_costs_the_items_go_costliest_first_to_whoever_is_free() -> None:
    """One slow item among quick ones: taken first, by one process, while the other takes
    every quick one (round robin would put half of them behind it); results in item order."""
    import time

    costs = [1.0, 1.0, 1.0, 10.0, 1.0, 1.0, 1.0, 1.0]

    def fn(k: int) -> tuple[int, int]:
        time.sleep(1.0 if k == 3 else 0.01)
        return k, os.getpid()
    out = fork_map(fn, range(8), 2, costs=costs)
    assert [k for k, _ in out] == list(range(8))
    heavy = out[3][1]
    assert all(pid != heavy for k, pid in out if k != 3), out
    with pytest.raises(ValueError, match="costs: expected 8 values, got 2"):
        fork_map(lambda k: k, range(8), 2, costs=[1.0, 2.0])
    # an exception is still raised first in item order
    def bad(k: int) -> int:
        if k in (2, 5):
            raise RuntimeError(f"item {k}")
        return k
    with pytest.raises(RuntimeError, match="item 2"):
        fork_map(bad, range(8), 2, costs=costs)


def test_an_exception_in_a_worker_is_raised_here_first_in_order() -> None:
    def fn(k: int) -> int:
        if k in (3, 4):
            raise ValueError(f"item {k} failed")
        return k
    with pytest.raises(ValueError, match="item 3 failed"):
        fork_map(fn, range(6), 2)


def test_one_worker_runs_here_and_a_worker_does_not_fork(monkeypatch) -> None:
    parent = os.getpid()
    monkeypatch.setenv(parallel.ENV, "1")
    assert workers() == 1
    assert {pid for pid in fork_map(lambda _k: os.getpid(), range(4))} == {parent}
    monkeypatch.setenv(parallel.ENV, "2")
    nested = fork_map(lambda _k: (parallel.workers(),
                                  len({p for p in fork_map(lambda _j: os.getpid(), range(4))})),
                      range(2))
    assert nested[1] == (1, 1)  # in the child: serial, one process


@pytest.mark.parametrize("bad", ["0", "two", "-1"])
def test_a_bad_worker_count_is_refused_naming_it(monkeypatch, bad: str) -> None:
    monkeypatch.setenv(parallel.ENV, bad)
    with pytest.raises(FitError, match=f"{parallel.ENV}.*{bad}"):
        workers()


def test_a_process_with_other_threads_runs_serially() -> None:
    """A ROS node's process has its executor and worker threads: a fork there could inherit a
    lock another thread holds, so :func:`workers` says 1 while another thread runs. Run in a
    fresh interpreter: a test process may hold threads of earlier tests (a Dask client's)."""
    code = textwrap.dedent("""
        import os, threading
        from dvt_identify.parallel import fork_map, workers
        before = workers()
        stop = threading.Event()
        t = threading.Thread(target=stop.wait, daemon=True)
        t.start()
        during = workers(), len({p for p in fork_map(lambda _k: os.getpid(), range(4))})
        stop.set()
        t.join(5)
        print(before, *during, workers())
        """)
    env = {**os.environ, parallel.ENV: "2"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, env=env).stdout.split()
    assert out == ["2", "1", "1", "2"]  # two workers, then serial while the thread runs
