"""Identification report, the data: ``report.json`` (the contract's keys plus details).

``report.json`` holds the contract's minimum keys (``estimation_bags``, ``validation_bags``,
``baseline``/``final`` with ``fit_percent``, ``rmse`` (validation data) and ``parameters``, and the
ranked ``effects``) plus: ``parameter_std``, figures on estimation and validation data (loss, FPE,
AIC, BIC), residual tests, the multi-start summary, every round's candidate scores, the
accept/reject decisions and an honest ``remaining`` list (what the final model leaves in the
residual). When no candidate is accepted, ``effects`` is ``[{"name": "none", "accepted": true}]``
and ``final`` equals ``baseline``.

Trust: ``warnings`` (the data warnings of loading, parameters the recording does not determine,
parameters at a bound, a suspect optimum, relative standard deviations above 100 %, drift),
``identifiability`` (the check before fitting, :mod:`dvt_identify.identifiability`), ``drift``
(:mod:`dvt_identify.drift`); standard deviations are HAC sandwich figures
(:mod:`dvt_identify.uncertainty`). The residual remarks are calibrated against the sensor noise:
a residual is called coloured only when its structured share (the part above the sensor floor
estimated from its first difference) is at least :data:`STRUCTURED_SHARE`.

Effects are ranked: accepted ones in the order they were accepted (each was the strongest of its
round by the refit's likelihood ratio), then the others by the largest likelihood ratio of their
refits, then by their last projected score.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.identifiability import advice_for
from dvt_identify.loop import Decision, IdentificationResult, Stage, stage_floors
from dvt_identify.resid import STRUCTURED_SHARE
from dvt_identify.scoring import CandidateScore
from dvt_identify.uncertainty import NoiseFloor

Array = NDArray[np.float64]
PEAK_RATIO = 5.0
"""A spectrum bin this many times the local median density is a prominent peak."""
MAX_RELATIVE_STD = 1.0
"""A fitted parameter whose relative standard deviation exceeds this gets a warning."""


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


def relative_std(stage: Stage) -> dict[str, float]:
    """``std / |value|`` of every estimated parameter (``inf`` for a zero value)."""
    vals = stage.parameters()
    out = {}
    for n, sd in stage.fit.parameter_std().items():
        v = abs(float(vals.get(n, math.nan)))
        out[n] = float(sd) / v if v > 0 else math.inf
    return out


def at_bounds(stage: Stage) -> list[str]:
    """Names of parameters at a bound (``at_bounds_`` of the fit when it has it, else the
    parameters within 1e-6 relative of a finite bound)."""
    fit = stage.fit
    given = getattr(fit, "at_bounds_", None)
    if given is not None:
        return [str(n) for n in given]
    out = []
    for spec, v, free in zip(fit.model.specs, fit.theta_, fit.model.free, strict=True):
        if not free:
            continue
        for b in (spec.lower, spec.upper):
            if math.isfinite(b) and abs(float(v) - b) <= 1e-6 * max(abs(b), 1e-9):
                out.append(spec.name)
                break
    return out


def suspect(stage: Stage) -> list[str]:
    """Reasons the fit's optimum is suspect (``suspect_`` of the fit; empty without it)."""
    return [str(r) for r in (getattr(stage.fit, "suspect_", None) or [])]


def residual_floors(stage: Stage, val: Sequence[Any]) -> list[NoiseFloor]:
    """Noise floor and structured share of each output's validation residual
    (:func:`dvt_identify.loop.stage_floors`: the augment loop's own verdict)."""
    return stage_floors(stage, val) if val else []


def stage_dict(stage: Stage, units: dict[str, str], val: Sequence[Any] = ()) -> dict[str, Any]:
    """Contract view of a stage (validation figures) plus details."""
    val_fig = stage.val.as_dict()
    floors = residual_floors(stage, val)
    return {
        "label": stage.label,
        "fit_percent": val_fig["fit_percent"],
        "rmse": val_fig["rmse"],
        "parameters": stage.parameters(),
        "parameter_std": stage.fit.parameter_std(),
        "parameter_relative_std": relative_std(stage),
        "parameter_std_method": ("HAC sandwich (Bartlett lag window, the longer of Andrews' "
                                 "AR(1) and Newey-West's nonparametric bandwidth)"),
        "at_bounds": at_bounds(stage),
        "suspect": suspect(stage),
        "effects": [e.label() for e in stage.effects],
        "validation": val_fig,
        "estimation": stage.est.as_dict(),
        "validation_initial_states": [x.tolist() for x in stage.val_x0],
        "estimation_initial_states": [x.tolist() for x in stage.fit.x0_],
        "residual_validation": {r.output: r.as_dict() for r in stage.resid_val},
        "residual_estimation": {r.output: r.as_dict() for r in stage.resid_est},
        "residual_spectrum_peak_hz": {n: sp.peak_hz for n, sp in
                                      zip(stage.val.output_names, stage.spectrum_val,
                                          strict=True)},
        "residual_noise_floor": {n: {"rms": f.rms, "sensor_floor_rms": f.floor_rms,
                                     "structured_share": f.structured_share}
                                 for n, f in zip(stage.val.output_names, floors, strict=False)},
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
    floors = residual_floors(fin, result.val_segments)
    for k, (r, sp) in enumerate(zip(fin.resid_val, fin.spectrum_val, strict=True)):
        nf = floors[k] if k < len(floors) else None
        structured = nf is None or not (nf.structured_share < STRUCTURED_SHARE)
        if r.white:
            out.append(f"{r.output}: the validation residual is white within the 99 % bounds "
                       f"(Ljung-Box p = {r.ljung_box_p:.3g}).")
        elif not structured and nf is not None:
            struct = math.sqrt(max(nf.rms ** 2 - nf.floor_rms ** 2, 0.0))
            out.append(f"{r.output}: the validation residual is close to the sensor noise "
                       f"floor: {100 * nf.structured_share:.2g} % of its variance lies above "
                       f"what the output and input noise give (RMS {nf.rms:.3g}, noise floor "
                       f"{nf.floor_rms:.3g}, structured part {struct:.3g}), below the "
                       f"{100 * STRUCTURED_SHARE:g} % threshold of a structured residual; "
                       f"its correlation (lag-1 {r.acf[1]:.3f}) shows no model error worth "
                       "modelling.")
        else:
            share = (f"{100 * nf.structured_share:.2g} % of its variance above the sensor "
                     f"noise floor, " if nf is not None else "")
            out.append(f"{r.output}: the validation residual is coloured ({share}Ljung-Box "
                       f"Q = {r.ljung_box:.4g}, p = {r.ljung_box_p:.3g}; lag-1 autocorrelation "
                       f"{r.acf[1]:.3f}): the OE model leaves correlated error.")
        for name, ok in r.independent.items():
            if ok:
                out.append(f"{r.output}: residual independent of input {name} within the 99 % "
                           f"Bartlett bounds (max |CCF|/bound = {r.max_ccf_ratio[name]:.2f}).")
            else:
                out.append(f"{r.output}: residual still correlated with input {name} (max "
                           f"|CCF|/bound = {r.max_ccf_ratio[name]:.2f}): input-driven dynamics "
                           "are not fully modelled.")
        if sp.peak_ratio > PEAK_RATIO and structured:
            out.append(f"{r.output}: the validation residual spectrum has a peak at "
                       f"{sp.peak_hz:.3g} Hz ({sp.peak_ratio:.3g} x the median density within "
                       "half an octave), e.g. an unmodelled resonance or periodic disturbance.")
        elif sp.peak_ratio > PEAK_RATIO:
            out.append(f"{r.output}: no peak above the sensor noise in the validation residual "
                       f"spectrum (largest bin {sp.peak_ratio:.2g} x the local median, at "
                       f"{sp.peak_hz:.3g} Hz, in a residual at the noise floor).")
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
    accepted_labels = {d.score.label for d in result.accepted}
    seen: set[str] = set()
    for d in result.decisions:  # large but not significant: said, not silenced
        if d.likely and d.score.label not in accepted_labels and d.score.label not in seen:
            seen.add(d.score.label)
            out.append(f"Likely, not proven: {d.score.label} (round {d.round}): {d.reason}.")
    out.extend(result.description.notes)
    return out


def build_warnings(result: IdentificationResult) -> list[str]:
    """What a reader must know before trusting the final model: the data warnings of loading,
    the parameters the recording does not determine (check before fitting, and a relative
    standard deviation above 100 % after it), parameters at a bound, a suspect optimum, and
    drift."""
    out = [f"data: {w}" for w in result.data_warnings]
    chk = result.identifiability
    flagged: set[str] = set()
    if chk is not None:
        for pc in chk.undetermined:
            flagged.add(pc.name)
            out.append(pc.statement())
    fin = result.final
    vals = fin.parameters()
    for name, rel in relative_std(fin).items():
        if not rel <= MAX_RELATIVE_STD:
            std = fin.fit.parameter_std().get(name, math.nan)
            rel_text = f"{100 * rel:.3g} %" if math.isfinite(rel) else "infinite"
            out.append(f"not determined by this recording: {name} = {vals.get(name, math.nan):.6g}"
                       f" has a relative standard deviation of {rel_text} (std {std:.3g}) > "
                       f"{100 * MAX_RELATIVE_STD:g} %; "
                       + advice_for(name, result.description, chk)
                       + (" (already flagged before fitting)" if name in flagged else ""))
    for name in at_bounds(fin):
        spec = next((sp for sp in fin.fit.model.specs if sp.name == name), None)
        where = (f" (bounds [{spec.lower:g}, {spec.upper:g}])" if spec is not None else "")
        out.append(f"parameter at a bound: {name} = {vals.get(name, math.nan):.6g}{where}: the "
                   "optimum is constrained, its standard deviation does not apply")
    for reason in suspect(fin):
        out.append(f"suspect optimum: {reason}")
    if result.drift is not None:
        out += [f"drift: {p.statement()}" for p in result.drift.drifting]
    out += time_clock_warnings(result)
    return out


def time_clock_warnings(result: IdentificationResult) -> list[str]:
    """A term clocked on time (``clock: time``) in the final model restarts its phase at
    ``t = 0`` in every segment: across several bags its fitted phase is a compromise and holds
    on new data only if each recording starts in phase with the disturbance."""
    n_est = len(getattr(result, "est_segments", []) or []) or len(result.estimation_bags)
    n_val = len(result.val_segments)
    out = []
    for e in result.final.effects:
        if str(e.options.get("clock", "")).strip().lower() == "time" and n_est + n_val > 1:
            out.append(f"{e.label()} is clocked on time: its phase restarts at t = 0 in each of "
                       f"the {n_est + n_val} segments ({n_est} estimation, {n_val} "
                       "validation), so its fitted phase holds on other data only if every "
                       "recording starts in phase with the disturbance; clock it on a member's "
                       "angle instead")
    return out


def _selection(result: IdentificationResult) -> dict[str, str]:
    """Which figure is which: the data that chose the effects and the test figure."""
    how = getattr(result, "selection", "validation")
    n_bags = len({s.name.split("#")[0] for s in getattr(result, "est_segments", []) or []})
    chosen = {"holdout": "the held-out last part of each estimation segment (the 'validation' "
                         "figures are on it, by the models fitted without it; the parameters "
                         "are the chosen models refitted on the whole segments)",
              "cv": f"leave-one-bag-out cross-validation across the {n_bags} estimation bags "
                    "(the 'validation' figures are out of fold: each bag simulated by the "
                    "model fitted on the other bags; the parameters are the fit on all of "
                    "them)"}
    return {"chosen_on": chosen.get(how, "the validation bags"),
            "validation_figures": ("selection figures: these data chose the effects, so they "
                                   "are not an independent test"),
            "test_figures": ("on test bags read after every choice: no part in fitting or "
                             "choosing" if getattr(result, "test", None) is not None
                             else "none (pass --test BAG...)")}


def reference_summary(result: IdentificationResult) -> dict[str, Any] | None:
    """The linear reference beside the physical model (``None`` without one): its order and
    figures, and ``flags``: plain statements when the physical model (the final one) scores
    worse than the reference on the validation (selection) data or on the test data, by the
    mean fit over the outputs; the report prints them first."""
    ref = result.reference
    if ref is None:
        return None
    out: dict[str, Any] = ref.as_dict()
    flags = []
    phys, lin = result.final.val.mean_fit, ref.val.mean_fit
    out["validation_mean_fit"] = {"physical": phys, "linear_reference": lin}
    role = "selection" if result.selection in ("holdout", "cv") else "validation"
    if lin > phys:
        flags.append(f"The physical model scores worse than the black-box linear reference "
                     f"(order {ref.model.order_}) on the {role} data: mean fit {phys:.2f} % "
                     f"against {lin:.2f} %.")
    test = result.test
    if test is not None and getattr(test, "reference", None) is not None:
        tp, tl = test.final.mean_fit, test.reference.mean_fit
        out["test_mean_fit"] = {"physical": tp, "linear_reference": tl}
        if tl > tp:
            flags.append(f"On the test data (no part in any choice) the physical model scores "
                         f"worse than the linear reference: mean fit {tp:.2f} % against "
                         f"{tl:.2f} %.")
    out["flags"] = flags
    return out


def build_report(result: IdentificationResult) -> dict[str, Any]:
    """The ``report.json`` content."""
    desc = result.description
    units = {n: desc.structure.speed_unit or "" for n in desc.output_names}
    baseline = stage_dict(result.baseline, units, result.val_segments)
    accepted = result.accepted
    if accepted:
        effects = ranked_effects(result)
        final = stage_dict(result.final, units, result.val_segments)
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
        "warnings": build_warnings(result),
        "identifiability": (result.identifiability.as_dict()
                            if result.identifiability is not None else None),
        "drift": result.drift.as_dict() if result.drift is not None else None,
        "settings": {"starts": result.config.starts, "refit_starts": result.config.refit_starts,
                     "alpha": result.config.alpha,
                     "validation_test": "Diebold-Mariano one-sided at alpha (HAC variance)",
                     "min_validation_gain": result.config.min_validation_gain,
                     "drift_windows": result.config.drift_windows,
                     "drift_min_change": result.config.drift_min_change,
                     "augment": result.config.augment, "fit_dt_s": result.fit_dt,
                     "fit_decimate": result.config.fit_decimate},
        "notes": result.notes,
        "seconds": result.seconds,
        "selection": _selection(result),
        "test": result.test.as_dict() if getattr(result, "test", None) is not None else None,
        "linear_reference": reference_summary(result),
        "records_agree": (result.agreement.as_dict() if getattr(result, "agreement", None)
                          is not None else None),
        "records_carrier": (result.carrier.as_dict() if getattr(result, "carrier", None)
                            is not None else None),
        "test_spread": (result.spread.as_dict() if getattr(result, "spread", None)
                        is not None else None),
    }
    if rep["candidates"] is None:
        del rep["candidates"]
    return dict(_clean(rep))
