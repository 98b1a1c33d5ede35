"""Position-dependent effects: gravity at the output and the generic ``unlisted`` term.

A member's angle is ``theta = c . q`` with ``q`` the generalised angles. It is taken from the
segment's measured angles when the segment carries them (an ``angles`` attribute of shape
(N, ny), from the recording's ``position``), else from integrating the measured member speed
from 0 at the segment's first sample (:func:`angle_of` says which; the evidence reports it).
With an integrated angle a phase is relative to the first sample.

- :class:`GravityLoad` (``gravity_load``): a torque ``a cos(theta / N) + b sin(theta / N)`` on
  the member (carrier 3: an arm behind an output stage of reduction ``N``), amplitude
  ``hypot(a, b)`` and phase ``atan2(-b, a)`` (``A cos(theta / N + phase)``). ``N`` is a
  description option (``reduction``, held fixed) or scanned (``reductions``) and then fitted.
- :class:`Unlisted` (``unlisted``): a sum of library terms ``sum_j k_j phi_j`` on one member,
  each ``phi_j = S(s) T(k theta) u_i`` (speed factor ``sign(s)``, ``|s| s``, ``s^3`` or 1, angle
  factor ``cos``/``sin`` of an order or 1, an input or 1). Built from a description entry it holds
  the whole library (the search :mod:`dvt_identify.unlisted` picks a few terms with
  :meth:`Unlisted.subset`); its label carries the formula in physical units.

All are exogenous forces evaluated on the measured speeds and angles (like a periodic
disturbance), so the simulation stays the compiled linear + dry-friction loop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.integrate import cumulative_trapezoid

from dvt_identify.effects.base import (
    Array,
    BuildContext,
    Effect,
    ParamSpec,
    ScoringContext,
    SegmentView,
    numbers_option,
)
from dvt_identify.errors import DescriptionError

ANGLE_FROM_POSITION = "measured position"
ANGLE_FROM_SPEED = "integrated measured speed (from 0 at the first sample)"


def angle_of(seg: SegmentView, member: Array) -> tuple[Array, str]:
    """The member angle ``c . theta`` over the segment, shape (N,), and its source.

    Uses ``seg.angles`` (measured angles of the outputs, shape (N, ny)) when the view carries
    them, else the integral of the measured member speed ``c . y`` from 0."""
    angles = getattr(seg, "angles", None)
    if isinstance(angles, np.ndarray) and angles.shape == seg.y.shape:
        return np.asarray(angles @ member, dtype=float), ANGLE_FROM_POSITION
    s = seg.y @ member
    return np.asarray(cumulative_trapezoid(s, dx=seg.dt, initial=0.0)), ANGLE_FROM_SPEED


def cell_mean_trig(theta: Array, order: float) -> tuple[Array, Array]:
    """Means of ``cos(k theta)`` and ``sin(k theta)`` over each step ``[theta_n, theta_n+1]``
    (the simulation holds a force over a step; the mean does not alias a fast ripple into a
    slow one), shape (N,) each; the last sample keeps its point value."""
    ph = order * theta
    c, s = np.cos(ph), np.sin(ph)
    d = np.diff(ph)
    small = np.abs(d) < 1e-6
    dd = np.where(small, 1.0, d)
    cm = np.where(small, 0.5 * (c[:-1] + c[1:]), (s[1:] - s[:-1]) / dd)
    sm = np.where(small, 0.5 * (s[:-1] + s[1:]), (c[:-1] - c[1:]) / dd)
    return np.append(cm, c[-1]), np.append(sm, s[-1])


@dataclass
class GravityLoad(Effect):
    """Gravity (or an unbalance) behind an output stage: ``a cos(theta / N) + b sin(theta / N)``
    on the member, ``theta`` its angle, ``N`` the stage's reduction.

    Options: ``reduction`` (known ``N``, fixed in the fit) or ``reductions`` (a list scanned
    by the scorer; the refit starts from the best and estimates ``N``). Parameters ``a``, ``b``
    [force unit], ``N`` [1].
    """

    name = "gravity_load"
    no_term = "the model node has no gravity-load term"

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        ctx.state_index()
        ns = ctx.numbers("reductions") or [ctx.number("reduction", 1.0)]
        if any(not n > 0 for n in ns):
            raise DescriptionError(f"candidate gravity_load@{ctx.where}: reductions must be > 0, "
                                   f"got {ns}")
        fu, sfx, inf = ctx.force_unit, ctx.suffix, math.inf
        params = (ParamSpec("gravity_a" + sfx, 0.0, -inf, inf, fu),
                  ParamSpec("gravity_b" + sfx, 0.0, -inf, inf, fu),
                  ParamSpec("reduction" + sfx, ns[0], 1e-9, inf, "1", null=ns[0]))
        return cls(where=ctx.where, params=params, member=ctx.member_vector(),
                   options={**ctx.options, "reductions": ns})

    def _reductions(self) -> list[float]:
        return numbers_option(self.options, "reductions", [float(self.params[2].initial)],
                              f"candidate {self.label()}")

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        theta, _ = angle_of(seg, self.require_member())
        c, s = cell_mean_trig(theta, 1.0 / float(p[2]))
        return np.asarray(float(p[0]) * c + float(p[1]) * s)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        name = self.params[2].name
        return [(f"{name}={n:g}", {name: n}) for n in self._reductions()]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name, self.params[1].name)

    def fixed_names(self) -> tuple[str, ...]:
        """A known reduction (one value) is held fixed while fitting; a scanned one starts at
        the scorer's best value and is fitted (the scan only needs to land in its basin)."""
        return (self.params[2].name,) if len(self._reductions()) == 1 else ()

    def inadmissible(self, p: Array) -> str | None:
        bad = super().inadmissible(p)
        if bad is not None:
            return bad
        if float(np.hypot(p[0], p[1])) == 0.0:
            return "amplitude 0: the gravity_load effect is absent"
        return None

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        """Amplitude ``A`` and phase of ``A cos(theta / N + phase)``, and the amplitude behind
        the stage ``A N`` (the arm's ``m l g`` for a gravity load)."""
        try:
            a = values[self.params[0].name]
            b = values[self.params[1].name]
            n = values[self.params[2].name]
        except KeyError:
            return {}
        sfx = self.params[0].name.removeprefix("gravity_a")
        amp = float(math.hypot(a, b))
        return {"gravity_amplitude" + sfx: amp, "gravity_phase" + sfx: math.atan2(-b, a),
                "gravity_amplitude_behind_stage" + sfx: amp * n}

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """Which angle was used, and how far the output stage turned."""
        theta, source = angle_of(ctx.views[0], self.require_member())
        span = float(np.max(theta) - np.min(theta))
        return {"angle_source": source, "member_angle_span": span,
                "reductions_scanned": self._reductions()}, {}


# -- the generic term library --------------------------------------------------------------

SPEED_FACTORS = ("", "sign", "abs_sq", "cube")
"""Speed factors of a library term: none, ``sign(s)``, ``|s| s``, ``s^3``."""


@dataclass(frozen=True)
class LibTerm:
    """One library term ``S(s) T(k theta) u_i`` on a member.

    Attributes:
        speed: one of :data:`SPEED_FACTORS`.
        trig: ``""``, ``"cos"`` or ``"sin"``.
        order: the angle order ``k`` (per member revolution) when ``trig`` is set.
        input: the input index of the product, or -1.
    """

    speed: str = ""
    trig: str = ""
    order: float = 0.0
    input: int = -1

    def key(self, input_names: Sequence[str]) -> str:
        """A short parameter-name stem (``sgn_cos1``, ``u_motor_sgn``, ...)."""
        parts = {"sign": ["sgn"], "abs_sq": ["absq"], "cube": ["cube"], "": []}[self.speed]
        if self.trig:
            parts.append(f"{self.trig}{self.order:g}".replace(".", "p"))
        if self.input >= 0:
            parts.append(f"u_{input_names[self.input]}")
        return "_".join(parts) or "const"

    def evaluate(self, s: Array, theta: Array, u: Array) -> Array:
        """The term's value, shape (N,) (angle factors as step means, :func:`cell_mean_trig`)."""
        out = np.ones_like(s)
        if self.speed == "sign":
            out = np.sign(s)
        elif self.speed == "abs_sq":
            out = np.abs(s) * s
        elif self.speed == "cube":
            out = s ** 3
        if self.trig:
            c, sn = cell_mean_trig(theta, self.order)
            out = out * (c if self.trig == "cos" else sn)
        if self.input >= 0:
            out = out * u[:, self.input]
        return np.asarray(out, dtype=float)

    def text(self, member: str, input_names: Sequence[str]) -> str:
        """The factor product in symbols (``sign(w_carrier3)*cos(1*th_carrier3)``)."""
        f = {"sign": [f"sign(w_{member})"], "abs_sq": [f"|w_{member}|*w_{member}"],
             "cube": [f"w_{member}^3"], "": []}[self.speed]
        if self.trig:
            f.append(f"{self.trig}({self.order:g}*th_{member})")
        if self.input >= 0:
            f.append(f"i_{input_names[self.input]}")
        return "*".join(f) or "1"

    def unit(self, force_unit: str, speed_unit: str, input_unit: str) -> str:
        """The coefficient's unit: force over the term's unit."""
        den = {"sign": [], "abs_sq": [f"({speed_unit})^2"], "cube": [f"({speed_unit})^3"],
               "": []}[self.speed]
        if self.input >= 0:
            den.append(input_unit)
        return force_unit + ("/" + "/".join(den) if den else "")


def default_library(orders: Sequence[float], inputs: Sequence[int]) -> tuple[LibTerm, ...]:
    """The generic library on one member: ``sign(s)``, ``|s| s``, ``s^3``; ``cos/sin(k theta)``
    and ``sign(s) cos/sin(k theta)`` for each order; ``u_i sign(s)``, ``u_i cos/sin(k theta)``
    for each listed input (products with the inputs)."""
    out = [LibTerm("sign"), LibTerm("abs_sq"), LibTerm("cube")]
    for k in orders:
        for trig in ("cos", "sin"):
            out.append(LibTerm("", trig, float(k)))
            out.append(LibTerm("sign", trig, float(k)))
    for i in inputs:
        out.append(LibTerm("sign", "", 0.0, i))
        for k in orders:
            for trig in ("cos", "sin"):
                out.append(LibTerm("", trig, float(k), i))
    return tuple(out)


def mesh_orders(params_name: str = "physical") -> list[float]:
    """Sun teeth of each stage of a parameter set (the mesh orders per sun-shaft revolution),
    distinct, in stage order (:mod:`dvt_model.params`)."""
    from dvt_model.params import load_parameters

    teeth = [float(st.sun) for st in load_parameters(params_name).stages]
    return list(dict.fromkeys(teeth))


@dataclass
class Unlisted(Effect):
    """A sum of library terms on one member (see the module docstring).

    Options (description entry): ``orders`` (angle orders per member revolution, default
    1, 2, 3), ``mesh_orders`` (true: add each stage's sun teeth from the parameter set
    ``params``, default ``physical``), ``inputs`` (input names for the products, default the
    first input), ``max_terms`` (the search's cap, default 3).
    """

    name = "unlisted"
    no_term = "the model node has no generic library term"
    terms: tuple[LibTerm, ...] = ()
    input_names: tuple[str, ...] = ()
    member_name: str = ""
    units: tuple[str, str, str] = ("", "", "")
    library: bool = True
    angle_source: str = field(default="")

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        ctx.state_index()
        what = f"candidate unlisted@{ctx.where}"
        orders = numbers_option(ctx.options, "orders", [1.0, 2.0, 3.0], what)
        if ctx.options.get("mesh_orders"):
            orders += mesh_orders(str(ctx.options.get("params", "physical")))
        orders = list(dict.fromkeys(orders))
        raw_inputs = ctx.options.get("inputs", list(ctx.input_names[:1]))
        if not isinstance(raw_inputs, list):
            raise DescriptionError(f"{what}: inputs: expected a list of input names")
        inputs = [ctx.input_index(str(n)) for n in raw_inputs]
        terms = default_library(orders, inputs)
        units = (ctx.force_unit, ctx.speed_unit, str(ctx.options.get("input_unit", "A")))
        eff = cls(where=ctx.where, member=ctx.member_vector(), options=dict(ctx.options),
                  terms=terms, input_names=ctx.input_names, member_name=ctx.where,
                  units=units, library=True)
        return eff.with_terms(terms, np.zeros(len(terms)), library=True, suffix=ctx.suffix)

    def with_terms(self, terms: Sequence[LibTerm], values: Array, library: bool = False,
                   suffix: str = "") -> Unlisted:
        """A copy with these terms and initial coefficients (parameter ``k_<term>_<member>``)."""
        fu, sp, iu = self.units
        params = tuple(ParamSpec(f"k_{t.key(self.input_names)}_{self.member_name}{suffix}",
                                 float(v), -math.inf, math.inf, t.unit(fu, sp, iu))
                       for t, v in zip(terms, values, strict=True))
        return replace(self, terms=tuple(terms), params=params, library=library)

    def avoiding(self, taken: set[str]) -> Unlisted:
        """A copy whose parameter names avoid ``taken`` (a second ``unlisted`` effect on the same
        member gets ``_2``, ``_3``, ... appended)."""
        if not any(s.name in taken for s in self.params):
            return self
        n = 2
        while any(f"{s.name}_{n}" in taken for s in self.params):
            n += 1
        return replace(self, params=tuple(replace(s, name=f"{s.name}_{n}") for s in self.params))

    def subset(self, idx: Sequence[int], values: Array) -> Unlisted:
        """The proposal: the terms ``idx`` of the library with start coefficients ``values``."""
        return self.with_terms([self.terms[i] for i in idx], values)

    def regressors(self, seg: SegmentView) -> Array:
        """Every term's value on the segment, shape (N, n_terms)."""
        c = self.require_member()
        s = seg.y @ c
        theta, _ = angle_of(seg, c)
        return np.column_stack([t.evaluate(s, theta, seg.u) for t in self.terms])

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        if not self.terms:
            return None
        return np.asarray(self.regressors(seg) @ np.asarray(p, float))

    def formula(self, p: Sequence[float] | Array) -> str:
        """``tau_<member> = k1 [unit]*term1 + ...`` in physical units (torque on the member)."""
        fu, sp, iu = self.units
        parts = []
        for t, v in zip(self.terms, p, strict=True):
            term = t.text(self.member_name, self.input_names)
            parts.append(f"{float(v):+.4g} {t.unit(fu, sp, iu)}*{term}")
        body = " ".join(parts) if parts else "0"
        return f"tau_{self.member_name} = {body}".replace("= +", "= ")

    def label(self) -> str:
        """``unlisted@member`` for the library; with the formula (start values) for a
        proposal."""
        if self.library:
            return f"{self.name}@{self.where}"
        return f"{self.name}@{self.where}: {self.formula([s.initial for s in self.params])}"

    def inadmissible(self, p: Array) -> str | None:
        if not np.all(np.isfinite(p)):
            return "a coefficient is not finite"
        if self.params and not np.any(np.asarray(p) != 0.0):
            return "every coefficient is 0: the unlisted effect is absent"
        return None

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """The formula (start values), the member, the angle source."""
        _, source = angle_of(ctx.views[0], self.require_member())
        return {"formula": self.formula([s.initial for s in self.params]),
                "member": self.member_name, "angle_source": source}, {}
