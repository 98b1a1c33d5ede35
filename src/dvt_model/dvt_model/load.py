"""The joint load of the actuator: an output stage and an arm under gravity (pure; reads files).

The DVT drives a robot-arm joint through a fixed output stage (e.g. a harmonic drive): carrier 3
turns ``reduction`` times per turn of the joint. The baseline requirement of the thesis
(eq. 1.1) is the torque of a uniform arm (length ``l``, mass ``Mp``) carrying a tip payload
``Ma`` at angle ``theta`` from the horizontal:

    T(theta'', theta) = (Mp/3 + Ma) l^2 theta'' + (Mp/2 + Ma) l g cos(theta)        [N m]

:class:`Arm` holds the arm (inertia, gravity torque, requirement torque), :class:`OutputStage`
the reduction and efficiency, :class:`JointLoad` both, reflected to carrier 3 for the
dynamics (:class:`dvt_model.hybrid.HybridModel` ``load=``):

- the joint angle is ``theta = theta_c3 / reduction + zero_angle`` (``theta_c3`` the carrier-3
  angle [rad] from the output encoder's zero; ``zero_angle`` the arm's angle from the
  horizontal when that encoder reads 0, e.g. ``-pi/2``: hanging straight down);
- reflected inertia at carrier 3: ``J_arm / reduction^2`` [kg m^2] (added to the mass matrix);
- gravity torque on carrier 3: ``-(Mp/2 + Ma) l g cos(theta) / reduction`` times ``1/eta``
  while the motor lifts (power flows to the arm) and ``eta`` while the arm back-drives the
  transmission; the switch is blended by ``tanh(omega_c3 / velocity_eps)`` so the force is
  smooth at rest (efficiency acts on the gravity torque only, not on the reflected inertia).

Units are SI in and out (m, kg, rad, s, N m); :data:`INCH`, :data:`POUND` convert the thesis's
figures. Presets (:data:`LOAD_PRESETS`): ``arm`` (the thesis's 71 in, 200 lb arm without
payload) and ``arm-payload`` (with the 240 lb payload), both on a 100:1 stage of efficiency
0.85 hanging down at the encoder's zero (``zero_angle = -pi/2``). A load YAML::

    output_stage: {reduction: 100.0, efficiency: 0.85}
    arm: {length: 1.8034, mass: 90.718, payload: 108.862, zero_angle: -1.5707963}
    # optional: g: 9.81 under arm, velocity_eps: 0.05 at the top level

Errors are :class:`~dvt_model.errors.ModelError` naming the field and the value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dvt_model.errors import ModelError
from dvt_model.presets import read_yaml_setting

__all__ = [
    "INCH",
    "LOAD_PRESETS",
    "POUND",
    "Arm",
    "G",
    "JointLoad",
    "OutputStage",
    "available_loads",
    "load_joint_load",
    "parse_joint_load",
    "thesis_arm",
]

Array = NDArray[np.float64]

INCH = 0.0254
"""One inch [m]."""
POUND = 0.45359237
"""One pound (mass) [kg]."""
G = 9.81
"""Gravitational acceleration [m/s^2], as the thesis rounds it (``dvt_model.requirements``)."""

DEFAULT_VELOCITY_EPS = 0.05
"""Carrier-3 speed [rad/s] over which the efficiency switches between lifting and lowering."""


def _positive(name: str, value: Any, *, allow_zero: bool = False, hi: float | None = None
              ) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ModelError(f"{name}: expected a finite number, got {value!r}")
    v = float(value)
    if v < 0.0 or (v == 0.0 and not allow_zero):
        raise ModelError(f"{name}: expected a number {'>=' if allow_zero else '>'} 0, "
                         f"got {value!r}")
    if hi is not None and v > hi:
        raise ModelError(f"{name}: expected a number <= {hi:g}, got {value!r}")
    return v


@dataclass(frozen=True)
class OutputStage:
    """Fixed reduction between carrier 3 and the joint.

    Attributes:
        reduction: carrier-3 turns per joint turn (input speed / output speed), > 0.
        efficiency: power efficiency in (0, 1] (the same both ways).
    """

    reduction: float
    efficiency: float = 1.0

    def __post_init__(self) -> None:
        _positive("reduction", self.reduction)
        _positive("efficiency", self.efficiency, hi=1.0)

    def input_torque(self, output_torque: float | Array, output_speed: float | Array = 1.0
                     ) -> float | Array:
        """Torque the stage's input must supply [N m] for ``output_torque`` [N m] at the joint.

        ``T / (reduction * eta)`` when power flows to the joint (``T * speed >= 0``), else
        ``T * eta / reduction`` (the joint back-drives the stage). Scalars or arrays.
        """
        t = np.asarray(output_torque, dtype=float)
        forward = t * np.asarray(output_speed, dtype=float) >= 0.0
        out = np.where(forward, t / (self.reduction * self.efficiency),
                       t * self.efficiency / self.reduction)
        return float(out) if out.ndim == 0 else np.asarray(out)

    def reflected_inertia(self, joint_inertia: float) -> float:
        """A joint-side inertia [kg m^2] seen at the stage input: ``J / reduction^2``."""
        return float(joint_inertia) / self.reduction**2


@dataclass(frozen=True)
class Arm:
    """A uniform arm with a tip payload turning about a horizontal joint axis.

    Attributes:
        length: arm length l [m], > 0.
        mass: arm mass Mp [kg], >= 0 (uniform along its length).
        payload: tip payload Ma [kg], >= 0.
        zero_angle: the arm's angle from the horizontal [rad] when the output encoder reads 0
            (``-pi/2``: hanging down; positive angles raise the arm).
        g: gravitational acceleration [m/s^2], >= 0.
    """

    length: float
    mass: float
    payload: float = 0.0
    zero_angle: float = 0.0
    g: float = G

    def __post_init__(self) -> None:
        _positive("length", self.length)
        _positive("mass", self.mass, allow_zero=True)
        _positive("payload", self.payload, allow_zero=True)
        _positive("g", self.g, allow_zero=True)
        if not math.isfinite(self.zero_angle) or abs(self.zero_angle) > 2.0 * math.pi:
            raise ModelError(f"zero_angle: expected a number in [-2 pi, 2 pi] rad, got "
                             f"{self.zero_angle!r}")

    @property
    def inertia(self) -> float:
        """``(Mp/3 + Ma) l^2`` about the joint [kg m^2]."""
        return (self.mass / 3.0 + self.payload) * self.length**2

    @property
    def gravity_coefficient(self) -> float:
        """``(Mp/2 + Ma) l g`` [N m]: the gravity torque with the arm horizontal."""
        return (self.mass / 2.0 + self.payload) * self.length * self.g

    def gravity_torque(self, theta: float | Array) -> float | Array:
        """Joint torque [N m] that holds the arm at ``theta`` [rad from horizontal]:
        ``(Mp/2 + Ma) l g cos(theta)`` (gravity itself pulls with the opposite sign)."""
        out = self.gravity_coefficient * np.cos(np.asarray(theta, dtype=float))
        return float(out) if out.ndim == 0 else np.asarray(out)

    def torque(self, alpha: float | Array, theta: float | Array = 0.0) -> float | Array:
        """The requirement torque ``T(theta'', theta)`` [N m] (thesis eq. 1.1): inertia times
        ``alpha`` [rad/s^2] plus :meth:`gravity_torque`; eq. 1.2 (``T_max``) at ``theta = 0``."""
        out = self.inertia * np.asarray(alpha, dtype=float) + np.asarray(
            self.gravity_torque(theta), dtype=float)
        return float(out) if out.ndim == 0 else np.asarray(out)


def thesis_arm(payload: bool = True, zero_angle: float = 0.0) -> Arm:
    """The thesis's arm: 71 in, 200 lb, with (``payload=True``) its 240 lb payload."""
    return Arm(length=71 * INCH, mass=200 * POUND, payload=240 * POUND if payload else 0.0,
               zero_angle=zero_angle)


@dataclass(frozen=True)
class JointLoad:
    """An arm behind an output stage, as a load on carrier 3 (module docstring).

    Attributes:
        stage: the :class:`OutputStage`.
        arm: the :class:`Arm`.
        name: preset name or file, for messages.
        velocity_eps: carrier-3 speed [rad/s] blending the lifting/lowering efficiency, > 0.
    """

    stage: OutputStage
    arm: Arm
    name: str = "custom"
    velocity_eps: float = field(default=DEFAULT_VELOCITY_EPS)

    def __post_init__(self) -> None:
        _positive("velocity_eps", self.velocity_eps)

    @property
    def reflected_inertia(self) -> float:
        """The arm's inertia seen at carrier 3 [kg m^2]."""
        return self.stage.reflected_inertia(self.arm.inertia)

    def arm_angle(self, theta_c3: float | Array) -> float | Array:
        """Joint angle [rad from horizontal] at carrier-3 angle ``theta_c3`` [rad]."""
        out = np.asarray(theta_c3, dtype=float) / self.stage.reduction + self.arm.zero_angle
        return float(out) if out.ndim == 0 else np.asarray(out)

    def carrier3_angle(self, arm_angle: float | Array) -> float | Array:
        """Carrier-3 angle [rad] at joint angle ``arm_angle`` [rad from horizontal]."""
        out = (np.asarray(arm_angle, dtype=float) - self.arm.zero_angle) * self.stage.reduction
        return float(out) if out.ndim == 0 else np.asarray(out)

    def carrier3_torque(self, theta_c3: float, omega_c3: float) -> float:
        """Torque the arm's gravity exerts on carrier 3 [N m] at carrier-3 angle ``theta_c3``
        [rad] and speed ``omega_c3`` [rad/s] (negative: it pulls the arm down when
        horizontal), with the stage's efficiency (module docstring)."""
        tg = self.arm.gravity_coefficient * math.cos(theta_c3 / self.stage.reduction
                                                     + self.arm.zero_angle)
        eta = self.stage.efficiency
        if eta >= 1.0:
            factor = 1.0
        else:
            lift = math.tanh(omega_c3 / self.velocity_eps) * (1.0 if tg >= 0.0 else -1.0)
            factor = 0.5 * ((1.0 / eta + eta) + (1.0 / eta - eta) * lift)
        return -tg * factor / self.stage.reduction

    def generalised_force(self, theta: ArrayLike, omega: ArrayLike) -> Array:
        """Generalised torque (2,) [N m] on ``(sun, carrier3)`` at angles ``theta`` (2,) [rad]
        and speeds ``omega`` (2,) [rad/s]: ``(0, carrier3_torque)``."""
        th = np.asarray(theta, dtype=float).reshape(2)
        w = np.asarray(omega, dtype=float).reshape(2)
        return np.array([0.0, self.carrier3_torque(float(th[1]), float(w[1]))])

    def requirement_torque(self, alpha: float | Array, theta: float | Array = 0.0
                           ) -> float | Array:
        """The joint torque ``T(theta'', theta)`` [N m] (:meth:`Arm.torque`)."""
        return self.arm.torque(alpha, theta)

    def carrier3_requirement(self, alpha: float, theta: float = 0.0, omega: float = 1.0
                             ) -> float:
        """The requirement torque reflected to carrier 3 [N m]: :meth:`requirement_torque`
        through the stage (``/ (reduction eta)`` when lifting at joint speed ``omega``)."""
        return float(self.stage.input_torque(float(self.arm.torque(alpha, theta)), omega))

    def to_mapping(self) -> dict[str, Any]:
        """The load as the YAML mapping :func:`parse_joint_load` reads."""
        a = self.arm
        return {"output_stage": {"reduction": self.stage.reduction,
                                 "efficiency": self.stage.efficiency},
                "arm": {"length": a.length, "mass": a.mass, "payload": a.payload,
                        "zero_angle": a.zero_angle, "g": a.g},
                "velocity_eps": self.velocity_eps}


_STAGE = OutputStage(reduction=100.0, efficiency=0.85)
LOAD_PRESETS: dict[str, JointLoad] = {
    "arm": JointLoad(_STAGE, thesis_arm(payload=False, zero_angle=-math.pi / 2), name="arm"),
    "arm-payload": JointLoad(_STAGE, thesis_arm(payload=True, zero_angle=-math.pi / 2),
                             name="arm-payload"),
}
"""Bundled loads: the thesis's arm without / with its payload, 100:1 stage, eta 0.85, hanging
down at the encoder's zero. ``none`` (no load) is accepted by :func:`load_joint_load` too."""


def available_loads() -> list[str]:
    """Names :func:`load_joint_load` accepts besides a YAML path: ``none`` and the presets."""
    return ["none", *LOAD_PRESETS]


def _section(data: Mapping[str, Any], key: str, where: str, keys: tuple[str, ...],
             required: tuple[str, ...]) -> Mapping[str, Any]:
    sec = data.get(key)
    if not isinstance(sec, Mapping):
        raise ModelError(f"{where}{key}: expected a mapping with {list(keys)}, got {sec!r}")
    for k in sec:
        if k not in keys:
            raise ModelError(f"{where}{key}.{k}: unknown key (expected one of {list(keys)}), "
                             f"value {sec[k]!r}")
    for k in required:
        if k not in sec:
            raise ModelError(f"{where}{key}.{k}: missing (required: {list(required)})")
    return sec


def parse_joint_load(data: Any, source: str = "<mapping>") -> JointLoad:
    """A :class:`JointLoad` from a parsed YAML mapping (module docstring's schema).

    Raises:
        ModelError: naming ``source``, the key and the value.
    """
    where = f"{source}: "
    if not isinstance(data, Mapping):
        raise ModelError(f"{where}expected a mapping with output_stage and arm, got {data!r}")
    for k in data:
        if k not in ("output_stage", "arm", "velocity_eps"):
            raise ModelError(f"{where}{k}: unknown key (expected output_stage, arm, "
                             f"velocity_eps), value {data[k]!r}")
    st = _section(data, "output_stage", where, ("reduction", "efficiency"), ("reduction",))
    arm = _section(data, "arm", where, ("length", "mass", "payload", "zero_angle", "g"),
                   ("length", "mass"))
    try:
        stage = OutputStage(st["reduction"], st.get("efficiency", 1.0))
    except ModelError as exc:
        raise ModelError(f"{where}output_stage.{exc}") from exc
    try:
        a = Arm(arm["length"], arm["mass"], arm.get("payload", 0.0), arm.get("zero_angle", 0.0),
                arm.get("g", G))
    except (ModelError, TypeError) as exc:
        raise ModelError(f"{where}arm.{exc}") from exc
    try:
        return JointLoad(stage, a, name=source,
                         velocity_eps=data.get("velocity_eps", DEFAULT_VELOCITY_EPS))
    except ModelError as exc:
        raise ModelError(f"{where}{exc}") from exc


def load_joint_load(name_or_path: str | Path) -> JointLoad | None:
    """``none`` -> ``None``; a preset name (``arm``, ``arm-payload``); or a load YAML path.

    Raises:
        ModelError: unknown name, unreadable file, invalid YAML or content.
    """
    if isinstance(name_or_path, str):
        if name_or_path in ("", "none"):
            return None
        if name_or_path in LOAD_PRESETS:
            return LOAD_PRESETS[name_or_path]
    data, source = read_yaml_setting(name_or_path, what="load", error=ModelError,
                                     names=available_loads())
    return parse_joint_load(data, source=source)
