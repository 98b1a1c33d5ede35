"""Starts from the data (:mod:`dvt_identify.startmap`): a structure's parameters mapped from a
linear model's frequency response, from priors far off."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.description import load_description
from dvt_identify.simulation import zoh
from dvt_identify.startmap import frequency_response_starts, match_band
from dvt_identify.structures import output_matrix

TRUE = {"Jm": 0.01, "Jl": 0.03, "k": 20.0, "c": 0.02, "dm": 0.005, "dl": 0.01}


@pytest.mark.parametrize("factors", [(3, 1 / 3, 3, 1 / 3, 3, 1 / 3), (1 / 3,) * 6, (3,) * 6])
def test_the_two_mass_drive_is_recovered_from_priors_3x_off(factors):
    st = load_description("two-mass").structure
    names = [p.name for p in st.params]
    theta = np.array([TRUE[n] for n in names])
    A, B, _ = st.matrices(theta)
    dt = 1 / 200
    Ad, Gd = zoh(A, dt)
    C = output_matrix(st)
    prior = theta * np.array(factors)
    lo = np.array([p.lower for p in st.params])
    hi = np.array([p.upper for p in st.params])
    starts = frequency_response_starts(st, Ad, Gd @ B, C, dt, 30.0, prior, lo, hi)
    assert starts and starts[0].mismatch < 1e-6
    np.testing.assert_allclose(starts[0].theta, theta, rtol=1e-4)


def test_an_integrating_drive_maps_mass_and_damping():
    """The EMPS structure (position measured, speed hidden, a free integrator): the mass and
    the viscous damping of a reference built from M 95, Fv 200, from priors 10x off."""
    st = load_description("emps-position").structure
    theta = np.array([95.0, 200.0])
    A, B, _ = st.matrices(theta)
    dt = 1e-3
    Ad, Gd = zoh(A, dt)
    starts = frequency_response_starts(st, Ad, Gd @ B, output_matrix(st), dt, 25.0,
                                       np.array([9.5, 2000.0]), np.array([1e-3, 0.0]),
                                       np.array([np.inf, np.inf]))
    np.testing.assert_allclose(starts[0].theta, theta, rtol=1e-5)


def test_an_unevaluable_reference_gives_no_start():
    st = load_description("two-mass").structure
    n = 4
    bad = np.full((n, n), np.nan)
    out = frequency_response_starts(st, bad, np.ones((n, 1)), np.ones((1, n)), 0.005, 30.0,
                                    np.ones(6) * 0.01, np.zeros(6), np.full(6, np.inf))
    assert out == []


def test_the_band_runs_from_two_periods_of_the_record_to_a_fifth_of_the_rate():
    f = match_band(0.001, 20.0, 10)
    assert f[0] == pytest.approx(0.1) and f[-1] == pytest.approx(200.0)
