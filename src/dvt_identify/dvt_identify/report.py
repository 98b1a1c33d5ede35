"""Identification report: ``report.json`` (contract keys plus details), ``report.md`` and plots.

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

import json
import math
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify import style
from dvt_identify.identifiability import experiment_for
from dvt_identify.loop import CandidateScore, Decision, IdentificationResult, Stage
from dvt_identify.resid import input_noise_response, robust_white_floor
from dvt_identify.simulation import simulate_linear, zoh
from dvt_identify.uncertainty import NoiseFloor, noise_floor

Array = NDArray[np.float64]
STRUCTURED_SHARE = 0.75
"""A validation residual is called coloured (structured) only when at least this share of its
variance lies above the sensor noise floor, i.e. its structured part's RMS is at least sqrt(3)
times the floor's. Measured on the committed recordings (validated on independent offline runs):
clean ``ident-none-1`` 0 % (sun shaft) and 61 % (carrier 3); ``ident-windage`` before windage is
modelled 80 % and 94 %."""
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
    """Noise floor and structured share of each output's validation residual.

    The floor is what the sensors alone leave in an output-error residual: the output's white
    noise (from the residual's first difference, :func:`dvt_identify.uncertainty.noise_floor`)
    plus the response of the model's linear part to the white noise of the measured inputs
    (robust first-difference floor of each input, :func:`dvt_identify.resid.input_noise_response`):
    an OE simulation is driven by the measured, noisy inputs. ``floor_rms`` is their sum in
    quadrature (at most the RMS) and ``structured_share`` the rest of the variance."""
    if not val:
        return []
    ny = len(stage.val.output_names)
    floors = [noise_floor([s.y[:, j] - p[:, j] for s, p in zip(val, stage.val_pred,
                                                                 strict=True)])
              for j in range(ny)]
    try:
        A, B = stage.linear()
        u_std = [robust_white_floor([s.u[:, i] for s in val]) for i in range(B.shape[1])]
        var_in = input_noise_response(A, B, float(val[0].dt), u_std)
    except (np.linalg.LinAlgError, ValueError):
        var_in = np.zeros(ny)
    out = []
    for j, nf in enumerate(floors):
        vi = float(var_in[j]) if j < var_in.size and math.isfinite(float(var_in[j])) else 0.0
        var = nf.rms ** 2
        if not math.isfinite(var) or var <= 0:
            out.append(nf)
            continue
        fl = min(nf.floor_rms ** 2 + vi, var)
        out.append(NoiseFloor(rms=nf.rms, floor_rms=math.sqrt(fl),
                              structured_share=float(np.clip(1.0 - fl / var, 0.0, 1.0))))
    return out


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
        "parameter_std_method": "HAC sandwich (Bartlett lag window, Andrews bandwidth)",
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
            cmd, what = experiment_for(name)
            std = fin.fit.parameter_std().get(name, math.nan)
            rel_text = f"{100 * rel:.3g} %" if math.isfinite(rel) else "infinite"
            out.append(f"not determined by this recording: {name} = {vals.get(name, math.nan):.6g}"
                       f" has a relative standard deviation of {rel_text} (std {std:.3g}) > "
                       f"{100 * MAX_RELATIVE_STD:g} %; record `{cmd}` ({what})"
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
                         "figures are on it)",
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
    }
    if rep["candidates"] is None:
        del rep["candidates"]
    return dict(_clean(rep))


# ---------------------------------------------------------------------------------------------
# Plots
#
# Drawing cost in matplotlib is mostly per axes, tick and text object, not per point. So the
# plots lay out with fixed margins instead of a second layout pass (``tight_layout``), place
# titles at a fixed height, label about six ticks an axis, let one legend serve the
# cross-correlation panels, draw an overlay only when it differs (final vs baseline), draw long
# series as their per-pixel min/max envelope (every peak stays, see :func:`envelope`), write
# log-axis labels without mathtext, and encode the PNGs with fast zlib settings in a background
# thread while the next figure is drawn (same pixels, somewhat larger files).

SaveFigure = Callable[[Any, Path], Path]
"""Writes (or, in a test, inspects) a figure and returns its path (:class:`_PngWriter`)."""
_DPI = 110
_PNG = {"compress_level": 1}
_SUPERSCRIPT = str.maketrans("0123456789-−", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻⁻")


def _plt() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (imported on first use: no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class _PngWriter:
    """Saves figures: draws in the caller's thread; with ``background`` the PNG encoding (which
    releases the GIL) runs in one worker thread while the next figure is drawn. :meth:`wait`
    returns when every file is written (re-raising a failure)."""

    def __init__(self, background: bool = False) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1) if background else None
        self._jobs: list[Future[None]] = []

    def __call__(self, fig: Any, path: Path) -> Path:
        from matplotlib.image import imsave

        fig.set_dpi(_DPI)
        fig.canvas.draw()
        rgba = np.array(fig.canvas.buffer_rgba())
        _plt().close(fig)
        job = partial(imsave, path, rgba, format="png", dpi=_DPI, pil_kwargs=dict(_PNG))
        if self._pool is None:
            job()
        else:
            self._jobs.append(self._pool.submit(job))
        return path

    def wait(self, timeout: float = 120.0) -> None:
        try:
            for job in self._jobs:
                job.result(timeout=timeout)
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)


def _title(ax: Any, text: str) -> None:
    """Axes title at a fixed height (matplotlib skips its costly search for tick labels that
    could collide with an automatically placed title; these plots have none on top)."""
    ax.set_title(text, y=1.0)


def _margins(fig: Any, left: float = 0.85, right: float = 0.2, top: float = 0.4,
             bottom: float = 0.55, hspace: float = 0.6) -> None:
    """Fixed margins [inch] (like ``tight_layout`` for the labels these plots have) and at most
    about seven (x) or five (y) labelled ticks on linear axes."""
    from matplotlib.ticker import AutoLocator, MaxNLocator

    for ax in fig.axes:
        for axis, nbins in ((ax.xaxis, 7), (ax.yaxis, 5)):
            if isinstance(axis.get_major_locator(), AutoLocator):
                axis.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))
    w, h = fig.get_size_inches()
    rows = max(len(fig.axes), 1)
    ax_h = (h - top - bottom - hspace * (rows - 1)) / rows
    fig.subplots_adjust(left=left / w, right=1 - right / w, top=1 - top / h, bottom=bottom / h,
                        hspace=hspace / max(ax_h, 1e-3))


def _log_label(text: str) -> str:
    r"""``$\mathdefault{2\times10^{-3}}$`` -> ``2×10⁻³`` (plain text: no mathtext parsing)."""
    if not (text.startswith("$\\mathdefault{") and text.endswith("}$")):
        return text
    inner = text[len("$\\mathdefault{"):-2].replace("\\times", "×").replace("\\;", " ")
    out, rest = "", inner
    while "^{" in rest:
        head, tail = rest.split("^{", 1)
        exp, rest = tail.split("}", 1)
        out += head + exp.translate(_SUPERSCRIPT)
    return out + rest


def _plain_log_labels(ax: Any, *, x: bool = False, y: bool = False) -> None:
    """Log/symlog tick labels (after the scale is set) as plain text (``10⁻³``: the scale's own
    formatters, their mathtext turned into Unicode); log axes get minor ticks at 2 and 5 per
    decade."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    for on, axis in ((x, ax.xaxis), (y, ax.yaxis)):
        if not on:
            continue
        for minor in (False, True):
            base = axis.get_minor_formatter() if minor else axis.get_major_formatter()
            fmt = FuncFormatter(lambda v, pos, f=base: _log_label(f(v, pos)))
            fmt.set_locs = base.set_locs  # type: ignore[method-assign]
            (axis.set_minor_formatter if minor else axis.set_major_formatter)(fmt)
            base.set_axis(axis)
        if axis.get_scale() == "log":
            axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))


def envelope(t: NDArray[Any], y: NDArray[Any], bins: int) -> tuple[NDArray[Any], NDArray[Any]]:
    """Min/max envelope of a long series for plotting: at most ``2 * bins`` points.

    ``t``, ``y``: shape (N,). The samples are cut into ``bins`` runs of equal length; each run
    keeps its smallest and its largest sample, in time order, at their own times. Drawn as a
    line at about one run per pixel column, the picture equals that of all N samples (every
    peak stays). Series with at most ``2 * bins`` samples are returned as they are.
    """
    n = y.shape[0]
    if n <= 2 * bins:
        return t, y
    k = -(-n // bins)
    m = -(-n // k)
    pad = np.concatenate([y, np.full(m * k - n, y[-1])]).reshape(m, k)
    base = np.arange(m) * k
    lo = np.minimum(base + np.argmin(pad, axis=1), n - 1)
    hi = np.minimum(base + np.argmax(pad, axis=1), n - 1)
    idx = np.column_stack([np.minimum(lo, hi), np.maximum(lo, hi)]).ravel()
    return t[idx], y[idx]


def plot_fits(result: IdentificationResult, out: Path,
              save: SaveFigure | None = None) -> list[Path]:
    """Measured vs simulated (baseline, final) on validation data, one PNG per output.

    Series longer than the figure is wide are drawn as their per-pixel min/max envelope.
    """
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    names = result.description.output_names
    segs = _val_segments(result)
    both = result.final is not result.baseline
    width_in, bins_total = 11.0, int(11.0 * _DPI)
    total = sum(seg.n for seg in segs) or 1
    offsets, offset = [], 0.0
    for seg in segs:
        offsets.append(offset)
        offset = offset + float(seg.t[-1]) + seg.dt
    unit = result.description.structure.speed_unit
    for j, name in enumerate(names):
        fig, axes = plt.subplots(2, 1, figsize=(width_in, 6.5), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
        for k, seg in enumerate(segs):
            t = seg.t + offsets[k]
            bins = max(bins_total * seg.n // total, 50)
            yb = result.baseline.val_pred[k][:, j]
            yf = result.final.val_pred[k][:, j]
            first = k == 0
            # the predictions under the measured trace (thin, black, on top): a prediction
            # that matches shows as a coloured edge and the measurement stays visible
            axes[0].plot(*envelope(t, yb, bins), **style.before(
                (f"baseline ({result.baseline.val.fit_percent[j]:.1f} %)" if both
                 else f"baseline = final ({result.baseline.val.fit_percent[j]:.1f} %)")
                if first else None))
            if both:
                axes[0].plot(*envelope(t, yf, bins), **style.after(
                    f"final ({result.final.val.fit_percent[j]:.1f} %)" if first else None))
            axes[0].plot(*envelope(t, seg.y[:, j], bins),
                         **style.measured("measured" if first else None))
            axes[1].plot(*envelope(t, seg.y[:, j] - yb, bins), **style.residual(
                "before", ("baseline" if both else "baseline = final") if first else None))
            if both:
                axes[1].plot(*envelope(t, seg.y[:, j] - yf, bins),
                             **style.residual("after", "final" if first else None))
        axes[0].set_ylabel(style.label(name, unit))
        _title(axes[0], f"Validation data: measured vs simulated {name} (fit % in the legend)")
        style.legend_outside(axes[0])
        axes[1].set_ylabel(style.label("measured − simulated", unit))
        axes[1].set_xlabel("time [s] (validation segments back to back)")
        style.legend_outside(axes[1])
        _margins(fig, hspace=0.15, right=style.LEGEND_WIDTH_IN)
        paths.append(save(fig, out / f"fit_{name}.png"))
    return paths


def _val_segments(result: IdentificationResult) -> list[Any]:
    return list(result.val_segments)


def _stems(ax: Any, x: NDArray[Any], y: NDArray[Any], color: str, label: str) -> None:
    """Stem plot (as ``Axes.stem``) from one line collection and one marker line."""
    ax.vlines(x, 0.0, y, colors=color, lw=1.0)
    ax.plot(x, y, "o", color=color, label=label)


def plot_residuals(result: IdentificationResult, out: Path,
                   save: SaveFigure | None = None) -> list[Path]:
    """ACF (with the white bound) and CCF per input (Bartlett and white bounds), validation
    data, baseline and final (one set of stems when the final model is the baseline); one PNG
    per output. The CCF panels share one legend."""
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    both = result.final is not result.baseline
    segs = _val_segments(result) or list(result.est_segments)  # est: cross-validated
    dt = float(segs[0].dt) if segs else None
    b_label = "baseline" if both else "baseline = final"
    for rb, rf in zip(result.baseline.resid_val, result.final.resid_val, strict=True):
        inputs = list(rf.ccf)
        fig, axes = plt.subplots(1 + len(inputs), 1, figsize=(11, 2.6 * (1 + len(inputs))))
        axes = np.atleast_1d(axes)
        for ax in axes[1:-1]:  # the cross-correlation panels share the lag axis
            ax.sharex(axes[-1])
            ax.tick_params(labelbottom=False)
        lags = np.arange(rf.lags + 1)
        _stems(axes[0], lags, rb.acf, style.BEFORE, b_label)
        if both:
            _stems(axes[0], lags + 0.25, rf.acf, style.AFTER, "final")
        axes[0].axhspan(-rf.acf_bound, rf.acf_bound, color=style.BAND,
                        label="99 % per lag (white noise)")
        _title(axes[0], f"{rf.output}: residual autocorrelation (validation); Ljung-Box p "
                f"= {rf.ljung_box_p:.2g} (final)")
        axes[0].set_ylabel(style.label("autocorrelation", style.DIMENSIONLESS))
        axes[0].set_xlabel(style.lag_label(dt))
        style.legend_outside(axes[0])
        cl = np.arange(-rf.lags, rf.lags + 1)
        for i, (ax, name) in enumerate(zip(axes[1:], inputs, strict=True)):
            _stems(ax, cl, rb.ccf[name], style.BEFORE, b_label)
            if both:
                _stems(ax, cl + 0.25, rf.ccf[name], style.AFTER, "final")
            ax.axhspan(-rf.ccf_bound[name], rf.ccf_bound[name], color=style.BAND,
                       label="99 % Bartlett, all lags\n(the test)")
            ax.axhline(rf.ccf_bound_per_lag[name], color=style.BOUND, ls="--", lw=0.8,
                       label="99 % Bartlett, per lag")
            ax.axhline(-rf.ccf_bound_per_lag[name], color=style.BOUND, ls="--", lw=0.8)
            ax.axhline(rf.ccf_bound_white, color="tab:red", ls=":", lw=0.8,
                       label="z/sqrt(N) (white)")
            ax.axhline(-rf.ccf_bound_white, color="tab:red", ls=":", lw=0.8)
            _title(ax, f"cross-correlation residual {rf.output} vs input {name} "
                   f"(lag > 0: residual after input)")
            ax.set_ylabel(style.label("cross-corr.", style.DIMENSIONLESS))
            if i == 0:
                style.legend_outside(ax, title="(all cross-\ncorrelation panels)",
                                     title_fontsize=style.LEGEND_FONTSIZE)
        if len(axes) > 1:
            axes[-1].set_xlabel(style.lag_label(dt))
        _margins(fig, left=0.8, hspace=0.8, bottom=0.5, right=style.LEGEND_WIDTH_IN)
        paths.append(save(fig, out / f"resid_{rf.output}.png"))
    return paths


def plot_spectrum(result: IdentificationResult, out: Path,
                  save: SaveFigure | None = None) -> list[Path]:
    """Welch PSD of the validation residual, baseline vs final (one line when the final model
    is the baseline), one PNG per output."""
    plt = _plt()
    save = save or _PngWriter()
    paths = []
    both = result.final is not result.baseline
    floors = residual_floors(result.final, result.val_segments)
    unit = result.description.structure.speed_unit
    for j, name in enumerate(result.description.output_names):
        fig, ax = plt.subplots(figsize=(11, 4))
        sb, sf = result.baseline.spectrum_val[j], result.final.spectrum_val[j]
        ax.loglog(sb.freq[1:], sb.psd[1:], color=style.BEFORE, lw=0.8,
                  label="baseline" if both else "baseline = final")
        if both:
            ax.loglog(sf.freq[1:], sf.psd[1:], color=style.AFTER, lw=0.8, label="final")
        # the same rule as the report's text (remaining_summary): a marker only for a peak the
        # text calls prominent; otherwise the title says where the largest bin is
        prominent = sf.peak_ratio > PEAK_RATIO and (
            j >= len(floors) or not floors[j].structured_share < STRUCTURED_SHARE)
        if prominent:
            ax.axvline(sf.peak_hz, color="k", ls=":", lw=0.8,
                       label=f"peak {sf.peak_hz:.3g} Hz\n({sf.peak_ratio:.2g} x local median)")
            note = f"peak at {sf.peak_hz:.3g} Hz (final)"
        elif sf.peak_ratio > PEAK_RATIO:
            note = (f"no peak above the sensor noise (final: largest bin {sf.peak_ratio:.2g} x "
                    f"the local median, at {sf.peak_hz:.3g} Hz, residual at the noise floor)")
        else:
            note = (f"no prominent peak (final: largest bin {sf.peak_ratio:.2g} x the local "
                    f"median, at {sf.peak_hz:.3g} Hz)")
        _plain_log_labels(ax, x=True, y=True)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"PSD [{style.psd_unit(unit)}]")
        ax.set_title(f"{name}: validation residual spectrum (Welch)\n{note}", y=1.0,
                     fontsize=10)
        style.legend_outside(ax)
        _margins(fig, left=0.9, right=style.LEGEND_WIDTH_IN, top=0.6)
        paths.append(save(fig, out / f"spectrum_{name}.png"))
    return paths


_MAX_LABEL = 44
"""Longest candidate label drawn in full on the candidates chart [characters]."""


def plot_candidates(result: IdentificationResult, out: Path,
                    save: SaveFigure | None = None) -> Path | None:
    """Projected scores (R^2, %) of every candidate per round, accepted ones highlighted."""
    if not result.rounds:
        return None
    plt = _plt()
    save = save or _PngWriter()
    accepted = {(d.round, d.score.label) for d in result.accepted}
    longest = max(len(r) for r in result.rounds)
    fig, axes = plt.subplots(len(result.rounds), 1,
                             figsize=(9, 2.6 + (0.35 * longest + 0.4) * len(result.rounds)))
    axes = np.atleast_1d(axes)
    def short(label: str) -> str:  # long labels would squeeze the bars out of the figure
        return label if len(label) <= _MAX_LABEL else label[: _MAX_LABEL - 1] + "…"

    for i, (ax, rnd) in enumerate(zip(axes, result.rounds, strict=True)):
        labels = [short(s.label) for s in rnd][::-1]
        vals = [100 * s.r2 for s in rnd][::-1]
        colors = [style.ACCEPTED if (i + 1, s.label) in accepted else style.OTHER
                  for s in rnd][::-1]
        ax.barh(labels, vals, color=colors)
        # a linear axis over the whole 0-100 % range: a 0.005 % candidate draws as the sliver
        # it is, a round where nothing explains much looks like it; the values are written
        for y, v in enumerate(vals):
            text = f"{v:.3g} %" if v >= 1e-3 else ("0 %" if v <= 0 else "< 0.001 %")
            ax.text(v + 0.8, y, text, va="center", fontsize=7)
        ax.set_xlim(0.0, 100.0)
        _title(ax, f"round {i + 1}")
        ax.set_xlabel(style.label("residual sum of squares explained after projection", "%"))
    fig.suptitle("Candidates scored per round (green: accepted in that round; grey: not)",
                 x=0.02, y=1.0 - 0.12 / fig.get_size_inches()[1], ha="left", va="top",
                 fontsize=11)
    width = max((len(short(s.label)) for r in result.rounds for s in r), default=10)
    _margins(fig, left=min(0.4 + 0.085 * width, 4.5), top=0.8, bottom=0.6, hspace=0.8)
    return save(fig, out / "candidates.png")


def plot_linear(result: IdentificationResult, out: Path,
                save: SaveFigure | None = None) -> Path:
    """Step response and Bode magnitude/phase of the final model's linear part (to the
    measured outputs: ``C`` of a structure with hidden states, else C = I)."""
    plt = _plt()
    save = save or _PngWriter()
    A, B = result.final.linear()
    nx, nu = B.shape
    ins = result.description.input_names
    outs = result.description.output_names
    C = result.final.fit.model.C  # None: C = I; else the measured states of hidden ones
    ny = nx if C is None else C.shape[0]
    eig = np.linalg.eigvals(A)
    if C is not None:  # an angle's integrator (eigenvalue 0) sets no time scale
        eig = eig[np.abs(eig) > 1e-9 * max(float(np.max(np.abs(eig), initial=0.0)), 1e-300)]
    slow = float(np.min(np.abs(eig.real))) if eig.size else 1.0
    fast = float(np.max(np.abs(eig))) if eig.size else 1.0
    tend = 6.0 / max(slow, 1e-6)
    t = np.linspace(0.0, min(tend, 1e4), 600)
    w = np.logspace(np.log10(max(slow, 1e-3) / 20), np.log10(max(fast, 1e-2) * 20), 400)
    fig, axes = plt.subplots(3, 1, figsize=(11, 9))
    Ad, Gd = zoh(A, float(t[1] - t[0]))
    H = _freq_all(A, B, w)  # (len(w), nx, nu)
    if C is not None:
        H = np.einsum("ij,wjk->wik", C, H)
    unit = result.description.structure.speed_unit
    in_units = {sp.name: str(getattr(sp, "unit", "") or "")
                for sp in getattr(result.description, "inputs", ())}
    per = {style.per_input_unit(unit, in_units.get(n, "")) for n in ins}
    resp_unit = per.pop() if len(per) == 1 else style.per_input_unit(unit)
    scale = float(np.max(np.abs(H), initial=0.0))
    silent = []  # inputs without a path through the linear part (e.g. the band brakes)
    for i in range(nu):
        if not np.any(np.abs(H[:, :, i]) > 1e-12 * max(scale, 1e-300)):
            silent.append(ins[i])
            continue
        d = np.tile(Gd @ B[:, i], (t.size, 1))
        yy = simulate_linear(Ad, d, np.zeros(nx))
        if C is not None:
            yy = yy @ C.T
        for j in range(ny):
            c = style.CHANNELS[(i * ny + j) % len(style.CHANNELS)]
            axes[0].plot(t, yy[:, j], color=c, label=f"{ins[i]} -> {outs[j]}")
            Hj = H[:, j, i]
            axes[1].loglog(w / (2 * np.pi), np.abs(Hj), color=c)
            axes[2].semilogx(w / (2 * np.pi), np.degrees(np.unwrap(np.angle(Hj))), color=c)
    _plain_log_labels(axes[1], x=True, y=True)
    _plain_log_labels(axes[2], x=True)
    axes[0].set_title("linear part of the final model: unit-step response"
                      + (f"\n({', '.join(silent)}: no path through the linear part; they act "
                         "through the model's effects)" if silent else ""), y=1.0, fontsize=10)
    axes[0].set_xlabel("time [s]")
    axes[0].set_ylabel(f"step response\n[{resp_unit}]")
    style.legend_outside(axes[0])
    _title(axes[1], "Bode magnitude (colours as above)")
    axes[1].set_ylabel(f"|H| [{resp_unit}]")
    axes[1].set_xlabel("frequency [Hz]")
    _title(axes[2], "Bode phase")
    axes[2].set_ylabel("phase [deg]")
    axes[2].set_xlabel("frequency [Hz]")
    _margins(fig, left=1.0, top=0.6, hspace=0.8, right=style.LEGEND_WIDTH_IN)
    return save(fig, out / "linear_step_bode.png")


def _freq_all(A: Array, B: Array, w: Array) -> NDArray[np.complex128]:
    """Frequency response ``(j w I - A)^-1 B`` of shape (len(w), nx, nu)."""
    nx = A.shape[0]
    M = 1j * w[:, None, None] * np.eye(nx)[None] - A[None]
    return np.asarray(np.linalg.solve(M, np.broadcast_to(B, (w.size, *B.shape))),
                      dtype=np.complex128)


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
    sel = rep.get("selection") or {}
    if sel:
        lines += ["", f"Effects chosen on {sel['chosen_on']}: the validation figures above are "
                  "selection figures.", ""]
    t = rep.get("test")
    if t:
        lines += ["## Test (took no part in any choice)", "",
                  f"Test bags: {', '.join(f'`{x}`' for x in t['bags'])}; initial state "
                  f"{t['initial_state']}.", "",
                  "| output | baseline fit % | final fit % | baseline RMSE | final RMSE |",
                  "|---|---|---|---|---|"]
        for o in rep["outputs"]:
            lines.append(f"| {o} | {_f(t['baseline']['fit_percent'][o])} | "
                         f"{_f(t['final']['fit_percent'][o])} | {_f(t['baseline']['rmse'][o])} "
                         f"| {_f(t['final']['rmse'][o])} |")
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
    chk = rep.get("identifiability")
    if chk:
        lines += ["## Is this recording enough? (check before fitting)", ""]
        und = [q for q in chk["parameters"] if not q["determined"]]
        if not und:
            lines.append("The recording determines every parameter of the baseline model.")
        else:
            lines += ["| parameter | prior | predicted relative std | why | fixed at prior | "
                      "experiment |", "|---|---|---|---|---|---|"]
            for q in und:
                prs = q["predicted_relative_std"]
                prs_text = f"{_f(100 * prs, 3)} %" if prs is not None else "infinite"
                lines.append(f"| {q['name']} | {_f(q['prior'], 6)} | {prs_text} | "
                             f"{q['reason']} | {'yes' if q['fixed_at_prior'] else 'no'} | "
                             f"`{q['experiment']}` |")
        lines.append("")
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
