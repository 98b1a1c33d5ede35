"""Per-band brake data in a parameter set (``brake.band_gain``, ``brake.band_time_constant``)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from dvt_model.errors import ParameterError
from dvt_model.params import load_parameters, parse_parameters
from dvt_model.presets import read_yaml_setting


def _raw(name: str) -> dict:
    data, _ = read_yaml_setting(name, what="parameter set", error=ParameterError,
                                package="dvt_model", directory="param_sets")
    return copy.deepcopy(dict(data))


def test_the_simulated_plants_bands_are_not_the_identifiers_prior() -> None:
    """The plant's set (`physical`) runs each band off the shared design law that the `thesis`
    set, and with it the identifier's priors, carry."""
    plant = load_parameters("physical").brake
    prior = load_parameters("thesis").brake
    assert np.all(np.abs(plant.gains / prior.gains - 1.0) > 0.05), plant.gains
    assert np.all(np.abs(plant.time_constants / prior.time_constants - 1.0) > 0.1), (
        plant.time_constants)


def test_per_band_overrides_are_read_and_checked() -> None:
    raw = _raw("thesis")
    raw["brake"]["band_gain"] = [6.0, 7.0, 8.0]
    raw["brake"]["band_time_constant"] = [0.01, 0.02, 0.03]
    p = parse_parameters(raw, "x.yaml")
    np.testing.assert_allclose(p.brake.gains, [6.0, 7.0, 8.0])
    np.testing.assert_allclose(p.brake.time_constants, [0.01, 0.02, 0.03])
    bad = copy.deepcopy(raw)
    bad["brake"]["band_gain"] = [6.0, 7.0]
    with pytest.raises(ParameterError, match=r"brake\.band_gain: expected a list of 3"):
        parse_parameters(bad, "x.yaml")
    bad = copy.deepcopy(raw)
    bad["brake"]["band_time_constant"] = [0.01, -0.02, 0.03]
    with pytest.raises(ParameterError, match=r"band_time_constant\[1"):
        parse_parameters(bad, "x.yaml")
    bad = copy.deepcopy(raw)
    bad["brake"]["band_gains"] = [6.0, 7.0, 8.0]
    with pytest.raises(ParameterError, match=r"brake\.band_gains: unknown key"):
        parse_parameters(bad, "x.yaml")


def test_describe_prints_each_bands_law() -> None:
    from dvt_model.cli import describe

    assert describe("physical")["band_gains"] == [8.9, 7.3, 8.5]
    assert describe("physical")["band_time_constants"] == [0.024, 0.017, 0.027]
    shared = describe("thesis")
    assert shared["band_gains"] == [shared["brake_static_torque_at_0.125A"] / 0.125] * 3
