"""Do the records agree? (:mod:`dvt_identify.disagree`): a cart whose dry friction is 0.3 N
higher in the test record than in the estimation record is told apart from one that is not."""

from __future__ import annotations

import re

import numpy as np

from dvt_identify.disagree import compare_records
from dvt_identify.fit import OEFit


def _fit(seg, model, start):
    return OEFit(model, starts=1, theta0=start).fit([seg])


def test_a_friction_higher_in_the_test_record_is_detected_and_read_as_friction(
        slide_record, slide_start):
    est, model = slide_record(1, fc=1.0)
    test, _ = slide_record(2, fc=1.3)
    ag = compare_records(_fit(est, model, slide_start()), [est], test=[test], unit="N")
    assert ag.disagree, ag.statement
    assert ag.test.labels == ["force +", "force -"]
    # bias(+) = -dFc, bias(-) = +dFc with dFc = 0.3 N: within 4 of their standard errors
    d = ag.test.value - ag.estimation.value
    se = np.sqrt(ag.test.std ** 2 + ag.estimation.std ** 2)
    assert abs(d[0] + 0.3) < 4 * se[0] and abs(d[1] - 0.3) < 4 * se[1], (d, se)
    assert re.search(r"a dry friction \+0\.(29|30|31)\d* N", ag.statement), ag.statement


def test_records_of_the_same_plant_agree(slide_record, slide_start):
    est, model = slide_record(1, fc=1.0)
    test, _ = slide_record(3, fc=1.0)
    ag = compare_records(_fit(est, model, slide_start()), [est], [test], unit="N")
    assert not ag.disagree, ag.statement
    assert ag.statement.startswith("The test record agrees")
