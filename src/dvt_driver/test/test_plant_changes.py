"""A plant that changes while it runs: the schedule (pure), its presets, the plant applying it,
the runtime change options of ``dvt-plant`` and the truth it writes."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from dvt_driver.errors import DvtDriverError, HiddenEffectsError
from dvt_driver.link.protocol import Command, Hello, Mode
from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.hidden import (
    Change,
    available_presets,
    changes_from_spec,
    load_hidden,
    parse_hidden,
    scheduled_values,
)
from dvt_driver.plant.server import parse_change_at
from dvt_model.params import load_parameters

PARAMS = load_parameters("physical")


def test_schedule_steps_and_ramps() -> None:
    h = parse_hidden({"coulomb": {"sun": 0.05, "carrier3": 0.2}, "changes": [
        {"at": 20.0, "ramp": 10.0, "coulomb": {"carrier3": 0.4}, "damping_scale": 0.5},
        {"at": 5.0, "windage": {"sun": 1e-6}, "load": "arm-payload"},
    ]}, source="t")
    v = scheduled_values(h, 4.999)
    assert (v.coulomb, v.windage, v.damping_scale, v.load, v.started) == (
        {"sun": 0.05, "carrier3": 0.2}, {}, 1.0, None, 0)
    v = scheduled_values(h, 5.0)  # in order of 'at', not of the list
    assert v.windage == {"sun": 1e-6} and v.load == "arm-payload" and v.started == 1
    v = scheduled_values(h, 25.0)  # half-way through the ramp
    assert v.ramping and v.coulomb["carrier3"] == pytest.approx(0.3)
    assert v.coulomb["sun"] == 0.05 and v.damping_scale == pytest.approx(0.75)
    v = scheduled_values(h, 100.0)
    assert not v.ramping and v.coulomb["carrier3"] == pytest.approx(0.4)
    assert v.damping_scale == pytest.approx(0.5) and v.started == 2
    # the schedule round-trips through the YAML mapping (truth.yaml)
    again = parse_hidden(h.to_mapping(), source="again")
    assert again.changes == h.changes and again.coulomb == h.coulomb


@pytest.mark.parametrize(("data", "match"), [
    ({"changes": {"at": 1.0}}, r"t: changes: expected a list"),
    ({"changes": [{"coulomb": {"sun": 0.1}}]}, r"changes\[0\]\.at: missing"),
    ({"changes": [{"at": -1.0, "coulomb": {"sun": 0.1}}]}, r"changes\[0\]\.at: .*>= 0"),
    ({"changes": [{"at": 1.0}]}, r"changes\[0\]: changes nothing"),
    ({"changes": [{"at": 1.0, "coulomb": {"sunn": 0.1}}]}, r"changes\[0\]\.coulomb\.sunn: unknown"),
    ({"changes": [{"at": 1.0, "damping_scale": 11.0}]}, r"damping_scale: .*<= 10"),
    ({"changes": [{"at": 1.0, "load": "piano"}]}, r"changes\[0\]\.load: "),
    ({"changes": [{"at": 1.0, "viscous": 0.1}]}, r"changes\[0\]\.viscous: unknown key"),
    ({"damping_scale": -0.5}, r"t: damping_scale: expected a number >= 0"),
])
def test_schedule_errors_name_key_and_value(data: dict, match: str) -> None:
    with pytest.raises(HiddenEffectsError, match=match):
        parse_hidden(data, source="t")


def test_changing_presets_load() -> None:
    for name in ("wear", "oil_warmup", "payload_added", "friction_step"):
        assert name in available_presets()
        h = load_hidden(name)
        assert h.changes, name
    assert load_hidden("wear").changes[0].ramp == 60.0
    assert load_hidden("payload_added").changes[0].load == "arm-payload"
    assert load_hidden("oil_warmup").changes[0].damping_scale == 0.8


def test_change_at_specs() -> None:
    (step,) = changes_from_spec("coulomb", 12.5)  # a preset without a schedule: a step
    assert step.at == 12.5 and step.coulomb == {"sun": 0.05, "carrier3": 0.2}
    (wear,) = changes_from_spec("wear", 3.0)  # a schedule: shifted to start at T
    assert wear.at == 3.0 and wear.ramp == 60.0
    assert parse_change_at("7:friction_step")[0].at == 7.0
    with pytest.raises(HiddenEffectsError, match="changes nothing at runtime"):
        changes_from_spec("backlash", 1.0)
    for bad in ("abc:coulomb", "5", "-1:coulomb", "5:"):
        with pytest.raises(DvtDriverError, match="--change-at"):
            parse_change_at(bad)


def _run(sim: PlantSim, seconds: float, current: float = 4.0) -> np.ndarray:
    out = []
    for i in range(round(seconds * 1000)):
        if i % 50 == 0:
            sim.handle(Command(i & 0xFFFF, Mode.CURRENT, current, (0.0, 0.0, 0.0)))
        out.append(sim.tick().omega_true)
    return np.asarray(out)


def test_plant_applies_a_friction_step_at_its_time() -> None:
    h = parse_hidden({"changes": [{"at": 3.0, "coulomb": {"sun": 0.05, "carrier3": 0.2},
                                   "note": "step"}]}, source="t")
    sim = PlantSim(PARAMS, h, seed=1)
    sim.handle(Hello())
    clean = PlantSim(PARAMS, None, seed=1)
    clean.handle(Hello())
    w = _run(sim, 5.0)
    w0 = _run(clean, 5.0)
    # identical before the change, slower after it (the friction brakes the machine)
    assert np.array_equal(w[:3000], w0[:3000])
    assert w[-1, 0] < w0[-1, 0] - 5.0 and w[-1, 1] < w0[-1, 1] - 1.0
    assert len(sim.changes_applied) == 1
    entry = sim.changes_applied[0]
    assert entry["at_s"] == pytest.approx(3.0, abs=1e-3)
    assert entry["change"]["note"] == "step"
    truth = yaml.safe_load(sim.truth_yaml())
    assert truth["changes_applied"] == sim.changes_applied
    assert truth["hidden"]["changes"][0]["at"] == 3.0
    assert "plant_changes" in truth["effects"]


def test_ramp_damping_and_runtime_change() -> None:
    sim = PlantSim(PARAMS, None, seed=1)
    sim.handle(Hello())
    base = _run(sim, 2.0)
    assert yaml.safe_load(sim.truth_yaml()).get("changes_applied") is None  # no schedule
    # lower damping at runtime: the machine runs faster under the same current
    sim.add_change(Change(at=sim.physics_time, ramp=0.5, damping_scale=0.8))
    w = _run(sim, 3.0)
    assert w[-1, 0] > base[-1, 0] + 5.0
    assert sim.hidden.damping_scale == pytest.approx(0.8)
    truth = yaml.safe_load(sim.truth_yaml())
    assert truth["changes_applied"][0]["change"]["damping_scale"] == 0.8


def test_payload_added_to_the_declared_arm() -> None:
    from dvt_model.load import load_joint_load

    arm = load_joint_load("arm")
    h = parse_hidden({"changes": [{"at": 1.0, "load": "arm-payload"}]}, source="t")
    sim = PlantSim(PARAMS, h, seed=1, load=arm)
    sim.handle(Hello())
    _run(sim, 1.5, current=0.0)
    assert sim.load is not None and sim.load.name != arm.name
    assert yaml.safe_load(sim.truth_yaml())["plant"]["load"]["name"] == arm.name  # the start's
