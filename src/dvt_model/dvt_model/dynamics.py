"""Lagrangian reduction of the DVT to the rigid two-DOF model.

Generalised speeds ``omega = (omega_sun, omega_carrier3)`` [rad/s]. With every member's speed a
linear form ``v_i . omega`` (see :mod:`dvt_model.kinematics`), the kinetic energy is
``T = 1/2 omega^T M omega`` with ``M = sum_i J_i v_i v_i^T``, the Rayleigh dissipation
``R = 1/2 omega^T D omega`` with ``D = sum_i b_i w_i w_i^T`` and the virtual work of a torque
``tau`` on member ``i`` gives the generalised force ``v_i tau``. Lagrange's equations:

    M omega' = -D omega + Q u,   u = [T_motor, T_brake] [N m]

so ``A = -M^-1 D`` and ``B = M^-1 Q`` for torque inputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dvt_model.errors import ModelError
from dvt_model.kinematics import BRAKED_RING, Kinematics, kinematics
from dvt_model.params import TransmissionParams

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RigidModel:
    """The rigid two-DOF model of a parameter set.

    Attributes:
        M: mass matrix [kg m^2], shape (2, 2), symmetric positive definite.
        D: damping matrix [N m s], shape (2, 2).
        Q_motor: generalised force of the drive-motor torque, shape (2,).
        Q_brake: generalised force of each band's torque on its ring, shape (2, 3);
            column g-1 is band g.
        motor_constant: K_M [N m/A].
    """

    M: Array
    D: Array
    Q_motor: Array
    Q_brake: Array
    motor_constant: float
    kin: Kinematics = field(repr=False)

    def Q(self, gear: int = 1) -> Array:
        """Input matrix for ``u = [T_motor, T_brake_gear]``, shape (2, 2)."""
        if gear not in BRAKED_RING:
            raise ModelError(f"gear: expected 1, 2 or 3, got {gear!r}")
        return np.column_stack([self.Q_motor, self.Q_brake[:, gear - 1]])

    @property
    def A(self) -> Array:
        """State matrix ``-M^-1 D`` [1/s], shape (2, 2)."""
        return np.asarray(-np.linalg.solve(self.M, self.D))

    def B(self, gear: int = 1) -> Array:
        """Input matrix ``M^-1 Q`` for torque inputs [1/(kg m^2)], shape (2, 2)."""
        return np.asarray(np.linalg.solve(self.M, self.Q(gear)))

    def B_thesis(self, brake_static_torque: float, gear: int = 1) -> Array:
        """Input matrix for the thesis's inputs (motor current [A], normalised brake profile).

        ``B diag(K_M, T_static)``, shape (2, 2).
        """
        return self.B(gear) @ np.diag([self.motor_constant, brake_static_torque])


def check_mass_matrix(M: Array, what: str = "M") -> None:
    """Raise :class:`ModelError` unless ``M`` is a finite, symmetric positive definite 2x2."""
    M = np.asarray(M, dtype=float)
    if M.shape != (2, 2):
        raise ModelError(f"{what}: expected shape (2, 2), got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ModelError(f"{what}: contains non-finite values: {M.tolist()}")
    if not np.allclose(M, M.T, rtol=1e-9, atol=1e-15):
        raise ModelError(f"{what}: not symmetric: {M.tolist()}")
    eig = np.linalg.eigvalsh(M)
    if eig.min() <= 0.0:
        raise ModelError(
            f"{what}: not positive definite (eigenvalues {eig.tolist()}): {M.tolist()}"
        )


def rigid_model(params: TransmissionParams) -> RigidModel:
    """Assemble M, D and Q for ``params`` (its ``lumping`` decides which members count).

    Thesis lumping: each carrier alone (the ring it carries not added), one ``J_p`` per stage on
    the planet speed, damping on every member's absolute speed except the sun, whose damping
    acts on its speed relative to ring 1. Complete lumping: every planet (count x spin inertia)
    plus its orbital inertia ``m r^2`` on the carrier, each carrier with its splined ring,
    damping on absolute speeds and on each planet's spin relative to its carrier.

    Raises:
        ModelError: M not symmetric positive definite.
    """
    kin = kinematics(params)
    v = kin.vector
    M = np.zeros((2, 2))
    D = np.zeros((2, 2))

    def add(mat: Array, coeff: float, vec: Array) -> None:
        mat += coeff * np.outer(vec, vec)

    add(M, params.j_sun, v("sun"))
    if params.lumping == "thesis":
        add(M, params.j_ring[0], v("ring1"))
        for k in range(3):
            add(M, params.j_carrier[k], v(f"carrier{k + 1}"))
            add(M, params.j_planet[k], v(f"planet{k + 1}"))
        add(D, params.b_sun, v("sun") - v("ring1"))
        add(D, params.b_ring[0], v("ring1"))
        for k in range(3):
            add(D, params.b_carrier[k], v(f"carrier{k + 1}"))
            add(D, params.b_planet[k], v(f"planet{k + 1}"))
    else:
        for k in range(3):
            n = params.stages[k].planets
            add(M, params.j_ring[k], v(f"ring{k + 1}"))
            orbital = n * params.planet_mass[k] * params.orbit_radius[k] ** 2
            add(M, params.j_carrier[k] + orbital, v(f"carrier{k + 1}"))
            add(M, n * params.j_planet[k], v(f"planet{k + 1}_abs"))
        add(D, params.b_sun, v("sun"))
        for k in range(3):
            n = params.stages[k].planets
            add(D, params.b_ring[k], v(f"ring{k + 1}"))
            add(D, params.b_carrier[k], v(f"carrier{k + 1}"))
            add(D, n * params.b_planet[k], v(f"planet{k + 1}_rel"))
    check_mass_matrix(M)
    Q_brake = np.column_stack([v(BRAKED_RING[g]) for g in (1, 2, 3)])
    return RigidModel(M=M, D=D, Q_motor=v("sun"), Q_brake=Q_brake,
                      motor_constant=params.motor_constant, kin=kin)


@dataclass(frozen=True)
class PhysicalFromIdentified:
    """Physical matrices recovered from identified ``A``, ``B`` (thesis eq. 4.98-4.101).

    Attributes:
        J: ``q B^-1`` [kg m^2], shape (2, 2).
        b_thesis: ``J A`` as the thesis prints it (eq. 4.101) [N m s], shape (2, 2).
        D: ``-J A``, the damping consistent with ``M omega' = -D omega`` [N m s].
    """

    J: Array
    b_thesis: Array
    D: Array


def physical_from_identified(A: Array, B: Array, q: Array) -> PhysicalFromIdentified:
    """``J = q B^-1``, ``b = J A`` (eq. 4.98-4.101) and the sign-consistent ``D = -J A``.

    Args:
        A: identified state matrix, shape (2, 2).
        B: identified input matrix for the inputs ``q`` maps to torques, shape (2, 2).
        q: generalised-force matrix of those inputs, shape (2, 2), e.g.
            ``[[K_M, a_ring1], [0, b_ring1]]``.

    Raises:
        ModelError: wrong shapes or singular ``B``.
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    q = np.asarray(q, dtype=float)
    for name, mat in (("A", A), ("B", B), ("q", q)):
        if mat.shape != (2, 2):
            raise ModelError(f"{name}: expected shape (2, 2), got {mat.shape}")
        if not np.all(np.isfinite(mat)):
            raise ModelError(f"{name}: contains non-finite values: {mat.tolist()}")
    if abs(np.linalg.det(B)) < 1e-300 or np.linalg.cond(B) > 1e14:
        raise ModelError(f"B: singular, cannot invert: {B.tolist()}")
    J = q @ np.linalg.inv(B)
    return PhysicalFromIdentified(J=J, b_thesis=J @ A, D=-(J @ A))
