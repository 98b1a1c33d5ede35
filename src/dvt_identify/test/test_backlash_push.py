"""Backlash reaches the model node: the identifier's three lost-motion maps and the node's
``dead_zone``/``play``/``spline_play`` terms are the same laws (:mod:`dvt_model.backlash`), and
the push maps each (pure, no ROS)."""

from __future__ import annotations

import json
from types import SimpleNamespace
from typing import Any

import numpy as np

from dvt_identify.description import load_description
from dvt_identify.effects import Effect, make_effect
from dvt_identify.effects.backlash import Backlash, CompliantOutputBacklash, OutputBacklash
from dvt_identify.effects.position import LibTerm, Unlisted
from dvt_identify.push import model_node_parameters
from dvt_identify.simulation import OEModel
from dvt_model.terms import parse_terms

DESC = load_description("dvt")
OUTS, INS = DESC.output_names, DESC.input_names
DT = 1e-3


def _eff(name: str, where: str, suffix: str = "", **opts: object) -> Effect:
    return make_effect(name, where, OUTS, INS, "N m", "rad/s", options=dict(opts),
                       suffix=suffix)


def _stage(effects: list[Effect], values: dict[str, float]) -> Any:
    """A fitted stage as model_node_parameters sees it (no segments kept)."""
    model = OEModel(DESC.structure, effects)
    theta = model.initial()
    for name, v in values.items():
        theta[model.names.index(name)] = v
    std = {n: abs(float(v)) * 0.01 for n, v in zip(model.names, theta, strict=True)}
    fit = SimpleNamespace(model=model, theta_=theta, parameter_std=lambda: std)
    return SimpleNamespace(fit=fit, parameters=lambda: model.parameters(theta))


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


def test_dead_zone_is_pushed_on_the_nodes_current_with_the_terms_on_that_input() -> None:
    zone = _eff("backlash", "motor", "_m")
    assert isinstance(zone, Backlash)
    lib = _eff("unlisted", "carrier3", "", orders=[1.0])
    assert isinstance(lib, Unlisted)
    prod = lib.subset([lib.terms.index(LibTerm("sign", "", 0.0, 0))], np.array([0.1]))
    push = model_node_parameters(_stage([zone, prod], {"delta_m": 0.4,
                                                       prod.params[0].name: 0.1}))
    terms = json.loads(push.parameters["effects"])
    assert terms[0] == {"kind": "dead_zone", "input": "drive_motor", "delta": 0.4}
    # the node applies the zone to the current first: the input term sees what it saw here
    assert terms[1]["kind"] == "library" and terms[1]["input"] == "drive_motor"
    assert push.skipped == []
    assert parse_terms(terms).dead_zones == (0.4, 0.0, 0.0, 0.0)


def test_a_dead_zone_behind_another_input_transform_is_not_pushed_nor_its_input_terms() -> None:
    lag = _eff("brake_engagement", "brake1")
    zone = _eff("backlash", "brake1", "_b")
    lib = _eff("unlisted", "carrier3", "", orders=[1.0], inputs=["brake1"])
    assert isinstance(lib, Unlisted)
    prod = lib.subset([lib.terms.index(LibTerm("sign", "", 0.0, 1))], np.array([0.1]))
    values = {lag.params[0].name: 0.02, "delta_b": 0.3, prod.params[0].name: 0.1}
    push = model_node_parameters(_stage([lag, zone, prod], values), n_model_effects=1)
    assert json.loads(push.parameters["effects"]) == []
    assert push.skipped[0] == ("backlash@brake1 (its input brake1 is also transformed by "
                               "brake_engagement@brake1 in the identified model; the model node "
                               "applies a dead zone to the raw current)")
    assert push.skipped[1].startswith(f"{prod.label()} (its input brake1 is transformed by "
                                      "brake_engagement@brake1")


def test_compliant_backlash_is_pushed_as_spline_play() -> None:
    eff = _eff("backlash", "carrier3", "_c", compliant=True)
    names = [s.name for s in eff.params]
    push = model_node_parameters(_stage([eff], dict(zip(names, (0.02, 380.0, 0.1),
                                                        strict=True))))
    assert json.loads(push.parameters["effects"]) == [
        {"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 380.0, "zeta": 0.1}]
    assert push.skipped == []
