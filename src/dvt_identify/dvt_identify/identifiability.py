"""Is this recording enough? Identifiability of the baseline model's parameters before fitting.

For every parameter of the baseline model (structure + model effects) the check asks whether the
estimation data excite it, from the output sensitivities at the prior (the description's initial
values; the same central differences of the full simulation the loop uses):

1. **Input rule**: a model effect whose input never varies, or carries only sensor noise (its
   structured share, :func:`dvt_identify.uncertainty.noise_floor`, below
   :data:`NOISE_ONLY_SHARE`: a band the run never used), has no influence: its parameters are
   *not determined*.
2. **Fisher rule** (local): with ``J`` the sensitivities of the weighted outputs
   (``yhat_j / std(y_j)``) to the *relative* change of each parameter (column ``i`` scaled by
   ``|theta_i|``) and to the initial states, the Fisher information for a residual of level
   ``sigma`` (in output standard deviations) is ``J^T J / sigma^2``; the predicted relative
   standard deviation of parameter ``i`` is ``sigma sqrt((J^T J)^+_ii)`` (joint: a parameter
   that only moves together with others is not determined either). ``sigma`` is
   :data:`RESIDUAL_LEVEL` (0.03: a 97 % fit, what a good baseline leaves; the sensor floor of
   the outputs when that is larger) and the predicted figure is inflated by
   :data:`COLOUR_FACTOR` (10, the overconfidence measured for white-noise figures on coloured
   OE residuals). A parameter whose inflated predicted relative std exceeds
   :data:`MAX_RELATIVE_STD` (100 %) is *not determined by this recording*.

A model effect is removed from the model, i.e. fixed at its prior, only when it has no influence
on the recording: its input is unused (rule 1) or the simulation without it differs by less than
:data:`NO_INFLUENCE` times ``sigma``; it is reported with the experiment that would determine it.
A parameter the Fisher rule flags but whose effect does influence the recording (a band that
holds in every gear: its gain is only bounded from below) stays in the fit: fixing it at a prior
the data contradict would bias the others. It is reported as *not determined* with that
experiment, and after the fit its sandwich standard deviation says how well the nonlinear fit
pinned it down. :data:`EXPERIMENTS` maps parameter
name patterns to the experiment that excites them (data, overridable by the caller).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment, _constant, decimate
from dvt_identify.description import Description
from dvt_identify.simulation import OEModel
from dvt_identify.structures import initial_state
from dvt_identify.uncertainty import noise_floor

Array = NDArray[np.float64]

RESIDUAL_LEVEL = 0.03
"""Residual level assumed before fitting [output standard deviations]."""
COLOUR_FACTOR = 10.0
"""Inflation of white-noise parameter figures for coloured OE residuals."""
MAX_RELATIVE_STD = 1.0
"""A parameter whose predicted relative std exceeds this is not determined."""
NO_INFLUENCE = 0.01
"""An effect that changes the simulated outputs by less than this times the residual level has
no influence on the recording: it is removed (fixed at its prior)."""
MAX_SAMPLES = 8000
"""The check runs on the estimation data decimated to about this many samples."""

EXPERIMENTS: tuple[tuple[str, str, str], ...] = (
    (r"^band_(gain|time_constant)_(ring|brake)(?P<n>\d)",
     "dvt-experiment ident_shifts",
     "band {n} engaging against a slipping ring (gain and lag show only while the band slips)"),
    (r"^(band_|dead_time|td)", "dvt-experiment ident_shifts",
     "band engagements against slipping rings"),
    (r"^(M|D)\d\d$", "dvt-experiment ident",
     "neutral PRBS/multisine, speed steps with reversals and each gear locked with PRBS"),
    (r".*", "dvt-experiment ident", "identification-grade excitation of every mode"),
)
"""(parameter-name regex, experiment command, what it does) in priority order; the first match
names the experiment that determines a parameter."""


def experiment_for(name: str, table: Sequence[tuple[str, str, str]] = EXPERIMENTS
                   ) -> tuple[str, str]:
    """The experiment command and its purpose for parameter ``name`` (first matching row)."""
    for pattern, command, what in table:
        m = re.search(pattern, name)
        if m:
            groups = {k: v for k, v in m.groupdict().items() if v is not None}
            try:
                return command, what.format(**groups)
            except (KeyError, IndexError):
                return command, what
    return "dvt-experiment ident", "identification-grade excitation"


@dataclass(frozen=True)
class ParameterCheck:
    """Identifiability of one parameter.

    Attributes:
        name: parameter name.
        prior: its prior (initial) value.
        determined: whether the recording determines it.
        predicted_relative_std: inflated predicted relative std (``inf``: no information).
        sensitivity: RMS of the weighted output change for a 100 % change of the parameter
            [output standard deviations].
        reason: why it is not determined ("" when it is).
        experiment: the experiment command that would determine it.
        purpose: what that experiment does for it.
        effect: label of the model effect it belongs to ("" for the structure).
        fixed: fixed at the prior (its effect was removed: no influence on this recording);
            otherwise an undetermined parameter is still fitted and reported as such.
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

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        rs = self.predicted_relative_std
        return {"name": self.name, "prior": self.prior, "determined": self.determined,
                "predicted_relative_std": rs if math.isfinite(rs) else None,
                "sensitivity": self.sensitivity, "reason": self.reason,
                "experiment": self.experiment, "purpose": self.purpose, "effect": self.effect,
                "fixed_at_prior": self.fixed}

    def statement(self) -> str:
        """One line for people."""
        if self.determined:
            return (f"{self.name}: determined (predicted relative std "
                    f"{100 * self.predicted_relative_std:.3g} %)")
        what = (f"fixed at its prior {self.prior:.6g} ({self.effect} removed)" if self.fixed
                else "still fitted, its value is not to be trusted")
        return (f"{self.name}: not determined by this recording ({self.reason}); {what}; "
                f"record `{self.experiment}` ({self.purpose})")


@dataclass
class Identifiability:
    """Result of :func:`check`.

    Attributes:
        parameters: one :class:`ParameterCheck` per baseline parameter.
        removed_effects: labels of model effects removed (every parameter not determined).
        residual_level: the ``sigma`` used [output standard deviations].
        samples: samples the check ran on.
    """

    parameters: list[ParameterCheck]
    removed_effects: list[str] = field(default_factory=list)
    residual_level: float = RESIDUAL_LEVEL
    samples: int = 0

    @property
    def undetermined(self) -> list[ParameterCheck]:
        """The parameters the recording does not determine."""
        return [p for p in self.parameters if not p.determined]

    @property
    def enough(self) -> bool:
        """Every parameter is determined."""
        return not self.undetermined

    def experiments(self) -> list[str]:
        """The experiments that would determine the undetermined parameters (unique, ordered)."""
        out: list[str] = []
        for p in self.undetermined:
            if p.experiment not in out:
                out.append(p.experiment)
        return out

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {"enough": self.enough, "parameters": [p.as_dict() for p in self.parameters],
                "not_determined": [p.name for p in self.undetermined],
                "removed_effects": self.removed_effects, "experiments": self.experiments(),
                "residual_level": self.residual_level, "colour_factor": COLOUR_FACTOR,
                "max_relative_std": MAX_RELATIVE_STD, "samples": self.samples}

    def summary(self) -> list[str]:
        """Lines for people (a verdict, then each undetermined parameter)."""
        if self.enough:
            return ["The recording determines every parameter of the baseline model."]
        lines = [f"The recording does not determine {len(self.undetermined)} of "
                 f"{len(self.parameters)} parameters: "
                 + ", ".join(p.name for p in self.undetermined)
                 + f". Record {' and '.join(f'`{e}`' for e in self.experiments())}."]
        lines += [p.statement() for p in self.undetermined]
        return lines


NOISE_ONLY_SHARE = 0.5
"""An input whose structured share (:func:`dvt_identify.uncertainty.noise_floor`) is below
this carries only sensor noise: the run never used it."""


def _unused_input(name: str, cols: Sequence[Array], desc: Description) -> str:
    """Why input ``name`` (columns per segment) is unused, or "" when it is used."""
    if all(_constant(c, desc.checks) for c in cols):
        return f"its input {name} never varies"
    nf = noise_floor(cols)
    if math.isfinite(nf.structured_share) and nf.structured_share < NOISE_ONLY_SHARE:
        return (f"its input {name} carries only sensor noise (std {nf.rms:.3g} at its white "
                f"floor {nf.floor_rms:.3g}): the run never used it")
    return ""


def _x0s(segs: Sequence[Segment], model: OEModel | None = None) -> list[Array]:
    y0s = [np.asarray(s.y[: min(3, s.n)].mean(axis=0), float) for s in segs]
    return y0s if model is None else [initial_state(model.structure, y) for y in y0s]


def _sensitivities(model: OEModel, theta: Array, segs: Sequence[Segment], w: Array,
                   rel_step: float = 1e-3) -> Array:
    """Columns: d(yhat/w)/d(log theta_i) for every parameter, then d/dx0 per segment."""
    x0s = _x0s(segs, model)

    def sim(th: Array, xs: Sequence[Array]) -> Array:
        with np.errstate(all="ignore"):
            return np.concatenate([(model.simulate(th, s, x) / w).ravel()
                                   for s, x in zip(segs, xs, strict=True)])
    cols = []
    for i in range(theta.size):
        scale = abs(float(theta[i])) or 1.0
        h = rel_step * scale
        spec = model.specs[i]
        hi = min(theta[i] + h, spec.upper)
        lo = max(theta[i] - h, spec.lower)
        tp, tm = theta.copy(), theta.copy()
        tp[i], tm[i] = hi, lo
        if hi <= lo:
            cols.append(np.zeros(sum(s.y.size for s in segs)))
            continue
        cols.append((sim(tp, x0s) - sim(tm, x0s)) / (hi - lo) * scale)
    wx = w if model.C is None else np.full(model.nx, float(np.max(w)))  # hidden states
    for k in range(len(segs)):
        for j in range(model.nx):
            h = 1e-3 * float(wx[j])
            xp = [x.copy() for x in x0s]
            xm = [x.copy() for x in x0s]
            xp[k][j] += h
            xm[k][j] -= h
            cols.append((sim(theta, xp) - sim(theta, xm)) / (2 * h) * float(wx[j]))
    return np.asarray(np.nan_to_num(np.column_stack(cols)))


def check(desc: Description, segments: Sequence[Segment],
          experiments: Sequence[tuple[str, str, str]] = EXPERIMENTS) -> Identifiability:
    """Which baseline parameters ``segments`` (the estimation data) determine (module docstring).

    Args:
        desc: the description (structure and model effects at their priors).
        segments: estimation segments.
        experiments: the parameter-pattern -> experiment table.
    """
    effects = desc.make_model_effects()
    model = OEModel(desc.structure, effects)
    theta = model.initial()
    n_samples = sum(s.n for s in segments)
    q = max(1, desc.preprocess.fit_decimate, math.ceil(n_samples / MAX_SAMPLES))
    segs = [decimate(s, q) for s in segments] if q > 1 else list(segments)
    w = np.std(np.vstack([s.y for s in segs]), axis=0)
    w[w == 0] = 1.0
    # the sensor floor of the outputs (first difference), in output standard deviations
    floor = max((noise_floor([s.y[:, j] for s in segments]).floor_rms / float(w[j])
                 for j in range(model.ny)), default=0.0)
    sigma = max(RESIDUAL_LEVEL, floor if math.isfinite(floor) else 0.0)
    J = _sensitivities(model, theta, segs, w)
    m = J.shape[0]
    H = J.T @ J
    ev, V = np.linalg.eigh(H)
    keep = ev > 1e-12 * max(float(ev.max(initial=0.0)), 1e-300)
    Hinv = (V[:, keep] / ev[keep]) @ V[:, keep].T
    dropped = V[:, ~keep]
    null_weight = np.sum(dropped ** 2, axis=1) if dropped.size else np.zeros(H.shape[0])
    rel_std = COLOUR_FACTOR * sigma * np.sqrt(np.clip(np.diag(Hinv), 0.0, None))
    rel_std = np.where(null_weight > 1e-6, np.inf, rel_std)
    sens = np.linalg.norm(J, axis=0) / math.sqrt(max(m, 1))
    owner: dict[str, str] = {}
    constant_input: dict[str, str] = {}
    for eff in effects:
        label = eff.label()
        for p in eff.params:
            owner[p.name] = label
        j = eff.index
        if 0 <= j < len(desc.input_names):
            why = _unused_input(desc.input_names[j], [s.u[:, j] for s in segments], desc)
            if why:
                for p in eff.params:
                    constant_input[p.name] = why
    out: list[ParameterCheck] = []
    for i, name in enumerate(model.names):
        cmd, purpose = experiment_for(name, experiments)
        if name in constant_input:
            det, why, rs = False, constant_input[name], math.inf
        elif not math.isfinite(float(rel_std[i])):
            det, why, rs = (False, "no output responds to it, or only together with other "
                            "parameters", math.inf)
        elif rel_std[i] > MAX_RELATIVE_STD:
            det, rs = False, float(rel_std[i])
            why = (f"predicted relative std {100 * rs:.3g} % > {100 * MAX_RELATIVE_STD:g} %: "
                   "the recording barely excites it")
        else:
            det, why, rs = True, "", float(rel_std[i])
        out.append(ParameterCheck(name=name, prior=float(theta[i]), determined=det,
                                  predicted_relative_std=rs, sensitivity=float(sens[i]),
                                  reason=why, experiment=cmd, purpose=purpose,
                                  effect=owner.get(name, "")))
    # an effect is removed (fixed at its prior) only when it has no influence on this
    # recording: its input never varies, or the simulation without it differs by less than
    # NO_INFLUENCE x sigma; a band that holds (gain undetermined locally) still matters
    base = np.concatenate([(model.simulate(theta, s, x) / w).ravel()
                           for s, x in zip(segs, _x0s(segs, model), strict=True)])
    removed: list[str] = []
    influence: dict[str, float] = {}
    for k, eff in enumerate(effects):
        label = eff.label()
        if eff.params and all(ps.name in constant_input for ps in eff.params):
            removed.append(label)
            influence[label] = 0.0
            continue
        others = [e for i, e in enumerate(effects) if i != k]
        sub = OEModel(desc.structure, others)
        th = np.concatenate([theta[: model.n_struct]]
                            + [np.array([p.initial for p in e.params], dtype=float)
                               for e in others]) if others else theta[: model.n_struct]
        with np.errstate(all="ignore"):
            y0 = np.concatenate([(sub.simulate(th, s, x) / w).ravel()
                                 for s, x in zip(segs, _x0s(segs, model), strict=True)])
        infl = float(np.sqrt(np.mean((base - y0) ** 2))) if np.all(np.isfinite(y0)) else math.inf
        influence[label] = infl
        if infl < NO_INFLUENCE * sigma:
            removed.append(label)
    final: list[ParameterCheck] = []
    for pc in out:
        if pc.effect in removed:
            why = (pc.reason if pc.name in constant_input else
                   f"the recording never engages {pc.effect}: the output changes by "
                   f"{influence[pc.effect]:.2g} output std without it")
            final.append(replace(pc, determined=False, reason=why, fixed=True))
        else:
            final.append(pc)
    out = final
    return Identifiability(parameters=out, removed_effects=removed, residual_level=sigma,
                           samples=sum(s.n for s in segs))


def apply(desc: Description, result: Identifiability) -> Description:
    """``desc`` without the model effects the check removed (fixed at their prior)."""
    gone = set(result.removed_effects)
    keep = tuple(spec for spec, eff in zip(desc.model_effects, desc.make_model_effects(),
                                           strict=True) if eff.label() not in gone)
    return replace(desc, model_effects=keep)
