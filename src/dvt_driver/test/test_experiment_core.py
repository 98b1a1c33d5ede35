"""Unit tests of the experiment schedules (pure core; the offline check drives the real
plant core and the driver's safety supervisor, no ROS, no wall clock)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvt_driver.errors import ExperimentError
from dvt_driver.hardware import RPM
from dvt_driver.link.safety import Limits as DriverLimits
from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import run_offline
from dvt_driver.run import experiment_core as ec
from dvt_driver.run.experiment_core import (
    BrakeCurrents,
    Experiment,
    Gear,
    Limits,
    MotorCurrent,
    MotorOff,
    Phase,
    Step,
    SunSpeed,
)
from dvt_model.params import load_parameters


@pytest.mark.parametrize("name", ec.available())
def test_every_experiment_is_valid_and_well_formed(name: str) -> None:
    e = ec.build(name)
    assert e.name == name
    assert e.validate() is e
    times = [s.t for s in e.steps]
    assert times == sorted(times)
    assert times[0] >= 0.0 and times[-1] <= e.duration
    # phases tile [0, duration) without gaps or overlaps
    assert e.phases[0].start == 0.0
    for a, b in zip(e.phases, e.phases[1:], strict=False):
        assert a.end == pytest.approx(b.start)
    assert e.phases[-1].end == pytest.approx(e.duration)
    # ends with the motor off, and the last motor command before it brings the sun to rest
    assert isinstance(e.steps[-1].command, MotorOff)
    motor = [s.command for s in e.steps if isinstance(s.command, MotorCurrent | SunSpeed)]
    assert motor[-1] == SunSpeed(0.0)
    # starts with the bands released (neutral or explicit zero currents)
    first_brake = next(s.command for s in e.steps if isinstance(s.command, Gear | BrakeCurrents))
    assert first_brake in (Gear(0), BrakeCurrents((0.0, 0.0, 0.0)))
    # the summary is plain data
    m = e.to_mapping()
    assert m["name"] == name and m["duration_s"] == pytest.approx(e.duration)
    assert sum(m["steps"].values()) == len(e.steps)


@pytest.mark.parametrize("name", ec.available())
def test_experiments_are_deterministic_per_seed(name: str) -> None:
    assert ec.build(name, seed=3).steps == ec.build(name, seed=3).steps


@pytest.mark.parametrize("name", ["prbs", "multisine", "gears_excitation", "ident", "smoke"])
def test_random_signals_change_with_the_seed(name: str) -> None:
    assert ec.build(name, seed=1).steps != ec.build(name, seed=2).steps


def test_unknown_experiment_and_bad_seed_and_settings() -> None:
    with pytest.raises(ExperimentError, match=r"unknown experiment 'nope' \(expected one of"):
        ec.build("nope")
    with pytest.raises(ExperimentError, match="seed: expected an integer >= 0, got -1"):
        ec.build("prbs", seed=-1)
    with pytest.raises(ExperimentError, match="experiment 'prbs': bad settings"):
        ec.build("prbs", colour="red")


def test_limits_are_enforced_with_exact_messages() -> None:
    with pytest.raises(ExperimentError,
                       match=r"experiment 'prbs': step 1 at t=0.0 s: motor current (-)?40 A "
                             r"exceeds the limit 32.1543 A"):
        ec.build("prbs", amplitude=40.0)
    with pytest.raises(ExperimentError, match=r"sun speed 261.799 rad/s \(2500.0 rpm\) exceeds "
                                              r"the limit 251.327 rad/s \(2400 rpm\)"):
        ec.build("speed_steps", levels_rpm=(1000.0, 2500.0))
    with pytest.raises(ExperimentError, match=r"brake1 current 7 A outside \[0, 6\] A"):
        ec.build("thesis", brake_current=7.0)
    bad = Experiment("x", "", (Step(0.0, Gear(4)),), (Phase(0.0, 1.0, "p"),), 1.0)
    with pytest.raises(ExperimentError, match=r"step 0 at t=0.0 s: gear: expected 0 \(neutral\), "
                                              r"1, 2 or 3, got 4"):
        bad.validate()
    nan = Experiment("x", "", (Step(0.0, MotorCurrent(math.nan)),), (), 1.0)
    with pytest.raises(ExperimentError, match="motor current: expected a finite number, got nan"):
        nan.validate()
    late = Experiment("x", "", (Step(2.0, MotorOff()),), (), 1.0)
    with pytest.raises(ExperimentError, match="time must be within"):
        late.validate()
    # the experiment limits are the driver's hardware limits
    hw = DriverLimits()
    assert Limits().motor_current == pytest.approx(hw.max_motor_current)
    assert Limits().sun_speed == pytest.approx(hw.max_sun_speed)
    assert Limits().brake_current == pytest.approx(hw.max_brake_current)


def test_prbs_signal_is_the_shared_generator_with_the_experiment_error() -> None:
    from dvt_model.excitation import prbs

    np.testing.assert_array_equal(ec.prbs_signal(127, 7, seed=5, stream=3), prbs(127, 7, 5, 3))
    with pytest.raises(ExperimentError, match="PRBS order: expected 3..24, got 2"):
        ec.prbs_signal(10, 2, seed=0)


def test_multisine_is_band_limited_and_normalised() -> None:
    period, fs = 5.0, 200.0
    t = np.arange(int(2 * period * fs)) / fs
    x = ec.multisine_signal(t, period, 0.2, 20.0, seed=1)
    assert np.max(np.abs(x)) <= 1.0 + 1e-12
    assert np.max(np.abs(x)) > 0.95
    spec = np.abs(np.fft.rfft(x[: int(period * fs)]))
    f = np.fft.rfftfreq(int(period * fs), 1 / fs)
    inband = (f >= 0.2 - 1e-9) & (f <= 20.0 + 1e-9)
    assert spec[~inband].max() < 1e-6 * spec.max()
    assert np.count_nonzero(spec[inband] > 1e-3 * spec.max()) >= 20
    with pytest.raises(ExperimentError, match="no harmonic"):
        ec.multisine_signal(t, 1.0, 0.2, 0.5, seed=0)


def test_thesis_protocol() -> None:
    e = ec.build("thesis")
    assert e.sample_period_us == 16000  # 62.5 Hz, the thesis's serial limit
    held = [ph for ph in e.phases if ph.label.endswith("-brake1")]
    assert [ph.label for ph in held] == ["1500rpm-brake1", "1600rpm-brake1", "2000rpm-brake1",
                                         "2400rpm-brake1"]
    t = np.arange(0.0, e.duration, 0.001)
    s = e.sample(t)
    for ph, rpm in zip(held, (1500, 1600, 2000, 2400), strict=True):
        m = (t >= ph.start) & (t < ph.end)
        assert np.all(s["mode"][m] == 2)
        np.testing.assert_allclose(s["setpoint"][m], rpm * RPM)
        np.testing.assert_allclose(s["brake"][m], [[0.125, 0.0, 0.0]] * int(m.sum()))
    # the sun is held at the speed before the band is applied, band released otherwise
    settle = [ph for ph in e.phases if ph.label.endswith("-settle")]
    for ph in settle:
        m = (t >= ph.end - 1.0) & (t < ph.end)
        assert np.all(s["brake"][m] == 0.0)
        assert np.ptp(s["setpoint"][m]) == 0.0


def test_ident_covers_neutral_and_every_gear_without_band_changes_during_excitation() -> None:
    e = ec.build("ident")
    labels = [p.label for p in e.phases]
    for needed in ("neutral-prbs", "neutral-multisine", "neutral-speed-steps", "gear1-prbs",
                   "gear2-prbs", "gear3-prbs"):
        assert needed in labels
    assert 25.0 <= e.duration <= 40.0  # committed bags stay small
    t = np.arange(0.0, e.duration, 0.001)
    s = e.sample(t)
    for ph in e.phases:
        m = (t >= ph.start) & (t < ph.end)
        if ph.label.startswith("neutral"):
            assert np.all(s["gear"][m] == 0)
        if ph.label.endswith("-prbs"):
            g = 0 if ph.label.startswith("neutral") else int(ph.label[4])
            assert np.all(s["gear"][m] == g)  # no shift inside the window
            cur = s["setpoint"][m]
            assert np.all(s["mode"][m] == 1)
            assert abs(cur.mean()) < 0.2 * np.abs(cur).max()  # zero mean: reversals
            assert np.count_nonzero(np.diff(np.sign(cur))) >= 20
    gear_steps = [st for st in e.steps if isinstance(st.command, Gear)]
    assert {st.command.gear for st in gear_steps if isinstance(st.command, Gear)} == {0, 1, 2, 3}
    assert not any(isinstance(st.command, BrakeCurrents) for st in e.steps)
    steps_rpm = [st.command.rad_s / RPM for st in e.steps
                 if isinstance(st.command, SunSpeed) and st.command.rad_s != 0.0]
    assert max(steps_rpm) == pytest.approx(2000.0) and min(steps_rpm) < 0


def test_sample_holds_commands() -> None:
    e = Experiment("x", "", (Step(0.0, MotorCurrent(1.0)), Step(0.5, BrakeCurrents((0.1, 0, 0))),
                             Step(1.0, SunSpeed(5.0)), Step(1.5, Gear(2)), Step(2.0, MotorOff())),
                   (Phase(0.0, 2.0, "a"),), 2.0)
    s = e.sample([0.0, 0.49, 0.5, 1.2, 1.6, 2.0])
    np.testing.assert_array_equal(s["mode"], [1, 1, 1, 2, 2, 0])
    np.testing.assert_array_equal(s["setpoint"], [1.0, 1.0, 1.0, 5.0, 5.0, 0.0])
    np.testing.assert_array_equal(s["brake"][:, 0], [0, 0, 0.1, 0.1, 0.1, 0.1])
    np.testing.assert_array_equal(s["gear"], [-1, -1, -1, -1, 2, 2])
    np.testing.assert_array_equal(s["brake_cmd"], [0, 0, 1, 1, 0, 0])
    assert e.phase_at(1.0) == "a" and e.phase_at(2.0) == ""


# ------------------------------------------------------------------ offline run on the plant core
def simulate(e: Experiment, hidden: str = "none") -> dict[str, np.ndarray]:
    """Run ``e`` through the driver's supervisor into the plant core (dvt_driver.plant.offline)."""
    r = run_offline(e, load_parameters("physical"), load_hidden(hidden), seed=1)
    return {"t": r.t - r.t[0], "sun": r.speeds[:, 0], "c3": r.speeds[:, 1],
            "i": r.currents[:, 0], "gear": r.gear.astype(float), "sun_true": r.omega_true[:, 0],
            "trips": np.array(r.trips, dtype=object), "nacks": np.array(r.nacks)}


def _check_run(e: Experiment, r: dict[str, np.ndarray]) -> None:
    assert r["trips"].size == 0, list(r["trips"])
    assert int(r["nacks"]) == 0
    assert np.abs(r["sun"]).max() < 0.9 * Limits().sun_speed
    for ph in e.phases:
        m = (r["t"] >= ph.start) & (r["t"] < ph.end)
        if ph.label.endswith("-prbs"):
            w = r["sun_true"][m]
            assert np.count_nonzero(np.diff(np.sign(w[np.abs(w) > 1.0]))) >= 5, ph.label
        if ph.label.startswith("gear") and ph.label.endswith("-prbs"):
            g = int(ph.label[4])
            # the band holds through the whole excitation: one degree of freedom, gear g
            assert np.all(r["gear"][m][1:] == g), (ph.label, np.unique(r["gear"][m]))


def test_smoke_experiment_runs_on_the_plant_core_within_limits() -> None:
    e = ec.build("smoke")
    _check_run(e, simulate(e))


@pytest.mark.slow
@pytest.mark.parametrize("hidden", ["none", "stribeck"])
def test_ident_runs_on_the_plant_core_within_limits_and_bands_hold(hidden: str) -> None:
    e = ec.build("ident")
    _check_run(e, simulate(e, hidden))


def test_cli_settings_are_parsed_as_yaml() -> None:
    from dvt_driver.run.experiment import parse_settings

    assert parse_settings(["amplitude=2", "speeds_rpm=[1500, 2000]", "clock=0.05"]) == {
        "amplitude": 2, "speeds_rpm": (1500, 2000), "clock": 0.05}
    e = ec.build("thesis", **parse_settings(["speeds_rpm=[1000,1200]"]))
    assert [p.label for p in e.phases][:2] == ["1000rpm-settle", "1000rpm-brake1"]
    with pytest.raises(ExperimentError, match="--set 'amplitude': expected NAME=VALUE"):
        parse_settings(["amplitude"])
    with pytest.raises(ExperimentError, match="value is not valid YAML"):
        parse_settings(["x=[1,"])


def test_offline_run_measures_positions_and_the_bag_carries_them(tmp_path: object) -> None:
    from pathlib import Path

    from dvt_driver.plant.offline import record_offline
    from dvt_model.contract import JOINT_STATES
    from dvt_model.load import load_joint_load
    from dvt_model.recording.read import read_topics
    e = Experiment("pos", "", (Step(0.0, MotorCurrent(3.0)),
                               Step(0.3, BrakeCurrents((2.0, 0.0, 0.0)))), (), 1.0)
    r = run_offline(e, load_parameters("physical"), seed=2, load=load_joint_load("arm"))
    assert r.positions.shape == r.theta_true.shape == (1000, 2)
    # encoder floors: within one count of the true angles (sun 4096, carrier 3 16384 counts/rev)
    assert np.all(np.abs(r.positions - r.theta_true) <= [2 * np.pi / 4096, 2 * np.pi / 16384])
    assert r.positions[-1, 0] > 10.0
    bag = record_offline(Path(str(tmp_path)) / "pos", e, load_parameters("physical"), seed=2)
    js = read_topics(bag, [JOINT_STATES])[JOINT_STATES]
    assert js.position.shape == (1000, 2) and np.all(np.isfinite(js.position))
