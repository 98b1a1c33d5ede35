"""Do the records agree? (:mod:`dvt_identify.disagree`): a cart whose dry friction is 0.3 N
higher in the test record than in the estimation record is told apart from one that is not."""

from __future__ import annotations

import re

import numpy as np

from dvt_identify.data import make_segment
from dvt_identify.description import parse_description
from dvt_identify.disagree import compare_records
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel


def _desc():
    return parse_description({
        "name": "slide",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "c"}],
        "outputs": [{"name": "v", "topic": "/s/joint_states", "field": "velocity",
                     "joint": "c"}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                      "parameters": {"M": {"initial": 2.0, "lower": 0.01},
                                     "Fv": {"initial": 3.0, "lower": 0.0}}},
        "candidates": [{"effect": "coulomb_friction", "where": "v", "offset": True,
                        "eps": 0.01}],
    }, "slide.yaml")


def _record(seed: int, fc: float, n: int = 4000):
    desc = _desc()
    model = OEModel(desc.structure, desc.make_candidates())
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-8.0, 8.0, n // 80 + 1), 80)[:n]
    t = np.arange(n) * 0.005
    clean = make_segment(f"s{seed}", t, u, np.zeros((n, 1)), desc.input_names,
                         desc.output_names)
    y = model.simulate(np.array([2.0, 3.0, fc, 0.0]), clean, np.zeros(1))
    y = y + 0.002 * rng.standard_normal(y.shape)
    return make_segment(f"s{seed}", t, u, y, desc.input_names, desc.output_names), model


def _fit(seg, model):
    return OEFit(model, starts=1, theta0=np.array([2.0, 3.0, 1.0, 0.0])).fit([seg])


def test_a_friction_higher_in_the_test_record_is_detected_and_read_as_friction():
    est, model = _record(1, fc=1.0)
    test, _ = _record(2, fc=1.3)
    ag = compare_records(_fit(est, model), [est], test=[test], unit="N")
    assert ag.disagree, ag.statement
    assert ag.test.labels == ["force +", "force -"]
    # bias(+) = -dFc, bias(-) = +dFc with dFc = 0.3 N: within 4 of their standard errors
    d = ag.test.value - ag.estimation.value
    se = np.sqrt(ag.test.std ** 2 + ag.estimation.std ** 2)
    assert abs(d[0] + 0.3) < 4 * se[0] and abs(d[1] - 0.3) < 4 * se[1], (d, se)
    assert re.search(r"a dry friction \+0\.(29|30|31)\d* N", ag.statement), ag.statement


def test_records_of_the_same_plant_agree():
    est, model = _record(1, fc=1.0)
    test, _ = _record(3, fc=1.0)
    ag = compare_records(_fit(est, model), [est], [test], unit="N")
    assert not ag.disagree, ag.statement
    assert ag.statement.startswith("The test record agrees")
