"""Hybrid simulation of the DVT: 2-DOF while no band holds, 1-DOF in a locked gear.

State: ``omega = (omega_sun, omega_carrier3)`` [rad/s], the angles ``theta = (theta_sun,
theta_carrier3)`` [rad] (every other member's angle is the same linear form of them as its
speed, :mod:`dvt_model.kinematics`, up to a constant), band capacities ``T_cap`` (3,) [N m] and
which rings are locked. Inputs per step (zero-order hold): drive-motor current [A] and the
three brake-motor currents [A].

Each step of length ``dt``:

1. the band capacities advance exactly (first-order lag, :func:`dvt_model.brake.capacity_step`);
2. a locked ring is released when the holding torque it needs exceeds
   ``static_factor * T_cap`` (it then slips in the direction the load drives it);
3. the linear dynamics restricted to the unlocked subspace, ``omega = N z``,
   ``(N^T M N) z' = -N^T D N z + N^T f`` with the generalised force ``f`` held over the step,
   are advanced by the exact zero-order-hold discretisation (``scipy.linalg.expm``, cached per
   lock set and step length);
4. if a slipping ring with an engaged band crosses zero speed within the step, the step is split
   at the crossing (its linear interpolation; with ``crossing_grid`` on a grid of that
   fraction of the step, :func:`crossing_fraction`, the model node's choice); the ring locks
   if the band can hold it (velocities
   projected onto the constraint conserving momentum, ``omega+ = N (N^T M N)^-1 N^T M
   omega-``), else the sliding torque reverses.

A ring slipping with the band on gets ``-T_cap sign(omega_ring)`` on its generalised speed.
An optional ``extra_force(omega, t) -> (2,)`` adds generalised torques (the plant's hidden
effects), evaluated at the step start and held over the step; so do the angle-dependent ones:
an optional joint ``load`` (:class:`dvt_model.load.JointLoad`: its reflected inertia is added
to ``M`` at carrier 3, its gravity torque depends on the carrier-3 angle), an optional
``angle_force(theta, omega, t) -> (2,)`` and an optional ``angle_input_force(theta, omega, t,
u, dt) -> (2,)`` that also gets the inputs ``u = (i_motor, i_brake (3,))`` [A] held over the
step and the length ``dt`` [s] of the (sub-)step it is held over (0 for an instantaneous value:
the release, lock and holding-torque checks), so it can return its mean over the step (the
model node's identified effect terms, :meth:`dvt_model.terms.Terms.angle_force`).

Angles: the step integrates ``theta`` exactly along the same zero-order-hold solution as the
speeds (the integral of ``N z`` from the augmented matrix exponential), so ``theta`` is
consistent with ``omega`` to round-off; a lock (a velocity jump) does not move the angles; a
fully locked transmission keeps them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm, null_space

from dvt_model.brake import BandLaw
from dvt_model.dynamics import RigidModel, rigid_model
from dvt_model.errors import SimulationError
from dvt_model.load import JointLoad
from dvt_model.params import BrakeParams, TransmissionParams

Array = NDArray[np.float64]
ExtraForce = Callable[[Array, float], Array]
AngleForce = Callable[[Array, Array, float], Array]
"""``(theta (2,) [rad], omega (2,) [rad/s], t [s]) -> generalised torque (2,) [N m]``."""
AngleInputForce = Callable[[Array, Array, float, Array, float], Array]
"""``(theta (2,) [rad], omega (2,) [rad/s], t [s], u (4,) [A], dt [s]) -> generalised torque
(2,) [N m]``: ``u`` the drive-motor and brake currents held over the step, ``dt`` the step the
torque is held over (0: the instantaneous value)."""
Engagement = Callable[[Array, Array, float, Array], tuple[Array, Array]]
"""``(capacity (3,), static target (3,), dt, ring speeds (3,)) -> (capacity at end, mean)``."""
LockSet = tuple[bool, bool, bool]

_ENGAGED = 1e-9  # N m: a band with less capacity than this is released
_ZERO_SPEED = 1e-9  # rad/s
CROSSING_GRID = 64
"""The model node's ``crossing_grid`` (:func:`dvt_model.config.build_predictor`): a zero
crossing within a (sub-)step splits it at a multiple of 1/64 of its length
(:func:`crossing_fraction`): the split points are then a few lengths whose discretisations are
cached like the step's own (at most 7.8 us off at 1 kHz, where the crossing itself is the
linear interpolation of the ring speed). Split at the exact interpolated instant (the default,
``crossing_grid`` 0: the plant's), every split needs two matrix exponentials of its own; in
neutral, with the brake currents' quantisation (+-1 count, 0.0078 A) engaging the bands a
little, 3.5 % of the 1-kHz samples of a live ``watch`` run crossed a ring's zero and cost the
node's predictor 0.3-0.7 ms instead of 0.03 ms (its p99 0.37 ms, 0.47 ms with two Coulomb
terms; with the grid 0.21 / 0.28 ms); a crossing found again at the very end of a split (the
interpolation is linear) split it again, down to the recursion's limit, which the grid ends."""


def crossing_fraction(frac: float, grid: int = CROSSING_GRID) -> float:
    """Where a (sub-)step is split for a zero crossing at the fraction ``frac`` of it (the
    linear interpolation, ``0 <= frac <= 1``) on a grid of ``1 / grid``: the nearest multiple,
    at least one (a crossing at the end is the end: no further split)."""
    return max(1, round(frac * grid)) / grid


@dataclass(frozen=True)
class HybridState:
    """Instantaneous state of the hybrid model.

    Attributes:
        t: time [s].
        omega: (omega_sun, omega_carrier3) [rad/s], shape (2,).
        capacity: each band's available torque [N m], shape (3,).
        locked: which rings are held by their band.
        holding: torque each locked band applies to hold its ring [N m], shape (3,)
            (0 for unlocked bands).
        theta: (theta_sun, theta_carrier3) [rad], shape (2,).
    """

    t: float
    omega: Array
    capacity: Array
    locked: LockSet
    holding: Array
    theta: Array = field(default_factory=lambda: np.zeros(2))

    @property
    def gear(self) -> int:
        """1-3 for one locked band, 0 for none (neutral or slipping), -1 for a tie-up."""
        n = sum(self.locked)
        if n == 0:
            return 0
        if n > 1:
            return -1
        return self.locked.index(True) + 1


@dataclass(frozen=True)
class SimulationResult:
    """Sampled simulation output.

    Attributes:
        t: sample times [s], shape (N,).
        omega: speeds at each sample [rad/s], shape (N, 2).
        capacity: band capacities [N m], shape (N, 3).
        locked: lock state, shape (N, 3), bool.
        gear: gear state per sample (see :attr:`HybridState.gear`), shape (N,).
        theta: angles (theta_sun, theta_carrier3) at each sample [rad], shape (N, 2).
    """

    t: Array
    omega: Array
    capacity: Array
    locked: NDArray[np.bool_]
    gear: NDArray[np.int64]
    theta: Array = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True)
class _Mode:
    N: Array  # (2, n) orthonormal basis of admissible velocities
    Mr_inv: Array  # (n, n)
    Phi: Array  # (n, n)
    Gamma: Array  # (n, 2): generalised force held over dt -> delta z
    Psi: Array  # (n, n): z at the step start -> integral of z over the step
    Lam: Array  # (n, 2): generalised force held over dt -> integral of z over the step
    identity: bool = False  # N is the 2x2 identity (no band holds)


class HybridModel:
    """The hybrid DVT model; stateless apart from caches (discretisations, band decays).

    Args:
        rigid: M, D, Q of the transmission.
        brake: band-brake data.
        extra_force: optional generalised torque ``f(omega (2,), t) -> (2,)`` [N m].
        engagement: optional replacement of the first-order band engagement (same contract
            as :func:`dvt_model.brake.capacity_step` plus the ring speeds), e.g. a wet-to-dry
            band in the simulated plant.
        load: optional joint load on carrier 3 (:class:`~dvt_model.load.JointLoad`): its
            reflected inertia is added to ``rigid.M`` (``self.rigid`` is the loaded model),
            its gravity torque is a generalised force depending on the carrier-3 angle.
        angle_force: optional generalised torque ``f(theta (2,), omega (2,), t) -> (2,)``
            [N m] depending on the angles (e.g. the plant's position-dependent hidden effects).
        angle_input_force: optional generalised torque ``f(theta, omega, t, u (4,), dt)`` [N m]
            depending on the angles and the inputs (:data:`AngleInputForce`).
    """

    def __init__(self, rigid: RigidModel, brake: BrakeParams,
                 extra_force: ExtraForce | None = None,
                 engagement: Engagement | None = None, *, load: JointLoad | None = None,
                 angle_force: AngleForce | None = None,
                 angle_input_force: AngleInputForce | None = None,
                 crossing_grid: int = 0) -> None:
        if isinstance(crossing_grid, bool) or not isinstance(crossing_grid, int) \
                or crossing_grid < 0:
            raise SimulationError(f"crossing_grid: expected an integer >= 0, got "
                                  f"{crossing_grid!r}")
        self.crossing_grid = crossing_grid
        if load is not None:
            c3 = rigid.kin.vector("carrier3")
            rigid = dataclasses.replace(
                rigid, M=rigid.M + load.reflected_inertia * np.outer(c3, c3))
        self.rigid = rigid
        self.brake = brake
        self.extra_force = extra_force
        self.engagement = engagement
        self.load = load
        self.angle_force = angle_force
        self.angle_input_force = angle_input_force
        self._ring = np.asarray(rigid.Q_brake, dtype=float)  # (2, 3) ring speed forms
        # the step's constants as plain floats (``brake`` is frozen; its array properties
        # would be rebuilt on every call)
        self._ring_cols = [(float(a), float(b)) for a, b in self._ring.T]
        self._q_motor = [float(q) for q in rigid.Q_motor]
        self._motor_constant = float(rigid.motor_constant)
        self._bands = BandLaw(brake)
        self._static_factor = float(brake.static_factor)
        self._modes: dict[tuple[LockSet, float], _Mode] = {}  # by rounded dt
        self._modes_raw: dict[tuple[LockSet, float], _Mode] = {}  # by raw dt
        self._bases: dict[LockSet, tuple[Array, Array, Array]] = {}
        self._holding_maps: dict[LockSet, Array] = {}

    @classmethod
    def from_params(cls, params: TransmissionParams, extra_force: ExtraForce | None = None,
                    engagement: Engagement | None = None, *, load: JointLoad | None = None,
                    angle_force: AngleForce | None = None,
                    angle_input_force: AngleInputForce | None = None,
                    crossing_grid: int = 0) -> HybridModel:
        """Build from a parameter set (optionally with a joint load and angle forces)."""
        return cls(rigid_model(params), params.brake, extra_force, engagement, load=load,
                   angle_force=angle_force, angle_input_force=angle_input_force,
                   crossing_grid=crossing_grid)

    # ------------------------------------------------------------------ helpers
    def ring_speeds(self, omega: ArrayLike) -> Array:
        """Ring 1-3 speeds [rad/s] for ``omega`` of shape (2,) or (N, 2) -> (3,) or (N, 3)."""
        return np.asarray(np.asarray(omega, dtype=float) @ self._ring)

    def _basis(self, locked: LockSet) -> tuple[Array, Array, Array]:
        cached = self._bases.get(locked)
        if cached is not None:
            return cached
        idx = [k for k in range(3) if locked[k]]
        if idx:
            C = self._ring[:, idx]
            N = null_space(C.T)
        else:
            N = np.eye(2)
        M, D = self.rigid.M, self.rigid.D
        Mr = N.T @ M @ N
        Mr_inv = np.linalg.inv(Mr) if N.shape[1] else np.zeros((0, 0))
        Ar = -Mr_inv @ (N.T @ D @ N) if N.shape[1] else np.zeros((0, 0))
        out = (N, Mr_inv, Ar)
        self._bases[locked] = out
        return out

    def _mode(self, locked: LockSet, dt: float) -> _Mode:
        """The discretisation for ``locked`` over ``dt``, cached per lock set and ``dt``
        rounded to 1e-12 s; found again by the raw ``dt`` first (``round`` is slow, and the
        node's float-second stamps give a few distinct raw step lengths)."""
        mode = self._modes_raw.get((locked, dt))
        if mode is not None:
            return mode
        key = (locked, round(dt, 12))
        mode = self._modes.get(key)
        if mode is None:
            mode = self._discretise(locked, dt)
            if len(self._modes) < 4096:
                self._modes[key] = mode
        if len(self._modes_raw) < 8192:
            self._modes_raw[(locked, dt)] = mode
        return mode

    def _discretise(self, locked: LockSet, dt: float) -> _Mode:
        N, Mr_inv, Ar = self._basis(locked)
        n = N.shape[1]
        if n == 0:
            return _Mode(N, Mr_inv, np.zeros((0, 0)), np.zeros((0, 2)), np.zeros((0, 0)),
                         np.zeros((0, 2)))
        Br = Mr_inv @ N.T  # (n, 2)
        # augmented state (z, f, s) with f' = 0 and s' = z: s(dt) is the integral of z
        big = np.zeros((2 * n + 2, 2 * n + 2))
        big[:n, :n] = Ar
        big[:n, n:n + 2] = Br
        big[n + 2:, :n] = np.eye(n)
        e = expm(big * dt)
        return _Mode(N, Mr_inv, e[:n, :n], e[:n, n:n + 2], e[n + 2:, :n], e[n + 2:, n:n + 2],
                     identity=not any(locked))

    def _base_force(self, omega: Array, t: float, i_motor: float, cap: list[float],
                    signs: list[float], locked: LockSet, theta: Array) -> tuple[float, float]:
        """Generalised force at the step start but the ``angle_input_force``: drive motor,
        sliding bands 1-3, ``extra_force``, load, ``angle_force``, summed in this order in
        plain floats."""
        m = self._motor_constant * i_motor
        f0 = self._q_motor[0] * m
        f1 = self._q_motor[1] * m
        for k in range(3):
            if not locked[k] and signs[k] != 0.0 and cap[k] > _ENGAGED:
                s = cap[k] * signs[k]
                c0, c1 = self._ring_cols[k]
                f0 = f0 - c0 * s
                f1 = f1 - c1 * s
        if self.extra_force is not None:
            e = self.extra_force(omega, t)
            f0 = f0 + float(e[0])
            f1 = f1 + float(e[1])
        if self.load is not None:  # its generalised force is (0, carrier3_torque)
            f0 = f0 + 0.0
            f1 = f1 + self.load.carrier3_torque(float(theta[1]), float(omega[1]))
        if self.angle_force is not None:
            e = self.angle_force(theta, omega, t)
            f0 = f0 + float(e[0])
            f1 = f1 + float(e[1])
        return f0, f1

    def _forces(self, omega: Array, t: float, i_motor: float, u: Array | None,
                cap: list[float], signs: list[float], locked: LockSet, theta: Array,
                dt: float = 0.0, base: tuple[float, float] | None = None) -> Array:
        """Generalised force (2,) at the step start: :meth:`_base_force` (``base`` if already
        evaluated at these arguments) plus the ``angle_input_force`` at the inputs ``u`` =
        (i_motor, i_brake (3,)) [A] (built by :meth:`step` when that force is set) held over
        ``dt`` (0: instantaneous)."""
        f0, f1 = base if base is not None else self._base_force(omega, t, i_motor, cap, signs,
                                                                 locked, theta)
        if self.angle_input_force is not None:
            e = self.angle_input_force(theta, omega, t, u, dt)  # type: ignore[arg-type]
            f0 = f0 + float(e[0])
            f1 = f1 + float(e[1])
        return np.array((f0, f1))

    def angle_forces(self, theta: ArrayLike, omega: ArrayLike, t: float = 0.0,
                     u: ArrayLike | None = None, dt: float = 0.0) -> Array:
        """The angle-dependent generalised torque (load + ``angle_force`` +
        ``angle_input_force`` at inputs ``u`` (4,) [A], default 0, held over ``dt`` [s])
        (2,) [N m]."""
        th = np.asarray(theta, dtype=float).reshape(2)
        w = np.asarray(omega, dtype=float).reshape(2)
        f = np.zeros(2)
        if self.load is not None:
            f = f + self.load.generalised_force(th, w)
        if self.angle_force is not None:
            f = f + np.asarray(self.angle_force(th, w, t), dtype=float)
        if self.angle_input_force is not None:
            uu = np.zeros(4) if u is None else np.asarray(u, dtype=float).reshape(4)
            f = f + np.asarray(self.angle_input_force(th, w, t, uu, dt), dtype=float)
        return f

    def holding_torques(self, omega: Array, f: Array, locked: LockSet) -> Array:
        """Torque each locked band must apply to keep its ring still [N m], shape (3,).

        Args:
            omega: current speeds (admissible for ``locked``), shape (2,).
            f: generalised force of everything but the locked bands, shape (2,).
        """
        if not any(locked):
            return np.zeros(3)
        L = self._holding_maps.get(locked)
        if L is None:
            idx = [k for k in range(3) if locked[k]]
            N, Mr_inv, _ = self._basis(locked)
            proj = N @ Mr_inv @ N.T if N.shape[1] else np.zeros((2, 2))
            # lambda = pinv(C) (M N Mr^-1 N^T - I) rhs,  rhs = -D omega + f
            L = np.zeros((3, 2))
            L[idx] = np.linalg.pinv(self._ring[:, idx]) @ (self.rigid.M @ proj - np.eye(2))
            self._holding_maps[locked] = L
        return np.asarray(L @ (f - self.rigid.D @ omega))

    def _project(self, omega: Array, locked: LockSet) -> Array:
        N, Mr_inv, _ = self._basis(locked)
        if N.shape[1] == 0:
            return np.zeros(2)
        M = self.rigid.M
        return np.asarray(N @ (Mr_inv @ (N.T @ (M @ omega))))

    # ------------------------------------------------------------------ public API
    def initial_state(self, omega: ArrayLike = (0.0, 0.0), t: float = 0.0,
                      locked: LockSet = (False, False, False),
                      capacity: ArrayLike = (0.0, 0.0, 0.0),
                      theta: ArrayLike = (0.0, 0.0)) -> HybridState:
        """A state at rest or at given speeds (projected onto ``locked``'s constraint) and
        angles ``theta`` (2,) [rad]."""
        w = np.asarray(omega, dtype=float).reshape(2)
        if not np.all(np.isfinite(w)):
            raise SimulationError(f"omega: expected finite speeds, got {w.tolist()}")
        th = np.asarray(theta, dtype=float).reshape(2)
        if not np.all(np.isfinite(th)):
            raise SimulationError(f"theta: expected finite angles, got {th.tolist()}")
        cap = np.asarray(capacity, dtype=float).reshape(3)
        if any(locked):
            w = self._project(w, locked)
        return HybridState(t=float(t), omega=w, capacity=cap, locked=locked, holding=np.zeros(3),
                           theta=th.copy())

    def step(self, state: HybridState, dt: float, i_motor: float,
             i_brake: ArrayLike) -> HybridState:
        """Advance ``state`` by ``dt`` [s] with currents held (ZOH): motor [A], brakes (3,) [A].

        The three-vectors (band targets, capacities, slip signs) and the forces are plain
        floats here, summed in the order of the plain numpy formulation, and the matrix products
        stay numpy's: the result is that formulation's bit for bit (``test_hybrid_fast.py``).
        """
        if not dt > 0.0:
            raise SimulationError(f"dt: expected > 0 s, got {dt!r}")
        ib = np.asarray(i_brake, dtype=float).reshape(3)
        i_motor = float(i_motor)
        u: Array | None = None
        if self.angle_input_force is not None:
            u = np.empty(4)
            u[0] = i_motor
            u[1:] = ib
        target = self._bands.targets(ib.tolist())
        omega = state.omega
        theta = state.theta
        locked = state.locked
        rings_arr = omega @ self._ring
        rings = rings_arr.tolist()
        cap_end_arr: Array | None = None
        if self.engagement is None:
            cap_end, cap_mean = self._bands.step(state.capacity.tolist(), target, dt)
        else:
            end, mean = self.engagement(state.capacity, np.array(target), dt, rings_arr)
            cap_end_arr = end
            cap_end, cap_mean = np.asarray(end).tolist(), np.asarray(mean).tolist()
        signs = [_sign(r) for r in rings]
        # the step-start force but the angle_input_force, while omega, locks and signs stand
        base: tuple[float, float] | None = None
        # releases: a locked band that cannot hold the ring any more lets it slip
        for _ in range(3):
            if not any(locked):
                break
            base = self._base_force(omega, state.t, i_motor, cap_mean, signs, locked, theta)
            f = self._forces(omega, state.t, i_motor, u, cap_mean, signs, locked, theta,
                             base=base)
            lam = self.holding_torques(omega, f, locked).tolist()
            excess = [abs(lam[k]) / max(self._static_factor * cap_mean[k], _ENGAGED)
                      if locked[k] else 0.0 for k in range(3)]
            k = _argmax(excess)
            if excess[k] <= 1.0:
                break
            locked = _with(locked, k, False)
            signs[k] = -_sign(lam[k])
            base = None
        # engagement at rest: a still ring with an engaged band locks if it can be held
        for k in range(3):
            if (not locked[k] and cap_mean[k] > _ENGAGED and abs(rings[k]) < _ZERO_SPEED
                    and self._can_lock(omega, state.t, i_motor, u, cap_mean, signs, locked,
                                       k, theta)):
                locked = _with(locked, k, True)
                omega = self._project(omega, locked)
                base = None
        omega, locked, signs, dtheta = self._advance(omega, state.t, dt, i_motor, u, cap_mean,
                                                     signs, locked, theta, depth=0, base=base)
        theta = theta + dtheta
        if any(locked):
            f = self._forces(omega, state.t + dt, i_motor, u, cap_end, signs, locked, theta)
            holding = self.holding_torques(omega, f, locked)
        else:  # nothing to hold: the force at the end is not needed
            holding = np.zeros(3)
        return HybridState(t=state.t + dt, omega=omega,
                           capacity=cap_end_arr if cap_end_arr is not None else np.array(cap_end),
                           locked=locked, holding=holding, theta=theta)

    def _can_lock(self, omega: Array, t: float, i_motor: float, u: Array | None,
                  cap: list[float], signs: list[float], locked: LockSet, k: int,
                  theta: Array) -> bool:
        trial = _with(locked, k, True)
        w = self._project(omega, trial)
        f = self._forces(w, t, i_motor, u, cap, signs, trial, theta)
        lam = self.holding_torques(w, f, trial)
        return bool(abs(float(lam[k])) <= self._static_factor * cap[k])

    def _advance(self, omega: Array, t: float, dt: float, i_motor: float, u: Array | None,
                 cap: list[float], signs: list[float], locked: LockSet, theta: Array,
                 depth: int, base: tuple[float, float] | None = None
                 ) -> tuple[Array, LockSet, list[float], Array]:
        """Advance over ``dt``; returns speeds, lock set, slip signs and the angle change
        (``base``: :meth:`_base_force` at these arguments if already evaluated)."""
        if depth == 0 or self.crossing_grid:  # a split on the grid has a cached length, too
            mode = self._mode(locked, dt)
        else:
            mode = self._discretise(locked, dt)
        if mode.N.shape[1] == 0:  # all held: nothing moves (and no force is needed)
            return np.zeros(2), locked, signs, np.zeros(2)
        f = self._forces(omega, t, i_motor, u, cap, signs, locked, theta, dt, base)
        N = mode.N
        z = omega if mode.identity and _identity_keeps(omega) else N.T @ omega
        v = mode.Phi @ z + mode.Gamma @ f
        omega_end = v if mode.identity and _identity_keeps(v) else N @ v
        v = mode.Psi @ z + mode.Lam @ f
        dtheta = v if mode.identity and _identity_keeps(v) else N @ v
        if depth >= 4:
            return omega_end, locked, signs, dtheta
        # rings that can reach zero speed within the step: slipping with the band engaged
        slipping = [k for k in range(3)
                    if not (locked[k] or cap[k] <= _ENGAGED or signs[k] == 0.0)]
        if not slipping:
            return omega_end, locked, signs, dtheta
        r0 = (omega @ self._ring).tolist()
        r1 = (omega_end @ self._ring).tolist()
        first, frac = -1, 2.0
        for k in slipping:
            if r0[k] * signs[k] > 0.0 and r1[k] * signs[k] <= 0.0:
                th = r0[k] / (r0[k] - r1[k])
                if th < frac:
                    first, frac = k, th
        if first < 0:
            return omega_end, locked, signs, dtheta
        t1 = (crossing_fraction(frac, self.crossing_grid) * dt if self.crossing_grid
              else max(frac * dt, 1e-9))
        w_mid, locked, signs, d1 = self._advance(omega, t, t1, i_motor, u, cap, signs,
                                                 locked, theta, depth + 1)
        th_mid = theta + d1
        k = first
        if self._can_lock(w_mid, t + t1, i_motor, u, cap, signs, locked, k, th_mid):
            locked = _with(locked, k, True)
            w_mid = self._project(w_mid, locked)
        else:
            signs = signs.copy()
            signs[k] = -signs[k]
        rest = dt - t1
        if rest <= 1e-12:
            return w_mid, locked, signs, d1
        w_end, locked, signs, d2 = self._advance(w_mid, t + t1, rest, i_motor, u, cap, signs,
                                                 locked, th_mid, depth + 1)
        return w_end, locked, signs, d1 + d2

    def simulate(self, t: ArrayLike, i_motor: ArrayLike, i_brake: ArrayLike,
                 omega0: ArrayLike = (0.0, 0.0), state0: HybridState | None = None
                 ) -> SimulationResult:
        """Simulate over sample times ``t`` (N,) with inputs held between samples.

        Args:
            t: strictly increasing sample times [s], shape (N,).
            i_motor: drive-motor current [A], shape (N,).
            i_brake: brake-motor currents [A], shape (N, 3).
            omega0: speeds at ``t[0]`` [rad/s], shape (2,) (ignored if ``state0`` given; the
                angles then start at 0).

        Returns:
            Speeds etc. at each ``t`` (row 0 is the initial state).

        Raises:
            SimulationError: shapes, non-finite values or non-increasing time.
        """
        tt = np.asarray(t, dtype=float)
        im = np.asarray(i_motor, dtype=float)
        ib = np.asarray(i_brake, dtype=float)
        n = tt.shape[0] if tt.ndim == 1 else -1
        if tt.ndim != 1 or n < 1:
            raise SimulationError(f"t: expected shape (N,), got {tt.shape}")
        if im.shape != (n,):
            raise SimulationError(f"i_motor: expected shape ({n},), got {im.shape}")
        if ib.shape != (n, 3):
            raise SimulationError(f"i_brake: expected shape ({n}, 3), got {ib.shape}")
        for name, arr in (("t", tt), ("i_motor", im), ("i_brake", ib)):
            bad = np.flatnonzero(~np.isfinite(arr.reshape(n, -1)).all(axis=1))
            if bad.size:
                raise SimulationError(f"{name}: non-finite value at sample {int(bad[0])}")
        if n > 1 and np.any(np.diff(tt) <= 0.0):
            k = int(np.flatnonzero(np.diff(tt) <= 0.0)[0])
            raise SimulationError(f"t: not strictly increasing at sample {k + 1}")
        state = state0 if state0 is not None else self.initial_state(omega0, t=float(tt[0]))
        omega = np.empty((n, 2))
        theta = np.empty((n, 2))
        cap = np.empty((n, 3))
        locked = np.zeros((n, 3), dtype=bool)
        gear = np.zeros(n, dtype=np.int64)
        for k in range(n):
            omega[k] = state.omega
            theta[k] = state.theta
            cap[k] = state.capacity
            locked[k] = state.locked
            gear[k] = state.gear
            if k + 1 < n:
                state = self.step(state, float(tt[k + 1] - tt[k]), float(im[k]), ib[k])
        return SimulationResult(t=tt, omega=omega, capacity=cap, locked=locked, gear=gear,
                                theta=theta)

    def kinetic_energy(self, omega: ArrayLike) -> Array:
        """``1/2 omega^T M omega`` [J] for shape (2,) or (N, 2)."""
        w = np.asarray(omega, dtype=float)
        return np.asarray(0.5 * np.einsum("...i,ij,...j->...", w, self.rigid.M, w))


def _identity_keeps(v: Array) -> bool:
    """Whether the 2x2 identity times ``v`` gives ``v`` bit for bit, so the product can be
    skipped: both entries finite and non-zero (the product adds ``0 * v_j`` to each entry, which
    can flip the sign of a zero and turns an infinity into NaN)."""
    a, b = v.tolist()
    return a != 0.0 and b != 0.0 and math.isfinite(a) and math.isfinite(b)


def _sign(x: float) -> float:
    """``np.sign(x)`` for a float: -1.0, 0.0 or 1.0 (NaN stays NaN)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0 if x == 0.0 else x


def _argmax(values: list[float]) -> int:
    """``np.argmax(values)``: the first largest value's index, a NaN's if there is one."""
    best = 0
    for k, v in enumerate(values):
        if v != v:  # NaN
            return k
        if v > values[best]:
            best = k
    return best


def _with(locked: LockSet, k: int, value: bool) -> LockSet:
    items = list(locked)
    items[k] = value
    return (items[0], items[1], items[2])


__all__ = ["HybridModel", "HybridState", "SimulationResult"]
