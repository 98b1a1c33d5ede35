"""The choice among a round's passing trials (:func:`dvt_identify.selection.choose`): the simplest
of those as good on validation as the largest-LR one.

The trials are real :class:`Decision` objects for real effects; their stages are stand-ins that
carry only what the validation test reads (the validation simulation and the output weights),
so each case sets the validation errors exactly."""

from __future__ import annotations

from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest

from dvt_identify.data import Segment, make_segment
from dvt_identify.effects import Effect, make_effect
from dvt_identify.scoring import CandidateScore
from dvt_identify.selection import choose, shape_parameters
from dvt_identify.stages import Decision, Stage

DT = 0.002
N = 2000
ALPHA = 0.01


def effect(name: str, **options: object) -> Effect:
    """A candidate on the 1-DOF toy's speed ``v`` (input ``force``)."""
    return make_effect(name, "v", ["v"], ["force"], "N", "m/s", options=dict(options))


def validation() -> tuple[list[Segment], np.ndarray]:
    """One validation segment and a reference error (white, RMS 0.05 m/s), shape (N, 1)."""
    rng = np.random.default_rng(7)
    t = np.arange(N) * DT
    y = np.sin(2 * np.pi * 0.7 * t)[:, None]
    seg = make_segment("val", t, np.zeros(N), y[:, 0], ["force"], ["v"])
    return [seg], 0.05 * rng.normal(size=(N, 1))


def trial(eff: Effect, lr: float, err: np.ndarray, val: list[Segment]) -> Decision:
    """A passing trial for ``eff`` with likelihood ratio ``lr`` whose validation simulation
    misses the measurement by ``err`` (N, 1)."""
    score = CandidateScore(effect=eff, r2=0.01, r2_raw=0.01, lm=100.0, dof=1, p_value=1e-20,
                           corr=0.1, corr_raw=0.1, variant="", variants=[], implied={})
    stage = SimpleNamespace(val_pred=[s.y - err for s in val],
                            fit=SimpleNamespace(weights_=np.ones(1)))
    return Decision(1, score, True, f"LR {lr:.4g} > 9.21", lr=lr, lr_threshold=9.21,
                    dof=len(eff.params), delta_bic=-lr / 2, stage=cast(Stage, stage))


def test_shape_parameters_of_real_effects() -> None:
    assert shape_parameters(effect("coulomb_friction")) == ()
    assert shape_parameters(effect("windage")) == ()
    assert shape_parameters(effect("stribeck_friction")) == ("vs",)
    # compliant play: the gap is the gain, the contact frequency and damping shape it
    play = make_effect("backlash", "v", ["v"], ["force"], options={"compliant": True})
    assert shape_parameters(play) == ("wn", "zeta")


def test_tie_of_equal_size_goes_to_the_law_without_shape_parameter() -> None:
    val, e = validation()
    # the same errors in reverse order: the same validation loss, no significant difference
    stribeck = trial(effect("stribeck_friction"), 60.2, e[::-1], val)
    coulomb = trial(effect("coulomb_friction"), 57.1, e, val)
    assert stribeck.dof == coulomb.dof == 2
    c = choose([stribeck, coulomb], val, ALPHA)
    assert c.chosen is coulomb
    assert c.largest_lr is stribeck
    assert len(c.tied) == 2 and c.p_values[1] > ALPHA
    [(loser, why)] = c.losers
    assert loser is stribeck
    assert why.startswith("coulomb_friction@v is as good on validation (Diebold-Mariano p = ")
    assert "simpler (no shape parameter; this one fits vs)" in why
    assert "at a smaller LR (57.1 < 60.2)" in why


def test_richer_law_significantly_better_on_validation_still_wins() -> None:
    val, e = validation()
    stribeck = trial(effect("stribeck_friction"), 60.2, 0.7 * e, val)
    coulomb = trial(effect("coulomb_friction"), 57.1, e, val)
    c = choose([coulomb, stribeck], val, ALPHA)
    assert c.chosen is stribeck
    assert [d for d in c.tied] == [stribeck]
    assert c.p_values[0] < ALPHA
    [(loser, why)] = c.losers
    assert loser is coulomb
    assert why.startswith("stribeck_friction@v has the larger LR (60.2 > 57.1) and is "
                          "significantly better on validation (error -51 % against it, "
                          "Diebold-Mariano p = ")


def test_fewer_parameters_win_a_tie() -> None:
    val, e = validation()
    coulomb = trial(effect("coulomb_friction"), 48.0, e[::-1], val)  # Fc, offset
    windage = trial(effect("windage"), 45.5, e, val)  # Cw
    c = choose([coulomb, windage], val, ALPHA)
    assert c.chosen is windage
    assert dict((d.score.label, w) for d, w in c.losers)["coulomb_friction@v"].endswith(
        "and simpler (1 estimated parameter instead of 2), at a smaller LR (45.5 < 48)")


def test_tie_of_equal_complexity_goes_to_the_larger_lr() -> None:
    val, e = validation()
    coulomb = trial(effect("coulomb_friction"), 48.0, e[::-1], val)
    asym = trial(effect("asymmetric_friction"), 47.0, e, val)
    windage = trial(effect("windage"), 46.0, e, val)
    c = choose([asym, windage, coulomb], val, ALPHA)
    assert c.chosen is asym  # one parameter, no shape: as simple as windage, larger LR
    why = dict((d.score.label, w) for d, w in c.losers)
    assert why["windage@v"].endswith("and has the larger LR (47 > 46)")
    assert ("is, like this one, as good on validation as the largest-LR coulomb_friction@v"
            in why["windage@v"])
    assert "and simpler (1 estimated parameter instead of 2)" in why["coulomb_friction@v"]


def test_a_single_trial_is_chosen_and_a_missing_stage_is_named() -> None:
    val, e = validation()
    only = trial(effect("windage"), 30.0, e, val)
    c = choose([only], val, ALPHA)
    assert c.chosen is only and c.losers == []
    broken = trial(effect("coulomb_friction"), 40.0, e, val)
    broken.stage = None
    with pytest.raises(ValueError, match="coulomb_friction@v has no refitted stage"):
        choose([only, broken], val, ALPHA)
    with pytest.raises(ValueError, match="no passing trial"):
        choose([], val, ALPHA)
