"""The identifier's band priors (the ``dvt`` description's model effects) are not the simulated
plant's bands (the ``physical`` parameter set): a band figure on the plant starts off the
truth."""

from __future__ import annotations

import numpy as np

from dvt_identify.description import load_description
from dvt_model.params import load_parameters


def test_the_dvt_descriptions_band_priors_are_not_the_simulated_plants_bands() -> None:
    prior = {p.name: p.initial for e in load_description("dvt").make_model_effects()
             for p in e.params}
    gains = np.array([prior[f"band_gain_ring{k}"] for k in (1, 2, 3)])
    lags = np.array([prior[f"band_time_constant_brake{k}"] for k in (1, 2, 3)])
    plant = load_parameters("physical").brake
    assert np.all(np.abs(plant.gains / gains - 1.0) > 0.05), (plant.gains, gains)
    assert np.all(np.abs(plant.time_constants / lags - 1.0) > 0.1), (plant.time_constants, lags)
