"""Forward sensitivities of the simulation (:mod:`dvt_identify.sensitivity`): the compiled loop
differentiated along every branch agrees with central differences of the simulation, on a
coupled model with a band (engagement lag and lock-up with its stick rule), Coulomb friction
with its stick rule, a smoothed (implicitly held) Stribeck law, windage, a constant force and
two output maps; and the ZOH derivative equals the block-exponential one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from dvt_identify.data import make_segment
from dvt_identify.effects import make_effect
from dvt_identify.sensitivity import simulate_sens, simulate_sens_states
from dvt_identify.simulation import OEModel, _zoh_derivatives_eig, zoh_derivatives
from dvt_identify.structures import MechanicalStructure

STATES = ["a", "b"]
INPUTS = ["motor", "brake"]


def _model() -> tuple[OEModel, np.ndarray]:
    st = MechanicalStructure(STATES, INPUTS, [["M11", "M12"], ["M12", "M22"]],
                             [["D11", "D12"], ["D12", "D22"]], [[1.0, 0.0], [0.0, 0.0]],
                             {"M11": {"initial": 0.02, "lower": 1e-6}, "M12": -0.004,
                              "M22": {"initial": 0.05, "lower": 1e-6}, "D11": 0.03,
                              "D12": -0.01, "D22": 0.08}, "N m", "rad/s")
    effs = [make_effect("brake_engagement", "brake", STATES, INPUTS),
            make_effect("brake_lockup", "ring", STATES, INPUTS, member=[-0.5, 1.5],
                        options={"input": "brake"}),
            make_effect("coulomb_friction", "a", STATES, INPUTS),
            make_effect("stribeck_friction", "b", STATES, INPUTS, options={"vs": 2.0,
                                                                          "eps": 0.05}),
            make_effect("windage", "a", STATES, INPUTS),
            make_effect("measurement_delay", "b", STATES, INPUTS, output_names=STATES),
            make_effect("sensor_gain", "a", STATES, INPUTS, output_names=STATES)]
    model = OEModel(st, effs)
    theta = np.array([0.02, -0.004, 0.05, 0.03, -0.01, 0.08,   # M, D
                      0.02, 3.0,                                # band lag [s], gain
                      0.4, 0.05,                                # Fc, offset
                      0.04, 2.0,                                # Fs, vs
                      2e-5,                                     # Cw
                      0.0047, 0.02])                            # delay [s], sensor gain
    return model, theta


def _segment(n: int = 3000, dt: float = 0.002) -> object:
    rng = np.random.default_rng(3)
    t = np.arange(n) * dt
    motor = np.repeat(rng.uniform(-1.5, 1.5, n // 150 + 1), 150)[:n]
    brake = ((t % 2.0) > 1.2).astype(float) * 1.0
    u = np.column_stack([motor, brake])
    return make_segment("s", t, u, np.zeros((n, 2)), INPUTS, STATES)


def _central(model: OEModel, theta: np.ndarray, seg: object, x0: np.ndarray, q: int
             ) -> np.ndarray:
    """Central difference of the outputs along parameter ``q`` (then the initial states)."""
    tp, tm, xp, xm = theta.copy(), theta.copy(), x0.copy(), x0.copy()
    if q < theta.size:
        h = 1e-6 * max(abs(theta[q]), 1e-3)
        tp[q] += h
        tm[q] -= h
    else:
        h = 1e-6
        xp[q - theta.size] += h
        xm[q - theta.size] -= h
    return (model.simulate(tp, seg, xp) - model.simulate(tm, seg, xm)) / (2 * h)


def test_the_sensitivities_are_the_derivatives_of_the_simulation() -> None:
    model, theta = _model()
    seg = _segment()
    x0 = np.array([3.0, 1.0])
    params = list(range(theta.size))
    x, y, J = simulate_sens(model, theta, seg, x0, params, True)
    assert np.array_equal(y, model.simulate(theta, seg, x0))  # the same simulation
    assert np.array_equal(x, model.simulate_states(theta, seg, x0)[0])
    assert J.shape == (seg.n, 2, theta.size + 2)
    checked = 0
    for q in range(theta.size + 2):
        fd = _central(model, theta, seg, x0, q)
        err = np.linalg.norm(J[:, :, q] - fd) / np.linalg.norm(fd)
        assert err < 1e-3, (model.names[q] if q < theta.size else f"x0[{q - theta.size}]", err)
        checked += 1
    assert checked == theta.size + 2
    # the stick rules were exercised: the Coulomb member at rest, the ring held (its speed
    # constant; the Coulomb member's hold, applied after it, moves it off zero)
    assert np.sum(x[:, 0] == 0.0) > 20
    assert np.sum(np.abs(np.diff(x @ np.array([-0.5, 1.5]))) < 1e-12) > 20


def test_the_state_tangents_carry_the_initial_state() -> None:
    """Splitting a simulation in two and chaining the tangents through the state at the cut
    gives the same derivative as the whole (what the drift check's windows rely on; without
    the engagement lag, whose own state restarts at a cut)."""
    full, theta_full = _model()
    model = OEModel(full.structure, full.effects[1:])
    theta = np.delete(theta_full, 6)
    seg = _segment(2000)
    x0 = np.array([2.0, -1.0])
    whole = simulate_sens(model, theta, seg, x0, [0, 6], True)[2]
    x1, tx1, _, J1 = simulate_sens_states(model, theta, seg.rows(0, 1001), x0, [0, 6], True)
    _, _, _, J2 = simulate_sens_states(model, theta, seg.rows(1000, 2000), x1[-1], [0, 6],
                                       True)
    T = tx1[-1]  # d x(1000) / d (M11, gain, x0)
    chained = J2[:, :, 2:] @ T
    chained[:, :, :2] += J2[:, :, :2]
    # the output maps (a delay) reach across the cut: compare away from it (the maps are
    # differenced along each direction: agreement to about 1e-6 of a column's scale)
    scale = np.linalg.norm(whole, axis=(0, 1))
    for part, ref in ((J1[:900], whole[:900]), (chained[100:], whole[1100:])):
        err = np.linalg.norm(part - ref, axis=(0, 1)) / scale
        assert np.all(err < 1e-5), err


@pytest.mark.parametrize("A", [np.array([[-2.0, 1.5], [-3.0, -4.0]]),
                               np.array([[-1.0, 0.3], [0.2, -40.0]]),
                               np.array([[0.0, 1.0], [0.0, -3.0]]),
                               np.array([[-1.0, 1.0], [0.0, -1.0]])])
def test_the_zoh_derivative_is_the_frechet_derivative(A: np.ndarray) -> None:
    rng = np.random.default_rng(1)
    nx, dt = A.shape[0], 0.005
    dA = rng.normal(size=(3, nx, nx))
    dAd, dGd = zoh_derivatives(A, dA, dt)
    X = np.zeros((4 * nx, 4 * nx))
    X[:nx, :nx] = A * dt
    X[:nx, nx:2 * nx] = np.eye(nx) * dt
    X[2 * nx:3 * nx, 2 * nx:3 * nx] = A * dt
    X[2 * nx:3 * nx, 3 * nx:] = np.eye(nx) * dt
    for k in range(3):
        X[:nx, 2 * nx:3 * nx] = dA[k] * dt
        L = expm(X)[:nx, 2 * nx:]
        assert dAd[k] == pytest.approx(L[:, :nx], rel=1e-9, abs=1e-12)
        assert dGd[k] == pytest.approx(L[:, nx:], rel=1e-9, abs=1e-14)
    # a defective A (a double eigenvalue) takes the block exponential
    if np.allclose(A, [[-1.0, 1.0], [0.0, -1.0]]):
        assert _zoh_derivatives_eig(A, dA, dt) is None


def test_a_chaotic_output_map_passes_the_tangents_and_takes_a_wide_secant() -> None:
    """A load rattling in a compliant play (``backlash``, ``compliant: true``) is chaotic: a
    change of 1e-9 in M11 moves the sensed speed by orders of magnitude more than 1e-9 times any
    mean effect, so its derivative is no regressor. The tangents pass the map as the identity
    (the structure's columns are those of the model without it) and its own parameters take the
    secant over :data:`~dvt_identify.effects.backlash.SECANT_SHARE` of their values."""
    from dvt_identify.effects.backlash import SECANT_SHARE

    full, theta_full = _model()
    rigid = OEModel(full.structure, [])
    play = make_effect("backlash", "a", STATES, INPUTS, output_names=STATES,
                       options={"compliant": True})
    assert play.chaotic_output
    model = OEModel(full.structure, [play])
    p_play = np.array([0.05, 300.0, 0.1])  # gap [rad], wn [rad/s], zeta
    theta = np.concatenate([theta_full[:6], p_play])
    seg = _segment()
    x0 = np.array([3.0, 1.0])
    # the premise: a step of 1e-9 in M11 moves the rattle by far more than 1e-9 x the rigid
    # path's own derivative (measured: 204 times its largest value)
    y = model.simulate(theta, seg, x0)
    tp = theta.copy()
    tp[0] += 1e-9
    moved = np.abs(model.simulate(tp, seg, x0) - y)[:, 0] / 1e-9
    J0 = simulate_sens(rigid, theta[:6], seg, x0, [0], False)[2][:, 0, 0]
    assert moved.max() > 100 * np.abs(J0).max(), (moved.max(), J0)
    # the structure's and the initial state's columns: the rigid model's
    _, yr, Jr = simulate_sens(rigid, theta[:6], seg, x0, range(6), True)
    _, yj, J = simulate_sens(model, theta, seg, x0, range(theta.size), True)
    np.testing.assert_allclose(J[:, :, [0, 1, 2, 3, 4, 5, 9, 10]], Jr, rtol=1e-12, atol=1e-12)
    # the play's own: the secant over SECANT_SHARE of each value (of the map on the same rigid
    # outputs: the plain simulation's differ from the tangent loop's by 1e-10, which the
    # rattle makes 1e-3)
    base = play.output_transform(p_play, yr, seg.dt)
    assert base is not None and np.array_equal(yj, base)
    for loc in range(3):
        h = SECANT_SHARE * p_play[loc]
        p2 = p_play.copy()
        p2[loc] += h
        np.testing.assert_allclose(J[:, :, 6 + loc],
                                   (play.output_transform(p2, yr, seg.dt) - base) / h,
                                   rtol=1e-12, atol=1e-12)


def test_the_lumped_one_state_loop_is_differenced_with_the_same_output_maps() -> None:
    """One state with dry friction runs the lumped scalar loop (no tangents): its states are
    differenced and the output maps carried as in the tangent loop; the Jacobian agrees with
    central differences of the simulation."""
    st = MechanicalStructure(["a"], ["motor"], [["M11"]], [["D11"]], [[1.0]],
                             {"M11": {"initial": 0.02, "lower": 1e-6}, "D11": 0.03},
                             "N m", "rad/s")
    effs = [make_effect("coulomb_friction", "a", ["a"], ["motor"]),
            make_effect("measurement_delay", "a", ["a"], ["motor"], output_names=["a"]),
            make_effect("sensor_gain", "a", ["a"], ["motor"], output_names=["a"])]
    model = OEModel(st, effs)
    theta = np.array([0.02, 0.03, 0.4, 0.05, 0.0047, 0.02])
    rng = np.random.default_rng(5)
    n, dt = 3000, 0.002
    u = np.repeat(rng.uniform(-1.5, 1.5, n // 150 + 1), 150)[:n, None]
    seg = make_segment("s", np.arange(n) * dt, u, np.zeros((n, 1)), ["motor"], ["a"])
    x0 = np.array([2.0])
    x, y, J = simulate_sens(model, theta, seg, x0, range(theta.size), True)
    assert np.array_equal(y, model.simulate(theta, seg, x0))
    assert np.sum(x[:, 0] == 0.0) > 20  # the stick rule was exercised
    for q in range(theta.size + 1):
        fd = _central(model, theta, seg, x0, q)
        err = np.linalg.norm(J[:, :, q] - fd) / np.linalg.norm(fd)
        assert err < 1e-3, (q, err)


def test_the_scorer_differences_the_model_with_its_chaotic_maps_passed() -> None:
    """The model the scorer differences (:meth:`OEModel.passing_chaotic`): the same parameters,
    names and free set, its outputs those of the model without the play; a model without a
    chaotic map is itself."""
    full, theta_full = _model()
    rigid = OEModel(full.structure, [])
    assert rigid.passing_chaotic() is rigid
    play = make_effect("backlash", "a", STATES, INPUTS, output_names=STATES,
                       options={"compliant": True})
    model = OEModel(full.structure, [play])
    passed = model.passing_chaotic()
    assert passed.names == model.names and np.array_equal(passed.free, model.free)
    theta = np.concatenate([theta_full[:6], [0.05, 300.0, 0.1]])
    seg = _segment()
    x0 = np.array([3.0, 1.0])
    assert np.array_equal(passed.simulate(theta, seg, x0), rigid.simulate(theta[:6], seg, x0))
    assert not np.array_equal(model.simulate(theta, seg, x0), passed.simulate(theta, seg, x0))


def test_the_fisher_rule_passes_a_chaotic_map_but_along_its_own_parameters() -> None:
    """The identifiability check's columns (:func:`dvt_identify.fisher._sensitivities`) of a
    model with a rattling play: the structure's and the initial states' are the rigid model's;
    the play's own differ from zero (it is differenced, not passed, along them)."""
    from dvt_identify.fisher import _sensitivities

    full, theta_full = _model()
    rigid = OEModel(full.structure, [])
    play = make_effect("backlash", "a", STATES, INPUTS, output_names=STATES,
                       options={"compliant": True})
    model = OEModel(full.structure, [play])
    assert model.chaotic_parameters() == [6, 7, 8]
    theta = np.concatenate([theta_full[:6], [0.05, 300.0, 0.1]])
    seg = _segment()
    w = np.ones(2)
    J = _sensitivities(model, theta, [seg], w)
    Jr = _sensitivities(rigid, theta[:6], [seg], w)
    np.testing.assert_allclose(J[:, [0, 1, 2, 3, 4, 5, 9, 10]], Jr, rtol=1e-12, atol=1e-12)
    assert np.all(np.linalg.norm(J[:, 6:9], axis=0) > 0)


def test_the_landing_spread_of_a_chaotic_fit_joins_its_std() -> None:
    """:meth:`OEFit.add_landing_spread`: nothing for a model without a chaotic map; with a
    rattling play, refits with its secant halved and doubled, and each free parameter's variance
    grows by the landings' sample variance exactly."""
    from dvt_identify.fit import OEFit

    full, theta_full = _model()
    seg = _segment(1500)
    x0 = np.array([3.0, 1.0])
    rigid = OEModel(full.structure, [])
    y = rigid.simulate(theta_full[:6], seg, x0)
    data = make_segment("s", seg.t, seg.u, y + np.random.default_rng(2).normal(0, 0.01, y.shape),
                        INPUTS, STATES)
    fit = OEFit(rigid, starts=1, more_starts=0).fit([data])
    std = fit.std_.copy()
    assert fit.add_landing_spread([data]) is fit
    assert not np.any(fit.landing_spread_) and np.array_equal(fit.std_, std)

    play = make_effect("backlash", "a", STATES, INPUTS, output_names=STATES,
                       options={"compliant": True, "wn": 300.0, "zeta": 0.1})
    model = OEModel(full.structure, [play])
    theta = np.concatenate([theta_full[:6], [0.05, 300.0, 0.1]])
    y = model.simulate(theta, seg, x0)
    data = make_segment("s", seg.t, seg.u, y + np.random.default_rng(2).normal(0, 0.01, y.shape),
                        INPUTS, STATES)
    start = theta.copy()
    start[6] = 0.04
    fit = OEFit(model, starts=1, theta0=start, more_starts=0).fit([data])
    std = fit.std_.copy()
    fit.add_landing_spread([data])
    spread = fit.landing_spread_
    assert spread.shape == theta.shape and spread[6] > 0
    np.testing.assert_allclose(fit.std_ ** 2, std ** 2 + spread ** 2, rtol=1e-12)
