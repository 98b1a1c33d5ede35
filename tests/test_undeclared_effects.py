"""Undeclared effects: the identifier finds what the plant hides, where it acts, with the plant's
drawn values, over the description's whole loop; nothing on a clean plant.

Estimation data: the committed recordings in ``bags/`` (made by the real chain: plant on a pty
-> driver -> recorder, ``scripts/make_bags.sh``). Each effect plant drew its magnitudes from its
seed (:mod:`dvt_driver.plant.hidden.draw`): the recording's ``truth.yaml`` holds the drawn
values, which only the tests read, never the identifier. Validation data: the same drawn plant
driven offline through the driver's supervisor with another experiment seed and noise seed
(:mod:`recorded`). The loop runs the description's own ``max_effects`` (3 rounds): a second
and third round must add nothing that is not in the plant.

Checked for every plant: every effect accepted is one of the plant's, at the member (or input,
or output) where the plant has it (no false or misplaced cause in any round); each is
significant on validation (Diebold-Mariano); an effect of the plant that is not accepted was
tried and lost only for power (it lowered the validation error, but not significantly at the
description's alpha on these 33 s: a drawn magnitude can be small); the plant's drawn values
are recovered for what was accepted. Tolerance rule: ``|estimate - truth| <= 3 std``, ``std``
the reported standard deviation (:meth:`OEFit.parameter_std`, the HAC sandwich covariance of the
output-error fit). Where the identifier's law is not the plant's, or the report has no usable
std, each check states its bound and why (delay: a quarter sample; engagement dead time: between
the plant's squeeze-film time and the middle of its rise; backlash: a factor 2, the scan grid's
resolution).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from recorded import (
    BAGS,
    PLANT_MEMBER,
    expected_labels,
    identify_recorded,
    named_as_drawn,
    truth_effects,
    within,
)

from dvt_driver.plant.hidden import HiddenEffects
from dvt_identify.effects.brakes import EngagementDeadTime
from dvt_identify.loop import IdentificationResult

pytestmark = pytest.mark.slow

SAMPLE_PERIOD = 1e-3
"""Sample period of the identification recordings [s]."""


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory
            ) -> dict[str, tuple[IdentificationResult, HiddenEffects]]:
    """Identification result and drawn truth per recording (made lazily, once per module)."""
    return {}


def _identify(results: dict[str, tuple[IdentificationResult, HiddenEffects]],
              tmp_path_factory: pytest.TempPathFactory, bag: str
              ) -> tuple[IdentificationResult, HiddenEffects]:
    if bag not in results:
        r, _ = identify_recorded(bag, tmp_path_factory.mktemp(bag))
        assert r.config.max_effects >= 3
        results[bag] = (r, truth_effects(BAGS / bag))
    return results[bag]


def test_clean_plant_accepts_nothing(tmp_path: Path) -> None:
    """A clean plant: nothing accepted in any of the 3 rounds; the baseline fits."""
    r, _ = identify_recorded("ident-none-1", tmp_path)
    assert r.config.max_effects >= 3
    assert r.accepted == []
    assert r.final is r.baseline
    # the baseline is already good on clean data: the physics structure is right
    assert min(r.baseline.val.fit_percent) > 96.0


# -- the recordings whose effect's law a candidate has (labels: recorded.expected_labels) ------

LABELLED = ("ident-coulomb", "ident-windage", "ident-delay", "ident-backlash", "ident-wet_brake")


def _stribeck_where(r: IdentificationResult, t: HiddenEffects) -> None:
    """The plant's Stribeck curve (static + Coulomb + regularised sign) has a form no
    candidate has: every accepted effect is a dry friction (Coulomb or Stribeck) on a member
    where the plant has its curve, and every such member gets one."""
    got = [(d.score.effect.name, d.score.effect.where, d.score.label) for d in r.accepted]
    assert named_as_drawn(t, got), got


@pytest.mark.parametrize("bag", [*LABELLED, "ident-stribeck"])
def test_hidden_effect_is_found_where_it_acts(
        bag: str, results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Round 1 ranks a cause of the plant's effect first and accepts one; after 3 rounds every
    accepted effect is the plant's, where the plant has it (member, input or output), accepted
    by the validation test (Diebold-Mariano, HAC variance) with its evidence; an effect of the
    plant left out was tried and lowered the validation error, only not significantly."""
    r, truth = _identify(results, tmp_path_factory, bag)
    assert truth.draw is not None and not truth.draw["fixed"], "not a drawn plant"
    assert r.rounds, "no scoring round ran"
    labels = [d.score.label for d in r.accepted]
    if bag == "ident-stribeck":
        assert r.rounds[0][0].effect.name in ("coulomb_friction", "stribeck_friction")
        _stribeck_where(r, truth)
    else:
        expected = expected_labels(truth)
        assert r.rounds[0][0].label in expected, [s.label for s in r.rounds[0][:4]]
        assert labels and set(labels) <= expected, [d.as_dict() for d in r.decisions]
        assert r.accepted[0].round == 1
        for missed in sorted(expected - set(labels)):
            # its last try (an earlier one may have passed and lost to a larger cause)
            tried = [d for d in r.decisions if d.score.label == missed]
            assert tried, f"{missed}: never tried"
            v = tried[-1].validation
            assert v is not None and v.gain > 0 and not v.p_value < r.config.alpha, (
                f"{missed}: lost for another reason than power", tried[-1].as_dict())
            print(f"\n{bag}: {missed} not accepted (power): validation p = {v.p_value:.3g}")
    gain = r.final.val.mean_fit - r.baseline.val.mean_fit
    assert gain > 0.0, (r.baseline.val.fit_percent, r.final.val.fit_percent)
    for d in r.accepted:
        dm = d.validation
        assert dm is not None and dm.gain > 0 and dm.p_value < r.config.alpha, d.as_dict()
    assert r.drift is not None
    assert r.drift.drifting == [], r.drift.summary()


# -- the drawn values ----------------------------------------------------------------------------

def _estimates(r: IdentificationResult) -> tuple[dict[str, float], dict[str, float]]:
    return r.final.parameters(), r.final.fit.parameter_std()


def test_coulomb_levels_are_the_drawn_ones(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each accepted member's Coulomb level ``Fc`` within 3 reported std of the drawn level."""
    r, truth = _identify(results, tmp_path_factory, "ident-coulomb")
    p, sd = _estimates(r)
    names = [f"Fc_{PLANT_MEMBER[m]}" for m in truth.coulomb]
    assert any(n in p for n in names), p
    for member, fc in truth.coulomb.items():
        name = f"Fc_{PLANT_MEMBER[member]}"
        if name in p:
            within(name, p[name], sd[name], fc)


def test_windage_coefficients_are_the_drawn_ones(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each accepted member's quadratic drag ``Cw`` within 3 reported std of the drawn
    coefficient (a member whose windage lost for power has no estimate).

    Measured 2026-11-28 on ``ident-windage`` re-recorded with the plant's bands as built (draw
    15: Cw sun 5.532e-6, carrier 3 8.474e-5 N m s^2): both accepted, Cw_sun_shaft 5.471e-6 +-
    2.07e-8 (-2.96 std: at the edge), Cw_carrier3 8.525e-5 +- 1.04e-6 (+0.49 std). On the
    earlier recording (bands at the priors) the carrier-3 windage lost for power in round 2
    and the sun's absorbed it (13 std off): this test was a strict xfail until then."""
    r, truth = _identify(results, tmp_path_factory, "ident-windage")
    p, sd = _estimates(r)
    names = [f"Cw_{PLANT_MEMBER[m]}" for m in truth.windage]
    assert any(n in p for n in names), p
    for member, cw in truth.windage.items():
        name = f"Cw_{PLANT_MEMBER[member]}"
        if name in p:
            within(name, p[name], sd[name], cw)


def test_stribeck_sliding_levels_are_the_drawn_ones(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """The sliding level: a Coulomb ``Fc`` accepted on a member within 3 reported std of the
    drawn ``Fc`` (the curve's level above its Stribeck speed). A strict xfail until
    2026-11-28: it passed in a plain process and failed in the suite, where numpy was loaded
    before the dvt packages could hold BLAS to one thread, and two threads' last bits moved
    the last refit's stop (Fc sun 3.5 std off instead of 2.5); ``dvt_model.one_blas_thread``
    now holds it to one thread in every process. Measured since the final refit at the
    recording's rate (2026-12-05): Fc sun 1.9 std, Fc carrier 3 0.4 std."""
    r, truth = _identify(results, tmp_path_factory, "ident-stribeck")
    p, sd = _estimates(r)
    checked = 0
    for member, curve in truth.stribeck.items():
        where = PLANT_MEMBER[member]
        if f"Fc_{where}" in p:
            within(f"Fc_{where}", p[f"Fc_{where}"], sd[f"Fc_{where}"], curve.Fc)
            checked += 1
    assert checked == len(truth.stribeck), (checked, sorted(p))


@pytest.mark.xfail(strict=True, reason=(
    "known bias: the sun's Stribeck hump is not in the final model (it passes every test in "
    "round 3 but loses the round to carrier 3's; the description's max_effects = 3 ends the "
    "loop there, and with 4 the residual verdict ends it in round 4: sun 0 %, carrier 3 13 % "
    "of the validation residual's variance above the sensor-noise floor; measured "
    "2026-12-06), and carrier 3's hump absorbs it through the coupling: Fs carrier 3 0.2807 "
    "+- 0.0082 against the drawn excess 0.2539, 3.3 std (docs/identification.md section 3)"))
def test_stribeck_hump_is_the_drawn_excess(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """A Stribeck term accepted on a member: its break-away excess ``Fs`` within 3 reported std
    of the drawn ``Fs - Fc`` (the identifier's Stribeck term is the excess over the Coulomb
    level). Strict xfail since 2026-12-05: at the decimated step the hump came out within
    1.9 std (0.2267 +- 0.0145), refitted at the recording's rate it is 3.12 std high with the
    sun's hump missing from the model; on fresh draws of the preset (``scripts/results.sh
    draws``) 8-16 std high. It passes only once the model carries every hump the plant has
    (then remove the mark)."""
    r, truth = _identify(results, tmp_path_factory, "ident-stribeck")
    p, sd = _estimates(r)
    checked = 0
    for member, curve in truth.stribeck.items():
        where = PLANT_MEMBER[member]
        if f"Fs_{where}" in p:
            within(f"Fs_{where}", p[f"Fs_{where}"], sd[f"Fs_{where}"], curve.Fs - curve.Fc)
            checked += 1
    assert checked >= 1, sorted(p)


def test_measurement_delays_are_the_drawn_one(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each speed's delay is the drawn delay, within 3 std or a quarter sample (0.25 ms),
    whichever is wider. The ``dvt`` description says how the signals behave between samples
    (``dvt_identify.data.intersample``): the measured motor current is held linear (its
    interval mean; held as sampled, the model's torque came half a sample late and the
    tachometer showed ``delay - T/2``) and the sun speed, encoder counts over the last
    period, is compared half a period back. A quarter sample: the chain's stamp mapping
    jitters by a fraction of a sample (0.1 ms measured), which the reported std (noise only)
    omits."""
    r, truth = _identify(results, tmp_path_factory, "ident-delay")
    p, sd = _estimates(r)
    assert "delay_sun_shaft" in p or "delay_carrier3" in p, p
    timing = {"sun_shaft": 0.0, "carrier3": 0.0}
    for where, offset in timing.items():
        name = f"delay_{where}"
        if name not in p:
            continue
        bound = max(3.0, 0.25 * SAMPLE_PERIOD / sd[name])
        within(name, p[name], sd[name], truth.measurement_delay + offset, bound=bound)


def test_engagement_dead_time_matches_the_drawn_wet_bands(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """The one dead time acts on every band the plant's wet shape is on (all three), and lies
    between the drawn squeeze-film time and the middle of the drawn asperity rise
    (``viscous_time <= td <= viscous_time + asperity_time / 2``). Why a range and not 3 std:
    the identifier's law (nothing for ``td``, then the first-order lag) is not the plant's
    (film shear for ``viscous_time``, then a smoothstep over ``asperity_time``); a dead time
    placed before the squeeze-film end or after the rise's middle would be a wrong engagement."""
    r, truth = _identify(results, tmp_path_factory, "ident-wet_brake")
    (d,) = r.accepted
    eff = d.score.effect
    assert isinstance(eff, EngagementDeadTime)
    names = r.description.inputs
    assert {names[i].name for i in eff.indices} == {f"brake{k}" for k in truth.wet_brake}
    shapes = set(truth.wet_brake.values())
    assert len(shapes) == 1, "the bands' shapes differ: one dead time cannot be all of them"
    (shape,) = shapes
    td = r.final.parameters()["td_brakes"]
    assert shape.viscous_time <= td <= shape.viscous_time + 0.5 * shape.asperity_time, (
        td, shape)


def test_backlash_gap_is_the_drawn_one_within_3_std(
        results: dict[str, tuple[IdentificationResult, HiddenEffects]],
        tmp_path_factory: pytest.TempPathFactory) -> None:
    """The play in the spline within 3 reported std of the drawn gap, and the structure's std
    not collapsed by it. The rattling load is chaotic: the fit passes the play's map as the
    identity to the tangents, takes a wide secant along its own parameters and adds where the
    fit lands with that secant halved and doubled to the std (before, its divergence went into
    the Jacobian: every std about 1e6 too small, the gap left at the scorer's grid value;
    docs/identification.md section 2). Measured: 0.04099 +- 0.00078 rad against the drawn
    0.04158 (0.75 std)."""
    r, truth = _identify(results, tmp_path_factory, "ident-backlash")
    assert truth.backlash is not None
    p, sd = _estimates(r)
    gap = p["gap_carrier3"]
    assert sd["M11"] > 0.2 * r.baseline.fit.parameter_std()["M11"], sd
    assert abs(gap - truth.backlash.gap) <= 3.0 * sd["gap_carrier3"], (gap, sd, truth.backlash)
