"""Identification report: ``report.json`` (contract keys plus details), ``report.md`` and plots.

``report.json`` holds the contract's minimum keys (``estimation_bags``, ``validation_bags``,
``baseline``/``final`` with ``fit_percent``, ``rmse`` (validation data) and ``parameters``, and the
ranked ``effects``) plus: ``parameter_std``, figures on estimation and validation data (loss, FPE,
AIC, BIC), residual tests, the multi-start summary, every round's candidate scores, the
accept/reject decisions and an honest ``remaining`` list (what the final model leaves in the
residual). When no candidate is accepted, ``effects`` is ``[{"name": "none", "accepted": true}]``
and ``final`` equals ``baseline``.

Effects are ranked: accepted ones in the order they were accepted (each was the strongest of its
round by the refit's likelihood ratio), then the others by the largest likelihood ratio of their
refits, then by their last projected score.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.loop import CandidateScore, Decision, IdentificationResult, Stage
from dvt_identify.oe import simulate_linear, zoh

Array = NDArray[np.float64]


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(float(x)) else None


def _clean(obj: Any) -> Any:
    """JSON-safe copy: numpy to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer | int):
        return int(obj)
    if isinstance(obj, np.floating | float):
        return _num(float(obj))
    return obj


def multistart_summary(stage: Stage) -> dict[str, Any]:
    """Starts of the stage's fit: costs, how many reached the best minimum (full-data cost within
    1e-6, or a screened start whose screening cost is within 0.1 % of the reference), and the
    spread of the structure parameters among those."""
    fit = stage.fit
    starts = fit.starts_
    if not starts:
        return {}
    best = min(s.cost for s in starts)
    near = [s for s in starts if s.cost <= best * (1 + 1e-6) + 1e-300
            or s.same_minimum is True]
    ns = fit.model.n_struct
    names = fit.model.names[:ns]
    spread = {}
    for i, n in enumerate(names):
        vals = [s.theta[i] for s in near if s.same_minimum is not True] or [near[0].theta[i]]
        spread[n] = [min(vals), max(vals)]
    return {"n_starts": len(starts), "n_at_best": len(near), "costs": [s.cost for s in starts],
            "how": [s.note or "full" for s in starts],
            "best_cost": best, "parameter_range_at_best": spread,
            "local_minima_found": len(starts) - len(near)}


def stage_dict(stage: Stage, units: dict[str, str]) -> dict[str, Any]:
    """Contract view of a stage (validation figures) plus details."""
    val = stage.val.as_dict()
    return {
        "label": stage.label,
        "fit_percent": val["fit_percent"],
        "rmse": val["rmse"],
        "parameters": stage.parameters(),
        "parameter_std": stage.fit.parameter_std(),
        "effects": [e.label() for e in stage.effects],
        "validation": val,
        "estimation": stage.est.as_dict(),
        "validation_initial_states": [x.tolist() for x in stage.val_x0],
        "estimation_initial_states": [x.tolist() for x in stage.fit.x0_],
        "residual_validation": {r.output: r.as_dict() for r in stage.resid_val},
        "residual_estimation": {r.output: r.as_dict() for r in stage.resid_est},
        "residual_spectrum_peak_hz": {n: sp.peak_hz for n, sp in
                                      zip(stage.val.output_names, stage.spectrum_val,
                                          strict=True)},
        "multistart": multistart_summary(stage),
        "fit_seconds": stage.fit.seconds_,
        "units": units,
    }


def _latest_scores(result: IdentificationResult) -> dict[str, CandidateScore]:
    out: dict[str, CandidateScore] = {}
    for rnd in result.rounds:
        for sc in rnd:
            out[sc.label] = sc
    return out


def ranked_effects(result: IdentificationResult) -> list[dict[str, Any]]:
    """Effect entries (contract form), strongest first; see module docstring."""
    latest = _latest_scores(result)
    trials: dict[str, list[Decision]] = {}
    for d in result.decisions:
        trials.setdefault(d.score.label, []).append(d)
    final_params = result.final.parameters()
    final_std = result.final.fit.parameter_std()
    entries: list[tuple[tuple[float, float, float], dict[str, Any]]] = []
    accepted_order = [d.score.label for d in result.accepted]
    for label, sc in latest.items():
        ds = trials.get(label, [])
        acc = label in accepted_order
        eff = sc.effect
        if acc:
            params = {p.name: final_params.get(p.name, math.nan) for p in eff.params}
            params.update({k: v for k, v in eff.derived(final_params).items()})
            std = {p.name: final_std.get(p.name, math.nan) for p in eff.params}
        else:
            tried = [d for d in ds if d.stage is not None]
            if tried:
                last = tried[-1]
                assert last.stage is not None
                sp = last.stage.parameters()
                params = {p.name: sp.get(p.name, math.nan) for p in eff.params}
                std = {}
            else:
                params = dict(sc.implied)
                std = {}
        evidence = sc.evidence()
        evidence["scored_in_round"] = max(i + 1 for i, r in enumerate(result.rounds)
                                          if any(s.label == label for s in r))
        evidence["refits"] = [d.as_dict() for d in ds]
        entry = {"name": eff.name, "where": eff.where, "accepted": acc, "evidence": evidence,
                 "parameters": params, "parameter_std": std}
        max_lr = max((d.lr for d in ds if math.isfinite(d.lr)), default=-math.inf)
        key = ((-accepted_order.index(label) if acc else -1e9), max_lr, sc.r2)
        entries.append((key, entry))
    entries.sort(key=lambda ke: ke[0], reverse=True)
    return [e for _, e in entries]


def remaining_summary(result: IdentificationResult) -> list[str]:
    """Plain statements of what the final model leaves in the validation residual."""
    out = []
    fin = result.final
    for r, sp in zip(fin.resid_val, fin.spectrum_val, strict=True):
        if r.white:
            out.append(f"{r.output}: the validation residual is white within the 99 % bounds "
                       f"(Ljung-Box p = {r.ljung_box_p:.3g}).")
        else:
            out.append(f"{r.output}: the validation residual is coloured (Ljung-Box Q = "
                       f"{r.ljung_box:.4g}, p = {r.ljung_box_p:.3g}; lag-1 autocorrelation "
                       f"{r.acf[1]:.3f}): the OE model leaves correlated error.")
        for name, ok in r.independent.items():
            if ok:
                out.append(f"{r.output}: residual independent of input {name} within the 99 % "
                           f"Bartlett bounds (max |CCF|/bound = {r.max_ccf_ratio[name]:.2f}).")
            else:
                out.append(f"{r.output}: residual still correlated with input {name} (max "
                           f"|CCF|/bound = {r.max_ccf_ratio[name]:.2f}): input-driven dynamics "
                           "are not fully modelled.")
        if sp.peak_ratio > 5.0:
            out.append(f"{r.output}: the validation residual spectrum has a peak at "
                       f"{sp.peak_hz:.3g} Hz ({sp.peak_ratio:.3g} x the median density within "
                       "half an octave), e.g. an unmodelled resonance or periodic disturbance.")
        else:
            out.append(f"{r.output}: no prominent peak in the validation residual spectrum "
                       f"(largest {sp.peak_ratio:.2g} x the local median, at {sp.peak_hz:.3g} "
                       "Hz).")
    if result.rounds:
        last = result.rounds[-1]
        accepted = {d.score.label for d in result.accepted}
        rest = [s for s in last if s.label not in accepted]
        if rest:
            s = rest[0]
            ds = [d for d in result.decisions if d.score.label == s.label and d.round ==
                  len(result.rounds)]
            why = ds[-1].reason if ds else (
                "not refitted: score not significant" if s.p_value >= result.config.alpha
                else "not refitted")
            out.append(f"Strongest remaining candidate: {s.label} (projected R2 "
                       f"{100 * s.r2:.2f} %, LM p = {s.p_value:.3g}); not accepted: {why}.")
    elif not result.config.augment:
        out.append("The augment loop was not run (--no-augment).")
    out.extend(result.description.notes)
    return out


def build_report(result: IdentificationResult) -> dict[str, Any]:
    """The ``report.json`` content."""
    desc = result.description
    units = {n: desc.structure.speed_unit or "" for n in desc.output_names}
    baseline = stage_dict(result.baseline, units)
    accepted = result.accepted
    if accepted:
        effects = ranked_effects(result)
        final = stage_dict(result.final, units)
    else:
        effects = [{"name": "none", "accepted": True}]
        final = baseline
    rep = {
        "tool": "dvt-identify",
        "description": {"name": desc.name, "source": desc.source},
        "estimation_bags": result.estimation_bags,
        "validation_bags": result.validation_bags,
        "outputs": list(desc.output_names),
        "inputs": list(desc.input_names),
        "baseline": baseline,
        "effects": effects,
        "final": final,
        "candidates": ranked_effects(result) if not accepted else None,
        "rounds": [[{"name": s.effect.name, "where": s.effect.where, "r2_projected": s.r2,
                     "lm_statistic": s.lm, "p_value": s.p_value} for s in r]
                   for r in result.rounds],
        "decisions": [d.as_dict() for d in result.decisions],
        "remaining": remaining_summary(result),
        "settings": {"starts": result.config.starts, "refit_starts": result.config.refit_starts,
                     "alpha": result.config.alpha,
                     "min_validation_gain": result.config.min_validation_gain,
                     "augment": result.config.augment, "fit_dt_s": result.fit_dt,
                     "fit_decimate": result.config.fit_decimate},
        "notes": result.notes,
        "seconds": result.seconds,
    }
    if rep["candidates"] is None:
        del rep["candidates"]
    return dict(_clean(rep))


# ---------------------------------------------------------------------------------------------
# Plots


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fits(result: IdentificationResult, out: Path) -> list[Path]:
    """Measured vs simulated (baseline, final) on validation data, one PNG per output."""
    plt = _plt()
    paths = []
    names = result.description.output_names
    for j, name in enumerate(names):
        fig, axes = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
        offset = 0.0
        for k, seg in enumerate(_val_segments(result)):
            t = seg.t + offset
            yb = result.baseline.val_pred[k][:, j]
            yf = result.final.val_pred[k][:, j]
            axes[0].plot(t, seg.y[:, j], color="0.3", lw=0.8,
                         label="measured" if k == 0 else None)
            axes[0].plot(t, yb, color="tab:orange", lw=0.8,
                         label=f"baseline ({result.baseline.val.fit_percent[j]:.1f} %)"
                         if k == 0 else None)
            if result.final is not result.baseline:
                axes[0].plot(t, yf, color="tab:blue", lw=0.8,
                             label=f"final ({result.final.val.fit_percent[j]:.1f} %)"
                             if k == 0 else None)
            axes[1].plot(t, seg.y[:, j] - yb, color="tab:orange", lw=0.6,
                         label="baseline" if k == 0 else None)
            if result.final is not result.baseline:
                axes[1].plot(t, seg.y[:, j] - yf, color="tab:blue", lw=0.6,
                             label="final" if k == 0 else None)
            offset = t[-1] + seg.dt
        unit = result.description.structure.speed_unit
        axes[0].set_ylabel(f"{name} [{unit}]")
        axes[0].set_title(f"Validation data: measured vs simulated {name}")
        axes[0].legend(loc="upper right")
        axes[1].set_ylabel("residual")
        axes[1].set_xlabel("time [s] (validation segments back to back)")
        axes[1].legend(loc="upper right")
        fig.tight_layout()
        p = out / f"fit_{name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def _val_segments(result: IdentificationResult) -> list[Any]:
    return list(result.val_segments)


def plot_residuals(result: IdentificationResult, out: Path) -> list[Path]:
    """ACF (with the white bound) and CCF per input (Bartlett and white bounds), validation
    data, baseline and final; one PNG per output."""
    plt = _plt()
    paths = []
    for rb, rf in zip(result.baseline.resid_val, result.final.resid_val, strict=True):
        inputs = list(rf.ccf)
        fig, axes = plt.subplots(1 + len(inputs), 1, figsize=(9, 2.8 * (1 + len(inputs))))
        axes = np.atleast_1d(axes)
        lags = np.arange(rf.lags + 1)
        axes[0].stem(lags, rb.acf, linefmt="C1-", markerfmt="C1o", basefmt=" ",
                     label="baseline")
        axes[0].stem(lags + 0.25, rf.acf, linefmt="C0-", markerfmt="C0o", basefmt=" ",
                     label="final")
        axes[0].axhspan(-rf.acf_bound, rf.acf_bound, color="0.85", label="99 % (white)")
        axes[0].set_title(f"{rf.output}: residual autocorrelation (validation); Ljung-Box p "
                          f"= {rf.ljung_box_p:.2g} (final)")
        axes[0].legend(loc="upper right", fontsize=8)
        cl = np.arange(-rf.lags, rf.lags + 1)
        for ax, name in zip(axes[1:], inputs, strict=True):
            ax.stem(cl, rb.ccf[name], linefmt="C1-", markerfmt="C1o", basefmt=" ",
                    label="baseline")
            ax.stem(cl + 0.25, rf.ccf[name], linefmt="C0-", markerfmt="C0o", basefmt=" ",
                    label="final")
            ax.axhspan(-rf.ccf_bound[name], rf.ccf_bound[name], color="0.85",
                       label="99 % Bartlett, all lags (test)")
            ax.axhline(rf.ccf_bound_per_lag[name], color="0.5", ls="--", lw=0.8,
                       label="99 % Bartlett, per lag")
            ax.axhline(-rf.ccf_bound_per_lag[name], color="0.5", ls="--", lw=0.8)
            ax.axhline(rf.ccf_bound_white, color="r", ls=":", lw=0.8, label="z/sqrt(N) (white)")
            ax.axhline(-rf.ccf_bound_white, color="r", ls=":", lw=0.8)
            ax.set_title(f"cross-correlation residual {rf.output} vs input {name} "
                         f"(lag > 0: residual after input)")
            ax.legend(loc="upper right", fontsize=8)
        axes[-1].set_xlabel("lag [samples]")
        fig.tight_layout()
        p = out / f"resid_{rf.output}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def plot_spectrum(result: IdentificationResult, out: Path) -> list[Path]:
    """Welch PSD of the validation residual, baseline vs final, one PNG per output."""
    plt = _plt()
    paths = []
    for j, name in enumerate(result.description.output_names):
        fig, ax = plt.subplots(figsize=(9, 4))
        sb, sf = result.baseline.spectrum_val[j], result.final.spectrum_val[j]
        ax.semilogy(sb.freq[1:], sb.psd[1:], color="tab:orange", lw=0.8, label="baseline")
        ax.semilogy(sf.freq[1:], sf.psd[1:], color="tab:blue", lw=0.8, label="final")
        ax.axvline(sf.peak_hz, color="k", ls=":", lw=0.8, label=f"peak {sf.peak_hz:.3g} Hz")
        ax.set_xscale("log")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("PSD")
        ax.set_title(f"{name}: validation residual spectrum")
        ax.legend()
        fig.tight_layout()
        p = out / f"spectrum_{name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def plot_candidates(result: IdentificationResult, out: Path) -> Path | None:
    """Projected scores (R^2, %) of every candidate per round, accepted ones highlighted."""
    if not result.rounds:
        return None
    plt = _plt()
    accepted = {(d.round, d.score.label) for d in result.accepted}
    fig, axes = plt.subplots(len(result.rounds), 1,
                             figsize=(9, 2.2 + 0.35 * max(len(r) for r in result.rounds)
                                      * len(result.rounds)))
    axes = np.atleast_1d(axes)
    for i, (ax, rnd) in enumerate(zip(axes, result.rounds, strict=True)):
        labels = [s.label for s in rnd][::-1]
        vals = [100 * s.r2 for s in rnd][::-1]
        colors = ["tab:green" if (i + 1, s.label) in accepted else "0.6" for s in rnd][::-1]
        ax.barh(labels, vals, color=colors)
        ax.set_xscale("symlog", linthresh=0.1)
        ax.set_title(f"round {i + 1}: residual SS explained after projection [%] "
                     "(green = accepted)")
    fig.tight_layout()
    p = out / "candidates.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def plot_linear(result: IdentificationResult, out: Path) -> Path:
    """Step response and Bode magnitude/phase of the final model's linear part (C = I)."""
    plt = _plt()
    A, B = result.final.linear()
    nx, nu = B.shape
    ins = result.description.input_names
    outs = result.description.output_names
    eig = np.linalg.eigvals(A)
    slow = float(np.min(np.abs(eig.real))) if eig.size else 1.0
    fast = float(np.max(np.abs(eig))) if eig.size else 1.0
    tend = 6.0 / max(slow, 1e-6)
    t = np.linspace(0.0, min(tend, 1e4), 600)
    w = np.logspace(np.log10(max(slow, 1e-3) / 20), np.log10(max(fast, 1e-2) * 20), 400)
    fig, axes = plt.subplots(3, 1, figsize=(9, 9))
    Ad, Gd = zoh(A, float(t[1] - t[0]))
    for i in range(nu):
        d = np.tile(Gd @ B[:, i], (t.size, 1))
        yy = simulate_linear(Ad, d, np.zeros(nx))
        for j in range(nx):
            axes[0].plot(t, yy[:, j], label=f"{ins[i]} -> {outs[j]}")
            Hj = _freq(A, B[:, i], j, w)
            axes[1].loglog(w / (2 * np.pi), np.abs(Hj), label=f"{ins[i]} -> {outs[j]}")
            axes[2].semilogx(w / (2 * np.pi), np.degrees(np.unwrap(np.angle(Hj))))
    axes[0].set_title("linear part of the final model: unit-step response")
    axes[0].set_xlabel("time [s]")
    axes[0].legend(fontsize=8)
    axes[1].set_title("Bode magnitude")
    axes[1].set_ylabel("|H|")
    axes[2].set_ylabel("phase [deg]")
    axes[2].set_xlabel("frequency [Hz]")
    fig.tight_layout()
    p = out / "linear_step_bode.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def _freq(A: Array, b: Array, j: int, w: Array) -> NDArray[np.complex128]:
    nx = A.shape[0]
    out = np.empty(w.size, dtype=complex)
    for k, wk in enumerate(w):
        out[k] = np.linalg.solve(1j * wk * np.eye(nx) - A, b)[j]
    return out


# ---------------------------------------------------------------------------------------------
# Markdown


def _f(x: Any, nd: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(v):
        return "-"
    return f"{v:.{nd}g}"


def build_markdown(rep: dict[str, Any], plots: Sequence[Path]) -> str:
    """Human report from the JSON content."""
    lines = [f"# Identification report: {rep['description']['name']}", ""]
    lines += [f"Description: `{rep['description']['source']}`  ",
              f"Estimation bags: {', '.join(f'`{b}`' for b in rep['estimation_bags'])}  ",
              f"Validation bags: {', '.join(f'`{b}`' for b in rep['validation_bags'])}  ",
              f"Run time: {rep['seconds']:.1f} s", ""]
    b, f = rep["baseline"], rep["final"]
    lines += ["## Summary (simulated output, validation data)", "",
              "| output | baseline fit % | final fit % | baseline RMSE | final RMSE |",
              "|---|---|---|---|---|"]
    for o in rep["outputs"]:
        lines.append(f"| {o} | {_f(b['fit_percent'][o])} | {_f(f['fit_percent'][o])} | "
                     f"{_f(b['rmse'][o])} | {_f(f['rmse'][o])} |")
    lines += ["", "Estimation data: " + ", ".join(
        f"{o}: baseline {_f(b['estimation']['fit_percent'][o])} %, final "
        f"{_f(f['estimation']['fit_percent'][o])} %" for o in rep["outputs"]), ""]
    lines += ["| model | loss | FPE | AIC | BIC (estimation data) | estimated numbers |",
              "|---|---|---|---|---|---|"]
    for lab, st in (("baseline", b), ("final", f)):
        e = st["estimation"]
        lines.append(f"| {lab} | {_f(e['loss'])} | {_f(e['fpe'])} | {_f(e['aic'], 8)} | "
                     f"{_f(e['bic'], 8)} | {e['n_params']} |")
    lines += ["", "## Parameters (final model)", "", "| parameter | value | std dev |",
              "|---|---|---|"]
    for k, v in f["parameters"].items():
        lines.append(f"| {k} | {_f(v, 6)} | {_f(f['parameter_std'].get(k, float('nan')), 3)} |")
    ms = f.get("multistart") or {}
    if ms:
        lines += ["", f"Multi-start: {ms['n_starts']} start(s), {ms['n_at_best']} reached the "
                  f"best cost; {ms['local_minima_found']} ended in another (local) minimum."]
    lines += ["", "Standard deviations come from the Jacobian assuming white residuals; with "
              "the coloured residuals below they are optimistic.", ""]
    lines += ["## Effects (ranked, strongest first)", ""]
    effs = rep["effects"] if rep["effects"][0]["name"] != "none" else rep.get("candidates", [])
    if rep["effects"][0]["name"] == "none":
        lines += ["No candidate was accepted: `effects = [none]`, final = baseline.", ""]
    lines += ["| effect | where | accepted | projected R2 % | LM p | refit LR | dBIC | "
              "validation fit | parameters |", "|---|---|---|---|---|---|---|---|---|"]
    for e in effs or []:
        ev = e["evidence"]
        ref = ev.get("refits") or []
        lr = _f(ref[-1]["lr"]) if ref else "-"
        db = _f(ref[-1]["delta_bic"]) if ref else "-"
        vf = (f"{_f(ref[-1]['validation_fit_before'])} -> {_f(ref[-1]['validation_fit_after'])}"
              if ref else "-")
        pars = ", ".join(f"{k}={_f(v)}" for k, v in e["parameters"].items())
        lines.append(f"| {e['name']} | {e['where']} | {'yes' if e['accepted'] else 'no'} | "
                     f"{_f(ev['r2_projected'] * 100)} | {_f(ev['p_value'], 2)} | {lr} | {db} | "
                     f"{vf} | {pars} |")
    lines += ["", "Decisions:", ""]
    for d in rep["decisions"]:
        lines.append(f"- round {d['round']}: {d['candidate']}: "
                     f"{'accepted' if d['accepted'] else 'not accepted'}: {d['reason']}")
    lines += ["", "## What is left", ""]
    lines += [f"- {s}" for s in rep["remaining"]]
    if rep["notes"]:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in rep["notes"]]
    lines += ["", "## Method", "",
              "Continuous-time output-error model (C = I, K = 0) simulated with an exact "
              "zero-order hold (matrix exponential); effect terms held over each step; Coulomb "
              "friction with a stick rule. Parameters and each segment's initial state by "
              "`scipy.optimize.least_squares` from several starts. Fit % is MATLAB's `compare` "
              "figure of the simulated output; validation initial states are estimated with the "
              "parameters fixed. Candidates are scored by the residual sum of squares their "
              "output sensitivities explain after projecting out the model's own parameter "
              "sensitivities; the significant ones are refitted, and one is accepted only if the "
              "likelihood-ratio test and BIC on the estimation data and the validation fit all "
              "improve. Residual bounds: 99 %; cross-correlation bounds by Bartlett's formula "
              "(valid for coloured residual and input).", ""]
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots]
    return "\n".join(lines) + "\n"


def write_report(result: IdentificationResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``report.json``, ``report.md`` and the PNG plots into ``out_dir`` (created).

    Args:
        result: the identification result.
        out_dir: output directory.

    Returns:
        Paths by name (``json``, ``md``, ``plots:<file>``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = build_report(result)
    paths: dict[str, Path] = {}
    jp = out / "report.json"
    jp.write_text(json.dumps(rep, indent=2, allow_nan=False) + "\n")
    paths["json"] = jp
    plots: list[Path] = []
    if result.val_segments:
        plots += plot_fits(result, out)
    plots += plot_residuals(result, out)
    plots += plot_spectrum(result, out)
    cp = plot_candidates(result, out)
    if cp is not None:
        plots.append(cp)
    plots.append(plot_linear(result, out))
    for p in plots:
        paths[f"plots:{p.name}"] = p
    mp = out / "report.md"
    mp.write_text(build_markdown(rep, plots))
    paths["md"] = mp
    return paths
