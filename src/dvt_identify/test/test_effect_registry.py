"""The effect registry: one class per effect, each declaring its parameters, bounds, the class
a ``where`` builds and the model-node term it pushes (checked against the contract)."""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

import numpy as np
import pytest

from dvt_identify import simloop
from dvt_identify.effects import (
    REGISTRY,
    VOCABULARY,
    Backlash,
    BrakeEngagement,
    BrakeLockup,
    CompliantOutputBacklash,
    Effect,
    EngagementDeadTime,
    OutputBacklash,
    make_effect,
)
from dvt_identify.push import INPUT_ALIASES
from dvt_model import friction
from dvt_model.contract import validate_term

STATES = ["sun_shaft", "carrier3"]
INPUTS = ["motor", "brake1", "brake2"]
# one description entry per class of the registry: (name, where, options)
ENTRIES: list[tuple[str, str, dict[str, object]]] = [
    ("coulomb_friction", "sun_shaft", {}),
    ("stribeck_friction", "sun_shaft", {"vs": 2.0}),
    ("windage", "carrier3", {}),
    ("backlash", "carrier3", {"compliant": True}),
    ("backlash", "carrier3", {}),
    ("backlash", "motor", {}),
    ("measurement_delay", "carrier3", {"max_delay": 0.01}),
    ("brake_engagement", "brakes", {"dead_time": True, "inputs": ["brake1", "brake2"]}),
    ("brake_engagement", "brake1", {}),
    ("brake_lockup", "sun_shaft", {"input": "brake2"}),
    ("sensor_gain", "carrier3", {}),
    ("periodic_disturbance", "sun_shaft", {"orders": [3.0]}),
    ("asymmetric_friction", "carrier3", {}),
    ("sign_blind", "carrier3", {}),
    ("sensor_lag", "carrier3", {"max_tau": 0.05}),
    ("sensor_saturation", "carrier3", {}),
    ("sensor_quantisation", "carrier3", {}),
    ("sensor_offset", "carrier3", {}),
    ("gravity_load", "carrier3", {"reductions": [20]}),
    ("unlisted", "carrier3", {}),
]


def _build(name: str, where: str, opts: dict[str, object]) -> Effect:
    return make_effect(name, where, STATES, INPUTS, "N m", "rad/s", options=opts)


def test_every_class_of_the_registry_is_built_for_its_entry() -> None:
    built = [type(_build(*e)) for e in ENTRIES]
    assert built == list(REGISTRY)
    assert VOCABULARY == ("coulomb_friction", "stribeck_friction", "windage", "backlash",
                          "measurement_delay", "brake_engagement", "brake_lockup", "sensor_gain",
                          "periodic_disturbance", "asymmetric_friction", "sign_blind",
                          "sensor_lag", "sensor_saturation", "sensor_quantisation", "sensor_offset",
                          "gravity_load", "unlisted")
    assert isinstance(_build("backlash", "carrier3", {"compliant": True}), CompliantOutputBacklash)
    assert isinstance(_build("backlash", "carrier3", {}), OutputBacklash)
    assert isinstance(_build("backlash", "motor", {"compliant": True}), Backlash)
    assert isinstance(_build("brake_engagement", "brake1", {"dead_time": True}),
                      EngagementDeadTime)
    assert type(_build("brake_engagement", "brake1", {})) is BrakeEngagement


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda e: f"{e[0]}@{e[1]}")
def test_parameters_start_at_their_null_within_physical_bounds(
        entry: tuple[str, str, dict[str, object]]) -> None:
    eff = _build(*entry)
    assert eff.params
    for spec in eff.params:
        assert spec.lower <= spec.null <= spec.upper, spec
        assert spec.initial == spec.null, spec
    lows = {s.name: s.lower for s in eff.params}
    for name in ("Fc", "Fs", "Cw", "delta", "gap", "band_gain", "band_time_constant", "td",
                 "delay"):
        if name in lows:
            assert lows[name] == 0.0, (name, lows[name])  # friction, drag, play, delay >= 0
    if "gain" in lows:
        assert lows["gain"] > -1.0  # a sensor scale 1 + gain stays positive


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda e: f"{e[0]}@{e[1]}")
def test_the_model_term_is_admissible_or_the_reason_is_given(
        entry: tuple[str, str, dict[str, object]]) -> None:
    eff = _build(*entry)
    p = np.clip([s.initial + 0.01 for s in eff.params], [s.lower for s in eff.params],
                [s.upper for s in eff.params])
    term = eff.model_term(p, STATES)
    if term is None:
        assert eff.why_no_term(STATES)
        return
    if term.get("input"):  # model input name -> the node's current, as the push maps it
        term["input"] = INPUT_ALIASES.get(term["input"], term["input"])
    checked = validate_term(term, f"{eff.label()}", n_outputs=len(STATES))
    assert checked["kind"] == term["kind"]
    for key, value in term.items():
        assert checked[key] == value


def test_band_effects_carry_the_model_node_parameter_name() -> None:
    for cls, entry in ((BrakeLockup, ENTRIES[9]), (BrakeEngagement, ENTRIES[8])):
        eff = make_effect(*entry[:2], STATES, INPUTS, options=entry[2], suffix="_x")
        assert isinstance(eff, cls) and cls.band_parameter is not None
        assert eff.params[0].name == f"{cls.band_parameter}_x"
    assert all(c.band_parameter is None for c in REGISTRY
               if c not in (BrakeLockup, BrakeEngagement))


def test_compiled_smooth_laws_are_the_model_friction_laws() -> None:
    """Compiled, they equal the interpreted laws of dvt_model.friction (up to the last bit of
    a compiled exp)."""
    for v in np.linspace(-30.0, 30.0, 241).tolist():
        cases = ((simloop.STRIBECK, 0.7, 2.5, 0.0, friction.stribeck(v, 0.7, 2.5, 0.0)),
                 (simloop.STRIBECK, 0.7, 2.5, 0.3, friction.stribeck(v, 0.7, 2.5, 0.3)),
                 (simloop.WINDAGE, 1e-3, 0.0, 0.0, friction.windage(v, 1e-3)),
                 (simloop.ABS_VISCOUS, 0.02, 0.0, 0.0, friction.abs_viscous(v, 0.02)),
                 (simloop.COULOMB, 0.4, 0.5, 0.0, friction.coulomb(v, 0.4, 0.0, 0.5)))
        for kind, p0, p1, p2, law in cases:
            assert simloop.smooth_value(kind, p0, p1, p2, v) == pytest.approx(
                -law, rel=1e-12, abs=0.0)


_NEW_MODULE = '''
from dataclasses import dataclass
import math
from dvt_identify.effects.base import BuildContext, Effect, ParamSpec


@dataclass
class TanhDragForTest(Effect):
    name = "tanh_drag_for_test"
    state_dependent = True

    @classmethod
    def build(cls, ctx: BuildContext) -> Effect:
        return cls(where=ctx.where, params=(ParamSpec("Cd" + ctx.suffix, 0.0, 0.0, math.inf,
                                                      ctx.force_unit),),
                   member=ctx.member_vector(), options=dict(ctx.options))
'''


def test_an_effect_in_a_new_module_registers_itself(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A class in a module nobody lists is found by the package's discovery and comes after
    the suite's classes; every class of every module of the package is in the registry."""
    from dvt_identify import effects
    from dvt_identify.effects import base

    for info in pkgutil.iter_modules(effects.__path__):
        module = importlib.import_module(f"dvt_identify.effects.{info.name}")
        for obj in vars(module).values():
            if (isinstance(obj, type) and issubclass(obj, Effect) and obj is not Effect
                    and "name" in obj.__dict__
                    and obj.__module__ == module.__name__):
                assert obj in REGISTRY, obj
    (tmp_path / "drag_for_test.py").write_text(_NEW_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        found = effects.discover([str(tmp_path)], prefix="")
        assert found[:-1] == REGISTRY  # the suite's classes first, in their order
        new = found[-1]
        assert new.__name__ == "TanhDragForTest" and new.name == "tanh_drag_for_test"
        ctx = effects.BuildContext(name=new.name, where="carrier3", state_names=tuple(STATES),
                                   input_names=tuple(INPUTS), force_unit="N m")
        assert new.accepts(ctx) and new.build(ctx).params[0].name == "Cd"
    finally:
        base._REGISTERED[:] = [c for c in base._REGISTERED if c.name != "tanh_drag_for_test"]
        sys.modules.pop("drag_for_test", None)
    assert base.registered() == REGISTRY
