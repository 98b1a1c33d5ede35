"""Hidden-effect configuration: presets, validation messages, friction and engagement shapes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from dvt_driver.errors import HiddenEffectsError
from dvt_driver.plant.hidden import (
    MEMBERS,
    HiddenEffects,
    StribeckFriction,
    WetBrake,
    available_presets,
    load_hidden,
    parse_hidden,
)
from dvt_driver.plant.physics import (
    FrictionForces,
    Transmission,
    WetBrakeEngagement,
    friction_velocity_floor,
)
from dvt_model.brake import capacity_step
from dvt_model.params import load_parameters

PRESETS = ["backlash", "bands", "coulomb", "delay", "friction_step", "gravity_arm", "mesh_ripple",
           "none", "oil_warmup", "payload_added", "position_friction", "stribeck", "wear",
           "wet_brake", "windage"]


def test_presets_are_bundled_and_valid() -> None:
    assert available_presets() == PRESETS
    expected = {"none": ["none"], "coulomb": ["coulomb_friction"],
                "stribeck": ["stribeck_friction"], "windage": ["windage"],
                "backlash": ["backlash"], "bands": ["bands"], "delay": ["measurement_delay"],
                "wet_brake": ["brake_engagement"], "gravity_arm": ["gravity_load"],
                "mesh_ripple": ["mesh_ripple"], "position_friction": ["position_friction"],
                # changing plants (test_plant_changes.py)
                "friction_step": ["plant_changes"], "oil_warmup": ["plant_changes"],
                "payload_added": ["plant_changes"],
                "wear": ["coulomb_friction", "plant_changes"]}
    for name in PRESETS:
        h = load_hidden(name)
        assert h.effect_names() == expected[name], name
        assert h.is_clean == (name == "none")
        assert h.source == f"{name}.yaml"


def test_load_by_path_and_round_trip(tmp_path: Path) -> None:
    data = {"coulomb": {"sun": 0.05}, "stribeck": {"carrier3": {"Fc": 0.1, "Fs": 0.3, "vs": 2}},
            "windage": {"planet1_rel": 1e-6}, "measurement_delay": 0.002,
            "backlash": {"gap": 0.02, "stiffness": 300, "damping": 0.1, "load_inertia": 0.002},
            "wet_brake": {"all": {"viscous_time": 0.03, "viscous_coefficient": 0.02,
                                  "viscous_fraction": 0.4, "asperity_time": 0.08,
                                  "release_time": 0.01},
                          "band2": {"viscous_time": 0.01, "viscous_coefficient": 0.0,
                                    "viscous_fraction": 0.0, "asperity_time": 0.05,
                                    "release_time": 0.02}},
            "friction_velocity": 0.1}
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(data))
    h = load_hidden(path)
    assert h.source == str(path)
    assert h.coulomb == {"sun": 0.05}
    assert h.stribeck == {"carrier3": StribeckFriction(0.1, 0.3, 2.0, 2.0)}
    assert h.measurement_delay == 0.002
    assert h.backlash is not None and h.backlash.where == "carrier3_output"
    assert h.wet_brake[2].viscous_time == 0.01  # band2 overrides "all"
    assert h.wet_brake[1].viscous_time == h.wet_brake[3].viscous_time == 0.03
    again = parse_hidden(h.to_mapping(), source="again")
    assert again.to_mapping() == h.to_mapping()
    assert again.effect_names() == h.effect_names()


def test_truth_yaml_carries_effects_and_plant_settings() -> None:
    h = load_hidden("stribeck")
    text = h.to_truth_yaml(params_name="physical", seed=7, sample_period_us=1000,
                           extra={"substeps": 1})
    doc = yaml.safe_load(text)
    assert doc["effects"] == ["stribeck_friction"]
    assert doc["plant"] == {"params": "physical", "seed": 7, "sample_period_us": 1000,
                            "substeps": 1}
    assert parse_hidden(doc["hidden"]).to_mapping() == h.to_mapping()
    assert text.startswith("# Hidden effects")


@pytest.mark.parametrize(("data", "message"), [
    ({"colomb": {"sun": 0.1}}, r"bad\.yaml: colomb: unknown effect .* value \{'sun': 0\.1\}"),
    ({"coulomb": {"sunn": 0.1}}, r"bad\.yaml: coulomb\.sunn: unknown member"),
    ({"coulomb": {"sun": -0.1}}, r"bad\.yaml: coulomb\.sun: expected a number >= 0, got -0\.1"),
    ({"coulomb": {"sun": "a lot"}}, r"coulomb\.sun: expected a number, got 'a lot'"),
    ({"coulomb": {"sun": True}}, r"coulomb\.sun: expected a number, got True"),
    ({"coulomb": [0.1]}, r"bad\.yaml: coulomb: expected a mapping, got \[0\.1\]"),
    ({"windage": {"sun": float("nan")}}, r"windage\.sun: expected a finite number, got nan"),
    ({"stribeck": {"sun": {"Fc": 0.2, "Fs": 0.1, "vs": 1.0}}},
     r"stribeck\.sun\.Fs: expected a number >= Fc \(0\.2\), got 0\.1"),
    ({"stribeck": {"sun": {"Fc": 0.1, "Fs": 0.2}}}, r"stribeck\.sun\.vs: missing"),
    ({"stribeck": {"sun": {"Fc": 0.1, "Fs": 0.2, "vs": 0.0}}},
     r"stribeck\.sun\.vs: expected a number > 0, got 0\.0"),
    ({"stribeck": {"sun": {"Fc": 0.1, "Fs": 0.2, "vs": 1, "Fv": 3}}},
     r"stribeck\.sun\.Fv: unknown key .* value 3"),
    ({"backlash": {"where": "ring2", "gap": 0.01, "stiffness": 1, "damping": 0,
                   "load_inertia": 1e-3}},
     r"backlash\.where: expected one of \['carrier3_output'\], got 'ring2'"),
    ({"backlash": {"gap": 0.01, "stiffness": 0, "damping": 0, "load_inertia": 1e-3}},
     r"backlash\.stiffness: expected a number > 0, got 0"),
    ({"backlash": {"gap": 0.01, "stiffness": 10, "damping": 0}},
     r"backlash\.load_inertia: missing"),
    ({"measurement_delay": {"seconds": -0.001}},
     r"measurement_delay\.seconds: expected a number >= 0, got -0\.001"),
    ({"measurement_delay": {"secs": 0.001}}, r"measurement_delay\.secs: unknown key"),
    ({"wet_brake": {"band4": {}}}, r"wet_brake\.band4: unknown band"),
    ({"wet_brake": {"all": {"viscous_time": 0.03, "viscous_coefficient": 0.02,
                            "viscous_fraction": 1.5, "asperity_time": 0.08,
                            "release_time": 0.01}}},
     r"wet_brake\.all\.viscous_fraction: expected a number <= 1, got 1\.5"),
    ({"friction_velocity": 0}, r"friction_velocity: expected a number > 0, got 0"),
    ({"bands": {"gain": [6.0, 7.0]}},
     r"bad\.yaml: bands\.gain: expected a list of 3 numbers \(bands 1, 2, 3\), got \[6\.0, 7\.0\]"),
    ({"bands": {"time_constant": [0.02, 0.0, 0.02]}},
     r"bands\.time_constant\[1\]: expected a number > 0, got 0\.0"),
    ({"bands": {"gain": [6.0, 7.0, "x"]}}, r"bands\.gain\[2\]: expected a number, got 'x'"),
    ({"bands": {"lag": [0.02, 0.02, 0.02]}}, r"bands\.lag: unknown key"),
    ([1, 2], r"bad\.yaml: expected a mapping at the top level, got \[1, 2\]"),
])
def test_bad_configuration_names_key_and_value(data: object, message: str) -> None:
    with pytest.raises(HiddenEffectsError, match=message):
        parse_hidden(data, source="bad.yaml")


def test_bad_files_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(HiddenEffectsError, match=r"unknown hidden-effects preset 'coulom'"):
        load_hidden("coulom")
    with pytest.raises(HiddenEffectsError, match=r"missing\.yaml: cannot read"):
        load_hidden(tmp_path / "missing.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("coulomb: {sun: [\n")
    with pytest.raises(HiddenEffectsError, match=r"broken\.yaml: not valid YAML"):
        load_hidden(broken)
    odd = tmp_path / "odd.yaml"
    odd.write_text("coulomb:\n  carrier4: 0.1\n")
    with pytest.raises(HiddenEffectsError, match=r"odd\.yaml: coulomb\.carrier4: unknown member"):
        load_hidden(odd)


def test_empty_file_is_a_clean_plant() -> None:
    assert parse_hidden(None).is_clean
    assert parse_hidden({}).effect_names() == ["none"]


def _friction(h: HiddenEffects, dt: float = 1e-3) -> FrictionForces:
    forms = {m: np.array([1.0, 0.0]) if m == "sun" else np.array([0.0, 1.0]) for m in MEMBERS}
    return FrictionForces(h, forms, {m: 1.0 for m in MEMBERS}, dt)


def test_stribeck_curve_differs_from_coulomb() -> None:
    coul = _friction(parse_hidden({"coulomb": {"sun": 0.1}, "friction_velocity": 0.01}))
    strib = _friction(parse_hidden({"stribeck": {"sun": {"Fc": 0.1, "Fs": 0.3, "vs": 2.0}},
                                    "friction_velocity": 0.01}))
    for v, expected_strib in ((0.2, 0.3), (20.0, 0.1)):
        w = np.array([v, 0.0])
        assert coul.member_torques(w)[0] == pytest.approx(0.1, rel=1e-3)
        assert strib.member_torques(w)[0] == pytest.approx(expected_strib, rel=0.02)
        # odd in the speed, opposing motion as a generalised torque on the sun
        assert strib.generalised(-w)[0] == pytest.approx(-strib.generalised(w)[0])
        assert strib.generalised(w)[0] < 0.0
    assert strib.member_torques(np.zeros(2))[0] == 0.0


def test_windage_is_quadratic_and_opposes_motion() -> None:
    wind = _friction(parse_hidden({"windage": {"carrier3": 1e-4}}))
    t1 = wind.generalised(np.array([0.0, 50.0]))
    t2 = wind.generalised(np.array([0.0, 100.0]))
    assert t1[0] == 0.0
    assert t1[1] == pytest.approx(-0.25)
    assert t2[1] == pytest.approx(4 * t1[1])
    assert wind.generalised(np.array([0.0, -50.0]))[1] == pytest.approx(0.25)


def test_friction_regularisation_respects_the_stability_floor() -> None:
    h = parse_hidden({"coulomb": {"sun": 0.1}, "friction_velocity": 1e-4})
    forms = {"sun": np.array([1.0, 0.0])}
    f = FrictionForces(h, forms, {"sun": 2000.0}, 1e-3)
    assert f.v_eps[0] == pytest.approx(friction_velocity_floor(0.1, 2000.0, 1e-3))
    assert f.v_eps[0] == pytest.approx(0.4)
    loose = FrictionForces(parse_hidden({"coulomb": {"sun": 0.1}}), forms, {"sun": 1.0}, 1e-3)
    assert loose.v_eps[0] == pytest.approx(0.05)


def test_wet_brake_shape_is_viscous_then_asperity() -> None:
    shape = WetBrake(viscous_time=0.04, viscous_coefficient=0.02, viscous_fraction=0.4,
                     asperity_time=0.1, release_time=0.01)
    eng = WetBrakeEngagement({1: shape}, time_constant=0.02)
    target = np.array([2.0, 2.0, 0.0])
    ring = np.array([20.0, 20.0, 0.0])
    cap = np.zeros(3)
    caps = []
    for _ in range(200):  # 0.2 s at 1 ms
        cap, mean = eng(cap, target, 1e-3, ring)
        assert np.all(mean >= 0.0)
        caps.append(cap.copy())
    c = np.array(caps)
    # band 1 (wet): only film shear (<= 0.4 x target, = 0.02 x 20 rad/s) in the viscous phase
    assert c[38, 0] <= 0.4 + 1e-9
    assert c[38, 0] == pytest.approx(0.4 * 39 / 40, rel=1e-6)
    # ... then an S-curve to the full torque at 0.14 s
    assert c[89, 0] == pytest.approx(0.4 + 2.0 * 0.5, rel=1e-6)
    assert c[139, 0] == pytest.approx(2.0)
    # band 2 keeps the first-order lag of the model
    ref = np.zeros(3)
    for _ in range(39):
        ref, _m = capacity_step(ref, target, 1e-3, 0.02)
    assert c[38, 1] == pytest.approx(ref[1])
    assert c[38, 1] > 4 * c[38, 0]
    # release: first-order decay with release_time, film re-forms
    cap, _ = eng(cap, np.zeros(3), 0.01, ring)
    assert cap[0] == pytest.approx(2.0 * np.exp(-1.0))
    assert eng.applied_time[0] == 0.0


def test_bands_as_built_replace_the_parameter_sets_law_per_band() -> None:
    """``bands``: the plant's model runs each band's own gain and lag (the ones given; the
    others the parameter set's law); the values round-trip through the mapping."""
    params = load_parameters("physical")
    law = params.brake
    h = parse_hidden({"bands": {"gain": [6.5, 9.5, 7.2]}}, source="b")
    assert not h.is_clean and h.effect_names() == ["bands"]
    plant = Transmission(params, h)
    assert plant.brake.gains.tolist() == [6.5, 9.5, 7.2]
    assert plant.brake.time_constants.tolist() == law.time_constants.tolist()
    assert plant.model.brake is plant.brake
    both = parse_hidden({"bands": {"gain": [6.5, 9.5, 7.2], "time_constant": [0.03, 0.01, 0.02]},
                         "wet_brake": {"band1": {"viscous_time": 0.03,
                                                 "viscous_coefficient": 0.02,
                                                 "viscous_fraction": 0.4, "asperity_time": 0.08,
                                                 "release_time": 0.01}}}, source="b")
    assert parse_hidden(both.to_mapping(), source="again").to_mapping() == both.to_mapping()
    wet = Transmission(params, both)
    # the bands without a wet shape keep a first-order lag: their own
    eng = wet.model.engagement
    assert isinstance(eng, WetBrakeEngagement)
    target = np.array([0.0, 2.0, 2.0])
    cap, _ = eng(np.zeros(3), target, 0.01, np.zeros(3))
    assert cap[1] == pytest.approx(2.0 * -np.expm1(-0.01 / 0.01))
    assert cap[2] == pytest.approx(2.0 * -np.expm1(-0.01 / 0.02))
    assert Transmission(params, parse_hidden(None)).brake is law


def test_position_effects_parse_round_trip_and_refuse_bad_values() -> None:
    data = {"gravity_arm": {"output_stage": {"reduction": 20.0},
                            "arm": {"length": 0.5, "mass": 10.0, "payload": 2.0}},
            "mesh_ripple": {"amplitude": 0.03, "stage": 3, "phase": 0.5},
            "position_friction": {"carrier3": {"amplitude": 0.3, "center": 1.0, "width": 0.3}}}
    h = parse_hidden(data, source="pos")
    assert h.has_angle_effects and not h.is_clean
    assert h.effect_names() == ["gravity_load", "mesh_ripple", "position_friction"]
    assert h.mesh_ripple is not None and h.mesh_ripple.stage == 3
    again = parse_hidden(h.to_mapping(), source="again")
    assert again.to_mapping() == h.to_mapping()
    for bad, match in (({"mesh_ripple": {"amplitude": 0.1, "stage": 4}}, "mesh_ripple.stage"),
                       ({"mesh_ripple": {"amplitude": -1}}, "mesh_ripple.amplitude"),
                       ({"position_friction": {"moon": {"amplitude": 1, "center": 0,
                                                        "width": 1}}}, "moon"),
                       ({"position_friction": {"sun": {"amplitude": 1, "center": 0,
                                                       "width": 0}}}, "width"),
                       ({"gravity_arm": {"output_stage": {"reduction": 0},
                                         "arm": {"length": 1, "mass": 1}}}, "reduction")):
        with pytest.raises(HiddenEffectsError, match=match):
            parse_hidden(bad, source="bad")


def test_mesh_ripple_step_mean_and_bump_level() -> None:
    from dvt_driver.plant.hidden import MeshRipple, PositionFriction
    r = MeshRipple(amplitude=2.0)
    # the step mean equals the numerical mean of the sine over the step
    grid = np.linspace(0.0, 1e-3, 10001)
    exact = np.mean(2.0 * np.sin(16 * (0.3 + 100.0 * grid)))
    assert r.mean_torque(16, 0.3, 100.0, 1e-3) == pytest.approx(exact, rel=1e-3, abs=1e-6)
    assert r.mean_torque(16, 0.3, 0.0, 1e-3) == pytest.approx(2.0 * np.sin(4.8))
    b = PositionFriction(amplitude=0.3, center=1.0, width=0.3)
    assert b.level(1.0) == pytest.approx(0.3) and b.level(1.0 + 2 * np.pi) == pytest.approx(0.3)
    assert b.level(1.0 + np.pi) < 1e-6
