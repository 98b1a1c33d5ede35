"""Dry friction with a smoothed sign (option ``eps``) and fits started from a state-initialisation
window (``OEFit(init_window=n)``).

A positioning cart ``M v' = F - Fv v - Fc tanh(v / eps) - offset`` with its *position* measured
(the speed a hidden state), the structure the EMPS description uses.
"""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.data import make_segment
from dvt_identify.description import parse_description
from dvt_identify.effects import make_effect
from dvt_identify.fit import OEFit
from dvt_identify.simloop import COULOMB, smooth_slope, smooth_value
from dvt_identify.simulation import OEModel

TRUE = {"M": 2.0, "Fv": 3.0, "Fc": 1.5, "offset": -0.2}
EPS = 0.01


def _desc(eps: float = EPS):
    return parse_description({
        "name": "slide",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "c"}],
        "outputs": [{"name": "position", "topic": "/s/joint_states", "field": "position",
                     "joint": "c"}],
        "structure": {"type": "mechanical", "members": ["cart"], "mass": [["M"]],
                      "damping": [["Fv"]], "stiffness": [[0.0]], "input_matrix": [[1.0]],
                      "outputs": {"position": "cart_angle"}, "force_unit": "N",
                      "speed_unit": "m/s", "angle_unit": "m",
                      "parameters": {"M": {"initial": 6.0, "lower": 0.01},
                                     "Fv": {"initial": 1.0, "lower": 0.0}}},
        "candidates": [{"effect": "coulomb_friction", "where": "cart", "offset": True,
                        "eps": eps}],
        "fit": {"starts": 1, "refit_starts": 1},
    }, "slide.yaml")


def _model(desc):
    cand = desc.make_candidates()[0]
    return OEModel(desc.structure, [cand]), cand


def _record(seed: int, dt: float = 0.005, n: int = 4000, noise: float = 1e-4):
    desc = _desc()
    model, _ = _model(desc)
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-6.0, 6.0, n // 100 + 1), 100)[:n]
    t = np.arange(n) * dt
    clean = make_segment(f"s{seed}", t, u, np.zeros((n, 1)), desc.input_names,
                         desc.output_names)
    theta = np.array([TRUE["M"], TRUE["Fv"], TRUE["Fc"], TRUE["offset"]])
    x0 = np.array([0.1, 0.0])
    y = model.simulate(theta, clean, x0) + noise * rng.standard_normal((n, 1))
    return make_segment(f"s{seed}", t, u, y, desc.input_names, desc.output_names), theta, x0


def test_the_compiled_slope_is_the_derivative_of_the_law():
    for s in np.linspace(-0.05, 0.05, 41):
        h = 1e-7
        num = (smooth_value(COULOMB, 1.5, EPS, 0.0, s + h)
               - smooth_value(COULOMB, 1.5, EPS, 0.0, s - h)) / (2 * h)
        assert smooth_slope(COULOMB, 1.5, EPS, 0.0, s) == pytest.approx(num, rel=1e-5, abs=1e-6)
        for kind, p in ((0, (0.7, 0.05, EPS)),):
            num = (smooth_value(kind, *p, s + h) - smooth_value(kind, *p, s - h)) / (2 * h)
            assert smooth_slope(kind, *p, s) == pytest.approx(num, rel=1e-5, abs=1e-6)


def test_a_stiff_smoothed_sign_stays_stable_and_converges_with_the_step():
    """At dt * Fc / (M eps) = 7.5 (an explicit hold of the tanh friction is unstable beyond
    about 2) the linearly implicit step stays bounded and within 10 % of the position's range
    of a 0.25-ms simulation; the error shrinks with the step (first order: forces are held
    over a step) and is below 1 % of the range at 2 ms."""
    eps = 0.002
    desc = _desc(eps)
    model, _ = _model(desc)
    theta = np.array([TRUE["M"], TRUE["Fv"], TRUE["Fc"], 0.0])
    fine_dt, block = 0.00025, 1600  # 0.4 s per force level
    n = 40 * block
    u = np.repeat([4.0, -2.5, 0.0, 3.0, -5.0, 2.5, 3.2, -3.2] * 5, block)[:n]
    t = np.arange(n) * fine_dt
    fine = make_segment("fine", t, u, np.zeros((n, 1)), desc.input_names, desc.output_names)
    yf = model.simulate(theta, fine, np.zeros(2))[:, 0]
    span = float(np.ptp(yf))
    errors = {}
    for q in (8, 20, 80):
        coarse = make_segment("coarse", t[::q].copy(), u[::q].copy(), np.zeros((n // q, 1)),
                              desc.input_names, desc.output_names)
        xc, yc = model.simulate_states(theta, coarse, np.zeros(2))
        assert np.all(np.isfinite(xc)) and np.max(np.abs(xc[:, 1])) < 2.0
        # no chatter: in the second half of the zero-force block the carriage has come to
        # rest (|v| < eps; an explicit hold flips the speed's sign every step at |v| ~ dt Fc / M)
        zero = slice((2 * block + block // 2) // q, (3 * block) // q)
        assert np.max(np.abs(xc[zero, 1])) < eps, (q, np.max(np.abs(xc[zero, 1])))
        errors[q * fine_dt] = float(np.max(np.abs(yc[:, 0] - yf[::q]))) / span
    assert 0.02 * TRUE["Fc"] / (TRUE["M"] * eps) > 7.0
    assert errors[0.02] < 0.10, errors
    assert errors[0.002] < errors[0.005] < errors[0.02], errors
    assert errors[0.002] < 0.01, errors


def test_window_fit_recovers_the_cart_from_priors_far_off():
    seg, _, x0 = _record(1)
    desc = _desc()
    model, _ = _model(desc)
    start = np.array([3 * TRUE["M"], TRUE["Fv"] / 3, TRUE["Fc"] * 3, 0.0])
    fit = OEFit(model, starts=1, theta0=start, init_window=20).fit([seg])
    got = dict(zip(model.names, fit.theta_, strict=True))
    std = dict(zip(model.names, fit.std_, strict=True))
    for k, v in TRUE.items():
        assert abs(got[k] - v) <= max(4 * std[k], 0.02 * abs(v)), (k, got[k], v, std[k])
    # the window's initial state: the fitted x0_ is the one estimate_x0 gives, from 20 samples
    assert fit.n_estimated_ == 4
    np.testing.assert_allclose(fit.x0_[0], fit.estimate_x0(seg), rtol=0, atol=1e-9)
    assert abs(fit.x0_[0][0] - x0[0]) < 1e-3  # the position; the speed from 0.1 s of noise
    moved = seg.rows(0, seg.n)
    part = moved.rows(0, 20)
    np.testing.assert_allclose(fit.window_x0(fit.theta_, part), fit.x0_[0], atol=1e-9)


def test_a_negative_window_is_refused_naming_it():
    desc = _desc()
    model, _ = _model(desc)
    with pytest.raises(Exception, match="init_window: expected an integer >= 0"):
        OEFit(model, init_window=-1)


def test_eps_below_zero_is_refused_naming_the_candidate():
    with pytest.raises(Exception, match=r"coulomb_friction@cart: eps: expected a speed >= 0"):
        _desc(eps=-1.0).make_candidates()


def test_the_pushed_term_carries_the_smoothing():
    _, cand = _model(_desc())
    term = cand.model_term(np.array([1.5, -0.2]), ["position"])
    assert term is not None and term["eps"] == EPS
    plain = make_effect("coulomb_friction", "cart", ("cart_angle", "cart"), ("force",))
    t2 = plain.model_term(np.array([1.5, -0.2]), ["position"])
    assert t2 is not None and "eps" not in t2
