"""The contract's model-node parameter schema and its effect-term checks."""

import json

import pytest

from dvt_model.contract import (
    MAX_EFFECT_TERMS,
    MODEL_PARAMETERS,
    NodeParam,
    effects_json,
    short_repr,
    validate_effects,
)
from dvt_model.errors import ContractError
from dvt_model.params import BrakeParams


def test_schema_names_and_defaults():
    assert list(MODEL_PARAMETERS) == ["params", "M", "D", "motor_constant", "band_gain",
                                      "band_time_constant", "A", "B", "effects", "mode",
                                      "reanchor_period", "gap_reset", "gap_reanchor", "load",
                                      "detector.enabled", "detector.sample_rate_hz",
                                      "detector.block_s", "detector.settle_s",
                                      "detector.learn_s",
                                      "detector.shift_sigma", "detector.false_alarm_period_s",
                                      "detector.max_gap_s", "detector.max_phi",
                                      "detector.colour_s", "detector.colour_lag_s",
                                          "detector.colour_file"]
    for name, spec in MODEL_PARAMETERS.items():
        assert spec.name == name
        assert spec.description and spec.unit
        assert spec.check(None) == spec.default  # not set = the default
        assert spec.check(spec.default) == spec.default  # the default is admissible


def test_band_parameters_named_as_the_brake_data():
    fields = set(BrakeParams.__dataclass_fields__)
    assert {"band_gain", "band_time_constant"} <= fields
    assert {"band_gain", "band_time_constant"} <= set(MODEL_PARAMETERS)


@pytest.mark.parametrize(("name", "value", "match"), [
    ("motor_constant", -1.0, r"^motor_constant: -1\.0 is not admissible: expected a number in "
                             r"\[0, 10\] \[N m/A\]"),
    ("motor_constant", True, "^motor_constant"),
    ("M", [1.0, 2.0], "^M: 2 values"),
    ("M", [1.0, 2.0, "x", 4.0], r"^M\[2\]"),
    ("band_gain", [1.0, 0.0, 1.0], r"^band_gain\[1\]: 0\.0 is not admissible.*\(0, 1000\]"),
    ("B", [1.0] * 6, "^B: 6 values.*4 or 8"),
    ("mode", "fast", r"^mode: 'fast' is not admissible: expected one of \['simulate'"),
    ("effects", "x" * 100_000, "^effects: 100000 characters"),
])
def test_check_names_parameter_value_and_range(name, value, match):
    with pytest.raises(ContractError, match=match):
        MODEL_PARAMETERS[name].check(value)


def test_check_normalises():
    assert MODEL_PARAMETERS["M"].check([1, 0, 0, 2]) == (1.0, 0.0, 0.0, 2.0)
    assert MODEL_PARAMETERS["M"].check([]) == ()
    assert MODEL_PARAMETERS["motor_constant"].check(1) == 1.0
    spec = NodeParam("x", "double", "s", "test", 1.0, lo=0.0, hi=2.0, hi_open=True)
    with pytest.raises(ContractError, match=r"\[0, 2\)"):
        spec.check(2.0)


def test_effects_limits():
    term = {"kind": "windage", "member": [1.0, 0.0], "Cw": 1e-5}
    assert len(validate_effects([term] * MAX_EFFECT_TERMS)) == MAX_EFFECT_TERMS
    with pytest.raises(ContractError, match="at most"):
        validate_effects([term] * (MAX_EFFECT_TERMS + 1))
    text = effects_json([term])
    assert json.loads(text)[0]["Cw"] == 1e-5


def test_short_repr_bounds_length():
    assert len(short_repr("x" * 10**6)) < 200
    assert len(short_repr(list(range(10**5)))) < 200
    assert short_repr([1.0, 2.0]) == "[1.0, 2.0]"


def test_change_topics_and_detector_schema():
    from dataclasses import fields

    from dvt_model.contract import (
        CHANGE_QOS,
        DETECTOR_PARAMETERS,
        MODEL_CHANGE,
        MODEL_PARAMETERS,
        RECORDER_SNAPSHOT_REQUEST,
        RECORDER_SNAPSHOT_RESULT,
    )
    from dvt_model.detect import DetectorConfig

    assert MODEL_CHANGE == "/dvt/model/change"
    assert RECORDER_SNAPSHOT_REQUEST == "/dvt/recorder/snapshot"
    assert RECORDER_SNAPSHOT_RESULT == "/dvt/recorder/snapshot_result"
    assert (CHANGE_QOS.depth, CHANGE_QOS.reliability, CHANGE_QOS.durability) == (
        10, "reliable", "transient_local")
    # every DetectorConfig field (but the output names) is a node parameter, same default
    cfg = DetectorConfig()
    for f in fields(DetectorConfig):
        if f.name == "names":
            continue  # the contract's SPEED_NAMES
        spec = MODEL_PARAMETERS[f"detector.{f.name}"]
        assert spec.default == getattr(cfg, f.name), f.name
        assert spec.name in DETECTOR_PARAMETERS
    assert MODEL_PARAMETERS["detector.enabled"].check(None) is True
    assert MODEL_PARAMETERS["detector.enabled"].check(False) is False
    with pytest.raises(ContractError, match=r"detector\.enabled: 1 .*true or false"):
        MODEL_PARAMETERS["detector.enabled"].check(1)
    with pytest.raises(ContractError, match=r"detector\.max_phi: 1\.0 .*\[0, 1\)"):
        MODEL_PARAMETERS["detector.max_phi"].check(1.0)
