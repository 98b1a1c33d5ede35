"""Exact kinematics and gear ratios against the thesis's printed figures."""

from fractions import Fraction

import pytest

from dvt_model.kinematics import kinematics, stage_ratio
from dvt_model.params import load_parameters


@pytest.fixture(scope="module")
def kin_derivation():
    return kinematics(load_parameters("thesis-derivation"))


@pytest.mark.parametrize(("member", "a", "b"), [
    ("ring1", "-439498/893101", "1332599/893101"),
    ("carrier1", "-2346/7381", "9727/7381"),
    ("ring2", "-2346/7381", "9727/7381"),
    ("carrier2", "-10/61", "71/61"),
    ("ring3", "-10/61", "71/61"),
    ("planet1", "279970/391193", "-671163/391193"),
    ("planet2", "1666/3233", "-4899/3233"),
    ("planet3", "2/5", "-7/5"),
    ("sun", "1", "0"),
    ("carrier3", "0", "1"),
])
def test_thesis_fractions_exact(kin_derivation, member, a, b):
    assert kin_derivation.forms[member] == (Fraction(a), Fraction(b))


def test_gear_ratios_thesis_table():
    kin = kinematics(load_parameters("thesis"))
    ratios = [float(kin.gear_ratio(g)) for g in (1, 2, 3)]
    assert ratios == pytest.approx([3.039, 4.161, 7.15], abs=5e-4)
    assert kin.gear_ratio(3) == Fraction(143, 20)


def test_gear_ratio_rejects_bad_gear(kin_derivation):
    with pytest.raises(ValueError, match="gear: expected 1, 2 or 3, got 4"):
        kin_derivation.gear_ratio(4)


def test_planet_sign_convention_and_willis(kin_derivation):
    # thesis planet speed = -(absolute); absolute planet speed obeys both meshes
    f = kin_derivation.forms
    for k in (1, 2, 3):
        assert f[f"planet{k}"] == (-f[f"planet{k}_abs"][0], -f[f"planet{k}_abs"][1])
    # rotating as a rigid body (sun = carrier3 = 1): every member turns at 1
    for m in ("ring1", "ring2", "ring3", "carrier1", "carrier2", "planet1_abs"):
        assert f[m][0] + f[m][1] == 1


def test_stage_ratios_against_printed():
    # the thesis prints 8.625 and 7.05: neither matches its own teeth table (docs/errata.md)
    assert stage_ratio(16, 121) == Fraction(137, 16)  # 8.5625
    assert stage_ratio(16, 122) == Fraction(138, 16)  # 8.625: ring 122
    assert stage_ratio(20, 121) == Fraction(141, 20)  # 7.05: stage-3 sun with a 121 ring
    assert stage_ratio(20, 123) == Fraction(143, 20)  # 7.15
