"""Undeclared effects: the identifier finds what the plant hides, and nothing on a clean plant.

Estimation data: the committed recordings in ``bags/`` (made by the real chain: plant on a pty
-> driver -> recorder). Validation data: the same plant (its hidden effects read from the
recording's ``truth.yaml`` - only tests read it, never the identifier) driven offline through the
driver's supervisor with another experiment seed and noise seed. One augmentation round: the
first-ranked candidates are refitted and the best passing one accepted.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from dvt_driver.plant.hidden import parse_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_model.params import load_parameters

pytestmark = pytest.mark.slow
BAGS = Path(__file__).resolve().parents[1] / "bags"


def _identify(name: str, tmp_path: Path) -> IdentificationResult:
    bag = BAGS / name
    truth = yaml.safe_load((bag / "truth.yaml").read_text())
    made = yaml.safe_load((bag / "run.yaml").read_text())
    experiment = build(made["experiment"]["name"], seed=int(made["experiment"]["seed"]) + 100)
    val = record_offline(tmp_path / "val", experiment, load_parameters(truth["plant"]["params"]),
                         parse_hidden(truth["hidden"]), seed=int(truth["plant"]["seed"]) + 100)
    desc = load_description("dvt")
    est = load_segments([bag], desc)
    vals = load_segments([val], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = replace(LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate), max_effects=1)
    return identify(est, vals, desc, cfg, check=chk)


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
