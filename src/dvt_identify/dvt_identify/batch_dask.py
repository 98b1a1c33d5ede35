"""Batch identification on Dask: the thin runner of :mod:`dvt_identify.batch`.

:func:`run_batch` runs every job (:func:`dvt_identify.batch.run_job`) as one Dask task, on a
``LocalCluster`` it starts (worker processes of one thread each, BLAS single-threaded) or on
the cluster of a running scheduler (``--scheduler ADDRESS``), the same code path; then writes
``OUT/summary.json`` and ``OUT/summary.md``. The cluster it starts and its client are closed
in every case (an error, an interrupt). docs/batch.md.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import dask
from distributed import Client, LocalCluster, as_completed, get_worker

from dvt_identify.batch import (
    MALLOC_TRIM,
    Job,
    JobOutcome,
    check_out,
    failed,
    run_job,
    summarize,
    write_summary,
)
from dvt_identify.bench_identify.common import BLAS_ENV
from dvt_identify.errors import BatchError
from dvt_identify.parallel import ENV as FORK_WORKERS

CONNECT_TIMEOUT_S = 30.0
"""Longest wait to connect to a scheduler [s]."""
WORKERS_TIMEOUT_S = 120.0
"""Longest wait for the workers: all of a local cluster's, at least one of a scheduler's [s]."""
INTERRUPTED = "interrupted before it finished"
"""The summary's error for a job still running or queued at an interrupt."""


@contextlib.contextmanager
def single_threaded_spawn() -> Iterator[None]:
    """While a local cluster is started: the BLAS thread variables at 1 in the environment
    the worker processes are spawned with (numerics on small matrices, where BLAS threads only
    add synchronisation; one job per core), and Dask's ``MALLOC_TRIM_THRESHOLD_`` not set
    (:data:`dvt_identify.batch.MALLOC_TRIM`; a user's own setting is kept). As the launcher
    does for its children (``dvt_driver.run.processes.SINGLE_THREAD_BLAS``), the BLAS setting
    overrides the user's: Dask's ``pre-spawn-environ`` takes a variable set in this process's
    environment before its own setting, so both are set; this process's values are restored
    afterwards (the nannies keep theirs for a restarted worker)."""
    saved = {k: os.environ.get(k) for k in BLAS_ENV}
    os.environ.update(dict.fromkeys(BLAS_ENV, "1"))
    spawn_env: dict[str, str | None] = {k: "1" for k in BLAS_ENV}
    spawn_env[MALLOC_TRIM] = None  # None: Dask does not set it
    try:
        with dask.config.set({f"distributed.nanny.pre-spawn-environ.{k}": v
                              for k, v in spawn_env.items()}):
            yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _on_worker(job: Job, out: str) -> JobOutcome:
    """The task: run the job here, in this process only (``DVT_IDENTIFY_WORKERS=1``: the
    identifier forks no workers of its own, :mod:`dvt_identify.parallel`; the batch's workers
    already take the cores, and a fork beside the worker's threads is unsafe), and say where
    (worker address and thread count)."""
    os.environ[FORK_WORKERS] = "1"
    w = get_worker()
    outcome = run_job(job, out)
    return replace(outcome, worker={**outcome.worker, "address": w.address,
                                    "threads": w.state.nthreads})


def run_batch(jobs: Sequence[Job], out: str | Path, *, manifest: str = "",
              scheduler: str | None = None, workers: int | None = None,
              on_done: Callable[[JobOutcome], None] | None = None,
              connect_timeout_s: float = CONNECT_TIMEOUT_S) -> dict[str, Any]:
    """Run ``jobs`` in parallel, each into ``OUT/<name>/``, and write the summary.

    Args:
        jobs: validated jobs (:func:`dvt_identify.batch.load_manifest`).
        out: the output folder ``OUT``; seen alike by the workers (a shared file system on a
            real cluster).
        manifest: the manifest's path, for the summary.
        scheduler: a running scheduler's address (``tcp://host:8786``); ``None``: start a
            ``LocalCluster`` of ``workers`` single-threaded worker processes on 127.0.0.1.
        workers: local worker processes (default: one per job, at most the CPU count).
        on_done: called with each outcome as its job ends (progress).
        connect_timeout_s: longest wait to connect to ``scheduler`` [s].

    Returns:
        The summary (:func:`dvt_identify.batch.summarize`), also written to ``OUT``. An
        interrupt (``KeyboardInterrupt``) while the jobs run closes the cluster, writes the
        summary (the jobs not finished failed, :data:`INTERRUPTED`) and is raised again.

    Raises:
        BatchError: ``OUT`` holds an earlier run, the scheduler address is malformed or cannot
            be reached, or no worker joins in time (``OUT`` is then not created). A failing job
            raises nothing: it is failed in the summary.
    """
    check_out(out, jobs)
    t0 = time.monotonic()
    with contextlib.ExitStack() as stack:
        if scheduler is None:
            n = workers if workers is not None else max(1, min(len(jobs), _cpus()))
            if n < 1:
                raise BatchError(f"--workers: expected at least 1, got {n}")
            with single_threaded_spawn():
                cluster = stack.enter_context(LocalCluster(
                    n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                    dashboard_address="127.0.0.1:0"))  # its HTTP server: any free port
            client = stack.enter_context(Client(cluster, timeout=CONNECT_TIMEOUT_S))
            address, kind, need = str(cluster.scheduler_address), "local", n
        else:
            try:
                client = stack.enter_context(Client(scheduler, timeout=connect_timeout_s))
            except ValueError as exc:
                raise BatchError(f"--scheduler {scheduler}: not a scheduler address such as "
                                 f"tcp://host:8786 ({exc})") from exc
            except (OSError, TimeoutError) as exc:
                raise BatchError(f"--scheduler {scheduler}: cannot connect in "
                                 f"{connect_timeout_s:g} s: {exc}") from exc
            address, kind, need = scheduler, "scheduler", 1
        try:
            client.wait_for_workers(need, timeout=WORKERS_TIMEOUT_S)
        except TimeoutError as exc:
            raise BatchError(f"{address}: fewer than {need} worker(s) joined in "
                             f"{WORKERS_TIMEOUT_S:g} s") from exc
        Path(out).mkdir(parents=True, exist_ok=True)
        threads = client.nthreads()
        cluster_info = {"kind": kind, "address": address, "workers": len(threads),
                        "threads": sorted(set(threads.values()))}
        batch = uuid.uuid4().hex[:8]  # keys unique also on a scheduler shared with others
        futures = {client.submit(_on_worker, job, str(out), key=f"identify-{job.name}-{batch}"
                                 ): job for job in jobs}
        outcomes: list[JobOutcome] = []
        interrupted = False
        try:
            for fut in as_completed(futures):
                job = futures[fut]
                try:
                    outcome = fut.result()
                except Exception as exc:  # the task failed (a worker died): that job only
                    outcome = failed(job, out, exc)
                outcomes.append(outcome)
                if on_done is not None:
                    on_done(outcome)
        except KeyboardInterrupt:  # Ctrl-C (SIGTERM in the CLI): summary of what finished
            interrupted = True
    # the cluster is closed here
    summary = summarize(jobs, outcomes, manifest=manifest, out=out, cluster=cluster_info,
                        wall_s=time.monotonic() - t0,
                        unfinished=INTERRUPTED if interrupted else "no outcome")
    write_summary(out, summary)
    if interrupted:
        raise KeyboardInterrupt
    return summary


def _cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
