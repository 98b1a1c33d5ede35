"""Hidden-effect presets as distributions: drawn per seed, the fixed (nominal) draw, the record in
``truth.yaml``, and the messages for a malformed distribution."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from dvt_driver.errors import HiddenEffectsError
from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.hidden import (
    available_presets,
    is_distribution,
    load_hidden,
    parse_hidden,
    resolve,
)
from dvt_model.params import load_parameters
from dvt_model.recording import parse_truth

DRAWN = ["backlash", "bands", "coulomb", "delay", "gravity_arm", "mesh_ripple", "position_friction",
         "stribeck", "wet_brake", "windage"]
"""The effect presets: every one draws its magnitudes (the changing plants and ``none`` do not)."""


def _numbers(mapping: object, path: str = "") -> dict[str, float]:
    """Every number of a nested mapping by key path."""
    out: dict[str, float] = {}
    if isinstance(mapping, dict):
        for k, v in mapping.items():
            out.update(_numbers(v, f"{path}.{k}" if path else str(k)))
    elif isinstance(mapping, list):
        for i, v in enumerate(mapping):
            out.update(_numbers(v, f"{path}[{i}]"))
    elif isinstance(mapping, int | float) and not isinstance(mapping, bool):
        out[path] = float(mapping)
    return out


def test_effect_presets_draw_and_the_others_do_not() -> None:
    assert [n for n in available_presets() if load_hidden(n).draw is not None] == DRAWN
    for name in DRAWN:
        rec = load_hidden(name, draw=3).draw
        assert rec is not None and rec["seed"] == 3 and rec["fixed"] is False
        assert rec["distributions"], name


@pytest.mark.parametrize("name", DRAWN)
def test_a_draw_is_reproducible_inside_its_ranges_and_differs_by_seed(name: str) -> None:
    a, b = load_hidden(name, draw=7), load_hidden(name, draw=7)
    assert a.to_mapping() == b.to_mapping()
    assert load_hidden(name, draw=8).to_mapping() != a.to_mapping()
    nominal = load_hidden(name)
    assert nominal.draw is not None and nominal.draw["fixed"] is True
    assert a.effect_names() == nominal.effect_names()
    for path, dist in a.draw["distributions"].items():  # type: ignore[index]
        drawn = _resolved(a.draw, name, 7)[path]
        fixed = _resolved(nominal.draw, name, None)[path]
        assert fixed == dist["fixed"], path
        if "choice" in dist:
            assert drawn in dist["choice"], (path, drawn)
        else:
            lo, hi = next(v for k, v in dist.items() if k != "fixed")
            assert lo <= drawn <= hi, (path, drawn, dist)


def _resolved(record: object, name: str, draw: int | None) -> dict[str, float]:
    """The values of a preset's distributions for a draw (``resolve`` on the preset's YAML)."""
    from importlib import resources

    text = (resources.files("dvt_driver.plant") / "config" / f"{name}.yaml").read_text()
    values, found = resolve(yaml.safe_load(text), draw, name)
    nums = _numbers(values)
    return {p: nums[p] for p in found}


def test_the_fixed_draw_is_the_nominal_plant() -> None:
    assert load_hidden("coulomb").coulomb == {"sun": 0.05, "carrier3": 0.20}
    strib = load_hidden("stribeck").stribeck
    assert (strib["sun"].vs, strib["carrier3"].vs) == (4.0, 2.0)
    arm = load_hidden("gravity_arm").gravity_arm
    assert arm is not None and arm.stage.reduction == 20.0
    assert arm.arm.zero_angle == pytest.approx(-math.pi / 2)
    backlash = load_hidden("backlash").backlash
    assert backlash is not None and backlash.gap == 0.03
    assert load_hidden("delay").measurement_delay == 0.004


def test_draws_spread_over_the_range() -> None:
    """50 draws: the magnitudes spread over their range, the stage of the ripple takes every
    value, the delay whole milliseconds only; the reduction never equals a round number."""
    suns = [load_hidden("coulomb", draw=s).coulomb["sun"] for s in range(50)]
    assert min(suns) < 0.037 and max(suns) > 0.065
    stages = {load_hidden("mesh_ripple", draw=s).mesh_ripple.stage  # type: ignore[union-attr]
              for s in range(50)}
    assert stages == {1, 2, 3}
    delays = {load_hidden("delay", draw=s).measurement_delay for s in range(50)}
    assert len(delays) > 3 and all(round(d * 1000) == pytest.approx(d * 1000) for d in delays)
    reductions = [load_hidden("gravity_arm", draw=s).gravity_arm.stage.reduction  # type: ignore[union-attr]
                  for s in range(50)]
    assert min(reductions) < 12 and max(reductions) > 35
    assert not any(float(r).is_integer() for r in reductions)


def test_each_value_has_its_own_stream(tmp_path: Path) -> None:
    """Adding an effect to a preset does not change the draws of the others."""
    base = {"coulomb": {"sun": {"uniform": [0.01, 0.1], "fixed": 0.05}}}
    more = {"windage": {"sun": {"log_uniform": [1e-6, 1e-5], "fixed": 4e-6}}, **base}
    one, two = tmp_path / "one.yaml", tmp_path / "two.yaml"
    one.write_text(yaml.safe_dump(base))
    two.write_text(yaml.safe_dump(more))
    for seed in range(5):
        assert load_hidden(one, draw=seed).coulomb == load_hidden(two, draw=seed).coulomb


def test_truth_yaml_holds_the_drawn_values_and_the_draw() -> None:
    h = load_hidden("coulomb", draw=13)
    doc = parse_truth(h.to_truth_yaml(params_name="physical", seed=13, sample_period_us=1000))
    assert doc["hidden"] == h.to_mapping() != load_hidden("coulomb").to_mapping()
    assert doc["hidden_draw"]["seed"] == 13 and doc["hidden_draw"]["fixed"] is False
    assert doc["hidden_draw"]["distributions"]["coulomb.sun"] == {
        "log_uniform": [0.03, 0.08], "fixed": 0.05}
    # the drawn plant comes back from the truth (a validation run of the same plant)
    assert parse_hidden(doc["hidden"]).coulomb == h.coulomb
    # the plant writes the same
    sim = PlantSim(load_parameters("physical"), h, seed=13)
    plant_doc = parse_truth(sim.truth_yaml())
    assert plant_doc["hidden"] == doc["hidden"] and plant_doc["hidden_draw"] == doc["hidden_draw"]
    # the band law the plant runs is in the truth: the parameter set's bands as built ...
    built = load_parameters("physical").brake
    assert plant_doc["plant"]["bands"] == {"gain": built.gains.tolist(),
                                           "time_constant": built.time_constants.tolist()}
    # ... or a `bands` draw
    drawn = load_hidden("bands", draw=13)
    assert drawn.bands is not None and drawn.bands.gain is not None
    bands_doc = parse_truth(PlantSim(load_parameters("physical"), drawn, seed=13).truth_yaml())
    assert bands_doc["plant"]["bands"]["gain"] == list(drawn.bands.gain) != built.gains.tolist()
    # a preset without distributions writes no draw
    assert "hidden_draw" not in parse_truth(load_hidden("none", draw=1).to_truth_yaml(
        params_name="physical", seed=1, sample_period_us=1000))


@pytest.mark.parametrize(("value", "message"), [
    ({"uniform": [0.1, 0.2]}, "x.y.fixed: missing"),
    ({"uniform": [0.1, 0.2], "choice": [1], "fixed": 0.1}, "x.y: a distribution needs exactly one"),
    ({"uniform": [0.2, 0.1], "fixed": 0.15}, "x.y.uniform: expected lo < hi"),
    ({"uniform": [0.1], "fixed": 0.1}, "x.y.uniform: expected [lo, hi]"),
    ({"log_uniform": [0.0, 1.0], "fixed": 0.5}, "x.y.log_uniform: expected 0 < lo"),
    ({"uniform": [0.1, 0.2], "fixed": 0.3}, "x.y.fixed: 0.3 is outside uniform [0.1, 0.2]"),
    ({"choice": [1, 2], "fixed": 3}, "x.y.fixed: 3 is not one of the choices [1, 2]"),
    ({"choice": [], "fixed": 3}, "x.y.choice: expected a non-empty list"),
    ({"uniform": ["a", 1], "fixed": 1}, "x.y.uniform: expected a finite number, got 'a'"),
    ({"normal": [0, 1], "fixed": 0}, "x.y.normal: unknown key in a distribution"),
])
def test_a_malformed_distribution_is_named(value: dict[str, object], message: str) -> None:
    assert is_distribution(value)
    with pytest.raises(HiddenEffectsError, match="^src: " + _escape(message)):
        resolve({"x": {"y": value}}, 1, "src")


def _escape(text: str) -> str:
    import re

    return re.escape(text)


@pytest.mark.parametrize("seed", [-1, True, 1.5])
def test_a_bad_draw_seed_is_refused(seed: object) -> None:
    with pytest.raises(HiddenEffectsError, match="the draw seed must be an integer >= 0"):
        resolve({}, seed, "src")  # type: ignore[arg-type]
