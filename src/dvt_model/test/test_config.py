"""The model node's configuration from parameters: every bad setting refused with its reason."""

import json
import time

import numpy as np
import pytest

from dvt_model.config import (
    build_predictor,
    check_parameters,
    defaults,
    detector_config,
    model_key,
    resolve,
)
from dvt_model.contract import GAP_REANCHOR_S, GAP_RESET_S, MAX_EFFECT_TERMS, MODEL_PARAMETERS
from dvt_model.errors import DvtModelError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel
from dvt_model.params import load_parameters

M_OK = [0.0004, 0.0001, 0.0001, 0.04]
A_OK = [-20.0, 1.0, 2.0, -3.0]
B_OK = [800.0, -400.0, 160.0, -47.0]


def _effects(*terms):
    return json.dumps(list(terms))


def _huge_effects(n=200_000):
    return json.dumps([{"kind": "viscous", "member": [1.0, 0.0], "b": 1e-3}] * n)


BAD = [
    # the twelve kinds
    ("D", {"D": [-0.01, 0.0, 0.0, -0.05]}, "positive semi-definite"),
    ("D", {"D": [0.01, 0.002, -0.002, 0.05]}, "symmetric"),
    ("M", {"M": [1e-30, 0.0, 0.0, 1e-30]}, "smallest eigenvalue"),
    ("M", {"M": [0.0004, 0.0001, 0.0002, 0.04]}, "symmetric"),
    ("effects", {"effects": _effects({"kind": "viscous", "member": [1, 0], "b": -1e-3})},
     r"effects\[0\]\.b"),
    ("effects", {"effects": _effects({"kind": "coulomb", "member": [1, 0], "Fc": -0.2})},
     r"effects\[0\]\.Fc"),
    ("effects", {"effects": _effects({"kind": "windage", "member": [1, 0], "Cw": -1e-4})},
     r"effects\[0\]\.Cw"),
    ("effects", {"effects": _effects({"kind": "stribeck", "member": [1, 0], "Fs": -0.1,
                                      "vs": 1.0})}, r"effects\[0\]\.Fs"),
    ("A", {"A": [5.0, 0.0, 0.0, -1.0], "B": B_OK}, "stable"),
    ("A", {"A": [0.1, -50.0, 50.0, 0.1], "B": B_OK}, "negative real part"),
    ("effects", {"effects": _effects({"kind": "gain", "output": 0, "gain": -1.0})},
     r"effects\[0\]\.gain"),
    ("effects", {"effects": _huge_effects()}, "at most"),
    # more of M and D
    ("M", {"M": [0.001665, -0.0059856, -0.0059856, 0.0028709]}, "not positive definite"),
    ("M", {"M": [0.0, 0.0, 0.0, 0.0]}, "not positive definite"),
    ("M", {"M": [1e-9, 0.0, 0.0, 1.0]}, "condition number"),
    ("M", {"M": [1.0, 0.0, 0.0]}, "3 values"),
    ("M", {"M": [float("nan"), 0.0, 0.0, 1.0]}, "M"),
    ("M", {"M": [float("inf"), 0.0, 0.0, 1.0]}, "M"),
    ("M", {"M": [1e6, 0.0, 0.0, 1e6]}, "M"),
    ("M", {"M": "0.001 0 0 0.04"}, "M"),
    ("M", {"M": [True, False, False, True]}, "M"),
    ("D", {"D": [0.01, 0.0, 0.0, float("nan")]}, "D"),
    ("D", {"D": [0.01, 0.0, 0.0, 0.05, 0.0]}, "5 values"),
    # scalars
    ("motor_constant", {"motor_constant": -0.3}, "motor_constant"),
    ("motor_constant", {"motor_constant": 100.0}, "motor_constant"),
    ("motor_constant", {"motor_constant": float("nan")}, "motor_constant"),
    ("motor_constant", {"motor_constant": "0.37"}, "motor_constant"),
    ("band_gain", {"band_gain": [8.0, 8.0]}, "2 values"),
    ("band_gain", {"band_gain": [8.0, -8.0, 8.0]}, "band_gain"),
    ("band_gain", {"band_gain": [8.0, 0.0, 8.0]}, "band_gain"),
    ("band_time_constant", {"band_time_constant": [0.02, 0.0, 0.02]}, "band_time_constant"),
    ("band_time_constant", {"band_time_constant": [0.02, float("inf"), 0.02]},
     "band_time_constant"),
    # the linear model
    ("A", {"A": [1.0, 2.0, 3.0], "B": B_OK}, "3 values"),
    ("A", {"A": A_OK}, "give both"),
    ("B", {"B": B_OK}, "give both"),
    ("B", {"A": A_OK, "B": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}, "6 values"),
    ("B", {"A": A_OK, "B": [1.0, float("nan"), 3.0, 4.0]}, "B"),
    ("effects", {"A": A_OK, "B": B_OK,
                 "effects": _effects({"kind": "viscous", "member": [1, 0], "b": 1e-3})},
     "force terms need the physical model"),
    # effects
    ("effects", {"effects": "{"}, "not valid JSON"),
    ("effects", {"effects": json.dumps([{"kind": "delay", "seconds": 0.1}] * (MAX_EFFECT_TERMS
                                                                             + 1))}, "at most"),
    ("effects", {"effects": _effects({"kind": "magic"})}, r"effects\[0\]\.kind"),
    ("effects", {"effects": _effects({"kind": "viscous", "member": [0, 0], "b": 1e-3})},
     r"effects\[0\]\.member"),
    ("effects", {"effects": 42}, "effects"),
    # strings and others
    ("params", {"params": "no-such-set"}, "unknown parameter set"),
    ("params", {"params": "/no/such/file.yaml"}, "cannot read"),
    ("params", {"params": "x" * 100_000}, "params"),
    ("mode", {"mode": "bogus"}, "simulate"),
    ("reanchor_period", {"reanchor_period": 0.0}, "reanchor_period"),
    ("gap_reset", {"gap_reset": -1.0}, "gap_reset"),
    ("gap_reset", {"gap_reset": [0.5]}, "gap_reset"),
    ("gap_reanchor", {"gap_reanchor": 0.0}, "gap_reanchor"),
    ("gap_reanchor", {"gap_reanchor": "soon"}, "gap_reanchor"),
    ("load", {"load": "piano"}, "unknown load"),
    ("load", {"load": "/no/such/load.yaml"}, "cannot read"),
    ("load", {"load": 3.0}, "load"),
    ("load", {"load": "x" * 100_000}, "load"),
    ("load", {"load": "arm", "A": [-1.0, 0.0, 0.0, -1.0], "B": [1.0, 0.0, 0.0, 1.0]},
     "physical model"),
    ("detector.enabled", {"detector.enabled": "yes"}, "true or false"),
    ("detector.sample_rate_hz", {"detector.sample_rate_hz": 0.0}, r"\(0, 100000\]"),
    ("detector.block_s", {"detector.block_s": 2.0}, r"\[0, 1\]"),
    ("detector.settle_s", {"detector.settle_s": -1.0}, r"\[0, 600\]"),
    ("detector.learn_s", {"detector.learn_s": 0.2}, "at least 100 samples"),
    ("detector.shift_sigma", {"detector.shift_sigma": 21.0}, r"\(0, 20\]"),
    ("detector.false_alarm_period_s", {"detector.false_alarm_period_s": 0.01},
     "at least 10 samples"),
    ("detector.max_gap_s", {"detector.max_gap_s": float("nan")}, "detector.max_gap_s"),
    ("detector.max_phi", {"detector.max_phi": -0.1}, r"\[0, 1\)"),
    ("detector.colour_s", {"detector.colour_s": -1.0}, r"\[0, 86400\]"),
    ("detector.colour_s", {"detector.colour_s": 10.0}, "at least 10 x the longest lag"),
    ("detector.colour_lag_s", {"detector.colour_lag_s": 0.0}, r"\(0, 600\]"),
    ("detector.colour_file", {"detector.colour_file": 3.0}, "detector.colour_file"),
    ("detector.colour_file", {"detector.colour_file": "x" * 5000}, "detector.colour_file"),
    ("brake_gain", {"brake_gain": [8.0, 8.0, 8.0]}, "unknown parameter"),
    ("no_such_parameter", {"no_such_parameter": 1.0}, "unknown parameter"),
]


@pytest.mark.parametrize(("name", "values", "match"), BAD,
                         ids=[f"{i}-{b[0]}" for i, b in enumerate(BAD)])
def test_bad_setting_refused_naming_the_parameter(name, values, match):
    t0 = time.perf_counter()
    with pytest.raises(DvtModelError, match=match) as info:
        check_parameters(values)
    msg = str(info.value)
    assert msg.startswith(name), msg
    assert len(msg) < 1000  # a huge value is not echoed back
    assert time.perf_counter() - t0 < 1.0  # refused quickly, even a 200,000-term list
    with pytest.raises(DvtModelError, match=match):
        build_predictor(values)


def test_bad_settings_cover_every_parameter():
    assert set(MODEL_PARAMETERS) <= {b[0] for b in BAD}


@pytest.mark.parametrize("values", [
    {},
    {"params": "thesis", "mode": "reanchor", "reanchor_period": 0.25, "gap_reset": 2.0},
    {"M": M_OK, "D": [0.01, 0.0, 0.0, 0.05], "motor_constant": 0.4},
    {"M": np.array(M_OK), "D": [0.0, 0.0, 0.0, 0.0]},  # numpy values as the push has them
    {"band_gain": [8, 9, 10], "band_time_constant": [0.01, 0.02, 0.03]},
    {"A": A_OK, "B": B_OK},
    {"A": A_OK, "B": [*B_OK, 1.0, 2.0, 3.0, 4.0]},
    {"A": A_OK, "B": B_OK, "effects": _effects({"kind": "delay", "seconds": 0.004})},
    {"effects": _effects({"kind": "coulomb", "member": [1, 0], "Fc": 0.3},
                         {"kind": "gain", "output": 1, "gain": -0.4})},
    {"A": [], "B": [], "M": [], "effects": ""},
])
def test_good_settings_accepted(values):
    check_parameters(values)
    predictor, desc = build_predictor(values)
    out = predictor.update(0.0, 1.0, (0, 0, 0), (10.0, 2.0))
    assert np.all(np.isfinite(out.predicted))
    assert desc


def test_defaults_build_the_physical_hybrid_model():
    assert defaults()["params"] == "physical"
    predictor, desc = build_predictor({})
    assert isinstance(predictor.model, HybridModel)
    assert desc == "hybrid physics 'physical'"
    assert predictor.mode == "simulate" and predictor.gap_reset == GAP_RESET_S
    assert predictor.gap_reanchor == GAP_REANCHOR_S


def test_overrides_reach_the_model():
    M = [0.0005, 0.0001, 0.0001, 0.05]
    predictor, desc = build_predictor({"M": M, "motor_constant": 0.5, "band_gain": [1, 2, 3],
                                       "band_time_constant": [0.01, 0.02, 0.03]})
    model = predictor.model
    assert isinstance(model, HybridModel)
    np.testing.assert_allclose(model.rigid.M, np.reshape(M, (2, 2)))
    assert model.rigid.motor_constant == 0.5
    np.testing.assert_allclose(predictor.brake.gains, [1, 2, 3])
    np.testing.assert_allclose(predictor.brake.time_constants, [0.01, 0.02, 0.03])
    assert "band_gain" in desc and "M" in desc
    assert resolve({"M": M}).changes == ("M",)


def test_linear_model_and_effect_terms():
    predictor, desc = build_predictor({"A": A_OK, "B": B_OK})
    assert isinstance(predictor.model, LinearModel)
    np.testing.assert_allclose(predictor.model.A, np.reshape(A_OK, (2, 2)))
    assert desc == "linear A,B (2x2)"
    predictor, desc = build_predictor({"effects": _effects(
        {"kind": "coulomb", "member": [1, 0], "Fc": 0.3},
        {"kind": "delay", "seconds": 0.004},
        {"kind": "gain", "output": 0, "gain": 0.02})})
    assert predictor.output_delay == 0.004
    np.testing.assert_allclose(predictor.output_gain, [1.02, 1.0])
    assert "1 force term(s), delay 0.004 s" in desc


def test_physics_matches_the_parameter_set():
    params = load_parameters("thesis")
    predictor, _ = build_predictor({"params": "thesis"})
    assert isinstance(predictor.model, HybridModel)
    np.testing.assert_allclose(predictor.model.rigid.M,
                               HybridModel.from_params(params).rigid.M)


def test_load_parameter_builds_the_loaded_model():
    from dvt_model.hybrid import HybridModel
    from dvt_model.load import LOAD_PRESETS
    predictor, desc = build_predictor({"load": "arm-payload"})
    assert isinstance(predictor.model, HybridModel)
    assert predictor.model.load is LOAD_PRESETS["arm-payload"]
    assert "load 'arm-payload'" in desc
    bare, _ = build_predictor({})
    assert isinstance(bare.model, HybridModel) and bare.model.load is None
    assert predictor.model.rigid.M[1, 1] == pytest.approx(
        bare.model.rigid.M[1, 1] + LOAD_PRESETS["arm-payload"].reflected_inertia)


def test_detector_settings_from_parameters():
    from dvt_model.config import detector_config
    from dvt_model.errors import ParameterError

    setup = detector_config({})
    assert setup is not None
    assert setup.block == 10  # 10 ms at 1 kHz
    assert setup.config.sample_rate_hz == pytest.approx(100.0)
    assert setup.config.learn_s == 20.0
    assert setup.settle_s == 3.0
    assert resolve({}).detector == setup
    assert detector_config({"detector.enabled": False}) is None
    assert detector_config({"detector.block_s": 0.0}).block == 1
    one = detector_config({"detector.block_s": 0.0, "detector.sample_rate_hz": 500.0})
    assert one.config.sample_rate_hz == 500.0
    # together: at least 100 detector samples in the reference window
    with pytest.raises(ParameterError, match=r"detector\.learn_s: .*100 samples.*got 0\.5"):
        check_parameters({"detector.learn_s": 0.5})
    with pytest.raises(ParameterError, match=r"detector\.max_gap_s: .*got 0\.005"):
        check_parameters({"detector.max_gap_s": 0.005})
    with pytest.raises(DvtModelError, match=r"detector\.shift_sigma: -1"):
        check_parameters({"detector.shift_sigma": -1})


def test_model_key_follows_the_model_not_the_detector() -> None:
    """The key a carried colour belongs to (detector.colour_file): the detector's settings do
    not change it, a model parameter does; the defaults given or left out are the same."""
    base = model_key({})
    assert base == model_key(defaults())
    assert base == model_key({"detector.learn_s": 30.0, "detector.colour_file": "/tmp/c.json"})
    assert base != model_key({"params": "thesis"})
    assert base != model_key({"mode": "reanchor"})
    setup = detector_config({"detector.colour_file": "/tmp/c.json"})
    assert setup is not None and setup.colour_file == "/tmp/c.json"
    setup = detector_config({})
    assert setup is not None and setup.colour_file == ""
