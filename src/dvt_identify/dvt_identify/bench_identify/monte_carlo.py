"""Monte Carlo mode of ``dvt-bench identify`` (``--monte-carlo``): the identifier's statistics
against the Cramér-Rao bound on records simulated from a known model, also misspecified
(``--coloured``; see :mod:`dvt_identify.bench_identify`)."""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from dvt_identify.bench_identify.common import (
    Array,
    Log,
    blas_env,
    load_average,
    num,
    quiet,
)
from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, load_description
from dvt_identify.errors import BenchError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_model.excitation import prbs

TARGET_CRLB_RATIO = 1.2
TARGET_COVERAGE = (0.93, 0.97)


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
                    log: Log = quiet, coloured: bool = False, ar: float = 0.9,
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
    load_before = load_average()
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
        "load_average": {"before": load_before, "after": load_average()},
        "cpu_count": os.cpu_count(),
    }


def pretty_monte_carlo(res: dict[str, Any]) -> str:
    """Human-readable text of :func:`run_monte_carlo`."""
    lines: list[str] = []
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
    lines.append(f"max crlb_ratio {num(res['max_crlb_ratio'])} (target <= "
                 f"{TARGET_CRLB_RATIO}; +-{100 * su['crlb_ratio_relative_se']:.0f} % "
                 f"sampling), mean coverage_95 {num(res['mean_coverage_95'])} (target "
                 f"{TARGET_COVERAGE[0]}-{TARGET_COVERAGE[1]}; +-"
                 f"{su['coverage_se_per_parameter']:.3f} per parameter)")
    lines.append(f"failed runs {len(res['failed'])}, fit {res['fit_seconds_mean']:.2f} s "
                 f"mean, wall {res['wall_seconds']:.1f} s with {res['workers']} worker(s)")
    return "\n".join(lines)
