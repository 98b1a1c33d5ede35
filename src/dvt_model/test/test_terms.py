"""Effect terms the identifier pushes to the model node."""

import json

import numpy as np
import pytest

from dvt_model.errors import ContractError
from dvt_model.hybrid import HybridModel
from dvt_model.params import load_parameters
from dvt_model.predictor import Predictor
from dvt_model.terms import parse_terms


def test_force_laws_oppose_motion():
    terms = parse_terms(json.dumps([
        {"kind": "coulomb", "member": [1.0, 0.0], "Fc": 0.2, "offset": 0.0},
        {"kind": "windage", "member": [0.0, 1.0], "Cw": 1e-4},
    ]))
    f = terms.extra_force(np.array([50.0, 20.0]), 0.0)
    assert f[0] == pytest.approx(-0.2, rel=1e-6)
    assert f[1] == pytest.approx(-1e-4 * 400.0)
    f_neg = terms.extra_force(np.array([-50.0, -20.0]), 0.0)
    assert np.allclose(f_neg, -f)


def test_coulomb_lowers_steady_speed():
    params = load_parameters("physical")
    n = 3000
    t = np.arange(n) * 1e-3
    im, ib = np.full(n, 4.0), np.zeros((n, 3))
    clean = HybridModel.from_params(params).simulate(t, im, ib)
    terms = parse_terms([{"kind": "coulomb", "member": [1.0, 0.0], "Fc": 0.3}])
    fric = HybridModel.from_params(params, extra_force=terms.extra_force).simulate(t, im, ib)
    assert fric.omega[-1, 0] < clean.omega[-1, 0] - 1.0


def test_output_delay_and_gain_in_predictor():
    params = load_parameters("physical")
    model = HybridModel.from_params(params)
    p = Predictor(model, params.brake, output_delay=0.005, output_gain=(0.1, 0.0))
    q = Predictor(HybridModel.from_params(params), params.brake)
    outs, refs = [], []
    for k in range(50):
        meas = (10.0, 2.0)
        outs.append(p.update(k * 1e-3, 4.0, (0, 0, 0), meas).predicted)
        refs.append(q.update(k * 1e-3, 4.0, (0, 0, 0), meas).predicted)
    outs, refs = np.array(outs), np.array(refs)
    assert outs[30, 0] == pytest.approx(1.1 * refs[25, 0])
    assert outs[30, 1] == pytest.approx(refs[25, 1])


@pytest.mark.parametrize(("text", "match"), [
    ("{", "not valid JSON"),
    ('{"kind": "coulomb"}', "expected a JSON list"),
    ('[{"kind": "magic"}]', r"effects\[0\]\.kind"),
    ('[{"kind": "coulomb", "member": [1], "Fc": 1}]', r"effects\[0\]\.member"),
    ('[{"kind": "coulomb", "member": [1, 0], "Fc": "x"}]', r"effects\[0\]\.Fc"),
    ('[{"kind": "delay", "seconds": 5}]', r"effects\[0\]\.seconds"),
    ('[{"kind": "gain", "output": 3, "gain": 0.1}]', r"effects\[0\]\.output"),
])
def test_bad_terms_refused(text, match):
    with pytest.raises(ContractError, match=match):
        parse_terms(text)


def test_empty():
    assert parse_terms("").empty
    assert parse_terms("[]").empty


def test_force_laws_are_the_friction_module_laws():
    from dvt_model import friction
    terms = parse_terms([
        {"kind": "stribeck", "member": [0.5, 1.0], "Fs": 0.2, "vs": 5.0, "eps": 0.1},
        {"kind": "viscous", "member": [0.5, 1.0], "b": 1e-3},
    ])
    omega = np.array([4.0, 1.0])
    v = 0.5 * 4.0 + 1.0
    law = friction.stribeck(v, 0.2, 5.0, 0.1) + friction.viscous(v, 1e-3)
    assert np.allclose(terms.extra_force(omega, 0.0), -np.array([0.5, 1.0]) * law)


@pytest.mark.parametrize("term", [
    {"kind": "coulomb", "member": [1, 0], "Fc": -0.1},
    {"kind": "viscous", "member": [1, 0], "b": -1e-3},
    {"kind": "gain", "output": 0, "gain": -1.0},
])
def test_physically_inadmissible_terms_refused(term):
    with pytest.raises(ContractError, match=r"effects\[0\]"):
        parse_terms([term])
