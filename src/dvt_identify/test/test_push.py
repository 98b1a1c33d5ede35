"""Mapping an identified DVT model onto the model node's parameters (pure, no ROS)."""

from __future__ import annotations

import json
import threading
from concurrent.futures import Future
from types import SimpleNamespace

import numpy as np
import pytest

from dvt_identify.description import load_description
from dvt_identify.effects import BrakeEngagement, BrakeLockup, make_effect
from dvt_identify.errors import PushError
from dvt_identify.push import model_node_parameters
from dvt_identify.simulation import OEModel
from dvt_model.contract import answer_of


def _stage(effects, values, rel_std=0.01):  # type: ignore[no-untyped-def]
    """A fitted stage as model_node_parameters sees it: the model, its parameter vector and
    standard deviations (``rel_std`` times each value, or per name when a dict)."""
    desc = load_description("dvt")
    model = OEModel(desc.structure, effects)
    theta = model.initial()
    for name, v in values.items():
        theta[model.names.index(name)] = v
    rel = rel_std if isinstance(rel_std, dict) else {}
    std = {n: abs(float(v)) * rel.get(n, 0.01 if rel else rel_std)
           for n, v in zip(model.names, theta, strict=True)}
    fit = SimpleNamespace(model=model, theta_=theta, parameter_std=lambda: std,
                          estimate_x0=lambda seg, th=None: np.zeros(model.nx))
    return SimpleNamespace(fit=fit, parameters=lambda: model.parameters(theta)), desc


def test_band_brakes_and_effects_are_mapped() -> None:
    desc = load_description("dvt")
    bands = desc.make_model_effects()
    names = [p.name for e in bands for p in e.params]
    values = {}
    for e in bands:
        band = int(desc.input_names[e.index][-1])
        if isinstance(e, BrakeLockup):
            values[e.params[0].name] = 7.5 + band
        elif isinstance(e, BrakeEngagement):
            values[e.params[0].name] = 0.01 * band
    coulomb = make_effect("coulomb_friction", "sun_shaft", desc.output_names, desc.input_names,
                          "N m", "rad/s")
    stage, _ = _stage([*bands, coulomb], {**values, coulomb.params[0].name: 0.07})
    push = model_node_parameters(stage, n_model_effects=len(bands))  # type: ignore[arg-type]
    p = push.parameters
    assert len(names) == 6
    np.testing.assert_allclose(p["band_gain"], [8.5, 9.5, 10.5])
    np.testing.assert_allclose(p["band_time_constant"], [0.01, 0.02, 0.03])
    terms = json.loads(p["effects"])
    assert [t["kind"] for t in terms] == ["coulomb"] and terms[0]["Fc"] == 0.07
    assert push.skipped == []


def test_unidentified_band_is_not_pushed_and_said() -> None:
    desc = load_description("dvt")
    # band 2 and 3 dropped (never excited): only band 1's effects in the model
    bands = [e for e in desc.make_model_effects() if desc.input_names[e.index] == "brake1"]
    values = {e.params[0].name: (8.0 if isinstance(e, BrakeLockup) else 0.02) for e in bands}
    stage, _ = _stage(bands, values)
    push = model_node_parameters(stage, n_model_effects=len(bands))  # type: ignore[arg-type]
    assert "band_gain" not in push.parameters
    assert "band_time_constant" not in push.parameters
    assert "band_gain (band(s) [2, 3] not identified)" in push.skipped


def test_band_values_the_data_did_not_determine_are_not_pushed_nor_their_partners() -> None:
    desc = load_description("dvt")
    bands = desc.make_model_effects()
    values = {e.params[0].name: (8.0 if isinstance(e, BrakeLockup) else 0.02) for e in bands}
    tau2 = next(e.params[0].name for e in bands if isinstance(e, BrakeEngagement)
                and desc.input_names[e.index] == "brake2")
    stage, _ = _stage(bands, values, rel_std={tau2: 0.8})
    push = model_node_parameters(stage, n_model_effects=len(bands))  # type: ignore[arg-type]
    # the gains look determined, but a band's gain and lag go together: neither is pushed
    assert "band_gain" not in push.parameters
    assert "band_time_constant" not in push.parameters
    assert push.skipped == ["band_time_constant (band(s) [2] not determined by the data: "
                            "standard deviation above 50% of the value)",
                            "band_gain (not pushed without band_time_constant: a band's gain "
                            "and lag are determined together)"]


def test_effects_push_their_declared_terms_and_the_rest_is_said() -> None:
    desc = load_description("dvt")
    outs, ins = desc.output_names, desc.input_names

    def eff(name: str, where: str, **opts: object):  # type: ignore[no-untyped-def]
        return make_effect(name, where, outs, ins, "N m", "rad/s", options=dict(opts),
                           suffix=f"_{where}")
    effects = [eff("stribeck_friction", "sun_shaft"), eff("windage", "carrier3"),
               eff("measurement_delay", "carrier3"), eff("sensor_gain", "carrier3"),
               eff("backlash", "carrier3"), eff("asymmetric_friction", "carrier3")]
    values = {"Fs_sun_shaft": 0.2, "vs_sun_shaft": 3.0, "Cw_carrier3": 1e-4,
              "delay_carrier3": 0.004, "gain_carrier3": 0.03, "delta_carrier3": 0.01,
              "dFv_carrier3": 1e-3}
    stage, _ = _stage(effects, values)
    push = model_node_parameters(stage)  # type: ignore[arg-type]
    terms = json.loads(push.parameters["effects"])
    assert [t["kind"] for t in terms] == ["stribeck", "windage", "delay", "gain", "play"]
    assert terms[0]["member"] == [1.0, 0.0] and terms[0]["vs"] == 3.0
    assert terms[3] == {"kind": "gain", "output": 1, "gain": 0.03}
    assert terms[4] == {"kind": "play", "output": 1, "delta": 0.01}
    assert push.skipped == ["asymmetric_friction@carrier3 (the model node has no "
                            "direction-dependent viscous term)"]


def test_a_term_the_node_would_refuse_is_not_pushed() -> None:
    desc = load_description("dvt")
    gain = make_effect("sensor_gain", "sun_shaft", desc.output_names, desc.input_names)
    stage, _ = _stage([gain], {"gain": 2.0})  # the identifier admits it, the node does not
    push = model_node_parameters(stage)  # type: ignore[arg-type]
    assert json.loads(push.parameters["effects"]) == []
    (line,) = push.skipped
    assert line.startswith("sensor_gain@sun_shaft (the model node would refuse it: ")
    assert "effects[0].gain: 2.0" in line


def test_a_mass_matrix_the_node_would_refuse_raises() -> None:
    stage, _ = _stage([], {"M11": 1e-3, "M12": 0.5, "M22": 1e-3})  # not positive definite
    with pytest.raises(PushError, match="M"):
        model_node_parameters(stage)  # type: ignore[arg-type]


def _band_run(desc, model, theta, seed=0):  # type: ignore[no-untyped-def]
    """A 20-s run at 5 ms of ``model`` at ``theta`` (each band engaged four times, the motor
    current a few sines), with 1 % noise: a segment whose bands the data determine."""
    from dvt_identify.data import Segment

    dt, n = 0.005, 4000
    t = np.arange(n) * dt
    u = np.zeros((n, 4))
    u[:, 0] = 2.0 + 1.5 * np.sin(2 * np.pi * 0.7 * t) + 0.8 * np.sin(2 * np.pi * 2.3 * t)
    band = (np.floor(t / 1.25).astype(int) % 4)  # 0: neutral, 1..3: band b engaged
    for b in (1, 2, 3):
        u[:, b] = np.where(band == b, 1.0, 0.0)
    seg = Segment(name="bands", t=t, u=u, y=np.zeros((n, 2)), input_names=desc.input_names,
                  output_names=desc.output_names, dt=dt)
    y = model.simulate(theta, seg, np.zeros(2))
    rng = np.random.default_rng(seed)
    y = y + 0.01 * np.std(y, axis=0) * rng.standard_normal(y.shape)
    return Segment(name="bands", t=t, u=u, y=y, input_names=desc.input_names,
                   output_names=desc.output_names, dt=dt)


def test_band_values_are_pushed_only_when_they_predict_held_out_data_better() -> None:
    from dvt_identify.push import band_check

    desc = load_description("dvt")
    bands = desc.make_model_effects()
    names = [e.params[0].name for e in bands]
    model = OEModel(desc.structure, bands)
    truth = model.initial()
    plant = {}
    for e in bands:  # a plant off the description's band values (8 N m/A, 20 ms)
        band = int(desc.input_names[e.index][-1])
        v = (5.5 + band) if isinstance(e, BrakeLockup) else 0.01 + 0.01 * band
        truth[model.names.index(e.params[0].name)] = plant[e.params[0].name] = v
    held_out = [_band_run(desc, model, truth, seed=1)]

    def fit(m, theta):  # type: ignore[no-untyped-def]
        return SimpleNamespace(model=m, theta_=theta,
                               estimate_x0=lambda seg, th: np.zeros(2))
    # the fitted values are the plant's, the start the description's: confirmed
    assert band_check(fit(model, truth), names, held_out) == ""  # type: ignore[arg-type]
    # the fit started at the plant's values and moved along the ridge: refused, with losses
    started = OEModel(desc.with_initial(plant).structure, desc.with_initial(plant)
                      .make_model_effects())
    ridge = truth.copy()
    for e in bands:
        i = model.names.index(e.params[0].name)
        ridge[i] *= 4.0  # gain and lag alike: the same initial slope, a slower rise
    why = band_check(fit(started, ridge), names, held_out)  # type: ignore[arg-type]
    assert why.startswith("the fitted band values predict the validation data worse than "
                          "the start values: loss "), why
    # start values equal to the fitted ones: nothing to compare, nothing refused
    assert band_check(fit(started, truth), names, held_out) == ""  # type: ignore[arg-type]
    # the push applies it: the plant's values are pushed, values off the ridge are not
    stage, _ = _stage(bands, plant)
    push = model_node_parameters(stage, len(bands), validation=held_out)  # type: ignore[arg-type]
    np.testing.assert_allclose(push.parameters["band_gain"], [6.5, 7.5, 8.5])
    stage, _ = _stage(bands, {k: 4.0 * v for k, v in plant.items()})
    push = model_node_parameters(stage, len(bands), validation=held_out)  # type: ignore[arg-type]
    assert "band_gain" not in push.parameters and "band_time_constant" not in push.parameters
    (line,) = push.skipped
    assert line.startswith("band_gain, band_time_constant (the fitted band values predict "
                           "the validation data worse than the start values: loss "), line


def test_an_unanswered_push_is_sent_again_and_the_first_answer_wins() -> None:
    """The first request's answer is lost (its future never completes); the resend's answer
    is returned. A request answered in time is sent once; none answered raises in time."""
    sent: list[Future] = []

    def lossy() -> Future:
        sent.append(Future())
        if len(sent) == 2:  # the resend is answered a little later
            threading.Timer(0.02, sent[-1].set_result, args=("applied",)).start()
        return sent[-1]

    assert answer_of(lossy, timeout=5.0, resend_after=0.1, poll=0.001) == ("applied", 2)

    def prompt() -> Future:
        future: Future = Future()
        future.set_result("applied")
        return future

    assert answer_of(prompt, timeout=5.0, resend_after=0.1) == ("applied", 1)
    with pytest.raises(TimeoutError, match=r"0.3 s to [34] request"):
        answer_of(Future, timeout=0.3, resend_after=0.1, poll=0.001)
