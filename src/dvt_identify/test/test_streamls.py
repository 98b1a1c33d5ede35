"""Least squares handed to the solver by the triangular factor folded block by block
(:mod:`dvt_identify.streamls`): the same solution and covariance as the whole problem, in the
fit and in the drift check."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from dvt_identify import streamls
from dvt_identify.data import make_segment
from dvt_identify.effects import make_effect
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_identify.streamls import Factored, fold
from dvt_identify.structures import MechanicalStructure
from dvt_identify.uncertainty import sandwich_by_segment, sandwich_covariance


def test_the_folded_factor_keeps_the_normal_equations() -> None:
    rng = np.random.default_rng(0)
    J = rng.normal(size=(500, 4))
    r = rng.normal(size=500)
    J[:250, 3] = 0.0  # two blocks, each with a column of its own
    J[250:, 2] = 0.0
    blocks = [(J[:250, [0, 1, 2]], r[:250], np.array([0, 1, 2])),
              (J[250:, [0, 1, 3]], r[250:], np.array([0, 1, 3]))]
    R, qtr, rho, rr = fold(blocks, 4)
    H = R.T @ R
    g = R.T @ qtr
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(g, J.T @ r, rtol=1e-10)
    assert qtr @ qtr + rho ** 2 == pytest.approx(r @ r, rel=1e-12)
    assert rr == pytest.approx(r @ r)


def test_a_factored_solve_reaches_the_whole_problems_optimum() -> None:
    t = np.linspace(0.0, 4.0, 400)
    y = 2.0 * np.exp(-0.7 * t) + 0.3 * np.sin(3.0 * t) + 0.01 * np.cos(40 * t)

    def res(z: np.ndarray) -> np.ndarray:
        return z[0] * np.exp(-z[1] * t) + z[2] * np.sin(z[3] * t) - y

    def jac(z: np.ndarray) -> np.ndarray:
        e = np.exp(-z[1] * t)
        return np.column_stack([e, -z[0] * t * e, np.sin(z[3] * t), z[2] * t * np.cos(z[3] * t)])
    cols = np.arange(4)
    fac = Factored(lambda z: ((jac(z)[k:k + 100], res(z)[k:k + 100], cols)
                              for k in range(0, 400, 100)), 4)
    z0 = np.array([1.0, 1.0, 0.1, 2.8])
    whole = least_squares(res, z0, jac=jac, x_scale="jac", method="trf")
    small = least_squares(fac.residual, z0, jac=fac.jacobian, x_scale="jac", method="trf")
    assert small.x == pytest.approx(whole.x, rel=1e-8)
    assert small.cost == pytest.approx(whole.cost, rel=1e-8)
    assert small.nfev == whole.nfev


def _cart() -> tuple[OEModel, list]:
    st = MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[1.0]],
                             {"M": {"initial": 1.0, "lower": 0.01}, "Fv": {"initial": 1.0}},
                             "N", "m/s")
    model = OEModel(st, [make_effect("windage", "v", ["v"], ["F"])])
    theta = np.array([2.0, 3.0, 0.05])
    rng = np.random.default_rng(4)
    segs = []
    for k in range(3):
        n, dt = 1500, 0.005
        u = np.repeat(rng.uniform(-8.0, 8.0, n // 60 + 1), 60)[:n]
        clean = make_segment(f"s{k}", np.arange(n) * dt, u, np.zeros((n, 1)), ["F"], ["v"])
        y = model.simulate(theta, clean, np.array([0.2 * k])) + 0.01 * rng.normal(size=(n, 1))
        segs.append(make_segment(f"s{k}", np.arange(n) * dt, u, y, ["F"], ["v"]))
    return model, segs


def test_the_fit_by_its_factor_equals_the_whole_fit(monkeypatch) -> None:
    """The same optimum and the same (HAC sandwich) standard deviations whether the fit holds
    its Jacobian or folds it segment by segment."""
    model, segs = _cart()
    whole = OEFit(model, starts=1, more_starts=0).fit(segs)
    assert whole.jac_ is not None
    monkeypatch.setattr(streamls, "DENSE_BYTES", 0)
    small = OEFit(model, starts=1, more_starts=0).fit(segs)
    assert small.jac_ is None  # never held whole
    assert small.theta_ == pytest.approx(whole.theta_, rel=1e-6)
    assert small.std_ == pytest.approx(whole.std_, rel=1e-4)
    assert small.residual_ == pytest.approx(whole.residual_, rel=1e-6, abs=1e-9)


def test_the_sandwich_by_segment_is_the_sandwich() -> None:
    rng = np.random.default_rng(2)
    sizes = [300, 200]
    J = rng.normal(size=(1000, 3))
    r = np.convolve(rng.normal(size=1003), np.ones(4) / 2, mode="valid")
    row = [0, 600]

    def rows(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        sl = slice(row[k], row[k] + 2 * sizes[k])
        return J[sl], r[sl], np.arange(3)
    resid, cov = sandwich_by_segment(rows, sizes, 2, 3)
    ref = sandwich_covariance(J, r, 2, sizes)
    assert resid == pytest.approx(r)
    assert cov.std == pytest.approx(ref.std, rel=1e-10) and cov.bandwidth == ref.bandwidth
