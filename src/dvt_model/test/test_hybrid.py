"""Hybrid model: lock-up, release, shifts, energy and speed constraints."""

import numpy as np
import pytest

from dvt_model.errors import SimulationError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel
from dvt_model.params import load_parameters

DT = 1e-3


@pytest.fixture(scope="module")
def model():
    return HybridModel.from_params(load_parameters("physical"))


def _run(model, n, i_motor, i_brake, omega0=(0.0, 0.0)):
    t = np.arange(n) * DT
    im = np.broadcast_to(np.asarray(i_motor, float), (n,)).copy()
    ib = np.broadcast_to(np.asarray(i_brake, float), (n, 3)).copy()
    return model.simulate(t, im, ib, omega0=omega0)


def test_neutral_free_decay_dissipates(model):
    r = _run(model, 2000, 0.0, (0.0, 0.0, 0.0), omega0=(150.0, 30.0))
    e = model.kinetic_energy(r.omega)
    assert np.all(np.diff(e) < 0.0)
    assert e[-1] < 0.05 * e[0]
    assert not r.locked.any()


def test_neutral_matches_linear_model(model):
    n = 500
    r = _run(model, n, 4.0, (0.0, 0.0, 0.0))
    rig = model.rigid
    lin = LinearModel(rig.A, rig.B(1) @ np.diag([rig.motor_constant, 1.0]))
    w = np.zeros(2)
    for _ in range(n - 1):
        w = lin.step(w, DT, np.array([4.0, 0.0, 0.0, 0.0]))
    assert np.allclose(r.omega[-1], w, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("gear", [1, 2, 3])
def test_band_locks_ring_and_speed_constraint_holds(model, gear):
    ib = np.zeros(3)
    ib[gear - 1] = 0.5
    r = _run(model, 3000, 5.0, ib)
    assert r.gear[-1] == gear
    rings = model.ring_speeds(r.omega)
    locked = r.locked[:, gear - 1]
    assert locked[-500:].all()
    assert np.max(np.abs(rings[locked, gear - 1])) < 1e-9
    ratio = r.omega[-1, 0] / r.omega[-1, 1]
    assert ratio == pytest.approx(float(model.rigid.kin.gear_ratio(gear)), rel=1e-9)


def test_lock_does_not_create_energy(model):
    # coast with the band on and no motor: energy may only fall, also across the lock event
    ib = (0.5, 0.0, 0.0)
    r = _run(model, 1500, 0.0, ib, omega0=(100.0, 20.0))
    e = model.kinetic_energy(r.omega)
    assert np.all(np.diff(e) <= 1e-12)
    assert r.locked[:, 0].any()


def test_holding_torque_within_capacity_and_release(model):
    n = 4000
    t = np.arange(n) * DT
    im = np.full(n, 5.0)
    ib = np.zeros((n, 3))
    ib[:2000, 0] = 0.5  # engage, then release at 2 s
    r = model.simulate(t, im, ib)
    assert r.locked[1500, 0]
    # after release the capacity decays and the ring slips again
    assert not r.locked[-1, 0]
    rings = model.ring_speeds(r.omega)
    assert abs(rings[-1, 0]) > 1.0


def test_state_holding_torque_bounded(model):
    state = model.initial_state()
    for _ in range(2000):
        state = model.step(state, DT, 5.0, (0.5, 0.0, 0.0))
        if state.locked[0]:
            cap = model.brake.static_factor * state.capacity[0]
            assert abs(state.holding[0]) <= cap * 1.05 + 1e-9
    assert state.locked[0]


def test_shift_one_to_two(model):
    n = 5000
    t = np.arange(n) * DT
    im = np.full(n, 6.0)
    ib = np.zeros((n, 3))
    ib[:2000, 0] = 0.5
    ib[2000:, 1] = 0.6
    r = model.simulate(t, im, ib)
    assert r.gear[1900] == 1
    assert r.gear[-1] == 2
    ratio = r.omega[-1, 0] / r.omega[-1, 1]
    assert ratio == pytest.approx(float(model.rigid.kin.gear_ratio(2)), rel=1e-9)


def test_weak_band_cannot_hold(model):
    # 0.05 A holds about 0.4 N m: far below what 10 A on the motor needs at ring 1
    r = _run(model, 3000, 10.0, (0.05, 0.0, 0.0))
    assert not r.locked[-1000:, 0].any()


def test_simulate_rejects_bad_input(model):
    t = np.arange(5) * DT
    with pytest.raises(SimulationError, match=r"i_motor: expected shape \(5,\), got \(4,\)"):
        model.simulate(t, np.zeros(4), np.zeros((5, 3)))
    with pytest.raises(SimulationError, match=r"i_brake: expected shape \(5, 3\)"):
        model.simulate(t, np.zeros(5), np.zeros((5, 2)))
    bad = np.zeros(5)
    bad[3] = np.nan
    with pytest.raises(SimulationError, match="i_motor: non-finite value at sample 3"):
        model.simulate(t, bad, np.zeros((5, 3)))
    with pytest.raises(SimulationError, match="t: not strictly increasing at sample 2"):
        model.simulate(np.array([0.0, 1.0, 1.0, 2.0, 3.0]), np.zeros(5), np.zeros((5, 3)))


def test_per_band_brake_gain_and_time_constant() -> None:
    """Band overrides (e.g. identified values): each band's capacity follows its own static
    torque per ampere and its own engagement time constant (exact first order)."""
    from dataclasses import replace

    from dvt_model.dynamics import rigid_model

    params = load_parameters("physical")
    g = params.brake.gain
    brake = replace(params.brake, band_gain=(2.0 * g, g, 0.5 * g),
                    band_time_constant=(0.01, 0.02, 0.05))
    np.testing.assert_allclose(brake.gains, [2.0 * g, g, 0.5 * g])
    model = HybridModel(rigid_model(params), brake)
    state = model.initial_state((0.0, 0.0))
    dt, i = 1e-3, 0.1
    for _ in range(20):  # 20 ms at rest, all bands energised
        state = model.step(state, dt, 0.0, (i, i, i))
    target = np.array([2.0, 1.0, 0.5]) * g * i
    expected = target * (1.0 - np.exp(-0.02 / np.array([0.01, 0.02, 0.05])))
    np.testing.assert_allclose(state.capacity, expected, rtol=1e-9)
    # without overrides the shared law applies to every band
    plain = replace(params.brake, band_gain=None, band_time_constant=None)
    np.testing.assert_allclose(plain.gains, [g, g, g])
    np.testing.assert_allclose(plain.time_constants, [plain.time_constant] * 3)
