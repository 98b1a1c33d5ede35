"""Models that carry the records' disagreement (:mod:`dvt_identify.carrier`): an input bias set
in the test record's initial-state window is recovered and cuts the test error; the choice is
made on estimation data alone and says "none" when the estimation record holds no change."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.carrier import choose_carrier, offer_carrier, window_bias
from dvt_identify.disagree import compare_records
from dvt_identify.fit import OEFit
from dvt_identify.series import evaluate_test

W = 200
"""Initial-state window [samples] (1 s at 5 ms)."""


@pytest.fixture(scope="module")
def fitted(slide_record, slide_start):
    est, model = slide_record(1)
    fit = OEFit(model, starts=1, theta0=slide_start(), init_window=W)
    return est, fit.fit([est])


def test_a_constant_test_bias_is_recovered_from_the_window_and_cuts_the_test_error(fitted, slide_record):
    est, fit = fitted
    test, _ = slide_record(2, bias=0.5)
    plain = evaluate_test(fit, fit, [test], W).final
    assert compare_records(fit, [est], [test], "N").disagree
    offer = offer_carrier(fit, [est], [test], W, plain, "N")
    const = next(c for c in offer.carried if c.kind == "constant")
    b = const.biases[0]
    assert b.labels == ["force"]
    assert abs(b.value[0] - 0.5) < 3 * b.std[0], (b.value, b.std)
    assert 0 < b.std[0] < 0.05, b.std
    assert const.figures.rmse[0] < 0.2 * plain.rmse[0], (const.figures.rmse, plain.rmse)
    # the estimation record holds no change: the carrier is offered, not chosen
    assert offer.choice.chosen == "none", offer.choice.reason
    rep = offer.as_dict()
    assert [r["kind"] for r in rep["test"]] == ["none", "constant", "direction"]


def test_without_a_bias_the_choice_is_none_and_the_test_figure_unchanged(fitted, slide_record):
    est, fit = fitted
    test, _ = slide_record(3)
    plain = evaluate_test(fit, fit, [test], W).final
    offer = offer_carrier(fit, [est], [test], W, plain, "N")
    assert offer.choice.chosen == "none", offer.choice.reason
    assert offer.plain.rmse == plain.rmse
    const = next(c for c in offer.carried if c.kind == "constant")
    assert abs(const.biases[0].value[0]) < 3 * const.biases[0].std[0]


def test_the_bias_comes_from_the_window_alone(fitted, slide_record):
    _, fit = fitted
    test, _ = slide_record(2, bias=0.5)
    other, _ = slide_record(2, bias=np.r_[np.full(W, 0.5), np.full(4000 - W, -3.0)])
    for kind in ("constant", "direction"):
        a, b = window_bias(fit, test, W, kind), window_bias(fit, other, W, kind)
        np.testing.assert_array_equal(a.value, b.value)
        np.testing.assert_array_equal(a.x0, b.x0)


def test_a_bias_that_changes_within_the_estimation_record_gets_a_carrier_chosen(
        slide_record, slide_start):
    # the linear slide: a friction in the model would absorb part of the changing bias
    n = 4000
    steps = np.repeat([0.0, 0.6, -0.4, 0.3, -0.5], n // 5)
    est, model = slide_record(4, bias=steps, n=n, friction=False)
    fit = OEFit(model, starts=1, theta0=slide_start(friction=False), init_window=W)
    fit.fit([est])
    choice = choose_carrier(fit, [est], W, blocks=5)
    # the constant carrier or the one per direction (more freedom for a model the changing
    # bias distorted): either carries it
    assert choice.chosen in ("constant", "direction"), choice.reason
    none = choice.scores[0]
    best = next(s for s in choice.scores if s.kind == choice.chosen)
    assert best.sse < 0.5 * none.sse and best.better >= 3, choice.reason
