"""Hidden effects of the simulated plant: what the identifier has to find (pure, no I/O but files).

The simulated plant (:mod:`dvt_driver.plant.core`) runs the clean ``dvt_model`` physics plus the
effects configured here. The configuration is a YAML mapping in which every effect is optional;
the identifier never reads it. The plant writes it, with its own parameters, as ``truth.yaml``
beside a recording (:meth:`HiddenEffects.to_truth_yaml`).

YAML schema (units SI; every top-level key optional)::

    coulomb:                 # Coulomb friction per member: torque -Fc sign(v) [N m]
      sun: 0.08
    stribeck:                # Stribeck static curve per member [N m, N m, rad/s]
      carrier3: {Fc: 0.10, Fs: 0.30, vs: 1.5}      # optional: delta (shape exponent, default 2)
    windage:                 # quadratic drag per member: torque -c |v| v, c [N m s^2]
      sun: 2.0e-6
    backlash:                # free play between carrier 3 and an output shaft with a load
      where: carrier3_output
      gap: 0.02              # total free play [rad]
      stiffness: 400.0       # spline/shaft stiffness in contact [N m/rad]
      damping: 0.2           # contact damping [N m s]
      load_inertia: 0.002    # output shaft + load [kg m^2]
      load_damping: 0.001    # optional, load bearing drag [N m s] (default 0)
    measurement_delay:       # latency of the speed measurement chain [s]
      seconds: 0.004
    wet_brake:               # wet-to-dry band engagement; key "all" or band1 / band2 / band3
      all: {viscous_time: 0.03, viscous_coefficient: 0.02, viscous_fraction: 0.4,
            asperity_time: 0.08, release_time: 0.01}
    friction_velocity: 0.05  # optional, regularisation speed of friction sign() [rad/s]
    gravity_arm:             # an undeclared arm under gravity behind an output stage on carrier 3
      output_stage: {reduction: 20.0, efficiency: 1.0}     # dvt_model.load YAML schema
      arm: {length: 0.5, mass: 10.0, payload: 2.0, zero_angle: -1.5708}
    mesh_ripple:             # torque ripple on the sun shaft at the sun gear's tooth order
      amplitude: 0.03        # [N m]
      stage: 1               # whose sun's teeth give the order (1..3; default 1)
      phase: 0.0             # optional [rad]
    position_friction:       # a friction bump at one angle of a member (a tight spot)
      carrier3: {amplitude: 0.3, center: 1.0, width: 0.3}   # [N m], [rad], [rad]

A plant that changes while it runs (``changes``, plus the base ``damping_scale``)::

    damping_scale: 1.0       # optional: the transmission's viscous damping D times this (>= 0)
    changes:                 # optional: time-varying effects, applied in order of ``at``
      - at: 30.0             # [s] of plant time (physics time since the plant started)
        ramp: 60.0           # optional [s]: linear from the values in force at ``at`` (0: step)
        coulomb: {carrier3: 0.4}   # sets these members' Coulomb levels [N m] (others kept)
        windage: {sun: 2.0e-6}     # sets these members' quadratic drag [N m s^2]
        damping_scale: 0.8         # sets the scale of D (oil warming: damping falls)
        load: arm-payload          # sets the declared joint load (a step; dvt_model.load
                                   # preset or load YAML path; ``none`` removes it)
        note: "band wear"          # optional text, copied into truth.yaml

A change sets the values it lists (members it does not list keep theirs); with ``ramp`` the
numbers move linearly from the values in force at ``at`` to the new ones over ``ramp``
seconds (a load always steps). :func:`scheduled_values` evaluates a schedule at a time (pure);
:class:`~dvt_driver.plant.core.PlantSim` applies it as its physics time passes, records every
change it applies (``PlantSim.changes_applied``) and writes both into ``truth.yaml`` (``hidden:
changes:`` the schedule; ``changes_applied:`` what happened, with the plant time and, from
``dvt-plant``, the host wall-clock time). ``dvt-plant`` also takes changes at runtime
(``--change-at T:SPEC``, ``--change-file`` + SIGHUP; :mod:`dvt_driver.plant.server`).
Presets: ``wear`` (Coulomb friction on carrier 3 rising), ``oil_warmup`` (damping falling),
``payload_added`` (the arm's payload added; run the plant with ``--load arm``),
``friction_step`` (a clear Coulomb step on both shafts, for tests).

Position-dependent effects (they need the angles the plant integrates, ``theta = (theta_sun,
theta_carrier3)`` [rad] from the plant's start; a member's angle is its linear form times
``theta``):

- ``gravity_arm``: a :class:`dvt_model.load.JointLoad` the plant carries but does not declare
  (the declared one is ``dvt-plant --load``): reflected inertia ``J_arm / reduction^2`` on
  carrier 3 and the gravity torque ``-(Mp/2 + Ma) l g cos(theta_c3 / reduction + zero_angle)
  / reduction`` (efficiency as in :mod:`dvt_model.load`). Effect name ``gravity_load``.
- ``mesh_ripple``: ``T = amplitude * sin(Z * theta_sun + phase)`` on the sun shaft, ``Z`` the
  tooth count of stage ``stage``'s sun in the parameter set (16 in the bundled sets): a torque
  periodic in the sun-shaft angle at the sun gear's tooth order. The plant applies its mean
  over each physics step at the step's speed (exact for a constant speed; no aliasing of the
  640 Hz ripple at 2400 rpm into a 1 kHz step). Effect name ``mesh_ripple``.
- ``position_friction``: ``F = amplitude * exp(-(wrap(phi - center) / width)^2) *
  tanh(v / v_eps)`` against the member's speed ``v``, ``phi`` the member's angle, ``wrap`` into
  ``[-pi, pi)``: a once-per-revolution tight spot (a dented bearing race, an eccentric seal).
  Coulomb and Stribeck depend on the speed only and the windage on ``|v|``; none of the
  identifier's candidates has a friction that depends on where the member stands. Effect name
  ``position_friction``.

Members are the kinematic members of :mod:`dvt_model.kinematics`: ``sun``, ``ring1..3``,
``carrier1..3``, ``planet1..3`` (thesis sign), ``planet1..3_abs``, ``planet1..3_rel``.

Friction on a member acts on that member's speed ``v = a . omega`` (``a`` its linear form in
``omega = (omega_sun, omega_carrier3)``) and contributes the generalised torque ``-a F(v)``
(virtual work). The laws are :mod:`dvt_model.friction`'s (``coulomb``, ``stribeck``,
``windage``: the same code the identifier and the model node use). Both friction laws use
``tanh(v / v_eps)`` in place of ``sign(v)``; ``v_eps`` is
``friction_velocity`` raised where needed so that an explicit step of the plant stays stable
(:func:`friction_velocity_floor`). The Stribeck curve is

    F(v) = (Fc + (Fs - Fc) exp(-|v / vs|^delta)) tanh(v / v_eps)

(break-away ``Fs`` at rest falling to ``Fc`` above ``vs``), which differs from Coulomb by the
hump at low speed.

Presets (``config/*.yaml`` in this package): ``none``, ``coulomb``, ``stribeck``, ``windage``,
``backlash``, ``delay``, ``wet_brake``, ``gravity_arm``, ``mesh_ripple``, ``position_friction``,
and the changing plants ``wear``, ``oil_warmup``, ``payload_added``, ``friction_step``
(:func:`available_presets`, :func:`load_hidden`).

Errors name the source, the key path and the value, e.g.
``coulomb.yaml: coulomb.sunn: unknown member (expected one of [...])``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dvt_driver.errors import HiddenEffectsError
from dvt_model import friction
from dvt_model.brake import capacity_step
from dvt_model.errors import ModelError
from dvt_model.load import JointLoad, load_joint_load, parse_joint_load
from dvt_model.presets import bundled_names, read_yaml_setting

__all__ = [
    "BACKLASH_LOCATIONS",
    "MEMBERS",
    "Backlash",
    "Change",
    "HiddenEffects",
    "MeshRipple",
    "PositionFriction",
    "ScheduledValues",
    "StribeckFriction",
    "WetBrake",
    "WetBrakeEngagement",
    "available_presets",
    "changes_from_spec",
    "friction_velocity_floor",
    "load_hidden",
    "parse_change",
    "parse_hidden",
    "scheduled_values",
]

Array = NDArray[np.float64]

MEMBERS: tuple[str, ...] = (
    "sun", "ring1", "ring2", "ring3", "carrier1", "carrier2", "carrier3",
    "planet1", "planet2", "planet3",
    "planet1_abs", "planet2_abs", "planet3_abs",
    "planet1_rel", "planet2_rel", "planet3_rel",
)
"""Members friction and windage may act on (forms in :mod:`dvt_model.kinematics`)."""

BACKLASH_LOCATIONS: tuple[str, ...] = ("carrier3_output",)
"""Where backlash can be placed: the spline between carrier 3 and the output shaft/load."""

DEFAULT_FRICTION_VELOCITY = 0.05
"""Default regularisation speed of the friction laws [rad/s]."""

_PRESET_DIR = "config"


@dataclass(frozen=True)
class StribeckFriction:
    """Stribeck static friction curve on one member.

    Attributes:
        Fc: Coulomb (sliding) level [N m], >= 0.
        Fs: static (break-away) level [N m], >= Fc.
        vs: Stribeck speed [rad/s], > 0.
        delta: shape exponent, > 0 (2 = Gaussian decay).
    """

    Fc: float
    Fs: float
    vs: float
    delta: float = 2.0


@dataclass(frozen=True)
class MeshRipple:
    """Torque ripple on the sun shaft at the sun gear's tooth order.

    Attributes:
        amplitude: ripple amplitude [N m], >= 0.
        stage: the stage (1..3) whose sun's tooth count is the order.
        phase: phase at sun angle 0 [rad].
    """

    amplitude: float
    stage: int = 1
    phase: float = 0.0

    def mean_torque(self, teeth: int, theta: float, omega: float, h: float) -> float:
        """Mean of ``amplitude sin(teeth theta + phase)`` [N m] over a step of ``h`` [s]
        starting at angle ``theta`` [rad] with constant speed ``omega`` [rad/s]."""
        x0 = teeth * theta + self.phase
        dx = teeth * omega * h
        if abs(dx) < 1e-6:
            return self.amplitude * math.sin(x0 + 0.5 * dx)
        return self.amplitude * (math.cos(x0) - math.cos(x0 + dx)) / dx


@dataclass(frozen=True)
class PositionFriction:
    """A friction bump at one angle of a member.

    Attributes:
        amplitude: peak friction [N m], >= 0.
        center: member angle of the peak [rad] (modulo 2 pi).
        width: angular width (Gaussian, 1/e half width) [rad], > 0.
    """

    amplitude: float
    center: float
    width: float

    def level(self, angle: float) -> float:
        """Friction level [N m] at member angle ``angle`` [rad]."""
        d = (angle - self.center + math.pi) % (2.0 * math.pi) - math.pi
        return self.amplitude * math.exp(-(d / self.width) ** 2)


@dataclass(frozen=True)
class Backlash:
    """Free play between carrier 3 and an output shaft carrying a load inertia.

    The spline transmits ``k (d - gap/2 sign d) + c (w_c3 - w_load)`` once the twist ``d`` exceeds
    half the gap (never pulling), nothing inside the gap. The tachometer sits on the output shaft.

    Attributes:
        where: one of :data:`BACKLASH_LOCATIONS`.
        gap: total free play [rad], >= 0.
        stiffness: contact stiffness [N m/rad], > 0.
        damping: contact damping [N m s], >= 0.
        load_inertia: output shaft + load inertia [kg m^2], > 0.
        load_damping: viscous drag of the load bearing [N m s], >= 0.
    """

    where: str
    gap: float
    stiffness: float
    damping: float
    load_inertia: float
    load_damping: float = 0.0

    def natural_frequency(self, carrier3_inertia: float) -> float:
        """Contact natural frequency [rad/s] against a carrier-3 inertia [kg m^2]."""
        return math.sqrt(self.stiffness * (1.0 / self.load_inertia + 1.0 / carrier3_inertia))


@dataclass(frozen=True)
class WetBrake:
    """Wet-to-dry band engagement shape (replaces the first-order lag of one band).

    After the coil is energised the band first squeezes the oil film out (viscous phase): it
    transmits only film shear, ``viscous_coefficient * |omega_ring|``, at most
    ``viscous_fraction`` of the static torque, building up linearly over ``viscous_time``. Then
    asperities touch and the contact torque rises along a smoothstep ``3u^2 - 2u^3``,
    ``u = (t - viscous_time) / asperity_time``, to the static torque. A released band decays
    with ``release_time`` and its oil film re-forms (the next engagement starts viscous again).

    Attributes:
        viscous_time: duration of the squeeze-film phase [s], >= 0.
        viscous_coefficient: film shear coefficient [N m s], >= 0.
        viscous_fraction: cap of the viscous torque relative to the static torque, 0..1.
        asperity_time: rise time of the asperity contact [s], > 0.
        release_time: release time constant [s], > 0.
    """

    viscous_time: float
    viscous_coefficient: float
    viscous_fraction: float
    asperity_time: float
    release_time: float

    def torque(self, applied_time: float, target: float, ring_speed: float) -> float:
        """Available band torque [N m] ``applied_time`` [s] after application of ``target``."""
        if target <= 0.0:
            return 0.0
        ramp = 1.0 if self.viscous_time <= 0.0 else min(1.0, applied_time / self.viscous_time)
        visc = min(self.viscous_fraction * target,
                   self.viscous_coefficient * abs(ring_speed)) * ramp
        u = (applied_time - self.viscous_time) / self.asperity_time
        u = min(1.0, max(0.0, u))
        asp = target * u * u * (3.0 - 2.0 * u)
        return min(target, visc + asp)


@dataclass(frozen=True)
class Change:
    """One scheduled change of the plant (see the module docstring, ``changes``).

    Attributes:
        at: plant time at which it starts [s] (physics time since the plant's start).
        ramp: duration of the linear ramp to the new values [s] (0: a step).
        coulomb: member -> new Coulomb level [N m].
        windage: member -> new quadratic drag coefficient [N m s^2].
        damping_scale: new scale of the transmission's viscous damping D, or ``None``.
        load: new declared joint load (preset name, ``none`` or a load YAML path), or ``None``.
        note: free text for ``truth.yaml``.
    """

    at: float
    ramp: float = 0.0
    coulomb: dict[str, float] = field(default_factory=dict)
    windage: dict[str, float] = field(default_factory=dict)
    damping_scale: float | None = None
    load: str | None = None
    note: str = ""

    def to_mapping(self) -> dict[str, Any]:
        """The change as a plain YAML-able mapping (same schema as the input)."""
        out: dict[str, Any] = {"at": self.at}
        if self.ramp > 0.0:
            out["ramp"] = self.ramp
        if self.coulomb:
            out["coulomb"] = dict(self.coulomb)
        if self.windage:
            out["windage"] = dict(self.windage)
        if self.damping_scale is not None:
            out["damping_scale"] = self.damping_scale
        if self.load is not None:
            out["load"] = self.load
        if self.note:
            out["note"] = self.note
        return out


@dataclass(frozen=True)
class ScheduledValues:
    """The changeable values in force at one time (:func:`scheduled_values`).

    Attributes:
        coulomb, windage: member -> level (the base merged with every change so far).
        damping_scale: scale of the transmission's D.
        load: the declared load named by the latest change that set one (``None``: no change
            named a load yet, the plant keeps its own).
        ramping: True while a ramp is in progress (the values move).
        started: number of changes whose ``at`` has passed.
    """

    coulomb: dict[str, float]
    windage: dict[str, float]
    damping_scale: float
    load: str | None
    ramping: bool
    started: int


def scheduled_values(base: HiddenEffects, t: float) -> ScheduledValues:
    """The changeable values of ``base`` with its ``changes`` applied up to plant time ``t`` [s].

    Changes apply in order of ``at`` (ties: in the order given); a ramping change moves each
    number it lists linearly from the value in force at its ``at`` (all earlier changes
    evaluated at that instant) to its target.
    """
    coulomb = dict(base.coulomb)
    windage = dict(base.windage)
    scale = base.damping_scale
    load: str | None = None
    ramping = False
    started = 0
    for ch in sorted(base.changes, key=lambda c: c.at):
        if t < ch.at:
            break
        started += 1
        u = 1.0
        if ch.ramp > 0.0 and t < ch.at + ch.ramp:
            u = (t - ch.at) / ch.ramp
            ramping = True
        for target, new in ((coulomb, ch.coulomb), (windage, ch.windage)):
            for m, v in new.items():
                v0 = target.get(m, 0.0)
                target[m] = v0 + u * (v - v0)
        if ch.damping_scale is not None:
            scale = scale + u * (ch.damping_scale - scale)
        if ch.load is not None:
            load = ch.load
    return ScheduledValues(coulomb=coulomb, windage=windage, damping_scale=scale, load=load,
                           ramping=ramping, started=started)


@dataclass(frozen=True)
class HiddenEffects:
    """The plant's hidden effects; every one optional (the default is a clean plant).

    Attributes:
        coulomb: member -> Coulomb level Fc [N m].
        stribeck: member -> :class:`StribeckFriction`.
        windage: member -> quadratic drag coefficient c [N m s^2].
        backlash: :class:`Backlash` or ``None``.
        measurement_delay: latency of the speed measurements [s], >= 0.
        wet_brake: band (1..3) -> :class:`WetBrake`.
        friction_velocity: regularisation speed of ``sign()`` [rad/s], > 0.
        gravity_arm: an undeclared :class:`~dvt_model.load.JointLoad` or ``None``.
        mesh_ripple: :class:`MeshRipple` or ``None``.
        position_friction: member -> :class:`PositionFriction`.
        damping_scale: the transmission's viscous damping D is scaled by this (1: as the
            parameter set says), >= 0.
        changes: the schedule of :class:`Change` (empty: the plant does not change).
        source: where it was loaded from (file name or preset), for messages.
    """

    coulomb: dict[str, float] = field(default_factory=dict)
    stribeck: dict[str, StribeckFriction] = field(default_factory=dict)
    windage: dict[str, float] = field(default_factory=dict)
    backlash: Backlash | None = None
    measurement_delay: float = 0.0
    wet_brake: dict[int, WetBrake] = field(default_factory=dict)
    friction_velocity: float = DEFAULT_FRICTION_VELOCITY
    gravity_arm: JointLoad | None = None
    mesh_ripple: MeshRipple | None = None
    position_friction: dict[str, PositionFriction] = field(default_factory=dict)
    damping_scale: float = 1.0
    changes: tuple[Change, ...] = ()
    source: str = "<default>"

    @property
    def is_clean(self) -> bool:
        """True when no effect is configured."""
        return not (self.coulomb or self.stribeck or self.windage or self.backlash
                    or self.measurement_delay > 0.0 or self.wet_brake or self.has_angle_effects
                    or self.damping_scale != 1.0 or self.changes)

    @property
    def has_angle_effects(self) -> bool:
        """True when an effect depends on the angles (gravity arm, mesh ripple, bump)."""
        return (self.gravity_arm is not None or self.mesh_ripple is not None
                or bool(self.position_friction))

    def effect_names(self) -> list[str]:
        """Names (vocabulary of the identification report) of the configured effects."""
        names: list[str] = []
        if self.coulomb:
            names.append("coulomb_friction")
        if self.stribeck:
            names.append("stribeck_friction")
        if self.windage:
            names.append("windage")
        if self.backlash is not None:
            names.append("backlash")
        if self.measurement_delay > 0.0:
            names.append("measurement_delay")
        if self.wet_brake:
            names.append("brake_engagement")
        if self.gravity_arm is not None:
            names.append("gravity_load")
        if self.mesh_ripple is not None:
            names.append("mesh_ripple")
        if self.position_friction:
            names.append("position_friction")
        if self.damping_scale != 1.0:
            names.append("damping_scale")
        if self.changes:
            names.append("plant_changes")
        return names or ["none"]

    def to_mapping(self) -> dict[str, Any]:
        """The configuration as a plain YAML-able mapping (same schema as the input)."""
        out: dict[str, Any] = {}
        if self.coulomb:
            out["coulomb"] = dict(self.coulomb)
        if self.stribeck:
            out["stribeck"] = {m: {"Fc": s.Fc, "Fs": s.Fs, "vs": s.vs, "delta": s.delta}
                               for m, s in self.stribeck.items()}
        if self.windage:
            out["windage"] = dict(self.windage)
        if self.backlash is not None:
            b = self.backlash
            out["backlash"] = {"where": b.where, "gap": b.gap, "stiffness": b.stiffness,
                               "damping": b.damping, "load_inertia": b.load_inertia,
                               "load_damping": b.load_damping}
        if self.measurement_delay > 0.0:
            out["measurement_delay"] = {"seconds": self.measurement_delay}
        if self.wet_brake:
            out["wet_brake"] = {f"band{k}": {
                "viscous_time": w.viscous_time, "viscous_coefficient": w.viscous_coefficient,
                "viscous_fraction": w.viscous_fraction, "asperity_time": w.asperity_time,
                "release_time": w.release_time} for k, w in sorted(self.wet_brake.items())}
        if self.friction_velocity != DEFAULT_FRICTION_VELOCITY:
            out["friction_velocity"] = self.friction_velocity
        if self.gravity_arm is not None:
            out["gravity_arm"] = self.gravity_arm.to_mapping()
        if self.mesh_ripple is not None:
            r = self.mesh_ripple
            out["mesh_ripple"] = {"amplitude": r.amplitude, "stage": r.stage, "phase": r.phase}
        if self.position_friction:
            out["position_friction"] = {m: {"amplitude": b.amplitude, "center": b.center,
                                            "width": b.width}
                                        for m, b in self.position_friction.items()}
        if self.damping_scale != 1.0:
            out["damping_scale"] = self.damping_scale
        if self.changes:
            out["changes"] = [c.to_mapping() for c in self.changes]
        return out

    def to_truth_yaml(self, *, params_name: str, seed: int | None, sample_period_us: int,
                      extra: Mapping[str, Any] | None = None,
                      applied: list[dict[str, Any]] | None = None) -> str:
        """Text of ``truth.yaml``: the hidden effects plus what else defines the plant.

        Args:
            params_name: the transmission parameter set the plant runs (name or path).
            seed: the plant's random seed (``None`` if not seeded).
            sample_period_us: controller sample period [µs].
            extra: further plant settings (sensors, limits, ...) stored under ``plant``.
            applied: the changes the plant applied so far (``changes_applied``: plant time
                ``at_s``, host ``unix_s`` when known, the change), if it has a schedule.
        """
        doc: dict[str, Any] = {
            "truth_version": 1,
            "effects": self.effect_names(),
            "hidden": self.to_mapping(),
            "hidden_source": self.source,
            "plant": {"params": params_name, "seed": seed,
                      "sample_period_us": int(sample_period_us), **dict(extra or {})},
        }
        if applied is not None:
            doc["changes_applied"] = list(applied)
        header = ("# Hidden effects of the simulated DVT plant (ground truth for tests).\n"
                  "# The identifier never reads this file.\n")
        return header + yaml.safe_dump(_plain(doc), sort_keys=False, default_flow_style=False)

    def friction_members(self) -> list[str]:
        """Members with any friction or windage term, in a stable order."""
        changed = {m for c in self.changes for m in (*c.coulomb, *c.windage)}
        return [m for m in MEMBERS
                if m in self.coulomb or m in self.stribeck or m in self.windage or m in changed]


def _plain(obj: Any) -> Any:
    """Convert numpy scalars/tuples to plain YAML types."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


# ---------------------------------------------------------------------------------------------
# loading and validation


def available_presets() -> list[str]:
    """Names of the bundled hidden-effect presets (``config/<name>.yaml``)."""
    return bundled_names("dvt_driver.plant", _PRESET_DIR)


def load_hidden(name_or_path: str | Path) -> HiddenEffects:
    """Load a preset by name (``coulomb``) or a YAML file by path.

    Raises:
        HiddenEffectsError: unknown preset, unreadable file, invalid YAML or content.
    """
    data, source = read_yaml_setting(name_or_path, what="hidden-effects preset",
                                     error=HiddenEffectsError, package="dvt_driver.plant",
                                     directory=_PRESET_DIR)
    return parse_hidden(data, source=source)


def _num(value: Any, where: str, *, lo: float | None = None, lo_open: bool = False,
         hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise HiddenEffectsError(f"{where}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise HiddenEffectsError(f"{where}: expected a finite number, got {value!r}")
    if lo is not None and (out <= lo if lo_open else out < lo):
        op = ">" if lo_open else ">="
        raise HiddenEffectsError(f"{where}: expected a number {op} {lo:g}, got {value!r}")
    if hi is not None and out > hi:
        raise HiddenEffectsError(f"{where}: expected a number <= {hi:g}, got {value!r}")
    return out


def _map(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise HiddenEffectsError(f"{where}: expected a mapping, got {value!r}")
    return value


def _keys(data: Mapping[str, Any], where: str, required: tuple[str, ...],
          optional: tuple[str, ...] = ()) -> None:
    allowed = required + optional
    for key in data:
        if key not in allowed:
            raise HiddenEffectsError(f"{where}.{key}: unknown key (expected one of "
                                     f"{sorted(allowed)}), value {data[key]!r}")
    for key in required:
        if key not in data:
            raise HiddenEffectsError(f"{where}.{key}: missing (required keys: "
                                     f"{list(required)})")


def _member(name: Any, where: str) -> str:
    if name not in MEMBERS:
        raise HiddenEffectsError(f"{where}.{name}: unknown member (expected one of "
                                 f"{list(MEMBERS)})")
    return str(name)


_TOP = ("coulomb", "stribeck", "windage", "backlash", "measurement_delay", "wet_brake",
        "friction_velocity", "gravity_arm", "mesh_ripple", "position_friction",
        "damping_scale", "changes")
_CHANGE_KEYS = ("at", "ramp", "coulomb", "windage", "damping_scale", "load", "note")
MAX_DAMPING_SCALE = 10.0
"""Largest admissible ``damping_scale``."""


def changes_from_spec(spec: str, at: float) -> list[Change]:
    """The changes ``dvt-plant --change-at T:SPEC`` adds: ``spec`` is a preset name or a
    hidden-effects YAML path. If it has ``changes``, those, shifted in time so that the first
    starts at ``at`` [s of plant time] (their spacing kept); else one step at ``at`` to its
    ``coulomb``, ``windage`` and ``damping_scale`` (e.g. ``40:coulomb`` on a clean plant: a
    friction step at 40 s).

    Raises:
        HiddenEffectsError: ``spec`` does not load, or changes nothing that can change.
    """
    h = load_hidden(spec)
    if h.changes:
        first = min(c.at for c in h.changes)
        return [dataclasses.replace(c, at=at + c.at - first) for c in h.changes]
    if not (h.coulomb or h.windage or h.damping_scale != 1.0):
        raise HiddenEffectsError(
            f"{h.source}: changes nothing at runtime (only coulomb, windage, damping_scale and "
            f"changes can change while the plant runs), effects {h.effect_names()}")
    return [Change(at=at, coulomb=dict(h.coulomb), windage=dict(h.windage),
                   damping_scale=None if h.damping_scale == 1.0 else h.damping_scale,
                   note=f"step to {h.source}")]


def parse_change(data: Any, where: str, at: float | None = None) -> Change:
    """Validate one change (a mapping; ``at`` may be left out when ``at`` is given here, e.g.
    a change applied now) into a :class:`Change`.

    Raises:
        HiddenEffectsError: naming ``where``, the key and the value.
    """
    d = _map(data, where)
    for key in d:
        if key not in _CHANGE_KEYS:
            raise HiddenEffectsError(f"{where}.{key}: unknown key (expected one of "
                                     f"{list(_CHANGE_KEYS)}), value {d[key]!r}")
    if "at" in d:
        t = _num(d["at"], f"{where}.at", lo=0.0)
    elif at is not None:
        t = float(at)
    else:
        raise HiddenEffectsError(f"{where}.at: missing (the plant time of the change [s])")
    coulomb = {_member(m, f"{where}.coulomb"): _num(v, f"{where}.coulomb.{m}", lo=0.0)
               for m, v in _map(d.get("coulomb") or {}, f"{where}.coulomb").items()}
    windage = {_member(m, f"{where}.windage"): _num(v, f"{where}.windage.{m}", lo=0.0)
               for m, v in _map(d.get("windage") or {}, f"{where}.windage").items()}
    scale = (None if d.get("damping_scale") is None else
             _num(d["damping_scale"], f"{where}.damping_scale", lo=0.0, hi=MAX_DAMPING_SCALE))
    load = d.get("load")
    if load is not None:
        if not isinstance(load, str) or not load:
            raise HiddenEffectsError(f"{where}.load: expected a load preset name, 'none' or a "
                                     f"load YAML path, got {load!r}")
        try:
            load_joint_load(load)
        except (ModelError, OSError) as exc:
            raise HiddenEffectsError(f"{where}.load: {exc}") from exc
    note = d.get("note", "")
    if not isinstance(note, str):
        raise HiddenEffectsError(f"{where}.note: expected text, got {note!r}")
    if not (coulomb or windage or scale is not None or load is not None):
        raise HiddenEffectsError(f"{where}: changes nothing (expected at least one of coulomb, "
                                 f"windage, damping_scale, load), got {dict(d)!r}")
    return Change(at=t, ramp=_num(d.get("ramp", 0.0), f"{where}.ramp", lo=0.0, hi=1e6),
                  coulomb=coulomb, windage=windage, damping_scale=scale,
                  load=None if load is None else str(load), note=note)


def parse_hidden(data: Any, source: str = "<mapping>") -> HiddenEffects:
    """Validate a parsed YAML mapping (``None`` or ``{}``: no effect) into :class:`HiddenEffects`.

    Raises:
        HiddenEffectsError: naming ``source``, the key path and the value.
    """
    w = f"{source}: "
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise HiddenEffectsError(f"{w}expected a mapping at the top level, got {data!r}")
    for key in data:
        if key not in _TOP:
            raise HiddenEffectsError(f"{w}{key}: unknown effect (expected one of "
                                     f"{list(_TOP)}), value {data[key]!r}")

    coulomb: dict[str, float] = {}
    if data.get("coulomb") is not None:
        for m, v in _map(data["coulomb"], f"{w}coulomb").items():
            name = _member(m, f"{w}coulomb")
            coulomb[name] = _num(v, f"{w}coulomb.{name}", lo=0.0)

    stribeck: dict[str, StribeckFriction] = {}
    if data.get("stribeck") is not None:
        for m, v in _map(data["stribeck"], f"{w}stribeck").items():
            name = _member(m, f"{w}stribeck")
            sw = f"{w}stribeck.{name}"
            d = _map(v, sw)
            _keys(d, sw, ("Fc", "Fs", "vs"), ("delta",))
            fc = _num(d["Fc"], f"{sw}.Fc", lo=0.0)
            fs = _num(d["Fs"], f"{sw}.Fs", lo=0.0)
            if fs < fc:
                raise HiddenEffectsError(f"{sw}.Fs: expected a number >= Fc ({fc:g}), "
                                         f"got {d['Fs']!r}")
            stribeck[name] = StribeckFriction(
                Fc=fc, Fs=fs, vs=_num(d["vs"], f"{sw}.vs", lo=0.0, lo_open=True),
                delta=_num(d.get("delta", 2.0), f"{sw}.delta", lo=0.0, lo_open=True))

    windage: dict[str, float] = {}
    if data.get("windage") is not None:
        for m, v in _map(data["windage"], f"{w}windage").items():
            name = _member(m, f"{w}windage")
            windage[name] = _num(v, f"{w}windage.{name}", lo=0.0)

    backlash: Backlash | None = None
    if data.get("backlash") is not None:
        bw = f"{w}backlash"
        d = _map(data["backlash"], bw)
        _keys(d, bw, ("gap", "stiffness", "damping", "load_inertia"),
              ("where", "load_damping"))
        where = d.get("where", "carrier3_output")
        if where not in BACKLASH_LOCATIONS:
            raise HiddenEffectsError(f"{bw}.where: expected one of {list(BACKLASH_LOCATIONS)}, "
                                     f"got {where!r}")
        backlash = Backlash(
            where=str(where),
            gap=_num(d["gap"], f"{bw}.gap", lo=0.0, hi=1.0),
            stiffness=_num(d["stiffness"], f"{bw}.stiffness", lo=0.0, lo_open=True),
            damping=_num(d["damping"], f"{bw}.damping", lo=0.0),
            load_inertia=_num(d["load_inertia"], f"{bw}.load_inertia", lo=0.0, lo_open=True),
            load_damping=_num(d.get("load_damping", 0.0), f"{bw}.load_damping", lo=0.0))

    delay = 0.0
    if data.get("measurement_delay") is not None:
        dw = f"{w}measurement_delay"
        raw = data["measurement_delay"]
        if isinstance(raw, Mapping):
            _keys(raw, dw, ("seconds",))
            delay = _num(raw["seconds"], f"{dw}.seconds", lo=0.0, hi=1.0)
        else:
            delay = _num(raw, dw, lo=0.0, hi=1.0)

    wet: dict[int, WetBrake] = {}
    if data.get("wet_brake") is not None:
        ww = f"{w}wet_brake"
        bands = _map(data["wet_brake"], ww)
        allowed = ("all", "band1", "band2", "band3")
        for key, v in bands.items():
            if key not in allowed:
                raise HiddenEffectsError(f"{ww}.{key}: unknown band (expected one of "
                                         f"{list(allowed)}), value {v!r}")
        for key, v in bands.items():
            kw = f"{ww}.{key}"
            d = _map(v, kw)
            _keys(d, kw, ("viscous_time", "viscous_coefficient", "viscous_fraction",
                          "asperity_time", "release_time"))
            shape = WetBrake(
                viscous_time=_num(d["viscous_time"], f"{kw}.viscous_time", lo=0.0, hi=10.0),
                viscous_coefficient=_num(d["viscous_coefficient"],
                                         f"{kw}.viscous_coefficient", lo=0.0),
                viscous_fraction=_num(d["viscous_fraction"], f"{kw}.viscous_fraction",
                                      lo=0.0, hi=1.0),
                asperity_time=_num(d["asperity_time"], f"{kw}.asperity_time", lo=0.0,
                                   lo_open=True, hi=10.0),
                release_time=_num(d["release_time"], f"{kw}.release_time", lo=0.0,
                                  lo_open=True, hi=10.0))
            if key == "all":
                for k in (1, 2, 3):
                    wet.setdefault(k, shape)
            else:
                wet[int(str(key)[-1])] = shape  # bandN overrides "all"

    fv = DEFAULT_FRICTION_VELOCITY
    if data.get("friction_velocity") is not None:
        fv = _num(data["friction_velocity"], f"{w}friction_velocity", lo=0.0, lo_open=True)

    gravity: JointLoad | None = None
    if data.get("gravity_arm") is not None:
        try:
            gravity = parse_joint_load(data["gravity_arm"], source=f"{w}gravity_arm")
        except ModelError as exc:
            raise HiddenEffectsError(str(exc)) from exc

    ripple: MeshRipple | None = None
    if data.get("mesh_ripple") is not None:
        rw = f"{w}mesh_ripple"
        d = _map(data["mesh_ripple"], rw)
        _keys(d, rw, ("amplitude",), ("stage", "phase"))
        stage = d.get("stage", 1)
        if isinstance(stage, bool) or stage not in (1, 2, 3):
            raise HiddenEffectsError(f"{rw}.stage: expected 1, 2 or 3, got {stage!r}")
        ripple = MeshRipple(amplitude=_num(d["amplitude"], f"{rw}.amplitude", lo=0.0, hi=100.0),
                            stage=int(stage), phase=_num(d.get("phase", 0.0), f"{rw}.phase"))

    bumps: dict[str, PositionFriction] = {}
    if data.get("position_friction") is not None:
        pw = f"{w}position_friction"
        for m, v in _map(data["position_friction"], pw).items():
            name = _member(m, pw)
            bw = f"{pw}.{name}"
            d = _map(v, bw)
            _keys(d, bw, ("amplitude", "center", "width"))
            bumps[name] = PositionFriction(
                amplitude=_num(d["amplitude"], f"{bw}.amplitude", lo=0.0, hi=100.0),
                center=_num(d["center"], f"{bw}.center"),
                width=_num(d["width"], f"{bw}.width", lo=0.0, lo_open=True, hi=10.0))

    scale = 1.0
    if data.get("damping_scale") is not None:
        scale = _num(data["damping_scale"], f"{w}damping_scale", lo=0.0, hi=MAX_DAMPING_SCALE)
    changes: list[Change] = []
    if data.get("changes") is not None:
        raw_changes = data["changes"]
        if not isinstance(raw_changes, list):
            raise HiddenEffectsError(f"{w}changes: expected a list of changes, got "
                                     f"{raw_changes!r}")
        changes = [parse_change(c, f"{w}changes[{i}]") for i, c in enumerate(raw_changes)]

    return HiddenEffects(coulomb=coulomb, stribeck=stribeck, windage=windage, backlash=backlash,
                         measurement_delay=delay, wet_brake=wet, friction_velocity=fv,
                         gravity_arm=gravity, mesh_ripple=ripple, position_friction=bumps,
                         damping_scale=scale, changes=tuple(changes), source=source)


# ---------------------------------------------------------------------------------------------
# numerical forms used by the plant


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
        effects: the hidden effects (coulomb, stribeck, windage are used).
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
        # per-member parameters as arrays: the dvt_model.friction laws broadcast over members
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

    def __bool__(self) -> bool:
        return bool(self.members)

    def member_torques(self, omega: Array) -> Array:
        """Friction + windage torque on each member [N m], shape (n_members,)."""
        v = self.A @ omega
        u = v / self.v_eps
        F = friction.coulomb(u, self._level, 0.0, 1.0)
        if self._has_stribeck:
            F = F + friction.stribeck(u, self.s_dF, self._vs_n, 1.0, self.s_delta)
        if self._has_windage:
            F = F + friction.windage(v, self.c_w)
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
        time_constant: first-order time constant of the other bands [s].
        on_threshold: static torque above which a band counts as applied [N m].
    """

    def __init__(self, shapes: Mapping[int, WetBrake], time_constant: float,
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
                mean[i] = cap0 * (1.0 - e) * shape.release_time / dt
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
