"""The hidden effects of the simulated plant as data: what each effect is, a changing plant's
schedule (:func:`scheduled_values`) and the ``truth.yaml`` text (pure; the schema is in
:mod:`dvt_driver.plant.hidden`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from dvt_model.load import JointLoad
from dvt_model.params import BrakeParams

__all__ = [
    "BACKLASH_LOCATIONS",
    "DEFAULT_FRICTION_VELOCITY",
    "MEMBERS",
    "Backlash",
    "Bands",
    "Change",
    "HiddenEffects",
    "MeshRipple",
    "PositionFriction",
    "ScheduledValues",
    "StribeckFriction",
    "WetBrake",
    "scheduled_values",
]

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
class Bands:
    """The three band brakes as built, not as designed: each band's own static gain and
    engagement time constant in place of the parameter set's shared law (a lining's friction
    coefficient and a band's fit spread from band to band). Not an effect the model lacks: the
    model carries one gain and one lag per band (``BrakeParams.band_gain``,
    ``band_time_constant``), and the identifier fits them in its baseline.

    Attributes:
        gain: static brake torque per brake-motor ampere of bands 1..3 [N m/A], each > 0, or
            ``None`` (the parameter set's law).
        time_constant: engagement time constant of bands 1..3 [s], each > 0, or ``None``.
    """

    gain: tuple[float, float, float] | None = None
    time_constant: tuple[float, float, float] | None = None

    def apply(self, brake: BrakeParams) -> BrakeParams:
        """``brake`` with these bands' gains and time constants (those given)."""
        return dataclasses.replace(
            brake,
            band_gain=self.gain if self.gain is not None else brake.band_gain,
            band_time_constant=(self.time_constant if self.time_constant is not None
                                else brake.band_time_constant))

    def to_mapping(self) -> dict[str, Any]:
        """The YAML mapping (schema of :mod:`dvt_driver.plant.hidden`, ``bands``)."""
        out: dict[str, Any] = {}
        if self.gain is not None:
            out["gain"] = list(self.gain)
        if self.time_constant is not None:
            out["time_constant"] = list(self.time_constant)
        return out


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
        bands: the band brakes as built (:class:`Bands`), or ``None`` (the parameter set's).
        laws: member -> speed laws of :data:`dvt_model.laws.LAWS` on it, each ``(law name,
            its parameters by the law's field names)``; their sign is smoothed with the
            friction laws' ``v_eps`` (a law of the table reaches the plant without a field
            of its own here: ``docs/effects.md``).
        damping_scale: the transmission's viscous damping D is scaled by this (1: as the
            parameter set says), >= 0.
        changes: the schedule of :class:`Change` (empty: the plant does not change).
        source: where it was loaded from (file name or preset), for messages.
        draw: how a preset's distributions were drawn (:func:`~.draw.draw_record`: seed,
            fixed, distributions by key path), ``None`` for a preset without one; written
            into ``truth.yaml`` as ``hidden_draw``.
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
    bands: Bands | None = None
    laws: dict[str, tuple[tuple[str, dict[str, float]], ...]] = field(default_factory=dict)
    damping_scale: float = 1.0
    changes: tuple[Change, ...] = ()
    source: str = "<default>"
    draw: Mapping[str, Any] | None = None

    @property
    def is_clean(self) -> bool:
        """True when no effect is configured."""
        return not (self.coulomb or self.stribeck or self.windage or self.laws or self.backlash
                    or self.measurement_delay > 0.0 or self.wet_brake or self.has_angle_effects
                    or self.damping_scale != 1.0 or self.changes or self.bands is not None)

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
        names.extend(dict.fromkeys(name for terms in self.laws.values() for name, _ in terms))
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
        if self.bands is not None:
            names.append("bands")
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
        if self.laws:
            out["laws"] = {m: [{"law": name, **params} for name, params in terms]
                           for m, terms in self.laws.items()}
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
        if self.bands is not None:
            out["bands"] = self.bands.to_mapping()
        if self.damping_scale != 1.0:
            out["damping_scale"] = self.damping_scale
        if self.changes:
            out["changes"] = [c.to_mapping() for c in self.changes]
        return out

    def to_truth_yaml(self, *, params_name: str, seed: int | None, sample_period_us: int,
                      extra: Mapping[str, Any] | None = None,
                      applied: list[dict[str, Any]] | None = None) -> str:
        """Text of ``truth.yaml``: the hidden effects plus what else defines the plant
        (``hidden``: the values the plant runs, drawn ones included; ``hidden_draw``: how a
        preset's distributions were drawn, when it has any).

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
            **({"hidden_draw": dict(self.draw)} if self.draw is not None else {}),
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
                if m in self.coulomb or m in self.stribeck or m in self.windage or m in self.laws
                or m in changed]


def _plain(obj: Any) -> Any:
    """Convert numpy scalars/tuples to plain YAML types."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
