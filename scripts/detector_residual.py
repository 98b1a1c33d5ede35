"""The change detector on the simulated plant's own residual: why the ARMA(1, 1) of each
reference window misses its false-alarm design there, and what the long-window whitening
(``detector.colour_s``) does (the figures of ``docs/loop.md``, "Colour" and "Limits", and of
``tests/test_detector_clean_plant.py``).

Records the model node's path without ROS for each ``--seeds`` entry (a clean
:class:`~dvt_driver.plant.core.PlantSim`, 1 kHz, the drive at 4 A in neutral ->
:class:`~dvt_model.predictor.Predictor` with the plant's own parameters ->
:class:`~dvt_model.predictor.ResidualBlocks` of the node's ``detector.block_s``), ``--seconds``
each, two recordings at a time, and prints, per output over all recordings:

* the residual's autocorrelation at a few lags (10-ms blocks) and ``B var(block means of B) /
  var`` (the long-run variance ratio; 1 for white noise);
* the reference windows' whitening out of sample: each ``learn_s`` window's
  :func:`~dvt_model.detect.reference_from_window` whitens the *next* window; the standard
  deviation of those windows' means of ``z`` against the ``1 / sqrt(L)`` the design assumes,
  and ``B`` times the mean square of its means of ``B`` samples (1 if the whitening were
  right; at ``B = L`` the window means' own);
* the false alarms of :class:`~dvt_model.detect.ChangeDetector` with the node's defaults but
  no colour (``colour_s`` 0: each window's ARMA(1, 1)) and ``learn_s`` 20, 60 and 120 s, and
  with the node's defaults (before the colour, with a colour fitted on less than
  ``colour_s`` of history while it grows, and with the full one), with the one-sided 95 %
  Poisson bounds, against the design;
* the first minute's allowance (before the colour) on white residual, where there is no
  colour to allow for: its thresholds over the ARMA's own design, and the expected delay to a
  ``shift_sigma`` step with and without it;
* the growing colour's allowance (minutes 1-5) on white residual: thresholds designed over
  the long-run variance ratio of a white ``COLOUR_CHUNK_S`` chunk with its uncertainty (as
  the detector does), and at the ratio alone (as it did before 2026-12-07), over the design
  for white increments, with the expected delays;
* a design tried and not kept (``--trial``): ``h`` for whitened increments of long-run
  variance ``lam`` (``k`` and ``h`` act divided by ``sqrt(lam)``), ``lam`` from
  :data:`TRIAL_BATCHES` batch means of the whitened reference window (at least 1) and the rate
  averaged over its scale-inverse-chi2 uncertainty; its false alarms on the recordings and on
  ``--white-hours`` of white residual at the block rate (where the node's design is right);
  and a whitening that sees the slow time scales: an AR(p) (the detector's
  :func:`~dvt_model.detect.ar_by_aic`, up to ``detector.colour_lag_s``) learned on
  ``--colour-s`` of residual whitens the next 20 s, windows every 60 s (the same mean-square
  figures as above).

About 2.5 minutes with the defaults on two cores, 4 more with ``--trial``.

Usage::

    .venv/bin/python scripts/detector_residual.py [--seeds 3100 3101 3102 3103] [--seconds 900]
        [--trial] [--restart-s 300 --node-only] [--json]

``--restart-s S`` starts a new detector every ``S`` s of each recording (the residual is
stationary, so each is a node start on fresh data): the first minutes after many starts.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
from scipy.signal import lfilter
from scipy.stats import chi2

LEAD_S = 2.0  # the model node starts this long after the motor [s]
CURRENT_A = 4.0
SETTLE_BLOCKS = 300  # blocks left out after the start (the node's settle_s)
WHITE_WINDOWS = 200
"""Reference windows of white residual on which the first minute's allowance is costed."""
TRIAL_BATCHES = 25
"""Batches of the whitened reference window in the ``--trial`` design."""


def record(seed: int, seconds: float) -> np.ndarray:
    """``(n, 3)`` block stamps [s] and block-mean residuals [rad/s] of one clean plant."""
    from dvt_driver.plant.core import PlantSim
    from dvt_driver.plant.offline import predicted_held_current
    from dvt_model.config import detector_config
    from dvt_model.params import load_parameters
    from dvt_model.predictor import ResidualBlocks

    params = load_parameters("physical")
    setup = detector_config({})
    if setup is None:
        raise SystemExit("the node's detector is disabled by default: nothing to measure")
    blocks = ResidualBlocks(setup.block, 2, setup.config.max_gap_s)
    out: list[list[float]] = []
    plant = PlantSim(params, None, seed=seed)
    for t, p in predicted_held_current(plant, params, CURRENT_A, seconds, LEAD_S):
        if p.anchored:
            blocks.clear()
        b = blocks.add(t, p.residual.tolist())
        if b is not None:
            out.append([b[0], *b[1]])
    return np.asarray(out, dtype=float)[SETTLE_BLOCKS:]


def lrv_ratio(x: np.ndarray, b: int) -> float:
    """``b var(means of b consecutive samples) / var(x)`` (``nan`` for fewer than 4 means)."""
    n = x.size // b
    if n < 4:
        return math.nan
    m = x[: n * b].reshape(n, b).mean(axis=1)
    return float(m.var() * b / x.var())


def pooled_lrv(zs: list[np.ndarray], b: int) -> float:
    """``b`` times the mean square of the means of ``b`` consecutive samples of each whitened
    window in ``zs``, about 0 (the level the design assumes): 1 for a right whitening."""
    m = np.concatenate([z[: z.size // b * b].reshape(-1, b).mean(axis=1) for z in zs])
    return float(b * np.mean(m * m))


def trial_h(k: float, rate: float, learn: int, lam: float, dof: int) -> float:
    """The ``--trial`` threshold: the smallest ``h`` whose false-alarm rate per sample, averaged
    over 16 equal-probability points of ``lam``'s scale-inverse-chi2 uncertainty, is at most
    ``rate``."""
    from dvt_model.detect import design_threshold

    q = (np.arange(16) + 0.5) / 16
    return design_threshold(k, rate, learn, list(lam * dof / chi2.ppf(1.0 - q, dof)))


def count_alarms(x: np.ndarray, trial: bool) -> tuple[int, int, list[float], list[float]]:
    """False alarms of the detector's algorithm (vectorised, re-learning after each alarm) on
    ``x`` ``(n, outputs)`` at the node's default settings, with its own threshold or the
    ``--trial`` one: ``(alarms, tested samples, thresholds of the last output, the detector's
    mean time between false alarms [h] each window's thresholds give on i.i.d. increments)``."""
    from dvt_model.config import detector_config
    from dvt_model.detect import false_alarm_rate, reference_from_window
    from dvt_model.detect_sim import _whiten, cusum_run

    setup = detector_config({})
    assert setup is not None
    cfg = setup.config
    L = cfg.learn_samples
    rate = 2.0 / (cfg.false_alarm_period_s * cfg.sample_rate_hz * 2 * x.shape[1])
    i = alarms = tested = 0
    hs: list[float] = []
    iid_h: list[float] = []
    while i + L < x.shape[0]:
        win = x[i:i + L]
        first = -1
        per_sample = 0.0
        for j in range(x.shape[1]):
            ref = reference_from_window(win[:, j], cfg)
            h = ref.h
            if trial:
                c = win[:, j] - ref.level
                z = np.asarray(lfilter([1.0, -ref.phi], [1.0, ref.theta], c))[1:] / ref.sigma_e
                b = z.size // TRIAL_BATCHES
                m = z[: b * TRIAL_BATCHES].reshape(TRIAL_BATCHES, b).mean(axis=1)
                lam = max(1.0, float(np.var(m, ddof=1)) * b)
                h = trial_h(ref.k, rate, L, lam, TRIAL_BATCHES - 1)
            per_sample += false_alarm_rate(ref.k, h, L)
            if j == x.shape[1] - 1:
                hs.append(h)
            z, _ = _whiten(x[i + L:, j], (ref.last_r, ref.last_a), ref)
            for sign in (1.0, -1.0):
                idx, _ = cusum_run(sign * z, ref.k, h)
                if idx >= 0 and (first < 0 or idx < first):
                    first = idx
        iid_h.append(1.0 / (per_sample * cfg.sample_rate_hz * 3600.0))
        if first < 0:
            tested += x.shape[0] - i - L
            break
        alarms += 1
        tested += first + 1
        i += L + first + 1
    return alarms, tested, hs, iid_h


def long_window_whitening(recs: list[np.ndarray], j: int, colour: int, test: int
                          ) -> tuple[list[np.ndarray], list[int]]:
    """Output ``j`` of each recording whitened ``test`` samples past each ``colour``-sample
    window (windows every 6000 samples) by that window's AR of
    :func:`~dvt_model.detect.ar_by_aic` (the node's ``colour_lag_s``), unit scale from the
    window's own innovations; and the AR orders chosen."""
    from dvt_model.config import detector_config
    from dvt_model.detect import ar_by_aic, lagged_products

    setup = detector_config({})
    assert setup is not None
    lags = setup.config.colour_order_max
    zs, orders = [], []
    for r in recs:
        x = r[:, 1 + j]
        for s0 in range(0, x.size - colour - test + 1, 6000):
            win = x[s0:s0 + colour]
            level = float(win.mean())
            coef = ar_by_aic(lagged_products(win, lags) / win.size, win.size, lags)
            poly = np.concatenate([[1.0], -coef])
            a = np.asarray(lfilter(poly, [1.0], x[s0:s0 + colour + test] - level))
            p = poly.size - 1
            zs.append(a[colour:] / float(np.std(a[p:colour])))
            orders.append(p)
    return zs, orders


def rate_line(alarms: int, hours: float) -> str:
    """``alarms / hours`` with its one-sided 95 % Poisson bounds."""
    if hours <= 0:
        return "nothing tested (the recordings are shorter than the reference window)"
    from dvt_model.detect_sim import rate_bounds

    lo, hi = rate_bounds(alarms, hours)
    return (f"{alarms:3d} in {hours:.2f} h tested: {alarms / hours:6.2f}/h (one-sided 95 %: "
            f"{lo:.2f} to {hi:.2f}/h)")


def main() -> int:
    from dvt_model.config import detector_config
    from dvt_model.detect import (
        COLOUR_CHUNK_S,
        SIEGMUND_OFFSET,
        ChangeDetector,
        long_run_ratio,
        long_run_spread,
        reference_from_window,
    )
    from dvt_model.detect_sim import rate_bounds

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3100, 3101, 3102, 3103])
    ap.add_argument("--seconds", type=float, default=900.0)
    ap.add_argument("--trial", action="store_true",
                    help="also count the alarms of the design tried and not kept")
    ap.add_argument("--white-hours", type=float, default=10.0,
                    help="hours of white residual for --trial (seed 1)")
    ap.add_argument("--colour-s", type=float, nargs="+", default=[20.0, 120.0, 300.0],
                    help="--trial: lengths of the long-window AR whitening's window [s]")
    ap.add_argument("--restart-s", type=float, default=0.0,
                    help="start a new detector (node defaults) every this many seconds of "
                    "each recording, to count the first minutes after many starts (0: one "
                    "start per recording)")
    ap.add_argument("--carry-s", type=float, default=0.0,
                    help="with --restart-s: the first this many seconds of each recording run "
                    "one detector whose colour (ChangeDetector.carry) every start on the rest "
                    "of it carries in (a node restarted with detector.colour_file); 0: none")
    ap.add_argument("--node-only", action="store_true",
                    help="count the node defaults' false alarms only (no residual figures, no "
                    "colour_s 0 variants)")
    ap.add_argument("--json", action="store_true",
                    help="print the figures as one JSON document on stdout (the text on stderr)")
    a = ap.parse_args()
    out = sys.stderr if a.json else sys.stdout

    def say(*args: object) -> None:
        print(*args, file=out)

    if a.carry_s and not (a.restart_s > 0 and a.node_only and a.carry_s < a.seconds):
        ap.error("--carry-s needs --restart-s, --node-only and a value below --seconds")
    figures: dict[str, object] = {"seeds": a.seeds, "seconds_each": a.seconds, "outputs": {},
                                  "false_alarms": [], "restart_s": a.restart_s,
                                  "carry_s": a.carry_s}
    with ProcessPoolExecutor(2) as pool:
        recs = list(pool.map(record, a.seeds, [a.seconds] * len(a.seeds)))
    setup = detector_config({})
    assert setup is not None
    cfg = setup.config
    L = cfg.learn_samples
    say(f"{len(recs)} clean plants (seeds {a.seeds}), {a.seconds:g} s each, 10-ms blocks, "
          f"{sum(r.shape[0] for r in recs) / cfg.sample_rate_hz / 3600:.2f} h in all")
    for j, name in enumerate([] if a.node_only else cfg.names):
        xs = [r[:, 1 + j] - r[:, 1 + j].mean() for r in recs]
        acf = []
        for lag in (1, 2, 5, 10, 20, 50, 100, 200):
            acf.append(float(np.mean([np.sum(x[lag:] * x[:-lag]) / np.sum(x * x) for x in xs])))
        ratios = [float(np.nanmean([lrv_ratio(x, b) for x in xs]))
                  for b in (10, 100, 1000, 2000, 5000)]
        say(f"\n{name}: residual autocorrelation at 1/2/5/10/20/50/100/200 blocks: "
              + " ".join(f"{v:.3f}" for v in acf))
        say(f"{name}: B var(means of B) / var at B = 10/100/1000/2000/5000 blocks: "
              + " ".join(f"{v:.2f}" for v in ratios))
        means, zs = [], []
        for r in recs:
            x = r[:, 1 + j]
            for w in range(x.size // L - 1):
                ref = reference_from_window(x[w * L:(w + 1) * L], cfg)
                c = x[w * L:(w + 2) * L] - ref.level
                z = np.asarray(lfilter([1.0, -ref.phi], [1.0, ref.theta], c))[L:] / ref.sigma_e
                means.append(float(z.mean()))
                zs.append(z)
        wz = [pooled_lrv(zs, b) for b in (1, 100, 400, 2000)]
        figures["outputs"][name] = {  # type: ignore[index]
            "acf_1_10_50_200": [acf[0], acf[3], acf[5], acf[7]],
            "lrv_ratio_10_100_1000_2000_5000": ratios,
            "arma_window_mean_sd": float(np.std(means)), "design_window_mean_sd": L ** -0.5,
            "arma_b_mean_square_1_100_400_2000": wz}
        say(f"{name}: whitened out of sample ({len(means)} windows of {cfg.learn_s:g} s): sd of "
              f"the window means {np.std(means):.4f} against 1/sqrt(L) = {L ** -0.5:.4f}; "
              "B mean(means of B ^ 2) at B = 1/100/400/2000: " + " ".join(f"{v:.2f}" for v in wz))
    design = 3600.0 / cfg.false_alarm_period_s
    say(f"\nfalse alarms of ChangeDetector (node defaults; design {design:.2f}/h):")
    for learn_s in (None,) if a.node_only else (cfg.learn_s, 60.0, 120.0, None):
        if learn_s is None:
            setting, label = cfg, f"colour_s {cfg.colour_s:g}"
        else:
            setting = dataclasses.replace(cfg, learn_s=learn_s, colour_s=0.0)
            label = f"colour_s 0, learn_s {learn_s:g}"
        # before the colour, with a colour on less than colour_s of history, with the full one
        alarms, tested = [0, 0, 0], [0, 0, 0]
        starts = 0
        restart = a.restart_s if learn_s is None else 0.0
        for seed, r in zip(a.seeds, recs, strict=True):
            carried = None
            if a.carry_s:  # an earlier run of the same plant and model: its colour carried
                earlier = ChangeDetector(setting)
                for row in r[r[:, 0] - r[0, 0] < a.carry_s].tolist():
                    earlier.update(row[0], row[1:])
                carried = earlier.carry()
                if carried is None:
                    raise SystemExit(f"seed {seed}: no full colour in the first "
                                     f"{a.carry_s:g} s (--carry-s below detector.colour_s?)")
                r = r[r[:, 0] - r[0, 0] >= a.carry_s]
            det, t0 = ChangeDetector(setting, carried), r[0, 0]
            starts += 1
            for row in r.tolist():
                if restart > 0 and row[0] - t0 >= restart:  # a new start of the node
                    det, t0 = ChangeDetector(setting, carried), row[0]
                    starts += 1
                if carried is not None:  # the first minute, minutes 1-5 and the own colour
                    phase = (0 if row[0] - t0 < 60.0 else 1) if det.colour_carried else 2
                else:
                    phase = int(det.colour_in_use) + int(det.colour_complete)
                before = det.counters.tested
                alarms[phase] += det.update(row[0], row[1:]) is not None
                tested[phase] += det.counters.tested - before
        for phase in (0, 1, 2) if learn_s is None else (0,):
            hours = tested[phase] / setting.sample_rate_hz / 3600
            what = ("" if learn_s is not None else
                    (", before the colour", ", with the colour on a shorter history",
                     ", with the colour")[phase] if not a.carry_s else
                    (", the first minute with the carried colour",
                     ", minutes 1-5 with the carried colour", ", with its own colour")[phase])
            say(f"  {label}{what}: " + rate_line(alarms[phase], hours)
                + (f" ({starts} starts)" if learn_s is None else ""))
            figures["false_alarms"].append({  # type: ignore[attr-defined]
                "detector": label + what, "alarms": alarms[phase], "hours": hours,
                "starts": starts if learn_s is None else len(recs),
                "per_hour_95": list(rate_bounds(alarms[phase], hours)),
                "design_per_hour": design})
    # what the first minute's allowance costs where there is no colour to allow for
    rng = np.random.default_rng(1)
    pairs = []
    for _ in range(WHITE_WINDOWS):
        w = rng.standard_normal(L)
        pairs.append((reference_from_window(w, cfg, None, None), reference_from_window(w, cfg)))
    ratio = np.asarray([first.h / arma.h for first, arma in pairs])
    def median_delay(refs: tuple[Any, ...]) -> float:
        """Median expected delay [s] to a ``shift_sigma`` step (Siegmund) of ``refs``."""
        return float(np.median([(r.h + SIEGMUND_OFFSET) / (cfg.shift_sigma - r.k)
                                / cfg.sample_rate_hz for r in refs]))

    delay = [median_delay(refs) for refs in zip(*pairs, strict=True)]
    figures["first_minute_white"] = {
        "windows": WHITE_WINDOWS, "h_ratio_quantiles_10_50_90_100":
        np.quantile(ratio, [0.1, 0.5, 0.9, 1.0]).round(3).tolist(),
        "delay_s_median_with_without": delay}
    say(f"\nbefore the colour, on {WHITE_WINDOWS} windows of white residual: h over the ARMA's "
        "own design, quantiles 10/50/90/100 %: "
        + " ".join(f"{v:.2f}" for v in np.quantile(ratio, [0.1, 0.5, 0.9, 1.0]))
        + f"; expected delay to a {cfg.shift_sigma:g} sigma step (Siegmund, median) "
        f"{delay[0]:.2f} s with the allowance, {delay[1]:.2f} s without")
    # what the growing colour's allowance costs on white residual: a reference window
    # whitened by a colour (here of order 0), lam from a white chunk
    chunk = round(COLOUR_CHUNK_S * cfg.sample_rate_hz)
    none = np.zeros(0)
    trios = []
    for _ in range(WHITE_WINDOWS):
        w, c = rng.standard_normal(L), rng.standard_normal(chunk)
        trios.append((reference_from_window(w, cfg, none, long_run_spread(c, cfg.sample_rate_hz)),
                      reference_from_window(w, cfg, none, long_run_ratio(c, cfg.sample_rate_hz)),
                      reference_from_window(w, cfg, none)))
    grow = {name: np.asarray([t[j].h / t[2].h for t in trios])
            for j, name in ((0, "spread"), (1, "ratio"))}
    gdelay = [median_delay(refs) for refs in zip(*trios, strict=True)]
    figures["growing_colour_white"] = {
        "windows": WHITE_WINDOWS, "chunk_s": COLOUR_CHUNK_S,
        "h_ratio_quantiles_10_50_90_100": {
            k: np.quantile(v, [0.1, 0.5, 0.9, 1.0]).round(3).tolist() for k, v in grow.items()},
        "delay_s_median_spread_ratio_white": gdelay}
    say(f"\nthe growing colour, on {WHITE_WINDOWS} white chunks of {COLOUR_CHUNK_S:g} s: h over "
        "the white design, quantiles 10/50/90/100 %: with the ratio's uncertainty "
        + " ".join(f"{v:.2f}" for v in np.quantile(grow["spread"], [0.1, 0.5, 0.9, 1.0]))
        + "; at the ratio alone "
        + " ".join(f"{v:.2f}" for v in np.quantile(grow["ratio"], [0.1, 0.5, 0.9, 1.0]))
        + f"; expected delay to a {cfg.shift_sigma:g} sigma step (median) {gdelay[0]:.2f} / "
        f"{gdelay[1]:.2f} / {gdelay[2]:.2f} s")
    if a.trial:
        rate_hz = cfg.sample_rate_hz
        white = np.random.default_rng(1).standard_normal(
            (round(a.white_hours * 3600 * rate_hz), len(cfg.names)))
        say(f"\ntrial design (long-run variance from {TRIAL_BATCHES} batch means, averaged "
              "over its uncertainty) against the node's, vectorised:")
        for label, data in (("clean plants", recs), ("white residual", [white])):
            for trial in (False, True):
                al = te = 0
                hs: list[float] = []
                iid: list[float] = []
                for x in data:
                    n_al, n_te, h, m = count_alarms(x[:, 1:] if x is not white else x, trial)
                    al, te, hs, iid = al + n_al, te + n_te, hs + h, iid + m
                say(f"  {label:14s} {'trial' if trial else 'node '}: "
                      + rate_line(al, te / rate_hz / 3600)
                      + f"; h of {cfg.names[-1]} median {np.median(hs):.1f}; on i.i.d. "
                      f"increments its thresholds give one false alarm per "
                      f"{np.median(iid):.3g} h (median over windows)")
        say("\ntrial whitening: AR(p) by AIC on a long window, scored on the next 20 s:")
        test = round(20.0 * rate_hz)
        for secs in a.colour_s:
            for j, name in enumerate(cfg.names):
                zs, orders = long_window_whitening(recs, j, round(secs * rate_hz), test)
                if not zs:
                    say(f"  {secs:5g} s {name}: the recordings are too short")
                    continue
                say(f"  {secs:5g} s {name:9s}: {len(zs)} windows, p median "
                      f"{int(np.median(orders))}; B mean(means of B ^ 2) at B = 1/100/400/2000: "
                      + " ".join(f"{pooled_lrv(zs, b):.2f}" for b in (1, 100, 400, 2000)))
    if a.json:
        print(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
