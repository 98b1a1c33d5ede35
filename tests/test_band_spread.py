"""The band brakes as built: each band's own gain and engagement lag come back from the data.

The plant (preset ``bands``, :mod:`dvt_driver.plant.hidden`) replaces the parameter set's
bands (a unit as built, off the ``dvt`` description's priors 8.0 N m/A and 20 ms, the design
law) by a gain and a lag per band,
drawn per seed (gains 5.6-10.8 N m/A, lags 10-40 ms). Estimation and validation runs are the
shift-rich experiment (``ident_shifts``: 12 engagements against a slipping ring, every band
four times), made offline through the driver's supervisor in ``tmp_path`` with different
experiment and noise seeds. The identifier's baseline (the bands are its model effects, no
candidate added) must give every band's gain and lag within 3 reported standard deviations of
the plant's (:func:`recorded.within`, the HAC sandwich std of the output-error fit).

The lags came out 5-30 % short until the identifier held each step's lag value at the step
start; it now holds the step mean, as the model node and the plant do (``BrakeEngagement``).
Seed 41's band 1 lag then still came out 4.7 % long (6 std) at every fit step tried: the
identifier held each motor-current sample over the interval that follows it, so its torque
came half a sample late against the plant's (whose current moves during the interval). The
``dvt`` description now holds the motor current linear between samples and compares the sun
speed as the encoder's interval mean (``hold``, ``sampling``: ``dvt_identify.data.
intersample``), and every band of both plants is within 3 std (``scripts/band_lags.py
--draw 41 [--no-intersample]``, ``docs/identification.md`` section 2).

The test can fail: for the fixed draw (the preset's nominal plant, every value off the law),
it first checks that each prior lies more than 3 reported std from the truth, so a fit that
stayed at its start would fail the recovery check. One drawn seed adds a plant nobody chose.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from recorded import STD_BOUND, identify_bags, within

from dvt_driver.plant.hidden import HiddenEffects, load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify.description import load_description
from dvt_model.params import load_parameters

pytestmark = pytest.mark.slow

PARAMS = "physical"
"""The parameter set the plant runs (the committed recordings' plant)."""


def _identify(hidden: HiddenEffects, seed: int, tmp_path: Path
              ) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """Baseline fit on an estimation run (experiment and noise seed ``seed``) validated on
    another (``seed + 100``): parameters, their reported std, and the description's priors."""
    params = load_parameters(PARAMS)
    est = record_offline(tmp_path / "est", build("ident_shifts", seed=seed), params, hidden,
                         seed=seed)
    val = record_offline(tmp_path / "val", build("ident_shifts", seed=seed + 100), params,
                         hidden, seed=seed + 100)
    r = identify_bags(est, val, max_effects=0)
    # the priors: the description's initial values
    desc = load_description("dvt")
    priors = {q.name: q.initial for e in desc.make_model_effects() for q in e.params}
    return r.baseline.parameters(), r.baseline.fit.parameter_std(), priors


def _truth(hidden: HiddenEffects) -> dict[str, float]:
    """The plant's band values by the identifier's parameter names."""
    assert hidden.bands is not None and hidden.bands.gain and hidden.bands.time_constant
    out = {}
    for k in (1, 2, 3):
        out[f"band_gain_ring{k}"] = hidden.bands.gain[k - 1]
        out[f"band_time_constant_brake{k}"] = hidden.bands.time_constant[k - 1]
    return out


GAIN_TOLERANCE = 0.03
"""Relative error allowed for a band's gain (measured at most 0.8 %, seed 41 band 2, with the
step-mean hold and the motor current held linear; 1.9 % before the step-mean hold; the priors
lie 11-26 % from the plants' gains)."""

_RESULTS: dict[int | None, tuple[dict[str, float], dict[str, float], dict[str, float]]] = {}


def _cached(draw: int | None, tmp_path: Path
            ) -> tuple[HiddenEffects, tuple[dict[str, float], dict[str, float], dict[str, float]]]:
    hidden = load_hidden("bands", draw=draw)
    if draw not in _RESULTS:
        _RESULTS[draw] = _identify(hidden, 31 if draw is None else draw, tmp_path)
    return hidden, _RESULTS[draw]


@pytest.mark.parametrize("draw", [None, 41], ids=["fixed", "seed41"])
def test_each_bands_gain_moves_from_the_prior_to_the_plants(draw: int | None,
                                                           tmp_path: Path) -> None:
    """Every band's gain within 3 % of the plant's, while its prior is more than 10 % off (a
    fit that stayed at its start fails)."""
    hidden, (p, _sd, priors) = _cached(draw, tmp_path)
    truth = _truth(hidden)
    for k in (1, 2, 3):
        name = f"band_gain_ring{k}"
        assert name in p, f"not identified: {name} (parameters {sorted(p)})"
        assert abs(priors[name] - truth[name]) > 0.1 * truth[name], (name, priors[name])
        assert abs(p[name] - truth[name]) <= GAIN_TOLERANCE * truth[name], (
            f"{name}: estimate {p[name]:.4g} vs the plant's {truth[name]:.4g} (prior "
            f"{priors[name]:.4g})")


@pytest.mark.parametrize("draw", [None, 41],
                         ids=["fixed", "seed41"])
def test_each_bands_gain_and_lag_are_the_plants(draw: int | None, tmp_path: Path) -> None:
    """Every band's gain [N m/A] and engagement time constant [s] within 3 reported std of the
    plant's; for the fixed draw, every prior more than 3 std off (the check has power)."""
    hidden, (p, sd, priors) = _cached(draw, tmp_path)
    truth = _truth(hidden)
    missing = sorted(set(truth) - set(p))
    assert not missing, f"not identified: {missing} (parameters {sorted(p)})"
    report = {n: (p[n], sd[n], truth[n], priors[n]) for n in truth}
    print("\nname: estimate, std, truth, prior", report)
    if draw is None:
        for name, t in truth.items():
            assert abs(priors[name] - t) > STD_BOUND * sd[name], (
                f"{name}: prior {priors[name]} within {STD_BOUND} std ({sd[name]:.3g}) of the "
                f"truth {t}: the check below could not fail")
    for name, t in truth.items():
        within(name, p[name], sd[name], t)
