"""Is this recording enough? Identifiability of the baseline model's parameters before fitting.

For every parameter of the baseline model (structure + model effects) the check asks whether the
estimation data excite it, from the output sensitivities at the prior (the description's
initial values, where the baseline fit starts; the same central differences of the full
simulation the loop uses), and how much each declared model effect influences the recording,
at a *probe point*: every model effect that sits at its null (where it vanishes: a sensor gain
0, a sign-blind blend 0; there a gain-type effect has no influence to measure) set to a neutral
non-zero value of meaningful size (:func:`probe_values`).

1. **Input rule**: a model effect whose input (the one its entry names: ``where``, ``input`` or
   ``inputs``) never varies, or carries only sensor noise (its structured share,
   :func:`dvt_identify.uncertainty.noise_floor`, below :data:`NOISE_ONLY_SHARE`: a band the run
   never used), has no influence: its parameters are *not determined*, and the effect is
   removed from the model, i.e. fixed at its prior. This is the only rule that removes a
   declared effect.
2. **Fisher rule** (local): with ``J`` the sensitivities of the weighted outputs
   (``yhat_j / std(y_j)``) to the *relative* change of each parameter (column ``i`` scaled by
   ``|theta_i|``, 1 for a prior of 0) and to the initial states, the Fisher information for a
   residual of level ``sigma`` (in output standard deviations) is ``J^T J / sigma^2``. The
   initial states are nuisance parameters: they are marginalised (the Schur complement
   ``H_pp - H_px H_xx^+ H_xp``, computed as the projection of the parameter columns on the
   orthogonal complement of the initial-state columns, a pseudo-inverse with the relative
   tolerance :data:`STATE_RCOND`), so a combination of initial states that no output sees
   (the common angle of a drive without a spring to ground, seen through speeds) drops out and
   leaves the parameters alone. Of the marginal information, a direction whose singular value
   is at most :data:`NULL_RCOND` times the largest is an exact null direction (within the
   error of the central differences): a parameter with a share above :data:`NULL_WEIGHT` in
   one has an infinite predicted std and moves the outputs only together with the other
   parameters of that direction (named in its reason). Every other parameter's predicted
   relative std is ``sigma sqrt(sum_k V_ik^2 / s_k^2)`` over the remaining directions (joint:
   a parameter that mostly moves together with others gets a large figure). ``sigma`` is
   :data:`RESIDUAL_LEVEL` (0.03: a 97 % fit, what a good baseline leaves; the sensor floor of
   the outputs when that is larger) and the predicted figure is inflated by
   :data:`COLOUR_FACTOR` (10, the overconfidence measured for white-noise figures on coloured
   OE residuals). A parameter whose inflated predicted relative std exceeds
   :data:`MAX_RELATIVE_STD` (100 %) is *not determined by this recording*.
3. **Influence**: the RMS change of the weighted outputs when a declared effect is taken out
   of the model at the probe point. Below :data:`NO_INFLUENCE` times ``sigma`` the recording
   never engages it: its parameters are not determined, but the effect stays in the fit (the
   description declares it; its sandwich standard deviation after the fit says how well the
   nonlinear fit pinned it down). So does a parameter the Fisher rule flags whose effect does
   influence the recording (a band that holds in every gear: its gain is only bounded from
   below; a saturation level at its null, where no output responds to it): fixing it at a
   prior the data contradict would bias the others.

After a fit, :func:`at_fit` takes the Fisher rule again for the parameters it flagged, at the
fitted values and with the fit's own residual level: the rule is local and its level a guess.

Whatever is fixed or not determined is stated first (:meth:`Identifiability.summary`). Each
undetermined parameter comes with advice: the first row of the description's own
``experiments`` section whose pattern matches its name
(:class:`dvt_identify.description.ExperimentSpec`, e.g. ``dvt-experiment ident_shifts`` for the
DVT's bands), else generic advice from the data and the model (:func:`generic_advice`): the
mode or pole of the linear structure the parameter moves most and the share of the input power
there, how much longer a record would have to be (the predicted std falls as one over the
square root of its length), or, for a parameter in a null direction, the parameters it moves
only together with (a longer record does not help).

The Fisher rule's sensitivities and figures are in :mod:`dvt_identify.fisher`, the advice in
:mod:`dvt_identify.advice`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from dvt_identify.advice import _band_share, _poles_moved, experiment_for, generic_advice
from dvt_identify.data import Segment, _constant, decimate
from dvt_identify.description import CandidateSpec, Description, ExperimentSpec
from dvt_identify.effects import Effect
from dvt_identify.effects.base import SegmentView
from dvt_identify.fisher import (
    COLOUR_FACTOR,
    MAX_RELATIVE_STD,
    _sensitivities,
    _x0s,
    predicted_std,
)
from dvt_identify.simulation import OEModel
from dvt_identify.uncertainty import noise_floor

Array = NDArray[np.float64]

RESIDUAL_LEVEL = 0.03
"""Residual level assumed before fitting [output standard deviations]."""
NO_INFLUENCE = 0.01
"""An effect that changes the simulated outputs by less than this times the residual level (at
the probe point) is never engaged by the recording: its parameters are not determined (the
effect stays in the fit)."""
MAX_SAMPLES = 8000
"""The check runs on the estimation data decimated to about this many samples."""
PROBE_STEPS = 100.0
"""An effect parameter at its null with no probe of the effect's own (:meth:`Effect.variants`)
is probed at this many finite-difference steps from the null (its
:meth:`Effect.scoring_step`, else its spec's ``step``, else 1e-3 of ``max(|null|, 1)``), kept
within its bounds: a sensor gain at 0.1, a measurement delay at its ``max_delay``."""
NOISE_ONLY_SHARE = 0.5
"""An input whose structured share (:func:`dvt_identify.uncertainty.noise_floor`) is below
this carries only sensor noise: the run never used it."""


@dataclass(frozen=True)
class ParameterCheck:
    """Identifiability of one parameter.

    Attributes:
        name: parameter name.
        prior: its prior (initial) value.
        determined: whether the recording determines it.
        predicted_relative_std: inflated predicted relative std at the prior (``inf``: no
            information).
        sensitivity: RMS of the weighted output change for a 100 % change of the parameter
            [output standard deviations].
        reason: why it is not determined ("" when it is).
        experiment: what would determine it: the description's command or procedure, or
            generic advice ("" when it is determined).
        purpose: what that experiment excites, or why the advice helps.
        effect: label of the model effect it belongs to ("" for the structure).
        fixed: fixed at the prior (its effect was removed: its input never varies);
            otherwise an undetermined parameter is still fitted and reported as such.
        advice_from: ``description`` (its ``experiments`` section) or ``generic``.
        probe: the value its effect's influence was measured at when that is not its prior
            (an effect at its null), else ``None``.
        kind: which rule found it undetermined: ``unused`` (rule 1), ``quiet`` (rule 3),
            ``null`` or ``weak`` (the Fisher rule); ``""`` when determined.
    """

    name: str
    prior: float
    determined: bool
    predicted_relative_std: float
    sensitivity: float
    reason: str
    experiment: str
    purpose: str
    effect: str = ""
    fixed: bool = False
    advice_from: str = "generic"
    probe: float | None = None
    kind: str = ""

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        rs = self.predicted_relative_std
        return {"name": self.name, "prior": self.prior, "determined": self.determined,
                "predicted_relative_std": rs if math.isfinite(rs) else None,
                "sensitivity": self.sensitivity, "reason": self.reason,
                "experiment": self.experiment, "purpose": self.purpose, "effect": self.effect,
                "fixed_at_prior": self.fixed, "advice_from": self.advice_from,
                "probe": self.probe}

    def advice(self) -> str:
        """The advice for people: ``record `COMMAND` (what)`` for the description's own
        experiment, ``advice: ... (why)`` for generic advice."""
        if self.advice_from == "description":
            return f"record `{self.experiment}` ({self.purpose})"
        return f"advice: {self.experiment} ({self.purpose})"

    def statement(self) -> str:
        """One line for people."""
        if self.determined:
            return (f"{self.name}: determined (predicted relative std "
                    f"{100 * self.predicted_relative_std:.3g} %)")
        what = (f"fixed at its prior {self.prior:.6g} ({self.effect} removed)" if self.fixed
                else "still fitted, its value is not to be trusted")
        return f"{self.name}: not determined by this recording ({self.reason}); {what}; " \
               + self.advice()


@dataclass
class Identifiability:
    """Result of :func:`check`.

    Attributes:
        parameters: one :class:`ParameterCheck` per baseline parameter.
        removed_effects: labels of model effects removed (their input never varies).
        residual_level: the ``sigma`` used [output standard deviations].
        samples: samples the check ran on.
        influence: each kept model effect's influence at the probe point [output standard
            deviations] (label -> RMS change of the weighted outputs without it).
        revised: the parameters the Fisher rule left undetermined at the priors and found
            determined at the fitted values (:func:`at_fit`), each with its reason at the
            priors (empty before fitting).
    """

    parameters: list[ParameterCheck]
    removed_effects: list[str] = field(default_factory=list)
    residual_level: float = RESIDUAL_LEVEL
    samples: int = 0
    influence: dict[str, float] = field(default_factory=dict)
    revised: dict[str, str] = field(default_factory=dict)

    @property
    def undetermined(self) -> list[ParameterCheck]:
        """The parameters the recording does not determine."""
        return [p for p in self.parameters if not p.determined]

    @property
    def enough(self) -> bool:
        """Every parameter is determined."""
        return not self.undetermined

    def experiments(self) -> list[str]:
        """The description's own experiments that would determine the undetermined parameters
        (unique, ordered)."""
        out: list[str] = []
        for p in self.undetermined:
            if p.advice_from == "description" and p.experiment not in out:
                out.append(p.experiment)
        return out

    def advice(self) -> list[str]:
        """The generic advice for the undetermined parameters the description has no
        experiment for (``NAME: what (why)``, in order)."""
        return [f"{p.name}: {p.experiment} ({p.purpose})" for p in self.undetermined
                if p.advice_from != "description"]

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"enough": self.enough, "parameters": [p.as_dict() for p in self.parameters],
                "not_determined": [p.name for p in self.undetermined],
                "fixed_at_prior": [p.name for p in self.parameters if p.fixed],
                "removed_effects": self.removed_effects, "experiments": self.experiments(),
                "advice": self.advice(), "effect_influence": self.influence,
                "residual_level": self.residual_level, "colour_factor": COLOUR_FACTOR,
                "max_relative_std": MAX_RELATIVE_STD, "samples": self.samples,
                "determined_at_fit": self.revised}

    def summary(self) -> list[str]:
        """Lines for people: :meth:`headline`, then each undetermined parameter with its
        reason and advice."""
        return self.headline() + [p.statement() for p in self.undetermined]

    def headline(self) -> list[str]:
        """The first lines for people: the verdict, what is fixed at its prior (its effect
        removed), what is still fitted though not determined; after the fit, what the fitted
        model determines though the priors did not (:meth:`revised_line`)."""
        if self.enough:
            return ["The recording determines every parameter of the baseline model."
                    + (" " + self.revised_line() if self.revised else "")]
        und = self.undetermined
        head = (f"The recording does not determine {len(und)} of {len(self.parameters)} "
                f"parameters: " + ", ".join(p.name for p in und) + ".")
        cmds = self.experiments()
        if cmds:
            head += f" Record {' and '.join(f'`{e}`' for e in cmds)}."
        if any(p.advice_from != "description" for p in und):
            head += " Advice for each below."
        lines = [head]
        fixed = [p.name for p in und if p.fixed]
        if fixed:
            lines.append(f"Fixed at their priors (removed from the fit, their input never "
                         f"varies: {', '.join(self.removed_effects)}): {', '.join(fixed)}.")
        kept = [p.name for p in und if not p.fixed]
        if kept:
            lines.append("Still fitted, their values not to be trusted: "
                         + ", ".join(kept) + ".")
        if self.revised:
            lines.append(self.revised_line())
        return lines

    def revised_line(self) -> str:
        """The parameters determined at the fitted values though not at the priors, with
        both verdicts (``""`` when none)."""
        if not self.revised:
            return ""
        figs = {p.name: p.predicted_relative_std for p in self.parameters}
        return ("Determined at the fitted values (the check before fitting is local, at the "
                "priors, with an assumed residual level; taken again at the fit with its own "
                "residual): " + "; ".join(
                    f"{n} (predicted relative std {100 * figs[n]:.3g} % at the fit; at the "
                    f"priors: {why})" for n, why in self.revised.items()) + ".")


def _unused_input(name: str, cols: Sequence[Array], desc: Description) -> str:
    """Why input ``name`` (columns per segment) is unused, or "" when it is used."""
    if all(_constant(c, desc.checks) for c in cols):
        return f"its input {name} never varies"
    nf = noise_floor(cols)
    if math.isfinite(nf.structured_share) and nf.structured_share < NOISE_ONLY_SHARE:
        return (f"its input {name} carries only sensor noise (std {nf.rms:.3g} at its white "
                f"floor {nf.floor_rms:.3g}): the run never used it")
    return ""


def effect_inputs(spec: CandidateSpec, desc: Description) -> list[str]:
    """The inputs a model effect's entry names (``where``, ``input``, ``inputs``): the ones it
    acts only through (a band's current); empty for an effect on a member or an output."""
    named = [spec.where, spec.options.get("input")]
    more = spec.options.get("inputs")
    if isinstance(more, list | tuple):
        named += list(more)
    out: list[str] = []
    for n in named:
        if isinstance(n, str) and n in desc.input_names and n not in out:
            out.append(n)
    return out


def probe_values(eff: Effect, view: SegmentView) -> Array:
    """A neutral non-zero value of each of ``eff``'s parameters, shape (n_params,): its prior
    when the effect is present there (a gain parameter, :meth:`Effect.gain_names`, away from
    its null); else the effect's own probe (its first variant, as the scorer uses it:
    sign-blind ``b = 1``, saturation at the measured largest magnitude, quantisation at the
    grid step), and for a gain the variant does not set, :data:`PROBE_STEPS` finite-difference
    steps from its null within its bounds (a sensor gain at 0.1).

    Args:
        eff: the effect at its prior.
        view: the segment the effect may read its probe from (the coarsest).
    """
    p = np.array([s.initial for s in eff.params], dtype=float)
    gains = [g for g in eff.gain_names() if any(s.name == g for s in eff.params)]
    if not gains or any(eff.params[eff.pindex(g)].initial != eff.params[eff.pindex(g)].null
                        for g in gains):
        return p
    variants = eff.variants(view)
    shape = variants[0][1] if variants else {}
    for name, v in shape.items():
        i = eff.pindex(name)
        p[i] = eff.params[i].null + float(v) if name in gains else float(v)
    for g in gains:
        if g in shape:
            continue
        i = eff.pindex(g)
        spec = eff.params[i]
        h = eff.scoring_step(g, view.dt) or spec.step or 1e-3 * max(abs(spec.null), 1.0)
        up = min(spec.null + PROBE_STEPS * abs(h), spec.upper)
        p[i] = up if up != spec.null else max(spec.null - PROBE_STEPS * abs(h), spec.lower)
    return np.clip(p, [s.lower for s in eff.params], [s.upper for s in eff.params])



def advice_for(name: str, desc: Description, result: Identifiability | None = None) -> str:
    """The advice for people on parameter ``name`` after a fit: the check's own advice when it
    flagged the parameter, else the description's experiment for it, else generic advice
    (never another actuator's experiment)."""
    for p in (result.undetermined if result is not None else []):
        if p.name == name:
            return p.advice()
    own = experiment_for(name, desc.experiments)
    if own is not None:
        return f"record `{own[0]}` ({own[1]})"
    return (f"advice: a richer input or a longer record for {name} (its standard deviation "
            "falls as one over the root of the record length)")


def _influence(model: OEModel, theta: Array, segs: Sequence[Segment], w: Array,
               skip: set[str]) -> dict[str, float]:
    """Each model effect's influence at ``theta``: the RMS change of the weighted outputs
    (``yhat / w``) when it is taken out, the others at their values in ``theta`` [output
    standard deviations]; effects whose label is in ``skip`` are left out."""
    x0s = _x0s(segs, model)

    def run(m: OEModel, th: Array) -> Array:
        with np.errstate(all="ignore"):
            return np.concatenate([(m.simulate(th, s, x) / w).ravel()
                                   for s, x in zip(segs, x0s, strict=True)])
    base = run(model, theta)
    cols, off = [], model.n_struct
    for eff in model.effects:
        cols.append(np.arange(off, off + len(eff.params)))
        off += len(eff.params)
    out: dict[str, float] = {}
    for k, eff in enumerate(model.effects):
        if eff.label() in skip:
            continue
        keep = np.concatenate([np.arange(model.n_struct),
                               *(c for i, c in enumerate(cols) if i != k)])
        y0 = run(OEModel(model.structure, [e for i, e in enumerate(model.effects) if i != k]),
                 theta[keep])
        out[eff.label()] = (float(np.sqrt(np.mean((base - y0) ** 2)))
                            if np.all(np.isfinite(y0)) else math.inf)
    return out


def check(desc: Description, segments: Sequence[Segment],
          experiments: Sequence[ExperimentSpec] | None = None,
          at: Mapping[str, float] | None = None,
          level: float | None = None) -> Identifiability:
    """Which baseline parameters ``segments`` (the estimation data) determine (module docstring).

    Args:
        desc: the description (structure and model effects at their priors).
        segments: estimation segments.
        experiments: the parameter-pattern -> experiment table (default: the description's
            ``experiments``; without a matching row the advice is generic).
        at: parameter values (by name) to take the Fisher rule and the influences at instead
            of the priors (the fitted values: :func:`at_fit`); a parameter it lacks stays at
            its prior.
        level: the residual level [output standard deviations] in place of the assumed one
            (the fitted model's own: :func:`at_fit`).
    """
    table = desc.experiments if experiments is None else tuple(experiments)
    effects = desc.make_model_effects()
    model = OEModel(desc.structure, effects)
    prior = model.initial()
    if at is not None:
        prior = np.array([float(at.get(n, v)) for n, v in zip(model.names, prior,
                                                              strict=True)])
    n_samples = sum(s.n for s in segments)
    q = max(1, desc.preprocess.fit_decimate, math.ceil(n_samples / MAX_SAMPLES))
    segs = [decimate(s, q) for s in segments] if q > 1 else list(segments)
    w = np.std(np.vstack([s.y for s in segs]), axis=0)
    w[w == 0] = 1.0
    # the sensor floor of the outputs (first difference), in output standard deviations
    floor = max((noise_floor([s.y[:, j] for s in segments]).floor_rms / float(w[j])
                 for j in range(model.ny)), default=0.0)
    sigma = (max(RESIDUAL_LEVEL, floor if math.isfinite(floor) else 0.0) if level is None
             else level)
    # rule 1: an effect whose every input is unused is removed (fixed at its prior)
    owner: dict[str, str] = {}
    unused: dict[str, tuple[str, str]] = {}  # parameter -> (reason, input)
    removed: list[str] = []
    for spec, eff in zip(desc.model_effects, effects, strict=True):
        for p in eff.params:
            owner[p.name] = eff.label()
        names = effect_inputs(spec, desc)
        whys = [(_unused_input(n, [s.u[:, desc.input_names.index(n)] for s in segments],
                               desc), n) for n in names]
        if names and all(why for why, _ in whys):
            removed.append(eff.label())
            for p in eff.params:
                unused[p.name] = ("; ".join(why for why, _ in whys), names[0])
    # the probe point of the influence: each kept effect at its null gets a neutral non-zero
    # value (the Fisher rule stays at the prior, where the baseline fit starts)
    coarsest = max(segs, key=lambda s: s.dt)
    view = SegmentView.of(coarsest)
    theta = prior.copy()
    off = model.n_struct
    for eff in effects:
        k = len(eff.params)
        if eff.label() not in removed and (at is None
                                           or not all(s.name in at for s in eff.params)):
            theta[off: off + k] = probe_values(eff, view)
        off += k
    J = _sensitivities(model, prior, segs, w)
    rel_std, partners = predicted_std(J, theta.size, sigma)
    sens = np.linalg.norm(J[:, : theta.size], axis=0) / math.sqrt(max(J.shape[0], 1))
    # rule 3: each kept effect's influence at the probe point (nothing is removed for it)
    influence = _influence(model, theta, segs, w, skip=set(removed))
    quiet = {lab for lab, v in influence.items() if v < NO_INFLUENCE * sigma}
    poles = _poles_moved(desc.structure, theta[: model.n_struct])
    seconds = sum(s.n * s.dt for s in segments)
    out: list[ParameterCheck] = []
    for i, name in enumerate(model.names):
        label = owner.get(name, "")
        probe = float(theta[i]) if theta[i] != prior[i] else None
        rs = float(rel_std[i])
        fixed = False
        if name in unused:
            det, why, kind, rs, fixed = False, unused[name][0], "unused", math.inf, True
        elif label in quiet:
            det, kind = False, "quiet"
            why = (f"the recording never engages {label}: the outputs change by "
                   f"{influence[label]:.2g} output std without it"
                   + ("" if probe is None else f" at {name} = {probe:.3g}"))
        elif not math.isfinite(rs):
            det, kind = False, "null"
            with_ = [model.names[j] for j in partners[i]]
            why = ("the outputs see it only together with " + ", ".join(with_) if with_
                   else f"no output responds to it at its prior {prior[i]:.6g}")
        elif rs > MAX_RELATIVE_STD:
            det, kind = False, "weak"
            why = (f"predicted relative std {100 * rs:.3g} % > {100 * MAX_RELATIVE_STD:g} %: "
                   "the recording barely excites it")
        else:
            det, kind, why = True, "", ""
        cmd = purpose = ""
        source = "generic"
        if not det:
            own = experiment_for(name, table)
            if own is not None:
                (cmd, purpose), source = own, "description"
            else:
                pole = poles[i] if i < model.n_struct else None
                cmd, purpose = generic_advice(
                    name, kind, rs, partners=[model.names[j] for j in partners[i]],
                    effect=label, pole=pole,
                    share=_band_share(segments, *pole.band()) if pole is not None else 0.0,
                    seconds=seconds, input_name=unused.get(name, ("", ""))[1],
                    influence=influence.get(label, 0.0), probe=probe)
        out.append(ParameterCheck(name=name, prior=float(prior[i]), determined=det,
                                  predicted_relative_std=rs, sensitivity=float(sens[i]),
                                  reason=why, experiment=cmd, purpose=purpose, effect=label,
                                  fixed=fixed, advice_from=source, probe=probe, kind=kind))
    return Identifiability(parameters=out, removed_effects=removed, residual_level=sigma,
                           samples=sum(s.n for s in segs), influence=influence)


def at_fit(pre: Identifiability, desc: Description, segments: Sequence[Segment],
           values: Mapping[str, float], level: float) -> Identifiability:
    """``pre`` (the check at the priors) with the Fisher rule taken again at the fitted
    ``values`` and the fit's own residual ``level``: a parameter the priors left in a null or
    weak direction gets the verdict at the fit (figure, reason and advice); one the fitted
    model determines has its reason at the priors in ``revised``. Before fitting the rule is
    local and its level a guess: at a prior where the model degenerates (a scale-only
    description with every prior 1, where the two-mass drive's zeros cancel its mode) it
    reports null directions the optimum does not have, and the first-difference floor of an
    output sampled coarsely against its dynamics (a few hundred samples at 50 Hz) counts the
    signal's own steps as noise. The data rules (an unused input, an effect the recording
    never engages) stand; ``pre`` itself when it flagged nothing by the Fisher rule.

    Args:
        pre: :func:`check` of ``desc`` on ``segments`` at the priors.
        desc: the description the fit ran (after :func:`apply`).
        segments: the estimation segments.
        values: the fitted parameters by name (the final model's; only the baseline
            model's are used).
        level: the fitted model's residual on ``segments`` [output standard deviations]: the
            largest over the outputs of its RMS over the output's standard deviation.
    """
    fisher = {p.name for p in pre.undetermined if p.kind in ("null", "weak")}
    if not fisher:
        return pre
    post = {p.name: p for p in check(desc, segments, at=values, level=level).parameters}
    params: list[ParameterCheck] = []
    revised: dict[str, str] = {}
    for p in pre.parameters:
        q = post.get(p.name)
        if p.name in fisher and q is not None:
            params.append(replace(q, prior=p.prior))  # the verdict and advice at the fit
            if q.determined:
                revised[p.name] = p.reason
        else:
            params.append(p)
    return replace(pre, parameters=params, revised=revised)


def apply(desc: Description, result: Identifiability) -> Description:
    """``desc`` without the model effects the check removed (fixed at their prior: their input
    never varies); every other declared effect stays."""
    gone = set(result.removed_effects)
    keep = tuple(spec for spec, eff in zip(desc.model_effects, desc.make_model_effects(),
                                           strict=True) if eff.label() not in gone)
    return replace(desc, model_effects=keep)
