"""The hybrid model's per-sample fast path gives the straightforward algorithm's results bit
for bit.

:class:`_Reference` is :class:`~dvt_model.hybrid.HybridModel` with the plain step of before the
fast path (numpy three-vectors, :func:`~dvt_model.brake.band_torques` and
:func:`~dvt_model.brake.capacity_step` with the brake's array properties on every step, the
discretisation cache keyed by ``round(dt, 12)`` only, every effect term evaluated anew, the
end-of-step force evaluated also with nothing locked); it shares only the lock-set algebra
(bases, holding maps, projections, ``expm``). Long runs through neutral, gears 1-3, lock-ups,
slip crossings, shifts, releases and a weak band, with float-second stamps (a few distinct raw
step lengths), speed terms, angle terms, an input term and a joint load, must agree in every
bit of every state.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from numpy.typing import ArrayLike

from dvt_model.brake import BandLaw, band_torques, capacity_step
from dvt_model.dynamics import rigid_model
from dvt_model.errors import SimulationError
from dvt_model.hybrid import (
    CROSSING_GRID,
    HybridModel,
    HybridState,
    LockSet,
    _Mode,
    _with,
    crossing_fraction,
)
from dvt_model.load import load_joint_load
from dvt_model.params import load_parameters
from dvt_model.terms import parse_terms

Array = np.ndarray
_ENGAGED = 1e-9
_ZERO_SPEED = 1e-9


class _Reference(HybridModel):
    """The straightforward step (the formulas before the per-sample fast path)."""

    def _mode(self, locked: LockSet, dt: float) -> _Mode:
        key = (locked, round(dt, 12))
        mode = self._modes.get(key)
        if mode is None:
            mode = self._discretise(locked, dt)
            if len(self._modes) < 256:
                self._modes[key] = mode
        return mode

    def _ref_forces(self, omega: Array, t: float, u: Array, cap: Array, signs: Array,
                    locked: LockSet, theta: Array, dt: float = 0.0) -> Array:
        f = self.rigid.Q_motor * (self.rigid.motor_constant * u[0])
        for k in range(3):
            if not locked[k] and signs[k] != 0.0 and cap[k] > _ENGAGED:
                f = f - self._ring[:, k] * (cap[k] * signs[k])
        if self.extra_force is not None:
            f = f + np.asarray(self.extra_force(omega, t), dtype=float)
        if self.load is not None:
            f = f + self.load.generalised_force(theta, omega)
        if self.angle_force is not None:
            f = f + np.asarray(self.angle_force(theta, omega, t), dtype=float)
        if self.angle_input_force is not None:
            f = f + np.asarray(self.angle_input_force(theta, omega, t, u, dt), dtype=float)
        return np.asarray(f)

    def step(self, state: HybridState, dt: float, i_motor: float,
             i_brake: ArrayLike) -> HybridState:
        ib = np.asarray(i_brake, dtype=float).reshape(3)
        u = np.empty(4)
        u[0] = i_motor
        u[1:] = ib
        target = band_torques(self.brake, ib)
        omega, theta, locked = state.omega, state.theta, state.locked
        rings = omega @ self._ring
        if self.engagement is None:
            cap_end, cap_mean = capacity_step(state.capacity, target, dt,
                                              self.brake.time_constants)
        else:
            cap_end, cap_mean = self.engagement(state.capacity, target, dt, rings)
        hold_cap = self.brake.static_factor * cap_mean
        signs = np.sign(rings)
        for _ in range(3):
            if not any(locked):
                break
            f = self._ref_forces(omega, state.t, u, cap_mean, signs, locked, theta)
            lam = self.holding_torques(omega, f, locked)
            excess = [abs(lam[k]) / max(hold_cap[k], _ENGAGED) if locked[k] else 0.0
                      for k in range(3)]
            k = int(np.argmax(excess))
            if excess[k] <= 1.0:
                break
            locked = _with(locked, k, False)
            signs[k] = -np.sign(lam[k])
        for k in range(3):
            if (not locked[k] and cap_mean[k] > _ENGAGED and abs(rings[k]) < _ZERO_SPEED
                    and self._ref_can_lock(omega, state.t, u, cap_mean, signs, locked, k,
                                           theta)):
                locked = _with(locked, k, True)
                omega = self._project(omega, locked)
        omega, locked, signs, dtheta = self._ref_advance(omega, state.t, dt, u, cap_mean,
                                                         signs, locked, theta, 0)
        theta = theta + dtheta
        f = self._ref_forces(omega, state.t + dt, u, cap_end, signs, locked, theta)
        holding = self.holding_torques(omega, f, locked)
        return HybridState(t=state.t + dt, omega=omega, capacity=cap_end, locked=locked,
                           holding=holding, theta=theta)

    def _ref_can_lock(self, omega: Array, t: float, u: Array, cap: Array, signs: Array,
                      locked: LockSet, k: int, theta: Array) -> bool:
        trial = _with(locked, k, True)
        w = self._project(omega, trial)
        f = self._ref_forces(w, t, u, cap, signs, trial, theta)
        lam = self.holding_torques(w, f, trial)
        return bool(abs(lam[k]) <= self.brake.static_factor * cap[k])

    def _ref_advance(self, omega: Array, t: float, dt: float, u: Array, cap: Array,
                     signs: Array, locked: LockSet, theta: Array, depth: int
                     ) -> tuple[Array, LockSet, Array, Array]:
        mode = self._mode(locked, dt) if depth == 0 else self._discretise(locked, dt)
        f = self._ref_forces(omega, t, u, cap, signs, locked, theta, dt)
        if mode.N.shape[1] == 0:
            return np.zeros(2), locked, signs, np.zeros(2)
        z = mode.N.T @ omega
        omega_end = mode.N @ (mode.Phi @ z + mode.Gamma @ f)
        dtheta = mode.N @ (mode.Psi @ z + mode.Lam @ f)
        if depth >= 4:
            return omega_end, locked, signs, dtheta
        r0 = omega @ self._ring
        r1 = omega_end @ self._ring
        first, frac = -1, 2.0
        for k in range(3):
            if locked[k] or cap[k] <= _ENGAGED or signs[k] == 0.0:
                continue
            if r0[k] * signs[k] > 0.0 and r1[k] * signs[k] <= 0.0:
                th = r0[k] / (r0[k] - r1[k])
                if th < frac:
                    first, frac = k, th
        if first < 0:
            return omega_end, locked, signs, dtheta
        t1 = max(frac * dt, 1e-9)
        w_mid, locked, signs, d1 = self._ref_advance(omega, t, t1, u, cap, signs, locked,
                                                     theta, depth + 1)
        th_mid = theta + d1
        k = first
        if self._ref_can_lock(w_mid, t + t1, u, cap, signs, locked, k, th_mid):
            locked = _with(locked, k, True)
            w_mid = self._project(w_mid, locked)
        else:
            signs = signs.copy()
            signs[k] = -signs[k]
        rest = dt - t1
        if rest <= 1e-12:
            return w_mid, locked, signs, d1
        w_end, locked, signs, d2 = self._ref_advance(w_mid, t + t1, rest, u, cap, signs,
                                                     locked, th_mid, depth + 1)
        return w_end, locked, signs, d1 + d2


_EFFECTS = [
    {"kind": "coulomb", "member": [1, 0], "Fc": 0.02},
    {"kind": "viscous", "member": [0, 1], "b": 1e-3},
    {"kind": "angle_periodic", "member": [1, 0], "a": 0.02, "b": 0.01, "order": 16},
    {"kind": "gravity", "member": [0, 1], "a": 0.3, "b": -0.1, "reduction": 20.0},
    {"kind": "library", "member": [0, 1], "k": 0.01, "speed": "sign", "trig": "cos",
     "order": 1, "input": "drive_motor"},
]


def _slow_ramp_engagement(capacity: Array, target: Array, dt: float, rings: Array
                          ) -> tuple[Array, Array]:
    """A pure engagement law (the ``engagement=`` branch): first order, slower while slipping."""
    tau = np.where(np.abs(rings) > 1.0, 0.03, 0.01)
    return capacity_step(capacity, target, dt, tau)


def _models(variant: str) -> tuple[HybridModel, HybridModel]:
    params = load_parameters("physical")
    brake = params.brake
    kwargs: dict[str, Any] = {}
    if variant in ("terms", "engagement"):
        terms = parse_terms(_EFFECTS)
        kwargs = {"extra_force": terms.extra_force, "load": load_joint_load("arm"),
                  "angle_input_force": terms.angle_force,
                  "angle_force": lambda th, w, t: np.array([0.0, 0.05 * math.sin(th[1])])}
        g = brake.gain
        brake = dataclasses.replace(brake, static_factor=1.2, band_gain=(g, 1.1 * g, 0.9 * g),
                                    band_time_constant=(0.01, 0.015, 0.02))
    if variant == "engagement":
        kwargs["engagement"] = _slow_ramp_engagement
    rigid = rigid_model(params)
    return HybridModel(rigid, brake, **kwargs), _Reference(rigid, brake, **kwargs)


def _inputs(n: int) -> tuple[Array, Array, Array]:
    """Float-second stamps near 1.7e9 s (raw step lengths of a few values around 1 ms), a
    motor current with sign changes and a brake schedule: neutral, gear 1, shift to 2, 3,
    a weak band that slips, gear 1 again, all off, a tie-up."""
    stamps = 1.7e9 + np.arange(n) * 1e-3
    t = np.arange(n) * 1e-3
    im = 3.0 * np.sin(2 * np.pi * 0.9 * t) + 1.5 + 0.5 * np.sin(2 * np.pi * 13.0 * t)
    ib = np.zeros((n, 3))
    s = n // 8
    ib[s:2 * s, 0] = 0.4
    ib[2 * s:3 * s, 1] = 0.5
    ib[3 * s:4 * s, 2] = 0.5
    ib[4 * s:5 * s, 0] = 0.04
    ib[5 * s:6 * s, 0] = 0.6
    ib[6 * s:7 * s, :] = -0.1  # released (negative currents)
    ib[7 * s:, 0] = 0.4
    ib[7 * s + s // 2:, 1] = 0.4
    return stamps, im, ib


@pytest.mark.parametrize("variant", ["plain", "terms", "engagement"])
def test_long_run_is_bit_identical_to_the_straightforward_step(variant: str) -> None:
    fast, ref = _models(variant)
    stamps, im, ib = _inputs(8000)
    a = fast.initial_state((0.0, 0.0), theta=(0.3, 1.2))  # at rest: zero speeds at first
    b = ref.initial_state((0.0, 0.0), theta=(0.3, 1.2))
    prev = a.locked
    gears: set[int] = set()
    locks = releases = 0
    for k in range(len(stamps) - 1):
        dt = float(stamps[k + 1] - stamps[k])
        a = fast.step(a, dt, float(im[k]), ib[k])
        b = ref.step(b, dt, float(im[k]), ib[k])
        assert a.locked == b.locked, k
        assert a.t == b.t
        for name in ("omega", "theta", "capacity", "holding"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and x.shape == y.shape
            assert x.tobytes() == y.tobytes(), (k, name, x, y)  # every bit, zero signs too
        gears.add(a.gear)
        locks += sum(x and not y for x, y in zip(a.locked, prev, strict=True))
        releases += sum(y and not x for x, y in zip(a.locked, prev, strict=True))
        prev = a.locked
    assert {0, 1, 2, 3} <= gears
    assert locks >= 5 and releases >= 4, (locks, releases)
    assert len({float(stamps[k + 1] - stamps[k]) for k in range(len(stamps) - 1)}) > 1


def test_the_band_law_in_floats_is_the_array_law_bit_for_bit() -> None:
    params = load_parameters("physical")
    g = params.brake.gain
    brake = dataclasses.replace(params.brake, band_gain=(g, 2.0 * g, 0.5 * g),
                                band_time_constant=(0.01, 0.02, 0.05))
    law = BandLaw(brake)
    rng = np.random.default_rng(3)
    for current in ([-0.0, 0.0, -1.0], [np.nan, 0.2, 1e-300], *rng.normal(0.2, 0.3, (50, 3))):
        ib = np.asarray(current, dtype=float)
        want = band_torques(brake, ib)
        got = np.array(law.targets(ib.tolist()))
        assert got.tobytes() == want.tobytes()
    cap = np.array([0.3, 0.0, 1.7])
    for dt in (1e-3, 0.0009999275207519531, 1e-3, 2.5e-4):
        target = band_torques(brake, rng.uniform(0.0, 0.5, 3))
        want_end, want_mean = capacity_step(cap, target, dt, brake.time_constants)
        end, mean = law.step(cap.tolist(), target.tolist(), dt)
        assert np.array(end).tobytes() == want_end.tobytes()
        assert np.array(mean).tobytes() == want_mean.tobytes()
        cap = want_end


def test_nothing_is_evaluated_for_the_holding_torque_in_neutral() -> None:
    """With nothing locked the end-of-step force is skipped (no holding torque to compute)."""
    calls: list[float] = []

    def spy(theta: Array, omega: Array, t: float) -> Array:
        calls.append(t)
        return np.zeros(2)
    params = load_parameters("physical")
    model = HybridModel.from_params(params, angle_force=spy)
    state = model.step(model.initial_state((10.0, 2.0)), 1e-3, 1.0, [0.0, 0.0, 0.0])
    assert calls == [0.0]  # the force held over the step only
    np.testing.assert_array_equal(state.holding, np.zeros(3))


# ------------------------------------------------- the model node's crossing grid
class _Counting(HybridModel):
    """Counts the matrix exponentials (discretisations) it computes."""

    exps = 0

    def _discretise(self, locked: LockSet, dt: float) -> _Mode:
        self.exps += 1
        return super()._discretise(locked, dt)


def _neutral_with_quantised_brakes(n: int) -> tuple[Array, Array, Array]:
    """Neutral with the brake currents at +-1 count (0.0078 A, as measured when off): the bands
    hold a little and every ring speed reversal is a zero crossing within a step."""
    stamps = 1.7e9 + np.arange(n) * 1e-3
    t = np.arange(n) * 1e-3
    im = 2.5 * np.sign(np.sin(2 * np.pi * 1.7 * t)) + 0.3 * np.sin(2 * np.pi * 11.0 * t)
    rng = np.random.default_rng(5)
    ib = rng.choice([-0.0078125, 0.0, 0.0078125], size=(n, 3))
    return stamps, im, ib


@pytest.mark.parametrize("inputs", ["gears", "neutral"])
def test_crossing_grid_follows_the_exact_split_and_caches_its_splits(inputs: str) -> None:
    params = load_parameters("physical")
    rigid = rigid_model(params)
    exact = _Counting(rigid, params.brake)
    grid = _Counting(rigid, params.brake, crossing_grid=CROSSING_GRID)
    stamps, im, ib = (_inputs(8000) if inputs == "gears" else
                      _neutral_with_quantised_brakes(8000))
    a = exact.initial_state((0.0, 0.0))
    b = grid.initial_state((0.0, 0.0))
    worst = 0.0
    crossings = 0
    for k in range(len(stamps) - 1):
        dt = float(stamps[k + 1] - stamps[k])
        before = exact.exps
        a = exact.step(a, dt, float(im[k]), ib[k])
        crossings += exact.exps > before  # an exact split computes its own exponentials
        b = grid.step(b, dt, float(im[k]), ib[k])
        assert a.locked == b.locked, k
        worst = max(worst, float(np.max(np.abs(a.omega - b.omega))))
    assert crossings >= 20, crossings  # the run does cross zero within steps
    # the same model to a fifth of a sensor count (the sun's: 1.53 rad/s at 1 kHz); a lock
    # placed up to 7.8 us off moves the speeds by up to 0.22 rad/s in the gears run
    assert worst < 0.3, worst
    # exact: two exponentials per split; the grid: a bounded set of split lengths, cached
    # (the more crossings, the more of them are found in the cache: neutral has hundreds)
    assert exact.exps > 2 * crossings - 1
    assert grid.exps < (exact.exps / 4 if inputs == "neutral" else exact.exps), \
        (grid.exps, exact.exps)
    print(f"\n{inputs}: {crossings} steps with a crossing, exponentials exact {exact.exps}, "
          f"grid {grid.exps}; largest speed difference {worst:.2g} rad/s")


def test_crossing_fraction_and_its_setting() -> None:
    assert crossing_fraction(0.0) == 1 / CROSSING_GRID  # at least one grid step
    assert crossing_fraction(1.0) == 1.0 and crossing_fraction(0.999) == 1.0  # the end
    assert crossing_fraction(0.5) == 0.5 and crossing_fraction(0.26, 4) == 0.25
    params = load_parameters("physical")
    with pytest.raises(SimulationError, match="crossing_grid: expected an integer >= 0"):
        HybridModel(rigid_model(params), params.brake, crossing_grid=-1)
    from dvt_model.config import build_predictor

    predictor, _ = build_predictor({"params": "physical"})
    assert isinstance(predictor.model, HybridModel)
    assert predictor.model.crossing_grid == CROSSING_GRID  # the model node's choice
