"""Quality figures against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvt_identify import metrics


def test_fit_percent_and_rmse_by_hand() -> None:
    y = np.array([1.0, 2.0, 3.0, 4.0])
    yhat = np.array([1.0, 2.0, 3.0, 5.0])
    # ||y - yhat|| = 1, ||y - mean|| = sqrt(2.25 + 0.25 + 0.25 + 2.25) = sqrt(5)
    assert metrics.fit_percent(y, yhat)[0] == pytest.approx(100 * (1 - 1 / math.sqrt(5)))
    assert metrics.rmse(y, yhat)[0] == pytest.approx(0.5)
    assert metrics.fit_percent(y, y)[0] == pytest.approx(100.0)
    assert metrics.fit_percent(y, np.full(4, 2.5))[0] == pytest.approx(0.0)


def test_multi_output_loss_is_determinant() -> None:
    y = np.zeros((4, 2))
    e = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 2.0], [0.0, -2.0]])
    # E^T E / N = diag(2, 8) / 4 = diag(0.5, 2) -> det 1
    assert metrics.loss(y, y - e) == pytest.approx(1.0)


def test_fpe_aic_bic_by_hand() -> None:
    assert metrics.fpe(2.0, 100, 10) == pytest.approx(2.0 * 1.1 / 0.9)
    assert metrics.fpe(1.0, 5, 5) == math.inf
    n, ny, d, lv = 1000, 1, 3, 0.25
    m2ll = n * math.log(lv) + n * ny * (1 + math.log(2 * math.pi))
    assert metrics.aic(lv, n, ny, d) == pytest.approx(m2ll + 6)
    assert metrics.bic(lv, n, ny, d) == pytest.approx(m2ll + 3 * math.log(1000))


def test_pooled_figures_equal_single_segment_compare() -> None:
    rng = np.random.default_rng(0)
    y = rng.normal(size=(200, 2))
    yh = y + 0.1 * rng.normal(size=(200, 2))
    f1 = metrics.figures([y], [yh], 3, ["a", "b"])
    assert f1.fit_percent == pytest.approx(tuple(metrics.fit_percent(y, yh)))
    assert f1.rmse == pytest.approx(tuple(metrics.rmse(y, yh)))
    # two segments: each keeps its own mean
    f2 = metrics.figures([y[:100] + 5.0, y[100:]], [yh[:100] + 5.0, yh[100:]], 3, ["a", "b"])
    num = np.sqrt(np.sum((y - yh) ** 2, axis=0))
    den = np.sqrt(np.sum((y[:100] - y[:100].mean(0)) ** 2, axis=0)
                  + np.sum((y[100:] - y[100:].mean(0)) ** 2, axis=0))
    assert f2.fit_percent == pytest.approx(tuple(100 * (1 - num / den)))
    assert f2.n_samples == 200
    d = f2.as_dict()
    fp = d["fit_percent"]
    assert isinstance(fp, dict) and set(fp) == {"a", "b"}


def test_shape_mismatch_message() -> None:
    with pytest.raises(ValueError, match=r"yhat: expected shape \(4, 1\), got \(3, 1\)"):
        metrics.fit_percent(np.zeros(4), np.zeros(3))


def test_parameter_std_matches_linear_regression_formula() -> None:
    rng = np.random.default_rng(1)
    x = np.column_stack([np.ones(500), rng.normal(size=500)])
    r = rng.normal(scale=0.3, size=500)
    std = metrics.parameter_std(x, r)
    s2 = r @ r / (500 - 2)
    want = np.sqrt(np.diag(s2 * np.linalg.inv(x.T @ x)))
    assert std == pytest.approx(want, rel=1e-9)
    # an undetermined direction gives inf
    xd = np.column_stack([x[:, 1], 2 * x[:, 1]])
    assert np.all(np.isinf(metrics.parameter_std(xd, r)))
