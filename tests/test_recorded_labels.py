"""The rule the hidden-effect tests and ``scripts/effect_draws.py`` name a plant's effects by
(``recorded.named_as_drawn``): exactly the plant's effects where they act, each law a candidate
lacks by where its accepted stand-ins act; an extra, a misplaced or a missing effect fails."""

from __future__ import annotations

import pytest
from recorded import expected_labels, named_as_drawn

from dvt_driver.plant.hidden import load_hidden


def _acc(*labels: str) -> list[tuple[str, str, str]]:
    """``(effect name, where, label)`` of accepted labels ``effect@where[...]``."""
    out = []
    for label in labels:
        name, rest = label.split("@", 1)
        out.append((name, rest.split("(")[0].split(":")[0], label))
    return out


def test_each_preset_with_a_candidate_law_names_where_it_acts() -> None:
    want = {"coulomb": {"coulomb_friction@sun_shaft", "coulomb_friction@carrier3"},
            "windage": {"windage@sun_shaft", "windage@carrier3"},
            "delay": {"measurement_delay@sun_shaft", "measurement_delay@carrier3"},
            "backlash": {"backlash@carrier3(compliant)"},
            "wet_brake": {"brake_engagement@brakes(dead_time)"},
            "gravity_arm": {"gravity_load@carrier3"},
            "mesh_ripple": {"periodic_disturbance@sun_shaft"},
            "none": set()}
    for preset, labels in want.items():
        assert expected_labels(load_hidden(preset, draw=1)) == labels, preset


@pytest.mark.parametrize("labels,named", [
    (("coulomb_friction@sun_shaft", "coulomb_friction@carrier3"), True),
    (("coulomb_friction@carrier3",), False),                                   # one missing
    (("coulomb_friction@sun_shaft", "coulomb_friction@carrier3", "windage@carrier3"), False),
    (("coulomb_friction@sun_shaft", "windage@carrier3"), False),               # misplaced law
])
def test_coulomb_plant(labels: tuple[str, ...], named: bool) -> None:
    assert named_as_drawn(load_hidden("coulomb", draw=1), _acc(*labels)) is named


@pytest.mark.parametrize("labels,named", [
    (("coulomb_friction@sun_shaft", "stribeck_friction@carrier3",
      "coulomb_friction@carrier3"), True),
    (("coulomb_friction@sun_shaft", "coulomb_friction@carrier3"), True),
    (("stribeck_friction@carrier3",), False),                                  # sun missing
    (("coulomb_friction@sun_shaft", "coulomb_friction@carrier3", "windage@sun_shaft"), False),
])
def test_stribeck_plant_by_where_its_dry_frictions_act(labels: tuple[str, ...],
                                                       named: bool) -> None:
    hidden = load_hidden("stribeck", draw=1)
    assert set(hidden.stribeck) == {"sun", "carrier3"}
    assert named_as_drawn(hidden, _acc(*labels)) is named


@pytest.mark.parametrize("labels,named", [
    (("coulomb_friction@carrier3", "unlisted@carrier3: tau_carrier3 = ..."), True),
    (("unlisted@carrier3: tau_carrier3 = ...",), True),
    ((), False),
    (("coulomb_friction@sun_shaft",), False),
    (("unlisted@carrier3: tau_carrier3 = ...", "windage@sun_shaft"), False),
])
def test_position_friction_by_its_member(labels: tuple[str, ...], named: bool) -> None:
    assert named_as_drawn(load_hidden("position_friction", draw=1), _acc(*labels)) is named


def test_a_clean_plant_is_named_by_nothing() -> None:
    assert named_as_drawn(load_hidden("none", draw=1), []) is True
    assert named_as_drawn(load_hidden("none", draw=1), _acc("windage@carrier3")) is False
