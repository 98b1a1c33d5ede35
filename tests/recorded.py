"""Identification on a committed recording in ``bags/`` with a fresh validation run of the same
plant, and the plant's drawn truth (shared by the tests on undeclared effects).

Validation data: the plant whose hidden effects the recording's ``truth.yaml`` names (only tests
read it, never the identifier; the drawn values, :mod:`dvt_driver.plant.hidden.draw`), driven
offline through the driver's supervisor with another experiment seed and noise seed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

from dvt_driver.plant.hidden import HiddenEffects, parse_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_model.params import load_parameters
from dvt_model.recording import read_run_info, read_truth

BAGS = Path(__file__).resolve().parents[1] / "bags"

PLANT_MEMBER = {"sun": "sun_shaft", "carrier3": "carrier3"}
"""The plant's kinematic member -> the dvt description's state (``where``) it is."""

STD_BOUND = 3.0
"""An estimate must lie within this many reported standard deviations of the truth."""


def truth_effects(bag: Path) -> HiddenEffects:
    """The plant of recording ``bag``: the hidden effects its ``truth.yaml`` states (the drawn
    values; ``draw`` the record of the draw, ``None`` for a preset without distributions)."""
    truth = read_truth(bag)
    assert truth is not None, f"{bag}: no truth.yaml"
    h = parse_hidden(truth["hidden"], source=f"{bag.name}/truth.yaml")
    return dataclasses.replace(h, draw=truth.get("hidden_draw"))


def expected_labels(t: HiddenEffects) -> set[str]:
    """The accepted effects that name plant ``t``'s hidden effects where they act, in the
    ``dvt`` description's labels (``effect@where``), for every effect whose law a candidate
    has (none for the plant's Stribeck curve and its friction that depends on position:
    :func:`named_as_drawn` names those by where the accepted effects act)."""
    out = {f"coulomb_friction@{PLANT_MEMBER[m]}" for m in t.coulomb}
    out |= {f"windage@{PLANT_MEMBER[m]}" for m in t.windage}
    if t.measurement_delay > 0:  # the plant delays both speed measurements
        out |= {"measurement_delay@sun_shaft", "measurement_delay@carrier3"}
    if t.backlash is not None:
        # play in a compliant spline to a load behind the carrier-3 tachometer: the load's
        # impacts make the measured speed a staircase only the compliant play explains
        assert t.backlash.where == "carrier3_output", t.backlash.where
        out.add("backlash@carrier3(compliant)")
    if t.wet_brake:
        # no torque while the oil film is squeezed out, then an S-shaped rise: one engagement
        # dead time shared by the three bands explains it
        out.add("brake_engagement@brakes(dead_time)")
    if t.gravity_arm is not None:
        out.add("gravity_load@carrier3")
    if t.mesh_ripple is not None:  # periodic in the sun's own angle
        out.add("periodic_disturbance@sun_shaft")
    return out


def named_as_drawn(t: HiddenEffects, accepted: Sequence[tuple[str, str, str]]) -> bool:
    """Whether the accepted effects ``(effect name, where, label)`` name what plant ``t``
    hides, where it acts, and nothing else: the labels of :func:`expected_labels`, and for
    the laws no candidate has a dry friction (Coulomb or Stribeck) on each member with the
    plant's Stribeck curve and on no other, and for a friction that depends on position only
    effects on its member (at least one)."""
    expected = expected_labels(t)
    if not expected <= {label for _, _, label in accepted}:
        return False
    rest = [(n, w) for n, w, label in accepted if label not in expected]
    if t.stribeck:
        members = {PLANT_MEMBER[m] for m in t.stribeck}
        dry = [(n, w) for n, w in rest if n in ("coulomb_friction", "stribeck_friction")]
        if {w for _, w in dry} != members:
            return False
        rest = [x for x in rest if x not in dry]
    if t.position_friction:
        members = {PLANT_MEMBER[m] for m in t.position_friction}
        if not any(w in members for _, w in rest):
            return False
        rest = [x for x in rest if x[1] not in members]
    return not rest


def within(name: str, estimate: float, std: float, truth: float,
           bound: float = STD_BOUND) -> None:
    """Assert ``|estimate - truth| <= bound * std`` (``std`` finite and > 0), naming the
    parameter and the figures."""
    assert math.isfinite(std) and std > 0, f"{name}: no usable reported std ({std})"
    z = abs(estimate - truth) / std
    assert z <= bound, (f"{name}: estimate {estimate:.6g} +- {std:.3g} (1 std) vs truth "
                        f"{truth:.6g}: {z:.2f} std off (bound {bound:g})")


def validation_run(name: str, out: Path) -> Path:
    """Record the validation run of recording ``name`` into ``out`` (experiment and noise seeds
    + 100, the same drawn plant); its path."""
    bag = BAGS / name
    truth = read_truth(bag)
    made = read_run_info(bag)
    assert truth is not None and made is not None, f"{bag}: truth.yaml and run.yaml needed"
    experiment = build(made["experiment"]["name"], seed=int(made["experiment"]["seed"]) + 100)
    return record_offline(out, experiment, load_parameters(truth["plant"]["params"]),
                          truth_effects(bag), seed=int(truth["plant"]["seed"]) + 100)


def identify_recorded(name: str, tmp_path: Path, max_effects: int | None = None
                      ) -> tuple[IdentificationResult, Path]:
    """Identify the ``dvt`` description on recording ``name`` (estimation) and its validation
    run (recorded under ``tmp_path / 'val'``), at most ``max_effects`` accepted effects
    (``None``: the description's own, 3 rounds); the result and the validation run's path."""
    val = validation_run(name, tmp_path / "val")
    return identify_bags(BAGS / name, val, max_effects), val


def identify_bags(est_bag: Path, val_bag: Path, max_effects: int | None = None,
                  fit_decimate: int | None = None) -> IdentificationResult:
    """Identify the ``dvt`` description on ``est_bag`` validated on ``val_bag`` as
    ``dvt-identify`` does (identifiability check applied), at most ``max_effects`` accepted
    effects (``None``: the description's own; 0: the baseline only), fitted at the
    description's rate or with ``fit_decimate`` (``dvt-identify --fit-decimate``)."""
    desc = load_description("dvt")
    est = load_segments([est_bag], desc)
    vals = load_segments([val_bag], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate)
    if max_effects is not None:
        cfg = dataclasses.replace(cfg, max_effects=max_effects)
    if fit_decimate is not None:
        cfg = dataclasses.replace(cfg, fit_decimate=fit_decimate)
    return identify(est, vals, desc, cfg, check=chk)
