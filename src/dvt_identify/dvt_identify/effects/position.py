"""Position-dependent effects: gravity at the output and the generic ``unlisted`` term.

A member's angle is ``theta = c . q`` with ``q`` the generalised angles. It is taken from the
segment's measured angles when the segment carries them (an ``angles`` attribute of shape
(N, ny), from the recording's ``position``), else from integrating the measured member speed
from 0 at the segment's first sample (:func:`angle_of` says which; the evidence reports it).
With an integrated angle a phase is relative to the first sample. On a structure with hidden
states (sensors that read some of the states, :attr:`Effect.readout`) the member's speed and
angle are read through the sensors (:func:`member_motion`: a measured position is the angle
and its central difference the speed).

- :class:`GravityLoad` (``gravity_load``): a torque ``a cos(theta / N) + b sin(theta / N)`` on
  the member (carrier 3: an arm behind an output stage of reduction ``N``), amplitude
  ``hypot(a, b)`` and phase ``atan2(-b, a)`` (``A cos(theta / N + phase)``). ``N`` is a
  description option (``reduction``, held fixed) or scanned (``reductions``) and then fitted.
- :class:`Unlisted` (``unlisted``): a sum of library terms ``sum_j k_j phi_j`` on one member,
  each ``phi_j = S(s) T(k theta) P(u_i)`` (speed factor ``sign(s)``, ``|s| s``, ``s^3``, ``s``,
  ``|s|`` or 1, angle factor ``cos``/``sin`` of an order, a Legendre polynomial of the
  position over the member's travel (:data:`POLY`) or 1, input factor ``u_i``, ``|u_i|
  u_i``, ``u_i^3`` or 1). Built from a description entry it holds the whole library (the search
  :mod:`dvt_identify.unlisted` picks a few terms with :meth:`Unlisted.subset`); its label
  carries the formula in physical units.

All are exogenous forces evaluated on the measured speeds and angles (like a periodic
disturbance), so the simulation stays the compiled linear + dry-friction loop. Model node:
a ``gravity`` term and one ``library`` term per coefficient (:mod:`dvt_model.terms`), pushed only
when the angle was the measured position (:mod:`dvt_identify.push`); a travel polynomial has
no node term (reported, not pushed).
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
    Term,
    numbers_option,
)
from dvt_identify.errors import DescriptionError
from dvt_model.contract import LIBRARY_INPUT_POWERS, LIBRARY_SPEED_FACTORS

ANGLE_FROM_POSITION = "measured position"
ANGLE_FROM_SPEED = "integrated measured speed (from 0 at the first sample)"


def angle_of(seg: SegmentView, member: Array) -> tuple[Array, str]:
    """The member angle ``c . theta`` over the segment, shape (N,) [rad for a rad/s member],
    and its source (:data:`ANGLE_FROM_POSITION` or :data:`ANGLE_FROM_SPEED`).

    Uses ``seg.angles`` (measured angles of the outputs, shape (N, ny): the recorded position
    of each speed output's joint, 0 for another output) when the view carries them, else the
    integral of the measured member speed ``c . y`` from 0. With angle states among the
    outputs (a position description: states ``(angles, speeds)``), a member given on the speeds
    gets the measured angle of the same joints (the angle states as recorded)."""
    angles = seg.angles
    if isinstance(angles, np.ndarray) and angles.shape == seg.y.shape:
        return np.asarray(angles @ member, dtype=float), ANGLE_FROM_POSITION
    s = seg.y @ member
    return np.asarray(cumulative_trapezoid(s, dx=seg.dt, initial=0.0)), ANGLE_FROM_SPEED


def motion_unreadable(member: Array, readout: Sequence[int]) -> str | None:
    """Why a member's speed and angle cannot be read from the measured outputs of a structure
    with hidden states (``readout``: the state each output reads, :attr:`Effect.readout`;
    states ``(angles, speeds)`` of a mechanical structure), or ``None`` when they can: each
    speed state of the member is measured itself or through its angle (a position sensor)."""
    if not readout:
        return None
    n = member.size // 2
    for i in np.flatnonzero(member):
        if i < n:
            return f"the member is given on angle state {i}, not on a speed"
        if i not in readout and i - n not in readout:
            return (f"neither speed state {i} nor its angle state {i - n} is measured (the "
                    f"outputs read states {list(readout)})")
    return None


def member_motion(seg: SegmentView, member: Array, readout: Sequence[int] = ()
                  ) -> tuple[Array, Array, str]:
    """The member's measured speed ``c . v`` and angle ``c . theta`` over the segment, shape
    (N,) each [speed unit, angle unit], and the angle's source.

    Without ``readout`` (the outputs are the states) the speed is ``y @ member`` and the angle
    :func:`angle_of`'s. With ``readout`` (:attr:`Effect.readout`: a mechanical structure with
    hidden states, ``(angles, speeds)``) each speed state of the member is read from the output
    that measures it, else from the output that measures its angle (the speed then by central
    differences of the measured position); each angle from its position output, else the
    recorded position or the integrated speed (:func:`angle_of` on the speed outputs).

    Raises:
        DescriptionError: the member cannot be read (:func:`motion_unreadable`).
    """
    if not readout:
        theta, source = angle_of(seg, member)
        return np.asarray(seg.y @ member, dtype=float), theta, source
    why = motion_unreadable(member, readout)
    if why is not None:
        raise DescriptionError(f"member {list(member)}: its motion is not measured: {why}")
    y = np.asarray(seg.y, dtype=float)
    n = member.size // 2
    w_speed, w_diff, w_angle, w_int = (np.zeros(y.shape[1]) for _ in range(4))
    for i in np.flatnonzero(member):
        c = float(member[i])
        if i in readout:  # the speed is measured
            w_speed[readout.index(i)] += c
        else:  # through its position
            w_diff[readout.index(i - n)] += c
        if i - n in readout:  # the angle is measured
            w_angle[readout.index(i - n)] += c
        else:  # the recorded position of the speed's joint, or its integral
            w_int[readout.index(i)] += c
    speed = y @ w_speed
    if np.any(w_diff):
        speed = speed + np.gradient(y @ w_diff, seg.dt)
    angle, source = y @ w_angle, ANGLE_FROM_POSITION
    if np.any(w_int):
        rest, source = angle_of(seg, w_int)
        angle = angle + rest
    return np.asarray(speed, dtype=float), np.asarray(angle, dtype=float), source


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
    order = 150
    no_term = ""

    def depends_on_angle(self) -> bool:
        """Always: the torque is a function of the member's angle."""
        return True

    def reads_motion(self) -> bool:
        """Always: the member's measured angle."""
        return True

    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        """A ``gravity`` term: the same torque ``a cos(theta / N) + b sin(theta / N)`` on the
        member (the push sends it only when the angle was the measured position)."""
        return {"kind": "gravity", "member": self.member_list(), "a": float(p[0]),
                "b": float(p[1]), "reduction": float(p[2])}

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
        _, theta, _ = member_motion(seg, self.require_member(), self.readout)
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
        _, theta, source = member_motion(ctx.views[0], self.require_member(), self.readout)
        span = float(np.max(theta) - np.min(theta))
        return {"angle_source": source, "member_angle_span": span,
                "reductions_scanned": self._reductions()}, {}


# -- the generic term library --------------------------------------------------------------

SPEED_FACTORS = LIBRARY_SPEED_FACTORS
"""Speed factors of a library term: none, ``sign(s)``, ``|s| s``, ``s^3``, ``s`` (``lin``),
``|s|`` (``abs``) (the model node's, :data:`dvt_model.contract.LIBRARY_SPEED_FACTORS`)."""
INPUT_POWERS = LIBRARY_INPUT_POWERS
"""Input factors of a library term with an input: ``u``, ``|u| u`` (``abs_sq``), ``u^3``
(``cube``) (the model node's, :data:`dvt_model.contract.LIBRARY_INPUT_POWERS`)."""
_SPEED_KEY = {"": "", "sign": "sgn", "abs_sq": "absq", "cube": "cube", "lin": "w", "abs": "absw"}
_SPEED_UNIT_POWER = {"": 0, "sign": 0, "abs_sq": 2, "cube": 3, "lin": 1, "abs": 1}
_INPUT_UNIT_POWER = {"": 1, "abs_sq": 2, "cube": 3}


def _unit_power(unit: str, n: int, bracket: bool) -> str:
    """``unit`` to the power ``n`` in a denominator (``A``, ``A^2``, ``(rad/s)``,
    ``(rad/s)^2``); ``bracket``: always in brackets (else only a compound unit, and only
    when raised to a power)."""
    if n == 0:
        return ""
    if bracket or (n > 1 and not unit.isalnum()):
        unit = f"({unit})"
    return unit if n == 1 else f"{unit}^{n}"


POLY = "poly"
"""A library term's position factor that is a Legendre polynomial of the position over the
member's travel (:attr:`LibTerm.span`), not a periodic one: a linear axis or a joint with end
stops, whose position-dependent force (a cable carrier, a preload that varies along a ball
screw, a seal) has no period."""
MAX_DEGREE = 8
"""Highest degree of the travel polynomials (option ``degree``)."""


def legendre_of_travel(theta: Array, degree: int, span: tuple[float, float]) -> Array:
    """``P_degree(x)``, ``x = (2 theta - lo - hi) / (hi - lo)`` for ``span = (lo, hi)``, shape
    of ``theta`` (outside the travel the polynomial is extrapolated)."""
    from numpy.polynomial import legendre

    lo, hi = span
    x = (2.0 * np.asarray(theta, dtype=float) - lo - hi) / (hi - lo)
    coef = np.zeros(degree + 1)
    coef[degree] = 1.0
    return np.asarray(legendre.legval(x, coef), dtype=float)


@dataclass(frozen=True)
class LibTerm:
    """One library term ``S(s) T(k theta) P(u_i)`` on a member.

    Attributes:
        speed: one of :data:`SPEED_FACTORS`.
        trig: ``""``, ``"cos"`` or ``"sin"``.
        order: the angle order ``k`` (per member revolution) when ``trig`` is set.
        input: the input index of the product, or -1.
        mesh: 0: ``theta`` is the member's angle; ``k``: stage ``k``'s mesh angle ``theta_sun -
            theta_carrier_k`` (:class:`MeshStage`, ``order`` its sun teeth).
        power: the input factor ``P(u)``, one of :data:`INPUT_POWERS` (``""``: ``u``; ignored
            without an input).
        span: ``(lo, hi)`` of the member's travel [angle unit] for ``trig`` ``"poly"``: the
            factor is then the Legendre polynomial of degree ``order`` of the position
            normalised to ``x = (2 theta - lo - hi) / (hi - lo)`` (``[-1, 1]`` over the travel).
    """

    speed: str = ""
    trig: str = ""
    order: float = 0.0
    input: int = -1
    mesh: int = 0
    power: str = ""
    span: tuple[float, float] = (0.0, 0.0)

    def key(self, input_names: Sequence[str]) -> str:
        """A short parameter-name stem (``sgn_cos1``, ``sgn_u_motor``, ``u_motor_absq``,
        ``w_u_motor``, ...)."""
        parts = [_SPEED_KEY[self.speed]] if self.speed else []
        if self.trig == POLY:
            parts.append(f"P{self.order:g}")
        elif self.trig:
            parts.append(f"{self.trig}{self.order:g}".replace(".", "p"))
            if self.mesh:
                parts.append(f"mesh{self.mesh}")
        if self.input >= 0:
            parts.append(f"u_{input_names[self.input]}")
            if self.power:
                parts.append(_SPEED_KEY[self.power])
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
        elif self.speed == "lin":
            out = s.copy()
        elif self.speed == "abs":
            out = np.abs(s)
        if self.trig == POLY:
            out = out * legendre_of_travel(theta, round(self.order), self.span)
        elif self.trig:
            c, sn = cell_mean_trig(theta, self.order)
            out = out * (c if self.trig == "cos" else sn)
        if self.input >= 0:
            x = u[:, self.input]
            out = out * (np.abs(x) * x if self.power == "abs_sq"
                         else x ** 3 if self.power == "cube" else x)
        return np.asarray(out, dtype=float)

    def text(self, member: str, input_names: Sequence[str]) -> str:
        """The factor product in symbols (``sign(w_carrier3)*cos(1*th_carrier3)``,
        ``i_motor*|i_motor|``, ``|w_sun_shaft|*i_motor``)."""
        w = f"w_{member}"
        f = {"sign": [f"sign({w})"], "abs_sq": [f"|{w}|*{w}"], "cube": [f"{w}^3"],
             "lin": [w], "abs": [f"|{w}|"], "": []}[self.speed]
        if self.trig == POLY:
            f.append(f"P{self.order:g}(x_{member})")
        elif self.trig:
            angle = f"mesh{self.mesh}" if self.mesh else member
            f.append(f"{self.trig}({self.order:g}*th_{angle})")
        if self.input >= 0:
            i = f"i_{input_names[self.input]}"
            f.append({"abs_sq": f"{i}*|{i}|", "cube": f"{i}^3"}.get(self.power, i))
        return "*".join(f) or "1"

    def unit(self, force_unit: str, speed_unit: str, input_unit: str) -> str:
        """The coefficient's unit: force over the term's unit (``N m/(rad/s)^2``, ``N m/A^2``,
        ``N m/(rad/s)/A``)."""
        den = [_unit_power(speed_unit, _SPEED_UNIT_POWER[self.speed], True)]
        if self.input >= 0:
            den.append(_unit_power(input_unit, _INPUT_UNIT_POWER[self.power], False))
        den = [d for d in den if d]
        return force_unit + ("/" + "/".join(den) if den else "")


def default_library(orders: Sequence[float], inputs: Sequence[int],
                    mesh: Sequence[tuple[int, float]] = (),
                    travel: tuple[float, float] | None = None, degree: int = 4
                    ) -> tuple[LibTerm, ...]:
    """The generic library on one member: ``sign(s)``, ``|s| s``, ``s^3``; ``cos/sin(k theta)``
    and ``sign(s) cos/sin(k theta)`` for each order; and for each listed input ``u_i`` the
    actuator-map terms: ``u_i sign(s)``, ``u_i s``, ``u_i |s|`` (a gain that depends on the
    speed), ``|u_i| u_i``, ``u_i^3`` (a torque constant that saturates or stiffens) and ``u_i
    cos/sin(k theta)`` (a gain that depends on the angle). Each ``(stage, teeth)`` of ``mesh``
    adds the same angle terms on that stage's mesh angle at order ``teeth``. With ``travel``
    ``(lo, hi)``: ``P_j(x)`` and ``sign(s) P_j(x)`` for ``j = 1..degree`` (:data:`POLY`), a
    force and a friction that depend on where the member is along its travel."""
    angles = [(float(k), 0) for k in orders] + [(float(z), int(st)) for st, z in mesh]
    out = [LibTerm("sign"), LibTerm("abs_sq"), LibTerm("cube")]
    for k, m in angles:
        for trig in ("cos", "sin"):
            out.append(LibTerm("", trig, k, mesh=m))
            out.append(LibTerm("sign", trig, k, mesh=m))
    if travel is not None:
        for j in range(1, degree + 1):
            out.append(LibTerm("", POLY, float(j), span=travel))
            out.append(LibTerm("sign", POLY, float(j), span=travel))
    for i in inputs:
        out.append(LibTerm("sign", "", 0.0, i))
        for k, m in angles:
            for trig in ("cos", "sin"):
                out.append(LibTerm("", trig, k, i, mesh=m))
        out += [LibTerm("lin", input=i), LibTerm("abs", input=i),
                LibTerm(input=i, power="abs_sq"), LibTerm(input=i, power="cube")]
    return tuple(out)


def _travel(options: dict[str, object], what: str) -> tuple[float, float] | None:
    """Option ``travel`` as ``(lo, hi)`` with ``lo < hi`` finite, or ``None`` when absent.

    Raises:
        DescriptionError: naming ``what``, the option and the value.
    """
    raw = options.get("travel")
    if raw is None:
        return None
    vals = numbers_option(options, "travel", [], what)
    if len(vals) != 2 or not all(math.isfinite(v) for v in vals) or not vals[0] < vals[1]:
        raise DescriptionError(f"{what}: travel: expected [lo, hi] with lo < hi (the member's "
                               f"travel in its angle unit), got {raw!r}")
    return vals[0], vals[1]


def _degree(options: dict[str, object], what: str) -> int:
    """Option ``degree`` (of the travel polynomials): an integer 1..:data:`MAX_DEGREE`.

    Raises:
        DescriptionError: naming ``what`` and the value.
    """
    raw = options.get("degree", 4)
    if isinstance(raw, bool) or not isinstance(raw, int) or not 1 <= raw <= MAX_DEGREE:
        raise DescriptionError(f"{what}: degree: expected an integer from 1 to {MAX_DEGREE}, "
                               f"got {raw!r}")
    return raw


def mesh_orders(params_name: str = "physical") -> list[float]:
    """Sun teeth of each stage of a parameter set (the mesh orders per sun-shaft revolution),
    distinct, in stage order (:mod:`dvt_model.params`)."""
    from dvt_model.params import load_parameters

    teeth = [float(st.sun) for st in load_parameters(params_name).stages]
    return list(dict.fromkeys(teeth))


MESH_SPEEDS = ("sun_shaft", "carrier3")
"""Default states of the generalised speeds ``(omega_sun, omega_carrier3)`` of
:mod:`dvt_model.kinematics` (option ``mesh_speeds``)."""


@dataclass(frozen=True)
class MeshStage:
    """The sun/planet mesh of one planetary stage: it turns with ``Z_sun (theta_sun -
    theta_carrier_k)`` (a tooth passes per ``2 pi / Z_sun`` of the sun relative to its carrier).

    Attributes:
        stage: stage number ``k`` (1 = the input stage).
        teeth: the stage's sun tooth count ``Z_sun_k`` (the mesh order of the relative angle).
        form: ``theta_sun - theta_carrier_k`` as ``(a, b)`` with ``a theta_sun + b
            theta_carrier3`` (:func:`dvt_model.kinematics.kinematics` of the parameter set).
    """

    stage: int
    teeth: float
    form: tuple[float, float]

    @property
    def symbol(self) -> str:
        """``mesh<k>``: the name of the stage's relative angle in formulas."""
        return f"mesh{self.stage}"


def mesh_stages(params_name: str = "physical") -> list[MeshStage]:
    """The mesh of every stage of a parameter set (:mod:`dvt_model.params`), in stage order:
    its sun teeth and the member form ``sun - carrier_k`` of :mod:`dvt_model.kinematics`.

    Raises:
        DescriptionError: no such parameter set.
    """
    from dvt_model.errors import ParameterError
    from dvt_model.kinematics import kinematics
    from dvt_model.params import load_parameters

    try:
        params = load_parameters(params_name)
    except ParameterError as exc:
        raise DescriptionError(f"mesh stages: parameter set {params_name!r}: {exc}") from exc
    kin = kinematics(params)
    sun = kin.forms["sun"]
    out = []
    for k, st in enumerate(params.stages, start=1):
        carrier = kin.forms[f"carrier{k}"]
        out.append(MeshStage(stage=k, teeth=float(st.sun),
                             form=(float(sun[0] - carrier[0]), float(sun[1] - carrier[1]))))
    return out


def mesh_members(ctx: BuildContext) -> list[tuple[MeshStage, Array]]:
    """Each stage's mesh (option ``params``, default ``physical``) with its relative-angle
    form over the structure's states, shape (nx,) each: ``a`` at the state of ``omega_sun``,
    ``b`` at that of ``omega_carrier3`` (option ``mesh_speeds``, default
    :data:`MESH_SPEEDS`).

    Raises:
        DescriptionError: ``mesh_speeds`` is not two state names (naming the candidate).
    """
    what = f"candidate {ctx.name}@{ctx.where}"
    raw = ctx.options.get("mesh_speeds", list(MESH_SPEEDS))
    if not isinstance(raw, list | tuple) or len(raw) != 2:
        raise DescriptionError(f"{what}: mesh_speeds: expected the two states of the sun and "
                               f"carrier-3 speeds, got {raw!r}")
    missing = [str(n) for n in raw if str(n) not in ctx.state_names]
    if missing:
        raise DescriptionError(f"{what}: mesh_speeds: {missing} not a state (states: "
                               f"{', '.join(ctx.state_names)})")
    i_sun, i_c3 = (ctx.state_names.index(str(n)) for n in raw)
    out = []
    for ms in mesh_stages(str(ctx.options.get("params", "physical"))):
        c = np.zeros(len(ctx.state_names))
        c[i_sun] += ms.form[0]
        c[i_c3] += ms.form[1]
        out.append((ms, c))
    return out


@dataclass
class Unlisted(Effect):
    """A sum of library terms on one member (see the module docstring).

    Options (description entry): ``orders`` (angle orders per member revolution, default
    1, 2, 3), ``mesh_orders`` (true: add each stage's sun teeth from the parameter set
    ``params``, default ``physical``), ``mesh_stages`` (true: add the angle terms of each
    stage's mesh angle ``theta_sun - theta_carrier_k`` at its sun teeth, ``th_mesh<k>`` in the
    formula; ``mesh_speeds`` names the states of the sun and carrier-3 speeds, see
    :func:`mesh_members`), ``inputs`` (input names of the input-side terms: products with
    the speed and angle factors and the input's powers, :func:`default_library`; default the
    first input; ``[]``: none), ``max_terms`` (the search's cap, default 3), ``travel``
    (``[lo, hi]`` [angle unit]: the member's travel, a linear axis or a joint between end
    stops; adds Legendre polynomials of the position over it, plain and times ``sign(s)``,
    :data:`POLY`; without ``orders`` the periodic angle terms are then left out) and
    ``degree`` (of those polynomials, 1 to :data:`MAX_DEGREE`, default 4). The model node
    has no polynomial factor: a proposal with one is identified and reported, not pushed.

    Attributes:
        mesh_forms: stage ``k``'s mesh-angle form over the states at index ``k - 1``
            (shape (nx,) each; empty without ``mesh_stages``).
    """

    name = "unlisted"
    order = 160
    no_term = "every coefficient is 0"

    def depends_on_angle(self) -> bool:
        """When a term has an angle factor (a library holds them, a proposal may not)."""
        return any(t.trig for t in self.terms)

    def reads_motion(self) -> bool:
        """Always: its terms are functions of the member's measured speed and angle."""
        return True

    def model_terms(self, p: Array, outputs: Sequence[str]) -> list[Term] | None:
        """One ``library`` term per non-zero coefficient: ``k S(s) T(order theta) P(u)`` on the
        member, ``theta`` the member's angle or the term's mesh angle (field ``angle``), the
        input named by the model's input name (the push maps it to the node's current) and
        its power (field ``input_power``, only when not ``u``); ``None`` when every
        coefficient is 0."""
        out: list[Term] = []
        for t, k in zip(self.terms, p, strict=True):
            if float(k) == 0.0:
                continue
            if t.trig == POLY:
                return None  # the model node has no polynomial factor (why_no_term)
            term: Term = {"kind": "library", "member": self.member_list(), "k": float(k),
                          "speed": t.speed, "trig": t.trig,
                          "order": float(t.order) if t.trig else 0.0,
                          "input": self.input_names[t.input] if t.input >= 0 else ""}
            if t.trig and t.mesh:
                term["angle"] = [float(v) for v in self.mesh_form(t.mesh)]
            if t.input >= 0 and t.power:
                term["input_power"] = t.power
            out.append(term)
        return out or None
    terms: tuple[LibTerm, ...] = ()
    input_names: tuple[str, ...] = ()
    member_name: str = ""
    units: tuple[str, str, str] = ("", "", "")
    library: bool = True
    angle_source: str = field(default="")
    mesh_forms: tuple[tuple[float, ...], ...] = ()

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        ctx.state_index()
        what = f"candidate unlisted@{ctx.where}"
        travel = _travel(ctx.options, what)
        orders = numbers_option(ctx.options, "orders",
                                [] if travel is not None else [1.0, 2.0, 3.0], what)
        if ctx.options.get("mesh_orders"):
            orders += mesh_orders(str(ctx.options.get("params", "physical")))
        orders = list(dict.fromkeys(orders))
        raw_inputs = ctx.options.get("inputs", list(ctx.input_names[:1]))
        if not isinstance(raw_inputs, list):
            raise DescriptionError(f"{what}: inputs: expected a list of input names")
        inputs = [ctx.input_index(str(n)) for n in raw_inputs]
        stages = mesh_members(ctx) if ctx.options.get("mesh_stages") else []
        terms = default_library(orders, inputs, [(ms.stage, ms.teeth) for ms, _ in stages],
                                travel, _degree(ctx.options, what))
        units = (ctx.force_unit, ctx.speed_unit, str(ctx.options.get("input_unit", "A")))
        eff = cls(where=ctx.where, member=ctx.member_vector(), options=dict(ctx.options),
                  terms=terms, input_names=ctx.input_names, member_name=ctx.where,
                  units=units, library=True,
                  mesh_forms=tuple(tuple(float(v) for v in c) for _, c in stages))
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

    def _motion(self, seg: SegmentView) -> tuple[Array, dict[int, Array]]:
        """The member's speed (N,) and the angle each term reads, by mesh (0: the member's)."""
        s, theta, _ = member_motion(seg, self.require_member(), self.readout)
        thetas = {0: theta}
        for t in self.terms:
            if t.mesh not in thetas:
                thetas[t.mesh] = member_motion(seg, self.mesh_form(t.mesh), self.readout)[1]
        return s, thetas

    def regressors(self, seg: SegmentView) -> Array:
        """Every term's value on the segment, shape (N, n_terms)."""
        s, thetas = self._motion(seg)
        return np.column_stack([t.evaluate(s, thetas[t.mesh], seg.u) for t in self.terms])

    def mesh_form(self, stage: int) -> Array:
        """Stage ``stage``'s mesh-angle form over the states, shape (nx,).

        Raises:
            DescriptionError: the library was built without that stage (naming it).
        """
        if not 1 <= stage <= len(self.mesh_forms):
            raise DescriptionError(f"{self.name}@{self.where}: mesh stage {stage}: built with "
                                   f"{len(self.mesh_forms)} mesh stages (mesh_stages: true)")
        return np.asarray(self.mesh_forms[stage - 1], dtype=float)

    def mesh_angles(self) -> dict[str, str]:
        """What each ``th_mesh<k>`` of the terms is (for the report)."""
        return {f"th_mesh{k}": f"th_sun - th_carrier{k} (stage {k} sun/planet mesh)"
                for k in sorted({t.mesh for t in self.terms if t.mesh})}

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        if not self.terms:
            return None
        return np.asarray(self.regressors(seg) @ np.asarray(p, float))

    def dry_friction(self, p: Array, seg: SegmentView
                     ) -> tuple[Array | float, Array | float] | None:
        """The terms ``k sign(s) T(theta)`` without an input factor are a friction that depends
        on where the member is: ``-sum k T(theta)`` opposes the motion in either direction,
        shape (N,); ``None`` without such a term (a force, or an input-side term)."""
        dry = [(t, float(k)) for t, k in zip(self.terms, p, strict=True)
               if t.speed == "sign" and t.input < 0]
        if not dry:
            return None
        s, thetas = self._motion(seg)
        out = -sum((k * replace(t, speed="").evaluate(np.ones_like(s), thetas[t.mesh], seg.u)
                    for t, k in dry), np.zeros_like(s))
        return out, out

    def why_no_term(self, outputs: Sequence[str]) -> str:
        """A polynomial of the position (the node has none), else every coefficient 0."""
        if any(t.trig == POLY for t in self.terms):
            return ("a Legendre polynomial of the position over the travel: the model node has "
                    "no such factor")
        return self.no_term

    def formula(self, p: Sequence[float] | Array) -> str:
        """``tau_<member> = k1 [unit]*term1 + ...`` in physical units (torque on the member);
        with a travel polynomial ``P_j(x_<member>)``, the normalised position
        ``x = (2 theta - lo - hi) / (hi - lo)`` follows."""
        fu, sp, iu = self.units
        parts = []
        for t, v in zip(self.terms, p, strict=True):
            term = t.text(self.member_name, self.input_names)
            parts.append(f"{float(v):+.4g} {t.unit(fu, sp, iu)}*{term}")
        body = " ".join(parts) if parts else "0"
        out = f"tau_{self.member_name} = {body}".replace("= +", "= ")
        spans = {t.span for t in self.terms if t.trig == POLY}
        for lo, hi in sorted(spans):
            out += (f"; x_{self.member_name} = (2*th_{self.member_name} - ({lo:g}) - ({hi:g})) "
                    f"/ ({hi - lo:g}), P_j Legendre")
        return out

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
        _, _, source = member_motion(ctx.views[0], self.require_member(), self.readout)
        return {"formula": self.formula([s.initial for s in self.params]),
                "member": self.member_name, "angle_source": source}, {}
