"""Candidate effects: named terms the augment loop may add to the simulated model.

The model is ``x' = A x + B u_eff + F (sum_e c_e tau_e)``, ``y = h(x)`` with ``C = I``, where
``F`` maps generalised forces to state derivatives (``M^-1`` for a mechanical structure, ``I`` for
a free state-space structure) and ``c_e`` (shape (nx,)) is the *member* an effect acts on: its
speed is ``s_e = c_e . x`` and, by virtual work, a force ``tau_e`` on it is the generalised force
``c_e tau_e``. An effect is one or more of these parts:

- input transform: ``u -> u_eff`` (backlash as an input dead zone, brake engagement lag);
- exogenous member force ``tau_e(t)`` known before simulating (Coulomb's constant offset, a periodic
  disturbance phase-locked to the measured member angle);
- state-dependent member force evaluated at the start of each step and held over it: a smooth
  ``tau = g(s)`` (Stribeck, windage, asymmetric viscous friction) or dry friction with a stick rule
  and a capacity ``C_k`` (Coulomb, brake lock-up);
- output transform ``y = h(x)`` (measurement delay, sensor gain).

Every effect has parameters (:class:`ParamSpec`) with *null* values for which it vanishes. The
scorer (:mod:`dvt_identify.loop`) uses the output sensitivities at the null values as regressors
(the Jacobian columns the parameters would add, by finite differences); ``variants`` lists the
shape parameters it scans (Stribeck speed, periodic order).

Vocabulary (contract): ``coulomb_friction``, ``stribeck_friction``, ``windage``, ``backlash``,
``measurement_delay``, ``brake_engagement``, ``brake_lockup``, ``sensor_gain``,
``periodic_disturbance``; project addition: ``asymmetric_friction`` (direction-dependent viscous
friction ``-dFv |s|``, so ``Fv+ = Fv + dFv``, ``Fv- = Fv - dFv``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import cumulative_trapezoid

from dvt_identify.errors import DescriptionError
from dvt_identify.simloop import ABS_VISCOUS, STRIBECK, WINDAGE, spline_load

Array = NDArray[np.float64]

VOCABULARY = ("coulomb_friction", "stribeck_friction", "windage", "backlash", "measurement_delay",
              "brake_engagement", "brake_lockup", "sensor_gain", "periodic_disturbance",
              "asymmetric_friction")


@dataclass(frozen=True)
class ParamSpec:
    """One estimated parameter.

    Attributes:
        name: name in reports (e.g. ``M``, ``Fc``).
        initial: start value.
        lower, upper: bounds (``-inf``/``inf`` for none).
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
    """What an effect may look at: sample time, inputs and measured outputs of one segment.

    Attributes:
        dt: sample time [s].
        u: inputs, shape (N, nu).
        y: measured outputs (= states), shape (N, ny).
    """

    dt: float
    u: Array
    y: Array


@dataclass
class Effect:
    """Base class of a candidate effect; subclasses override the parts they have.

    Attributes:
        where: human-readable place (member/state, input or output name).
        params: parameter specs (names already made unique by the description).
        member: member vector c, shape (nx,), for force effects; else ``None``.
        index: input or output index for input/output effects; else -1.
        options: effect-specific options from the description.
    """

    name: ClassVar[str] = "effect"
    state_dependent: ClassVar[bool] = False
    where: str = ""
    params: tuple[ParamSpec, ...] = ()
    member: Array | None = None
    index: int = -1
    options: dict[str, object] = field(default_factory=dict)

    # -- parts ---------------------------------------------------------------------------
    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        """Transformed inputs, shape (N, nu), or ``None`` when this effect has no input part."""
        return None

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        """Member force known before simulation, shape (N,), or ``None``."""
        return None

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        """A coded smooth member force ``(kind, p0, p1)`` (:mod:`dvt_identify.simloop`; the
        simulation compiles these), or ``None``."""
        return None

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        """Dry-friction capacity (>= 0): a number or shape (N,); ``None`` for no dry part."""
        return None

    def breakaway(self, p: Array) -> float:
        """Extra holding capacity at rest added to the member's dry friction."""
        return 0.0

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        """Transformed outputs, shape (N, ny), or ``None``."""
        return None

    # -- scoring helpers -----------------------------------------------------------------
    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        """Shape-parameter values the scorer tries: (label, {param name: value})."""
        return [("", {})]

    def gain_names(self) -> tuple[str, ...]:
        """Parameters whose sensitivities at the null values are the scoring regressors."""
        return tuple(s.name for s in self.params)

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


def _sign(s: float) -> float:
    return 1.0 if s > 0.0 else (-1.0 if s < 0.0 else 0.0)


@dataclass
class CoulombFriction(Effect):
    """Dry friction ``-Fc sign(s)`` with a stick rule, plus a constant ``-offset`` (optional).

    Parameters ``Fc`` (>= 0) and ``offset`` [force unit]. At rest the member stays stuck while the
    force needed to hold it is within ``Fc``.
    """

    name = "coulomb_friction"
    state_dependent = True

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        return float(p[0])

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        if len(self.params) < 2:
            return None
        return np.full(seg.u.shape[0], -float(p[1]))

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        if len(self.params) < 2:
            return {}
        fc, off = values[self.params[0].name], values[self.params[1].name]
        sfx = self.params[0].name[2:]
        # Force opposing motion: +dir: Fc + offset, -dir: Fc - offset.
        return {f"Fc+{sfx}": fc + off, f"Fc-{sfx}": fc - off}


@dataclass
class StribeckFriction(Effect):
    """Stribeck term ``-Fs exp(-(s/vs)^2) sign(s)``; ``Fs`` adds to the holding capacity at rest.

    Parameters ``Fs`` (>= 0, force unit) and ``vs`` (> 0, member speed unit; scanned).
    """

    name = "stribeck_friction"
    state_dependent = True

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (STRIBECK, float(p[0]), max(float(p[1]), 1e-12))

    def breakaway(self, p: Array) -> float:
        return max(float(p[0]), 0.0)

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        assert self.member is not None
        s_std = float(np.std(seg.y @ self.member)) or 1.0
        name = self.params[1].name
        return [(f"{name}={f * s_std:.3g}", {name: f * s_std}) for f in (0.02, 0.05, 0.1, 0.2, 0.5)]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name,)


@dataclass
class Windage(Effect):
    """Quadratic drag ``-Cw s |s|``; parameter ``Cw`` (>= 0)."""

    name = "windage"
    state_dependent = True

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (WINDAGE, float(p[0]), 0.0)


@dataclass
class AsymmetricFriction(Effect):
    """Direction-dependent viscous friction ``-dFv |s|`` (project addition to the vocabulary).

    With the structure's viscous coefficient ``Fv``: ``Fv+ = Fv + dFv``, ``Fv- = Fv - dFv``.
    """

    name = "asymmetric_friction"
    state_dependent = True

    def smooth_law(self, p: Array) -> tuple[int, float, float] | None:
        return (ABS_VISCOUS, float(p[0]), 0.0)

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        fv_name = str(self.options.get("viscous", "Fv"))
        if fv_name not in values:
            return {}
        fv, d = values[fv_name], values[self.params[0].name]
        sfx = self.params[0].name[3:]
        return {f"Fv+{sfx}": fv + d, f"Fv-{sfx}": fv - d}


@dataclass
class Backlash(Effect):
    """Dead zone of half-width ``delta`` on one input: ``u -> u - clip(u, -delta, delta)``.

    Models transmission backlash/lost motion seen from the input side (no position state is
    needed). Parameter ``delta`` (>= 0, input unit).
    """

    name = "backlash"

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        d = max(float(p[0]), 0.0)
        out = u.copy()
        out[:, self.index] = u[:, self.index] - np.clip(u[:, self.index], -d, d)
        return out


@dataclass
class OutputBacklash(Effect):
    """Lost motion of half-width ``delta`` between a member and its speed sensor (play
    operator on the integrated output): after a reversal the sensed shaft stands still until
    the gap is crossed. ``theta_out`` follows ``theta = integral of x_j`` within
    ``[theta - delta, theta + delta]``; the measured speed is ``d theta_out / dt``.
    Parameter ``delta`` (>= 0, rad or m).
    """

    name = "backlash"

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        d = max(float(p[0]), 0.0)
        if d == 0.0:
            return None
        j = self.index
        theta = np.concatenate([[0.0], np.cumsum(y[:-1, j]) * dt])
        out_pos = np.empty_like(theta)
        pos = 0.0
        for k, th in enumerate(theta.tolist()):
            if th - pos > d:
                pos = th - d
            elif pos - th > d:
                pos = th + d
            out_pos[k] = pos
        out = y.copy()
        speed = np.empty(y.shape[0])
        speed[:-1] = np.diff(out_pos) / dt
        speed[-1] = y[-1, j] if abs(theta[-1] - out_pos[-1]) >= d else 0.0
        out[:, j] = speed
        return out


@dataclass
class BrakeEngagement(Effect):
    """First-order engagement lag of one input: ``tau u_eff' = u - u_eff`` (exact ZOH steps).

    Parameter ``tau`` (>= 0, s); ``u_eff`` starts at ``u[0]``.
    """

    name = "brake_engagement"

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        tau = float(p[0])
        if tau <= 0.0:
            return None
        from scipy.signal import lfilter

        e = math.exp(-dt / tau)
        out = u.copy()
        col = u[:, self.index]
        # u_eff[k+1] = e u_eff[k] + (1 - e) u[k], u_eff[0] = u[0]
        zi = np.array([e * col[0]])
        filt, _ = lfilter([0.0, 1.0 - e], [1.0, -e], col, zi=zi)
        filt[0] = col[0]
        out[:, self.index] = filt
        return out


@dataclass
class BrakeLockup(Effect):
    """Brake on a member: dry friction with capacity ``Tb * max(u_brake, 0)`` and stick rule.

    The member (``c`` over the states) locks when its speed reaches zero while the holding force
    is within the capacity. Parameter ``Tb`` (>= 0, force unit per brake-input unit).
    """

    name = "brake_lockup"
    state_dependent = True

    def dry_capacity(self, p: Array, seg: SegmentView) -> Array | float | None:
        return np.asarray(float(p[0]) * np.clip(seg.u[:, self.index], 0.0, None))


@dataclass
class MeasurementDelay(Effect):
    """Output ``j`` measured ``d`` seconds late: ``y_j(t) = x_j(t - d)`` (linear interpolation,
    the first value held before the start). Parameter ``d`` in ``[0, max_delay]`` s."""

    name = "measurement_delay"

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        d = float(p[0])
        if d == 0.0:
            return None
        out = y.copy()
        n = y.shape[0]
        k = np.arange(n, dtype=float) - d / dt
        out[:, self.index] = np.interp(k, np.arange(n, dtype=float), y[:, self.index])
        return out

    def scan(self, y_sim: Array, y_meas: Array, dt: float, weight: float) -> list[dict[str, float]]:
        """Delay scan: weighted SSE of output ``j`` for the simulated output shifted by 0..K
        samples (K = max_delay / dt), without refitting."""
        kmax = max(1, int(np.rint(float(self.params[0].upper) / dt)))
        out = []
        for k in range(0, kmax + 1):
            shifted = self.output_transform(np.array([k * dt]), y_sim, dt)
            ys = y_sim if shifted is None else shifted
            e = (y_meas[:, self.index] - ys[:, self.index]) / weight
            out.append({"delay_s": k * dt, "sse": float(e @ e)})
        return out


@dataclass
class SensorGain(Effect):
    """Output ``j`` scaled by ``(1 + g)``; parameter ``g`` (dimensionless)."""

    name = "sensor_gain"

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        g = float(p[0])
        if g == 0.0:
            return None
        out = y.copy()
        out[:, self.index] = (1.0 + g) * y[:, self.index]
        return out


def member_angle(seg: SegmentView, member: Array) -> Array:
    """Measured member angle ``int c.y dt`` from 0 [member speed unit x s], shape (N,)."""
    s = seg.y @ member
    return np.asarray(cumulative_trapezoid(s, dx=seg.dt, initial=0.0))


@dataclass
class PeriodicDisturbance(Effect):
    """Force ``a cos(k theta) + b sin(k theta)`` phase-locked to the measured member angle
    ``theta`` (order ``k``, e.g. 1 per shaft revolution, tooth count for a mesh), or to time
    (``theta = 2 pi t``, ``k`` in Hz) when the option ``clock`` is ``time``.

    Parameters ``a``, ``b`` (force unit) and ``order`` (fixed during a fit; the scorer scans the
    listed ``orders``).
    """

    name = "periodic_disturbance"

    def _phase(self, seg: SegmentView) -> Array:
        if self.options.get("clock") == "time":
            return np.asarray(2.0 * math.pi * seg.dt * np.arange(seg.u.shape[0]))
        assert self.member is not None
        return member_angle(seg, self.member)

    def exogenous_force(self, p: Array, seg: SegmentView) -> Array | None:
        a, b, k = float(p[0]), float(p[1]), float(p[2])
        ph = k * self._phase(seg)
        return np.asarray(a * np.cos(ph) + b * np.sin(ph))

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        orders = self.options.get("orders") or [float(self.params[2].initial)]
        name = self.params[2].name
        return [(f"{name}={float(k):g}", {name: float(k)}) for k in orders]  # type: ignore

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name, self.params[1].name)

    def order_spectrum(self, residual: Array, seg: SegmentView, n_grid: int = 200
                       ) -> dict[str, object]:
        """Amplitude of the residual's best-fitting ``cos/sin(k theta)`` pair for the listed
        orders and on a grid up to 1.5x the largest; the ratio to the grid's median is the
        evidence that a listed order stands out.

        Args:
            residual: weighted residual of the member's output(s), shape (N,).
        """
        raw = self.options.get("orders") or [self.params[2].initial]
        orders = [float(k) for k in raw]  # type: ignore[attr-defined]
        theta = self._phase(seg)
        kmax = 1.5 * max(orders)
        grid = np.linspace(kmax / n_grid, kmax, n_grid)

        def amp(k: float) -> float:
            X = np.column_stack([np.cos(k * theta), np.sin(k * theta)])
            coef, *_ = np.linalg.lstsq(X, residual, rcond=None)
            return float(np.hypot(coef[0], coef[1]))
        base = float(np.median([amp(k) for k in grid])) or 1e-300
        listed = {f"{k:g}": {"amplitude": amp(k), "ratio_to_median": amp(k) / base}
                  for k in orders}
        return {"orders": listed, "grid_median_amplitude": base,
                "grid": [float(grid[0]), float(grid[-1]), n_grid]}


EFFECT_CLASSES: dict[str, type[Effect]] = {
    "coulomb_friction": CoulombFriction,
    "stribeck_friction": StribeckFriction,
    "windage": Windage,
    "asymmetric_friction": AsymmetricFriction,
    "backlash": Backlash,
    "brake_engagement": BrakeEngagement,
    "brake_lockup": BrakeLockup,
    "measurement_delay": MeasurementDelay,
    "sensor_gain": SensorGain,
    "periodic_disturbance": PeriodicDisturbance,
}


def make_effect(name: str, where: str, state_names: Sequence[str], input_names: Sequence[str],
                force_unit: str = "", speed_unit: str = "", member: Sequence[float] | None = None,
                options: dict[str, object] | None = None, suffix: str = "") -> Effect:
    """Build a candidate effect.

    Args:
        name: effect name from :data:`VOCABULARY`.
        where: a state/output name (force and output effects), or an input name (``backlash``,
            ``brake_engagement``); ``brake_lockup`` acts on a member and names its brake input in
            ``options['input']``.
        state_names, input_names: the structure's names.
        force_unit, speed_unit: units for parameter reports.
        member: explicit member vector over the states (default: the unit vector of ``where``).
        options: effect options (``offset``: bool for Coulomb, ``orders``/``clock`` for periodic,
            ``max_delay`` [s] for the delay, ``input`` for lock-up, ``viscous`` for asymmetric).
        suffix: appended to parameter names to keep them unique (e.g. ``_sun_shaft``).

    Raises:
        DescriptionError: unknown effect, state or input name.
    """
    opts = dict(options or {})
    if name not in EFFECT_CLASSES:
        raise DescriptionError(f"candidate effect {name!r}: unknown (known: "
                               f"{', '.join(EFFECT_CLASSES)})")
    nx = len(state_names)
    inf = math.inf
    fu, su = force_unit, speed_unit
    cls = EFFECT_CLASSES[name]

    def state_index(w: str) -> int:
        if w not in state_names:
            raise DescriptionError(f"candidate {name}: where {w!r} is not a state/output "
                                   f"(states: {', '.join(state_names)})")
        return list(state_names).index(w)

    def input_index(w: str) -> int:
        if w not in input_names:
            raise DescriptionError(f"candidate {name}: {w!r} is not an input (inputs: "
                                   f"{', '.join(input_names)})")
        return list(input_names).index(w)

    def mvec() -> Array:
        if member is not None:
            c = np.asarray(member, dtype=float)
            if c.shape != (nx,):
                raise DescriptionError(f"candidate {name}@{where}: member: expected shape "
                                       f"({nx},), got {c.shape}")
            return c
        c = np.zeros(nx)
        c[state_index(where)] = 1.0
        return c

    P = ParamSpec
    sfx = suffix
    if name == "coulomb_friction":
        params: tuple[ParamSpec, ...] = (P("Fc" + sfx, 0.0, 0.0, inf, fu),)
        if opts.get("offset", True):
            params += (P("offset" + sfx, 0.0, -inf, inf, fu),)
        return cls(where=where, params=params, member=mvec(), options=opts)
    if name == "stribeck_friction":
        vs = float(opts.get("vs", 1.0))  # type: ignore[arg-type]
        params = (P("Fs" + sfx, 0.0, 0.0, inf, fu),
                  P("vs" + sfx, vs, 1e-9, inf, su, null=vs))
        return cls(where=where, params=params, member=mvec(), options=opts)
    if name == "windage":
        unit = f"{fu}/({su})^2" if fu and su else ""
        return cls(where=where, params=(P("Cw" + sfx, 0.0, 0.0, inf, unit),), member=mvec(),
                   options=opts)
    if name == "asymmetric_friction":
        unit = f"{fu}/({su})" if fu and su else ""
        return cls(where=where, params=(P("dFv" + sfx, 0.0, -inf, inf, unit),), member=mvec(),
                   options=opts)
    if name == "backlash":
        if where in state_names and opts.get("compliant"):  # play in a spline to a load
            unit = su.split("/")[0] if su else ""
            wn0 = float(opts.get("wn", 400.0))  # type: ignore[arg-type]
            z0 = float(opts.get("zeta", 0.15))  # type: ignore[arg-type]
            probe = float(opts.get("probe_gap", 0.01))  # type: ignore[arg-type]
            if not (wn0 > 0 and z0 > 0 and probe > 0):
                raise DescriptionError(f"candidate backlash@{where} (compliant): wn, zeta and "
                                       f"probe_gap must be > 0, got {wn0}, {z0}, {probe}")
            return CompliantOutputBacklash(
                where=where, index=state_index(where), options=opts,
                params=(P("gap" + sfx, 0.0, 0.0, 1.0, unit, step=probe),
                        P("wn" + sfx, wn0, 10.0, 1e4, f"1/{su.split('/')[-1]}" if su else "",
                          null=wn0),
                        P("zeta" + sfx, z0, 1e-3, 2.0, "1", null=z0)))
        if where in state_names:  # lost motion between the member and its sensor
            unit = su.split("/")[0] if su else ""
            return OutputBacklash(where=where, params=(P("delta" + sfx, 0.0, 0.0, 1.0, unit,
                                                         step=2e-3),),
                                  index=state_index(where), options=opts)
        return cls(where=where, params=(P("delta" + sfx, 0.0, 0.0, inf, "input unit"),),
                   index=input_index(where), options=opts)
    if name == "brake_engagement" and opts.get("dead_time"):
        tmax = float(opts.get("max_dead_time", 0.2))  # type: ignore[arg-type]
        if not tmax > 0:
            raise DescriptionError(f"candidate brake_engagement@{where} (dead_time): "
                                   f"max_dead_time must be > 0 s, got {tmax}")
        shared = opts.get("inputs")  # one dead time for several bands (same oil, same bands)
        if shared is None:
            idx: tuple[int, ...] = (input_index(where),)
        elif isinstance(shared, (list, tuple)) and shared:
            idx = tuple(input_index(str(n)) for n in shared)
            if len(set(idx)) != len(idx):
                raise DescriptionError(f"candidate brake_engagement@{where} (dead_time): "
                                       f"inputs: duplicate names in {list(shared)}")
        else:
            raise DescriptionError(f"candidate brake_engagement@{where} (dead_time): inputs: "
                                   f"expected a non-empty list of input names, got {shared!r}")
        return EngagementDeadTime(where=where, index=idx[0] if len(idx) == 1 else -1,
                                  indices=idx, options=opts,
                                  params=(P("td" + sfx, 0.0, 0.0, tmax, "s", step=5e-3),))
    if name == "brake_engagement":
        return cls(where=where, params=(P("tau" + sfx, 0.0, 0.0, 10.0, "s"),),
                   index=input_index(where), options=opts)
    if name == "brake_lockup":
        brake = str(opts.get("input", ""))
        return cls(where=where, params=(P("Tb" + sfx, 0.0, 0.0, inf, f"{fu}/input unit"),),
                   member=mvec(), index=input_index(brake), options=opts)
    if name == "measurement_delay":
        dmax = float(opts.get("max_delay", 0.02))  # type: ignore[arg-type]
        return cls(where=where, params=(P("delay" + sfx, 0.0, 0.0, dmax, "s"),),
                   index=state_index(where), options=opts)
    if name == "sensor_gain":
        return cls(where=where, params=(P("gain" + sfx, 0.0, -0.9, 10.0, "1", step=1e-3),),
                   index=state_index(where), options=opts)
    # periodic_disturbance
    orders = opts.get("orders")
    if not orders:
        raise DescriptionError(f"candidate periodic_disturbance@{where}: needs 'orders' "
                               "(per member revolution/unit, or Hz with clock: time)")
    k0 = float(orders[0])  # type: ignore[index]
    params = (P("a" + sfx, 0.0, -inf, inf, fu), P("b" + sfx, 0.0, -inf, inf, fu),
              P("order" + sfx, k0, 0.0, inf, "1", null=k0))
    return cls(where=where, params=params, member=mvec(), options=opts)


def fixed_names(effect: Effect) -> tuple[str, ...]:
    """Parameters held fixed while fitting (the periodic order)."""
    if isinstance(effect, PeriodicDisturbance):
        return (effect.params[2].name,)
    return ()


# ---------------------------------------------------------------------------------------------
# Compliant play between a member and its sensor shaft (backlash with a load behind a spline)

@dataclass
class CompliantOutputBacklash(Effect):
    """Free play in a compliant spline between a member and the shaft that carries its speed
    sensor and a load (vocabulary name ``backlash``; description option ``compliant: true``).

    The sensed shaft (load speed ``w_L``) is driven one way by the model's member speed ``w``
    through the play ``gap`` and a spring-damper contact: with the twist ``z = theta - theta_L``,
    ``w_L' = max(0, wn^2 (z - gap/2) + 2 zeta wn (w - w_L))`` for ``z > gap/2`` (mirrored for
    ``z < -gap/2``, nothing inside the gap), ``z' = w - w_L``; the output is ``w_L`` averaged over
    the sample interval centred on the sample (the zero-phase anti-alias filter of decimated
    data leaves no more of a sub-sample impact transient). ``wn`` is the contact frequency of the
    load on the spline (``sqrt(k / J_load)``) and ``zeta`` its damping ratio. The load's
    inertia and drag load the member at low frequency like a rigid part of it, which the fitted
    structure absorbs; the reaction of the impacts on the member is not modelled (one-way).

    Parameters: ``gap`` [rad, total play, >= 0; 0 = rigid: the effect vanishes, compliance
    included], ``wn`` [rad/s] and ``zeta`` [1] (shape parameters, scanned by the scorer). The
    effect is not differentiable at ``gap = 0`` (an impact oscillator), so the scorer's gap
    regressor is the secant to a probe play (``gap`` spec ``step``, default 0.01 rad).
    """

    name = "backlash"

    def label(self) -> str:
        """``backlash@where(compliant)``: distinct from the rigid play on the same output."""
        return f"{self.name}@{self.where}(compliant)"

    def output_transform(self, p: Array, y: Array, dt: float) -> Array | None:
        gap, wn, zeta = max(float(p[0]), 0.0), max(float(p[1]), 1e-9), max(float(p[2]), 0.0)
        if gap == 0.0:
            return None
        # sub-steps: wn h <= 0.2 (the explicit contact stays accurate) and an even count
        sub = max(2, math.ceil(dt * wn / 0.2))
        sub += sub % 2
        out = y.copy()
        out[:, self.index] = spline_load(y[:, self.index], dt, 0.5 * gap, wn * wn,
                                          2.0 * zeta * wn, sub)
        return out

    def variants(self, seg: SegmentView) -> list[tuple[str, dict[str, float]]]:
        """Grid of contact frequency ``wn`` (below the Nyquist frequency of ``seg``: the data
        cannot show a faster contact), damping ratio and probe play (the gap regressor's
        secant step); options ``wn_scan``, ``zeta_scan``, ``gap_scan``."""
        g_name, wn_name, z_name = (s.name for s in self.params)
        opts = self.options

        def grid(key: str, default: tuple[float, ...]) -> list[float]:
            return [float(v) for v in opts.get(key, default)]  # type: ignore[attr-defined]
        nyq = math.pi / seg.dt
        return [(f"{g_name}={g:g},{wn_name}={wn:g},{z_name}={z:g}",
                 {g_name: g, wn_name: wn, z_name: z})
                for g in grid("gap_scan", (0.005, 0.01, 0.02, 0.04))
                for wn in grid("wn_scan", (150.0, 250.0, 350.0, 450.0, 600.0, 1000.0)) if wn < nyq
                for z in grid("zeta_scan", (0.05, 0.1, 0.2, 0.4))]

    def gain_names(self) -> tuple[str, ...]:
        return (self.params[0].name,)

    def derived(self, values: dict[str, float]) -> dict[str, float]:
        wn = values.get(self.params[1].name)
        if wn is None:
            return {}
        return {f"fn{self.params[1].name[2:]}": wn / (2.0 * math.pi)}


@dataclass
class EngagementDeadTime(Effect):
    """Dead time of a band's engagement (vocabulary name ``brake_engagement``; description
    option ``dead_time: true``): a wet band first squeezes out its oil film and transmits
    (almost) nothing for ``t_d`` seconds after it is energised, then builds its torque; it
    releases at once. On the (already lagged) brake input ``u``:
    ``u_eff(t) = min(u(t), u(t - t_d))`` (linear interpolation, the first value held before the
    start), which delays every rise by ``t_d`` and no fall. Together with the model's
    first-order engagement lag this gives an S-shaped (delayed) engagement; ``t_d = 0`` is the
    lag alone. Parameter ``t_d`` in ``[0, max_dead_time]`` s.

    With the description option ``inputs: [brake1, brake2, ...]`` one ``t_d`` applies to every
    listed input (identical bands in the same oil; ``where`` is then only a label, e.g.
    ``brakes``): ``indices`` holds the input columns, ``index`` is -1 (no single input).
    """

    name = "brake_engagement"
    indices: tuple[int, ...] = ()

    def label(self) -> str:
        """``brake_engagement@where(dead_time)``: distinct from the second lag stage."""
        return f"{self.name}@{self.where}(dead_time)"

    def input_transform(self, p: Array, u: Array, dt: float) -> Array | None:
        td = float(p[0])
        if td <= 0.0:
            return None
        cols = self.indices or (self.index,)
        n = u.shape[0]
        k = np.arange(n, dtype=float)
        out = u.copy()
        for j in cols:
            col = u[:, j]
            late = np.interp(k - td / dt, k, col)
            out[:, j] = np.minimum(col, late)
        return out
