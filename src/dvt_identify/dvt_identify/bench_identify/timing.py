"""Timing mode of ``dvt-bench identify``: how fast the identifier is on recordings (see
:mod:`dvt_identify.bench_identify`)."""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dvt_identify.bench_identify.common import (
    DEFAULT_ESTIMATION,
    DEFAULT_VALIDATION,
    Log,
    blas_env,
    default_bag,
    fit_percent,
    load_average,
    num,
    prefix_copy,
    quiet,
    recording_info,
    timed,
)
from dvt_identify.description import load_description
from dvt_identify.errors import BenchError
from dvt_identify.simloop import warm_up
from dvt_model.presets import safe_load

TARGET_BASELINE_SECONDS = 0.5
"""Target of ``baseline_seconds`` on the 38-s recording at 1 kHz (issue: fast again) [s]."""
TARGET_LOOP_SECONDS = 2.0
"""Target of ``loop_seconds`` on the same recording [s]."""


def description_with(desc_name: str, work: Path, max_tries: int | None) -> str:
    """The description to use: ``desc_name`` itself, or a copy in ``work`` with
    ``fit.max_tries_per_round`` replaced (returns its path)."""
    if max_tries is None:
        return desc_name
    desc = load_description(desc_name)
    data = safe_load(desc.text)
    data.setdefault("fit", {})["max_tries_per_round"] = int(max_tries)
    path = work / f"{desc.name}-max-tries-{max_tries}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def power_law_exponent(samples: Sequence[float], seconds: Sequence[float]) -> float | None:
    """Least-squares slope of ``log(seconds)`` over ``log(samples)`` (``None`` for < 2 points
    or a non-positive value)."""
    pts = [(n, s) for n, s in zip(samples, seconds, strict=True) if n > 0 and s > 0]
    if len({n for n, _ in pts}) < 2:
        return None
    x = np.log([n for n, _ in pts])
    y = np.log([s for _, s in pts])
    return float(np.polyfit(x, y, 1)[0])


def run_timing(estimation: Sequence[str | Path] | None = None,
               validation: Sequence[str | Path] | None = None, seconds: float | None = None,
               description: str = "dvt", fit_decimate: int | None = None,
               starts: int | None = None, max_tries: int | None = None,
               scaling: Sequence[float] = (15.0, 30.0), loop: bool = True,
               keep: Path | None = None, log: Log = quiet, verbose: bool = False
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
    load_before = load_average()
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
            return timed(lambda: run([e["path"] for e in est], [v["path"] for v in val],
                                      work / out, desc_spec, augment=augment, starts=starts,
                                      fit_decimate=fit_decimate, quiet=not verbose,
                                      plots=plots))

        est, val = pair(seconds)
        n = sum(int(e["samples"]) for e in est)
        used = min(float(e["seconds"]) for e in est)
        log("timing: loading the compiled simulation kernels")
        _, jit_s, _ = timed(warm_up)
        log("timing: reading both bags")
        _, read_s, read_cpu = timed(lambda: load_segments(
            [e["path"] for e in est] + [v["path"] for v in val], desc))
        log("timing: baseline (pipeline.run, augment=False)")
        base, base_s, base_cpu = identify(est, val, False, "report-baseline")
        log(f"baseline: {base_s:.2f} s")
        log("timing: baseline without plots (pipeline.run, augment=False, plots=False)")
        _, base_np_s, _ = identify(est, val, False, "report-baseline-no-plots", plots=False)
        log("timing: report writing alone")
        _, report_s, _ = timed(lambda: write_report(base, work / "report-again"))
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
                          "made_by": recording_info(est_src[0]),
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
            "fit": {"baseline_validation_fit_percent": fit_percent(base.baseline.val),
                    "baseline_estimation_fit_percent": fit_percent(base.baseline.est),
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
                "loop_validation_fit_percent": fit_percent(res.final.val),
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
        out["load_average"] = {"before": load_before, "after": load_average()}
        out["cpu_count"] = os.cpu_count()
        out["blas_env"] = blas_env()
        if keep is not None:
            shutil.copytree(work, keep)
            out["kept"] = str(keep)
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def pretty_timing(res: dict[str, Any]) -> str:
    """Human-readable text of :func:`run_timing`."""
    lines: list[str] = []
    st = res["settings"]
    rec = res["recording"]
    lines.append(f"recording: {', '.join(rec['estimation'])} (estimation), "
                 f"{', '.join(rec['validation'])} (validation)")
    lines.append(f"  {res['samples']} samples ({rec['seconds']:g} s at "
                 f"{rec['rate_hz']:g} Hz), description {st['description']}, "
                 f"fit_decimate {st['fit_decimate']}, starts {st['starts']}, "
                 f"max_tries_per_round {st['max_tries_per_round']}")
    lines.append(f"baseline_seconds {num(res['baseline_seconds'], '.2f')} (target <= "
                 f"{TARGET_BASELINE_SECONDS:g})   loop_seconds "
                 f"{num(res['loop_seconds'], '.2f')} (target <= {TARGET_LOOP_SECONDS:g})")
    lines.append(f"end to end (bags in, report out): baseline "
                 f"{num(res['baseline_end_to_end_seconds'], '.2f')} s "
                 f"({num(res['baseline_end_to_end_no_plots_seconds'], '.2f')} s without plots), "
                 f"loop {num(res['loop_end_to_end_seconds'], '.2f')} s")
    for k, v in res["breakdown"].items():
        if not isinstance(v, list):
            lines.append(f"  {k:28s} {num(v)}")
    for k, v in res["fit"].items():
        if k != "decisions":
            lines.append(f"  {k:34s} {v}")
    for p in res["scaling"]:
        lines.append(f"  scaling: {p['samples']:7d} samples  baseline {p['baseline_seconds']:.2f} s"
                     f"  end to end {p['end_to_end_seconds']:.2f} s  fit {p['fit_seconds']:.2f} s"
                     f"  ({p['fit_nfev']} evaluations)")
    lines.append(f"scaling exponent {num(res['scaling_exponent'], '.2f')} (baseline), "
                 f"{num(res['scaling_exponent_end_to_end'], '.2f')} (end to end), "
                 f"{num(res['scaling_exponent_fit'], '.2f')} (fit alone); load average "
                 f"{res['load_average']['before']} -> {res['load_average']['after']}")
    return "\n".join(lines)
