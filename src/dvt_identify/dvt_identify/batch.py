"""Batch identification, the pure part: a manifest of jobs (each one call of
:func:`dvt_identify.pipeline.run`), its validation, one job run with its outcome, and the summary
of a batch. No Dask here: :mod:`dvt_identify.batch_dask` runs the jobs on a cluster and
:mod:`dvt_identify.batch_cli` is ``dvt-identify-batch`` (docs/batch.md).

A manifest (YAML, or JSON for a ``.json`` file) is a mapping::

    defaults:                 # optional: any job field but name; a job's own value wins
      description: dvt        # bundled name or YAML file (default dvt)
      plots: false
    jobs:
      - name: joint1          # [A-Za-z0-9][A-Za-z0-9._-]*, unique: the job's folder OUT/joint1
        estimation_bags: [bags/j1-a, bags/j1-b]
        validation_bags: [bags/j1-val]   # required unless select_on is holdout or cv
        test_bags: [bags/j1-test]        # optional (default none)
        select_on: validation            # validation | holdout | cv (default validation)
        init_window: 0                   # samples (default 0)

Relative paths are taken from the manifest's folder. Everything is checked before any job runs
(:func:`parse_manifest`): fields, types, names, a bag given twice in one job, and each
description is loaded (``cv`` on one estimation bag crosses contiguous blocks of it, as
``dvt-identify --select-on cv`` does). The bags themselves are read by the
job, on its worker: a missing or unusable bag fails that job only (with the pipeline's error).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import time
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from dvt_identify import pipeline
from dvt_identify.bench_identify.common import BLAS_ENV
from dvt_identify.description import DEFAULT_DESCRIPTION, available_descriptions, load_description
from dvt_identify.errors import BatchError, DescriptionError
from dvt_identify.parallel import ENV as FORK_WORKERS
from dvt_model.presets import safe_load

TOOL = "dvt-identify-batch"
SELECT_ON = ("validation", "holdout", "cv")
"""What may choose the effects (``select_on`` of :func:`dvt_identify.pipeline.run`)."""
JOB_FIELDS = ("name", "description", "estimation_bags", "validation_bags", "test_bags",
              "select_on", "init_window", "plots")
"""The keys of a job entry (and, but ``name``, of ``defaults``)."""
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*\Z")
SUMMARY_FILES = ("summary.json", "summary.md")
"""The batch's own files in OUT (no job may be named so)."""
JOB_LOG = "job.log"
"""In each job's folder: what the job wrote on stderr (data warnings) and a failure's
traceback."""
OK, FAILED = "ok", "failed"
MALLOC_TRIM = "MALLOC_TRIM_THRESHOLD_"
"""Dask sets it (65536) in the workers it spawns by default; glibc then keeps a fixed mmap
threshold and every large array is mapped and unmapped anew: a DVT identification took 19 s of
CPU instead of 12 s with it set (ident-coulomb, docs/batch.md). The local cluster leaves it
unset."""


@dataclass(frozen=True)
class Job:
    """One identification: the arguments of :func:`dvt_identify.pipeline.run`, paths absolute
    (bags are directories or ``.mcap`` files; ``description`` a bundled name or a file)."""

    name: str
    estimation_bags: tuple[str, ...]
    validation_bags: tuple[str, ...] = ()
    test_bags: tuple[str, ...] = ()
    description: str = DEFAULT_DESCRIPTION
    select_on: str = "validation"
    init_window: int = 0
    plots: bool = True


@dataclass
class JobOutcome:
    """What became of one job.

    ``status`` is ``ok`` or ``failed`` (then ``error`` is the one-line reason and
    ``error_type`` the exception's class); ``wall_s`` the job's wall time [s] on its worker
    and ``cpu_s`` the CPU time [s] its process and the children it waited for used meanwhile
    (a worker runs one job at a time): ``cpu_s`` well below ``wall_s`` means the core was
    shared, above it that the job used more than one core; both ``None`` when it never ran
    there; ``worker`` where it ran
    (:func:`worker_identity`; the runner adds ``address`` and ``threads``); ``figures`` those of
    :func:`report_figures` (``None`` for a failed job)."""

    name: str
    status: str
    out_dir: str
    wall_s: float | None = None
    cpu_s: float | None = None
    error: str | None = None
    error_type: str | None = None
    worker: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


# ------------------------------------------------------------------------------ the manifest
def load_manifest(path: str | Path) -> list[Job]:
    """Read and validate a manifest (:func:`parse_manifest`); YAML, or JSON for ``.json``.

    Raises:
        BatchError: unreadable, not YAML/JSON, or invalid (every problem, one per line).
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise BatchError(f"{p}: cannot read the manifest: {exc.strerror or exc}") from exc
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        kind = "JSON" if p.suffix.lower() == ".json" else "YAML"
        raise BatchError(f"{p}: not valid {kind}: {' '.join(str(exc).split())}") from exc
    return parse_manifest(data, str(p), p.resolve().parent)


def parse_manifest(data: Any, source: str, base: str | Path) -> list[Job]:
    """The jobs of a parsed manifest, every field checked and each description loaded.

    Args:
        data: the parsed YAML/JSON.
        source: the manifest's name in messages (its path).
        base: folder that relative paths are taken from (the manifest's).

    Raises:
        BatchError: every problem found, one per line, each as ``SOURCE: jobs[I] (NAME):
            FIELD: what is wrong``.
    """
    problems: list[str] = []
    if not isinstance(data, Mapping):
        raise BatchError(f"{source}: expected a mapping with 'jobs' (a list of jobs), got "
                         f"{type(data).__name__}")
    unknown = sorted(set(map(str, data)) - {"jobs", "defaults"})
    if unknown:
        problems.append(f"{source}: unknown key(s) {unknown} (expected jobs, defaults)")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, Mapping):
        problems.append(f"{source}: defaults: expected a mapping, got {type(defaults).__name__}")
        defaults = {}
    bad = sorted(set(map(str, defaults)) - set(JOB_FIELDS[1:]))
    if bad:
        problems.append(f"{source}: defaults: unknown key(s) {bad} (expected "
                        f"{', '.join(JOB_FIELDS[1:])})")
        defaults = {k: v for k, v in defaults.items() if k not in bad}
    entries = data.get("jobs")
    if not isinstance(entries, list) or not entries:
        problems.append(f"{source}: jobs: expected a non-empty list of jobs, got {entries!r}")
        entries = []
    jobs: list[Job] = []
    seen: dict[str, int] = {}
    descriptions: dict[str, str | None] = {}  # resolved value -> error (None: loads)
    for i, entry in enumerate(entries):
        where = f"{source}: jobs[{i}]"
        if not isinstance(entry, Mapping):
            problems.append(f"{where}: expected a mapping, got {entry!r}")
            continue
        name = entry.get("name")
        if isinstance(name, str) and name:
            where += f" ({name})"
        job = _parse_job({**defaults, **entry}, set(entry), where, Path(base), descriptions,
                         problems)
        if job is None:
            continue
        if job.name in seen:
            problems.append(f"{where}: name: {job.name!r} already names jobs[{seen[job.name]}]")
            continue
        seen[job.name] = i
        jobs.append(job)
    if problems:
        raise BatchError("\n".join(problems))
    return jobs


def _parse_job(e: Mapping[str, Any], own: set[Any], where: str, base: Path,
               descriptions: dict[str, str | None], problems: list[str]) -> Job | None:
    """One job entry (defaults merged in; ``own``: the keys the entry itself gives), or
    ``None`` after appending its problems."""
    n0 = len(problems)

    def bad(key: str, msg: str) -> None:
        problems.append(f"{where}: {key}{'' if key in own else ' (from defaults)'}: {msg}")

    unknown = sorted(set(map(str, e)) - set(JOB_FIELDS))
    if unknown:
        problems.append(f"{where}: unknown key(s) {unknown} (expected {', '.join(JOB_FIELDS)})")
    name = e.get("name")
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        bad("name", f"expected a folder name of letters, digits, '.', '_' and '-' (not "
                    f"starting with '.', '_' or '-'), got {name!r}")
    elif name in SUMMARY_FILES:
        bad("name", f"{name!r} is the batch summary's file name")
    select_on = e.get("select_on", "validation")
    if select_on not in SELECT_ON:
        bad("select_on", f"expected one of {', '.join(SELECT_ON)}, got {select_on!r}")
    bags: dict[str, tuple[str, ...]] = {}
    for key, required in (("estimation_bags", True),
                          ("validation_bags", select_on == "validation"),
                          ("test_bags", False)):
        value = e.get(key, [])
        if (not isinstance(value, list) or not all(isinstance(b, str) and b for b in value)
                or (required and not value)):
            need = "a non-empty" if required else "a"
            why = " (select_on is validation)" if key == "validation_bags" and required else ""
            bad(key, f"expected {need} list of bag paths{why}, got {value!r}")
            continue
        bags[key] = tuple(_absolute(base, b) for b in value)
    owner: dict[str, str] = {}
    for key, paths in bags.items():
        for b in paths:
            if b in owner:
                bad(key, f"{b} is also in {owner[b]}" if owner[b] != key
                    else f"{b} is given twice")
            owner.setdefault(b, key)
    init_window = e.get("init_window", 0)
    if isinstance(init_window, bool) or not isinstance(init_window, int) or init_window < 0:
        bad("init_window", f"expected a whole number of samples >= 0, got {init_window!r}")
    plots = e.get("plots", True)
    if not isinstance(plots, bool):
        bad("plots", f"expected true or false, got {plots!r}")
    description = e.get("description", DEFAULT_DESCRIPTION)
    if not isinstance(description, str) or not description:
        bad("description", f"expected a bundled name or a file, got {description!r}")
    else:
        description = _description(description, base)
        if description not in descriptions:
            try:
                load_description(description)
                descriptions[description] = None
            except DescriptionError as exc:
                descriptions[description] = " ".join(str(exc).split())
        if descriptions[description] is not None:
            bad("description", str(descriptions[description]))
    if len(problems) > n0:
        return None
    return Job(name=str(name), estimation_bags=bags["estimation_bags"],
               validation_bags=bags["validation_bags"], test_bags=bags["test_bags"],
               description=description, select_on=select_on, init_window=init_window,
               plots=plots)


def _absolute(base: Path, path: str) -> str:
    """``path`` (``~`` expanded) taken from ``base`` when relative; no symlink resolved."""
    return os.path.abspath(base / os.path.expanduser(path))


def _description(value: str, base: Path) -> str:
    """A bundled description's name as it is (unless the manifest's folder holds a file of
    that name), any other value as a file path taken from ``base``."""
    if value in available_descriptions() and not (base / value).is_file():
        return value
    return _absolute(base, value)


def check_out(out: str | Path, jobs: Sequence[Job]) -> None:
    """Refuse an output folder that would mix this batch with an earlier one: ``OUT`` not a
    folder, a summary already in it, or a job's folder that exists and is not empty.

    Raises:
        BatchError: every such path, one per line.
    """
    o = Path(out)
    if o.exists() and not o.is_dir():
        raise BatchError(f"--out {o}: exists and is not a folder")
    taken = [o / f for f in SUMMARY_FILES if (o / f).exists()]
    taken += [o / j.name for j in jobs if (o / j.name).exists()
              and (not (o / j.name).is_dir() or any((o / j.name).iterdir()))]
    if taken:
        raise BatchError("\n".join(f"--out {o}: {p} exists and is not empty (an earlier run?); "
                                   "choose another --out or remove it" for p in taken))


def plan_lines(jobs: Sequence[Job], out: str | Path) -> list[str]:
    """One line per job: what it reads, how it chooses, where its report goes."""
    lines = []
    for j in jobs:
        parts = [f"{len(j.estimation_bags)} estimation", f"{len(j.validation_bags)} validation"]
        if j.test_bags:
            parts.append(f"{len(j.test_bags)} test")
        lines.append(f"{j.name}: {', '.join(parts)} bag(s), select on {j.select_on}, "
                     f"description {j.description} -> {Path(out) / j.name}")
    return lines


# ---------------------------------------------------------------------------- one job's run
def worker_identity() -> dict[str, Any]:
    """This process: host name, pid, the BLAS thread variables, ``MALLOC_TRIM_THRESHOLD_`` and
    ``DVT_IDENTIFY_WORKERS`` (:mod:`dvt_identify.parallel`; ``None``: unset)."""
    return {"host": socket.gethostname(), "pid": os.getpid(),
            "blas": {k: os.environ.get(k) for k in BLAS_ENV},
            "malloc_trim_threshold": os.environ.get(MALLOC_TRIM),
            "fork_workers": os.environ.get(FORK_WORKERS)}


def error_text(exc: BaseException) -> str:
    """One line for a failure: the message's first line (the class name if empty)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def failed(job: Job, out_root: str | Path, exc: BaseException,
           times: tuple[float, float] | None = None,
           worker: Mapping[str, Any] | None = None) -> JobOutcome:
    """The outcome of a job that failed with ``exc`` after ``times`` (wall, CPU) [s]."""
    wall, cpu = times if times is not None else (None, None)
    return JobOutcome(name=job.name, status=FAILED, out_dir=str(Path(out_root) / job.name),
                      wall_s=wall, cpu_s=cpu, error=error_text(exc),
                      error_type=type(exc).__name__, worker=dict(worker or {}))


def run_job(job: Job, out_root: str | Path) -> JobOutcome:
    """Run one job into ``OUT/<name>/`` and return its outcome; never raises for a failing
    job (any ``Exception``: bad bag, bad data, failed fit, unreadable report), so that one job
    never stops the others. The job's stderr goes to ``OUT/<name>/job.log``, with a failure's
    traceback.

    Args:
        job: the job.
        out_root: the batch's output folder (``OUT``).
    """
    out = Path(out_root) / job.name
    t0, c0 = time.monotonic(), _cpu()

    def times() -> tuple[float, float]:
        return time.monotonic() - t0, _cpu() - c0

    who = worker_identity()
    try:
        out.mkdir(parents=True, exist_ok=True)
        log = (out / JOB_LOG).open("w")
    except OSError as exc:
        return failed(job, out_root, exc, times(), who)
    with log, contextlib.redirect_stderr(log):
        try:
            pipeline.run(list(job.estimation_bags), list(job.validation_bags), out,
                description=job.description, select_on=job.select_on,
                test_bags=list(job.test_bags), init_window=job.init_window, plots=job.plots,
                quiet=True)
            rep_path = out / "report.json"
            figures = report_figures(json.loads(rep_path.read_text()), str(rep_path))
        except Exception as exc:  # a failing job never stops the others: reported instead
            traceback.print_exc(file=log)
            return failed(job, out_root, exc, times(), who)
    wall, cpu = times()
    return JobOutcome(name=job.name, status=OK, out_dir=str(out), wall_s=wall, cpu_s=cpu,
                      worker=who, figures=figures)


def _cpu() -> float:
    """CPU time [s] of this process and of its children waited for (the identifier's forked
    workers, :mod:`dvt_identify.parallel`)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def report_figures(rep: Mapping[str, Any], source: str = "report.json") -> dict[str, Any]:
    """What the summary shows of a job's ``report.json``: the accepted effects
    (``name@where``), the selection figures (fit [%] per output, baseline and final, on the
    data that chose the effects) and the test figures (``None`` without test data).

    Raises:
        BatchError: a key missing from the report (naming ``source`` and the key).
    """
    def get(d: Any, *keys: str) -> Any:
        for k in keys:
            if not isinstance(d, Mapping) or k not in d:
                raise BatchError(f"{source}: no {'.'.join(keys)}")
            d = d[k]
        return d

    def pair(base: Mapping[str, Any], fin: Mapping[str, Any]) -> dict[str, dict[str, float]]:
        return {o: {"baseline": base[o], "final": fin[o]} for o in fin}

    accepted = [f"{e['name']}@{e['where']}" for e in get(rep, "effects")
                if e.get("accepted") and e.get("name") != "none"]
    test = get(rep, "test")
    return {
        "accepted": accepted,
        "chosen_on": get(rep, "selection", "chosen_on"),
        "selection_fit_percent": pair(get(rep, "baseline", "fit_percent"),
                                      get(rep, "final", "fit_percent")),
        "test_fit_percent": None if test is None else pair(
            get(test, "baseline", "fit_percent"), get(test, "final", "fit_percent")),
        "report_seconds": get(rep, "seconds"),
    }


# ------------------------------------------------------------------------------ the summary
def summarize(jobs: Sequence[Job], outcomes: Sequence[JobOutcome], *, manifest: str,
              out: str | Path, cluster: Mapping[str, Any], wall_s: float,
              unfinished: str = "no outcome") -> dict[str, Any]:
    """The batch summary (``summary.json``): every job in manifest order with its outcome (a
    job without one is failed with the error ``unfinished``), the counts, the workers used and
    the cluster.

    Args:
        jobs: the manifest's jobs.
        outcomes: their outcomes, any order.
        manifest: the manifest's path; out: ``OUT``.
        cluster: how the jobs ran (kind, scheduler address, workers, threads).
        wall_s: the whole batch's wall time [s].
        unfinished: the error of a job without outcome.
    """
    by_name = {o.name: o for o in outcomes}
    rows = []
    for j in jobs:
        o = by_name.get(j.name) or JobOutcome(name=j.name, status=FAILED,
                                              out_dir=str(Path(out) / j.name),
                                              error=unfinished, error_type=None)
        rows.append({**o.as_dict(), "select_on": j.select_on, "description": j.description,
                     "report": str(Path(o.out_dir) / "report.json") if o.status == OK else None})
    workers = {_worker_name(r["worker"]): r["worker"] for r in rows if r["worker"]}
    return {"tool": TOOL, "manifest": manifest, "out": str(out), "cluster": dict(cluster),
            "wall_s": wall_s, "counts": {OK: sum(r["status"] == OK for r in rows),
                                         FAILED: sum(r["status"] != OK for r in rows)},
            "workers_used": sorted(workers), "warnings": worker_warnings(workers),
            "jobs": rows}


def _worker_name(w: Mapping[str, Any]) -> str:
    return str(w.get("address") or f"{w.get('host')}:{w.get('pid')}")


def worker_warnings(workers: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """A line for each worker that ran a job with more than one task thread or a BLAS thread
    variable not at 1 (jobs share cores), and for each with ``MALLOC_TRIM_THRESHOLD_`` set
    (slower); possible on a cluster started by others (docs/batch.md says how to start one)."""
    out = []
    for name, w in sorted(workers.items()):
        threads = w.get("threads")
        blas = {k: v for k, v in (w.get("blas") or {}).items() if v != "1"}
        if threads not in (None, 1) or blas:
            out.append(f"worker {name}: {threads} task thread(s), BLAS "
                       f"{', '.join(f'{k}={v}' for k, v in blas.items()) or 'at 1'}: jobs "
                       "there share cores (start workers with --nthreads 1 and "
                       "OMP_NUM_THREADS=OPENBLAS_NUM_THREADS=MKL_NUM_THREADS=1)")
        if w.get("malloc_trim_threshold") is not None:
            out.append(f"worker {name}: {MALLOC_TRIM}={w['malloc_trim_threshold']} (Dask's "
                       "default): identification about 1.6x slower (docs/batch.md)")
    return out


def _figs(d: Mapping[str, Mapping[str, float]] | None) -> str:
    if not d:
        return "-"
    return ", ".join(f"{o} {v['baseline']:.1f} → {v['final']:.1f}" for o, v in d.items())


def summary_markdown(s: Mapping[str, Any]) -> str:
    """``summary.md``: the counts, one table row per job, then each failure's error."""
    c = s["cluster"]
    lines = [f"# Batch identification: {s['counts'][OK]} ok, {s['counts'][FAILED]} failed",
             "",
             f"Manifest `{s['manifest']}`; {len(s['jobs'])} job(s) in {s['wall_s']:.1f} s on "
             f"{c.get('kind', '?')} cluster `{c.get('address', '?')}` "
             f"({c.get('workers', '?')} worker(s), threads {c.get('threads', '?')}); "
             f"workers used: {len(s['workers_used'])}.",
             "",
             "Fit [%] baseline → final per output; selection: on the data that chose the "
             "effects (validation, held-out or out-of-fold); test: data that took no part.",
             "",
             "| job | status | accepted effects | selection fit | test fit | wall [s] | CPU [s] "
             "| worker |",
             "|---|---|---|---|---|---:|---:|---|"]
    for r in s["jobs"]:
        f = r["figures"] or {}
        acc = ", ".join(f.get("accepted", [])) or ("none" if r["status"] == OK else "-")
        wall, cpu = ("-" if r[k] is None else f"{r[k]:.1f}" for k in ("wall_s", "cpu_s"))
        worker = _worker_name(r["worker"]) if r["worker"] else "-"
        job = f"[{r['name']}]({r['name']}/report.md)" if r["status"] == OK else r["name"]
        sel = _figs(f.get("selection_fit_percent"))
        sel += f" ({r['select_on']})" if f else ""
        lines.append(f"| {job} | {r['status']} | {acc} | {sel} | "
                     f"{_figs(f.get('test_fit_percent'))} | {wall} | {cpu} | {worker} |")
    if s.get("warnings"):
        lines += ["", "## Warnings", "", *(f"- {w}" for w in s["warnings"])]
    fails = [r for r in s["jobs"] if r["status"] != OK]
    if fails:
        lines += ["", "## Failures", ""]
        lines += [f"- **{r['name']}**: {r['error_type'] or 'error'}: {r['error']} "
                  f"(log: `{r['name']}/{JOB_LOG}`)" for r in fails]
    return "\n".join(lines) + "\n"


def write_summary(out: str | Path, summary: Mapping[str, Any]) -> tuple[Path, Path]:
    """Write ``OUT/summary.json`` and ``OUT/summary.md``; returns their paths."""
    o = Path(out)
    o.mkdir(parents=True, exist_ok=True)
    js, md = o / SUMMARY_FILES[0], o / SUMMARY_FILES[1]
    js.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    md.write_text(summary_markdown(summary))
    return js, md
