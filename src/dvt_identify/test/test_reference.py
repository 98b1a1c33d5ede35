"""The black-box linear reference: order and dynamics recovered from known LTI systems, the
analytic Jacobian, initial states, other sample rates, refused input."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.linalg import expm

from dvt_identify import oerefine
from dvt_identify.data import Segment, make_segment
from dvt_identify.errors import DataError, FitError
from dvt_identify.lti import StateSpace
from dvt_identify.metrics import figures
from dvt_identify.reference import LinearReference

Array = NDArray[np.float64]


def _zoh(Ac: Array, Bc: Array, dt: float) -> tuple[Array, Array]:
    n, nu = Bc.shape
    M = np.zeros((n + nu, n + nu))
    M[:n, :n] = Ac
    M[:n, n:] = Bc
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def _mode(f_hz: float, zeta: float, gain: float) -> tuple[Array, Array, Array]:
    """A damped mode ``gain wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (output the position)."""
    wn = 2 * np.pi * f_hz
    return (np.array([[0.0, 1.0], [-wn ** 2, -2 * zeta * wn]]), np.array([[0.0], [wn ** 2]]),
            np.array([[gain, 0.0]]))


def _two_modes() -> tuple[Array, Array, Array]:
    """Two modes in parallel: 1 Hz (zeta 0.3, gain 1) and 8 Hz (zeta 0.1, gain 0.5)."""
    A1, B1, C1 = _mode(1.0, 0.3, 1.0)
    A2, B2, C2 = _mode(8.0, 0.1, 0.5)
    Ac = np.zeros((4, 4))
    Ac[:2, :2], Ac[2:, 2:] = A1, A2
    return Ac, np.vstack([B1, B2]), np.hstack([C1, C2])


def _record(name: str, sys: tuple[Array, Array, Array], dt: float, n: int, seed: int,
            noise: float = 0.0, x0: Array | None = None, hold: int = 10
            ) -> tuple[Segment, Array]:
    """Random input steps (held ``hold`` samples) through the continuous system ``sys`` at
    sample time ``dt`` (zero-order hold), output noise ``noise * std(y)``: the segment and the
    noise-free output (n, 1)."""
    rng = np.random.default_rng(seed)
    Ac, Bc, C = sys
    A, B = _zoh(Ac, Bc, dt)
    u = np.repeat(rng.standard_normal(n // hold + 1), hold)[:n, None]
    x = np.zeros(Ac.shape[0]) if x0 is None else np.asarray(x0, float)
    y = np.empty((n, 1))
    for k in range(n):
        y[k] = C @ x
        x = A @ x + B @ u[k]
    noisy = y + noise * y.std() * rng.standard_normal(y.shape)
    return make_segment(name, np.arange(n) * dt, u, noisy, ["u"], ["y"]), y


def _response(A: Array, B: Array, C: Array, D: Array, dt: float, f: Array) -> Array:
    """Frequency response of the discrete model at ``f`` [Hz] (SISO), complex (len(f),)."""
    n = A.shape[0]
    return np.array([(C @ np.linalg.solve(np.exp(2j * np.pi * fk * dt) * np.eye(n) - A, B)
                      + D)[0, 0] for fk in f])


def _poles_match(fitted: NDArray[Any], true: NDArray[Any], rtol: float) -> None:
    """Every true continuous pole has a fitted one within ``rtol`` (relative to its size)."""
    assert len(fitted) == len(true), (fitted, true)
    for p in true:
        d = np.min(np.abs(fitted - p))
        assert d <= rtol * abs(p), (p, fitted)


SYS2 = _mode(0.8, 0.3, 1.0)


def test_second_order_system_gives_order_two_and_its_response() -> None:
    est, _ = _record("est", SYS2, 0.01, 2000, seed=1, noise=0.02)
    sel, _ = _record("sel", SYS2, 0.01, 1000, seed=2, noise=0.02)
    ref = LinearReference(max_order=4).fit([est], [sel])
    assert ref.order_ == 2, [(r.order, r.sel_fit_percent) for r in ref.orders_]
    assert [r.order for r in ref.orders_] == [1, 2, 3, 4]
    _poles_match(ref.model_.poles_s(), np.linalg.eigvals(SYS2[0]), rtol=0.002)
    f = np.geomspace(0.02, 5.0, 40)
    A, B = _zoh(SYS2[0], SYS2[1], 0.01)
    true = _response(A, B, SYS2[2], np.zeros((1, 1)), 0.01, f)
    fitted = _response(ref.A_, ref.B_, ref.C_, ref.D_, ref.dt_, f)
    assert np.max(np.abs(fitted - true) / np.abs(true)) < 0.01
    assert ref.D_.shape == (1, 1) and ref.D_[0, 0] == 0.0  # no feedthrough
    assert ref.sel_fit_percent_[0] > 95.0
    assert ref.n_estimated_ == 2 * (1 + 1) + 2


def test_two_mode_system_gives_order_four_and_both_modes() -> None:
    sys4 = _two_modes()
    est, _ = _record("est", sys4, 0.002, 6000, seed=3, noise=0.02)
    sel, _ = _record("sel", sys4, 0.002, 3000, seed=4, noise=0.02)
    ref = LinearReference(max_order=5).fit([est], [sel])
    assert ref.order_ == 4, [(r.order, r.sel_fit_percent) for r in ref.orders_]
    _poles_match(ref.model_.poles_s(), np.linalg.eigvals(sys4[0]), rtol=0.005)
    f = np.geomspace(0.05, 20.0, 60)
    A, B = _zoh(sys4[0], sys4[1], 0.002)
    true = _response(A, B, sys4[2], np.zeros((1, 1)), 0.002, f)
    fitted = _response(ref.A_, ref.B_, ref.C_, ref.D_, ref.dt_, f)
    assert np.max(np.abs(fitted - true) / np.abs(true)) < 0.01
    # the second-order models miss the 8 Hz mode: clearly worse on the selection data
    assert ref.orders_[1].sel_mean_fit < ref.orders_[3].sel_mean_fit - 5.0


def test_jacobian_equals_finite_differences() -> None:
    rng = np.random.default_rng(5)
    n, nu, ny = 3, 2, 2
    Ac = rng.standard_normal((n, n)) - 3.0 * np.eye(n)
    A, B = _zoh(Ac, rng.standard_normal((n, nu)), 0.05)
    model = StateSpace(A, B, rng.standard_normal((ny, n)), rng.standard_normal((ny, nu)), 0.05)
    segs = [make_segment("a", np.arange(150) * 0.05, rng.standard_normal((150, nu)),
                         rng.standard_normal((150, ny)), ["u1", "u2"], ["y1", "y2"]),
            make_segment("b", np.arange(80) * 0.125, rng.standard_normal((80, nu)),
                         rng.standard_normal((80, ny)), ["u1", "u2"], ["y1", "y2"])]
    w = np.array([0.7, 1.9])
    prob = oerefine._OEProblem(segs, w, n, nu, ny, True, 0.05)
    theta = prob.pack(model, [rng.standard_normal(n), rng.standard_normal(n)])
    J = prob.jacobian(theta)
    Jfd = np.empty_like(J)
    for i in range(theta.size):
        h = 1e-6 * max(1.0, abs(theta[i]))
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        Jfd[:, i] = (prob.residual(tp) - prob.residual(tm)) / (2 * h)
    assert J.shape == (150 * ny + 80 * ny, n * n + n * nu + ny * n + ny * nu + 2 * n)
    scale = np.max(np.abs(Jfd), axis=0)
    assert np.all(scale > 0)
    assert np.max(np.abs(J - Jfd) / scale) < 1e-5
    # the other-rate segment's rows depend on A and B through the rate conversion
    assert np.max(np.abs(J[300:, : n * n])) > 1e-3


def test_several_segments_fit_jointly_each_with_its_own_initial_state() -> None:
    x0s = [np.array([2.0, 0.0]), np.array([-1.5, 6.0]), np.array([0.5, -8.0])]
    recs = [_record(f"est{k}", SYS2, 0.01, 600, seed=10 + k, noise=0.005, x0=x0)
            for k, x0 in enumerate(x0s)]
    sel, _ = _record("sel", SYS2, 0.01, 800, seed=20, noise=0.005)
    ref = LinearReference(max_order=3).fit([s for s, _ in recs], [sel])
    assert ref.order_ == 2
    assert len(ref.x0_) == 3
    for k, (seg, clean) in enumerate(recs):
        err = ref.simulate(seg, ref.x0_[k]) - clean
        assert np.sqrt(np.mean(err ** 2)) < 0.01 * clean.std(), seg.name
        other = ref.simulate(seg, ref.x0_[(k + 1) % 3]) - clean
        assert np.sqrt(np.mean(other ** 2)) > 0.05 * clean.std(), seg.name
    # the model's responses to the true initial states match the data's transients
    assert np.allclose(np.abs(np.linalg.eigvals(ref.A_)),
                       np.abs(np.linalg.eigvals(_zoh(SYS2[0], SYS2[1], 0.01)[0])), rtol=0.002)


def test_init_window_initial_state_reproduces_a_noise_free_simulation() -> None:
    est, _ = _record("est", SYS2, 0.01, 1500, seed=30, noise=0.02)
    sel, _ = _record("sel", SYS2, 0.01, 800, seed=31, noise=0.02)
    ref = LinearReference(max_order=2).fit([est], [sel])
    rng = np.random.default_rng(32)
    u = rng.standard_normal((700, 1))
    x0 = rng.standard_normal(ref.order_) * 3.0
    probe = make_segment("probe", np.arange(700) * 0.01, u, np.zeros((700, 1)), ["u"], ["y"])
    y = ref.simulate(probe, x0)
    clean = dataclasses.replace(probe, y=y)
    got = ref.estimate_x0(clean, n_init=6)
    assert np.allclose(got, x0, rtol=1e-7, atol=1e-9 * np.abs(x0).max())
    assert np.max(np.abs(ref.predict(clean, n_init=6) - y)) < 1e-8 * y.std()
    # only the first n_init samples count: corrupting the rest changes nothing ...
    bent = dataclasses.replace(clean, y=y + np.where(np.arange(700) >= 6, 5.0, 0.0)[:, None])
    assert np.allclose(ref.estimate_x0(bent, n_init=6), x0, rtol=1e-7,
                       atol=1e-9 * np.abs(x0).max())
    # ... while the window rule (n_init 0) sees them
    assert not np.allclose(ref.estimate_x0(bent), x0, rtol=1e-3)


def test_selection_is_scored_like_predict_with_the_init_window() -> None:
    est, _ = _record("est", SYS2, 0.01, 1500, seed=40, noise=0.05)
    sel, _ = _record("sel", SYS2, 0.01, 800, seed=41, noise=0.05, x0=np.array([1.0, 3.0]))
    for window in (20, 0):
        ref = LinearReference(max_order=2, init_window=window).fit([est], [sel])
        want = figures([sel.y], [ref.predict(sel, window)], 1, ["y"])
        assert ref.sel_fit_percent_ == pytest.approx(want.fit_percent, abs=1e-9)
        assert ref.sel_rmse_ == pytest.approx(want.rmse, rel=1e-9)
    short = LinearReference(max_order=2, init_window=20).fit([est], [sel])
    assert short.sel_fit_percent_[0] != pytest.approx(ref.sel_fit_percent_[0], abs=1e-6)


def test_segment_at_another_rate_is_simulated_like_the_system_at_that_rate() -> None:
    est, _ = _record("est", SYS2, 0.01, 2000, seed=50, noise=0.01)
    sel, _ = _record("sel", SYS2, 0.01, 800, seed=51, noise=0.01)
    ref = LinearReference(max_order=2).fit([est], [sel])
    fast, clean = _record("fast", SYS2, 0.004, 2500, seed=52, hold=25)
    err = ref.simulate(fast, np.zeros(2)) - clean
    assert np.sqrt(np.mean(err ** 2)) < 0.003 * clean.std()
    # the same samples taken as if at the fit rate are a different system
    relabelled = make_segment("relabelled", np.arange(2500) * 0.01, fast.u, fast.y, ["u"], ["y"])
    wrong = ref.simulate(relabelled, np.zeros(2)) - clean
    assert np.sqrt(np.mean(wrong ** 2)) > 0.3 * clean.std()


def test_estimation_segments_at_two_rates_fit_one_system() -> None:
    a, _ = _record("slow", SYS2, 0.01, 1200, seed=60, noise=0.01)
    b, _ = _record("fast", SYS2, 0.004, 2000, seed=61, noise=0.01, hold=25)
    sel, _ = _record("sel", SYS2, 0.01, 800, seed=62, noise=0.01)
    ref = LinearReference(max_order=3).fit([a, b], [sel])
    assert ref.dt_ == pytest.approx(0.01)
    assert ref.order_ == 2
    _poles_match(ref.model_.poles_s(), np.linalg.eigvals(SYS2[0]), rtol=0.002)
    assert ref.orders_[1].est_fit_percent[0] > 98.0


def test_no_continuous_equivalent_raises_naming_segment_and_rates() -> None:
    rng = np.random.default_rng(70)
    u = rng.standard_normal((800, 1))
    y = np.zeros((800, 1))
    x = 0.0
    for k in range(800):  # a pole at z = -0.6: no real logarithm
        y[k] = x
        x = -0.6 * x + u[k, 0]
    seg = make_segment("alt", np.arange(800) * 0.01, u, y, ["u"], ["y"])
    ref = LinearReference(max_order=1).fit([seg], [seg])
    assert ref.A_[0, 0] == pytest.approx(-0.6, abs=1e-3)
    other = make_segment("at5ms", np.arange(800) * 0.005, u, y, ["u"], ["y"])
    with pytest.raises(FitError, match=r"at5ms.*0\.005.*0\.01"):
        ref.simulate(other, np.zeros(1))


def test_an_overflowing_simulation_gives_a_finite_penalty() -> None:
    seg = make_segment("s", np.arange(3000) * 0.01, np.ones(3000), np.zeros(3000), ["u"], ["y"])
    prob = oerefine._OEProblem([seg], np.ones(1), 1, 1, 1, False, 0.01)
    theta = prob.pack(StateSpace(np.array([[1.5]]), np.ones((1, 1)), np.ones((1, 1)),
                                 np.zeros((1, 1)), 0.01), [np.ones(1)])
    r = prob.residual(theta)
    assert np.all(np.isfinite(r)) and np.all(r == oerefine.PENALTY)
    assert np.all(np.isfinite(prob.jacobian(theta)))


def test_a_failed_subspace_start_falls_back_to_the_previous_order_plus_a_mode() -> None:
    # 30 samples are too few for the subspace step's block rows
    sys1 = (np.array([[-2.0]]), np.array([[2.0]]), np.array([[1.0]]))
    est, _ = _record("short", sys1, 0.05, 30, seed=80, noise=0.001, hold=3)
    sel, _ = _record("sel", sys1, 0.05, 200, seed=81, noise=0.001, hold=3)
    ref = LinearReference(max_order=2).fit([est], [sel])
    assert ref.orders_[0].start.startswith("stable mode (n4sid start failed")
    assert ref.orders_[1].start.startswith("previous order + stable mode (n4sid start failed")
    assert ref.order_ == 1
    assert ref.orders_[0].sel_fit_percent[0] > 98.0
    assert ref.model_.poles_s()[0].real == pytest.approx(-2.0, rel=0.02)


def _seg(name: str = "s", inputs: tuple[str, ...] = ("u",), outputs: tuple[str, ...] = ("y",),
         n: int = 400) -> Segment:
    rng = np.random.default_rng(90)
    return make_segment(name, np.arange(n) * 0.01, rng.standard_normal((n, len(inputs))),
                        rng.standard_normal((n, len(outputs))), inputs, outputs)


@pytest.mark.parametrize("kwargs, match", [
    ({"max_order": 0}, r"max_order.*>= 1.*got 0"),
    ({"max_order": 2.5}, r"max_order.*got 2\.5"),
    ({"init_window": -1}, r"init_window.*got -1"),
    ({"max_nfev": 0}, r"max_nfev.*got 0"),
])
def test_bad_settings_raise_naming_the_value(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(FitError, match=match):
        LinearReference(**kwargs)  # type: ignore[arg-type]


def test_bad_segments_raise_naming_the_value() -> None:
    ref = LinearReference(max_order=1)
    with pytest.raises(DataError, match=r"est: expected at least one segment"):
        ref.fit([], [_seg()])
    with pytest.raises(DataError, match=r"sel: expected at least one segment"):
        ref.fit([_seg()], [])
    with pytest.raises(DataError, match=r"odd: input_names: expected \['u'\], got \['v'\]"):
        ref.fit([_seg()], [_seg("odd", inputs=("v",))])
    with pytest.raises(DataError, match=r"two: input_names: expected \['u'\], got \['u', 'w'\]"):
        ref.fit([_seg(), _seg("two", inputs=("u", "w"))], [_seg()])
    with pytest.raises(DataError, match=r"ys: output_names: expected \['y'\], got \['z'\]"):
        ref.fit([_seg()], [_seg("ys", outputs=("z",))])
    bad = _seg("nan")
    bad.y[7, 0] = np.nan
    with pytest.raises(DataError, match=r"nan: y: non-finite value at sample 7"):
        ref.fit([_seg()], [bad])
    with pytest.raises(FitError, match="not fitted"):
        ref.predict(_seg())


def test_bad_calls_after_fit_raise_naming_the_value() -> None:
    est, _ = _record("est", SYS2, 0.01, 600, seed=95, noise=0.01)
    ref = LinearReference(max_order=2).fit([est], [est])
    with pytest.raises(FitError, match=r"est: x0: expected shape \(2,\), got \(3,\)"):
        ref.simulate(est, np.zeros(3))
    with pytest.raises(FitError, match=r"n_init: expected an integer >= 0, got -2"):
        ref.estimate_x0(est, n_init=-2)
    with pytest.raises(DataError, match=r"other: output_names: expected \['y'\], got \['q'\]"):
        ref.predict(_seg("other", outputs=("q",)))
