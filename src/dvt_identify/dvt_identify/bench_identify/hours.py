"""Long-recording mode of ``dvt-bench identify`` (``--hours H``): how fast, and in how much
memory, the identifier takes hours of 1 kHz data (see :mod:`dvt_identify.bench_identify`).

The recording: ``H`` hours of the simulated plant (``physical`` parameters, no hidden effect)
driven through the offline runner (the driver's supervisor into the plant core, no ROS) with
the ``watch`` experiment (neutral PRBS and multisine, then each gear engaged with PRBS,
repeated with fresh signals), recorded as runs of :data:`RUN_MINUTES` minutes each (a lab's
hour is several recordings; each run is a segment with its own initial state), plus one
``ident`` run for validation: ``scripts/make_hour_bags.py`` of the workspace, run in a
process of its own (the identifier, and so its benchmark, does not depend on the plant's
package). The runs are made once (on both cores) and kept in a cache directory (``--cache``,
default ``~/.cache/dvt-bench/identify-hours``); recording an hour takes about 15 minutes of
one core per hour of data.

The identification runs in a child process of its own, so that its peak resident memory is
its own (``peak_rss_mb``: the largest of that process and of the worker processes it forks).
It reads the estimation runs one at a time (a run's messages are decoded and dropped before the
next is read) and keeps each at the fit rate only (:func:`dvt_identify.fitrate.fit_segments`: the
rate the identification would fit at anyway, consistent with the simulation's hold), then runs
:func:`dvt_identify.loop.identify` (baseline, drift check, augment loop) on them and on the
full-rate validation run. ``loop_seconds`` is that call (as for the short recordings);
``read_seconds`` the reading. The estimation figures are then at the fit rate (200 Hz).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import resource
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dvt_identify.bench_identify.common import Log, finite, load_average, num, quiet
from dvt_identify.errors import BenchError

TARGET_LOOP_SECONDS = 60.0
TARGET_PEAK_RSS_MB = 2048.0
RUN_MINUTES = 5.0
"""Length of one estimation run [min] (the last one shorter to make up the hours; reading
one run at 1 kHz holds its raw messages, about 250 MB for five minutes)."""
SEED = 0
"""Base seed of the runs' experiments and plant noise."""
MIN_RUN_SECONDS = 20.0
"""Shortest run recorded [s] (as ``scripts/make_hour_bags.py``)."""


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/dvt-bench/identify-hours`` (``~/.cache`` by default)."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "dvt-bench" / "identify-hours"


def run_lengths(hours: float, run_minutes: float = RUN_MINUTES) -> list[float]:
    """The estimation runs' lengths [s] that make up ``hours`` (runs of ``run_minutes``, the
    last one shorter, at least :data:`MIN_RUN_SECONDS`).

    Raises:
        BenchError: ``hours`` or ``run_minutes`` not > 0.
    """
    if not (hours > 0 and math.isfinite(hours)):
        raise BenchError(f"--hours: expected > 0, got {hours}")
    if not (run_minutes > 0 and math.isfinite(run_minutes)):
        raise BenchError(f"--run-minutes: expected > 0, got {run_minutes}")
    total = hours * 3600.0
    step = run_minutes * 60.0
    out = []
    while total > 1e-9:
        out.append(max(min(step, total), MIN_RUN_SECONDS))
        total -= step
    return out


def plant_fingerprint() -> str:
    """Short hash of what the cached recordings depend on beyond their lengths and seed: the
    ``physical`` parameter set the plant runs and the generator script (a changed plant or
    recipe records anew instead of reusing a stale cache)."""
    from dvt_model.errors import ParameterError
    from dvt_model.presets import read_yaml_setting

    data, _ = read_yaml_setting("physical", what="parameter set", error=ParameterError,
                                package="dvt_model", directory="param_sets")
    h = hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode())
    h.update(generator_script().read_bytes())
    return h.hexdigest()[:10]


def recording_dir(cache: Path, hours: float, run_minutes: float, seed: int) -> Path:
    """The cache directory of one recording configuration (:func:`plant_fingerprint` in its
    name)."""
    return cache / f"watch-{hours:g}h-{run_minutes:g}min-seed{seed}-{plant_fingerprint()}"


def generator_script() -> Path:
    """``scripts/make_hour_bags.py`` of the workspace (found from the working directory and
    its parents, then beside this package's source tree): the recording needs the plant, which
    the identifier does not depend on.

    Raises:
        BenchError: not found.
    """
    here = Path(__file__).resolve()
    for root in (Path.cwd(), *Path.cwd().parents, *here.parents):
        cand = root / "scripts" / "make_hour_bags.py"
        if cand.is_file():
            return cand
    raise BenchError(f"--hours: scripts/make_hour_bags.py not found from {Path.cwd()} (it "
                     "records the hours; run it from the workspace)")


def generate(where: Path, hours: float, run_minutes: float = RUN_MINUTES, seed: int = SEED,
             timeout: float = 7200.0) -> dict[str, Any]:
    """Record the runs into ``where`` (:func:`generator_script` in a process of its own);
    returns what its ``done.json`` holds.

    Raises:
        BenchError: ``where`` exists without ``done.json`` (an interrupted recording: remove
            it), or the script failed.
    """
    if where.exists():
        raise BenchError(f"{where}: exists without done.json (an interrupted recording? "
                         "remove it)")
    cmd = [sys.executable, str(generator_script()), str(where), "--hours", repr(hours),
           "--run-minutes", repr(run_minutes), "--seed", str(seed)]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                              check=False)
    except subprocess.TimeoutExpired as exc:
        raise BenchError(f"--hours: recording took longer than {timeout:g} s") from exc
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise BenchError(f"--hours: {cmd[1]} failed (exit status {done.returncode}): {tail}")
    return dict(json.loads((where / "done.json").read_text()))


def peak_rss_mb() -> float:
    """The largest resident set of this process and of the children it waited for [MB]."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0  # ru_maxrss is in kB on Linux


def identify_runs(est_bags: Sequence[str], val_bags: Sequence[str], description: str = "dvt",
                  log: Log = quiet) -> dict[str, Any]:
    """Identify from the runs (module docstring): estimation runs read one at a time and
    kept at the fit rate; returns the figures (run in a process of its own for
    ``peak_rss_mb``)."""
    import numpy as np

    from dvt_identify import identifiability
    from dvt_identify.description import load_description
    from dvt_identify.fitrate import fit_segments
    from dvt_identify.loop import identify
    from dvt_identify.pipeline import load_segments, loop_config
    from dvt_identify.simloop import warm_up
    from dvt_identify.simulation import OEModel

    warm_up()
    desc = load_description(description)
    cfg = loop_config(desc, True)
    model = OEModel(desc.structure, desc.make_model_effects())
    c0, t0 = time.process_time(), time.perf_counter()
    est = []
    n_full = 0
    rss_read = []
    for bag in est_bags:
        segs = load_segments([bag], desc)
        n_full += sum(s.n for s in segs)
        fit_rate, _ = fit_segments(segs, model, cfg.fit_decimate)
        est.extend(fit_rate)
        del segs
        rss_read.append(peak_rss_mb())
        log(f"read {Path(bag).name}: {sum(s.n for s in est)} fit samples so far")
    val = load_segments(val_bags, desc)
    read_s, read_cpu = time.perf_counter() - t0, time.process_time() - c0
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    c0, t0 = time.process_time(), time.perf_counter()
    res = identify(est, val, desc, cfg, log, check=chk)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    fin = res.final
    par = fin.parameters()
    return {
        "samples": n_full, "fit_samples": sum(s.n for s in est), "segments": len(est),
        "validation_samples": sum(s.n for s in val),
        "read_seconds": read_s, "read_cpu_seconds": read_cpu,
        "loop_seconds": res.seconds, "identify_wall_seconds": wall,
        "identify_cpu_seconds": cpu,
        "identify_children_cpu_seconds": kids.ru_utime + kids.ru_stime,
        "peak_rss_mb": peak_rss_mb(), "peak_rss_mb_after_reading": rss_read[-1] if rss_read
        else None,
        "fit_rate_hz": 1.0 / est[0].dt,
        "baseline_validation_fit_percent": dict(zip(
            res.baseline.val.output_names, map(float, res.baseline.val.fit_percent),
            strict=True)),
        "validation_fit_percent": dict(zip(fin.val.output_names,
                                           map(float, fin.val.fit_percent), strict=True)),
        "estimation_fit_percent_at_fit_rate": dict(zip(
            fin.est.output_names, map(float, fin.est.fit_percent), strict=True)),
        "accepted": [d.score.label for d in res.accepted],
        "decisions": [{"candidate": d.score.label, "accepted": d.accepted,
                       "reason": d.reason} for d in res.decisions],
        "drifting": [p.name for p in res.drift.drifting] if res.drift else [],
        "parameters": {k: float(v) for k, v in par.items()
                       if k[:1] in ("M", "D") and k[1:].isdigit()},
        "parameter_std": {k: float(v) for k, v in fin.fit.parameter_std().items()
                          if k[:1] in ("M", "D") and k[1:].isdigit()},
        "baseline_fit_seconds": res.baseline.fit.seconds_,
        "notes": list(res.notes),
        "rss_note": "peak resident set of the identifying process or of a worker it forked",
        "np_version": np.__version__,
    }


def _child(role: str, args: dict[str, Any], timeout: float, log: Log) -> dict[str, Any]:
    """Run ``role`` (``identify``) in a new Python process; its JSON result.

    Raises:
        BenchError: the child failed (its last stderr line) or timed out.
    """
    cmd = [sys.executable, "-m", "dvt_identify.bench_identify.hours", role, json.dumps(args)]
    log(f"{role}: {' '.join(cmd[:4])} ...")
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                              check=False)
    except subprocess.TimeoutExpired as exc:
        raise BenchError(f"{role}: no result within {timeout:g} s") from exc
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise BenchError(f"{role}: exit status {done.returncode}: {tail}")
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def run_hours(hours: float, description: str = "dvt", cache: Path | None = None,
              run_minutes: float = RUN_MINUTES, seed: int = SEED, log: Log = quiet,
              timeout: float = 3600.0) -> dict[str, Any]:
    """Long-recording mode (module docstring); returns the figures.

    Raises:
        BenchError: a bad setting, or the generation or the identification failed.
    """
    run_lengths(hours, run_minutes)  # checks the settings
    where = recording_dir(cache or default_cache(), hours, run_minutes, seed)
    load_before = load_average()
    done = where / "done.json"
    if done.exists():
        info = json.loads(done.read_text())
        generated = False
        log(f"recording: {where} (cached)")
    else:
        log(f"recording: generating {hours:g} h into {where}")
        info = generate(where, hours, run_minutes, seed, timeout)
        generated = True
    out = _child("identify", {"est": info["estimation"], "val": [info["validation"]],
                              "description": description}, timeout, log)
    out.update({
        "mode": "hours", "hours": hours, "recording": str(where), "runs": len(info["runs_s"]),
        "run_minutes": run_minutes, "generated_now": generated,
        "generate_seconds": info.get("generate_seconds"), "made_by": info.get("made_by"),
        "targets": {"loop_seconds": TARGET_LOOP_SECONDS, "peak_rss_mb": TARGET_PEAK_RSS_MB},
        "load_average": {"before": load_before, "after": load_average()},
        "cpu_count": os.cpu_count()})
    out["meets_targets"] = {"loop_seconds": out["loop_seconds"] <= TARGET_LOOP_SECONDS,
                            "peak_rss_mb": out["peak_rss_mb"] <= TARGET_PEAK_RSS_MB}
    return dict(finite(out))


def pretty_hours(res: dict[str, Any]) -> str:
    """Human-readable text of :func:`run_hours`."""
    lines = [f"recording: {res['hours']:g} h at 1 kHz ({res['samples']} samples, "
             f"{res['runs']} runs of {res['run_minutes']:g} min, validation "
             f"{res['validation_samples']} samples) in {res['recording']}"
             + (f", generated in {num(res['generate_seconds'], '.0f')} s"
                if res.get("generated_now") else " (cached)"),
             f"loop_seconds {num(res['loop_seconds'], '.1f')} (target <= "
             f"{TARGET_LOOP_SECONDS:g})   peak_rss_mb {num(res['peak_rss_mb'], '.0f')} "
             f"(target <= {TARGET_PEAK_RSS_MB:g})",
             f"  read {num(res['read_seconds'], '.1f')} s; identify cpu "
             f"{num(res['identify_cpu_seconds'], '.1f')} s (+ workers "
             f"{num(res['identify_children_cpu_seconds'], '.1f')} s); fit at "
             f"{num(res['fit_rate_hz'], '.0f')} Hz, {res['fit_samples']} samples, "
             f"{res['segments']} segments",
             f"  validation fit {res['validation_fit_percent']}, accepted {res['accepted']}",
             f"  load average {res['load_average']['before']} -> "
             f"{res['load_average']['after']}"]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """The identifying child's entry: ``python -m dvt_identify.bench_identify.hours identify
    JSON``; prints the result as one JSON line."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2 or args[0] != "identify":
        print("usage: python -m dvt_identify.bench_identify.hours identify JSON",
              file=sys.stderr)
        return 2
    spec = json.loads(args[1])
    out = identify_runs(spec["est"], spec["val"], spec.get("description", "dvt"))
    print(json.dumps(finite(out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
