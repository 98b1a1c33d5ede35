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

Long-recording mode::

    dvt-bench identify --hours H [--run-minutes 5] [--cache DIR] [--json]

Generates ``H`` hours of the simulated plant at 1 kHz through the offline runner (runs of
``--run-minutes``, cached in ``--cache``, default ``~/.cache/dvt-bench/identify-hours``) and
identifies them in a process of its own: ``loop_seconds`` (the identification, as above) and
``peak_rss_mb`` (its largest resident set, worker processes included), targets 60 s and 2 GB
for one hour (:mod:`dvt_identify.bench_identify.hours`).

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

    dvt-bench identify --compare [EST=VAL ...] [--no-peer] [--starts K] [--fit-decimate Q]
                       [--json]

Runs the identification (baseline and augment loop, the bundled description) on each
estimation/validation pair (default: ``bags/ident-coulomb`` with ``bags/ident-coulomb-val`` and
``bags/ident-none-1`` with ``bags/ident-none-val``, the validation runs written by
``scripts/make_validation_bags.sh``) and prints per pair: the validation fit per output (free
run from the first validation sample, like the peer, and with the initial state estimated,
like the report), the largest relative error of ``M`` and ``D`` against the plant of
``truth.yaml`` and the identification seconds; beside them the same figures of a peer run in the
same process on the same pair (:mod:`dvt_identify.bench_identify.peer_casadi`: a
multiple-shooting fit of the same grey box by CasADi + IPOPT, told the friction structure of
``truth.yaml``, started from the description's prior), and the targets against it: validation
fit no worse, ``M`` and ``D`` within 2 %, at least twice as fast. CasADi is an optional
benchmark dependency (``requirements-dev.txt``): without it the output says ``peer not run:
casadi not installed``; ``--no-peer`` skips the peer.

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
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dvt_identify.bench_identify.common import (
    DEFAULT_ESTIMATION,
    DEFAULT_VALIDATION,
    finite,
    quiet,
    stderr_log,
)
from dvt_identify.bench_identify.compare import (
    COMPARE_PAIRS,
    pretty_compare,
    run_compare,
)
from dvt_identify.bench_identify.hours import pretty_hours, run_hours
from dvt_identify.bench_identify.monte_carlo import (
    coloured_noise,
    crlb_std,
    mc_input,
    pretty_monte_carlo,
    run_monte_carlo,
)
from dvt_identify.bench_identify.timing import power_law_exponent, pretty_timing, run_timing
from dvt_identify.errors import DvtIdentifyError
from dvt_model.errors import DvtModelError

__all__ = [
    "COMPARE_PAIRS",
    "DEFAULT_ESTIMATION",
    "DEFAULT_VALIDATION",
    "coloured_noise",
    "crlb_std",
    "main",
    "mc_input",
    "power_law_exponent",
    "pretty",
    "run_compare",
    "run_hours",
    "run_monte_carlo",
    "run_timing",
]


def pretty(res: dict[str, Any]) -> str:
    """Human-readable text of a result of :func:`run_timing`, :func:`run_compare` or
    :func:`run_monte_carlo` (by its ``mode``)."""
    if res.get("mode") == "compare":
        return pretty_compare(res)
    if res.get("mode") == "monte_carlo":
        return pretty_monte_carlo(res)
    if res.get("mode") == "hours":
        return pretty_hours(res)
    return pretty_timing(res)


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
                   help="identify and compare with the peer (multiple shooting, CasADi + "
                        "IPOPT, run on the same data): estimation=validation "
                        "bag pairs (default: bags/ident-coulomb=bags/ident-coulomb-val "
                        "bags/ident-none-1=bags/ident-none-val)")
    c.add_argument("--no-peer", action="store_true",
                   help="--compare without the peer (the identifier's figures only)")
    h = p.add_argument_group("long-recording mode")
    h.add_argument("--hours", type=float, default=None, metavar="H",
                   help="generate H hours at 1 kHz through the offline runner and identify "
                        "them (loop_seconds, peak_rss_mb)")
    h.add_argument("--run-minutes", type=float, default=5.0,
                   help="length of one generated run [min] (5)")
    h.add_argument("--cache", default=None,
                   help="where the generated runs are kept (~/.cache/dvt-bench/"
                        "identify-hours)")
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
    log = quiet if args.json and not args.verbose else stderr_log
    try:
        if args.compare is not None:
            pairs = []
            for item in args.compare:
                e, sep, v = item.partition("=")
                if not sep or not e or not v:
                    p.error(f"--compare: expected ESTIMATION=VALIDATION, got {item!r}")
                pairs.append((e, v))
            res = run_compare(pairs or None, args.description, args.starts, args.fit_decimate,
                              log, peer=not args.no_peer)
        elif args.hours is not None:
            res = run_hours(args.hours, args.description,
                            Path(args.cache) if args.cache else None, args.run_minutes,
                            args.seed, log)
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
    res = finite(res)
    print(json.dumps(res) if args.json else pretty(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
