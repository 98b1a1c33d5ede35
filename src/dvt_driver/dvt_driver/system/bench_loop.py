"""``dvt-bench loop``: the self-closing loop on the simulated plant (``docs/loop.md``).

Without ``--with-identifier``: the change-detection benchmark of
:func:`dvt_driver.system.bench_detect.loop_main` (plant -> driver -> model node with its
detector; a change by SIGHUP).

With ``--with-identifier``: the whole loop as ``dvt-launch sim --supervise`` runs it
(:func:`episode_launch_args`): 1 kHz, the sample path in the real-time scheduler
(``--realtime`` :data:`REALTIME_PRIORITY`), the ``watch`` experiment (continuous neutral PRBS +
multisine), the model node with the plant's own parameters as its prior, a change injected at
plant time ``--change-at`` (``--change`` preset, default ``friction_step``), the identifier's
supervisor (short windows, :func:`live_supervisor`; the refit in its own process) and the ring
recorder; the run ends when an episode whose alarm follows the change is reported (or at
``--timeout``). The figures come from the ring's recording, the plant's ``truth.yaml``, the
episode report (:func:`analyse_episode`) and ``/proc`` (:class:`CpuSampler`)::

    dvt-bench loop --with-identifier [--rate 1000] [--change-at 50] [--change friction_step]
                   [--learn-s 10] [--seed 0] [--timeout 420] [--keep DIR] [--refit-nice N]
                   [--realtime P] [--json]

JSON: ``rate_hz``; ``detection_delay_s`` (first alarm after the change: detection stamp - true
change time), ``change_time_error_s``, ``restored_s`` (true change -> the first of
:data:`RESTORED_BINS` consecutive 1-s bins after the push whose residual RMS is within
:data:`RESTORED_FACTOR` x the clean level on both outputs), ``push_after_change_s``,
``realtime`` (the chain's priority asked for), ``outcome``, ``reason``, ``pushed``,
``rolled_back``, ``accepted``, ``stage`` / ``stages``
(the refits: stage, decision, accepted effects, seconds), ``refit_seconds`` (request to result)
and ``refit_cpu_seconds`` (the refit process's CPU time), ``refit_process``;
``false_alarms`` / ``clean_tested_s`` / ``false_alarms_per_hour`` (+ upper 95 % Poisson bound:
alarms before the change while the detector tested the clean plant); the chain's figures
(:func:`chain_figures`) from the ring's first residual to the episode's verdict (then the bench
stops the launcher; the shutdown's are ``after_verdict``): ``model_latency_ms`` (``p50``,
``p99``, ``max``: the ring recorder's reception of the residual minus its reception of the
sample with the same stamp, detector on), ``model_dropped`` (samples without a residual),
``chain_missing`` (samples missing from the ring's ``/dvt/joint_states``); the same from the
episode's first alarm (``model_latency_episode_ms``, ``episode_chain``) and while each refit ran
(``refit_chain``, ``model_dropped_refit``, ``chain_missing_refit``); ``cpu`` (each chain
process's CPU share and priority, the other processes'); ``residual_rms_clean`` / ``_changed``
(median 1-s RMS before the change / in its first 15 s) / ``_restored`` (the pushed model's,
push to verdict) [rad/s].
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dvt_driver.errors import LaunchError
from dvt_driver.run.processes import script
from dvt_driver.system.cpuload import CpuSampler
from dvt_driver.system.launch_args import IDENTIFY_DIR
from dvt_model.contract import (
    JOINT_STATES,
    MODEL_CHANGE,
    MODEL_RESIDUAL,
    RESET_DETECTOR_LOG,
    SPEED_NAMES,
)
from dvt_model.errors import DvtModelError
from dvt_model.recording import (
    BagMessages,
    changes_applied,
    decode,
    raw_stamp_ns,
    read_truth,
)
from dvt_model.recording.cdr import parse_joint_state
from dvt_model.recording.ring import segment_paths


def live_supervisor(rate: float = 1000.0, description: str = "dvt") -> dict[str, float | int]:
    """Supervisor settings of the live demo, tests and bench at controller rate ``rate`` [Hz]
    [s]: the first refit ``min_post_change_s`` after the change (from 0.5 s after it, the
    newest ``validation_s`` held out: 2.5 s to fit and 1 s to validate at 1 kHz, longer at a
    rate where that is fewer samples than the description's ``checks.min_samples`` needs per
    bag, with a fifth to spare; the structure held at the model in use), the full refit on 30 s
    (5 s held out) only if the first is not pushed; a 15-s watch against the (at most) 15 s
    before the push; a loaded model node answers its parameter services late (push timeout
    40 s)."""
    from dvt_identify.description import load_description

    need = 1.2 * load_description(description).checks.min_samples / rate  # [s]
    est = max(2.5, math.ceil(2.0 * need) / 2.0)
    val = max(1.0, math.ceil(2.0 * need) / 2.0)
    settle = 0.5
    return {"min_post_change_s": settle + est + val, "settle_s": settle, "validation_s": val,
            "full_post_change_s": 30.0, "full_validation_s": 5.0, "watch_s": 15.0,
            "watch_settle_s": 1.0, "baseline_s": 15.0, "push_timeout_s": 40.0,
            "fit_timeout_s": 180.0}


LIVE_SUPERVISOR = live_supervisor(1000.0)
"""The live settings at 1 kHz (:func:`live_supervisor`): the first refit 4 s after the
change."""
SNAPSHOT_MARGIN_S = 0.25
"""The ring recorder's ``snapshot_margin_s`` in the live runs [s]: how long after a window's
end its snapshot is written (the samples' way from the driver to the ring takes
milliseconds)."""
REALTIME_PRIORITY = 10
"""``dvt-launch --realtime`` of the live runs: the sample path (plant, driver, model node) at
``SCHED_RR`` 10, the ring at 9; the identifier and its refit process (niceness 19) stay in the
normal scheduler. Measured, ``dvt-bench model`` at 1 kHz on this 2-core machine with a load
average of 6 from other jobs: the model node's p99 latency 3.4-6.6 ms at niceness 0,
1.5-1.8 ms at niceness -10, 0.41-0.61 ms at ``SCHED_RR`` 10."""
DETECTOR_SETTLE_S = 5.0
"""The model node's ``detector.settle_s`` in the live runs [s]."""
PRINT_WAIT_S = 10.0
"""Longest wait [s] in :func:`run_episode`, after the episode's report file appeared, for the
launcher to print the record (the identifier writes the file, then publishes the record on
the contract's topic; the launcher polls its monitor every 0.1 s): a stop sent between the two
would cut the record from the launcher's log. About 0.1-0.5 s on this machine; the bound only
delays the stop."""

RESTORED_FACTOR = 1.5
"""The residual is back at the noise level when its 1-s RMS is within this factor of the
clean level (median 1-s RMS before the change) on both outputs."""
RESTORED_BINS = 3
"""... for this many consecutive 1-s bins."""


def episode_launch_args(logdir: Path, rate: float = 1000.0, change_at: float = 50.0,
                        change: str = "friction_step", duration: float = 240.0,
                        learn_s: float = 10.0, seed: int = 0, params: str = "physical",
                        realtime: int | None = REALTIME_PRIORITY,
                        refit_nice: int | None = None) -> list[str]:
    """``dvt-launch`` arguments (after the program) of one live-loop episode run.

    ``rate`` [Hz] the controller rate; ``change_at`` [s of plant time] when the ``change``
    preset (or hidden-effects YAML) is applied; ``duration`` [s] of the ``watch`` experiment;
    ``learn_s`` [s] the detector's reference window; the model node's prior is ``params``, the
    plant's own set. The ring records the samples and the residual (the refit's data and the
    figure's); the refit is decimated to about 100 Hz. ``realtime``: the chain's real-time
    priority (``dvt-launch --realtime``; ``None``: the normal scheduler); ``refit_nice``: the
    refit process's niceness (``None``: the launcher's choice, 0 with a real-time chain).
    """
    args = ["sim", "--params", params, "--hidden", "none", "--seed", str(seed),
            "--rate", f"{rate:g}", "--experiment", "watch", "--experiment-seed", str(seed),
            "--experiment-set", f"duration={duration:g}",
            "--change-at", f"{change_at:g}:{change}", "--supervise",
            "--ring-minutes", f"{max(5.0, (duration + 60.0) / 60.0):g}",
            "--ring-segment-seconds", "5",
            "--record-topics", JOINT_STATES, "/dvt/currents", MODEL_RESIDUAL,
            "--record-param", f"snapshot_margin_s:={SNAPSHOT_MARGIN_S!r}",
            "--model-param", f"detector.learn_s:={float(learn_s)!r}",
            "--model-param", f"detector.settle_s:={DETECTOR_SETTLE_S!r}",
            "--log-dir", str(logdir)]
    if realtime:
        args += ["--realtime", str(realtime)]
    for k, v in live_supervisor(rate).items():
        args += ["--identify-param", f"supervisor.{k}:={v!r}"]
    args += ["--identify-param", f"supervisor.fit_decimate:={max(1, round(rate / 100.0))}"]
    if refit_nice is not None:
        args += ["--identify-param", f"supervisor.refit_nice:={refit_nice}"]
    return args


def true_change(logdir: Path) -> float | None:
    """Host time [s] at which the plant applied its first change (``truth.yaml`` in
    ``logdir``), if any."""
    applied = changes_applied(read_truth(logdir))
    return float(applied[0]["unix_s"]) if applied else None


def episode_reports(directory: Path) -> list[Path]:
    """The episode reports the identifier writes (``episode-N.json``, also ``episode-N-K.json``
    of a later node) under ``<directory>/episodes``, in episode order."""
    def key(p: Path) -> tuple[int, ...]:
        return tuple(int(x) for x in p.stem.split("-")[1:] if x.isdigit())

    base = directory / "episodes"
    return sorted(base.glob("episode-*.json"), key=key) if base.is_dir() else []


def episodes(logdir: Path) -> list[dict[str, Any]]:
    """The episode reports the identifier wrote under ``<logdir>/identify/episodes``."""
    out = []
    for p in episode_reports(logdir / IDENTIFY_DIR):
        with contextlib.suppress(OSError, ValueError):
            out.append(json.loads(p.read_text()))
    return out


def change_episode(logdir: Path, tolerance_s: float = 2.0) -> dict[str, Any] | None:
    """The first finished episode with an alarm at most ``tolerance_s`` [s] before the true
    change or later (the one that handled the injected change), if any."""
    change = true_change(logdir)
    if change is None:
        return None
    for rec in episodes(logdir):
        if any(float(a.get("stamp_s", -math.inf)) >= change - tolerance_s
               for a in rec.get("alarms") or []):
            return rec
    return None


def run_episode(logdir: Path, launch_args: Sequence[str], timeout: float,
                env: dict[str, str] | None = None, log: Any = None,
                cpu: CpuSampler | None = None) -> int:
    """Run ``dvt-launch`` with ``launch_args`` until :func:`change_episode` finds the episode
    of the injected change and the launcher has printed it (at most :data:`PRINT_WAIT_S`
    later; then SIGINT: the launcher stops everything in order), the launcher ends, or
    ``timeout`` [s] (SIGINT, then SIGKILL of its process group). Returns the
    launcher's exit status (130 when stopped here). ``cpu``: a started sampler; the launcher's
    process tree is its chain, and it is stopped before the launcher is (its figures in
    ``cpu.figures``)."""
    logdir.mkdir(parents=True, exist_ok=True)
    out = (logdir / "launch.log").open("wb")
    proc = subprocess.Popen([script("dvt-launch"), *launch_args], stdout=out,
                            stderr=subprocess.STDOUT, env=env, start_new_session=True)
    if cpu is not None:
        cpu.set_root(proc.pid)
    deadline = time.monotonic() + timeout
    printed_by: float | None = None  # set once the episode's report file is there
    line = ""  # the launcher's print of that episode
    try:
        while proc.poll() is None:
            now = time.monotonic()
            if printed_by is None:
                rec = change_episode(logdir)
                if rec is not None:
                    printed_by = now + PRINT_WAIT_S
                    line = f"episode {rec.get('episode')}:"
            done = printed_by is not None and (
                now > printed_by or line in (logdir / "launch.log").read_text(errors="replace"))
            if done or now > deadline:
                if cpu is not None:
                    cpu.figures = cpu.stop()
                os.killpg(proc.pid, signal.SIGINT)
                try:
                    proc.wait(timeout=90.0)  # the launcher's own bounded stop of its children
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10.0)
                break
            time.sleep(0.5 if printed_by is None else 0.1)
    finally:
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10.0)
        out.close()
    if log is not None:
        print((logdir / "launch.log").read_text(errors="replace")[-3000:], file=log)
    return int(proc.returncode)


@dataclass
class EpisodeRun:
    """What a live episode run recorded (:func:`analyse_episode`); times are host time [s].

    ``bins``: start of each 1-s bin; ``rms``: (N, 2) live residual RMS per bin [rad/s] (NaN
    without samples); ``counts``: residual samples per bin; ``alarms``: the change alarms (the
    model node's JSON); ``change``: the true change time; ``episode``: its report;
    ``samples``: the stamps of the ``/dvt/joint_states`` samples the ring holds [s], sorted;
    ``latency_ms``: per sample, the ring's reception of its residual minus that of the sample
    [ms] (NaN: no residual for it, a sample the model node dropped); ``dropped``: how many;
    ``rearmed``: the launcher's re-arm of the detector (host time [s]) if any.
    """

    bins: np.ndarray
    rms: np.ndarray
    counts: np.ndarray
    alarms: list[dict[str, Any]]
    change: float | None
    episode: dict[str, Any] | None
    samples: np.ndarray
    latency_ms: np.ndarray
    dropped: int
    rearmed: float | None
    figures: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Ring:
    """What :func:`_read_ring` takes from the ring's segments."""

    res_stamps: np.ndarray  # residual stamps [s], sorted
    res_values: np.ndarray  # (N, 2) [rad/s]
    js_stamps: np.ndarray  # sample stamps [ns], sorted
    latency_ms: np.ndarray  # per sample: residual reception - sample reception [ms] (NaN)
    alarms: list[dict[str, Any]]


def _read_ring(ring: Path) -> _Ring:
    """The residual, the samples' and the residuals' reception times and the alarms, from
    every ring segment (a segment cut by a kill is read as far as it goes)."""
    stamps: list[int] = []
    values: list[tuple[float, ...]] = []
    res_at: dict[int, int] = {}
    js_at: dict[int, int] = {}
    alarms: list[dict[str, Any]] = []
    for seg in segment_paths(ring):
        try:
            with BagMessages(seg) as bag:
                wanted = [t for t in (JOINT_STATES, MODEL_RESIDUAL, MODEL_CHANGE)
                          if t in bag.types]
                for msg in bag.messages(wanted):
                    if msg.topic == MODEL_CHANGE:
                        with contextlib.suppress(ValueError, KeyError):
                            alarms.append(json.loads(decode(msg).data))
                        continue
                    try:
                        stamp = raw_stamp_ns(msg.data)
                    except ValueError:
                        continue
                    if msg.topic == JOINT_STATES:
                        js_at[stamp] = msg.log_time_ns
                    else:
                        fields_ = parse_joint_state(msg.data)
                        vel = dict(zip(fields_.names, fields_.velocity, strict=False))
                        stamps.append(stamp)
                        values.append(tuple(float(vel.get(n, math.nan)) for n in SPEED_NAMES))
                        res_at[stamp] = msg.log_time_ns
        except Exception:  # a segment cut by a kill: the others still count
            continue
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    st = np.asarray(stamps, dtype=np.int64)[order]
    val = np.asarray(values, dtype=float).reshape(-1, len(SPEED_NAMES))[order]
    js = np.asarray(sorted(js_at), dtype=np.int64)
    latency = np.asarray([(res_at[s] - js_at[s]) * 1e-6 if s in res_at else math.nan
                          for s in js.tolist()], dtype=float)
    return _Ring(st * 1e-9, val, js, latency, alarms)


def _rearm_time(logdir: Path) -> float | None:
    """Host time [s] of the launcher's re-arm: the model node's first log line of a reset
    through its ``reset_detector`` service (:data:`dvt_model.contract.RESET_DETECTOR_LOG`) in
    ``<logdir>/model.log``; ``None`` without one."""
    path = logdir / "model.log"
    if not path.exists():
        return None
    pattern = re.compile(r"\[(\d+\.\d+)\] \[[^]]*\]: " + re.escape(RESET_DETECTOR_LOG))
    for line in path.read_text(errors="replace").splitlines():
        m = pattern.search(line)
        if m:
            return float(m.group(1))
    return None


def chain_figures(samples_s: np.ndarray, latency_ms: np.ndarray, t0: float, t1: float,
                  period_s: float) -> dict[str, Any]:
    """The chain's figures over the samples stamped in ``[t0, t1)`` [s]: ``samples``,
    ``model_dropped`` (samples without a residual), ``chain_missing`` (samples missing from
    the ring's ``/dvt/joint_states``: stamp steps of more than 1.5 ``period_s`` [s], each
    counted as the samples it skips: what the plant, the driver or the ring lost) and
    ``model_latency_ms`` (``p50``, ``p99``, ``max`` of the residuals' latency [ms]; ``None``
    without any)."""
    k = (samples_s >= t0) & (samples_s < t1)
    st, lat = samples_s[k], latency_ms[k]
    steps = np.diff(st) / period_s
    missing = int(np.sum(np.round(steps[steps > 1.5]) - 1.0)) if st.size > 1 else 0
    ok = lat[np.isfinite(lat)]

    def pct(q: float) -> float | None:
        return round(float(np.percentile(ok, q)), 3) if ok.size else None

    return {"from_s": round(t0, 3), "to_s": round(t1, 3), "samples": int(st.size),
            "model_dropped": int(np.sum(~np.isfinite(lat))), "chain_missing": missing,
            "model_latency_ms": {"p50": pct(50), "p99": pct(99),
                                 "max": round(float(ok.max()), 3) if ok.size else None}}


def _refit_windows(rec: dict[str, Any]) -> list[tuple[float, float]]:
    """The refits of an episode record: from each ``refitting`` step to the next step [s]."""
    steps = [(float(s_["t"]), str(s_.get("state"))) for s_ in rec.get("steps") or []]
    return [(t, steps[i + 1][0]) for i, (t, state) in enumerate(steps[:-1])
            if state == "refitting"]


def analyse_episode(logdir: Path, learn_s: float = 10.0, rate: float | None = None
                    ) -> EpisodeRun:
    """Figures of a live episode run in ``logdir`` (see the module docstring); ``rate`` [Hz]
    the controller rate (``None``: from the samples' median stamp step)."""
    from dvt_driver.system.bench_detect import chi2_upper

    ring = _read_ring(logdir / "ring")
    st, val = ring.res_stamps, ring.res_values
    alarms = ring.alarms
    change = true_change(logdir)
    rec = change_episode(logdir)
    if st.size == 0:
        raise RuntimeError(f"{logdir / 'ring'}: no residual recorded")
    lo = math.floor(st[0])
    idx = (np.floor(st) - lo).astype(np.int64)
    n = int(idx[-1]) + 1
    counts = np.bincount(idx, minlength=n).astype(float)
    ok = np.isfinite(val).all(axis=1)
    rms = np.full((n, val.shape[1]), np.nan)
    for j in range(val.shape[1]):
        ss = np.bincount(idx[ok], weights=val[ok, j] ** 2, minlength=n)
        cnt = np.bincount(idx[ok], minlength=n).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms[:, j] = np.sqrt(ss / cnt)
    bins = lo + np.arange(n, dtype=float)
    rearmed = _rearm_time(logdir)
    samples = ring.js_stamps * 1e-9
    dropped = int(np.sum(~np.isfinite(ring.latency_ms)))
    run = EpisodeRun(bins, rms, counts, alarms, change, rec, samples, ring.latency_ms,
                     dropped, rearmed)
    f: dict[str, Any] = {"change_unix_s": change, "episode": None}
    # a re-arm (a reset on request, no anchor) learns at once, or once the settling after the
    # node's first anchor ends (the ring starts after the re-arm: that first sample is not in
    # it): testing starts at the latest settle + learn after the re-arm
    tested_from = (rearmed if rearmed is not None else st[0]) + DETECTOR_SETTLE_S + learn_s
    verdict = math.inf
    if change is not None:
        pre = (bins >= max(tested_from - learn_s, change - 30.0)) & (bins + 1 <= change)
        clean = np.nanmedian(rms[pre], axis=0) if pre.any() else np.full(2, np.nan)
        f["residual_rms_clean"] = dict(zip(SPEED_NAMES, np.round(clean, 4).tolist(),
                                           strict=True))
        after = [a for a in alarms if float(a["stamp_s"]) >= change]
        before = [a for a in alarms if float(a["stamp_s"]) < change]
        first = min(after, key=lambda a: float(a["stamp_s"])) if after else None
        f["detection_delay_s"] = round(float(first["stamp_s"]) - change, 3) if first else None
        f["change_time_error_s"] = round(float(first["change_s"]) - change, 3) if first else None
        f["alarm_output"] = first.get("name") if first else None
        clean_s = max(0.0, change - tested_from)
        f["false_alarms"] = len([a for a in before if float(a["stamp_s"]) >= tested_from])
        f["false_alarms_before_rearm"] = len(before) - f["false_alarms"]
        f["clean_tested_s"] = round(clean_s, 1)
        hours = clean_s / 3600.0
        f["false_alarms_per_hour"] = round(f["false_alarms"] / hours, 1) if hours else None
        f["false_alarms_per_hour_upper95"] = (round(chi2_upper(f["false_alarms"]) / hours, 1)
                                              if hours else None)
        post = (bins >= change + 1.0) & (bins < change + 15.0)
        f["residual_rms_changed"] = dict(zip(SPEED_NAMES, np.round(
            np.nanmedian(rms[post], axis=0), 4).tolist(), strict=True)) if post.any() else None
        f["restored_s"] = None
        if rec is not None:
            f["episode"] = rec.get("episode")
            f["outcome"] = rec.get("outcome")
            f["reason"] = rec.get("reason")
            f["pushed"] = rec.get("pushed")
            f["rolled_back"] = rec.get("rolled_back")
            f["timings"] = rec.get("timings")
            refit_ = rec.get("refit") or {}
            f["accepted"] = refit_.get("accepted")
            f["stage"] = rec.get("stage")
            f["stages"] = [{"stage": s_.get("stage"), "decision": s_.get("decision"),
                            "accepted": (s_.get("refit") or {}).get("accepted"),
                            "refit_seconds": (s_.get("refit") or {}).get("refit_seconds")}
                           for s_ in rec.get("stages") or []]
            f["refit_seconds"] = refit_.get("refit_seconds")
            f["refit_cpu_seconds"] = refit_.get("refit_cpu_seconds")
            f["refit_process"] = refit_.get("refit_process")
            push = rec.get("push_s")
            f["push_after_change_s"] = round(float(push) - change, 3) if push else None
            verdict = max((float(s_["t"]) for s_ in rec.get("steps") or []
                           if s_.get("state") == "idle"), default=math.inf)
            if push and rec.get("pushed"):
                # the new model's residual: after the push, until the verdict (a rollback
                # restores the old model; after the verdict the run is stopped)
                done = (bins >= push + 1.0) & (bins + 1 <= verdict) & np.isfinite(rms).all(axis=1)
                f["residual_rms_restored"] = dict(zip(SPEED_NAMES, np.round(
                    np.nanmedian(rms[done], axis=0), 4).tolist(), strict=True)) \
                    if done.any() else None
            if push and rec.get("pushed") and not rec.get("rolled_back"):
                good = (rms <= RESTORED_FACTOR * clean).all(axis=1) & (bins >= push)
                for k in range(good.size - RESTORED_BINS + 1):
                    if good[k:k + RESTORED_BINS].all():
                        f["restored_s"] = round(float(bins[k]) - change, 3)
                        break
    # the chain's figures: the armed loop (the detector testing) until the episode's verdict
    # (then the bench stops the launcher; what happens while it shuts the chain down, and
    # before, while the ring's and the identifier's subscriptions match the publishers, is
    # reported apart), the episode (from its first alarm) and the refit(s) alone
    period = (1.0 / rate if rate else float(np.median(np.diff(samples))) if samples.size > 1
              else 1e-3)
    end = min(verdict, float(samples[-1]) + period) if samples.size else verdict
    ring_from = max(float(samples[0]), float(st[0])) if samples.size else 0.0
    start = max(ring_from, tested_from)
    whole = chain_figures(samples, ring.latency_ms, start, end, period)
    setup = chain_figures(samples, ring.latency_ms, ring_from, start, period)
    f["before_armed"] = {k: setup[k] for k in ("from_s", "to_s", "samples", "model_dropped",
                                               "chain_missing")}
    f["model_latency_ms"] = whole["model_latency_ms"]
    f["model_samples_timed"] = whole["samples"] - whole["model_dropped"]
    f["model_dropped"] = whole["model_dropped"]
    f["chain_missing"] = whole["chain_missing"]
    f["measured"] = {"from": "the detector testing (re-arm + settle + learn)",
                     "until": ("the episode's verdict" if math.isfinite(verdict)
                               else "the run's end"),
                     "from_s": round(start, 3), "seconds": round(end - start, 1)}
    if rec is not None and math.isfinite(verdict):
        first_alarm = min((float(a.get("stamp_s", math.inf)) for a in rec.get("alarms") or []),
                          default=verdict)
        ep = chain_figures(samples, ring.latency_ms, first_alarm, verdict, period)
        f["episode_chain"] = ep
        f["model_latency_episode_ms"] = ep["model_latency_ms"]
        refits = [chain_figures(samples, ring.latency_ms, a, b, period)
                  for a, b in _refit_windows(rec)]
        f["refit_chain"] = refits
        f["model_dropped_refit"] = sum(r["model_dropped"] for r in refits)
        f["chain_missing_refit"] = sum(r["chain_missing"] for r in refits)
        tail = chain_figures(samples, ring.latency_ms, verdict, math.inf, period)
        f["after_verdict"] = {k: tail[k] for k in ("samples", "model_dropped", "chain_missing")}
    f["restored_factor"] = RESTORED_FACTOR
    run.figures = f
    return run


def run_with_identifier(rate: float = 1000.0, change_at: float = 50.0,
                        change: str = "friction_step", learn_s: float = 10.0, seed: int = 0,
                        timeout: float = 420.0, keep: Path | None = None,
                        log: Any = None, refit_nice: int | None = None,
                        realtime: int | None = REALTIME_PRIORITY) -> dict[str, Any]:
    """The loop bench with the identifier in the loop; returns the figures (module doc)."""
    import shutil

    work = Path(tempfile.mkdtemp(prefix="dvt-bench-loop-id-"))
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(201 + os.getpid() % 30))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    duration = max(120.0, timeout - 30.0)
    args = episode_launch_args(work / "run", rate, change_at, change, duration, learn_s, seed,
                               realtime=realtime, refit_nice=refit_nice)
    t0 = time.monotonic()
    cpu = CpuSampler()
    cpu.start()
    rc = run_episode(work / "run", args, timeout, env=env, log=log, cpu=cpu)
    if not cpu.figures:
        cpu.figures = cpu.stop()
    res = analyse_episode(work / "run", learn_s, rate).figures
    res.update({"launch_status": rc, "wall_s": round(time.monotonic() - t0, 1),
                "rate_hz": rate, "realtime": realtime, "change": change,
                "change_at_plant_s": change_at,
                "learn_s": learn_s, "supervisor": live_supervisor(rate), "cpu": cpu.figures,
                "load_average_1min": round(os.getloadavg()[0], 2)})
    if keep is not None:
        shutil.copytree(work, keep)
    shutil.rmtree(work, ignore_errors=True)
    return res


def main(argv: Sequence[str] | None = None) -> int:
    """``dvt-bench loop`` (argv without the ``loop`` word); returns the exit status."""
    from dvt_driver.run.bench import print_results
    from dvt_driver.system.bench_detect import loop_main

    args_in = list(sys.argv[1:] if argv is None else argv)
    if "--with-identifier" not in args_in:
        return loop_main(args_in)
    p = argparse.ArgumentParser(prog="dvt-bench loop --with-identifier",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--with-identifier", action="store_true", required=True)
    p.add_argument("--rate", type=float, default=1000.0, help="controller rate [Hz] (1000)")
    p.add_argument("--change-at", type=float, default=50.0,
                   help="plant time of the change [s] (50)")
    p.add_argument("--change", default="friction_step", help="preset or YAML of the change")
    p.add_argument("--learn-s", type=float, default=10.0,
                   help="the detector's reference window [s] (10)")
    p.add_argument("--seed", type=int, default=0, help="plant and experiment seed (0)")
    p.add_argument("--timeout", type=float, default=420.0, help="longest run [s] (420)")
    p.add_argument("--keep", default=None, help="copy the run's directory here (new)")
    p.add_argument("--refit-nice", type=int, default=None,
                   help="niceness of the identifier's refit process, -20..19 (default: the "
                        "launcher's, -10 with the real-time chain, else 19; below 0 needs the "
                        "right to)")
    p.add_argument("--realtime", type=int, default=REALTIME_PRIORITY,
                   help=f"the chain's real-time priority (dvt-launch --realtime; default "
                        f"{REALTIME_PRIORITY}; 0: the normal scheduler)")
    p.add_argument("--json", action="store_true", help="print JSON only")
    a = p.parse_args(args_in)
    for name in ("rate", "change_at", "learn_s", "timeout"):
        if not getattr(a, name) > 0:
            p.error(f"--{name.replace('_', '-')}: expected > 0, got {getattr(a, name)}")
    if a.keep is not None and Path(a.keep).exists():
        p.error(f"--keep: {a.keep} already exists")
    try:
        res = run_with_identifier(a.rate, a.change_at, a.change, a.learn_s, a.seed, a.timeout,
                                  Path(a.keep) if a.keep else None,
                                  log=None if a.json else sys.stderr, refit_nice=a.refit_nice,
                                  realtime=a.realtime or None)
    except (OSError, RuntimeError, LaunchError, DvtModelError) as exc:
        print(f"dvt-bench loop: error: {exc}", file=sys.stderr)
        return 1
    print_results(res, a.json, 32)
    return 0


__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
