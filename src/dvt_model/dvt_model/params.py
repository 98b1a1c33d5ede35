"""Transmission parameter sets: YAML files validated into frozen objects.

A parameter set describes the three-stage carrier-to-ring DVT: teeth and planet count per
stage, inertia [kg m^2] and viscous damping [N m s] of each member, the drive-motor constant
[N m/A] and the band-brake data. Bundled sets: ``thesis``, ``thesis-derivation`` and
``physical`` (see ``available_parameter_sets``).

Errors name the source, the key path and the value, e.g.
``thesis.yaml: stages[2].ring: expected an integer > planet teeth, got 12``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from dvt_model.errors import ParameterError
from dvt_model.presets import bundled_names, read_yaml_setting

Lumping = Literal["thesis", "complete"]


@dataclass(frozen=True)
class Stage:
    """One planetary stage: tooth counts and number of planets."""

    sun: int
    planet: int
    ring: int
    planets: int


@dataclass(frozen=True)
class BrakeParams:
    """Band-brake data shared by the three bands.

    Static torque law (band brake, Eytelwein): the brake motor's torque
    ``motor_constant * i`` [N m] becomes a band pull ``actuation_gain * motor_constant * i`` [N],
    and the band holds ``pull * (exp(mu * wrap) - 1) * drum_radius`` [N m].
    ``time_constant`` [s] is the first-order engagement time, ``static_factor`` the ratio of the
    holding (stick) capacity to the sliding torque. ``band_gain`` [N m/A] and
    ``band_time_constant`` [s] (3 values each, bands 1..3) override the shared law per band:
    a unit as built (the ``physical`` set's ``brake.band_gain``/``brake.band_time_constant``)
    or identified values; ``None`` = the shared law.
    """

    motor_constant: float
    actuation_gain: float
    friction_coefficient: float
    wrap_angle: float
    drum_radius: float
    time_constant: float
    static_factor: float = 1.0
    band_gain: tuple[float, float, float] | None = None
    band_time_constant: tuple[float, float, float] | None = None

    @property
    def gains(self) -> NDArray[np.float64]:
        """Static torque per brake-motor ampere of each band [N m/A], shape (3,)."""
        if self.band_gain is not None:
            return np.asarray(self.band_gain, dtype=float)
        return np.full(3, self.gain)

    @property
    def time_constants(self) -> NDArray[np.float64]:
        """Engagement time constant of each band [s], shape (3,)."""
        if self.band_time_constant is not None:
            return np.asarray(self.band_time_constant, dtype=float)
        return np.full(3, self.time_constant)

    @property
    def gain(self) -> float:
        """Static brake torque per brake-motor ampere [N m/A]."""
        return (
            self.motor_constant
            * self.actuation_gain
            * math.expm1(self.friction_coefficient * self.wrap_angle)
            * self.drum_radius
        )


@dataclass(frozen=True)
class TransmissionParams:
    """A validated, immutable DVT parameter set.

    Attributes:
        name: set name.
        lumping: ``"thesis"`` (each carrier alone, one J_p per stage, sun damping relative to
            ring 1) or ``"complete"`` (planet count, orbital inertia, carrier + splined ring).
        stages: three stages, input side first.
        j_sun: sun shaft inertia incl. motor rotor [kg m^2].
        j_ring, j_carrier, j_planet: per stage [kg m^2]; ``j_planet`` is one planet's spin
            inertia (thesis lumping: the whole stage's).
        planet_mass [kg], orbit_radius [m]: per stage, used by the complete lumping only.
        b_sun, b_ring, b_carrier, b_planet: viscous damping [N m s].
        motor_constant: drive-motor torque constant K_M [N m/A].
        brake: band-brake data.
    """

    name: str
    description: str
    lumping: Lumping
    stages: tuple[Stage, Stage, Stage]
    j_sun: float
    j_ring: tuple[float, float, float]
    j_carrier: tuple[float, float, float]
    j_planet: tuple[float, float, float]
    planet_mass: tuple[float, float, float]
    orbit_radius: tuple[float, float, float]
    b_sun: float
    b_ring: tuple[float, float, float]
    b_carrier: tuple[float, float, float]
    b_planet: tuple[float, float, float]
    motor_constant: float
    brake: BrakeParams


def available_parameter_sets() -> list[str]:
    """Names of the bundled parameter sets."""
    return bundled_names("dvt_model", "param_sets")


def load_parameters(name_or_path: str | Path) -> TransmissionParams:
    """Load a bundled set by name (``thesis``) or a YAML file by path.

    Raises:
        ParameterError: unknown name, unreadable file, or invalid content.
    """
    data, source = read_yaml_setting(name_or_path, what="parameter set", error=ParameterError,
                                     package="dvt_model", directory="param_sets")
    return parse_parameters(data, source=source)


def _number(data: Mapping[str, Any], key: str, where: str, *, positive: bool = False,
            nonneg: bool = False, default: float | None = None) -> float:
    if key not in data:
        if default is not None:
            return default
        raise ParameterError(f"{where}{key}: missing")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ParameterError(f"{where}{key}: expected a number, got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ParameterError(f"{where}{key}: expected a finite number, got {value!r}")
    if positive and out <= 0.0:
        raise ParameterError(f"{where}{key}: expected a number > 0, got {value!r}")
    if nonneg and out < 0.0:
        raise ParameterError(f"{where}{key}: expected a number >= 0, got {value!r}")
    return out


def _triple(data: Mapping[str, Any], key: str, where: str, *, positive: bool = False,
            default: tuple[float, float, float] | None = None) -> tuple[float, float, float]:
    if key not in data:
        if default is not None:
            return default
        raise ParameterError(f"{where}{key}: missing")
    value = data[key]
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 3:
        raise ParameterError(f"{where}{key}: expected a list of 3 numbers, got {value!r}")
    items = {str(i): v for i, v in enumerate(value)}
    out = tuple(
        _number(items, str(i), f"{where}{key}[", positive=positive, nonneg=True)
        for i in range(3)
    )
    return (out[0], out[1], out[2])


def _known_keys(data: Mapping[str, Any], known: set[str], where: str) -> None:
    """Raise :class:`ParameterError` naming the first key of ``data`` not in ``known``."""
    unknown = sorted(set(map(str, data)) - known)
    if unknown:
        raise ParameterError(f"{where}{unknown[0]}: unknown key (expected one of "
                             f"{sorted(known)})")


def _mapping(data: Any, key: str, where: str) -> Mapping[str, Any]:
    value = data.get(key) if isinstance(data, Mapping) else None
    if not isinstance(value, Mapping):
        raise ParameterError(f"{where}{key}: expected a mapping, got {value!r}")
    return value


def parse_parameters(data: Any, source: str = "<mapping>") -> TransmissionParams:
    """Validate a parsed YAML mapping into :class:`TransmissionParams`.

    Raises:
        ParameterError: naming ``source``, the key path and the value.
    """
    w = f"{source}: "
    if not isinstance(data, Mapping):
        raise ParameterError(f"{w}expected a mapping at the top level, got {data!r}")
    _known_keys(data, {"name", "description", "lumping", "stages", "inertia", "damping",
                       "motor_constant", "brake", "planet_mass", "orbit_radius"}, w)
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name:
        raise ParameterError(f"{w}name: expected a non-empty string, got {name!r}")
    lumping = data.get("lumping", "complete")
    if lumping not in ("thesis", "complete"):
        raise ParameterError(f"{w}lumping: expected 'thesis' or 'complete', got {lumping!r}")
    stages_raw = data.get("stages")
    if not isinstance(stages_raw, Sequence) or isinstance(stages_raw, str) or len(stages_raw) != 3:
        raise ParameterError(f"{w}stages: expected a list of 3 stages, got {stages_raw!r}")
    stages: list[Stage] = []
    for k, st in enumerate(stages_raw):
        sw = f"{w}stages[{k}]."
        if not isinstance(st, Mapping):
            raise ParameterError(f"{w}stages[{k}]: expected a mapping, got {st!r}")
        vals: dict[str, int] = {}
        for key in ("sun", "planet", "ring", "planets"):
            v = st.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ParameterError(f"{sw}{key}: expected a positive integer, got {v!r}")
            vals[key] = v
        # profile-shifted gears may deviate a few teeth from sun + 2 * planet
        if abs(vals["ring"] - (vals["sun"] + 2 * vals["planet"])) > 5:
            raise ParameterError(
                f"{sw}ring: {vals['ring']} teeth cannot mesh with sun {vals['sun']} and planet "
                f"{vals['planet']} (expected about sun + 2*planet = "
                f"{vals['sun'] + 2 * vals['planet']})"
            )
        stages.append(Stage(**vals))
    inertia = _mapping(data, "inertia", w)
    damping = _mapping(data, "damping", w)
    iw, dw = f"{w}inertia.", f"{w}damping."
    zero3 = (0.0, 0.0, 0.0)
    brake_raw = _mapping(data, "brake", w)
    bw = f"{w}brake."
    _known_keys(brake_raw, {"motor_constant", "actuation_gain", "friction_coefficient",
                            "wrap_angle", "drum_radius", "time_constant", "static_factor",
                            "band_gain", "band_time_constant"}, bw)
    brake = BrakeParams(
        motor_constant=_number(brake_raw, "motor_constant", bw, positive=True),
        actuation_gain=_number(brake_raw, "actuation_gain", bw, positive=True),
        friction_coefficient=_number(brake_raw, "friction_coefficient", bw, positive=True),
        wrap_angle=_number(brake_raw, "wrap_angle", bw, positive=True),
        drum_radius=_number(brake_raw, "drum_radius", bw, positive=True),
        time_constant=_number(brake_raw, "time_constant", bw, positive=True),
        static_factor=_number(brake_raw, "static_factor", bw, positive=True, default=1.0),
        band_gain=(_triple(brake_raw, "band_gain", bw, positive=True)
                   if "band_gain" in brake_raw else None),
        band_time_constant=(_triple(brake_raw, "band_time_constant", bw, positive=True)
                            if "band_time_constant" in brake_raw else None),
    )
    params = TransmissionParams(
        name=name,
        description=str(data.get("description", "")),
        lumping=lumping,
        stages=(stages[0], stages[1], stages[2]),
        j_sun=_number(inertia, "sun", iw, positive=True),
        j_ring=_triple(inertia, "ring", iw),
        j_carrier=_triple(inertia, "carrier", iw, positive=True),
        j_planet=_triple(inertia, "planet", iw),
        planet_mass=_triple(data, "planet_mass", w, default=zero3),
        orbit_radius=_triple(data, "orbit_radius", w, default=zero3),
        b_sun=_number(damping, "sun", dw, nonneg=True),
        b_ring=_triple(damping, "ring", dw),
        b_carrier=_triple(damping, "carrier", dw),
        b_planet=_triple(damping, "planet", dw),
        motor_constant=_number(data, "motor_constant", w, positive=True),
        brake=brake,
    )
    if lumping == "complete" and "planet_mass" not in data:
        raise ParameterError(f"{w}planet_mass: missing (required by lumping 'complete')")
    return params
