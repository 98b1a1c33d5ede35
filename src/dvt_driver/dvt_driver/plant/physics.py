"""The simulated transmission: ``dvt_model`` hybrid physics plus the hidden effects (pure).

:class:`Transmission` is the physical half of the simulated plant (:class:`~dvt_driver.plant.
core.PlantSim` is the controller firmware that drives it): the members' speeds and angles, the
drive's power stage (the motor current follows the controller's reference with a first-order
lag), the band-brake coil currents the controller holds, the output shaft behind a backlash,
and the hidden effects of :mod:`dvt_driver.plant.hidden` as generalised torques
(:class:`FrictionForces`, :class:`WetBrakeEngagement`, the position-dependent effects). It is
stepped one physics sub-step at a time (:meth:`Transmission.advance`) with the sub-step length
set by :meth:`Transmission.configure`.

Angles and loads. The physics integrates the members' angles (``HybridState.theta``, sun shaft
and carrier 3 from the plant's start; every other member's angle is its linear form of them).
An optional declared joint load (``load=``, ``dvt-plant --load arm|arm-payload|<yaml>``,
:mod:`dvt_model.load`: output stage + arm under gravity, hanging down at the output encoder's
zero in the presets) acts on carrier 3 through the output stage: reflected inertia
``J_arm / reduction^2`` and the gravity torque ``-(Mp/2 + Ma) l g cos(theta_arm) / reduction``
(efficiency by power direction). The arm has no end stops in the simulation. The hidden
effects may add an undeclared ``gravity_arm``, a ``mesh_ripple`` and a ``position_friction``.

A changing plant. ``hidden.changes`` (and ``hidden.damping_scale``) make the plant change while
it runs (:func:`dvt_driver.plant.hidden.scheduled_values`): Coulomb friction and windage per
member, the scale of the transmission's viscous damping ``D`` (applied as the extra generalised
torque ``-(scale - 1) D omega``) and the declared joint load (a step: the model is rebuilt with
the new load, speeds continuous). The schedule is evaluated against the physics time at the
start of each sample period (:meth:`Transmission.due`, :meth:`Transmission.apply_schedule`): at
every change's ``at`` and, during a ramp, every :data:`RAMP_UPDATE_S` (the ramp is a staircase
of 10 ms steps). :meth:`Transmission.add_change` adds a change at runtime (``dvt-plant``
``--change-at``, SIGHUP). Every change the plant starts is appended to
:attr:`Transmission.changes_applied` (plant time ``at_s``, the change) and written into
``truth.yaml``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_driver.errors import PlantError
from dvt_driver.plant.hidden import Change, HiddenEffects, WetBrake, scheduled_values
from dvt_model import laws
from dvt_model.brake import capacity_step, lag_mean_factor
from dvt_model.dynamics import rigid_model
from dvt_model.hybrid import HybridModel, HybridState
from dvt_model.load import JointLoad, load_joint_load
from dvt_model.params import TransmissionParams

__all__ = [
    "RAMP_UPDATE_S",
    "FrictionForces",
    "Transmission",
    "WetBrakeEngagement",
    "friction_velocity_floor",
]

Array = NDArray[np.float64]

RAMP_UPDATE_S = 0.01
"""Update period of a ramping change [s of plant time]."""
_OSC_STEP = 0.35  # rad: largest phase advance of the backlash contact oscillation per sub-step


class Transmission:
    """The transmission the simulated controller drives (see the module docstring).

    Args:
        params: transmission parameter set.
        hidden: hidden effects (``None`` = clean plant).
        max_step: longest physics sub-step [s] (:attr:`step_limit` may be shorter: a stiff
            backlash contact needs it).
        load: declared joint load on carrier 3 (``None``: none).

    Raises:
        PlantError: ``max_step`` is not a number > 0.
    """

    def __init__(self, params: TransmissionParams, hidden: HiddenEffects | None = None, *,
                 max_step: float = 0.001, load: JointLoad | None = None) -> None:
        if not (math.isfinite(max_step) and max_step > 0.0):
            raise PlantError(f"max_step: expected a number > 0 s, got {max_step!r}")
        self.params = params
        self.load = load
        self.initial_load = load
        """The declared load at the start (``truth.yaml``; changes may replace :attr:`load`)."""
        self.hidden = hidden if hidden is not None else HiddenEffects()
        h = self.hidden
        self.brake = h.bands.apply(params.brake) if h.bands is not None else params.brake
        """The bands the plant runs: the parameter set's, or as built (``bands``)."""
        self._engagement = (WetBrakeEngagement(h.wet_brake, self.brake.time_constants)
                            if h.wet_brake else None)
        rigid0 = rigid_model(params)
        self._gravity = h.gravity_arm
        if self._gravity is not None:  # the undeclared arm's inertia, on carrier 3
            c3 = rigid0.kin.vector("carrier3")
            rigid0 = dataclasses.replace(
                rigid0, M=rigid0.M + self._gravity.reflected_inertia * np.outer(c3, c3))
        self._ripple_teeth = (params.stages[h.mesh_ripple.stage - 1].sun
                              if h.mesh_ripple is not None else 0)
        self._bumps: list[tuple[Array, Any, float]] = []  # (form, bump, v_eps) per member
        self.model = HybridModel(rigid0, self.brake, extra_force=self._extra_force,
                                 engagement=self._engagement, load=load,
                                 angle_force=self._angle_force if h.has_angle_effects else None)
        self._m_inv = np.linalg.inv(self.model.rigid.M)
        self.step_limit = max_step
        """Longest physics sub-step [s] the effects allow."""
        if h.backlash is not None:
            j_c3 = 1.0 / float(self._m_inv[1, 1])  # smallest inertia carrier 3 can present
            wn = h.backlash.natural_frequency(j_c3)
            self.step_limit = min(self.step_limit, _OSC_STEP / wn)
        self._friction: FrictionForces | None = None
        self._rigid0 = rigid0
        # the changing plant: the effects in force (base + changes so far), the D correction
        self.base_hidden = self.hidden
        """The effects with the whole schedule (the base of :func:`scheduled_values`)."""
        self._damping_extra: Array | None = None  # -(scale - 1) D, or None
        self._next_change_t = math.inf if not self.hidden.changes else 0.0
        self._started_changes = 0
        self.changes_applied: list[dict[str, Any]] = []
        """Every change the plant started: ``{"at_s": plant time, "change": mapping}``."""
        if self.hidden.damping_scale != 1.0:
            self._damping_extra = -(self.hidden.damping_scale - 1.0) * self.model.rigid.D
        # physical state
        self.state: HybridState = self.model.initial_state()
        self.theta_sun = 0.0
        """Sun-shaft angle [rad] from the plant's start."""
        self.bl_twist = 0.0
        """Carrier 3 minus output shaft [rad] (backlash only)."""
        self.w_load = 0.0
        """Output-shaft speed [rad/s] (backlash only)."""
        self.i_motor = 0.0
        """Actual motor current [A] (the power stage's output)."""
        self.i_brake = np.zeros(3)
        """Applied brake coil currents [A] (the controller holds them)."""
        self.t_phys = 0.0
        """Simulated time since the start [s]."""
        self.h = 0.0
        """The physics sub-step [s] (:meth:`configure`)."""
        self._memo_key: tuple[float, float] | None = None
        self._memo_force = np.zeros(2)

    # ------------------------------------------------------------------ configuration
    def configure(self, h: float) -> None:
        """Set the physics sub-step ``h`` [s] (the friction laws' stability floors depend on
        it)."""
        self.h = h
        self._rebuild_friction()
        self._bumps = []
        for member, bump in self.hidden.position_friction.items():
            a = self.model.rigid.kin.vector(member)
            floor = friction_velocity_floor(bump.amplitude, float(a @ self._m_inv @ a), h)
            self._bumps.append((a, bump, max(self.hidden.friction_velocity, floor)))
        self._memo_key = None

    def _rebuild_friction(self) -> None:
        self._friction = None
        if self.hidden.friction_members():
            rigid = self.model.rigid
            forms = {m: rigid.kin.vector(m) for m in self.hidden.friction_members()}
            mob = {m: float(a @ self._m_inv @ a) for m, a in forms.items()}
            self._friction = FrictionForces(self.hidden, forms, mob, self.h)

    # ------------------------------------------------------------------ a changing plant
    def add_change(self, change: Change) -> None:
        """Add ``change`` to the schedule (its ``at`` in plant time; at or before
        :attr:`t_phys`: applied at the next :meth:`apply_schedule`)."""
        base = self.base_hidden
        self.base_hidden = dataclasses.replace(base, changes=(*base.changes, change))
        self.hidden = dataclasses.replace(self.hidden, changes=self.base_hidden.changes)
        self._next_change_t = min(self._next_change_t, change.at)

    def due(self) -> bool:
        """Whether the schedule asks for an update now (a change starts or a ramp moves)."""
        return self.t_phys >= self._next_change_t - 1e-6

    def apply_schedule(self) -> None:
        """Bring the changeable effects to the schedule's values at the present plant time."""
        t = self.t_phys
        base = self.base_hidden
        v = scheduled_values(base, t + 1e-6)  # 1 us: the physics time's rounding
        ordered = sorted(base.changes, key=lambda c: c.at)
        for ch in ordered[self._started_changes:v.started]:
            self.changes_applied.append({"at_s": round(t, 6), "change": ch.to_mapping()})
        self._started_changes = v.started
        if v.load is not None:
            load = None if v.load == "none" else load_joint_load(v.load)
            if (load is None) != (self.load is None) or (
                    load is not None and self.load is not None and load != self.load):
                self.load = load
                self.model = HybridModel(self._rigid0, self.brake,
                                         extra_force=self._extra_force,
                                         engagement=self._engagement, load=load,
                                         angle_force=self.model.angle_force)
        self.hidden = dataclasses.replace(self.hidden, coulomb=v.coulomb, windage=v.windage,
                                          damping_scale=v.damping_scale)
        self._damping_extra = (None if v.damping_scale == 1.0 else
                               -(v.damping_scale - 1.0) * self.model.rigid.D)
        self._rebuild_friction()
        self._memo_key = None
        upcoming = [c.at for c in ordered[v.started:]]
        nxt = min(upcoming) if upcoming else math.inf
        self._next_change_t = min(nxt, t + RAMP_UPDATE_S) if v.ramping else nxt

    # ------------------------------------------------------------------ forces
    def output_speed(self) -> float:
        """True output-shaft speed [rad/s] (carrier 3 unless backlash)."""
        return self.w_load if self.hidden.backlash is not None else float(self.state.omega[1])

    def output_angle(self) -> float:
        """True output-shaft angle [rad] (carrier 3 unless backlash)."""
        theta = float(self.state.theta[1])
        return theta - self.bl_twist if self.hidden.backlash is not None else theta

    def _angle_force(self, theta: Array, omega: Array, t: float) -> Array:
        """Position-dependent hidden generalised torque (2,) [N m]: the undeclared gravity arm,
        the mesh ripple (its mean over the physics step) and the friction bumps."""
        f = np.zeros(2)
        if self._gravity is not None:
            f = f + self._gravity.generalised_force(theta, omega)
        ripple = self.hidden.mesh_ripple
        if ripple is not None:
            f[0] += ripple.mean_torque(self._ripple_teeth, float(theta[0]), float(omega[0]),
                                       self.h)
        for a, bump, eps in self._bumps:
            v = float(a @ omega)
            f = f - a * (bump.level(float(a @ theta)) * float(laws.sign_eps(v, eps)))
        return f

    def _spline_torque(self, w_c3: float) -> float:
        bl = self.hidden.backlash
        if bl is None:
            return 0.0
        half = 0.5 * bl.gap
        d = self.bl_twist
        if d > half:
            return max(0.0, bl.stiffness * (d - half) + bl.damping * (w_c3 - self.w_load))
        if d < -half:
            return min(0.0, bl.stiffness * (d + half) + bl.damping * (w_c3 - self.w_load))
        return 0.0

    def _extra_force(self, omega: Array, t: float) -> Array:
        """Hidden generalised torque (2,) [N m]; memoised per speed within a sub-step (the
        hybrid model asks several times at the same speeds)."""
        key = (float(omega[0]), float(omega[1]))
        if key == self._memo_key:
            return self._memo_force
        f = self._friction.generalised(omega) if self._friction is not None else np.zeros(2)
        if self._damping_extra is not None:
            f = f + self._damping_extra @ omega
        if self.hidden.backlash is not None:
            f = f.copy()
            f[1] -= self._spline_torque(key[1])
        self._memo_key, self._memo_force = key, f
        return f

    # ------------------------------------------------------------------ stepping
    def advance(self, i_ref: float, current_time_constant: float) -> None:
        """Advance one sub-step :attr:`h` with the motor current following ``i_ref`` [A]
        (first-order lag ``current_time_constant`` [s], 0: ideal) and the held brake
        currents :attr:`i_brake`."""
        h = self.h
        tau = current_time_constant
        i0 = self.i_motor
        if tau > 0.0:
            e = math.exp(-h / tau)
            i1 = i_ref + (i0 - i_ref) * e
            i_mean = i_ref + (i0 - i_ref) * lag_mean_factor(h, tau)
        else:
            i1 = i_mean = i_ref
        w0 = self.state.omega
        bl = self.hidden.backlash
        t_spline = self._spline_torque(float(w0[1])) if bl is not None else 0.0
        self._memo_key = None  # the spline state changed since the last sub-step
        self.state = self.model.step(self.state, h, i_mean, self.i_brake)
        w1 = self.state.omega
        self.i_motor = i1
        self.theta_sun = float(self.state.theta[0])  # exact integral of the step's speed
        if bl is not None:  # symplectic Euler: speeds first, then the twist with new speeds
            self.w_load += h * (t_spline - bl.load_damping * self.w_load) / bl.load_inertia
            self.bl_twist += h * (float(w1[1]) - self.w_load)
        self.t_phys += h


# ---------------------------------------------------------------------------------------------
# the hidden effects' forces


def friction_velocity_floor(force: float, mobility: float, dt: float) -> float:
    """Smallest stable regularisation speed [rad/s] of a friction law held over a step.

    A friction torque ``F tanh(v / v_eps)`` on a member with mobility ``a^T M^-1 a``
    [1/(kg m^2)] acts like a damper ``F / v_eps``; held over a step ``dt`` [s] it must not
    reverse the member's speed: ``dt * mobility * F / v_eps <= 1/2``.
    """
    return 2.0 * dt * mobility * force


class FrictionForces:
    """Generalised friction + windage torque of a set of members, vectorised.

    Args:
        effects: the hidden effects (coulomb, stribeck, windage and the table's ``laws`` are
            used).
        forms: member -> linear form (2,) in ``(omega_sun, omega_carrier3)``.
        mobility: member -> ``a^T M^-1 a`` [1/(kg m^2)] (for the stability floor).
        dt: the plant's physics step [s].
    """

    def __init__(self, effects: HiddenEffects, forms: Mapping[str, Array],
                 mobility: Mapping[str, float], dt: float) -> None:
        members = effects.friction_members()
        self.members = members
        n = len(members)
        self.A = np.array([forms[m] for m in members], dtype=float).reshape(n, 2)
        # per-member parameters as arrays: the dvt_model.laws functions broadcast over members
        # (typed Any: the laws are annotated for scalars)
        self.fc: Any = np.array([effects.coulomb.get(m, 0.0) for m in members])
        st = [effects.stribeck.get(m) for m in members]
        self.s_fc: Any = np.array([s.Fc if s else 0.0 for s in st])
        self.s_dF: Any = np.array([(s.Fs - s.Fc) if s else 0.0 for s in st])
        self.s_vs: Any = np.array([s.vs if s else 1.0 for s in st])
        self.s_delta: Any = np.array([s.delta if s else 2.0 for s in st])
        self.c_w: Any = np.array([effects.windage.get(m, 0.0) for m in members])
        peak = self.fc + self.s_fc + self.s_dF
        floor = np.array([friction_velocity_floor(float(peak[i]), mobility[m], dt)
                          for i, m in enumerate(members)])
        self.v_eps = np.maximum(effects.friction_velocity, floor)
        # the laws take one scalar eps; each member has its own, so they run on the normalised
        # speed u = v / v_eps with eps = 1 (tanh(u) = tanh(v / v_eps), |u / (vs / v_eps)| =
        # |v / vs|)
        self._vs_n: Any = self.s_vs / self.v_eps
        self._level: Any = self.fc + self.s_fc  # Coulomb level of both laws
        self._has_stribeck = bool(np.any(self.s_fc + self.s_dF > 0.0))
        self._has_windage = bool(np.any(self.c_w > 0.0))
        # the table's laws named in ``laws`` (HiddenEffects.laws), with the member's smoothing
        self._laws = [(i, laws.LAWS[name], {**params, "eps": float(self.v_eps[i])})
                      for i, m in enumerate(members) for name, params in effects.laws.get(m, ())]

    def __bool__(self) -> bool:
        return bool(self.members)

    def member_torques(self, omega: Array) -> Array:
        """Friction + windage torque on each member [N m], shape (n_members,)."""
        v = self.A @ omega
        u = v / self.v_eps
        F = laws.coulomb(u, self._level, 0.0, 1.0)
        if self._has_stribeck:
            F = F + laws.stribeck(u, self.s_dF, self._vs_n, 1.0, self.s_delta)
        if self._has_windage:
            F = F + laws.windage(v, self.c_w)
        if self._laws:
            F = np.array(F, dtype=float)
            for i, law, fields in self._laws:
                F[i] += law(float(v[i]), fields)
        return np.asarray(F)

    def generalised(self, omega: Array) -> Array:
        """Generalised torque ``-sum a_i F_i(v_i)`` [N m], shape (2,)."""
        return np.asarray(-(self.A.T @ self.member_torques(omega)))


class WetBrakeEngagement:
    """Stateful engagement law for :class:`dvt_model.hybrid.HybridModel` (``engagement=``).

    Bands listed in ``shapes`` follow :class:`WetBrake`; the others keep the model's
    first-order lag with ``time_constant``. The object keeps each band's applied time and must
    be called exactly once per model step (the hybrid model does).

    Args:
        shapes: band (1..3) -> :class:`WetBrake`.
        time_constant: first-order time constant of the other bands [s] (one, or one per
            band, shape (3,)).
        on_threshold: static torque above which a band counts as applied [N m].
    """

    def __init__(self, shapes: Mapping[int, WetBrake], time_constant: float | Array,
                 on_threshold: float = 1e-6) -> None:
        self.shapes = dict(shapes)
        self.time_constant = time_constant
        self.on_threshold = on_threshold
        self.applied_time = np.zeros(3)

    def reset(self) -> None:
        """Forget the engagement history (every film re-formed)."""
        self.applied_time[:] = 0.0

    def __call__(self, capacity: Array, target: Array, dt: float,
                 ring_speeds: Array) -> tuple[Array, Array]:
        """``(capacity (3,), static target (3,), dt [s], ring speeds (3,)) -> (end, mean)``."""
        end, mean = capacity_step(capacity, target, dt, self.time_constant)
        end = end.copy()
        mean = mean.copy()
        for k, shape in self.shapes.items():
            i = k - 1
            cap0 = float(capacity[i])
            tgt = float(target[i])
            e = math.exp(-dt / shape.release_time)
            if tgt <= self.on_threshold:
                self.applied_time[i] = 0.0
                end[i] = cap0 * e
                mean[i] = cap0 * lag_mean_factor(dt, shape.release_time)
                continue
            t0 = float(self.applied_time[i])
            t1 = t0 + dt
            self.applied_time[i] = t1
            w = float(ring_speeds[i])
            a0 = shape.torque(t0, tgt, w)
            a1 = shape.torque(t1, tgt, w)
            # a band never loses torque faster than it releases (target lowered while applied)
            d0 = max(a0, cap0)
            d1 = max(a1, tgt + (cap0 - tgt) * e) if cap0 > tgt else a1
            end[i] = d1
            mean[i] = 0.5 * (d0 + d1)
        return end, mean
