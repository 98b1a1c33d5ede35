"""Candidate effects: named terms the augment loop may add to the simulated model.

Each effect is one class (:mod:`dvt_identify.effects.base` describes the model and the parts an
effect may have): it declares its vocabulary word, its parameters with their bounds and physical
constraints (:meth:`~dvt_identify.effects.base.Effect.build`), its simulation and scoring hooks
and the model-node effect term it pushes
(:meth:`~dvt_identify.effects.base.Effect.model_term`). Effects register themselves: every
:class:`~dvt_identify.effects.base.Effect` subclass that declares a ``name`` is in the registry
(:meth:`~dvt_identify.effects.base.Effect.__init_subclass__`), and this package imports every
module in it, so :data:`REGISTRY` (the classes by their ``order``) holds a class defined in a
new module here without any list being edited. :func:`make_effect` builds the first class of
the registry with the given name that accepts the ``where`` and options. Adding an effect is
adding one class (and its test) in a module here (``docs/effects.md``).

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

import importlib
import pkgutil
from collections.abc import Sequence
from dataclasses import replace

from dvt_identify.effects.backlash import Backlash, CompliantOutputBacklash, OutputBacklash
from dvt_identify.effects.base import (
    Array,
    BuildContext,
    Effect,
    ParamSpec,
    ScoringContext,
    SegmentView,
    Term,
    registered,
)
from dvt_identify.effects.brakes import BrakeEngagement, BrakeLockup, EngagementDeadTime
from dvt_identify.effects.friction import (
    AsymmetricFriction,
    CoulombFriction,
    StribeckFriction,
    Windage,
)
from dvt_identify.effects.periodic import PeriodicDisturbance
from dvt_identify.effects.position import GravityLoad, Unlisted, motion_unreadable
from dvt_identify.effects.sensors import (
    MeasurementDelay,
    SensorGain,
    SensorLag,
    SensorOffset,
    SensorQuantisation,
    SensorSaturation,
    SignBlindSensor,
)
from dvt_identify.errors import DescriptionError


def discover(path: Sequence[str] = tuple(__path__), prefix: str = f"{__name__}."
             ) -> tuple[type[Effect], ...]:
    """Import every module in the directories ``path`` (as ``prefix + name``): their effect
    classes register themselves on import; the registry then
    (:func:`~dvt_identify.effects.base.registered`)."""
    for module in pkgutil.iter_modules(list(path)):
        importlib.import_module(prefix + module.name)
    return registered()


REGISTRY: tuple[type[Effect], ...] = discover()
"""Every effect class; for a name shared by several, the first that accepts a ``where`` wins."""

VOCABULARY: tuple[str, ...] = tuple(dict.fromkeys(cls.name for cls in REGISTRY))
"""The effect names a description may use, in the contract's order."""


def make_effect(name: str, where: str, state_names: Sequence[str], input_names: Sequence[str],
                force_unit: str = "", speed_unit: str = "", member: Sequence[float] | None = None,
                options: dict[str, object] | None = None, suffix: str = "",
                output_names: Sequence[str] = (), output_states: Sequence[str] = ()
                ) -> Effect:
    """Build a candidate effect: the first class of :data:`REGISTRY` named ``name`` that
    accepts ``where`` and the options.

    Args:
        name: effect name from :data:`VOCABULARY`.
        where: a state/output name (force and output effects), or an input name (``backlash``,
            ``brake_engagement``); ``brake_lockup`` acts on a member and names its brake input in
            ``options['input']``.
        state_names, input_names: the structure's names.
        force_unit, speed_unit: units for parameter reports.
        member: explicit member vector over the states, shape (nx,) (default: the unit vector
            of ``where``).
        options: effect options (see each class).
        suffix: appended to parameter names to keep them unique (e.g. ``_sun_shaft``).
        output_names: the measured outputs of a structure with hidden states (empty: the
            states); output effects act on these.
        output_states: the state each of ``output_names`` reads (same length; empty: the
            outputs are the states): the effect's :attr:`Effect.readout`.

    Raises:
        DescriptionError: unknown effect, state or input name, bad option.
    """
    ctx = BuildContext(name=name, where=where, state_names=tuple(state_names),
                       input_names=tuple(input_names), force_unit=force_unit,
                       speed_unit=speed_unit,
                       member=None if member is None else tuple(float(v) for v in member),
                       options=dict(options or {}), suffix=suffix,
                       output_names=tuple(output_names))
    named = [cls for cls in REGISTRY if cls.name == name]
    if not named:
        raise DescriptionError(f"candidate effect {name!r}: unknown (known: "
                               f"{', '.join(VOCABULARY)})")
    cls = next((c for c in named if c.accepts(ctx)), named[-1])
    effect = cls.build(ctx)
    if output_states:
        unknown = [s for s in output_states if s not in ctx.state_names]
        if unknown or len(output_states) != len(ctx.output_names):
            raise DescriptionError(f"candidate {name}@{where}: output_states {list(output_states)}"
                                   f": expected one state of {list(ctx.state_names)} per output "
                                   f"{list(ctx.output_names)}")
        effect = replace(effect, readout=tuple(ctx.state_names.index(s) for s in output_states))
        if effect.reads_motion() and effect.member is not None:
            why = motion_unreadable(effect.member, effect.readout)
            if why is not None:
                raise DescriptionError(
                    f"candidate {name}@{where}: is evaluated on the member's measured motion, "
                    f"but {why}; measured: "
                    + ", ".join(f"{o} = {s}" for o, s in zip(ctx.output_names, output_states,
                                                            strict=True)))
    return effect


__all__ = [
    "REGISTRY", "VOCABULARY", "Array", "AsymmetricFriction", "Backlash", "BrakeEngagement",
    "BrakeLockup", "BuildContext", "CompliantOutputBacklash", "CoulombFriction", "Effect",
    "EngagementDeadTime", "GravityLoad", "MeasurementDelay", "OutputBacklash", "ParamSpec",
    "PeriodicDisturbance", "ScoringContext", "SegmentView", "SensorGain", "SensorLag",
    "SensorOffset", "SensorQuantisation", "SensorSaturation", "SignBlindSensor", "StribeckFriction",
    "Term", "Unlisted", "Windage", "discover", "make_effect",
]
