"""HAC sandwich covariance, Diebold-Mariano comparison and noise floor (pure, no ROS)."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.uncertainty import (
    UncertaintyError,
    bartlett_bandwidth,
    diebold_mariano,
    long_run_covariance,
    noise_floor,
    sandwich_covariance,
    scores,
)


def _ar1(rng: np.random.Generator, n: int, rho: float, sigma: float) -> np.ndarray:
    e = rng.normal(0.0, sigma, n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - rho**2)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


def _regression(rng: np.random.Generator, n: int, rho: float) -> tuple[np.ndarray, np.ndarray,
                                                                       np.ndarray]:
    """Least squares on a slowly varying regressor with AR(1) noise: (J, r, beta_hat - beta)."""
    t = np.arange(n)
    X = np.column_stack([np.ones(n), np.sin(2 * np.pi * t / 400.0)])
    beta = np.array([1.0, 2.0])
    y = X @ beta + _ar1(rng, n, rho, 0.1)
    bh, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ bh
    # residual = y - X b, so d r / d b = -X
    return -X, r, bh - beta


def test_coverage_with_coloured_noise() -> None:
    """Naive intervals are far too narrow for AR(1) noise; the sandwich's hold (~95 %)."""
    rng = np.random.default_rng(1)
    reps, n = 300, 2000
    hit_sandwich = np.zeros(2)
    hit_naive = np.zeros(2)
    for _ in range(reps):
        J, r, err = _regression(rng, n, rho=0.9)
        cov = sandwich_covariance(J, r, ny=1, seg_sizes=[n])
        hit_sandwich += np.abs(err) <= 1.96 * cov.std
        hit_naive += np.abs(err) <= 1.96 * cov.naive_std
    cov_s = hit_sandwich / reps
    cov_n = hit_naive / reps
    # 300 repetitions: binomial standard error of a 95 % coverage is 1.3 points
    assert np.all(cov_s >= 0.88), cov_s
    assert np.all(cov_s <= 0.99), cov_s
    assert np.all(cov_n < 0.75), cov_n


def test_white_noise_matches_naive() -> None:
    rng = np.random.default_rng(2)
    J, r, _ = _regression(rng, 5000, rho=0.0)
    cov = sandwich_covariance(J, r, ny=1, seg_sizes=[5000])
    np.testing.assert_allclose(cov.std, cov.naive_std, rtol=0.15)
    assert cov.bandwidth <= 10


def test_scores_group_outputs_and_segments() -> None:
    J = np.arange(12.0).reshape(6, 2)
    r = np.array([1.0, 2.0, 0.5, 0.0, 1.0, -1.0])
    g = scores(J, r, ny=2, seg_sizes=[2, 1])
    assert [x.shape for x in g] == [(2, 2), (1, 2)]
    np.testing.assert_allclose(g[0][0], J[0] * 1.0 + J[1] * 2.0)
    np.testing.assert_allclose(g[1][0], J[4] * 1.0 - J[5])


def test_bartlett_window_equals_lag_sum() -> None:
    """The block-sum form equals the explicit weighted lag sum away from the ends."""
    rng = np.random.default_rng(3)
    g = rng.normal(size=(4000, 2))
    g[1:] += 0.5 * g[:-1]
    L = 8
    S = long_run_covariance([g], L)
    direct = g.T @ g
    for lag in range(1, L):
        G = g[lag:].T @ g[:-lag]
        direct += (1 - lag / L) * (G + G.T)
    np.testing.assert_allclose(S, direct, rtol=0.02)


def test_bandwidth_grows_with_colour() -> None:
    rng = np.random.default_rng(4)
    white = [rng.normal(size=(5000, 1))]
    red = [_ar1(rng, 5000, 0.95, 1.0)[:, None]]
    assert bartlett_bandwidth(white) < bartlett_bandwidth(red)


def test_undetermined_parameter_is_infinite() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(size=500)
    J = np.column_stack([x, 2 * x, rng.normal(size=500)])  # first two collinear
    r = rng.normal(size=500)
    cov = sandwich_covariance(J, r, ny=1, seg_sizes=[500])
    assert np.isinf(cov.std[0]) and np.isinf(cov.std[1])
    assert np.isfinite(cov.std[2])


def test_shape_errors_name_the_sizes() -> None:
    with pytest.raises(UncertaintyError, match=r"seg_sizes: \[3\] samples x 2 outputs = 6"):
        sandwich_covariance(np.zeros((4, 1)), np.zeros(4), ny=2, seg_sizes=[3])
    with pytest.raises(UncertaintyError, match="jac: expected shape"):
        sandwich_covariance(np.zeros((4, 1)), np.zeros(5), ny=1, seg_sizes=[5])


def test_diebold_mariano_scales_with_the_noise() -> None:
    rng = np.random.default_rng(6)
    n = 20000
    noise = _ar1(rng, n, 0.5, 1.0)
    effect = 0.15 * np.sin(np.arange(n) / 50.0)  # small: 0.8 % of the error power
    old = [(noise + effect)[:, None]]
    new_good = [noise[:, None]]
    assert diebold_mariano(old, new_good).better(0.01)
    # a model that only changes the error by chance is not accepted (clean data)
    false = 0
    for k in range(40):
        other = _ar1(np.random.default_rng(100 + k), n, 0.5, 1.0)
        a = [noise[:, None]]
        b = [(0.999 * noise + 0.045 * other)[:, None]]  # same power, reshuffled
        false += diebold_mariano(a, b).better(0.01)
    assert false <= 3


def test_diebold_mariano_shapes() -> None:
    with pytest.raises(UncertaintyError, match="segment 0"):
        diebold_mariano([np.zeros((3, 2))], [np.zeros((4, 2))])


def test_noise_floor_separates_white_from_structured() -> None:
    rng = np.random.default_rng(7)
    white = rng.normal(0, 0.3, 10000)
    nf = noise_floor([white])
    assert nf.structured_share < 0.03
    assert abs(nf.floor_rms - 0.3) < 0.01
    slow = white + 1.0 * np.sin(np.arange(10000) / 100.0)
    assert noise_floor([slow]).structured_share > 0.8
