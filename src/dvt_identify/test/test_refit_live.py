"""Regressions of the supervisor's live refit at 250 Hz (``docs/loop.md`` section 4).

* candidate scores count only what a candidate removes from the residual *projected* off the
  model's span (a bound-constrained baseline left 18.5 % of its residual in its own span, and
  every candidate was credited with it);
* an even fit decimation keeps the decimated outputs centred (``np.ones(2) / 2`` lagged them
  by half a fine step: 2 ms at 250 Hz, which only the estimation data had);
* a linear part that cannot be simulated (a finite-difference step or trial point off a
  bound-hugging mass matrix) is a named :class:`DivergedError`, a penalty in the fit and a
  zero sensitivity in scoring, never a ``LinAlgError`` from ``np.linalg.eig``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import run_offline
from dvt_driver.run.experiment_core import build
from dvt_identify.data import Segment
from dvt_identify.description import load_description
from dvt_identify.fit import OEFit
from dvt_identify.scoring import column as _column
from dvt_identify.scoring import explained as _explained
from dvt_identify.simulation import DivergedError, OEModel, zoh_decimate
from dvt_identify.structures import PENALTY
from dvt_model.params import load_parameters

PERIOD_US = 4000  # 250 Hz, the live loop's rate


@pytest.fixture(scope="module")
def seg250() -> Segment:
    """4 s of the ``watch`` experiment on the ``physical`` plant with the ``coulomb`` preset
    (the friction step's after state), 250 Hz, offline."""
    desc = load_description("dvt")
    exp = dataclasses.replace(build("watch", seed=0, duration=4.0), sample_period_us=PERIOD_US)
    run = run_offline(exp, load_parameters("physical"), load_hidden("coulomb"), seed=0)
    k = run.t >= 1.0
    return Segment(name="watch250", t=run.t[k], u=run.currents[k], y=run.speeds[k],
                   input_names=tuple(desc.input_names),
                   output_names=tuple(desc.output_names), dt=PERIOD_US * 1e-6)


def test_score_counts_only_the_projected_residual() -> None:
    rng = np.random.default_rng(0)
    e = rng.standard_normal(400)
    ee = float(e @ e)
    e_p = np.zeros_like(e)  # all of the residual lies in the model's own span
    Z = rng.standard_normal((400, 2))
    inf = np.full(2, np.inf)
    r2, _, _ = _explained(Z, e_p, ee, -inf, inf, np.ones(2, dtype=bool))
    assert r2 == 0.0, f"a candidate was credited with {100 * r2:.3g} % the model holds"
    # the raw score (unprojected residual) is unchanged: the columns' own share
    r2_raw, beta, _ = _explained(Z, e, ee, -inf, inf, np.ones(2, dtype=bool))
    res = e - Z @ beta
    assert r2_raw == pytest.approx((ee - float(res @ res)) / ee)


@pytest.mark.parametrize("q", [2, 3, 4])
def test_decimated_outputs_are_centred(q: int, seg250: Segment) -> None:
    ramp = dataclasses.replace(seg250, y=np.column_stack([seg250.t, 2.0 * seg250.t]))
    dec = zoh_decimate(ramp, q)
    inner = slice(1, dec.y.shape[0] - 1)  # the first is the measured sample; the last edge
    lag = dec.t[inner] - dec.y[inner, 0]
    assert np.max(np.abs(lag)) < 1e-9, f"q = {q}: outputs lag by {np.max(lag):.3g} s"
    # the input stays the step mean of the held samples
    np.testing.assert_allclose(dec.u[0], seg250.u[:q].mean(axis=0))


def _dvt_model() -> tuple[OEModel, np.ndarray]:
    desc = load_description("dvt")
    model = OEModel(desc.structure, desc.make_model_effects())
    return model, model.initial()


def test_singular_mass_matrix_is_a_named_divergence(seg250: Segment) -> None:
    model, theta = _dvt_model()
    bad = theta.copy()
    i11, i12, i22 = (model.names.index(n) for n in ("M11", "M12", "M22"))
    bad[[i11, i12, i22]] = [1e-3, 1e-3, 1e-3]  # det M = 0
    with pytest.raises(DivergedError, match=r"simulation diverged.*M11 = 0\.001"):
        model.simulate(bad, seg250, seg250.y[0].astype(float))
    with pytest.raises(ValueError):  # callers that take a ValueError as a penalty keep doing so
        model.simulate(bad, seg250, seg250.y[0].astype(float))


def test_divergence_is_a_penalty_in_the_fit_and_no_information_in_scoring(
        seg250: Segment) -> None:
    model, _ = _dvt_model()
    fit = OEFit(model, starts=1, max_nfev=5, more_starts=0).fit([seg250])
    x0 = fit.x0_[0]
    bad = fit.theta_.copy()
    i11, i12, i22 = (model.names.index(n) for n in ("M11", "M12", "M22"))
    bad[[i11, i12, i22]] = [1e-3, 1e-3, 1e-3]
    r = fit._residual(bad, [seg250], [x0], fit.weights_)
    assert r.shape == (seg250.y.size,) and np.all(r == PENALTY)
    base = [model.simulate(fit.theta_, seg250, x0)]
    # a probe of M12 that makes M singular: a zero column, not a crash
    h = 1e-3 - float(fit.theta_[i12])
    th = fit.theta_.copy()
    th[[i11, i22]] = [1e-3, 1e-3]
    col = _column(model, th, [seg250], [x0], base, fit.weights_, i12, h)
    assert col.shape == (seg250.y.size,) and not np.any(col)
