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

Whatever is fixed or not determined is stated first (:meth:`Identifiability.summary`). Each
undetermined parameter comes with advice: the first row of the description's own
``experiments`` section whose pattern matches its name
(:class:`dvt_identify.description.ExperimentSpec`, e.g. ``dvt-experiment ident_shifts`` for the
DVT's bands), else generic advice from the data and the model (:func:`generic_advice`): the
mode or pole of the linear structure the parameter moves most and the share of the input power
there, how much longer a record would have to be (the predicted std falls as one over the
square root of its length), or, for a parameter in a null direction, the parameters it moves
only together with (a longer record does not help).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment, _constant, decimate
from dvt_identify.description import CandidateSpec, Description, ExperimentSpec
from dvt_identify.effects import Effect
from dvt_identify.effects.base import SegmentView
from dvt_identify.simulation import OEModel
from dvt_identify.structures import ModelStructure, initial_state
from dvt_identify.uncertainty import noise_floor

Array = NDArray[np.float64]

RESIDUAL_LEVEL = 0.03
"""Residual level assumed before fitting [output standard deviations]."""
COLOUR_FACTOR = 10.0
"""Inflation of white-noise parameter figures for coloured OE residuals."""
MAX_RELATIVE_STD = 1.0
"""A parameter whose predicted relative std exceeds this is not determined."""
NO_INFLUENCE = 0.01
"""An effect that changes the simulated outputs by less than this times the residual level (at
the probe point) is never engaged by the recording: its parameters are not determined (the
effect stays in the fit)."""
MAX_SAMPLES = 8000
"""The check runs on the estimation data decimated to about this many samples."""
STATE_RCOND = 1e-9
"""Relative tolerance of the pseudo-inverse that marginalises the initial states: a direction
of the initial-state sensitivities with a singular value below this times the largest is one
that no output sees (it is not projected out)."""
NULL_RCOND = 1e-5
"""A direction of the marginal parameter sensitivities with a singular value at most this times
the largest is an exact null direction. Central differences with a relative step of 1e-3 leave
an error of about 1e-6 of a column (measured on the two-mass drive: the exact scale direction of
a sensor gain with the whole structure comes out at 4e-6, a parameter duplicated under another
name at 2e-8); a genuinely weak direction sits far above (the dampers to ground of the two-mass
drive, 2e-3)."""
NULL_WEIGHT = 1e-3
"""A parameter whose squared share in the null directions exceeds this lies in one (its
predicted std is infinite); below, the share is the numerical mixing of nearby directions."""
PROBE_STEPS = 100.0
"""An effect parameter at its null with no probe of the effect's own (:meth:`Effect.variants`)
is probed at this many finite-difference steps from the null (its
:meth:`Effect.scoring_step`, else its spec's ``step``, else 1e-3 of ``max(|null|, 1)``), kept
within its bounds: a sensor gain at 0.1, a measurement delay at its ``max_delay``."""
NOISE_ONLY_SHARE = 0.5
"""An input whose structured share (:func:`dvt_identify.uncertainty.noise_floor`) is below
this carries only sensor noise: the run never used it."""


def experiment_for(name: str, table: Sequence[ExperimentSpec]) -> tuple[str, str] | None:
    """The experiment (command or procedure) and what it excites for parameter ``name``: the
    first row of ``table`` (a description's ``experiments``) whose pattern matches, its named
    groups filled into ``excites``; ``None`` when no row matches."""
    for row in table:
        m = re.search(row.parameters, name)
        if m:
            groups = {k: (v or "") for k, v in m.groupdict().items()}
            try:
                return row.run, row.excites.format(**groups)
            except (KeyError, IndexError, ValueError):
                return row.run, row.excites
    return None


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
    """

    parameters: list[ParameterCheck]
    removed_effects: list[str] = field(default_factory=list)
    residual_level: float = RESIDUAL_LEVEL
    samples: int = 0
    influence: dict[str, float] = field(default_factory=dict)

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
                "max_relative_std": MAX_RELATIVE_STD, "samples": self.samples}

    def summary(self) -> list[str]:
        """Lines for people: :meth:`headline`, then each undetermined parameter with its
        reason and advice."""
        return self.headline() + [p.statement() for p in self.undetermined]

    def headline(self) -> list[str]:
        """The first lines for people: the verdict, what is fixed at its prior (its effect
        removed), what is still fitted though not determined."""
        if self.enough:
            return ["The recording determines every parameter of the baseline model."]
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
        return lines


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


def marginal_information(J: Array, n_params: int) -> tuple[Array, Array, NDArray[np.bool_]]:
    """The parameters' information with the initial states marginalised, as an SVD.

    Args:
        J: sensitivities, shape (m, n_params + n_states): the parameters' columns first.
        n_params: number of parameter columns.

    Returns:
        ``(s, V, null)``: singular values (n_params,), right singular vectors as columns
        (n_params, n_params) of the parameter columns projected on the orthogonal complement
        of the initial-state columns (:data:`STATE_RCOND`), and which directions are null
        (:data:`NULL_RCOND`).
    """
    Jp, Jx = J[:, :n_params], J[:, n_params:]
    if Jx.shape[1]:
        U, sx, _ = np.linalg.svd(Jx, full_matrices=False)
        seen = sx > STATE_RCOND * float(sx[0]) if sx.size and sx[0] > 0 else sx > math.inf
        Ux = U[:, seen]
        Jp = Jp - Ux @ (Ux.T @ Jp)
    if Jp.shape[0] < n_params:  # fewer rows than parameters: pad, the rest is null
        Jp = np.vstack([Jp, np.zeros((n_params - Jp.shape[0], n_params))])
    _, s, Vt = np.linalg.svd(Jp, full_matrices=False)
    top = float(s[0]) if s.size else 0.0
    null = s <= NULL_RCOND * top if top > 0 else np.ones(s.size, dtype=bool)
    return np.asarray(s, float), np.asarray(Vt.T, float), np.asarray(null, bool)


def predicted_std(J: Array, n_params: int, sigma: float) -> tuple[Array, list[list[int]]]:
    """Inflated predicted relative std of each parameter (module docstring, Fisher rule) and,
    for one in a null direction (``inf``), the other parameters of that direction.

    Args:
        J: sensitivities, shape (m, n_params + n_states).
        n_params: number of parameter columns.
        sigma: residual level [output standard deviations].
    """
    s, V, null = marginal_information(J, n_params)
    Vn = V[:, null]
    weight = np.sum(Vn ** 2, axis=1)
    live = ~null
    inv = np.sum(V[:, live] ** 2 / s[live] ** 2, axis=1) if np.any(live) else np.zeros(n_params)
    rel = COLOUR_FACTOR * sigma * np.sqrt(inv)
    in_null = weight > NULL_WEIGHT
    rel = np.where(in_null, np.inf, rel)
    P = Vn @ Vn.T
    partners = [[j for j in range(n_params) if j != i and in_null[j]
                 and abs(float(P[i, j])) > NULL_WEIGHT] if in_null[i] else []
                for i in range(n_params)]
    return rel, partners


@dataclass(frozen=True)
class _Pole:
    """The eigenvalue of the linear part a parameter moves most (relative to its size)."""

    lam: complex
    mode: int  # 1-based index among the oscillating modes (slowest first); 0 for a real pole

    def where(self) -> str:
        f = abs(self.lam) / (2 * math.pi)
        if self.mode:
            zeta = -self.lam.real / abs(self.lam)
            return f"mode {self.mode} near {f:.3g} Hz (damping ratio {zeta:.2g})"
        return f"the pole at {f:.3g} Hz (time constant {1 / abs(self.lam):.3g} s)"

    def band(self) -> tuple[float, float]:
        """Frequency band [Hz] that excites it: around a mode, below twice a real pole."""
        f = abs(self.lam) / (2 * math.pi)
        return (f / 1.5, 1.5 * f) if self.mode else (0.0, 2.0 * f)

    def band_words(self) -> str:
        lo, hi = self.band()
        if self.mode:
            return f"between {lo:.3g} and {hi:.3g} Hz"
        return f"below {hi:.3g} Hz (inputs held longer than {1 / abs(self.lam):.3g} s)"


def _poles_moved(structure: ModelStructure, theta: Array) -> list[_Pole | None]:
    """For each structure parameter, the eigenvalue of ``A`` it moves most relative to the
    eigenvalue's size (first-order eigenvalue sensitivity ``(V^-1 dA V)_kk`` to a relative
    change), ignoring zero eigenvalues (a free angle); ``None`` when it moves none or ``A`` is
    not diagonalisable."""
    none: list[_Pole | None] = [None] * theta.size
    try:
        A = np.asarray(structure.matrices(theta)[0], dtype=float)
        lam, V = np.linalg.eig(A)
        if not np.all(np.isfinite(lam)) or np.linalg.cond(V) > 1e10:
            return none
        Vinv = np.linalg.inv(V)
    except (np.linalg.LinAlgError, ValueError):
        return none
    size = np.abs(lam)
    live = (size > 1e-9 * max(float(size.max(initial=0.0)), 1e-300)) & (lam.imag >= 0)
    oscill = sorted((k for k in range(lam.size) if live[k] and lam[k].imag > 1e-9),
                    key=lambda k: size[k])
    out: list[_Pole | None] = []
    for i in range(theta.size):
        scale = abs(float(theta[i])) or 1.0
        h = 1e-6 * scale
        tp = theta.copy()
        tp[i] += h
        try:
            dA = (np.asarray(structure.matrices(tp)[0], dtype=float) - A) / h * scale
        except (np.linalg.LinAlgError, ValueError):
            out.append(None)
            continue
        d = np.abs(np.einsum("ij,jk,ki->i", Vinv, dA, V)) / np.maximum(size, 1e-300)
        d = np.where(live, d, 0.0)
        k = int(np.argmax(d)) if d.size else 0
        if not d.size or d[k] <= 1e-9:
            out.append(None)
            continue
        out.append(_Pole(complex(lam[k]), oscill.index(k) + 1 if k in oscill else 0))
    return out


def _band_share(segments: Sequence[Segment], lo: float, hi: float) -> float:
    """Share of the inputs' power (each varying input's own, averaged) within ``[lo, hi]`` Hz
    in ``segments`` (their periodograms pooled); 0 when no input varies."""
    if not segments:
        return 0.0
    shares = []
    for j in range(segments[0].u.shape[1]):
        inside = total = 0.0
        for s in segments:
            u = s.u[:, j] - float(np.mean(s.u[:, j]))
            p = np.abs(np.fft.rfft(u)) ** 2
            f = np.fft.rfftfreq(u.size, s.dt)
            inside += float(np.sum(p[(f >= lo) & (f <= hi) & (f > 0)]))
            total += float(np.sum(p[f > 0]))
        if total > 0:
            shares.append(inside / total)
    return float(np.mean(shares)) if shares else 0.0


def generic_advice(name: str, kind: str, rel_std: float, *, partners: Sequence[str] = (),
                   effect: str = "", pole: _Pole | None = None, share: float = 0.0,
                   seconds: float = 0.0, input_name: str = "", influence: float = 0.0,
                   probe: float | None = None) -> tuple[str, str]:
    """What would determine parameter ``name``, from the data and the model, when the
    description names no experiment for it: ``(what to record, why)``.

    Args:
        name: the parameter.
        kind: why it is not determined: ``unused`` (its effect's input never varies),
            ``quiet`` (its effect is never engaged), ``null`` (in a null direction), ``weak``
            (a finite predicted relative std above :data:`MAX_RELATIVE_STD`).
        rel_std: its predicted relative std.
        partners: the parameters it moves the outputs only together with (``null``).
        effect: label of its effect ("" for the structure).
        pole: the mode or pole of the linear part it moves most (structure parameters).
        share: share of the input power that excites that pole in this recording.
        seconds: length of this recording [s].
        input_name: its effect's input (``unused``).
        influence: its effect's influence at the probe [output std] (``quiet``, ``null``).
        probe: the probe value of the parameter (``quiet``, ``null``).
    """
    if kind == "unused":
        return (f"a record that uses input {input_name}",
                f"{effect} acts only when {input_name} varies")
    if kind == "quiet":
        at = f"{name} = {probe:.3g}" if probe is not None else "its prior"
        return (f"a record in which {effect} acts",
                f"at {at} it changes the outputs of this one by {influence:.2g} output std")
    if kind == "null":
        if partners:
            return (f"an experiment that moves {name} differently from "
                    f"{', '.join(partners)}: a further sensor or input (a longer record does "
                    "not help)", f"the outputs see {name} only together with them")
        if effect and probe is not None:
            return (f"a prior where {effect} acts (e.g. {name} {probe:.3g} in its `initial`)",
                    f"at its prior no output responds to it, at {probe:.3g} the outputs "
                    f"change by {influence:.2g} output std")
        return (f"an input or sensor that {name} acts on",
                "no output of this recording responds to it")
    factor = (rel_std / MAX_RELATIVE_STD) ** 2 if math.isfinite(rel_std) else math.inf
    longer = f"a record about {factor:.2g} x as long ({factor * seconds:.3g} s)"
    if pole is not None:
        return (f"more excitation {pole.band_words()}: a richer input there, or {longer}",
                f"{name} moves {pole.where()} most; this recording puts {100 * share:.2g} % "
                "of its input power there")
    what = f"{effect} engaged more often" if effect else "a richer input"
    return (f"{what}, or {longer}",
            f"the predicted std of {name} falls as one over the root of the record length")


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
          experiments: Sequence[ExperimentSpec] | None = None) -> Identifiability:
    """Which baseline parameters ``segments`` (the estimation data) determine (module docstring).

    Args:
        desc: the description (structure and model effects at their priors).
        segments: estimation segments.
        experiments: the parameter-pattern -> experiment table (default: the description's
            ``experiments``; without a matching row the advice is generic).
    """
    table = desc.experiments if experiments is None else tuple(experiments)
    effects = desc.make_model_effects()
    model = OEModel(desc.structure, effects)
    prior = model.initial()
    n_samples = sum(s.n for s in segments)
    q = max(1, desc.preprocess.fit_decimate, math.ceil(n_samples / MAX_SAMPLES))
    segs = [decimate(s, q) for s in segments] if q > 1 else list(segments)
    w = np.std(np.vstack([s.y for s in segs]), axis=0)
    w[w == 0] = 1.0
    # the sensor floor of the outputs (first difference), in output standard deviations
    floor = max((noise_floor([s.y[:, j] for s in segments]).floor_rms / float(w[j])
                 for j in range(model.ny)), default=0.0)
    sigma = max(RESIDUAL_LEVEL, floor if math.isfinite(floor) else 0.0)
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
    view = SegmentView(coarsest.dt, coarsest.u, coarsest.y, coarsest.angles)
    theta = prior.copy()
    off = model.n_struct
    for eff in effects:
        k = len(eff.params)
        if eff.label() not in removed:
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
                                  fixed=fixed, advice_from=source, probe=probe))
    return Identifiability(parameters=out, removed_effects=removed, residual_level=sigma,
                           samples=sum(s.n for s in segs), influence=influence)


def apply(desc: Description, result: Identifiability) -> Description:
    """``desc`` without the model effects the check removed (fixed at their prior: their input
    never varies); every other declared effect stays."""
    gone = set(result.removed_effects)
    keep = tuple(spec for spec, eff in zip(desc.model_effects, desc.make_model_effects(),
                                           strict=True) if eff.label() not in gone)
    return replace(desc, model_effects=keep)
