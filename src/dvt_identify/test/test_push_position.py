"""Pushing the position-dependent effects to the model node (pure, no ROS)."""

from __future__ import annotations

import json
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import load_description
from dvt_identify.effects import Effect, make_effect
from dvt_identify.effects.backlash import Backlash
from dvt_identify.effects.base import SegmentView
from dvt_identify.effects.position import LibTerm, Unlisted
from dvt_identify.errors import PushError
from dvt_identify.push import model_node_parameters
from dvt_identify.simulation import OEModel
from dvt_model.terms import parse_terms

DESC = load_description("dvt")
OUTS, INS = DESC.output_names, DESC.input_names


def _segment(measured: bool, n: int = 400, seed: int = 1) -> Segment:
    """Speeds well away from 0 (the node's smoothed sign is then the identifier's sign), the
    angles their left-rectangle integral (so a step's angle interval is ``omega dt``)."""
    rng = np.random.default_rng(seed)
    dt = 1e-3
    t = np.arange(n) * dt
    y = np.column_stack([80.0 + 20.0 * np.sin(7.0 * t) + rng.normal(0, 1, n),
                         20.0 + 4.0 * np.cos(5.0 * t) + rng.normal(0, 0.3, n)])
    seg = make_segment("synthetic", t, rng.normal(0, 2, (n, 4)), y, INS, OUTS)
    if not measured:
        return seg
    angles = np.vstack([[0.4, -1.3], np.array([0.4, -1.3]) + np.cumsum(y[:-1] * seg.dt, 0)])
    return make_segment("synthetic", t, seg.u, y, INS, OUTS, angles=angles)


def _stage(effects: list[Effect], values: dict[str, float],
           segments: list[Segment] | None) -> Any:
    """A fitted stage as model_node_parameters sees it (``segments``: the fit's, or none)."""
    model = OEModel(DESC.structure, effects)
    theta = model.initial()
    for name, v in values.items():
        theta[model.names.index(name)] = v
    std = {n: abs(float(v)) * 0.01 for n, v in zip(model.names, theta, strict=True)}
    fit = SimpleNamespace(model=model, theta_=theta, parameter_std=lambda: std)
    if segments is not None:
        fit.segments_ = segments
    return SimpleNamespace(fit=fit, parameters=lambda: model.parameters(theta))


def _eff(name: str, where: str, suffix: str, **opts: object) -> Effect:
    return make_effect(name, where, OUTS, INS, "N m", "rad/s", options=dict(opts),
                       suffix=suffix)


def _unlisted(where: str, picks: dict[LibTerm, float], **opts: object) -> Unlisted:
    lib = _eff("unlisted", where, "", **opts)
    assert isinstance(lib, Unlisted)
    idx = [lib.terms.index(t) for t in picks]
    return lib.subset(idx, np.array(list(picks.values())))


VALUES_G = {"gravity_a_g": 0.8, "gravity_b_g": -0.3}
PICKS = {LibTerm("sign"): 0.05, LibTerm("", "cos", 1.0): 0.2,
         LibTerm("", "sin", 2.0, 0): 0.01, LibTerm("abs_sq"): 1e-4}


def _effects() -> tuple[list[Effect], dict[str, float]]:
    grav = _eff("gravity_load", "carrier3", "_g", reduction=20.0)
    per = _eff("periodic_disturbance", "sun_shaft", "_p", orders=[3.0])
    mesh = _eff("periodic_disturbance", "sun_shaft", "_m", mesh_stages=True)
    unl = _unlisted("carrier3", PICKS, orders=[1.0, 2.0])
    values = {**VALUES_G, "a_p": 0.02, "b_p": -0.01, "a_m": 0.015, "b_m": 0.005,
              **{s.name: s.initial for s in unl.params}}
    return [grav, per, mesh, unl], values


def test_each_effect_maps_to_its_terms_with_measured_angles() -> None:
    effects, values = _effects()
    mesh_form = effects[2].options["mesh_forms"][0]  # type: ignore[index]
    push = model_node_parameters(_stage(effects, values, [_segment(True)]))
    terms = json.loads(push.parameters["effects"])
    assert push.skipped == []
    assert terms[0] == {"kind": "gravity", "member": [0.0, 1.0], "a": 0.8, "b": -0.3,
                        "reduction": 20.0}
    assert terms[1] == {"kind": "angle_periodic", "member": [1.0, 0.0], "a": 0.02, "b": -0.01,
                        "order": 3.0}
    assert terms[2]["kind"] == "angle_periodic" and terms[2]["angle"] == mesh_form
    assert terms[2]["order"] == effects[2].params[2].initial  # stage 1's sun teeth
    lib = [t for t in terms if t["kind"] == "library"]
    assert [(t["speed"], t["trig"], t["order"], t["input"], t["k"]) for t in lib] == [
        ("sign", "", 0.0, "", 0.05), ("", "cos", 1.0, "", 0.2),
        ("", "sin", 2.0, "drive_motor", 0.01), ("abs_sq", "", 0.0, "", 1e-4)]
    assert all(t["member"] == [0.0, 1.0] for t in lib)
    parse_terms(push.parameters["effects"])  # the node takes it


def test_integrated_angles_are_not_pushed_and_said() -> None:
    effects, values = _effects()
    speed_only = _unlisted("sun_shaft", {LibTerm("sign"): 0.03})
    stage = _stage([*effects, speed_only], {**values, speed_only.params[0].name: 0.03},
                   [_segment(True), _segment(False, seed=2)])
    push = model_node_parameters(stage)
    terms = json.loads(push.parameters["effects"])
    # only the term without an angle factor
    assert terms == [{"kind": "library", "member": [1.0, 0.0], "k": 0.03, "order": 0.0,
                      "eps": 0.5, "speed": "sign", "trig": "", "input": "",
                      "input_power": ""}]
    assert len(push.skipped) == 4
    why = ("(its angle is the integrated measured speed (from 0 at the first sample): its "
           "phase is relative to the recording, the model node's angles are the measured "
           "positions; identify on a recording with positions to push it)")
    assert push.skipped[0] == f"gravity_load@carrier3 {why}"
    assert all(line.endswith(why) for line in push.skipped)
    # a fit that kept no segments: the source is unknown, nothing angle-dependent is pushed
    push = model_node_parameters(_stage(effects[:1], VALUES_G, None))
    assert push.skipped == ["gravity_load@carrier3 (its angle is the angle of unknown source "
                            "(the fit keeps no segments): its phase is relative to the "
                            "recording, the model node's angles are the measured positions; "
                            "identify on a recording with positions to push it)"]


def test_a_time_clocked_disturbance_is_skipped_with_its_reason() -> None:
    per = _eff("periodic_disturbance", "carrier3", "_t", orders=[50.0], clock="time")
    push = model_node_parameters(_stage([per], {"a_t": 0.1}, [_segment(True)]))
    assert json.loads(push.parameters["effects"]) == []
    assert push.skipped == ["periodic_disturbance@carrier3 (clocked on time (clock: time): the "
                            "model node's periodic term (angle_periodic) is phase-locked to an "
                            "angle)"]


def test_a_transformed_input_is_not_pushed() -> None:
    lag = _eff("brake_engagement", "brake1", "")
    prod = _unlisted("carrier3", {LibTerm("", "cos", 1.0, 1): 0.1}, orders=[1.0],
                     inputs=["brake1"])
    values = {lag.params[0].name: 0.02, prod.params[0].name: 0.1}
    push = model_node_parameters(_stage([lag, prod], values, [_segment(True)]),
                                 n_model_effects=1)
    assert json.loads(push.parameters["effects"]) == []
    assert push.skipped[0] == (f"{prod.label()} (its input brake1 is transformed by "
                               "brake_engagement@brake1 in the identified model; the model "
                               "node's term takes the raw current)")


def test_input_joints_name_the_nodes_currents() -> None:
    prod = _unlisted("carrier3", {LibTerm("", "cos", 1.0, 0): 0.1}, orders=[1.0])
    stage = _stage([prod], {prod.params[0].name: 0.1}, [_segment(True)])
    push = model_node_parameters(stage, input_joints=["brake3", "brake1", "brake2", "x"])
    assert json.loads(push.parameters["effects"])[0]["input"] == "brake3"
    push = model_node_parameters(stage, input_joints=["motor_x", "brake1", "brake2", "brake3"])
    assert push.skipped == [f"{prod.label()} (input 'motor' is not a current of the model node "
                            "(expected one of ['drive_motor', 'brake1', 'brake2', 'brake3'], "
                            "or input_joints naming it))"]
    with pytest.raises(PushError, match=r"^input_joints: expected 4 names"):
        model_node_parameters(stage, input_joints=["drive_motor"])


def test_identifier_force_equals_the_node_terms_force() -> None:
    """Round trip: every effect's exogenous force on a segment with measured angles, as a
    generalised torque, equals the pushed terms' torque held over each step (the last sample:
    the point value) on the same speeds, angles and inputs."""
    effects, values = _effects()
    seg = _segment(True)
    stage = _stage(effects, values, [seg])
    model = stage.fit.model
    push = model_node_parameters(stage)
    assert push.skipped == []
    terms = parse_terms(push.parameters["effects"])
    view = SegmentView(seg.dt, seg.u, seg.y, seg.angles)
    ident = np.zeros_like(seg.y)
    for eff, p in zip(model.effects, model.effect_params(stage.fit.theta_), strict=True):
        ident += np.outer(eff.exogenous_force(p, view), eff.member)
    assert seg.angles is not None
    node = np.array([terms.angle_force(seg.angles[n], seg.y[n], 0.0, seg.u[n],
                                       seg.dt if n + 1 < seg.n else 0.0)
                     for n in range(seg.n)])
    assert float(np.max(np.abs(ident))) > 0.1
    np.testing.assert_allclose(node, ident, rtol=0.0, atol=1e-9)


def test_members_and_outputs_are_reordered_to_the_nodes_speeds() -> None:
    from dvt_identify.push import _Mapping, _node_term, _speed_order

    order = _speed_order(["carrier3", "sun_shaft"])
    assert order == [1, 0] and _speed_order(["a", "b"]) is None
    ctx = _Mapping(outputs=["carrier3", "sun_shaft"], order=order,
                   inputs={"motor": "drive_motor"}, transformed={}, angle_source="")
    term, why = _node_term({"kind": "library", "member": [1.0, 0.0], "angle": [2.0, -1.0],
                            "k": 1.0, "input": "motor"}, ctx)
    assert why == "" and term == {"kind": "library", "member": [0.0, 1.0],
                                  "angle": [-1.0, 2.0], "k": 1.0, "input": "drive_motor"}
    term, _ = _node_term({"kind": "gain", "output": 0, "gain": 0.1}, ctx)
    assert term == {"kind": "gain", "output": 1, "gain": 0.1}


# -- backlash: a dead zone on an input, play in a compliant spline on an output ------------

def test_dead_zone_is_pushed_on_the_nodes_current_with_the_terms_on_that_input() -> None:
    zone = _eff("backlash", "motor", "_m")
    assert isinstance(zone, Backlash)
    lib = _eff("unlisted", "carrier3", "", orders=[1.0])
    assert isinstance(lib, Unlisted)
    prod = lib.subset([lib.terms.index(LibTerm("sign", "", 0.0, 0))], np.array([0.1]))
    push = model_node_parameters(_stage([zone, prod], {"delta_m": 0.4,
                                                       prod.params[0].name: 0.1}, None))
    terms = json.loads(push.parameters["effects"])
    assert terms[0] == {"kind": "dead_zone", "input": "drive_motor", "delta": 0.4}
    # the node applies the zone to the current first: the input term sees what it saw here
    assert terms[1]["kind"] == "library" and terms[1]["input"] == "drive_motor"
    assert push.skipped == []
    assert parse_terms(terms).dead_zones == (0.4, 0.0, 0.0, 0.0)


def test_a_dead_zone_behind_another_input_transform_is_not_pushed_nor_its_input_terms() -> None:
    lag = _eff("brake_engagement", "brake1", "")
    zone = _eff("backlash", "brake1", "_b")
    lib = _eff("unlisted", "carrier3", "", orders=[1.0], inputs=["brake1"])
    assert isinstance(lib, Unlisted)
    prod = lib.subset([lib.terms.index(LibTerm("sign", "", 0.0, 1))], np.array([0.1]))
    values = {lag.params[0].name: 0.02, "delta_b": 0.3, prod.params[0].name: 0.1}
    push = model_node_parameters(_stage([lag, zone, prod], values, None),
                                 n_model_effects=1)
    assert json.loads(push.parameters["effects"]) == []
    assert push.skipped[0] == ("backlash@brake1 (its input brake1 is also transformed by "
                               "brake_engagement@brake1 in the identified model; the model node "
                               "applies a dead zone to the raw current)")
    assert push.skipped[1].startswith(f"{prod.label()} (its input brake1 is transformed by "
                                      "brake_engagement@brake1")


def test_compliant_backlash_is_pushed_as_spline_play() -> None:
    eff = _eff("backlash", "carrier3", "_c", compliant=True)
    names = [s.name for s in eff.params]
    push = model_node_parameters(_stage([eff], dict(zip(names, (0.02, 380.0, 0.1), strict=True)),
                                        None))
    assert json.loads(push.parameters["effects"]) == [
        {"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 380.0, "zeta": 0.1}]
    assert push.skipped == []
