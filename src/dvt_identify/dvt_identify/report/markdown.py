"""Identification report, the Markdown (``report.md``) and the writer of the whole report
(``report.json``, ``report.md``, plots).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.loop import IdentificationResult
from dvt_identify.report.data import build_report
from dvt_identify.report.plots import (
    _PngWriter,
    plot_candidates,
    plot_fits,
    plot_linear,
    plot_residuals,
    plot_spectrum,
)

Array = NDArray[np.float64]

def _f(x: Any, nd: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(v):
        return "-"
    return f"{v:.{nd}g}"


def _carrier_lines(c: dict[str, Any] | None, outputs: Sequence[str]) -> list[str]:
    """The test table of the plain final model and the models carrying the records'
    disagreement (:mod:`dvt_identify.carrier`), with the choice made on estimation data."""
    if not c:
        return []
    unit = f" [{c['unit']}]" if c.get("unit") else ""
    kinds = {"none": "final model (plain)", "constant": "final + constant input bias",
             "direction": "final + input bias per direction of motion"}
    lines = ["", f"Models carrying the disagreement: a disturbance state (an input bias) set, "
             f"like the initial state, in each test segment's first {c['init_window']} samples "
             "only; the rest scored untouched.", "",
             "| model | chosen on estimation data | "
             + " | ".join(f"{o} fit % | {o} RMSE" for o in outputs)
             + f" | bias set in the window ± std{unit} | the windows' bias on estimation "
             f"blocks (RMS){unit} |",
             "|---|---|" + "---|---|" * len(outputs) + "---|---|"]
    scatter = {s["kind"]: s.get("window_bias_scatter") or [] for s in c["choice"]["scores"]}
    for row in c["test"]:
        f = row["figures"]
        bias = "; ".join(", ".join(
            f"{lab} {_f(v, 3)} ± {_f(s, 2)}" if s is not None else f"{lab} not seen (0)"
            for lab, v, s in zip(b["labels"], b["bias"], b["std"], strict=True))
            for b in row["biases"]) or "-"
        lines.append(f"| {kinds.get(row['kind'], row['kind'])} | "
                     f"{'**yes**' if row['kind'] == c['chosen'] else 'no'} | "
                     + " | ".join(f"{_f(f['fit_percent'][o])} | {_f(f['rmse'][o])}"
                                  for o in outputs) + f" | {bias} | "
                     + (", ".join(_f(v, 3) for v in scatter.get(row["kind"], [])) or "-")
                     + " |")
    lines += ["", f"Choice on estimation data only: {c['choice']['reason']}."]
    return lines


def _lr_cell(x: Any) -> str:
    """A refit's likelihood ratio for the table: <= 0 (the loss did not decrease) as
    "0 (no improvement)"; the raw value stays in ``report.json``."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "-"
    return "0 (no improvement)" if v <= 0 else _f(v)


def build_markdown(rep: dict[str, Any], plots: Sequence[Path]) -> str:
    """Human report from the JSON content."""
    lines = [f"# Identification report: {rep['description']['name']}", ""]
    lines += [f"Description: `{rep['description']['source']}`  ",
              f"Estimation bags: {', '.join(f'`{b}`' for b in rep['estimation_bags'])}  ",
              f"Validation bags: {', '.join(f'`{b}`' for b in rep['validation_bags'])}  ",
              f"Run time: {rep['seconds']:.1f} s", ""]
    lr = rep.get("linear_reference")
    if lr and lr.get("flags"):  # first of all: a physical model worse than the yardstick
        lines += ["## Worse than the linear reference", ""] + [f"**{x}**" for x in lr["flags"]]
        lines += ["", "A black-box LTI model of the same data (subspace start, output-error "
                  "refinement, order chosen on the selection data) is simulated and scored "
                  "exactly like the physical model; see the summary below.", ""]
    chk = rep.get("identifiability")
    if chk:  # first: what the recording does not determine, what is fixed or still fitted
        lines += ["## Is this recording enough? (check before fitting)", ""]
        und = [q for q in chk["parameters"] if not q["determined"]]
        if not und and chk.get("determined_at_fit"):
            lines.append("At the fitted values the recording determines every parameter of "
                         "the baseline model; at the priors the check found some undetermined "
                         "(below).")
        elif not und:
            lines.append("The recording determines every parameter of the baseline model.")
        else:
            fixed = [q["name"] for q in und if q["fixed_at_prior"]]
            kept = [q["name"] for q in und if not q["fixed_at_prior"]]
            if fixed:
                lines += [f"**Fixed at their priors** (removed from the fit, their input never "
                          f"varies: {', '.join(chk.get('removed_effects') or [])}): "
                          f"{', '.join(fixed)}.", ""]
            if kept:
                lines += [f"**Still fitted, not to be trusted:** {', '.join(kept)}.", ""]
            lines += ["| parameter | prior | predicted relative std | why | fixed at prior | "
                      "experiment or advice |", "|---|---|---|---|---|---|"]
            for q in und:
                prs = q["predicted_relative_std"]
                prs_text = f"{_f(100 * prs, 3)} %" if prs is not None else "infinite"
                own = q.get("advice_from", "description") == "description"
                exp = f"`{q['experiment']}`" if own else f"{q['experiment']} ({q['purpose']})"
                lines.append(f"| {q['name']} | {_f(q['prior'], 6)} | {prs_text} | "
                             f"{q['reason']} | {'yes' if q['fixed_at_prior'] else 'no'} | "
                             f"{exp} |")
        revised = chk.get("determined_at_fit") or {}
        if revised:  # the Fisher rule taken again at the fitted values
            figs = {q["name"]: q["predicted_relative_std"] for q in chk["parameters"]}
            lines += ["", "**Determined at the fitted values** (the check before fitting is "
                      "local, at the priors, with an assumed residual level; taken again at "
                      "the fit with its own residual):", "",
                      "| parameter | predicted relative std at the fit | at the priors |",
                      "|---|---|---|"]
            lines += [f"| {n} | {_f(100 * figs[n], 3)} % | {why} |"
                      for n, why in revised.items()]
        lines.append("")
    b, f = rep["baseline"], rep["final"]
    lv = (lr or {}).get("validation") if lr else None
    head = ("| output | baseline fit % | final fit % | baseline RMSE | final RMSE |"
            + (" linear reference fit % | linear reference RMSE |" if lv else ""))
    lines += ["## Summary (simulated output, validation data)", "", head,
              "|---|---|---|---|---|" + ("---|---|" if lv else "")]
    for o in rep["outputs"]:
        lines.append(f"| {o} | {_f(b['fit_percent'][o])} | {_f(f['fit_percent'][o])} | "
                     f"{_f(b['rmse'][o])} | {_f(f['rmse'][o])} |"
                     + (f" {_f(lv['fit_percent'][o])} | {_f(lv['rmse'][o])} |" if lv else ""))
    if lr:
        lines += ["", f"Linear reference: order {lr['order']} (chosen on {lr['chosen_on']}; "
                  f"fitted in {lr['seconds']:.1f} s), poles at "
                  + ", ".join(f"{p:.3g}" for p in lr["poles_hz"]) + " Hz."]
    lines += ["", "Estimation data: " + ", ".join(
        f"{o}: baseline {_f(b['estimation']['fit_percent'][o])} %, final "
        f"{_f(f['estimation']['fit_percent'][o])} %" for o in rep["outputs"]), ""]
    lines += ["| model | loss | FPE | AIC | BIC (estimation data) | estimated numbers |",
              "|---|---|---|---|---|---|"]
    for lab, st in (("baseline", b), ("final", f)):
        e = st["estimation"]
        lines.append(f"| {lab} | {_f(e['loss'])} | {_f(e['fpe'])} | {_f(e['aic'], 8)} | "
                     f"{_f(e['bic'], 8)} | {e['n_params']} |")
    sel = rep.get("selection") or {}
    if sel:
        lines += ["", f"Effects chosen on {sel['chosen_on']}: the validation figures above are "
                  "selection figures.", ""]
    t = rep.get("test")
    if t:
        tr = t.get("linear_reference")
        lines += ["## Test (took no part in any choice)", "",
                  f"Test bags: {', '.join(f'`{x}`' for x in t['bags'])}; initial state "
                  f"{t['initial_state']}.", "",
                  "| output | baseline fit % | final fit % | baseline RMSE | final RMSE |"
                  + (" linear reference fit % | linear reference RMSE |" if tr else ""),
                  "|---|---|---|---|---|" + ("---|---|" if tr else "")]
        for o in rep["outputs"]:
            lines.append(f"| {o} | {_f(t['baseline']['fit_percent'][o])} | "
                         f"{_f(t['final']['fit_percent'][o])} | {_f(t['baseline']['rmse'][o])} "
                         f"| {_f(t['final']['rmse'][o])} |"
                         + (f" {_f(tr['fit_percent'][o])} | {_f(tr['rmse'][o])} |" if tr
                            else ""))
        ag = rep.get("records_agree")
        if ag:
            lines += ["", ("**" + ag["statement"] + "**") if ag["disagree"]
                      else ag["statement"]]
        lines += _carrier_lines(rep.get("records_carrier"), rep["outputs"])
        sp = rep.get("test_spread")
        if sp:
            lines += ["", sp["statement"]]
    lines += ["", "## Parameters (final model)", "",
              "| parameter | value | std dev | relative std % |", "|---|---|---|---|"]
    rel = f.get("parameter_relative_std") or {}
    for k, v in f["parameters"].items():
        r = rel.get(k)
        rs = "-" if k not in rel else ("not determined" if r is None else _f(100 * r, 3))
        lines.append(f"| {k} | {_f(v, 6)} | {_f(f['parameter_std'].get(k, float('nan')), 3)} | "
                     f"{rs} |")
    ms = f.get("multistart") or {}
    if ms:
        lines += ["", f"Multi-start: {ms['n_starts']} start(s), {ms['n_at_best']} reached the "
                  f"best cost; {ms['local_minima_found']} ended in another (local) minimum."]
    lines += ["", "Standard deviations: HAC sandwich covariance with a Bartlett lag window "
              "(valid for coloured residuals and model error; see docs/identification.md).", ""]
    if rep.get("warnings"):
        lines += ["## Warnings", ""] + [f"- {w}" for w in rep["warnings"]] + [""]
    dr = rep.get("drift")
    if dr:
        lines += ["## Drift over the recording", ""] + [f"- {x}" for x in dr["summary"]] + [""]
    lines += ["## Effects (ranked, strongest first)", ""]
    effs = rep["effects"] if rep["effects"][0]["name"] != "none" else rep.get("candidates", [])
    if rep["effects"][0]["name"] == "none":
        lines += ["No candidate was accepted: `effects = [none]`, final = baseline.", ""]
    lines += ["| effect | where | accepted | projected R2 % | LM p | refit LR | dBIC | "
              "validation fit | validation test p | parameters |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for e in effs or []:
        ev = e["evidence"]
        ref = ev.get("refits") or []
        lr = _lr_cell(ref[-1]["lr"]) if ref else "-"
        db = _f(ref[-1]["delta_bic"]) if ref else "-"
        vf = (f"{_f(ref[-1]['validation_fit_before'])} -> {_f(ref[-1]['validation_fit_after'])}"
              if ref else "-")
        vt = (ref[-1].get("validation_test") or {}) if ref else {}
        vp = _f(vt.get("p_value"), 2) if vt else "-"
        pars = ", ".join(f"{k}={_f(v)}" for k, v in e["parameters"].items())
        lines.append(f"| {e['name']} | {e['where']} | {'yes' if e['accepted'] else 'no'} | "
                     f"{_f(ev['r2_projected'] * 100)} | {_f(ev['p_value'], 2)} | {lr} | {db} | "
                     f"{vf} | {vp} | {pars} |")
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
              "likelihood-ratio test and BIC pass on the estimation data and the validation "
              "error is significantly smaller (one-sided Diebold-Mariano test with a HAC "
              "variance at the loop's alpha). Residual bounds: 99 %; cross-correlation "
              "bounds by Bartlett's formula "
              "(valid for coloured residual and input).", ""]
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots]
    return "\n".join(lines) + "\n"


def write_report(result: IdentificationResult, out_dir: str | Path,
                 plots_enabled: bool = True) -> dict[str, Path]:
    """Write ``report.json``, ``report.md`` and the PNG plots into ``out_dir`` (created).

    Args:
        result: the identification result.
        out_dir: output directory.
        plots_enabled: draw the PNG plots (``False``: ``report.json`` and ``report.md`` only,
            for batch refits; the figures in them are the same).

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
    save = _PngWriter(background=True)
    try:
        if plots_enabled:
            if result.val_segments:
                plots += plot_fits(result, out, save)
            plots += plot_residuals(result, out, save)
            plots += plot_spectrum(result, out, save)
            cp = plot_candidates(result, out, save)
            if cp is not None:
                plots.append(cp)
            plots.append(plot_linear(result, out, save))
    finally:
        save.wait()
    for p in plots:
        paths[f"plots:{p.name}"] = p
    mp = out / "report.md"
    mp.write_text(build_markdown(rep, plots))
    paths["md"] = mp
    return paths
