"""Forms of the compliant-play (``backlash``, ``compliant: true``) and engagement dead-time
(``brake_engagement``, ``dead_time: true``) candidates: null = baseline exactly, shapes, checks;
and the engagement lag's held value (the model node's)."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.effects import (
    BrakeEngagement,
    CompliantOutputBacklash,
    EngagementDeadTime,
    SegmentView,
    make_effect,
)
from dvt_identify.errors import DescriptionError
from dvt_identify.simloop import spline_load, spline_load_py
from dvt_model.brake import capacity_step

STATES = ("sun_shaft", "carrier3")
INPUTS = ("motor", "brake1", "brake2", "brake3")


def _spline(**opts: object) -> CompliantOutputBacklash:
    e = make_effect("backlash", "carrier3", STATES, INPUTS, "N m", "rad/s",
                    options={"compliant": True, **opts})
    assert isinstance(e, CompliantOutputBacklash)
    return e


def test_spline_null_is_the_baseline_exactly() -> None:
    e = _spline()
    y = np.random.default_rng(0).normal(size=(500, 2))
    assert e.output_transform(e.null_vector(), y, 1e-3) is None
    assert e.params[0].name == "gap" and e.params[0].null == 0.0
    assert e.label() == "backlash@carrier3(compliant)"
    assert e.gain_names() == ("gap",)


def test_spline_rigid_contact_follows_the_member_in_steady_motion() -> None:
    e = _spline()
    dt = 1e-3
    t = np.arange(3000) * dt
    w = np.where(t < 1.0, 5.0 * t, 5.0)  # ramp, then constant speed
    y = np.column_stack([np.zeros_like(w), w])
    out = e.output_transform(np.array([0.02, 400.0, 1.0]), y, dt)  # no rebound
    assert out is not None
    np.testing.assert_array_equal(out[:, 0], y[:, 0])  # only the sensed output changes
    # after the transient the load runs at the member speed on average (rad/s): it stays
    # within the play (without drag it may keep bouncing between the flanks)
    assert np.mean(out[-1000:, 1]) == pytest.approx(5.0, abs=1e-2)
    # while accelerating, the load lags: it first crosses the gap, then is pushed
    assert out[100, 1] < w[100]


def test_spline_load_stands_still_in_the_gap_after_a_reversal() -> None:
    # member at constant speed, then reversed: the load coasts at its speed (no drag) while
    # the member crosses the play, then is hit and reverses too
    dt = 1e-4
    n = 40000
    w = np.where(np.arange(n) < 2000, 1.0, -1.0)
    out = spline_load(w, dt, 0.05, 400.0 ** 2, 2 * 1.0 * 400.0, 2)
    k = 2000 + 30  # 3 ms after the reversal, the member has turned back 3 mrad < gap
    assert abs(out[k] - 1.0) < 1e-6
    # then it stays within the play: on average it runs at the member speed
    assert np.mean(out[20000:]) == pytest.approx(-1.0, abs=5e-2)


def test_spline_compiled_kernel_matches_python() -> None:
    w = np.sin(np.linspace(0.0, 20.0, 400)) * 3.0
    a = spline_load(w, 1e-3, 0.01, 300.0 ** 2, 2 * 0.5 * 300.0, 4)
    b = spline_load_py(w, 1e-3, 0.01, 300.0 ** 2, 2 * 0.5 * 300.0, 4)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_spline_variants_stay_below_nyquist_and_probe_the_gap() -> None:
    e = _spline(wn_scan=[100.0, 500.0, 900.0], zeta_scan=[0.1], gap_scan=[0.01, 0.03])
    view = SegmentView(0.005, np.zeros((10, 4)), np.zeros((10, 2)))  # Nyquist 628 rad/s
    v = e.variants(view)
    assert [d["wn"] for _, d in v] == [100.0, 500.0, 100.0, 500.0]
    assert sorted({d["gap"] for _, d in v}) == [0.01, 0.03]
    assert e.derived({"gap": 0.03, "wn": 2 * np.pi * 50.0, "zeta": 0.1})["fn"] == \
        pytest.approx(50.0)


def test_spline_parameter_checks() -> None:
    with pytest.raises(DescriptionError, match="wn, zeta, probe_gap and secant_scale must be"):
        _spline(wn=-1.0)
    with pytest.raises(DescriptionError, match=r"> 0, got 400.0, 0.15, 0.01, 0.0"):
        _spline(secant_scale=0.0)
    with pytest.raises(DescriptionError, match="'ring9' is not an input"):
        make_effect("backlash", "ring9", STATES, INPUTS, options={"compliant": True})


def _dead(**opts: object) -> EngagementDeadTime:
    e = make_effect("brake_engagement", "brake2", STATES, INPUTS,
                    options={"dead_time": True, **opts})
    assert isinstance(e, EngagementDeadTime)
    return e


def test_dead_time_null_is_the_baseline_exactly() -> None:
    e = _dead()
    u = np.random.default_rng(1).normal(size=(300, 4))
    assert e.input_transform(e.null_vector(), u, 1e-3) is None
    assert e.params[0].name == "td" and e.params[0].upper == 0.2
    assert e.label() == "brake_engagement@brake2(dead_time)"


def test_dead_time_delays_rises_not_falls() -> None:
    e = _dead()
    dt = 1e-3
    col = np.zeros(400)
    col[100:300] = 0.5  # applied at 0.1 s, released at 0.3 s
    u = np.zeros((400, 4))
    u[:, 2] = col
    out = e.input_transform(np.array([0.04]), u, dt)
    assert out is not None
    np.testing.assert_array_equal(out[:, [0, 1, 3]], u[:, [0, 1, 3]])
    assert np.all(out[100:140, 2] == 0.0) and np.all(out[140:300, 2] == 0.5)
    assert np.all(out[300:, 2] == 0.0)  # released at once


def test_dead_time_parameter_checks() -> None:
    with pytest.raises(DescriptionError, match="max_dead_time must be > 0"):
        _dead(max_dead_time=0.0)
    with pytest.raises(DescriptionError, match="not an input"):
        make_effect("brake_engagement", "brake9", STATES, INPUTS, options={"dead_time": True})


def test_shared_dead_time_delays_every_listed_band() -> None:
    e = make_effect("brake_engagement", "brakes", STATES, INPUTS,
                    options={"dead_time": True, "inputs": ["brake1", "brake3"]})
    assert isinstance(e, EngagementDeadTime)
    assert e.indices == (1, 3) and e.index == -1
    assert e.label() == "brake_engagement@brakes(dead_time)"
    dt = 1e-3
    u = np.zeros((400, 4))
    u[100:300, 1:] = 0.5  # every band applied at 0.1 s, released at 0.3 s
    u[:, 0] = np.linspace(-1.0, 1.0, 400)  # the motor current is left alone
    assert e.input_transform(e.null_vector(), u, dt) is None
    out = e.input_transform(np.array([0.03]), u, dt)
    assert out is not None
    np.testing.assert_array_equal(out[:, [0, 2]], u[:, [0, 2]])  # unlisted inputs unchanged
    for j in (1, 3):
        assert np.all(out[100:130, j] == 0.0) and np.all(out[130:300, j] == 0.5)
        assert np.all(out[300:, j] == 0.0)


def test_shared_dead_time_checks_its_inputs() -> None:
    with pytest.raises(DescriptionError, match="inputs: expected a non-empty list"):
        make_effect("brake_engagement", "brakes", STATES, INPUTS,
                    options={"dead_time": True, "inputs": []})
    with pytest.raises(DescriptionError, match="duplicate names"):
        make_effect("brake_engagement", "brakes", STATES, INPUTS,
                    options={"dead_time": True, "inputs": ["brake1", "brake1"]})
    with pytest.raises(DescriptionError, match="'brake7' is not an input"):
        make_effect("brake_engagement", "brakes", STATES, INPUTS,
                    options={"dead_time": True, "inputs": ["brake1", "brake7"]})


@pytest.mark.parametrize("dt", [1e-3, 5e-3, 0.02])
def test_engagement_lag_holds_the_model_nodes_step_mean(dt: float) -> None:
    """The lagged brake input held over each step is the capacity's mean over that step, as
    the model node and the plant hold it (``capacity_step``), not its value at the step
    start (half a step late: the fit shortened the lag by that)."""
    e = make_effect("brake_engagement", "brake1", STATES, INPUTS)
    assert isinstance(e, BrakeEngagement)
    tau = 0.015
    rng = np.random.default_rng(3)
    u = np.zeros((200, 4))
    u[:, 1] = np.repeat(rng.uniform(-0.2, 1.0, 20), 10)  # held levels, negative ones too
    u[:, 3] = rng.normal(size=200)
    out = e.input_transform(np.array([tau]), u, dt)
    assert out is not None
    np.testing.assert_array_equal(out[:, [0, 2, 3]], u[:, [0, 2, 3]])
    cap = np.full(3, u[0, 1])
    means = []
    for k in range(200):
        cap, mean = capacity_step(cap, np.full(3, u[k, 1]), dt, tau)
        means.append(mean[0])
    np.testing.assert_allclose(out[:, 1], means, rtol=0, atol=1e-12)
    # the step-start value differs by about half a step's rise where the input steps
    start = u[0, 1]
    k = int(np.flatnonzero(np.diff(u[:, 1]))[0]) + 1
    jump = u[k, 1] - start
    assert abs(out[k, 1] - start) == pytest.approx(abs(jump) * (1 - tau / dt
                                                                * -np.expm1(-dt / tau)),
                                                   rel=1e-9)
