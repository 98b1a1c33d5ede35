"""Batch identification (dvt_identify.batch, batch_dask, dvt-identify-batch): the manifest
checked before anything runs, one job's run and the summary (pure, in process), then real
jobs on a real Dask LocalCluster of two single-threaded worker processes (one job fails: a
missing bag), and the console script on the workers of a running scheduler."""

from __future__ import annotations

import contextlib
import gc
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import yaml

from dvt_identify.batch import (
    FAILED,
    JOB_LOG,
    OK,
    Job,
    check_out,
    load_manifest,
    parse_manifest,
    run_job,
    summarize,
    summary_markdown,
    worker_warnings,
    write_summary,
)
from dvt_identify.data import JointStateSeries, Segment, write_jointstate_bag
from dvt_identify.description import Description
from dvt_identify.errors import BatchError

EXE = Path(sys.executable).parent / "dvt-identify-batch"


def _write(path: Path, seg: Segment) -> Path:
    stamps = (10**9 + np.round(seg.t * 1e9)).astype(np.int64)
    return write_jointstate_bag(path, {
        "/cart/joint_states": JointStateSeries(stamps, ("cart",), velocity=seg.y[:, :1]),
        "/cart/drive": JointStateSeries(stamps, ("cart",), effort=seg.u[:, :1]),
    })


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory, cart_spec: Callable[..., dict[str, Any]],
        cart_desc: Callable[..., Description], cart_record: Callable[..., Segment]) -> Path:
    """A lab folder: the cart's description ``cart.yaml`` and four recordings ``r1..r4`` of
    the cart read with a 0.3 m/s sensor offset (the effect every job should accept)."""
    d = tmp_path_factory.mktemp("lab")
    (d / "cart.yaml").write_text(yaml.safe_dump(cart_spec()))
    desc = cart_desc()
    for k in range(1, 5):
        _write(d / f"r{k}", cart_record(desc, f"r{k}", seed=k, offset=0.3))
    return d


def manifest(lab: Path, jobs: list[dict[str, Any]], name: str = "m.yaml",
             defaults: dict[str, Any] | None = None) -> Path:
    data: dict[str, Any] = {"defaults": {"description": "cart.yaml", "plots": False,
                                         **(defaults or {})}, "jobs": jobs}
    path = lab / name
    path.write_text(json.dumps(data) if name.endswith(".json") else yaml.safe_dump(data))
    return path


OK_JOBS = [
    {"name": "joint1", "estimation_bags": ["r1"], "validation_bags": ["r2"],
     "test_bags": ["r3"]},
    {"name": "joint2", "estimation_bags": ["r2"], "validation_bags": ["r1"]},
    {"name": "joint3-holdout", "estimation_bags": ["r4"], "select_on": "holdout"},
]
MISSING = {"name": "lost", "estimation_bags": ["nope"], "validation_bags": ["r1"]}


def children() -> list[psutil.Process]:
    """This process's children but multiprocessing's resource tracker (which lives as long as
    this interpreter, whatever was started)."""
    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if "multiprocessing.resource_tracker" not in " ".join(p.cmdline()):
                out.append(p)
        except psutil.NoSuchProcess:
            continue
    return out


@pytest.fixture
def no_leftover() -> Iterator[None]:
    """The test leaves no process behind that it started (workers, nannies)."""
    before = {p.pid for p in children()}
    yield
    left = [p for p in children() if p.pid not in before]
    for p in left:  # stop them, then fail
        p.kill()
    assert not left, f"processes outlived the test: {[p.cmdline() for p in left]}"


# ------------------------------------------------------------------------- manifest, pure
def test_manifest_jobs_defaults_and_paths(lab: Path) -> None:
    path = manifest(lab, [*OK_JOBS, {"name": "bundled", "description": "dvt",
                                     "estimation_bags": ["/abs/a", "/abs/b"], "select_on": "cv",
                                     "init_window": 20, "plots": True}])
    jobs = load_manifest(path)
    assert [j.name for j in jobs] == ["joint1", "joint2", "joint3-holdout", "bundled"]
    j1 = jobs[0]
    assert j1 == Job(name="joint1", estimation_bags=(str(lab / "r1"),),
                     validation_bags=(str(lab / "r2"),), test_bags=(str(lab / "r3"),),
                     description=str(lab / "cart.yaml"), select_on="validation",
                     init_window=0, plots=False)
    assert jobs[2].validation_bags == () and jobs[2].select_on == "holdout"
    assert jobs[3] == Job(name="bundled", estimation_bags=("/abs/a", "/abs/b"), description="dvt",
                          select_on="cv", init_window=20, plots=True)
    # JSON reads the same
    assert load_manifest(manifest(lab, [*OK_JOBS], name="m.json")) == jobs[:3]


@pytest.mark.parametrize(("entry", "field", "message"), [
    ({"estimation_bags": ["r1"], "validation_bags": ["r2"]}, "name", "got None"),
    ({"name": "../up", "estimation_bags": ["r1"], "validation_bags": ["r2"]}, "name",
     "got '../up'"),
    ({"name": "summary.md", "estimation_bags": ["r1"], "validation_bags": ["r2"]}, "name",
     "the batch summary's file name"),
    ({"name": "j", "validation_bags": ["r2"]}, "estimation_bags",
     "expected a non-empty list of bag paths, got []"),
    ({"name": "j", "estimation_bags": "r1", "validation_bags": ["r2"]}, "estimation_bags",
     "expected a non-empty list of bag paths, got 'r1'"),
    ({"name": "j", "estimation_bags": ["r1"]}, "validation_bags",
     "expected a non-empty list of bag paths (select_on is validation), got []"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "test_bags": [3]},
     "test_bags", "expected a list of bag paths, got [3]"),
    ({"name": "j", "estimation_bags": ["r1"], "select_on": "bic"}, "select_on",
     "expected one of validation, holdout, cv, got 'bic'"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["./r1"]}, "validation_bags",
     "r1 is also in estimation_bags"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "test_bags": ["r2"]},
     "test_bags", "r2 is also in validation_bags"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "init_window": -1},
     "init_window", "expected a whole number of samples >= 0, got -1"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "init_window": True},
     "init_window", "got True"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "plots": "yes"},
     "plots", "expected true or false, got 'yes'"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"],
      "description": "nosuch.yaml"}, "description", "no such file"),
    ({"name": "j", "estimation_bags": ["r1"], "validation_bags": ["r2"], "augment": False},
     "unknown key(s) ['augment']", "expected name, description"),
])
def test_manifest_error_names_file_entry_and_field(lab: Path, entry: dict[str, Any],
                                                   field: str, message: str) -> None:
    path = manifest(lab, [OK_JOBS[0], entry])
    with pytest.raises(BatchError) as exc:
        load_manifest(path)
    text = str(exc.value)
    assert len(text.splitlines()) == 1, text
    name = entry.get("name")
    where = f"{path}: jobs[1]" + (f" ({name})" if name else "")
    assert text.startswith(f"{where}: {field}"), text
    assert message in text, text


def test_manifest_every_problem_at_once(lab: Path) -> None:
    path = lab / "bad.yaml"
    path.write_text(yaml.safe_dump({
        "defaults": {"name": "x", "descripton": "dvt"},
        "jobs": [OK_JOBS[0], {"name": "joint1", "estimation_bags": ["r3"],
                              "validation_bags": ["r4"]}, "joint5"]}))
    with pytest.raises(BatchError) as exc:
        load_manifest(path)
    assert str(exc.value).splitlines() == [
        f"{path}: defaults: unknown key(s) ['descripton', 'name'] (expected description, "
        "estimation_bags, validation_bags, test_bags, select_on, init_window, plots)",
        f"{path}: jobs[1] (joint1): name: 'joint1' already names jobs[0]",
        f"{path}: jobs[2]: expected a mapping, got 'joint5'"]


def test_a_bad_default_is_named_in_each_job(lab: Path) -> None:
    path = manifest(lab, OK_JOBS[:2], defaults={"init_window": "20"})
    with pytest.raises(BatchError) as exc:
        load_manifest(path)
    assert str(exc.value).splitlines() == [
        f"{path}: jobs[{i}] ({j['name']}): init_window (from defaults): expected a whole "
        "number of samples >= 0, got '20'" for i, j in enumerate(OK_JOBS[:2])]


@pytest.mark.parametrize(("text", "message"), [
    ("jobs: [", "not valid YAML"),
    ("- name: a", "expected a mapping with 'jobs' (a list of jobs), got list"),
    ("jobs: []", "jobs: expected a non-empty list of jobs, got []"),
    ("jobs: [{name: a, estimation_bags: [r1], validation_bags: [r2]}]\nthreads: 4",
     "unknown key(s) ['threads'] (expected jobs, defaults)"),
])
def test_manifest_file_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(BatchError) as exc:
        load_manifest(path)
    assert str(exc.value).startswith(f"{path}: ") and message in str(exc.value), str(exc.value)
    with pytest.raises(BatchError) as exc:
        load_manifest(tmp_path / "none.yaml")
    assert str(exc.value).startswith(f"{tmp_path / 'none.yaml'}: cannot read the manifest")


def test_check_out_refuses_an_earlier_run(tmp_path: Path) -> None:
    jobs = parse_manifest({"jobs": [{"name": "a", "estimation_bags": ["x"],
                                     "validation_bags": ["y"]}]}, "m", tmp_path)
    check_out(tmp_path / "new", jobs)  # not there yet: fine
    (tmp_path / "o" / "a").mkdir(parents=True)
    check_out(tmp_path / "o", jobs)  # an empty job folder: fine
    (tmp_path / "o" / "a" / "report.json").write_text("{}")
    (tmp_path / "o" / "summary.json").write_text("{}")
    with pytest.raises(BatchError) as exc:
        check_out(tmp_path / "o", jobs)
    lines = str(exc.value).splitlines()
    assert [ln.split(": ")[1].split(" exists")[0] for ln in lines] == [
        str(tmp_path / "o" / "summary.json"), str(tmp_path / "o" / "a")]
    assert lines[0].startswith(f"--out {tmp_path / 'o'}: ") and lines[0].endswith(
        "exists and is not empty (an earlier run?); choose another --out or remove it")
    (tmp_path / "f").write_text("")
    with pytest.raises(BatchError, match="exists and is not a folder"):
        check_out(tmp_path / "f", jobs)


# ------------------------------------------------------------ one job and the summary, pure
def test_run_job_and_summary_in_process(lab: Path, tmp_path: Path) -> None:
    """A job that works gives its report's figures; one with a missing bag is failed with
    the pipeline's error (and its traceback in job.log), never raised; the summary lists
    every job in manifest order, a job without outcome failed."""
    jobs = load_manifest(manifest(lab, [OK_JOBS[0], MISSING, OK_JOBS[1]]))
    good = run_job(jobs[0], tmp_path)
    bad = run_job(jobs[1], tmp_path)
    assert good.status == OK and good.error is None
    assert good.wall_s is not None and good.wall_s > 0
    assert good.cpu_s is not None and good.cpu_s > 0
    rep = json.loads((tmp_path / "joint1" / "report.json").read_text())
    assert good.figures is not None
    assert good.figures["accepted"] == ["sensor_offset@v"]
    assert good.figures["selection_fit_percent"] == {
        "v": {"baseline": rep["baseline"]["fit_percent"]["v"],
              "final": rep["final"]["fit_percent"]["v"]}}
    assert good.figures["selection_fit_percent"]["v"]["final"] > 90
    assert good.figures["test_fit_percent"]["v"]["final"] == rep["test"]["final"]["fit_percent"]["v"]
    assert good.worker["pid"] == os.getpid() and set(good.worker["blas"]) >= {"OMP_NUM_THREADS"}
    assert (bad.status, bad.error_type, bad.figures) == (FAILED, "DataError", None)
    assert bad.error == f"{lab / 'nope'}: bag not found"
    log = (tmp_path / "lost" / JOB_LOG).read_text()
    assert "Traceback" in log and "bag not found" in log
    s = summarize(jobs, [bad, good], manifest="m.yaml", out=tmp_path,
                  cluster={"kind": "none", "address": "-", "workers": 1, "threads": [1]},
                  wall_s=1.0)
    assert [(r["name"], r["status"]) for r in s["jobs"]] == [
        ("joint1", OK), ("lost", FAILED), ("joint2", FAILED)]
    assert s["jobs"][2]["error"] == "no outcome"
    assert s["counts"] == {OK: 1, FAILED: 2}
    assert s["jobs"][0]["report"] == str(tmp_path / "joint1" / "report.json")
    js, md = write_summary(tmp_path, s)
    assert json.loads(js.read_text()) == s
    text = md.read_text()
    assert text.startswith("# Batch identification: 1 ok, 2 failed")
    assert "| [joint1](joint1/report.md) | ok | sensor_offset@v | v " in text
    assert "| lost | failed | - | - | - | " in text
    assert f"- **lost**: DataError: {lab / 'nope'}: bag not found (log: `lost/job.log`)" in text
    assert summary_markdown(s) == text


def test_a_worker_with_threads_or_malloc_trim_is_warned_about() -> None:
    one = dict.fromkeys(("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"), "1")
    fine = {"threads": 1, "blas": one, "malloc_trim_threshold": None}
    assert worker_warnings({"tcp://a:1": fine}) == []
    warned = worker_warnings({
        "tcp://a:1": fine,
        "tcp://b:2": {**fine, "blas": {**one, "OMP_NUM_THREADS": None}},
        "tcp://c:3": {**fine, "threads": 4, "malloc_trim_threshold": "65536"}})
    assert [w.split(":")[:3] for w in warned] == [
        ["worker tcp", "//b", "2"], ["worker tcp", "//c", "3"], ["worker tcp", "//c", "3"]]
    assert "1 task thread(s), BLAS OMP_NUM_THREADS=None: jobs there share cores" in warned[0]
    assert "4 task thread(s), BLAS at 1: jobs there share cores" in warned[1]
    assert "MALLOC_TRIM_THRESHOLD_=65536 (Dask's default)" in warned[2]


def test_the_core_and_the_cli_import_no_dask() -> None:
    """Planning, validation and summary (and the CLI until it runs jobs) load without Dask."""
    code = ("import sys, dvt_identify.batch, dvt_identify.batch_cli; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'dask', 'distributed'}))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, check=True)
    assert r.stdout.strip() == "[]"


# ----------------------------------------------------------------- on a real LocalCluster
def test_local_cluster_runs_every_job_in_its_own_worker_process(
        lab: Path, tmp_path: Path, no_leftover: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """Four jobs on LocalCluster(n_workers=2, threads_per_worker=1, processes=True): both
    worker processes run jobs (one thread, BLAS at 1 thread even where this environment and
    the Dask settings say 4), every report exists, the failing job (a missing bag) is failed
    with its error and the others are ok; the cluster is gone when run_batch returns."""
    import dask

    from dvt_identify.batch_dask import run_batch

    path = manifest(lab, [OK_JOBS[0], MISSING, *OK_JOBS[1:]])
    jobs = load_manifest(path)
    out = tmp_path / "out"
    seen: list[str] = []
    four = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    for var in four:
        monkeypatch.setenv(var, "4")
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)  # Dask sets it here, too
    with dask.config.set({f"distributed.nanny.pre-spawn-environ.{v}": "4" for v in four}):
        s = run_batch(jobs, out, manifest=str(path), workers=2,
                      on_done=lambda o: seen.append(o.name))
    assert sorted(seen) == sorted(j.name for j in jobs)
    assert s["cluster"]["kind"] == "local" and s["cluster"]["workers"] == 2
    assert s["cluster"]["threads"] == [1] and s["warnings"] == []
    assert [(r["name"], r["status"]) for r in s["jobs"]] == [
        ("joint1", OK), ("lost", FAILED), ("joint2", OK), ("joint3-holdout", OK)]
    lost = s["jobs"][1]
    assert (lost["error_type"], lost["error"]) == ("DataError", f"{lab / 'nope'}: bag not found")
    workers = {r["worker"]["address"]: r["worker"] for r in s["jobs"]}
    assert len(workers) == 2 and s["workers_used"] == sorted(workers)
    pids = {w["pid"] for w in workers.values()}
    assert len(pids) == 2 and os.getpid() not in pids
    for w in workers.values():
        assert w["threads"] == 1
        assert w["blas"] == {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                             "MKL_NUM_THREADS": "1"}
        assert w["malloc_trim_threshold"] is None
        assert w["fork_workers"] == "1"  # the identifier forks no workers of its own there
    for r in s["jobs"]:
        if r["status"] == OK:
            assert (out / r["name"] / "report.json").is_file()
            assert (out / r["name"] / "report.md").is_file()
            assert r["figures"]["accepted"] == ["sensor_offset@v"]
            assert r["wall_s"] > 0
    assert s["jobs"][0]["figures"]["test_fit_percent"]["v"]["final"] > 90
    assert s["jobs"][3]["select_on"] == "holdout"
    assert json.loads((out / "summary.json").read_text()) == s
    assert "## Failures" in (out / "summary.md").read_text()
    assert not any(psutil.pid_exists(p) for p in pids), "a worker outlived run_batch"


def test_the_cluster_is_closed_when_the_caller_fails(lab: Path, tmp_path: Path,
                                                     no_leftover: None) -> None:
    from dvt_identify.batch_dask import run_batch

    jobs = load_manifest(manifest(lab, OK_JOBS[:2]))

    def boom(_: object) -> None:
        raise RuntimeError("stop here")

    with pytest.raises(RuntimeError, match="stop here"):
        run_batch(jobs, tmp_path / "out", workers=2, on_done=boom)
    assert not (tmp_path / "out" / "summary.json").exists()


@pytest.mark.parametrize(("address", "message"), [
    ("tcp://127.0.0.1:1", "--scheduler tcp://127.0.0.1:1: cannot connect in 2 s: "),
    ("foo:bar", "--scheduler foo:bar: not a scheduler address such as tcp://host:8786 ("),
])
def test_no_scheduler_is_an_error_and_nothing_is_written(
        lab: Path, tmp_path: Path, address: str, message: str) -> None:
    from dvt_identify.batch_dask import run_batch

    jobs = load_manifest(manifest(lab, OK_JOBS[:1]))
    with pytest.raises(BatchError) as exc:
        run_batch(jobs, tmp_path / "out", scheduler=address, connect_timeout_s=2.0)
    assert str(exc.value).startswith(message), str(exc.value)
    assert not (tmp_path / "out").exists()
    # finalise the client that failed to connect here: its __del__ closes it synchronously,
    # and run by a later collection it would block whichever thread allocates then (suspected
    # in a CI run where a LocalCluster's IO-loop thread did not start in 10 s)
    del exc
    gc.collect()


# ------------------------------------------------------------------------- the console script
DASK = Path(sys.executable).parent / "dask"


def _stop(procs: list[subprocess.Popen[str]]) -> None:
    """SIGTERM each process (the worker CLI closes its nannies and workers), wait up to 30 s,
    then kill what is left of its tree."""
    for p in reversed(procs):
        tree: list[psutil.Process] = []
        with contextlib.suppress(psutil.NoSuchProcess):
            tree = psutil.Process(p.pid).children(recursive=True)
        p.terminate()
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)
        for c in tree:
            with contextlib.suppress(psutil.NoSuchProcess):
                c.kill()
        psutil.wait_procs(tree, timeout=10)


def _wait_for_line(path: Path, needle: str, count: int, proc: subprocess.Popen[str],
                   deadline_s: float) -> str:
    """Poll the log ``path`` until ``needle`` appears ``count`` times; fail naming the log if
    ``proc`` ends or the deadline passes first."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        text = path.read_text() if path.exists() else ""
        if text.count(needle) >= count:
            return text
        assert proc.poll() is None, f"{proc.args!r} ended ({proc.returncode}): {text}"
        time.sleep(0.2)
    raise AssertionError(f"{path}: {needle!r} not seen {count} time(s) in {deadline_s} s: "
                         f"{path.read_text() if path.exists() else ''}")


@pytest.fixture
def running_cluster(tmp_path: Path) -> Iterator[tuple[str, psutil.Process]]:
    """A cluster started the way a lab starts one: ``dask scheduler`` and ``dask worker``
    (two single-threaded worker processes) as processes of their own on 127.0.0.1; yields
    the scheduler's address and the worker command's process, stops both afterwards."""
    sched_file = tmp_path / "scheduler.json"
    procs: list[subprocess.Popen[str]] = []
    try:
        with open(tmp_path / "scheduler.log", "w") as log:
            procs.append(subprocess.Popen(
                [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0",
                 "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file)],
                stdout=log, stderr=subprocess.STDOUT, text=True))
        _wait_for_line(tmp_path / "scheduler.log", "Scheduler at:", 1, procs[0], 120)
        # the file is written before the log line; read it only once the line is there
        address = json.loads(sched_file.read_text())["address"]
        with open(tmp_path / "worker.log", "w") as log:
            procs.append(subprocess.Popen(
                [str(DASK), "worker", address, "--nworkers", "2", "--nthreads", "1",
                 "--host", "127.0.0.1", "--no-dashboard"],
                stdout=log, stderr=subprocess.STDOUT, text=True))
        _wait_for_line(tmp_path / "worker.log", "Registered to:", 2, procs[1], 120)
        yield address, psutil.Process(procs[1].pid)
    finally:
        _stop(procs)


def test_cli_on_a_running_scheduler(lab: Path, tmp_path: Path, no_leftover: None,
                                    running_cluster: tuple[str, psutil.Process]) -> None:
    """``dvt-identify-batch --scheduler`` runs the jobs on the workers of a running cluster
    (here one this test starts with ``dask scheduler`` and ``dask worker``): exit 3 as a job
    failed, a line per job, the summary; the jobs ran in those worker processes."""
    address, worker_cli = running_cluster
    path = manifest(lab, [OK_JOBS[1], MISSING])
    out = tmp_path / "out"
    worker_pids = {p.pid for p in worker_cli.children(recursive=True)}
    r = subprocess.run([str(EXE), str(path), "--out", str(out), "--scheduler", address],
                       capture_output=True, text=True, timeout=240, check=False)
    assert r.returncode == 3, r.stderr
    assert r.stdout.splitlines()[-1] == (f"2 job(s): 1 ok, 1 failed; summary: "
                                         f"{out}/summary.md")
    progress = [ln for ln in r.stderr.splitlines() if ln.startswith("[dvt-identify-batch]")]
    assert len(progress) == 2
    assert any("lost failed in " in ln and ln.endswith(f"{lab / 'nope'}: bag not found")
               for ln in progress), progress
    s = json.loads((out / "summary.json").read_text())
    assert s["cluster"] == {"kind": "scheduler", "address": address,
                            "workers": 2, "threads": [1]}
    assert [(j["name"], j["status"]) for j in s["jobs"]] == [("joint2", OK), ("lost", FAILED)]
    assert {j["worker"]["pid"] for j in s["jobs"]} <= worker_pids, worker_pids
    assert (out / "joint2" / "report.md").is_file()
    # a cluster started with Dask's defaults: its workers are flagged, not refused
    assert s["warnings"] == [f"worker {a}: MALLOC_TRIM_THRESHOLD_=65536 (Dask's default): "
                             "identification about 1.6x slower (docs/batch.md)"
                             for a in s["workers_used"]]
    assert "## Warnings" in (out / "summary.md").read_text()


def test_cli_sigterm_closes_the_cluster_and_writes_the_summary(
        lab: Path, tmp_path: Path, no_leftover: None, cart_desc: Callable[..., Description],
        cart_record: Callable[..., Segment]) -> None:
    """SIGTERM while jobs run (one worker: a cart job, then two on a recording 40 times as
    long, seconds each): exit 130, the cluster closed, a summary with the finished job ok and
    the others failed as interrupted."""
    import signal

    long = _write(tmp_path / "long", cart_record(cart_desc(), "long", seed=5, n=60000,
                                                 offset=0.3))
    path = manifest(lab, [OK_JOBS[1],
                          {"name": "long1", "estimation_bags": [str(long)],
                           "validation_bags": ["r2"]},
                          {"name": "long2", "estimation_bags": [str(long)],
                           "validation_bags": ["r3"]}], name="sig.yaml")
    out = tmp_path / "out"
    with subprocess.Popen([str(EXE), str(path), "--out", str(out), "--workers", "1"],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as p:
        try:
            assert p.stderr is not None
            first = ""
            while not first.startswith("[dvt-identify-batch] "):  # bounded: the test timeout
                first = p.stderr.readline()
                assert first, "no job finished"
            assert first.startswith("[dvt-identify-batch] 1/3 "), first
            p.send_signal(signal.SIGTERM)
            _, err = p.communicate(timeout=60)
        finally:
            p.kill()
    assert p.returncode == 130, err
    assert err.splitlines()[-1] == (f"dvt-identify-batch: interrupted; the cluster is closed; "
                                    f"summary of the jobs that finished: {out}/summary.md")
    s = json.loads((out / "summary.json").read_text())
    status = {j["name"]: (j["status"], j["error"]) for j in s["jobs"]}
    done = first.split()[2]
    assert status.pop(done) == (OK, None)
    assert "interrupted before it finished" in {e for _, e in status.values()}
    assert all(st == OK or e == "interrupted before it finished"
               for st, e in status.values()), status


def test_cli_checks_everything_before_running(lab: Path, tmp_path: Path) -> None:
    good = manifest(lab, OK_JOBS[:2])
    r = subprocess.run([str(EXE), str(good), "--out", str(tmp_path / "o"), "--check"],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == [
        f"joint1: 1 estimation, 1 validation, 1 test bag(s), select on validation, "
        f"description {lab / 'cart.yaml'} -> {tmp_path / 'o' / 'joint1'}",
        f"joint2: 1 estimation, 1 validation bag(s), select on validation, "
        f"description {lab / 'cart.yaml'} -> {tmp_path / 'o' / 'joint2'}",
        "2 job(s): manifest ok"]
    bad = manifest(lab, [OK_JOBS[0], {"name": "j", "estimation_bags": ["r1"],
                                      "select_on": "bic"}], name="bad.yaml")
    r = subprocess.run([str(EXE), str(bad), "--out", str(tmp_path / "o"), "--workers", "2"],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 1
    assert r.stderr.splitlines() == [
        f"dvt-identify-batch: error: {bad}: jobs[1] (j): select_on: expected one of "
        "validation, holdout, cv, got 'bic'"]
    assert not (tmp_path / "o").exists()  # nothing was run
    r = subprocess.run([str(EXE), str(good), "--out", str(tmp_path / "o"), "--workers", "2",
                        "--scheduler", "tcp://127.0.0.1:1"], capture_output=True, text=True,
                       timeout=120, check=False)
    assert r.returncode == 2 and "not allowed with argument" in r.stderr
