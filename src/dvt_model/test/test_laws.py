"""The law table: one function per law, the contract's force terms built from it, the
partials exact, the smoothed sign the same in every law."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_model import laws
from dvt_model.contract import EFFECT_TERMS
from dvt_model.terms import parse_terms

SPEEDS = np.concatenate([np.linspace(-20.0, 20.0, 161), np.linspace(-1e-3, 1e-3, 41)])
CODED = {law.code: law.example for law in laws.LAWS.values()}
"""Each law's code -> its typical coded parameters (p0, p1, p2)."""


def test_codes_are_unique_and_every_law_has_a_branch() -> None:
    codes = [law.code for law in laws.LAWS.values()]
    assert len(set(codes)) == len(codes)
    assert len(CODED) == len(laws.LAWS)
    for law in laws.LAWS.values():
        assert laws.law_of_code(law.code) is law
        fields = {p.name: (p.default if p.default is not None else 0.7) for p in law.params}
        fields["eps"] = 0.05
        p = CODED[law.code]
        coded = {name: value for name, value in zip(law.coded, p, strict=True) if name}
        fields.update(coded)
        for v in (-3.0, -1e-4, 0.0, 2e-3, 7.0):  # the table's dispatch is the law itself
            assert laws.coded_value(law.code, *p, v) == pytest.approx(
                law(v, fields) - fields.get("offset", 0.0), rel=1e-15, abs=1e-15)


def test_the_contract_force_terms_are_the_table() -> None:
    for name in laws.TERM_LAWS:
        kind, law = EFFECT_TERMS[name], laws.LAWS[name]
        assert kind.member and kind.doc == law.doc
        names = [p.name for p in law.params] + (["eps"] if law.dry else [])
        assert [p.name for p in kind.params] == names
        for lp in law.params:
            cp = kind.param(lp.name)
            assert (cp.unit, cp.lo, cp.hi, cp.lo_open, cp.default) == (
                lp.unit, lp.lower, lp.upper, lp.lo_open, lp.default)


@pytest.mark.parametrize("code", sorted(CODED))
def test_partials_are_the_derivatives_of_the_law(code: int) -> None:
    p = np.array(CODED[code])
    for v in SPEEDS[np.abs(SPEEDS) > 1e-6].tolist():  # the exact sign has no slope at 0
        f, *d = laws.coded_partials(code, *p, v)
        assert f == pytest.approx(laws.coded_value(code, *p, v), rel=1e-12, abs=1e-15)
        h = 1e-7 * max(1.0, abs(v))
        num = (laws.coded_value(code, *p, v + h) - laws.coded_value(code, *p, v - h)) / (2 * h)
        assert d[0] == pytest.approx(num, rel=1e-5, abs=1e-6)
        for k in range(3):
            if not p[k]:
                continue
            q = p.copy()
            hk = 1e-7 * abs(p[k])
            q[k] += hk
            up = laws.coded_value(code, *q, v)
            q[k] -= 2 * hk
            dn = laws.coded_value(code, *q, v)
            assert d[1 + k] == pytest.approx((up - dn) / (2 * hk), rel=1e-5, abs=1e-6)


def test_dry_laws_use_the_one_smoothed_sign_and_the_hard_sign_at_eps_zero() -> None:
    v = SPEEDS
    for eps in (1e-3, 0.05, 0.5):
        s = np.tanh(v / eps)
        np.testing.assert_array_equal(laws.sign_eps(v, eps), s)
        np.testing.assert_array_equal(laws.coulomb(v, 0.3, 0.0, eps), 0.3 * s)
        np.testing.assert_array_equal(laws.stribeck(v, 0.2, 4.0, eps),
                                      0.2 * np.exp(-np.abs(v / 4.0) ** 2.0) * s)
    np.testing.assert_array_equal(laws.coulomb(v, 0.3, 0.0, 0.0), 0.3 * np.sign(v))
    assert laws.coulomb(0.0, 0.3, 0.0, 0.0) == 0.0


def test_a_pushed_term_is_evaluated_by_its_law_in_the_table() -> None:
    terms = parse_terms([{"kind": "stribeck", "member": [1, 0], "Fs": 0.2, "vs": 5.0,
                          "eps": 0.01},
                         {"kind": "coulomb", "member": [0, 1], "Fc": 0.3, "offset": 0.05}])
    for v in SPEEDS.tolist():
        f = terms.extra_force(np.array([v, -v]), 0.0)
        assert f[0] == -laws.stribeck(v, 0.2, 5.0, 0.01)
        assert f[1] == -laws.coulomb(-v, 0.3, 0.05, 0.5)  # contract default eps 0.5

