"""The effect base class, its parameter specs and what an effect is built from.

The model is ``x' = A x + B u_eff + F (sum_e c_e tau_e)``, ``y = h(x)`` with ``C = I``, where
``F`` maps generalised forces to state derivatives (``M^-1`` for a mechanical structure, ``I`` for
a free state-space structure) and ``c_e`` (shape (nx,)) is the *member* an effect acts on: its
speed is ``s_e = c_e . x`` and, by virtual work, a force ``tau_e`` on it is the generalised force
``c_e tau_e``. An effect is one or more of these parts:

- input transform: ``u -> u_eff`` (backlash as an input dead zone, brake engagement lag);
- exogenous member force ``tau_e(t)`` known before simulating (Coulomb's constant offset, a periodic
  disturbance phase-locked to the measured member angle);
- state-dependent member force evaluated at the start of each step and held over it: a smooth
  ``tau = g(s)`` (Stribeck, windage, asymmetric viscous friction; the laws of
  :mod:`dvt_model.laws`, compiled in :mod:`dvt_identify.simloop`) or dry friction with a
  stick rule and a capacity ``C_k`` (Coulomb, brake lock-up);
- output transform ``y = h(x)`` (measurement delay, sensor gain).

Every effect is one class (:class:`Effect` subclass) that declares its vocabulary word
(``name``), how it is built for a ``where`` (:meth:`Effect.accepts`, :meth:`Effect.build`: its
parameters with bounds and physical constraints), its simulation hooks, its scoring hooks and the
model-node effect term it pushes (:meth:`Effect.model_term`, checked against
:mod:`dvt_model.contract`). The registry (:data:`dvt_identify.effects.REGISTRY`) is the tuple of
classes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from dvt_identify.errors import DescriptionError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ParamSpec:
    """One estimated parameter.

    Attributes:
        name: name in reports (e.g. ``M``, ``Fc``).
        initial: start value.
        lower, upper: bounds (``-inf``/``inf`` for none); an effect's physical constraint
            (friction >= 0, play >= 0, ...) is its bound.
        unit: unit text for reports.
        null: for an effect parameter, the value at which the effect vanishes.
        step: finite-difference step for the scoring regressor; ``None`` = automatic.
    """

    name: str
    initial: float
    lower: float = -math.inf
    upper: float = math.inf
    unit: str = ""
    null: float = 0.0
    step: float | None = None

    def __post_init__(self) -> None:
        if not self.lower <= self.initial <= self.upper:
            raise DescriptionError(f"parameter {self.name}: initial {self.initial} outside "
                                   f"bounds [{self.lower}, {self.upper}]")


@dataclass(frozen=True)
class SegmentView:
    """What an effect may look at: sample time, inputs, measured outputs and angles of one
    segment.

    Attributes:
        dt: sample time [s].
        u: inputs, shape (N, nu).
        y: measured outputs (= states), shape (N, ny).
        angles: measured angles, shape (N, ny) (:attr:`dvt_identify.data.Segment.angles`:
            column ``j`` the recorded position of the joint whose speed output ``j`` is, 0 for
            another output), or ``None`` when the recording has none (member angles then
            integrate the measured speed, :func:`dvt_identify.effects.position.angle_of`).
    """

    dt: float
    u: Array
    y: Array
    angles: Array | None = None

    @classmethod
    def of(cls, seg: Any) -> SegmentView:
        """The view of a segment (:class:`dvt_identify.data.Segment`, or anything with its
        ``dt``, ``u``, ``y`` and ``angles``)."""
        return cls(seg.dt, seg.u, seg.y, seg.angles)


def speed_scale(seg: SegmentView, member: Array) -> float:
    """The spread (std) of a member's speed ``c . x`` over a segment [speed unit]: from the
    measured outputs when they are the states (``y @ c``); when the structure has hidden states
    (fewer outputs than states) the largest spread of the outputs' time derivatives, the speed
    of a measured position (a rough scale, what a shape variant needs). 1 when it is 0."""
    y = np.asarray(seg.y, dtype=float)
    if y.ndim == 2 and y.shape[1] == member.shape[0]:
        s = float(np.std(y @ member))
    elif y.ndim == 2 and y.shape[0] >= 3:
        s = float(np.max(np.std(np.gradient(y, seg.dt, axis=0), axis=0)))
    else:
        s = 0.0
    return s if s > 0 and np.isfinite(s) else 1.0


@dataclass(frozen=True)
class ScoringContext:
    """What an effect may use for extra scoring evidence (:meth:`Effect.scoring_evidence`).

    Attributes:
        views: the scored segments, each as a :class:`SegmentView`.
        simulated: the baseline simulation of each segment, shape (N, ny) each.
        weights: output scale of the fit's residuals, shape (ny,).
        member_residual: the OE residual of the first segment mapped to a force on a member
            ``c`` (nx,): returns shape (N,) [force unit].
    """

    views: Sequence[SegmentView]
    simulated: Sequence[Array]
    weights: Array
    member_residual: Callable[[Array], Array]


@dataclass(frozen=True)
class BuildContext:
    """What an effect is built from: a description's ``{effect, where, ...}`` entry and the
    structure's names and units.

    Attributes:
        name: the vocabulary word.
        where: a state/output name or an input name (or a label, see the effect).
        state_names, input_names: the structure's names.
        force_unit, speed_unit: units for parameter reports.
        member: explicit member vector over the states, or ``None`` (unit vector of ``where``).
        options: effect options from the description.
        suffix: appended to parameter names to keep them unique (e.g. ``_sun_shaft``).
        output_names: the measured outputs when the structure has hidden states (empty: the
            outputs are the states).
    """

    name: str
    where: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    force_unit: str = ""
    speed_unit: str = ""
    member: tuple[float, ...] | None = None
    options: dict[str, object] = field(default_factory=dict)
    suffix: str = ""
    output_names: tuple[str, ...] = ()

    def output_index(self, w: str | None = None) -> int:
        """Index of output ``w`` (default ``where``) among the measured outputs (the states
        when the structure has no hidden states, ``output_names`` empty).

        Raises:
            DescriptionError: not an output.
        """
        outs = self.output_names or self.state_names
        w = self.where if w is None else w
        if w not in outs:
            raise DescriptionError(f"candidate {self.name}: where {w!r} is not a measured "
                                   f"output (outputs: {', '.join(outs)})")
        return outs.index(w)

    @property
    def at_state(self) -> bool:
        """Whether ``where`` names a state/output."""
        return self.where in self.state_names

    def state_index(self, w: str | None = None) -> int:
        """Index of state ``w`` (default ``where``).

        Raises:
            DescriptionError: not a state/output.
        """
        w = self.where if w is None else w
        if w not in self.state_names:
            raise DescriptionError(f"candidate {self.name}: where {w!r} is not a state/output "
                                   f"(states: {', '.join(self.state_names)})")
        return self.state_names.index(w)

    def input_index(self, w: str | None = None) -> int:
        """Index of input ``w`` (default ``where``).

        Raises:
            DescriptionError: not an input.
        """
        w = self.where if w is None else w
        if w not in self.input_names:
            raise DescriptionError(f"candidate {self.name}: {w!r} is not an input (inputs: "
                                   f"{', '.join(self.input_names)})")
        return self.input_names.index(w)

    def member_vector(self) -> Array:
        """The member vector, shape (nx,): the explicit one or the unit vector of ``where``.

        Raises:
            DescriptionError: wrong shape, or ``where`` is not a state.
        """
        nx = len(self.state_names)
        if self.member is not None:
            c = np.asarray(self.member, dtype=float)
            if c.shape != (nx,):
                raise DescriptionError(f"candidate {self.name}@{self.where}: member: expected "
                                       f"shape ({nx},), got {c.shape}")
            return c
        c = np.zeros(nx)
        c[self.state_index()] = 1.0
        return c

    def number(self, key: str, default: float) -> float:
        """Option ``key`` as a float (``default`` when absent).

        Raises:
            DescriptionError: not a number.
        """
        raw = self.options.get(key, default)
        if isinstance(raw, bool) or not isinstance(raw, int | float | str):
            raise DescriptionError(f"candidate {self.name}@{self.where}: {key}: expected a "
                                   f"number, got {raw!r}")
        try:
            return float(raw)
        except ValueError as exc:
            raise DescriptionError(f"candidate {self.name}@{self.where}: {key}: expected a "
                                   f"number, got {raw!r}") from exc

    def numbers(self, key: str, default: Sequence[float] = ()) -> list[float]:
        """Option ``key`` as a list of floats (``default`` when absent or empty).

        Raises:
            DescriptionError: not a list of numbers.
        """
        return numbers_option(self.options, key, default, f"candidate {self.name}@{self.where}")


def numbers_option(options: dict[str, object], key: str, default: Sequence[float],
                   what: str) -> list[float]:
    """``options[key]`` as a list of floats (``default`` when absent or empty).

    Raises:
        DescriptionError: naming ``what`` and ``key``: not a list of numbers.
    """
    raw = options.get(key)
    if not raw:
        return [float(v) for v in default]
    if not isinstance(raw, list | tuple):
        raise DescriptionError(f"{what}: {key}: expected a list of numbers, got {raw!r}")
    try:
        return [float(v) for v in raw]
    except (TypeError, ValueError) as exc:
        raise DescriptionError(f"{what}: {key}: expected a list of numbers, got {raw!r}") from exc


Term = dict[str, Any]
"""A model-node effect term (:data:`dvt_model.contract.EFFECT_TERMS`)."""


_REGISTERED: list[type[Effect]] = []
"""Every effect class in the order defined (:meth:`Effect.__init_subclass__`)."""


def overrides(effect: Effect | type[Effect], name: str) -> bool:
    """Whether the class of ``effect`` (an effect or an effect class) has its own ``name``
    method, not :class:`Effect`'s no-op."""
    cls = effect if isinstance(effect, type) else type(effect)
    return getattr(cls, name) is not getattr(Effect, name)


def registered() -> tuple[type[Effect], ...]:
    """Every effect class defined so far, by :attr:`Effect.order` (ties in definition order).

    :data:`dvt_identify.effects.REGISTRY` is this once every module of the package is
    imported."""
    return tuple(sorted(_REGISTERED, key=lambda c: c.order))


@dataclass
class Effect:
    """Base class of a candidate effect; subclasses override the parts they have.

    Class attributes (declared by each effect):
        name: the vocabulary word of the description (several classes may share one; the
            registry picks the first whose :meth:`accepts` is true).
        state_dependent: whether the effect adds a state-dependent member force.
        band_parameter: the model node's per-band parameter that a baseline instance on an
            input ``brake1..3`` sets with its first parameter (which carries the same name).
        no_term: why the model node cannot represent the effect (``""``: it can,
            see :meth:`model_term`).
        node_input_transform: the model node applies the effect's input transform itself, to
            the raw current before its model sees it (a ``dead_zone`` term): the push does not
            count it as an input transform the node's input terms would miss.
        order: the class's place in the registry (:func:`registered`; lower first, ties in
            definition order): the vocabulary lists names in the order of their first class,
            and of several classes sharing a name the first that accepts a ``where`` is built
            (the more specific one first). Default: after the suite's own effects.
        global_map: a non-local output map (sign-blind, saturation) that the baseline fit can
            absorb so that no local score sees it: the loop refits it when its
            :meth:`scoring_evidence` reports ``signature: True`` (a data signature a reader
            can check), first from the structure's prior values.
        chaotic_output: the output map is an impact oscillator whose long-horizon derivative
            carries no information (a change of 1e-9 in its input moves its output by O(1)
            a few seconds later: a load rattling in a play). The fit's tangents pass such a map
            as the identity for the directions that reach it from upstream (the load follows
            the member's mean speed) and difference it along its own parameters by the secant
            of :meth:`secant_step`; without this every figure of the fit's covariance came
            out about 1e6 times too small.

    Attributes:
        where: human-readable place (member/state, input or output name).
        params: parameter specs (names already made unique by the description).
        member: member vector c, shape (nx,), for force effects; else ``None``.
        index: input or output index for input/output effects; else -1.
        options: effect-specific options from the description.
        readout: the state each measured output reads (indices into the states, one per
            output) when the structure has hidden states (a mechanical structure whose sensors
            read positions, ``y = C x``); empty when the outputs are the states. An effect
            evaluated on the measured motion reads a member's speed and angle through it
            (:func:`dvt_identify.effects.position.member_motion`).
    """

    name: ClassVar[str] = "effect"
    order: ClassVar[float] = 1000.0
    state_dependent: ClassVar[bool] = False
    band_parameter: ClassVar[str | None] = None
    no_term: ClassVar[str] = "the model node has no such term"
    global_map: ClassVar[bool] = False
    node_input_transform: ClassVar[bool] = False
    chaotic_output: ClassVar[bool] = False
    where: str = ""
    params: tuple[ParamSpec, ...] = ()
    member: Array | None = None
    index: int = -1
    options: dict[str, object] = field(default_factory=dict)
    readout: tuple[int, ...] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Register every subclass that declares its own :attr:`name` (the registry,
        :func:`registered`): an effect class is found by being defined, in any module of
        :mod:`dvt_identify.effects` (the package imports them all)."""
        super().__init_subclass__(**kwargs)
        if "name" in cls.__dict__:
            _REGISTERED.append(cls)

    def reads_motion(self) -> bool:
        """Whether the effect is evaluated on the member's measured speed or angle (an
        exogenous force: gravity, a periodic or ``unlisted`` term), so that a structure with
        hidden states must measure the member's speed or position (:attr:`readout`)."""
        return False

    def depends_on_angle(self) -> bool:
        """Whether the effect's force depends on a member's angle (gravity behind a stage, a
        ripple phase-locked to an angle, an ``unlisted`` angle term). The angle is the one
        state an experiment does not repeat: a static effect in it is seen differently by
        windows of different angle coverage, which the drift check can read as a parameter
        changing over the recording (:mod:`dvt_identify.loop` tries these effects first when
        the baseline drifts)."""
        return False

    @classmethod
    def output_only(cls) -> bool:
        """Whether the effect acts on the outputs only: it has an output map
        (:meth:`output_transform`) and none of the parts that move the states (an input
        transform, a member force, a smooth law, a dry capacity, a break-away), so its
        parameters leave the simulated states as they are."""
        moving = ("input_transform", "exogenous_force", "smooth_law", "dry_capacity",
                  "breakaway")
        return overrides(cls, "output_transform") and not any(overrides(cls, n)
                                                               for n in moving)

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def accepts(cls, ctx: BuildContext) -> bool:
        """Whether this class is the one built for ``ctx`` (among those sharing its name)."""
        return True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:  # pragma: no cover - every effect overrides
        """The effect for ``ctx`` with its parameter specs.

        Raises:
            DescriptionError: bad where, member or options (naming them).
        """
        raise NotImplementedError

    # -- parts ---------------------------------------------------------------------------
    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        """Transformed inputs, shape (N, nu), or ``None`` when this effect has no input part."""
        return None

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        """Member force known before simulation, shape (N,), or ``None``."""
        return None

    def smooth_law(self, p: Array) -> tuple[int, float, float, float] | None:
        """A coded smooth member force ``(kind, p0, p1, p2)`` (:mod:`dvt_identify.simloop`;
        the simulation compiles these), or ``None``."""
        return None

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        """Dry-friction capacity (>= 0): a number or shape (N,); ``None`` for no dry part."""
        return None

    def dry_friction(self, p: Array, seg: SegmentView
                     ) -> tuple[Array | float, Array | float] | None:
        """The effect's share of its member's sliding dry friction: the force that opposes the
        member's motion in the positive and in the negative direction [force unit], each a
        number or shape (N,) over the segment's samples (it may depend on where the member
        is); ``None`` for an effect with no dry part. The shares of one member must add up to
        a friction that opposes the motion everywhere the data take the member
        (:mod:`dvt_identify.effects.dissipation`)."""
        return None

    def breakaway(self, p: Array) -> float:
        """Extra holding capacity at rest added to the member's dry friction."""
        return 0.0

    def blind_output(self) -> int | None:
        """The output this effect reads without its sign (a sign-blind sensor), or ``None``:
        a fit's starts then come from that output unfolded (:mod:`dvt_identify.unfold`)."""
        return None

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        """Transformed outputs, shape (N, ny), or ``None``."""
        return None

    def output_inverse(self, p: Array, y: Array, dt: float) -> Array | None:
        """Measured outputs (N, ny) with this effect's output map undone, approximately (for
        starts only: the fit runs through :meth:`output_transform`), or ``None`` when the map
        has no inverse to offer (a sign-blind map's is :mod:`dvt_identify.unfold`)."""
        return None

    def inverse_probes(self, dt: float) -> list[Array]:
        """Parameter vectors at which :meth:`output_inverse` is worth trying for starts when
        the effect's own value is not known yet (sample time ``dt`` [s]): its initial values."""
        return [np.array([q.initial for q in self.params], float)]

    # -- the model node ------------------------------------------------------------------
    def model_term(self, p: Array, outputs: Sequence[str]) -> Term | None:
        """The model node's effect term for parameters ``p`` (not yet validated; the push
        checks it with :func:`dvt_model.contract.validate_term`), or ``None`` when the node
        cannot represent this effect (the reason: :meth:`why_no_term`).

        Args:
            p: this effect's parameters, shape (n_params,).
            outputs: the model's output (state) names, in order.
        """
        return None

    def model_terms(self, p: Array, outputs: Sequence[str]) -> list[Term] | None:
        """The model node's effect terms for parameters ``p``: an effect may need several
        (``unlisted``: one ``library`` term per coefficient); default: :meth:`model_term` as a
        list. ``None`` when the node cannot represent the effect (:meth:`why_no_term`).

        Members are over ``outputs`` (the push reorders them to the node's speeds); a term's
        ``input`` is named by the model's input name (the push maps it to the contract's
        current name, :data:`dvt_model.contract.CURRENT_NAMES`).
        """
        term = self.model_term(p, outputs)
        return None if term is None else [term]

    def why_no_term(self, outputs: Sequence[str]) -> str:
        """Why :meth:`model_term` gives ``None`` for these outputs."""
        return self.no_term

    def member_list(self) -> list[float]:
        """The member vector as a list of floats.

        Raises:
            DescriptionError: the effect has no member.
        """
        return [float(v) for v in self.require_member()]

    def time_constants(self, p: Array) -> tuple[float, ...]:
        """Time constants [s] of the effect's own dynamics at ``p`` (the fit step must resolve
        them, :func:`dvt_identify.fitrate.fit_decimation`); none by default."""
        return ()

    # -- admissibility -------------------------------------------------------------------
    def inadmissible(self, p: Array) -> str | None:
        """Why the fitted parameters ``p`` are not a physical instance of the effect, or
        ``None`` when they are.

        Every parameter's bounds are its physical constraint (friction, drag, play, delay
        >= 0, ...): a value outside them (a fit that did not respect them) is inadmissible.
        The effect's first parameter is the one that makes it present; at its null value on
        a bound (friction 0, play 0, delay 0) the effect is absent: the other parameters
        alone are not this effect (e.g. Coulomb friction 0 with only its offset left)."""
        for spec, v in zip(self.params, p, strict=True):
            val = float(v)
            if not math.isfinite(val):
                return f"{spec.name} = {val}: not a finite value"
            scale = max(abs(spec.lower) if math.isfinite(spec.lower) else 0.0,
                        abs(spec.upper) if math.isfinite(spec.upper) else 0.0,
                        abs(spec.initial), 1e-12)
            tol = 1e-9 * scale
            if val < spec.lower - tol or val > spec.upper + tol:
                return (f"{spec.name} = {val:.6g} {spec.unit}".rstrip()
                        + f" violates its physical constraint {self._range(spec)}")
        if self.params:
            first = self.params[0]
            val = float(p[0])
            on_bound = first.null in (first.lower, first.upper)
            if on_bound and abs(val - first.null) <= 1e-9 * max(abs(first.initial), 1.0) + 1e-12:
                return (f"{first.name} = {val:.6g} sits at its physical limit {first.null:g}: "
                        f"the {self.name} effect is absent")
        return None

    @staticmethod
    def _range(spec: ParamSpec) -> str:
        if math.isfinite(spec.lower) and math.isfinite(spec.upper):
            return f"{spec.lower:g} <= {spec.name} <= {spec.upper:g}"
        if math.isfinite(spec.lower):
            return f"{spec.name} >= {spec.lower:g}"
        if math.isfinite(spec.upper):
            return f"{spec.name} <= {spec.upper:g}"
        return "(none)"

    def inadmissible_on(self, p: Array, states: Sequence[Array]) -> str | None:
        """Why the fitted parameters ``p`` are not a physical instance of the effect *on this
        data*, or ``None``: :meth:`inadmissible`, and what only the data can tell (a shape
        the fit stretched over the whole operating range, e.g. a Stribeck speed the member
        never gets beyond). ``states``: the fitted model's simulated states (N, nx) of each
        estimation segment (every member's speed, measured or hidden)."""
        return self.inadmissible(p)

    def unavailable(self, segs: Sequence[SegmentView]) -> str | None:
        """Why the effect cannot be built for these segments' rates (e.g. every contact
        frequency of the scan is above the Nyquist frequency), or ``None``: the scorer then
        skips it with this note."""
        for seg in segs:
            if not self.variants(seg):
                return (f"{self.label()}: no variant can be built at {1.0 / seg.dt:g} Hz "
                        "(its shapes are faster than the data can show)")
        return None

    # -- scoring helpers -----------------------------------------------------------------
    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        """Shape-parameter values the scorer tries: (label, {param name: value})."""
        return [("", {})]

    def gain_names(self) -> tuple[str, ...]:
        """Parameters whose sensitivities at the null values are the scoring regressors."""
        return tuple(s.name for s in self.params)

    def scoring_step(self, name: str, dt: float) -> float | None:
        """A fixed finite-difference step for the scoring regressor of parameter ``name``
        (``None``: the scorer chooses, from a probe or the spec's ``step``)."""
        return None

    def secant_step(self, loc: int, value: float) -> float | None:
        """The fit's difference step for own parameter ``loc`` at ``value`` when the output map
        is chaotic (:attr:`chaotic_output`; ``None``: the smooth rule's step)."""
        return None

    def scoring_evidence(self, ctx: ScoringContext) -> tuple[dict[str, object], dict[str, float]]:
        """Extra evidence for the report and better start values (parameter name -> value)."""
        return {}, {}

    def fixed_names(self) -> tuple[str, ...]:
        """Parameters held fixed while fitting."""
        return ()

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        """Derived physical figures given all fitted parameters by name (may be empty)."""
        return {}

    def label(self) -> str:
        """``name@where``."""
        return f"{self.name}@{self.where}"

    def with_initial(self, values: dict[str, float]) -> Effect:
        """Copy with new initial values (clipped into the bounds)."""
        new = tuple(replace(s, initial=float(np.clip(values.get(s.name, s.initial), s.lower,
                                                      s.upper)))
                    for s in self.params)
        return replace(self, params=new)

    def null_vector(self) -> Array:
        """Parameter values at which the effect vanishes, shape (n_params,)."""
        return np.array([s.null for s in self.params], dtype=float)

    def pindex(self, name: str) -> int:
        """Index of parameter ``name``."""
        for i, s in enumerate(self.params):
            if s.name == name:
                return i
        raise KeyError(name)

    def require_member(self) -> Array:
        """The member vector, shape (nx,).

        Raises:
            DescriptionError: the effect was built without one.
        """
        if self.member is None:
            raise DescriptionError(f"{self.label()}: needs a member vector")
        return self.member


@dataclass
class PassedOutput(Effect):
    """A chaotic output map's stand-in (:attr:`Effect.chaotic_output`): the same parameters and
    fixed names, no behaviour, so its map is the identity (:meth:`dvt_identify.simulation.
    OEModel.passing_chaotic`)."""

    fixed: tuple[str, ...] = ()

    def fixed_names(self) -> tuple[str, ...]:
        return self.fixed
