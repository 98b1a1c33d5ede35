"""Undeclared effects: the identifier finds what the plant hides, and nothing on a clean plant.

Estimation data: the committed recordings in ``bags/`` (made by the real chain: plant on a pty
-> driver -> recorder). Validation data: the same plant (its hidden effects read from the
recording's ``truth.yaml`` - only tests read it, never the identifier) driven offline through the
driver's supervisor with another experiment seed and noise seed (:mod:`recorded`). One
augmentation round: the first-ranked candidates are refitted and the best passing one accepted.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from recorded import identify_recorded

from dvt_identify.loop import IdentificationResult

pytestmark = pytest.mark.slow


def _identify(name: str, tmp_path: Path) -> IdentificationResult:
    return identify_recorded(name, tmp_path)[0]


def test_clean_plant_accepts_nothing(tmp_path: Path) -> None:
    r = _identify("ident-none-1", tmp_path)
    assert r.accepted == []
    assert r.final is r.baseline
    # the baseline is already good on clean data: the physics structure is right
    assert min(r.baseline.val.fit_percent) > 96.0


@pytest.mark.parametrize(("bag", "expected"), [
    ("ident-coulomb", {"coulomb_friction"}),
    # the plant's Stribeck curve (static + Coulomb + regularised sign) has a form no candidate
    # has: a friction term on the right member must be found
    ("ident-stribeck", {"coulomb_friction", "stribeck_friction"}),
    ("ident-delay", {"measurement_delay"}),
    ("ident-windage", {"windage"}),
    # play in a compliant spline to a load behind the carrier-3 tachometer: the load's
    # impacts make the measured speed a staircase only the compliant play explains
    ("ident-backlash", {"backlash"}),
    # wet bands (shift-rich run): no torque while the oil film is squeezed out, then an
    # S-shaped rise; one engagement dead time shared by the three bands explains it
    ("ident-wet_brake", {"brake_engagement"}),
])
def test_hidden_effect_is_ranked_first_and_accepted(bag: str, expected: set[str],
                                                   tmp_path: Path) -> None:
    r = _identify(bag, tmp_path)
    assert r.rounds, "no scoring round ran"
    first = r.rounds[0][0]
    assert first.effect.name in expected, [s.label for s in r.rounds[0][:4]]
    accepted = r.accepted
    assert accepted and accepted[0].score.effect.name in expected
    gain = r.final.val.mean_fit - r.baseline.val.mean_fit
    assert gain > 0.0, (r.baseline.val.fit_percent, r.final.val.fit_percent)
    # accepted by the validation test (Diebold-Mariano, HAC variance), with its evidence
    dm = accepted[0].validation
    assert dm is not None and dm.gain > 0 and dm.p_value < r.config.alpha, dm
    assert r.drift is not None
    assert r.drift.drifting == [], r.drift.summary()
