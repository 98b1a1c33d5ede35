"""The dry frictions of one member add up to a friction (:mod:`dvt_identify.effects.dissipation`).

A Coulomb friction is admissible alone (``Fc >= 0``, ``|offset| <= Fc``), and an ``unlisted``
term ``k sign(s) T(theta)`` has no bound of its own; their sum may still be below 0 somewhere
along the member's travel: a passive part that drives the member. The final model's notes
flag it, naming the member, the direction, the value and where (flagged, not refused: a
truncated series of a true friction undershoots beside a narrow peak,
``test_unlisted.py``'s tight spot)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from dvt_identify.data import Segment
from dvt_identify.description import Description
from dvt_identify.effects import Unlisted
from dvt_identify.effects.base import Effect, SegmentView
from dvt_identify.effects.dissipation import undissipative
from dvt_identify.effects.position import POLY
from dvt_identify.loop import identify
from dvt_identify.stages import LoopConfig

TRAVEL = (0.0, 1.0)


def _travel_cart(axis_desc: Callable[..., Description], coulomb: dict[str, Any]
                 ) -> tuple[Effect, Unlisted]:
    """A Coulomb friction with ``coulomb``'s options on the cart and its travel library over
    :data:`TRAVEL` (degree 2)."""
    desc = axis_desc([{"effect": "coulomb_friction", "where": "cart", **coulomb},
                      {"effect": "unlisted", "where": "cart", "inputs": [],
                       "travel": list(TRAVEL), "degree": 2}])
    coul, lib = desc.make_candidates()
    assert isinstance(lib, Unlisted)
    return coul, lib


def _sweep(n: int = 201) -> SegmentView:
    """The cart's position over its whole travel, measured (N, 1) [m]."""
    q = np.linspace(*TRAVEL, n)
    return SegmentView(0.002, np.zeros((n, 1)), q[:, None], None)


def _term(lib: Unlisted, speed: str, trig: str, order: float) -> int:
    return next(i for i, t in enumerate(lib.terms)
                if (t.speed, t.trig, t.order) == (speed, trig, order))


def test_a_coulomb_friction_and_a_friction_along_the_travel_that_stay_positive_pass(
        axis_desc: Callable[..., Description]) -> None:
    """``Fc = 2 N`` and ``-1 sign(v) P2(x)``: the friction is ``2 + P2(x)`` in [1.5, 3] N."""
    coul, lib = _travel_cart(axis_desc, {"offset": False})
    prop = lib.subset([_term(lib, "sign", POLY, 2.0)], np.array([-1.0]))
    assert undissipative([coul, prop], [np.array([2.0]), np.array([-1.0])], [_sweep()]) == []
    # one constant share alone is the Coulomb law's own check, not this one
    assert undissipative([coul], [np.array([2.0])], [_sweep()]) == []


def test_a_sum_that_drives_the_member_at_the_ends_of_its_travel_is_named(
        axis_desc: Callable[..., Description]) -> None:
    """``Fc = 2 N`` and ``+3 sign(v) P2(x)``: ``2 - 3 P2(x)`` is -1 N at both ends of the
    travel; the text names the member, the direction, the value, where, and each share."""
    coul, lib = _travel_cart(axis_desc, {"offset": False})
    prop = lib.subset([_term(lib, "sign", POLY, 2.0)], np.array([3.0]))
    (why,) = undissipative([coul, prop], [np.array([2.0]), np.array([3.0])], [_sweep()])
    assert "dry friction on cart" in why and "falls to -1 N" in why, why
    assert "at its angle 0 " in why or "at its angle 1 " in why, why
    assert "coulomb_friction@cart +2" in why and "unlisted@cart -3" in why, why


def test_an_offset_counts_in_its_direction(axis_desc: Callable[..., Description]) -> None:
    """``Fc = 2``, ``offset = -1.5`` (0.5 N moving forward, 3.5 N moving back) and ``-1 sign(v)
    P1(x)`` (``+1 x``): forward the friction is ``0.5 + x``, -0.5 N at the start of the travel;
    backwards it stays above 2.5 N."""
    coul, lib = _travel_cart(axis_desc, {})
    prop = lib.subset([_term(lib, "sign", POLY, 1.0)], np.array([-1.0]))
    (why,) = undissipative([coul, prop], [np.array([2.0, -1.5]), np.array([-1.0])],
                           [_sweep()])
    assert "positive direction falls to -0.5 N at its angle 0 " in why, why


def test_a_friction_ripple_with_no_friction_under_it_is_named(
        axis_desc: Callable[..., Description]) -> None:
    """An ``unlisted`` friction alone, ``sign(v) cos(theta)`` with nothing under it: half of each
    period drives the member; a plain ``sign(v)`` term is a friction only with k < 0."""
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [], "orders": [6.0]}])
    lib = desc.make_candidates()[0]
    assert isinstance(lib, Unlisted)
    ripple = lib.subset([_term(lib, "sign", "cos", 6.0)], np.array([-0.5]))
    assert undissipative([ripple], [np.array([-0.5])], [_sweep()])
    plain = lib.subset([_term(lib, "sign", "", 0.0)], np.array([0.5]))
    (why,) = undissipative([plain], [np.array([0.5])], [_sweep()])
    assert "falls to -0.5 N" in why, why
    assert undissipative([plain], [np.array([-0.5])], [_sweep()]) == []


@pytest.mark.parametrize("dry", [0.0, 3.0])
def test_the_loop_flags_a_friction_that_drives_the_cart(
        dry: float, axis_desc: Callable[..., Description],
        axis_record: Callable[..., Segment]) -> None:
    """A cart whose friction along the travel is ``(dry + 2 x) sign(v)``, ``x`` in [-1, 1]
    over the travel (smoothed over 0.01 m/s). With ``dry`` = 3 N declared as a Coulomb law
    (fitted from 0) the friction is 1-5 N: the loop accepts the travel term, both come out
    within 10 % of the truth, and nothing is flagged. With nothing under it the truth drives
    the cart on half of its travel, not a passive part: the final model's notes flag it,
    naming the member and the direction (flagged, not refused: see
    :data:`dvt_identify.loop.UNDISSIPATIVE_NOTE`)."""
    span = (-1.0, 2.0)

    def friction(q: float, v: float) -> float:
        x = (2 * q - span[0] - span[1]) / (span[1] - span[0])
        return float(np.tanh(v / 0.01) * (dry + 2.0 * x))

    est, val = axis_record(5, force=friction), axis_record(6, force=friction)
    declared = ([{"effect": "coulomb_friction", "where": "cart", "offset": False,
                  "eps": 0.01}] if dry else [])
    desc = axis_desc([{"effect": "unlisted", "where": "cart", "inputs": [],
                       "travel": list(span), "degree": 2}], declared)
    res = identify([est], [val], desc, LoopConfig(max_effects=2))
    assert [d.score.effect.name for d in res.accepted] == ["unlisted"], \
        [d.reason for d in res.decisions]
    flags = [n for n in res.notes if n.startswith("physics: the dry friction on cart")]
    if dry:
        assert flags == [], flags
        # measured: Fc 3.000 N, k -1.997 N (the truth's 3 and -2: the force opposes the motion)
        p = res.final.parameters()
        assert abs(p["Fc_cart"] / dry - 1) < 0.1 and abs(p["k_sgn_P1_cart"] / -2.0 - 1) < 0.1, p
    else:
        assert len(flags) == 1 and "in the positive direction falls to -" in flags[0], res.notes
