"""Design formulas (dvt_model.design) against independent hand calculations."""

import math

import pytest

from dvt_model.design import involute as inv
from dvt_model.design.components import (
    eq_3_17,
    eq_3_18,
    l10_hours,
    min_diameter,
)
from dvt_model.design.report import printed_tolerance

A20 = math.radians(20.0)


def test_involute_function_and_inverse():
    # inv 20 deg = tan 20 - 20 pi/180 = 0.3639702343 - 0.3490658504 = 0.0149043839 (tables)
    assert inv.inv(A20) == pytest.approx(0.0149043839, abs=1e-10)
    for deg in (5.0, 10.87, 20.0, 23.82, 35.0):
        a = math.radians(deg)
        assert inv.inv_inverse(inv.inv(a)) == pytest.approx(a, abs=1e-12)
    with pytest.raises(ValueError, match="expected a value >= 0"):
        inv.inv_inverse(-1e-3)


def test_operating_pressure_angle_hand_calc():
    # stage 1 sun-planet: a = (16+53)/2 = 34.5 mm, a' = 1.375 in = 34.925 mm
    # cos a' = 34.5 cos 20 / 34.925 = 32.41939 / 34.925 = 0.928258 -> a' = 21.835 deg
    a = inv.operating_pressure_angle(34.5, 34.925, A20)
    assert math.degrees(a) == pytest.approx(21.835, abs=5e-4)
    # internal planet-ring, signed: a = (53-121)/2 = -34, a' = -34.925 -> 23.822 deg
    a = inv.operating_pressure_angle(-34.0, -34.925, A20)
    assert math.degrees(a) == pytest.approx(23.822, abs=5e-4)
    with pytest.raises(ValueError, match="too short"):
        inv.operating_pressure_angle(34.5, 30.0, A20)


def test_shift_sum_and_its_inverse():
    # x1 + x2 = (inv a' - inv a)(z1 + z2) / (2 tan a); stage 1 sun-planet by hand:
    # inv 21.8352 deg = 0.4006841 - 0.3810960 = 0.0195881; (0.0195881 - 0.0149044) 69 / 0.727940
    a_op = inv.operating_pressure_angle(34.5, 34.925, A20)
    hand = (0.0195881 - 0.0149044) * 69 / 0.727940
    assert inv.shift_sum(16, 53, A20, a_op) == pytest.approx(hand, abs=1e-5)
    assert inv.shift_sum(16, 53, A20, a_op) == pytest.approx(0.4440, abs=5e-5)
    # the independent inverse gives the centre distance back, external and internal
    assert inv.centre_distance_from_shifts(16, 53, 0.444, 0.0, 1.0, A20) == pytest.approx(
        34.925, abs=2e-4)
    s = inv.shift_sum(53, -121, A20, inv.operating_pressure_angle(-34.0, -34.925, A20))
    assert s == pytest.approx(-1.0121, abs=5e-5)
    assert inv.centre_distance_from_shifts(53, -121, 0.0, s, 1.0, A20) == pytest.approx(
        -34.925, abs=1e-9)


def test_undercut_limit_is_the_classical_17_teeth():
    # 2 / sin^2 20 = 2 / 0.116978 = 17.097; with x = 0.5: 8.55
    assert inv.undercut_teeth_limit(0.0, A20) == pytest.approx(17.097, abs=5e-4)
    assert inv.undercut_teeth_limit(0.5, A20) == pytest.approx(8.549, abs=5e-4)


def test_contact_ratio_external_hand_calc():
    # 20/40 teeth, m = 1, x = 0, a = 30: r_a = 11, 21; r_b = 9.396926, 18.793852
    g1 = math.sqrt(11**2 - 9.396926**2)  # 5.71830
    g2 = math.sqrt(21**2 - 18.793852**2)  # 9.36958
    path = g1 + g2 - 30 * math.sin(A20)  # 10.26060 -> 4.82728
    assert path == pytest.approx(4.8273, abs=1e-4)
    got = inv.path_of_contact(11.0, 9.396926, 21.0, 18.793852, 30.0, A20)
    assert got == pytest.approx(path, abs=1e-5)
    assert inv.contact_ratio(got, 1.0, A20) == pytest.approx(1.6352, abs=1e-4)


def test_contact_ratio_internal_hand_calc():
    # pinion 20 in ring 60, m = 1, x = 0, a = 20: r_a,ring = 29 (inside), r_b,ring = 28.190779
    # path = sqrt(11^2 - 9.396926^2) - sqrt(29^2 - 28.190779^2) + 20 sin 20
    #      = 5.71830 - 6.80306 + 6.84040 = 5.75564 ; eps = 5.75564 / 2.952131 = 1.94965
    got = inv.path_of_contact(11.0, 9.396926, -29.0, -28.190779, -20.0, A20)
    assert got == pytest.approx(5.7556, abs=1e-4)
    assert inv.contact_ratio(got, 1.0, A20) == pytest.approx(1.9497, abs=1e-4)


def test_tooth_thickness_at_base_circle():
    # s_b = d_b (s/d + inv a): z = 20, x = 0: 18.793852 (1.570796/20 + 0.014904) = 1.756184
    d_b = 20 * math.cos(A20)
    assert inv.thickness_at_diameter(20, 1.0, 0.0, A20, d_b) == pytest.approx(1.75618, abs=1e-5)
    # on the reference circle: pi/2 + 2 x tan a
    assert inv.thickness_at_diameter(20, 1.0, 0.3, A20, 20.0) == pytest.approx(
        math.pi / 2 + 0.6 * math.tan(A20), abs=1e-12)
    with pytest.raises(ValueError, match="inside the base circle"):
        inv.thickness_at_diameter(20, 1.0, 0.0, A20, 18.0)


def test_shaft_equations_hand_calc():
    # eq. 3.17: (16 * 12 * 2 / (pi * 860e6))^(1/3) = (384 / 2.701770e9)^(1/3) = 5.2187 mm
    assert eq_3_17(12.0, 2.0, 860e6) * 1000 == pytest.approx(5.2187, abs=5e-5)
    # eq. 3.18 with R_D = 0 is eq. 3.17 with S_y / 2 (maximum shear stress)
    assert eq_3_18(12.0, 2.0, 860e6, 0.0) == pytest.approx(eq_3_17(12.0, 2.0, 430e6), rel=1e-12)
    # von Mises, solid: (16 T N / (pi 0.57735 S_y))^(1/3) = 5.21868 * 1.200937 = 6.2673 mm
    assert min_diameter(12.0, 2.0, 860e6 / math.sqrt(3)) * 1000 == pytest.approx(6.2673, abs=5e-5)
    # hollow: the result satisfies tau = 16 T D / (pi (D^4 - d^4)) = tau_allow / N
    D = min_diameter(85.8, 2.0, 290e6, bore=0.01905)
    assert 16 * 85.8 * D / (math.pi * (D**4 - 0.01905**4)) == pytest.approx(145e6, rel=1e-9)


def test_bearing_life_hand_calc():
    # (C/P)^3 10^6 / (60 n): C/P = 10, n = 1000 rpm -> 1e9 / 6e4 = 16667 h (eq. 3.19's constant)
    assert l10_hours(1000.0, 100.0, 1000.0, 3.0) == pytest.approx(1e9 / 6e4, rel=1e-12)
    # roller exponent 10/3: (C/P)^(1/3) = 10^(1/3) = 2.1544 times longer
    assert l10_hours(1000.0, 100.0, 1000.0, 10 / 3) == pytest.approx(
        1e9 / 6e4 * 10 ** (1 / 3), rel=1e-12)
    assert math.isinf(l10_hours(1000.0, 0.0, 1000.0, 3.0))
    assert math.isinf(l10_hours(1000.0, 10.0, 0.0, 3.0))


def test_printed_tolerance_is_half_the_last_digit():
    assert printed_tolerance(8.625) == pytest.approx(5e-4)
    assert printed_tolerance(7.05) == pytest.approx(5e-3)
    assert printed_tolerance(3) == pytest.approx(0.5)
    assert printed_tolerance(0.87) == pytest.approx(5e-3)
