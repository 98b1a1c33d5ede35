"""The first-order lag's step mean (:func:`dvt_model.brake.lag_mean_factor`), the one formula
the band capacities, the plant's motor-current lag and band release and the identifier's
engagement transform hold over a step."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from dvt_model.brake import capacity_step, lag_mean_factor


@pytest.mark.parametrize("dt, tau", [(1e-3, 0.02), (5e-3, 0.003), (0.2, 0.01), (1e-3, 1e3)])
def test_the_factor_is_the_mean_of_the_lags_gap_over_the_step(dt: float, tau: float) -> None:
    mean, _err = quad(lambda s: math.exp(-s / tau), 0.0, dt, epsabs=0.0, epsrel=1e-13)
    assert lag_mean_factor(dt, tau) == pytest.approx(mean / dt, rel=1e-12)


def test_a_step_short_against_the_lag_keeps_its_digits() -> None:
    """``1 - dt / (2 tau)`` to first order; ``1 - exp(-x)`` would keep about 7 of 16 digits
    at ``x = 1e-9``."""
    dt, tau = 1e-12, 1e-3
    assert lag_mean_factor(dt, tau) == pytest.approx(1.0 - 0.5 * dt / tau, rel=1e-15)


def test_floats_and_arrays_agree_and_capacity_step_uses_it() -> None:
    taus = np.array([0.01, 0.02, 0.05])
    arr = lag_mean_factor(1e-3, taus)
    assert arr.shape == (3,)
    assert [float(v) for v in arr] == [lag_mean_factor(1e-3, float(t)) for t in taus]
    cap, target = np.array([0.3, 0.0, 1.7]), np.array([1.0, 0.5, 0.0])
    end, mean = capacity_step(cap, target, 1e-3, taus)
    assert np.array_equal(mean, target + (cap - target) * arr)
    assert np.array_equal(end, target + (cap - target) * np.exp(-1e-3 / taus))
