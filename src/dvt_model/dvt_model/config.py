"""The model node's configuration from its parameters (pure: no rclpy).

:func:`check_parameters` validates a (partial) set of model-node parameter values against the
contract (:data:`dvt_model.contract.MODEL_PARAMETERS`) and the physics: the node refuses what
it refuses, and the identifier's push checks its values with it before writing them, so the
push cannot write what the node would refuse. :func:`build_predictor` turns valid values into
the running :class:`~dvt_model.predictor.Predictor`.

Admissibility beyond each parameter's own type, length and range:

- ``M``: symmetric positive definite, smallest eigenvalue at least
  :data:`~dvt_model.contract.M_MIN_EIGENVALUE` [kg m^2], condition number at most
  :data:`~dvt_model.contract.M_MAX_CONDITION`.
- ``D``: symmetric positive semi-definite (damping dissipates, never feeds energy).
- ``A``: stable, every eigenvalue with a negative real part; ``A`` and ``B`` both given or
  both empty; the linear model carries no force terms (they need the physics).
- ``effects``: :func:`dvt_model.contract.validate_effects` (physically admissible terms, at
  most :data:`~dvt_model.contract.MAX_EFFECT_TERMS`); the speed-dependent terms become the
  hybrid model's ``extra_force``, the angle-dependent ones (``gravity``, ``angle_periodic``,
  ``library``) its ``angle_input_force`` (:mod:`dvt_model.terms`).
- ``params``: a bundled parameter set or a readable, valid YAML file.
- ``load``: ``none``, a preset of :mod:`dvt_model.load` or a readable, valid load YAML; not
  with the linear model (the load acts through the physics).
- ``detector.*``: the change detector's settings (:func:`detector_config`), checked together
  by :meth:`dvt_model.detect.DetectorConfig.validated` (e.g. a reference window of at least 100
  samples).

Every error is a :class:`~dvt_model.errors.ContractError`,
:class:`~dvt_model.errors.ModelError` or :class:`~dvt_model.errors.ParameterError` whose message
starts with the parameter's name and gives the value and what is admissible.

A change of the running node's parameters is one transaction (:func:`model_transaction`): the
whole set of changed values is validated together against the current ones and turned into one
predictor, or refused as a whole (the first bad value named); :func:`partner_clears` is the
A/B rule (emptying one of them empties the other in the same transaction). The model node
(:mod:`dvt_model.node`) applies an accepted transaction at once: one predictor swap, one
change-detector reset.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
from collections.abc import Callable, Mapping, Sized
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from dvt_model.contract import (
    CURRENT_NAMES,
    DETECTOR_PARAMETERS,
    DETECTOR_PREFIX,
    M_MAX_CONDITION,
    M_MIN_EIGENVALUE,
    MODEL_PARAMETERS,
    SPEED_NAMES,
    short_repr,
)
from dvt_model.detect import DetectorConfig
from dvt_model.dynamics import RigidModel, rigid_model
from dvt_model.errors import ContractError, DvtModelError, ModelError, ParameterError
from dvt_model.hybrid import CROSSING_GRID, HybridModel
from dvt_model.linear import LinearModel
from dvt_model.load import JointLoad, load_joint_load
from dvt_model.params import BrakeParams, TransmissionParams, load_parameters
from dvt_model.predictor import Predictor
from dvt_model.terms import Terms, parse_terms

Array = NDArray[np.float64]

_SYMMETRY_RTOL = 1e-9
"""Relative tolerance of the symmetry checks (the push writes the off-diagonal entry twice)."""
_PSD_RTOL = 1e-12
"""An eigenvalue of D down to ``-_PSD_RTOL * max |eigenvalue|`` counts as zero (round-off)."""


def defaults() -> dict[str, Any]:
    """Every model-node parameter's default value, by name."""
    return {name: spec.default for name, spec in MODEL_PARAMETERS.items()}


@dataclass(frozen=True)
class ModelConfig:
    """Validated model-node configuration.

    Attributes:
        params: the parameter set (``params``).
        rigid: its rigid model with the ``M``, ``D``, ``motor_constant`` overrides applied.
        brake: its band data with the ``band_gain``/``band_time_constant`` overrides applied.
        linear: ``(A (2, 2) [1/s], B (2, 2) or (2, 4))`` of the linear model, or ``None``.
        terms: the effect terms.
        mode, reanchor_period [s], gap_reset [s], gap_reanchor [s]: the predictor's settings.
        changes: names of the overrides applied to the parameter set.
        load: the joint load on carrier 3 (``load``), or ``None``.
        detector: the change detector's settings, or ``None`` (``detector.enabled`` false).
    """

    params: TransmissionParams
    rigid: RigidModel
    brake: BrakeParams
    linear: tuple[Array, Array] | None
    terms: Terms
    mode: str
    reanchor_period: float
    gap_reset: float
    gap_reanchor: float
    changes: tuple[str, ...]
    load: JointLoad | None = None
    detector: DetectorSetup | None = None


def _plain(value: Any) -> Any:
    """numpy arrays and scalars as plain Python values (the contract checks Python types)."""
    if isinstance(value, np.ndarray):
        return value.reshape(-1).tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def normalise(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` merged onto the defaults, each checked against its contract entry (type,
    length, range) and normalised (str, float, tuple of floats).

    Raises:
        ContractError: an unknown name, or a value of the wrong type, length or range.
    """
    unknown = sorted(str(k) for k in values if k not in MODEL_PARAMETERS)
    if unknown:
        raise ContractError(f"{unknown[0]}: unknown parameter of the model node (expected one "
                            f"of {list(MODEL_PARAMETERS)})")
    out = defaults()
    for name, value in values.items():
        out[name] = MODEL_PARAMETERS[name].check(_plain(value))
    return out


def _matrix(name: str, raw: tuple[float, ...], cols: int = 2) -> Array:
    return np.asarray(raw, dtype=float).reshape(2, cols)


def _check_symmetric(name: str, mat: Array) -> None:
    scale = float(np.max(np.abs(mat)))
    if abs(mat[0, 1] - mat[1, 0]) > _SYMMETRY_RTOL * scale:
        raise ModelError(f"{name}: {mat.reshape(-1).tolist()} is not admissible: expected a "
                         f"symmetric matrix (entries 1 and 2 equal)")


def check_mass(raw: tuple[float, ...]) -> Array:
    """``M`` (4 values row-major) as a (2, 2) array [kg m^2] if admissible, else ModelError."""
    M = _matrix("M", raw)
    _check_symmetric("M", M)
    eig = np.linalg.eigvalsh(M)
    if eig[0] < M_MIN_EIGENVALUE:
        raise ModelError(
            f"M: {M.reshape(-1).tolist()} is not admissible: expected symmetric positive "
            f"definite with smallest eigenvalue >= {M_MIN_EIGENVALUE:g} kg m^2, got eigenvalues "
            f"{eig.tolist()}" + (" (not positive definite)" if eig[0] <= 0.0 else ""))
    cond = float(eig[1] / eig[0])
    if cond > M_MAX_CONDITION:
        raise ModelError(f"M: {M.reshape(-1).tolist()} is not admissible: condition number "
                         f"{cond:.3g}, at most {M_MAX_CONDITION:g} allowed")
    return M


def check_damping(raw: tuple[float, ...]) -> Array:
    """``D`` (4 values row-major) as a (2, 2) array [N m s] if admissible, else ModelError."""
    D = _matrix("D", raw)
    _check_symmetric("D", D)
    eig = np.linalg.eigvalsh(D)
    if eig[0] < -_PSD_RTOL * max(float(np.max(np.abs(eig))), 1e-300):
        raise ModelError(f"D: {D.reshape(-1).tolist()} is not admissible: expected symmetric "
                         f"positive semi-definite (damping dissipates energy), got eigenvalues "
                         f"{eig.tolist()}")
    return D


def check_linear(a_raw: tuple[float, ...], b_raw: tuple[float, ...]) -> tuple[Array, Array]:
    """``(A (2, 2), B (2, m))`` of the linear model if admissible, else ModelError."""
    A = _matrix("A", a_raw)
    B = _matrix("B", b_raw, len(b_raw) // 2)
    eig = np.linalg.eigvals(A)
    if not np.all(eig.real < 0.0):
        shown = [complex(e) if e.imag else float(e.real) for e in eig]
        raise ModelError(f"A: {A.reshape(-1).tolist()} is not admissible: expected a stable "
                         f"matrix (every eigenvalue with negative real part), got eigenvalues "
                         f"{shown}")
    return A, B


def _load(name: str) -> TransmissionParams:
    try:
        return load_parameters(name)
    except DvtModelError as exc:
        raise ContractError(f"params: {short_repr(name)}: {exc}") from exc
    except (OSError, ValueError) as exc:  # e.g. a path too long for the file system
        raise ContractError(f"params: {short_repr(name)}: cannot load: {exc}") from exc


def _joint_load(name: str) -> JointLoad | None:
    try:
        return load_joint_load(name)
    except DvtModelError as exc:
        text = str(exc)
        raise ContractError(text if text.startswith("load:") else
                            f"load: {short_repr(name)}: {text}") from exc
    except (OSError, ValueError) as exc:
        raise ContractError(f"load: {short_repr(name)}: cannot load: {exc}") from exc


@dataclass(frozen=True)
class DetectorSetup:
    """How the model node runs its change detector.

    Attributes:
        block: residual samples averaged into one detector sample (1: every sample).
        config: the detector's settings at the block rate (``sample_rate_hz`` is
            ``detector.sample_rate_hz / block``).
        settle_s: wait after an anchor of the model before learning [s].
        colour_file: the file that carries the colour between runs ("": none;
            :class:`dvt_model.detect.ColourKeeper`).
    """

    block: int
    config: DetectorConfig
    settle_s: float = 3.0
    colour_file: str = ""


def _detector(v: Mapping[str, Any]) -> DetectorSetup | None:
    """The detector's settings from normalised values (``None`` when disabled)."""
    p = DETECTOR_PREFIX + "."
    rate = float(v[p + "sample_rate_hz"])
    block = max(1, round(float(v[p + "block_s"]) * rate))
    cfg = DetectorConfig(
        sample_rate_hz=rate / block, learn_s=float(v[p + "learn_s"]),
        shift_sigma=float(v[p + "shift_sigma"]),
        false_alarm_period_s=float(v[p + "false_alarm_period_s"]),
        max_gap_s=float(v[p + "max_gap_s"]), max_phi=float(v[p + "max_phi"]),
        colour_s=float(v[p + "colour_s"]), colour_lag_s=float(v[p + "colour_lag_s"])).validated()
    if cfg.max_gap_s <= 1.0 / cfg.sample_rate_hz:
        raise ParameterError(f"{p}max_gap_s: expected more than one detector sample period "
                             f"({block / rate:g} s with {p}block_s = {v[p + 'block_s']:g} s), "
                             f"got {cfg.max_gap_s:g}")
    return (DetectorSetup(block=block, config=cfg, settle_s=float(v[p + "settle_s"]),
                          colour_file=str(v[p + "colour_file"]))
            if v[p + "enabled"] else None)


def model_key(values: Mapping[str, Any]) -> str:
    """A short digest of the model-node parameters other than the detector's (merged onto the
    defaults): the key under which a carried colour belongs to the model whose residual it
    is (:class:`dvt_model.detect.ColourKeeper`). A file named by ``params`` or ``load``
    counts by its name, not its content."""
    v = normalise(values)
    model = {k: v[k] for k in sorted(v) if not k.startswith(DETECTOR_PREFIX + ".")}
    text = json.dumps(model, sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def detector_config(values: Mapping[str, Any]) -> DetectorSetup | None:
    """The change detector's settings from model-node parameter values (merged onto the
    defaults), or ``None`` when ``detector.enabled`` is false.

    Raises:
        ContractError: a ``detector.*`` value of the wrong type or out of its range.
        ParameterError: the values together are not admissible (e.g. fewer than 100 samples in
            the reference window); the message names ``detector.<name>`` and the value.
    """
    return _detector(normalise(values))


def resolve(values: Mapping[str, Any]) -> ModelConfig:
    """Validate model-node parameter values (merged onto the defaults) into a configuration.

    Raises:
        ContractError, ModelError: naming the parameter, the value and what is admissible.
    """
    v = normalise(values)
    detector = _detector(v)
    params = _load(str(v["params"]))
    rigid = rigid_model(params)
    changes: dict[str, Any] = {}
    if v["M"]:
        changes["M"] = check_mass(v["M"])
    if v["D"]:
        changes["D"] = check_damping(v["D"])
    if v["motor_constant"] > 0.0:
        changes["motor_constant"] = float(v["motor_constant"])
    if changes:
        rigid = dataclasses.replace(rigid, **changes)
    brake = params.brake
    band_gain, band_tau = v["band_gain"] or None, v["band_time_constant"] or None
    if band_gain is not None or band_tau is not None:
        brake = dataclasses.replace(brake, band_gain=band_gain, band_time_constant=band_tau)
        changes.update({k: True for k in ("band_gain", "band_time_constant") if v[k]})
    a_raw, b_raw = v["A"], v["B"]
    linear: tuple[Array, Array] | None = None
    if a_raw or b_raw:
        if not (a_raw and b_raw):
            missing = "B" if a_raw else "A"
            raise ModelError(f"{'A' if a_raw else 'B'}: A and B: give both (4 and 4 or 8 "
                             f"values) or neither; {missing} is empty (set both at once with "
                             "set_parameters_atomically)")
        linear = check_linear(a_raw, b_raw)
    terms = parse_terms(str(v["effects"]))
    if linear is not None and (terms.forces or terms.has_angle_terms):
        raise ModelError("effects: force terms need the physical model (clear A and B)")
    load = _joint_load(str(v["load"]))
    if linear is not None and load is not None:
        raise ModelError(f"load: {short_repr(v['load'])} needs the physical model (clear A "
                         "and B, or set load to none)")
    return ModelConfig(params=params, rigid=rigid, brake=brake, linear=linear, terms=terms,
                       mode=str(v["mode"]), reanchor_period=float(v["reanchor_period"]),
                       gap_reset=float(v["gap_reset"]),
                       gap_reanchor=float(v["gap_reanchor"]), changes=tuple(sorted(changes)),
                       load=load, detector=detector)


def check_parameters(values: Mapping[str, Any]) -> None:
    """Validate a (partial) set of model-node parameter values merged onto the defaults.

    What the model node refuses, this refuses (the identifier's push calls it before writing).

    Raises:
        ContractError, ModelError (both :class:`~dvt_model.errors.DvtModelError`): the message
            starts with the parameter's name and gives the value and what is admissible.
    """
    resolve(values)


def build_predictor(values: Mapping[str, Any]) -> tuple[Predictor, str]:
    """Validate parameter values (merged onto the defaults) and build the node's predictor.

    Returns:
        The predictor and a one-line description of its model.

    Raises:
        ContractError, ModelError: as :func:`check_parameters`.
    """
    cfg = resolve(values)
    terms = cfg.terms
    model: HybridModel | LinearModel
    if cfg.linear is not None:
        A, B = cfg.linear
        model = LinearModel(A, B)
        desc = f"linear A,B (2x{B.shape[1]})"
    else:
        # a ring's zero crossing splits a step on a grid: cached splits, no per-sample expm
        model = HybridModel(cfg.rigid, cfg.brake,
                            extra_force=terms.extra_force if terms.forces else None,
                            load=cfg.load,
                            angle_input_force=(terms.angle_force if terms.has_angle_terms
                                               else None),
                            crossing_grid=CROSSING_GRID)
        desc = f"hybrid physics '{cfg.params.name}'" + (
            f" with {list(cfg.changes)}" if cfg.changes else "")
        if cfg.load is not None:
            desc += f", load '{cfg.load.name}'"
    if not terms.empty:
        desc += f" + {len(terms.forces)} force term(s)"
        if terms.has_angle_terms:
            desc += f", {len(terms.angle_terms)} angle term(s)"
        desc += f", delay {terms.delay:g} s"
        if terms.has_lost_motion:
            zones = [n for n, d in zip(CURRENT_NAMES, terms.dead_zones, strict=True) if d]
            plays = [f"{t['kind']} on {SPEED_NAMES[i]}" for i, t in enumerate(terms.plays)
                     if t is not None]
            desc += ", lost motion: " + ", ".join(
                ([f"dead zone on {', '.join(zones)}"] if zones else []) + plays)
    predictor = Predictor(model, cfg.brake, mode="reanchor" if cfg.mode == "reanchor"
                          else "simulate", reanchor_period=cfg.reanchor_period,
                          gap_reset=cfg.gap_reset,
                          gap_reanchor=cfg.gap_reanchor, output_delay=terms.delay,
                          output_gain=terms.gains, input_dead_zone=terms.dead_zones,
                          output_maps=terms.output_maps())
    return predictor, desc


# ------------------------------------------------------------------- parameter transactions
class _Unset(enum.Enum):
    UNSET = "unset"


UNSET: Final = _Unset.UNSET
"""The value of a parameter in a change set that asks to unset it (ROS ``PARAMETER_NOT_SET``);
a model parameter cannot be unset."""
LINEAR_PAIR: Final = ("A", "B")
"""The linear model's parameters, given together or both empty."""


def _is_empty(value: Any) -> bool:
    """``None`` (not set) or an empty list; a string or a number is not empty."""
    return value is None or (isinstance(value, Sized) and not isinstance(value, str | bytes)
                             and len(value) == 0)


def partner_clears(current: Mapping[str, Any], changes: Mapping[str, Any]) -> tuple[str, ...]:
    """The A/B rule: names to empty together with ``changes``.

    Emptying ``A`` (or ``B``) while the other is set and not in the same change set clears the
    linear model: the other is emptied in the same transaction (so that no reader ever sees
    one without the other).

    Args:
        current: the node's current model-parameter values (``None``: not set).
        changes: the change set, name -> new value (:data:`UNSET` to unset).
    """
    a, b = LINEAR_PAIR
    out: list[str] = []
    for key, other in ((a, b), (b, a)):
        if (key in changes and changes[key] is not UNSET and _is_empty(changes[key])
                and other not in changes and not _is_empty(current.get(other))):
            out.append(other)
    return tuple(out)


@dataclass(frozen=True)
class ModelTransaction:
    """A set of model-node parameter changes validated together, ready to apply at once.

    Attributes:
        changed: the model parameters whose value the set changes, in request order, then
            the partner emptied by the A/B rule (:func:`partner_clears`); a member that
            repeats its value in use is not listed.
        values: every model parameter's value after the change (``None``: not set).
        predictor: the one predictor built for ``values``.
        description: a one-line description of its model.
    """

    changed: tuple[str, ...]
    values: dict[str, Any]
    predictor: Predictor
    description: str


def _never_declared(name: str) -> bool:
    return False


def model_transaction(current: Mapping[str, Any], changes: Mapping[str, Any],
                      is_declared: Callable[[str], bool] = _never_declared
                      ) -> ModelTransaction | None:
    """Validate a set of parameter changes of the model node together, as one transaction.

    Each name is checked in order (a ``detector.*`` parameter is read-only, a model parameter
    cannot be unset, a name that is neither a model parameter nor ``is_declared`` is unknown),
    then the changed model parameters merged onto ``current`` (with the A/B rule's partner,
    :func:`partner_clears`) are validated and built into one predictor
    (:func:`build_predictor`). Pure: nothing is applied; a refusal of any member refuses the
    whole set.

    Args:
        current: the node's current model-parameter values by name (``None``: not set).
        changes: name -> new value, in request order (:data:`UNSET` to unset).
        is_declared: whether the node has another (not model) parameter of this name, e.g.
            ``use_sim_time``; such changes pass unchecked.

    Returns:
        The transaction, or ``None`` when the set changes no model parameter's value (a set
        that only repeats the values in use, such as a push sent again after its answer was
        lost, is no model change: no predictor swap, no detector reset).

    Raises:
        ContractError, ModelError, ParameterError (all :class:`DvtModelError`): the message
            starts with the refused parameter's name and gives the value and what is
            admissible. The numeric checks may also raise ``ValueError``/``ArithmeticError``
            on values no contract check foresaw; the node refuses those too.
    """
    model: dict[str, Any] = {}
    for name, value in changes.items():
        if name in DETECTOR_PARAMETERS:
            raise ContractError(f"{name}: read-only (the detector's settings are fixed at "
                                "start; restart the node to change them), got "
                                f"{short_repr(value)}")
        if name in MODEL_PARAMETERS:
            if value is UNSET:
                raise ContractError(f"{name}: cannot be unset: expected "
                                    f"{MODEL_PARAMETERS[name].admissible}")
            model[name] = value
        elif not is_declared(name):
            shown = name if len(name) <= 100 else short_repr(name)
            raise ContractError(f"{shown}: unknown parameter of the model node (expected one "
                                f"of {list(MODEL_PARAMETERS)})")
    cleared = partner_clears(current, model)
    values = {**current, **model, **dict.fromkeys(cleared)}
    changed = tuple(n for n in (*model, *cleared) if not same_value(values[n], current.get(n)))
    if not changed:  # nothing new (a resent push, a rollback to the model in use)
        return None
    predictor, description = build_predictor(values)
    return ModelTransaction(changed=changed, values=values, predictor=predictor,
                            description=description)


def same_value(new: Any, old: Any) -> bool:
    """Whether a model parameter's ``new`` value equals its ``old`` one: both unset or empty,
    equal strings, or numbers / number lists of one shape with equal elements (exact: a value
    that differs in its last bit is a change)."""
    if _is_empty(new) or _is_empty(old):
        return _is_empty(new) and _is_empty(old)
    if isinstance(new, str | bytes) or isinstance(old, str | bytes):
        return bool(type(new) is type(old) and new == old)
    try:
        a, b = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.shape == b.shape and bool(np.array_equal(a, b))
