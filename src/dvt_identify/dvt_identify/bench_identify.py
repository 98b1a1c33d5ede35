"""``dvt-bench identify``: how fast the identifier is, and how good its statistics are.

A benchmark, not a test: it prints what it measured, met targets or not. It needs only
``dvt_model`` (the recordings and the identifier's own simulation), not the plant.

Timing mode (default)::

    dvt-bench identify [--estimation BAG...] [--validation BAG...] [--seconds S]
                       [--scaling 15,30] [--json] [--fit-decimate Q] [--starts K]
                       [--max-tries T] [--no-loop] [--keep DIR]

Identifies from recordings: by default the committed runs of the repository's ``bags/``
(:data:`DEFAULT_ESTIMATION` for estimation, :data:`DEFAULT_VALIDATION` for validation: the
``ident`` experiment on the simulated plant with no hidden effect, recorded through the real
driver chain; ``scripts/make_bags.sh`` re-creates them), else the bags given. ``--seconds S``
uses the first ``S`` seconds of each recording (copies written with
:func:`dvt_model.recording.write_run` into a temporary directory). Then
:func:`dvt_identify.pipeline.run` runs with ``augment=False`` and with the augment loop, on the
bundled ``dvt`` description.
``baseline_seconds`` and ``loop_seconds`` are the identification itself
(:func:`dvt_identify.loop.identify` on the loaded recordings: checks, decimation, the fit with
its start guard, figures and residual analysis on estimation and validation data, and for the
loop the scoring, refits and decisions), as a fit time is usually quoted;
``*_end_to_end_seconds`` add reading both bags and writing the report with its plots. The
breakdown (loading the compiled kernels, bag reading, report writing, baseline fit alone) is
measured separately. ``scaling`` repeats the baseline on shorter prefixes of the same
recordings (``--scaling`` lengths in seconds; a prefix may leave out the gear phases and with
them the band-brake model, which the pipeline then drops) and fits
``seconds ~ samples^exponent``.

Monte Carlo mode::

    dvt-bench identify --monte-carlo [N] [--mc-seconds 10] [--mc-rate 500] [--noise 0.05]
                       [--workers 2] [--seed 0] [--json]

``N`` (default 50) records simulated from a known linear model in the framework's own form: the
description's structure (``dvt``: the mechanical grey box ``M11..D22`` in neutral, no brakes, no
effects) at its initial (``thesis``) values, from rest, with a PRBS on every input its ``B`` uses
(the motor current, +-2.5 A, clock 30 ms), plus white Gaussian output noise of known standard
deviation ``sigma_j = noise * std(y_j, noise-free)`` (equal signal-to-noise ratio on every output,
so the fit's default weighting ``1/std(y_j)`` is the maximum-likelihood one). Each record gets
its own noise realisation (input fixed) and is fitted with :class:`dvt_identify.fit.OEFit` (no
augmentation). Per parameter: ``true``, ``mean``, ``std`` (over the runs), ``crlb_std`` (the
Cramér-Rao bound at the true values from the Fisher information ``J^T J`` with ``J`` the
central-difference sensitivity of the noise-free output to the parameters and the initial
states, each output divided by its ``sigma``), ``crlb_ratio = std / crlb_std``, ``bias``,
``reported_std_mean`` (the fit's own standard deviation, averaged) and ``coverage_95`` (fraction
of runs whose ``estimate +- 1.96 reported std`` contains the true value).

Targets (from the issue): ``baseline_seconds <= 2``, ``loop_seconds <= 30``,
``crlb_ratio <= 1.2``, ``0.93 <= coverage_95 <= 0.97``. With ``N`` runs the ratio itself is
uncertain by about ``1/sqrt(2 (N - 1))`` (10 % at N = 50) and a coverage by
``sqrt(0.95 * 0.05 / N)`` (3 points at N = 50); both are printed.

Comparison mode::

    dvt-bench identify --compare [EST=VAL ...] [--starts K] [--fit-decimate Q] [--json]

Runs the identification (baseline and augment loop, the bundled description) on each
estimation/validation pair (default: ``bags/ident-coulomb`` with ``bags/ident-coulomb-val`` and
``bags/ident-none-1`` with ``bags/ident-none-val``, the validation runs written by
``scripts/make_validation_bags.sh``) and prints per pair: the validation fit per output (free
run from the first validation sample, like the reference, and with the initial state estimated,
like the report), the largest relative error of ``M`` and ``D`` against the plant of
``truth.yaml``, the identification seconds, and the issue's reference figures
(:data:`REFERENCE`: a multiple-shooting fit of the same grey box told the friction structure,
and this identifier before the fit-rate fix) with the targets: validation fit no worse, ``M``
and ``D`` within 2 %, at least twice as fast.

Misspecified Monte Carlo (``--monte-carlo N --coloured [--ar 0.9] [--unmodelled 0.02]``): the
same records with AR(1) output noise (coefficient ``ar`` per sample, the same standard
deviation) and an unmodelled Coulomb friction on the first output (``unmodelled`` x the RMS
input force) that the fitted structure does not have. The estimates then converge to the
pseudo-true values (the structure's best fit to the noise-free record), and ``coverage_95`` is
counted for them (target 90-97 %; for information also for the nominal values). The printed
``crlb_std`` is the white-noise bound, not the bound of the coloured noise.

Wall times depend on the machine's load: the load average before and after, and this process's
CPU time of the bag reading, the baseline and the loop, are printed too.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from scipy.signal import max_len_seq

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, load_description
from dvt_identify.errors import BenchError, DvtIdentifyError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.simloop import warm_up
from dvt_identify.simulation import OEModel
from dvt_model.errors import DvtModelError

Array = NDArray[np.float64]

TARGET_BASELINE_SECONDS = 2.0
TARGET_LOOP_SECONDS = 30.0
TARGET_CRLB_RATIO = 1.2
TARGET_COVERAGE = (0.93, 0.97)

DEFAULT_ESTIMATION = "ident-none-1"
"""The committed recording used for estimation by default (in the repository's ``bags/``)."""
DEFAULT_VALIDATION = "ident-none-2"
"""The committed recording used for validation by default."""

Log = Callable[[str], None]


BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def blas_env() -> dict[str, str | None]:
    """The BLAS/OpenMP thread-count variables of this process's environment."""
    return {key: os.environ.get(key) for key in BLAS_ENV}


def _quiet(_msg: str) -> None:
    return None


def _stderr(msg: str) -> None:
    print(f"[dvt-bench identify] {msg}", file=sys.stderr, flush=True)


def _load() -> list[float]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on Linux
        return []


# ---------------------------------------------------------------------------------------------
# Recordings


def default_bag(name: str, option: str) -> Path:
    """The committed recording ``bags/<name>``: looked up in the working directory and its
    parents, then beside this package's source tree.

    Raises:
        BenchError: not found (naming ``option``, which gives the bag explicitly).
    """
    here = Path(__file__).resolve()
    for root in (Path.cwd(), *Path.cwd().parents, *here.parents):
        cand = root / "bags" / name
        if (cand / "metadata.yaml").is_file():
            return cand
    raise BenchError(f"{option}: no default recording bags/{name} found from {Path.cwd()} "
                     "(give the bag directories explicitly)")


def prefix_copy(src: Path, dst: Path, seconds: float | None) -> dict[str, Any]:
    """``src`` itself, or its first ``seconds`` [s] written to ``dst`` (the two sample topics
    only, :func:`dvt_model.recording.write_run`).

    Returns:
        ``{"path", "source", "samples", "seconds", "rate_hz", "write_seconds"}``.

    Raises:
        BenchError: ``seconds`` leaves fewer than 2 samples.
    """
    from dvt_model.recording import read_run, read_truth, write_run

    run = read_run(src)
    n_all = int(run.t.size)
    rate = (n_all - 1) / float(run.t[-1] - run.t[0]) if n_all > 1 else math.nan
    if seconds is None:
        return {"path": str(src), "source": str(src), "samples": n_all,
                "seconds": float(run.t[-1] - run.t[0]) if n_all else 0.0, "rate_hz": rate,
                "write_seconds": 0.0}
    n = int(np.searchsorted(run.t - run.t[0], seconds, side="right"))
    if n < 2:
        raise BenchError(f"--seconds: {seconds} s leaves {n} sample(s) of {src}")
    t0 = time.perf_counter()
    write_run(dst, run.stamps_ns[:n], run.speeds[:n], run.currents[:n], truth=read_truth(src))
    return {"path": str(dst), "source": str(src), "samples": n,
            "seconds": float(run.t[n - 1] - run.t[0]), "rate_hz": rate,
            "write_seconds": time.perf_counter() - t0}


def _recording_info(path: Path) -> dict[str, Any]:
    """What ``run.yaml`` beside a committed recording says about how it was made (experiment,
    parameter set, hidden preset), or ``{}``."""
    try:
        data = yaml.safe_load((Path(path) / "run.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    if not isinstance(data, dict):
        return {}
    exp = data.get("experiment")
    return {k: v for k, v in (("experiment", exp.get("name") if isinstance(exp, dict) else exp),
                              ("params", data.get("params")), ("hidden", data.get("hidden")))
            if v is not None}


# ---------------------------------------------------------------------------------------------
# Timing mode


def description_with(desc_name: str, work: Path, max_tries: int | None) -> str:
    """The description to use: ``desc_name`` itself, or a copy in ``work`` with
    ``fit.max_tries_per_round`` replaced (returns its path)."""
    if max_tries is None:
        return desc_name
    desc = load_description(desc_name)
    data = yaml.safe_load(desc.text)
    data.setdefault("fit", {})["max_tries_per_round"] = int(max_tries)
    path = work / f"{desc.name}-max-tries-{max_tries}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def _timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """``fn()``, its wall time [s] and this process's CPU time [s]."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def power_law_exponent(samples: Sequence[float], seconds: Sequence[float]) -> float | None:
    """Least-squares slope of ``log(seconds)`` over ``log(samples)`` (``None`` for < 2 points
    or a non-positive value)."""
    pts = [(n, s) for n, s in zip(samples, seconds, strict=True) if n > 0 and s > 0]
    if len({n for n, _ in pts}) < 2:
        return None
    x = np.log([n for n, _ in pts])
    y = np.log([s for _, s in pts])
    return float(np.polyfit(x, y, 1)[0])


def _fit_percent(fig: Any) -> dict[str, float]:
    return {n: float(v) for n, v in zip(fig.output_names, fig.fit_percent, strict=True)}


def run_timing(estimation: Sequence[str | Path] | None = None,
               validation: Sequence[str | Path] | None = None, seconds: float | None = None,
               description: str = "dvt", fit_decimate: int | None = None,
               starts: int | None = None, max_tries: int | None = None,
               scaling: Sequence[float] = (15.0, 30.0), loop: bool = True,
               keep: Path | None = None, log: Log = _quiet, verbose: bool = False
               ) -> dict[str, Any]:
    """Timing mode (module docstring); returns the figures.

    Args:
        estimation, validation: bag directories (``None``: the committed
            :data:`DEFAULT_ESTIMATION` / :data:`DEFAULT_VALIDATION`).
        seconds: use the first ``seconds`` [s] of each recording (``None``: all of it).
        description: description name or file.
        fit_decimate, starts: overrides passed to :func:`dvt_identify.pipeline.run` (``None``:
            the description's).
        max_tries: override of ``fit.max_tries_per_round`` (``None``: the description's).
        scaling: further lengths [s] timed with the baseline only (shorter than the used
            length of the recordings).
        loop: also time the augment loop.
        keep: copy bags (when cut) and reports to this new directory.
        log: progress lines.
        verbose: let :func:`dvt_identify.pipeline.run` print its progress on stderr.

    Raises:
        BenchError: a bad setting or a missing default recording.
    """
    from dvt_identify.pipeline import load_segments, run
    from dvt_identify.report import write_report

    if seconds is not None and not seconds > 0:
        raise BenchError(f"--seconds: expected > 0, got {seconds}")
    est_src = [Path(b) for b in estimation] if estimation else [
        default_bag(DEFAULT_ESTIMATION, "--estimation")]
    val_src = [Path(b) for b in validation] if validation else [
        default_bag(DEFAULT_VALIDATION, "--validation")]
    for b in (*est_src, *val_src):
        if not Path(b).is_dir():
            raise BenchError(f"--estimation/--validation: {b}: no such bag directory")
    load_before = _load()
    work = Path(tempfile.mkdtemp(prefix="dvt-bench-identify-"))
    try:
        desc_spec = description_with(description, work, max_tries)
        desc = load_description(desc_spec)

        def pair(secs: float | None) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
            tag = "all" if secs is None else f"{secs:g}s"
            log(f"recordings: {tag} of {[str(b) for b in est_src]} (estimation) and "
                f"{[str(b) for b in val_src]} (validation)")
            est = [prefix_copy(b, work / f"est-{i}-{tag}", secs) for i, b in enumerate(est_src)]
            val = [prefix_copy(b, work / f"val-{i}-{tag}", secs) for i, b in enumerate(val_src)]
            return est, val

        def identify(est: list[dict[str, Any]], val: list[dict[str, Any]], augment: bool,
                     out: str, plots: bool = True) -> tuple[Any, float, float]:
            return _timed(lambda: run([e["path"] for e in est], [v["path"] for v in val],
                                      work / out, desc_spec, augment=augment, starts=starts,
                                      fit_decimate=fit_decimate, quiet=not verbose,
                                      plots=plots))

        est, val = pair(seconds)
        n = sum(int(e["samples"]) for e in est)
        used = min(float(e["seconds"]) for e in est)
        log("timing: loading the compiled simulation kernels")
        _, jit_s, _ = _timed(warm_up)
        log("timing: reading both bags")
        _, read_s, read_cpu = _timed(lambda: load_segments(
            [e["path"] for e in est] + [v["path"] for v in val], desc))
        log("timing: baseline (pipeline.run, augment=False)")
        base, base_s, base_cpu = identify(est, val, False, "report-baseline")
        log(f"baseline: {base_s:.2f} s")
        log("timing: baseline without plots (pipeline.run, augment=False, plots=False)")
        _, base_np_s, _ = identify(est, val, False, "report-baseline-no-plots", plots=False)
        log("timing: report writing alone")
        _, report_s, _ = _timed(lambda: write_report(base, work / "report-again"))
        cfg = base.config
        out: dict[str, Any] = {
            "mode": "timing",
            "samples": n,
            "baseline_seconds": base.seconds,
            "loop_seconds": None,
            "baseline_end_to_end_seconds": base_s,
            "loop_end_to_end_seconds": None,
            "baseline_end_to_end_no_plots_seconds": base_np_s,
            "targets": {"baseline_seconds": TARGET_BASELINE_SECONDS,
                        "loop_seconds": TARGET_LOOP_SECONDS},
            "definitions": {
                "baseline_seconds": "dvt_identify.loop.identify without augmentation on the "
                                    "loaded recordings: checks, decimation, the baseline fit "
                                    "with its start guard, figures and residual analysis on "
                                    "estimation and validation data",
                "loop_seconds": "the same with the augment loop (scoring, refits, decisions)",
                "*_end_to_end_seconds": "dvt_identify.pipeline.run: read both bags, identify, "
                                        "write report.json, report.md and the plots",
                "baseline_end_to_end_no_plots_seconds": "the same without the PNG plots "
                                                        "(dvt-identify --no-plots)"},
            "settings": {"description": desc.name, "fit_decimate": cfg.fit_decimate,
                         "fit_samples": math.ceil(n / max(cfg.fit_decimate, 1)),
                         "starts": cfg.starts, "refit_starts": cfg.refit_starts,
                         "max_tries_per_round": cfg.max_tries_per_round,
                         "max_effects": cfg.max_effects, "alpha": cfg.alpha,
                         "min_validation_gain": cfg.min_validation_gain},
            "recording": {"seconds": used, "rate_hz": est[0]["rate_hz"], "samples": n,
                          "estimation": [e["source"] for e in est],
                          "validation": [v["source"] for v in val],
                          "cut_to_seconds": seconds,
                          "made_by": _recording_info(est_src[0]),
                          "write_seconds": sum(e["write_seconds"] for e in est + val),
                          "validation_samples": sum(int(v["samples"]) for v in val)},
            "breakdown": {"jit_load_seconds": jit_s,
                          "read_both_bags_seconds": read_s, "read_cpu_seconds": read_cpu,
                          "baseline_end_to_end_cpu_seconds": base_cpu,
                          "baseline_fit_seconds": base.baseline.fit.seconds_,
                          "baseline_fit_starts": [
                              {"cost": s.cost, "nfev": s.nfev, "note": s.note}
                              for s in base.baseline.fit.starts_],
                          "report_seconds": report_s},
            "fit": {"baseline_validation_fit_percent": _fit_percent(base.baseline.val),
                    "baseline_estimation_fit_percent": _fit_percent(base.baseline.est),
                    "baseline_model_effects": [e.label() for e in base.baseline.effects]},
        }
        if loop:
            log("timing: augment loop (pipeline.run, augment=True)")
            res, loop_s, loop_cpu = identify(est, val, True, "report-loop")
            log(f"loop: {loop_s:.2f} s")
            out["loop_seconds"] = res.seconds
            out["loop_end_to_end_seconds"] = loop_s
            out["breakdown"].update({"loop_end_to_end_cpu_seconds": loop_cpu,
                                     "loop_refits": len(res.decisions),
                                     "loop_rounds": len(res.rounds)})
            out["fit"].update({
                "loop_validation_fit_percent": _fit_percent(res.final.val),
                "accepted": [d.score.label for d in res.accepted],
                "decisions": [{"candidate": d.score.label, "accepted": d.accepted,
                               "reason": d.reason} for d in res.decisions]})
        points = []
        for secs in sorted({float(s) for s in scaling if 0 < float(s) < used}):
            e2, v2 = pair(secs)
            log(f"timing: baseline on {secs:g} s")
            r2, s2, c2 = identify(e2, v2, False, f"report-baseline-{secs:g}s")
            points.append({"seconds": secs, "samples": sum(int(e["samples"]) for e in e2),
                           "baseline_seconds": r2.seconds, "end_to_end_seconds": s2,
                           "end_to_end_cpu_seconds": c2,
                           "fit_seconds": r2.baseline.fit.seconds_,
                           "fit_nfev": sum(s.nfev for s in r2.baseline.fit.starts_)})
        points.append({"seconds": used, "samples": n, "baseline_seconds": base.seconds,
                       "end_to_end_seconds": base_s, "end_to_end_cpu_seconds": base_cpu,
                       "fit_seconds": base.baseline.fit.seconds_,
                       "fit_nfev": sum(s.nfev for s in base.baseline.fit.starts_)})
        out["scaling"] = points
        ns = [p["samples"] for p in points]
        out["scaling_exponent"] = power_law_exponent(ns, [p["baseline_seconds"] for p in points])
        out["scaling_exponent_end_to_end"] = power_law_exponent(
            ns, [p["end_to_end_seconds"] for p in points])
        out["scaling_exponent_fit"] = power_law_exponent(ns, [p["fit_seconds"] for p in points])
        out["scaling_note"] = ("each point is a prefix of the same recordings; exponent = slope "
                               "of log time over log samples (1 = linear); a short prefix may "
                               "leave out the gear phases and with them the band model")
        out["meets_targets"] = {
            "baseline_seconds": out["baseline_seconds"] <= TARGET_BASELINE_SECONDS,
            "loop_seconds": (None if out["loop_seconds"] is None
                             else out["loop_seconds"] <= TARGET_LOOP_SECONDS),
            "baseline_end_to_end_seconds": base_s <= TARGET_BASELINE_SECONDS,
            "loop_end_to_end_seconds": (None if out["loop_end_to_end_seconds"] is None
                                        else out["loop_end_to_end_seconds"]
                                        <= TARGET_LOOP_SECONDS)}
        out["load_average"] = {"before": load_before, "after": _load()}
        out["cpu_count"] = os.cpu_count()
        out["blas_env"] = blas_env()
        if keep is not None:
            shutil.copytree(work, keep)
            out["kept"] = str(keep)
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


# ---------------------------------------------------------------------------------------------
# Comparison mode (--compare)

COMPARE_PAIRS: tuple[tuple[str, str], ...] = (("ident-coulomb", "ident-coulomb-val"),
                                              ("ident-none-1", "ident-none-val"))
"""Estimation / validation recordings of ``--compare`` (``bags/``; the validation runs are
second runs of the same plant preset, ``scripts/make_validation_bags.py``)."""

REFERENCE: dict[str, dict[str, Any]] = {
    "ident-coulomb": {"validation_fit_percent": [98.87, 98.69], "M_error_percent": 1.0,
                      "D_error_percent": None, "fit_seconds": 19.9,
                      "before": {"validation_fit_percent": [97.62, 98.19],
                                 "M_error_percent": 7.0, "fit_seconds": 7.7}},
    "ident-none-1": {"validation_fit_percent": [98.89, 98.74], "M_error_percent": None,
                     "D_error_percent": None, "fit_seconds": 21.7,
                     "before": {"validation_fit_percent": [97.92, 98.41],
                                "D_error_percent": 9.0, "fit_seconds": 2.2}},
}
"""The issue's reference: a multiple-shooting fit of the same grey box (CasADi + IPOPT, 10 ms
shooting nodes, exact Hessian) told the friction structure, validated by free-run simulation
from the first validation sample; ``before``: this identifier before the fit-rate fix."""
TARGET_MD_ERROR_PERCENT = 2.0


def truth_md(bag: Path) -> tuple[Array, Array]:
    """The plant's ``M`` and ``D`` of a simulated recording (its ``truth.yaml`` parameter
    set, :class:`dvt_model.hybrid.HybridModel`).

    Raises:
        BenchError: no readable ``truth.yaml``.
    """
    from dvt_model.hybrid import HybridModel
    from dvt_model.params import load_parameters

    try:
        truth = yaml.safe_load((Path(bag) / "truth.yaml").read_text()) or {}
        params = str(truth["plant"]["params"])
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise BenchError(f"{bag}: no plant parameter set in truth.yaml ({exc})") from exc
    rigid = HybridModel.from_params(load_parameters(params)).rigid
    return np.asarray(rigid.M, float), np.asarray(rigid.D, float)


def _md(params: dict[str, float]) -> tuple[Array, Array] | None:
    try:
        M = np.array([[params["M11"], params["M12"]], [params["M12"], params["M22"]]])
        D = np.array([[params["D11"], params["D12"]], [params["D12"], params["D22"]]])
    except KeyError:
        return None
    return M, D


def compare_one(est_bag: Path, val_bag: Path, description: str = "dvt",
                starts: int | None = None, fit_decimate: int | None = None,
                log: Log = _quiet) -> dict[str, Any]:
    """Identify (baseline and augment loop) from ``est_bag``, validate on ``val_bag``; the
    validation fit per output twice (initial state estimated as the report does, and free
    run from the first validation sample as the reference), ``M``/``D`` errors against the
    plant's truth (largest relative error over the entries) and the time."""
    from dvt_identify.loop import identify
    from dvt_identify.metrics import figures
    from dvt_identify.pipeline import (
        drop_unexcited_model_effects,
        load_segments,
        loop_config,
    )

    desc = load_description(description)
    est = load_segments([est_bag], desc)
    val = load_segments([val_bag], desc)
    desc, _ = drop_unexcited_model_effects(desc, est)
    cfg = loop_config(desc, True, starts, fit_decimate)
    log(f"compare: {est_bag.name} -> {val_bag.name}")
    res, wall, cpu = _timed(lambda: identify(est, val, desc, cfg))
    fin = res.final
    fit = fin.fit
    free = [fit.model.simulate(fit.theta_, s, s.y[0].copy()) for s in val]
    ffree = figures([s.y for s in val], free, fit.n_estimated_, val[0].output_names)
    out: dict[str, Any] = {
        "estimation": str(est_bag), "validation": str(val_bag),
        "validation_fit_percent": _fit_percent(fin.val),
        "validation_fit_percent_free_run": _fit_percent(ffree),
        "baseline_validation_fit_percent": _fit_percent(res.baseline.val),
        "accepted": [d.score.label for d in res.accepted],
        "seconds": res.seconds, "wall_seconds": wall, "cpu_seconds": cpu,
        "baseline_fit_seconds": res.baseline.fit.seconds_,
        "fit_rate_hz": [1.0 / s.dt for s in est] if not res.notes else None,
        "baseline_suspect": list(res.baseline.fit.suspect_),
        "baseline_at_bounds": list(res.baseline.fit.at_bounds_),
        "notes": list(res.notes),
        "parameters": fin.parameters(),
    }
    md = _md(fin.parameters())
    try:
        Mt, Dt = truth_md(est_bag)
    except BenchError as exc:
        out["truth"] = str(exc)
        md = None
    if md is not None:
        M, D = md
        out["M_error_percent"] = float(100 * np.max(np.abs(M / Mt - 1)))
        out["D_error_percent"] = float(100 * np.max(np.abs(D / Dt - 1)))
    ref = REFERENCE.get(est_bag.name)
    if ref is not None:
        out["reference"] = ref
        rv = ref["validation_fit_percent"]
        ours = list(out["validation_fit_percent_free_run"].values())
        out["meets_targets"] = {
            "validation_fit_no_worse": bool(all(o >= r - 0.005 for o, r in
                                                zip(ours, rv, strict=True))),
            "M_D_within_2_percent": bool(md is not None
                                         and out["M_error_percent"] <= TARGET_MD_ERROR_PERCENT
                                         and out["D_error_percent"] <= TARGET_MD_ERROR_PERCENT),
            # on a loaded machine the wall time grows with the other processes; this process's
            # CPU time does not (the identification runs on one thread)
            "twice_as_fast": bool(min(res.seconds, cpu) <= 0.5 * float(ref["fit_seconds"]))}
    return out


def run_compare(pairs: Sequence[tuple[str | Path, str | Path]] | None = None,
                description: str = "dvt", starts: int | None = None,
                fit_decimate: int | None = None, log: Log = _quiet) -> dict[str, Any]:
    """Comparison mode: :func:`compare_one` for each (estimation, validation) pair (default
    :data:`COMPARE_PAIRS` in ``bags/``).

    Raises:
        BenchError: a missing recording.
    """
    load_before = _load()
    warm_up()
    todo = []
    for e, v in pairs or COMPARE_PAIRS:
        ep = Path(e) if Path(e).is_dir() else default_bag(str(e), "--compare")
        vp = Path(v) if Path(v).is_dir() else default_bag(str(v), "--compare")
        todo.append((ep, vp))
    rows = [compare_one(e, v, description, starts, fit_decimate, log) for e, v in todo]
    return {"mode": "compare", "runs": rows,
            "reference_method": "multiple shooting (CasADi + IPOPT, 10 ms nodes, exact "
                                "Hessian) of the same grey box told the friction structure; "
                                "free-run validation from the first validation sample",
            "load_average": {"before": load_before, "after": _load()},
            "cpu_count": os.cpu_count()}


def pretty_compare(res: dict[str, Any]) -> str:
    """Human-readable text of :func:`run_compare`."""
    lines = [f"comparison with the reference fit ({res['reference_method']})"]
    for r in res["runs"]:
        name = Path(r["estimation"]).name
        ref = r.get("reference") or {}
        vf = list(r["validation_fit_percent_free_run"].values())
        ve = list(r["validation_fit_percent"].values())
        lines.append(f"{name} -> {Path(r['validation']).name}: accepted "
                     f"{', '.join(r['accepted']) or 'none'}")
        lines.append("  validation fit (free run from the first sample) "
                     + " / ".join(f"{v:.2f}" for v in vf) + " %   (x0 estimated: "
                     + " / ".join(f"{v:.2f}" for v in ve) + " %)")
        if ref:
            rv = ref["validation_fit_percent"]
            lines.append("  reference " + " / ".join(f"{v:.2f}" for v in rv) + " %, before "
                         + " / ".join(f"{v:.2f}" for v in ref["before"]["validation_fit_percent"])
                         + " %; unexplained error ours/reference "
                         + " / ".join(f"{(100 - o) / (100 - v):.2f}" for o, v in
                                      zip(vf, rv, strict=True)))
        lines.append(f"  M error {_num(r.get('M_error_percent'), '.2f')} %, D error "
                     f"{_num(r.get('D_error_percent'), '.2f')} % (target <= "
                     f"{TARGET_MD_ERROR_PERCENT:g} %; reference M "
                     f"{_num(ref.get('M_error_percent'), 'g')} %)")
        lines.append(f"  identify {r['seconds']:.1f} s wall, {r['cpu_seconds']:.1f} s CPU "
                     f"(baseline fit "
                     f"{r['baseline_fit_seconds']:.1f} s), reference "
                     f"{_num(ref.get('fit_seconds'), 'g')} s, before "
                     f"{_num(ref.get('before', {}).get('fit_seconds'), 'g')} s")
        if r["baseline_suspect"]:
            lines.append("  suspect baseline: " + "; ".join(r["baseline_suspect"]))
        if "meets_targets" in r:
            lines.append("  targets: " + ", ".join(f"{k} {'yes' if v else 'NO'}"
                                                    for k, v in r["meets_targets"].items()))
    lines.append(f"load average {res['load_average']['before']} -> "
                 f"{res['load_average']['after']}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Monte Carlo mode


def prbs(n_bits: int, order: int, seed: int, stream: int = 0) -> Array:
    """``n_bits`` values of a maximum-length binary sequence in {-1, +1} (period
    ``2**order - 1``); ``seed`` and ``stream`` choose its starting state (the generator of the
    driver's experiments, so the same seeds give the same sequence).

    Raises:
        BenchError: ``order`` outside 3..24.
    """
    if not 3 <= order <= 24:
        raise BenchError(f"PRBS order: expected 3..24, got {order}")
    state = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(stream)]).integers(0, 2, order)
    if not state.any():
        state[0] = 1
    seq, _ = max_len_seq(order, state=state, length=n_bits)
    return np.asarray(seq, dtype=np.float64) * 2.0 - 1.0


def mc_input(desc: Description, seconds: float, rate_hz: float, amplitude: float = 2.5,
             clock: float = 0.03, seed: int = 0) -> Segment:
    """A segment (outputs zero) with a PRBS of +-``amplitude`` (clock ``clock`` [s]) on every
    input the structure's ``B`` uses (independent sequences), other inputs 0; shape (N, nu)
    with ``N = round(seconds * rate_hz)``.

    Raises:
        BenchError: the structure uses no input, or the record is too short.
    """
    n = round(seconds * rate_hz)
    if n < 50:
        raise BenchError(f"--mc-seconds/--mc-rate: {n} samples are too few (need >= 50)")
    theta = np.array([p.initial for p in desc.structure.params], dtype=float)
    _, B, _ = desc.structure.matrices(theta)
    used = {name for j, name in enumerate(desc.input_names) if np.any(B[:, j] != 0.0)}
    if not used:
        raise BenchError(f"{desc.source}: the structure's B uses no input")
    t = np.arange(n) / rate_hz
    idx = np.floor(t / clock + 1e-9).astype(int)
    u = np.zeros((n, len(desc.input_names)))
    for j, name in enumerate(desc.input_names):
        if name in used:
            u[:, j] = amplitude * prbs(int(idx[-1]) + 1, 8, seed, 100 + j)[idx]
    return make_segment("monte-carlo", t, u, np.zeros((n, len(desc.output_names))),
                        desc.input_names, desc.output_names)


def output_sensitivity(model: OEModel, theta: Array, seg: Segment, x0: Array, scale: Array,
                       rel_step: float = 1e-5) -> Array:
    """Central-difference sensitivity of the simulated outputs divided by ``scale`` (ny,) to
    the parameters and the initial state; shape (N * ny, p + nx), rows like ``y.ravel()``."""
    cols = []

    def sim(th: Array, x: Array) -> Array:
        return np.asarray((model.simulate(th, seg, x) / scale).ravel())
    for i in range(theta.size):
        h = rel_step * max(abs(float(theta[i])), 1e-8)
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((sim(tp, x0) - sim(tm, x0)) / (2 * h))
    ys = model.simulate(theta, seg, x0)
    for j in range(x0.size):
        h = rel_step * max(float(np.std(ys[:, j])), 1e-8)
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        cols.append((sim(theta, xp) - sim(theta, xm)) / (2 * h))
    return np.column_stack(cols)


def crlb_std(jac: Array, n_params: int) -> Array:
    """Cramér-Rao standard deviations of the first ``n_params`` unknowns from the
    noise-normalised sensitivity ``jac`` (m, q): ``sqrt(diag((J^T J)^-1))``, shape
    (n_params,); the remaining unknowns (initial states) are nuisance parameters."""
    fisher = jac.T @ jac
    cov = np.linalg.pinv(fisher, rcond=1e-15, hermitian=True)
    return np.asarray(np.sqrt(np.diag(cov)[:n_params]))


_WORKER_DESC: dict[str, Description] = {}


def coloured_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: Array,
                   ar: float) -> Array:
    """AR(1) noise ``e[k] = ar e[k-1] + w[k]`` per column, stationary, with standard
    deviation ``sigma`` (ny,); ``ar = 0`` is white noise. Shape ``shape`` (N, ny)."""
    from scipy.signal import lfilter

    w = rng.standard_normal(shape)
    if ar == 0.0:
        return np.asarray(w * sigma)
    e0 = w[0] / math.sqrt(1.0 - ar * ar)  # start in the stationary distribution
    rest, _ = lfilter([1.0], [1.0, -ar], w[1:], axis=0, zi=(ar * e0)[None, :])
    e = np.vstack([e0[None, :], rest])
    return np.asarray(e * math.sqrt(1.0 - ar * ar) * sigma)


def _mc_one(job: tuple[str, int, int, Array, Array, Array, Array, int, float]
            ) -> dict[str, Any]:
    """One Monte Carlo run (in a worker process): noise, fit, estimates."""
    desc_spec, seed, run, t, u, y_clean, sigma, starts, ar = job
    desc = _WORKER_DESC.get(desc_spec)
    if desc is None:
        desc = _WORKER_DESC.setdefault(desc_spec, load_description(desc_spec))
    rng = np.random.default_rng([int(seed), int(run)])
    y = y_clean + coloured_noise(rng, y_clean.shape, sigma, ar)
    seg = make_segment(f"monte-carlo-{run}", t, u, y, desc.input_names, desc.output_names)
    model = OEModel(desc.structure, ())
    t0 = time.perf_counter()
    try:
        fit = OEFit(model, starts=starts, seed=int(seed) + run).fit([seg])
    except FitError as exc:
        return {"run": run, "error": str(exc)}
    return {"run": run, "theta": fit.theta_.tolist(), "std": fit.std_.tolist(),
            "x0": fit.x0_[0].tolist(), "cost": fit.cost_, "seconds": time.perf_counter() - t0,
            "nfev": sum(s.nfev for s in fit.starts_)}


def _with_unmodelled(desc: Description, model: OEModel, theta: Array, seg: Segment,
                     size: float) -> tuple[Array, str]:
    """The noise-free record of ``model`` plus an unmodelled Coulomb friction on the first
    output's member of ``size`` x the RMS input force there; returns (outputs, text)."""
    from dvt_identify.effects import make_effect

    st = desc.structure
    _, B, F = st.matrices(theta[: model.n_struct])
    force = seg.u @ B.T
    g = np.linalg.solve(F, force.T).T[:, 0]
    fc = float(size * np.sqrt(np.mean(g ** 2)))
    eff = make_effect("coulomb_friction", st.state_names[0], st.state_names, st.input_names,
                      suffix="_unmodelled", options={"offset": False})
    true_model = OEModel(st, (eff,))
    y = true_model.simulate(np.concatenate([theta, [fc]]), seg, np.zeros(model.nx))
    return y, (f"Coulomb friction {fc:.4g} {st.force_unit} on {st.state_names[0]} "
               f"({size:g} x the RMS input force), not in the fitted model")


def run_monte_carlo(runs: int = 50, seconds: float = 10.0, rate_hz: float = 500.0,
                    noise: float = 0.05, workers: int = 2, seed: int = 0,
                    description: str = "dvt", starts: int | None = None,
                    log: Log = _quiet, coloured: bool = False, ar: float = 0.9,
                    unmodelled: float = 0.02) -> dict[str, Any]:
    """Monte Carlo mode (module docstring); returns the figures.

    Args:
        runs: number of simulated records N.
        seconds, rate_hz: record length [s] and sample rate [Hz].
        noise: output noise standard deviation as a fraction of each noise-free output's std.
        workers: worker processes (1: in this process).
        seed: seed of the input PRBS and of the noise (run r uses ``[seed, r]``).
        description: description whose structure (no effects) is the true model.
        starts: starts of each fit (``None``: the description's).
        log: progress lines.
        coloured: the misspecified mode: AR(1) output noise with coefficient ``ar`` (per
            sample) and an unmodelled Coulomb friction of ``unmodelled`` x the RMS input
            force on the first output. Coverage is then counted for the pseudo-true values
            (the structure's best fit to the noise-free record, which the estimates converge
            to) and, for information, for the nominal ones.

    Raises:
        BenchError: bad settings.
    """
    if coloured and not 0.0 <= ar < 1.0:
        raise BenchError(f"--ar: expected 0 <= ar < 1, got {ar}")
    if runs < 2:
        raise BenchError(f"--monte-carlo: expected N >= 2, got {runs}")
    if not noise > 0:
        raise BenchError(f"--noise: expected > 0, got {noise}")
    t_start = time.perf_counter()
    load_before = _load()
    desc = load_description(description)
    model = OEModel(desc.structure, ())
    theta = model.initial()
    nx = model.nx
    x0 = np.zeros(nx)
    seg = mc_input(desc, seconds, rate_hz, seed=seed)
    y_clean = model.simulate(theta, seg, x0)
    theta_nominal = theta.copy()
    unmodelled_text = ""
    if coloured:
        y_clean, unmodelled_text = _with_unmodelled(desc, model, theta, seg, unmodelled)
        try:
            pseudo = OEFit(model, starts=1, theta0=theta).fit([replace(seg, y=y_clean)])
        except FitError as exc:
            raise BenchError(f"--coloured: no pseudo-true fit: {exc}") from exc
        theta = pseudo.theta_.copy()
    else:
        ar = 0.0
    sigma = noise * np.std(y_clean, axis=0)
    if not np.all(sigma > 0):
        raise BenchError(f"{desc.source}: an output does not move under the PRBS input "
                         f"(std {np.std(y_clean, axis=0).tolist()})")
    jac = output_sensitivity(model, theta, replace(seg, y=y_clean), x0, sigma)
    bound = crlb_std(jac, theta.size)
    n_starts = desc.fit.starts if starts is None else max(1, int(starts))
    jobs = [(description, seed, r, seg.t, seg.u, y_clean, sigma, n_starts, ar)
            for r in range(runs)]
    log(f"Monte Carlo: {runs} runs of {seg.n} samples, {workers} worker(s)")
    results: list[dict[str, Any]] = []
    if workers > 1:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for i, res in enumerate(pool.map(_mc_one, jobs)):
                results.append(res)
                if (i + 1) % 10 == 0:
                    log(f"  {i + 1}/{runs} runs done")
    else:
        for i, job in enumerate(jobs):
            results.append(_mc_one(job))
            if (i + 1) % 10 == 0:
                log(f"  {i + 1}/{runs} runs done")
    ok = [r for r in results if "theta" in r]
    failed = [{"run": r["run"], "error": r["error"]} for r in results if "theta" not in r]
    names = list(model.names)
    params: dict[str, dict[str, Any]] = {}
    if ok:
        est = np.array([r["theta"] for r in ok])
        rep = np.array([r["std"] for r in ok])
        mean = est.mean(axis=0)
        std = est.std(axis=0, ddof=1) if len(ok) > 1 else np.full(theta.size, math.nan)
        inside = np.abs(est - theta) <= 1.96 * rep
        inside_nominal = np.abs(est - theta_nominal) <= 1.96 * rep
        for i, name in enumerate(names):
            params[name] = {
                "true": float(theta[i]), "mean": float(mean[i]), "std": float(std[i]),
                "crlb_std": float(bound[i]), "crlb_ratio": float(std[i] / bound[i]),
                "bias": float(mean[i] - theta[i]),
                "bias_over_crlb": float((mean[i] - theta[i]) / bound[i]),
                "reported_std_mean": float(rep[:, i].mean()),
                "reported_over_crlb": float(rep[:, i].mean() / bound[i]),
                "coverage_95": float(inside[:, i].mean()),
                "nominal": float(theta_nominal[i]),
                "coverage_95_nominal": float(inside_nominal[:, i].mean()),
                "unit": desc.structure.params[i].unit}
    ratios = [p["crlb_ratio"] for p in params.values()]
    covs = [p["coverage_95"] for p in params.values()]
    max_ratio = max(ratios) if ratios else math.nan
    mean_cov = float(np.mean(covs)) if covs else math.nan
    n_ok = len(ok)
    return {
        "mode": "monte_carlo",
        "runs": runs,
        "runs_ok": n_ok,
        "failed": failed,
        "seed": seed,
        "workers": workers,
        "blas_env": blas_env(),
        "model": {"description": desc.name,
                  "structure": f"{type(desc.structure).__name__} "
                               f"({', '.join(names)}), no effects",
                  "x0_true": x0.tolist(), "starts": n_starts},
        "record": {"seconds": seconds, "rate_hz": rate_hz, "samples": seg.n,
                   "input": "PRBS +-2.5 (input unit), clock 0.03 s, order 8, on "
                            + ", ".join(n for j, n in enumerate(desc.input_names)
                                        if np.any(seg.u[:, j])) + "; other inputs 0",
                   "noise_fraction": noise,
                   "noise": (f"AR(1) coefficient {ar:g} per sample" if coloured
                             else "white"),
                   "unmodelled": unmodelled_text or "none",
                   "true_values": ("pseudo-true: the structure's fit to the noise-free record"
                                   if coloured else "the model's"),
                   "noise_sigma": dict(zip(desc.output_names, sigma.tolist(), strict=True)),
                   "output_std_noise_free": dict(zip(desc.output_names,
                                                     np.std(y_clean, axis=0).tolist(),
                                                     strict=True))},
        "parameters": params,
        "max_crlb_ratio": max_ratio,
        "mean_coverage_95": mean_cov,
        "min_coverage_95": min(covs) if covs else math.nan,
        "max_coverage_95": max(covs) if covs else math.nan,
        "sampling_uncertainty": {
            "crlb_ratio_relative_se": 1.0 / math.sqrt(2.0 * max(n_ok - 1, 1)),
            "coverage_se_per_parameter": math.sqrt(0.95 * 0.05 / max(n_ok, 1))},
        "targets": {"crlb_ratio_max": TARGET_CRLB_RATIO, "coverage_95": list(TARGET_COVERAGE)},
        "meets_targets": {
            "crlb_ratio": bool(max_ratio <= TARGET_CRLB_RATIO),
            "coverage_95": bool(TARGET_COVERAGE[0] <= mean_cov <= TARGET_COVERAGE[1])},
        "fit_seconds_mean": float(np.mean([r["seconds"] for r in ok])) if ok else math.nan,
        "fit_nfev_mean": float(np.mean([r["nfev"] for r in ok])) if ok else math.nan,
        "wall_seconds": time.perf_counter() - t_start,
        "load_average": {"before": load_before, "after": _load()},
        "cpu_count": os.cpu_count(),
    }


# ---------------------------------------------------------------------------------------------
# Output


def _finite(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by ``None`` (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _num(v: Any, fmt: str = ".4g") -> str:
    return "-" if v is None else format(v, fmt) if isinstance(v, float) else str(v)


def pretty(res: dict[str, Any]) -> str:
    """Human-readable text of a result of :func:`run_timing` or :func:`run_monte_carlo`."""
    lines: list[str] = []
    if res.get("mode") == "compare":
        return pretty_compare(res)
    if res.get("mode") == "monte_carlo":
        rec = res["record"]
        lines.append(f"Monte Carlo: {res['runs_ok']}/{res['runs']} runs, {rec['samples']} "
                     f"samples each ({rec['seconds']:g} s at {rec['rate_hz']:g} Hz), noise "
                     f"{rec['noise_fraction']:g} x std ({rec.get('noise', 'white')}), seed "
                     f"{res['seed']}")
        if rec.get("unmodelled", "none") != "none":
            lines.append(f"unmodelled: {rec['unmodelled']}; true values: {rec['true_values']}")
        lines.append(f"{'param':8s} {'true':>12s} {'mean':>12s} {'std':>10s} {'crlb_std':>10s} "
                     f"{'ratio':>6s} {'bias/crlb':>9s} {'rep/crlb':>8s} {'cov95':>6s}")
        for name, p in res["parameters"].items():
            lines.append(f"{name:8s} {p['true']:12.5g} {p['mean']:12.5g} {p['std']:10.3g} "
                         f"{p['crlb_std']:10.3g} {p['crlb_ratio']:6.3f} "
                         f"{p['bias_over_crlb']:9.3f} {p['reported_over_crlb']:8.3f} "
                         f"{p['coverage_95']:6.3f}"
                         + (f"  (nominal {p['coverage_95_nominal']:.3f})"
                            if rec.get("unmodelled", "none") != "none" else ""))
        su = res["sampling_uncertainty"]
        lines.append(f"max crlb_ratio {_num(res['max_crlb_ratio'])} (target <= "
                     f"{TARGET_CRLB_RATIO}; +-{100 * su['crlb_ratio_relative_se']:.0f} % "
                     f"sampling), mean coverage_95 {_num(res['mean_coverage_95'])} (target "
                     f"{TARGET_COVERAGE[0]}-{TARGET_COVERAGE[1]}; +-"
                     f"{su['coverage_se_per_parameter']:.3f} per parameter)")
        lines.append(f"failed runs {len(res['failed'])}, fit {res['fit_seconds_mean']:.2f} s "
                     f"mean, wall {res['wall_seconds']:.1f} s with {res['workers']} worker(s)")
        return "\n".join(lines)
    st = res["settings"]
    rec = res["recording"]
    lines.append(f"recording: {', '.join(rec['estimation'])} (estimation), "
                 f"{', '.join(rec['validation'])} (validation)")
    lines.append(f"  {res['samples']} samples ({rec['seconds']:g} s at "
                 f"{rec['rate_hz']:g} Hz), description {st['description']}, "
                 f"fit_decimate {st['fit_decimate']}, starts {st['starts']}, "
                 f"max_tries_per_round {st['max_tries_per_round']}")
    lines.append(f"baseline_seconds {_num(res['baseline_seconds'], '.2f')} (target <= "
                 f"{TARGET_BASELINE_SECONDS:g})   loop_seconds "
                 f"{_num(res['loop_seconds'], '.2f')} (target <= {TARGET_LOOP_SECONDS:g})")
    lines.append(f"end to end (bags in, report out): baseline "
                 f"{_num(res['baseline_end_to_end_seconds'], '.2f')} s "
                 f"({_num(res['baseline_end_to_end_no_plots_seconds'], '.2f')} s without plots), "
                 f"loop {_num(res['loop_end_to_end_seconds'], '.2f')} s")
    for k, v in res["breakdown"].items():
        if not isinstance(v, list):
            lines.append(f"  {k:28s} {_num(v)}")
    for k, v in res["fit"].items():
        if k != "decisions":
            lines.append(f"  {k:34s} {v}")
    for p in res["scaling"]:
        lines.append(f"  scaling: {p['samples']:7d} samples  baseline {p['baseline_seconds']:.2f} s"
                     f"  end to end {p['end_to_end_seconds']:.2f} s  fit {p['fit_seconds']:.2f} s"
                     f"  ({p['fit_nfev']} evaluations)")
    lines.append(f"scaling exponent {_num(res['scaling_exponent'], '.2f')} (baseline), "
                 f"{_num(res['scaling_exponent_end_to_end'], '.2f')} (end to end), "
                 f"{_num(res['scaling_exponent_fit'], '.2f')} (fit alone); load average "
                 f"{res['load_average']['before']} -> {res['load_average']['after']}")
    return "\n".join(lines)


def _seconds_list(text: str) -> list[float]:
    if not text.strip() or text.strip().lower() == "none":
        return []
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected seconds like 15,30, got {text!r}") from exc


def main(argv: Sequence[str] | None = None) -> int:
    """``dvt-bench identify`` (argv without the ``identify`` word); returns the exit status."""
    p = argparse.ArgumentParser(prog="dvt-bench identify",
                                description="identifier speed (default) or statistics "
                                            "(--monte-carlo); prints what it measured")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--description", default="dvt", help="description name or file (dvt)")
    p.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo (0)")
    p.add_argument("--verbose", action="store_true", help="progress of every step on stderr")
    g = p.add_argument_group("timing mode")
    g.add_argument("--estimation", nargs="+", default=None, metavar="BAG",
                   help=f"estimation bag directories (default bags/{DEFAULT_ESTIMATION})")
    g.add_argument("--validation", nargs="+", default=None, metavar="BAG",
                   help=f"validation bag directories (default bags/{DEFAULT_VALIDATION})")
    g.add_argument("--seconds", type=float, default=None,
                   help="use the first SECONDS [s] of each recording (default: all)")
    g.add_argument("--scaling", type=_seconds_list, default=[15.0, 30.0],
                   help="shorter prefixes [s] for the scaling figure, e.g. 15,30 (none: skip)")
    g.add_argument("--fit-decimate", type=int, default=None,
                   help="override the description's fit_decimate")
    g.add_argument("--starts", type=int, default=None, help="override the baseline starts")
    g.add_argument("--max-tries", type=int, default=None,
                   help="override the description's fit.max_tries_per_round")
    g.add_argument("--no-loop", action="store_true", help="skip the augment loop")
    g.add_argument("--keep", default=None,
                   help="copy the cut bags and the reports to this new directory")
    c = p.add_argument_group("comparison mode")
    c.add_argument("--compare", nargs="*", default=None, metavar="EST=VAL",
                   help="identify and compare with the reference fit: estimation=validation "
                        "bag pairs (default: bags/ident-coulomb=bags/ident-coulomb-val "
                        "bags/ident-none-1=bags/ident-none-val)")
    m = p.add_argument_group("Monte Carlo mode")
    m.add_argument("--monte-carlo", type=int, nargs="?", const=50, default=None, metavar="N",
                   help="run N simulated fits (default N 50)")
    m.add_argument("--mc-seconds", type=float, default=10.0, help="record length [s] (10)")
    m.add_argument("--mc-rate", type=float, default=500.0, help="sample rate [Hz] (500)")
    m.add_argument("--noise", type=float, default=0.05,
                   help="output noise std as a fraction of the output's std (0.05)")
    m.add_argument("--coloured", action="store_true",
                   help="misspecified mode: AR(1) output noise and an unmodelled Coulomb "
                        "friction; coverage of the 95 %% intervals per parameter")
    m.add_argument("--ar", type=float, default=0.9,
                   help="AR(1) coefficient of the coloured noise per sample (0.9)")
    m.add_argument("--unmodelled", type=float, default=0.02,
                   help="unmodelled Coulomb friction as a fraction of the RMS input force "
                        "(0.02)")
    m.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="worker processes (2)")
    args = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    if args.seed < 0:
        p.error(f"--seed: expected >= 0, got {args.seed}")
    if args.keep is not None and Path(args.keep).exists():
        p.error(f"--keep: {args.keep} already exists")
    for opt in ("fit_decimate", "starts", "max_tries"):
        v = getattr(args, opt)
        if v is not None and v < 1:
            p.error(f"--{opt.replace('_', '-')}: expected >= 1, got {v}")
    if args.workers < 1:
        p.error(f"--workers: expected >= 1, got {args.workers}")
    log = _quiet if args.json and not args.verbose else _stderr
    try:
        if args.compare is not None:
            pairs = []
            for item in args.compare:
                e, sep, v = item.partition("=")
                if not sep or not e or not v:
                    p.error(f"--compare: expected ESTIMATION=VALIDATION, got {item!r}")
                pairs.append((e, v))
            res = run_compare(pairs or None, args.description, args.starts, args.fit_decimate,
                              log)
        elif args.monte_carlo is not None:
            res = run_monte_carlo(args.monte_carlo, args.mc_seconds, args.mc_rate, args.noise,
                                  args.workers, args.seed, args.description, args.starts, log,
                                  coloured=args.coloured, ar=args.ar,
                                  unmodelled=args.unmodelled)
        else:
            res = run_timing(args.estimation, args.validation, args.seconds, args.description,
                             args.fit_decimate, args.starts, args.max_tries, args.scaling,
                             not args.no_loop, Path(args.keep) if args.keep else None, log,
                             args.verbose)
    except (DvtIdentifyError, DvtModelError, OSError) as exc:
        print(f"dvt-bench identify: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    res = _finite(res)
    print(json.dumps(res) if args.json else pretty(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
