"""A fit you can trust on ordinary inputs: any rate and any mix of recordings, no traceback,
candidates that cannot be built for a rate skipped with a note; the fit reaches the accuracy of
the best fit of the same structure on the committed recordings.

Estimation data: the committed recordings in ``bags/``; validation: ``bags/ident-none-val``,
a second offline run of the same plant preset (``scripts/make_validation_bags.py``). Only the
tests read ``truth.yaml`` (for M and D), never the identifier.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dvt_identify.description import load_description
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.pipeline import drop_unexcited_model_effects, load_segments

BAGS = Path(__file__).resolve().parents[1] / "bags"


def _cut(segs, seconds):
    out = []
    for s in segs:
        n = min(s.n, round(seconds / s.dt))
        out.append(s.rows(0, n))
    return out


def _setup(est_bags, val_bag, val_seconds=8.0):
    desc = load_description("dvt")
    est = load_segments([BAGS / b for b in est_bags], desc)
    val = _cut(load_segments([BAGS / val_bag], desc), val_seconds)
    desc, _ = drop_unexcited_model_effects(desc, est)
    return desc, est, val


def test_62_5_hz_recording_with_the_default_description() -> None:
    desc, est, val = _setup(["thesis-none"], "ident-none-val")
    desc = replace(desc, candidates=tuple(
        c for c in desc.candidates if c.effect in ("measurement_delay", "backlash")))
    cfg = replace(LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate),
                  max_effects=1, max_tries_per_round=1)
    r = identify(est, val, desc, cfg)
    assert r.fit_dt == pytest.approx(est[0].dt)  # auto: fitted at its own 62.5 Hz
    # at 62.5 Hz the compliant play is scored (contact frequencies below 196 rad/s)
    assert any(s.label == "backlash@carrier3(compliant)" for s in r.rounds[0])
    # (validated on an ident run with gear shifts the thesis run never made: no figure asserted)
    assert min(r.baseline.est.fit_percent) > 80.0, r.baseline.est.fit_percent
    # the old fixed factor 5 (12.5 Hz): the compliant play cannot be built, skipped with a note
    r5 = identify(est, val, desc, replace(cfg, fit_decimate=5, augment=False))
    skipped = [n for n in r5.notes if n.startswith("candidate skipped")]
    assert any("backlash@carrier3" in n and "12.5 Hz" in n for n in skipped), r5.notes


def test_recordings_of_different_rates_fit_jointly() -> None:
    desc, est, val = _setup(["ident-none-1", "thesis-none"], "ident-none-val")
    assert sorted(1 / s.dt for s in est) == pytest.approx([62.5, 1000.0], rel=1e-3)
    # the candidates whose scoring depends on the rate (delay scan, contact-frequency scan)
    # and one force effect: keeps the test short
    desc = replace(desc, candidates=tuple(
        c for c in desc.candidates
        if c.effect == "measurement_delay" or c.options.get("compliant")
        or (c.effect == "coulomb_friction" and c.where == "sun_shaft")))
    cfg = replace(LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate),
                  max_effects=1, max_tries_per_round=1)
    r = identify(est, val, desc, cfg)
    assert any("different rates" in n for n in r.notes), r.notes
    assert r.rounds and r.rounds[0]  # scored, the delay scan included
    delay = [s for s in r.rounds[0] if s.effect.name == "measurement_delay"]
    assert delay and "delay_scan" in delay[0].extra
    assert min(r.baseline.val.fit_percent) > 95.0


@pytest.mark.slow
def test_clean_baseline_reaches_the_reference_accuracy() -> None:
    """The reference (multiple shooting, CasADi + IPOPT) reaches 98.89 / 98.74 % on this pair;
    M and D within 2 % of the plant."""
    from dvt_model.hybrid import HybridModel
    from dvt_model.params import load_parameters

    desc, est, val = _setup(["ident-none-1"], "ident-none-val", val_seconds=1e9)
    cfg = replace(LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate),
                  augment=False)
    r = identify(est, val, desc, cfg)
    assert r.baseline.fit.suspect_ == []
    assert min(r.baseline.val.fit_percent) > 98.6
    p = r.baseline.parameters()
    rigid = HybridModel.from_params(load_parameters("physical")).rigid
    M = np.array([[p["M11"], p["M12"]], [p["M12"], p["M22"]]])
    D = np.array([[p["D11"], p["D12"]], [p["D12"], p["D22"]]])
    assert np.max(np.abs(M / rigid.M - 1)) < 0.02
    assert np.max(np.abs(D / rigid.D - 1)) < 0.02
