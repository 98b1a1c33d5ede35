"""HAC sandwich covariance, Diebold-Mariano comparison and noise floor (pure, no ROS)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest

from dvt_identify.uncertainty import (
    UncertaintyError,
    bartlett_bandwidth,
    covariance_bandwidth,
    diebold_mariano,
    lag_sums,
    long_run_covariance,
    long_run_term,
    noise_floor,
    nw_bandwidth,
    nw_lags,
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


COVERAGE_CLAIM = (0.90, 0.95)
"""Coverage of the sandwich's nominal 95 % intervals that the test claims under AR(0.9) noise
(the HAC window is biased low under strong colour; measured 272 and 275 of 300)."""


def test_coverage_with_coloured_noise() -> None:
    """Naive intervals are far too narrow for AR(1) noise; the sandwich's cover the truth at a
    rate consistent with :data:`COVERAGE_CLAIM` (two-sided 95 % Clopper-Pearson interval of 300
    runs meets it: 259 to 292 inside pass; a std reported 35 % too small, coverage 0.80, fails
    with probability above 0.99)."""
    rng = np.random.default_rng(1)
    reps, n = 300, 2000
    hit_sandwich = np.zeros(2)
    hit_naive = np.zeros(2)
    for _ in range(reps):
        J, r, err = _regression(rng, n, rho=0.9)
        cov = sandwich_covariance(J, r, ny=1, seg_sizes=[n])
        hit_sandwich += np.abs(err) <= 1.96 * cov.std
        hit_naive += np.abs(err) <= 1.96 * cov.naive_std
    for k in hit_sandwich:
        ci = binomtest(int(k), reps).proportion_ci(0.95, method="exact")
        assert ci.high >= COVERAGE_CLAIM[0] and ci.low <= COVERAGE_CLAIM[1], (k, reps, ci)
    cov_n = hit_naive / reps
    assert np.all(cov_n < 0.75), cov_n


def test_white_noise_matches_naive() -> None:
    rng = np.random.default_rng(2)
    J, r, _ = _regression(rng, 5000, rho=0.0)
    cov = sandwich_covariance(J, r, ny=1, seg_sizes=[5000])
    np.testing.assert_allclose(cov.std, cov.naive_std, rtol=0.15)
    # short: Newey-West's plug-in reads the sampling noise of its 10 autocovariances, a window
    # of the order of N^(1/3) = 17 samples (Andrews' AR(1) rule alone gave <= 10 here)
    assert cov.bandwidth <= 20


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


def test_a_slow_tail_beside_a_fast_decay_lengthens_the_covariance_window() -> None:
    """Scores like the gravity arm's (docs/identification.md): a fast AR(0.15) part and a
    small AR(0.97) part that carries most of the long-run variance. Andrews' AR(1) rule fits
    the fast decay (about 12 samples); the covariance window (the longer of it and Newey-West's
    nonparametric rule) is at least twice as long and its long-run variance nearer the truth
    in each of 10 draws (both below it: a Bartlett window that short is biased low)."""
    n, truth = 6000, 1.0 / (1 - 0.15) ** 2 + 0.06**2 / (1 - 0.97) ** 2
    for seed in range(10):
        rng = np.random.default_rng(seed)
        z = (_ar1(rng, n, 0.15, 1.0) + _ar1(rng, n, 0.97, 0.06))[:, None]
        short, long = bartlett_bandwidth([z]), covariance_bandwidth([z])
        assert long >= 2 * short, (seed, short, long)
        s_short = long_run_term(z, short)[0, 0] / n
        s_long = long_run_term(z, long)[0, 0] / n
        assert s_short < s_long < truth, (seed, s_short / truth, s_long / truth)


def test_the_covariance_window_keeps_the_ar1_rule_where_it_is_longer() -> None:
    """A strong AR(0.9) persistence: Newey-West's few lags fall short of it, Andrews' rule
    does not, and the covariance window is Andrews'; white scores keep a short window."""
    rng = np.random.default_rng(6)
    red = [_ar1(rng, 5000, 0.9, 1.0)[:, None]]
    assert nw_bandwidth([lag_sums(red[0], nw_lags(5000))]) < bartlett_bandwidth(red)
    assert covariance_bandwidth(red) == bartlett_bandwidth(red)
    assert covariance_bandwidth([rng.normal(size=(5000, 3))]) <= 5


def test_lag_sums_standardise_each_column() -> None:
    """A column scaled by 1000 weighs as much as the others in the Newey-West sum."""
    rng = np.random.default_rng(7)
    x = rng.normal(size=(400, 2))
    a, n = lag_sums(x, 3)
    b, _ = lag_sums(x * np.array([1.0, 1000.0]), 3)
    assert n == 400
    np.testing.assert_allclose(a, b, rtol=1e-9)
    assert lag_sums(np.zeros((0, 2)), 3)[1] == 0


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
