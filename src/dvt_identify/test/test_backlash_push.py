"""Backlash reaches the model node: the identifier's lost-motion maps and the node's ``play``
and ``spline_play`` terms are the same laws (:mod:`dvt_model.backlash`; pure, no ROS). How the
push maps each backlash variant: ``test_push_position.py``."""

from __future__ import annotations

from typing import Any

import numpy as np

from dvt_identify.description import load_description
from dvt_identify.effects import Effect, make_effect
from dvt_identify.effects.backlash import CompliantOutputBacklash, OutputBacklash
from dvt_model.terms import parse_terms

DESC = load_description("dvt")
OUTS, INS = DESC.output_names, DESC.input_names
DT = 1e-3


def _eff(name: str, where: str, suffix: str = "", **opts: object) -> Effect:
    return make_effect(name, where, OUTS, INS, "N m", "rad/s", options=dict(opts),
                       suffix=suffix)


def _speeds(n: int = 3000) -> np.ndarray:
    """Model speeds (n, 2) [rad/s] with many reversals of carrier 3."""
    t = np.arange(n) * DT
    return np.column_stack([60.0 * np.sin(2 * np.pi * 0.7 * t),
                            20.0 * np.sin(2 * np.pi * 1.3 * t) + 3.0 * np.sin(2 * np.pi * 7 * t)])


def _node_map(term: dict[str, Any], y: np.ndarray) -> np.ndarray:
    """The node's sensor map of ``term`` over the speeds ``y`` sample by sample, as its
    predictor runs it (reset at the first sample)."""
    out_map = parse_terms([term]).output_maps()[term["output"]]
    assert out_map is not None
    out_map.reset()
    return np.array([out_map.sensed_speed(float(v), 0.0 if k == 0 else DT)
                     for k, v in enumerate(y[:, term["output"]])])


def test_play_term_is_the_identifiers_output_map() -> None:
    eff = _eff("backlash", "carrier3")
    assert isinstance(eff, OutputBacklash)
    p = np.array([0.015])
    y = _speeds()
    ident = eff.output_transform(p, y, DT)
    assert ident is not None
    term = eff.model_term(p, OUTS)
    assert term == {"kind": "play", "output": 1, "delta": 0.015}
    node = _node_map(term, y)
    # the same play operator on the same integrated angle: equal to round-off (the last
    # sample has no next one in the batch map)
    assert np.allclose(node[:-1], ident[:-1, 1], rtol=0, atol=1e-9)
    assert np.abs(ident[:, 1] - y[:, 1]).max() > 5.0  # and the play does act


def test_spline_play_term_follows_the_identifiers_compliant_map() -> None:
    """The node takes the load speed at the sample instant, the identifier its mean over the
    sample interval (its decimated data's anti-alias filter): at the node's raw rate the two
    differ by a small fraction of what the spline changes."""
    eff = _eff("backlash", "carrier3", compliant=True)
    assert isinstance(eff, CompliantOutputBacklash)
    p = np.array([0.02, 350.0, 0.2])
    y = _speeds()
    ident = eff.output_transform(p, y, DT)
    assert ident is not None
    term = eff.model_term(p, OUTS)
    assert term == {"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 350.0, "zeta": 0.2}
    node = _node_map(term, y)
    effect = np.sqrt(np.mean((ident[:, 1] - y[:, 1]) ** 2))
    differ = np.sqrt(np.mean((node - ident[:, 1]) ** 2))
    assert effect > 0.2 and differ < 0.05 * effect, (effect, differ)
