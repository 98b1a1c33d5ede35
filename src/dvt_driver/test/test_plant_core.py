"""The simulated controller + transmission (PlantSim), without I/O: control, safety, sensors,
session rules and the direction of every hidden effect against the clean plant."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import cache

import numpy as np
import pytest
import yaml

from dvt_driver.errors import PlantError
from dvt_driver.hardware import RPM
from dvt_driver.link.protocol import (
    Ack,
    Command,
    Config,
    FrameType,
    Hello,
    HelloAck,
    Mode,
    Nack,
    NackReason,
    Status,
)
from dvt_driver.plant.core import (
    PlantSim,
    SafetyLimits,
    SampleValues,
)
from dvt_driver.plant.hidden import HiddenEffects, load_hidden, parse_hidden
from dvt_model.params import TransmissionParams, load_parameters

OFF3 = (0.0, 0.0, 0.0)


@cache
def params() -> TransmissionParams:
    return load_parameters("physical")


def make(hidden: HiddenEffects | str | None = None, period_us: int = 1000, seed: int = 5,
         **kw: object) -> PlantSim:
    h = load_hidden(hidden) if isinstance(hidden, str) else hidden
    sim = PlantSim(params(), h, period_us, seed, **kw)  # type: ignore[arg-type]
    assert isinstance(sim.handle(Hello())[0], HelloAck)
    return sim


def run(sim: PlantSim, seconds: float, cmd: Command | Callable[[float], Command] | None,
        every: float = 0.02, strict: bool = True) -> list[SampleValues]:
    """Tick for ``seconds``, (re)sending ``cmd`` every ``every`` s (a keep-alive); ``strict``:
    every command must be acknowledged."""
    n = round(seconds * 1e6 / sim.sample_period_us)
    k_every = max(1, round(every * 1e6 / sim.sample_period_us))
    out = []
    for k in range(n):
        if cmd is not None and k % k_every == 0:
            c = cmd(k * sim.sample_period_us * 1e-6) if callable(cmd) else cmd
            replies = sim.handle(c)
            assert not strict or isinstance(replies[0], Ack), replies
        out.append(sim.tick())
    return out


def speed(rpm: float, brakes: Sequence[float] = OFF3) -> Command:
    return Command(1, Mode.SPEED, rpm * RPM, (brakes[0], brakes[1], brakes[2]))


def current(amps: float, brakes: Sequence[float] = OFF3) -> Command:
    return Command(2, Mode.CURRENT, amps, (brakes[0], brakes[1], brakes[2]))


def col(samples: Sequence[SampleValues], name: str) -> np.ndarray:
    return np.array([getattr(s, name) for s in samples], dtype=float)


# ------------------------------------------------------------------------- speed loop, gears


def test_speed_loop_holds_1500_rpm_in_neutral() -> None:
    sim = make()
    out = run(sim, 1.5, speed(1500))
    last = out[-500:]
    assert {s.gear for s in last} == {0}
    true_rpm = np.array([s.omega_true[0] for s in last]) / RPM
    assert np.max(np.abs(true_rpm - 1500)) < 3.0
    assert abs(np.mean(col(last, "sun_speed")) / RPM - 1500) < 1.0
    assert all(s.status & Status.ENABLED for s in last)
    # the carrier follows through the damping coupling, well below the sun
    c3 = np.mean(col(last, "carrier3_speed")) / RPM
    assert 200 < c3 < 600


@pytest.mark.parametrize("k", [1, 2, 4])
def test_brake_locks_gear_1_and_speed_loop_holds_in_gear(k: int) -> None:
    sim = make()
    run(sim, 1.0, speed(1500))
    out = run(sim, 2.0, speed(1500, (0.125 * k, 0.0, 0.0)))
    last = out[-500:]
    assert {s.gear for s in last} == {1}
    assert all(s.status & Status.BRAKE1 and not s.status & Status.BRAKE2 for s in last)
    true_rpm = np.array([s.omega_true[0] for s in last]) / RPM
    assert np.max(np.abs(true_rpm - 1500)) < 3.0
    ratio = np.mean(col(last, "sun_speed")) / np.mean(col(last, "carrier3_speed"))
    exact = float(sim.model.rigid.kin.gear_ratio(1))
    assert ratio == pytest.approx(exact, rel=2e-3)
    assert np.mean(col(last, "brake_currents")[:, 0]) == pytest.approx(0.125 * k, abs=0.005)


def test_stronger_brake_locks_sooner() -> None:
    times = []
    for amps in (0.125, 0.25, 1.0):
        sim = make()
        run(sim, 1.0, speed(1500))
        out = run(sim, 1.5, speed(1500, (amps, 0.0, 0.0)))
        times.append(next(i for i, s in enumerate(out) if s.gear == 1))
    assert times[0] > times[1] > times[2] > 0


def test_gear_shift_1_to_3() -> None:
    sim = make()
    run(sim, 1.0, speed(1000, (0.5, 0.0, 0.0)))
    out = run(sim, 1.5, speed(1000, (0.0, 0.0, 0.5)))
    assert out[-1].gear == 3
    ratio = np.mean(col(out[-300:], "sun_speed")) / np.mean(col(out[-300:], "carrier3_speed"))
    assert ratio == pytest.approx(float(sim.model.rigid.kin.gear_ratio(3)), rel=5e-3)


def test_16_ms_sample_period_like_the_thesis_serial_line() -> None:
    sim = make(period_us=16000)
    assert sim.substeps == 16
    out = run(sim, 2.0, speed(1500), every=0.048)
    assert np.all(np.diff(col(out, "t_us")) == 16000)
    assert np.all(np.diff(col(out, "seq")) == 1)
    assert abs(out[-1].omega_true[0] / RPM - 1500) < 3.0
    # finer encoder quantisation: 2 pi / (4096 x 16 ms)
    q = 2 * math.pi / 4096 / 0.016
    counts = col(out, "sun_speed") / q
    assert np.allclose(counts, np.round(counts), atol=1e-3)


# ------------------------------------------------------------------------- safety


def test_watchdog_turns_the_motor_off_and_holds_the_brakes() -> None:
    sim = make(limits=SafetyLimits(watchdog_timeout=0.1))
    assert sim.handle(current(3.0, (0.3, 0.0, 0.0))) == [Ack(FrameType.COMMAND, 2)]
    out = [sim.tick() for _ in range(300)]
    assert all(s.status & Status.ENABLED for s in out[:100])
    assert not any(s.status & Status.WATCHDOG for s in out[:100])
    tripped = [s for s in out if s.status & Status.WATCHDOG]
    assert tripped and tripped[0].seq in (100, 101)
    assert all(not s.status & Status.ENABLED for s in tripped)
    assert all(s.status & Status.BRAKE1 for s in tripped)  # brakes hold their current
    assert abs(out[-1].brake_currents[0] - 0.3) < 0.01
    assert abs(sim.motor_current) < 1e-6  # current loop decayed to zero
    assert sim.watchdog_trips == 1
    # the next accepted command clears it
    sim.handle(current(1.0, (0.3, 0.0, 0.0)))
    s = sim.tick()
    assert not s.status & Status.WATCHDOG and s.status & Status.ENABLED


def test_watchdog_can_be_disabled() -> None:
    sim = make(limits=SafetyLimits(watchdog_timeout=0.0))
    sim.handle(current(1.0))
    out = [sim.tick() for _ in range(500)]
    assert all(s.status & Status.ENABLED for s in out)
    assert sim.handle(Hello(1)) == [HelloAck(1, 1000, 0, "dvt-plant-sim 0.1")]


def test_overspeed_trips_latches_and_is_cleared_by_off() -> None:
    sim = make()
    out = run(sim, 1.5, current(20.0), strict=False)  # ~440 rad/s in neutral if nothing stopped it
    trips = [s for s in out if s.status & Status.OVERSPEED]
    assert trips, "no overspeed trip"
    first = trips[0]
    assert first.status & Status.FAULT and not first.status & Status.ENABLED
    # 20 A accelerate the sun by ~16 rad/s per ms: it overshoots the trip while the current
    # loop (1 ms) winds down, then coasts down
    peak = max(s.omega_true[0] for s in out)
    assert peak < sim.limits.trip_speed * 1.12
    assert out[-1].omega_true[0] < 0.9 * peak
    assert sim.trips == 1
    # latched: motor commands refused, the speed decays
    assert sim.handle(current(1.0)) == [Nack(FrameType.COMMAND, 2, NackReason.FAULT_LATCHED)]
    assert sim.handle(speed(100)) == [Nack(FrameType.COMMAND, 1, NackReason.FAULT_LATCHED)]
    later = [sim.tick() for _ in range(200)]
    assert all(s.status & Status.FAULT for s in later)
    assert later[-1].omega_true[0] < first.omega_true[0]
    # OFF clears it (speed below the trip now), then motor commands are accepted again
    assert sim.handle(Command(3, Mode.OFF, 0.0, OFF3)) == [Ack(FrameType.COMMAND, 3)]
    s = sim.tick()
    assert not s.status & (Status.FAULT | Status.OVERSPEED)
    assert sim.handle(current(1.0)) == [Ack(FrameType.COMMAND, 2)]


def test_current_clamp_and_refused_speed() -> None:
    sim = make()
    lim = sim.limits.motor_current_limit
    assert lim == pytest.approx(12.0 / 0.3732)
    sim.handle(current(0.0, (6.0, 0.0, 0.0)))
    [sim.tick() for _ in range(100)]  # gear 1 engaged at rest
    sim.handle(current(100.0, (6.0, 0.0, 0.0)))
    out = [sim.tick() for _ in range(10)]
    assert all(s.status & Status.CURRENT_LIMIT for s in out[1:])
    assert abs(sim.motor_current) <= lim + 1e-9
    assert sim.motor_current > 0.9 * lim
    # over-limit speed set-point refused, brake currents clamped to [0, limit]
    assert sim.handle(speed(2500)) == [Nack(FrameType.COMMAND, 1, NackReason.INVALID_VALUE)]
    sim.handle(Command(4, Mode.CURRENT, 1.0, (-1.0, 50.0, 0.0)))
    s = [sim.tick() for _ in range(5)][-1]
    assert not s.status & Status.CURRENT_LIMIT
    assert s.brake_currents[0] == pytest.approx(0.0, abs=0.01)
    assert s.brake_currents[1] == pytest.approx(sim.limits.brake_current_limit, abs=0.02)


def test_speed_loop_saturates_without_windup() -> None:
    sim = make()
    out = run(sim, 0.6, speed(2400))  # full current until close to the limit
    assert any(s.status & Status.CURRENT_LIMIT for s in out[:50])
    rpm = np.array([s.omega_true[0] for s in out]) / RPM
    assert rpm.max() < 2400 * 1.02  # no wind-up overshoot, no trip
    assert not any(s.status & Status.OVERSPEED for s in out)
    assert abs(rpm[-1] - 2400) < 5


# ------------------------------------------------------------------------- session, clock


def test_session_rules() -> None:
    sim = PlantSim(params(), None, 1000, 1)
    assert not sim.session_open
    assert sim.handle(current(1.0)) == [Nack(FrameType.COMMAND, 2, NackReason.NOT_READY)]
    assert sim.handle(Config(9, 2000)) == [Nack(FrameType.CONFIG, 9, NackReason.NOT_READY)]
    assert sim.handle(Hello(3)) == [Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION)]
    assert sim.handle(Hello()) == [HelloAck(2, 1000, 200000, "dvt-plant-sim 0.1", 4096, 16384)]
    assert sim.handle(Hello(1)) == [HelloAck(1, 1000, 200000, "dvt-plant-sim 0.1")]
    assert sim.handle(Ack(FrameType.COMMAND, 1)) == []  # device-bound only
    a = [sim.tick() for _ in range(3)]
    assert sim.handle(Config(10, 2000)) == [Ack(FrameType.CONFIG, 10)]
    assert sim.handle(Config(11, 100)) == [Nack(FrameType.CONFIG, 11, NackReason.INVALID_VALUE)]
    assert sim.handle(Hello()) == [HelloAck(2, 2000, 200000, "dvt-plant-sim 0.1", 4096, 16384)]
    b = [sim.tick() for _ in range(3)]
    assert [s.seq for s in a + b] == [0, 1, 2, 3, 4, 5]
    assert [s.t_us for s in a + b] == [0, 1000, 2000, 3000, 5000, 7000]
    sim.reset_controller()
    assert not sim.session_open
    assert sim.tick().seq == 0 and sim.t_us == 2000


def test_config_refuses_periods_the_line_cannot_carry() -> None:
    sim = make(period_us=5000, baud=115200)  # 268 samples/s (version 1), 226 (version 2)
    assert sim.handle(Config(1, 1000)) == [Nack(FrameType.CONFIG, 1, NackReason.INVALID_VALUE)]
    assert sim.handle(Config(2, 4000)) == [Nack(FrameType.CONFIG, 2, NackReason.INVALID_VALUE)]
    assert sim.handle(Config(3, 4500)) == [Ack(FrameType.CONFIG, 3)]
    assert sim.handle(Hello(1)) == [HelloAck(1, 4500, 200000, "dvt-plant-sim 0.1")]
    assert sim.handle(Config(2, 4000)) == [Ack(FrameType.CONFIG, 2)]  # 43-byte samples
    with pytest.raises(PlantError, match=r"sample period: 1000 µs is shorter than one sample"):
        PlantSim(params(), None, 1000, baud=115200)
    with pytest.raises(PlantError, match=r"sample period: expected 500\.\.1000000 µs, got 20"):
        PlantSim(params(), None, 20)


def test_command_takes_effect_from_the_next_sample() -> None:
    sim = make(seed=3)
    [sim.tick() for _ in range(3)]
    sim.handle(current(5.0))
    s0 = sim.tick()
    s1 = sim.tick()
    assert not s0.status & Status.ENABLED or s0.motor_current < 0.2
    assert s1.status & Status.ENABLED and s1.motor_current > 1.0


# ------------------------------------------------------------------------- sensors


def test_sensor_quantisation_and_noise() -> None:
    sim = make(seed=11)
    out = run(sim, 1.5, current(4.0))[-500:]
    q_sun = 2 * math.pi / 4096 / 1e-3
    counts = col(out, "sun_speed") / q_sun
    assert np.allclose(counts, np.round(counts), atol=1e-3)
    assert len(np.unique(counts)) >= 2
    tach_step = 20.0 / 4096 * 90.793 * RPM  # one A/D step [rad/s]
    codes = col(out, "carrier3_speed") / tach_step
    assert np.allclose(codes, np.round(codes), atol=1e-3)
    # tach noise 10 mV rms = 0.95 rpm; the true carrier speed barely moves at steady state
    true_c3 = np.array([s.omega_true[1] for s in out])
    resid = col(out, "carrier3_speed") - true_c3
    sigma = 0.01 * 90.793 * RPM  # 0.095 rad/s
    assert 0.8 * sigma < np.std(resid) < 1.3 * sigma
    assert abs(np.mean(resid)) < 0.05
    i_m = col(out, "motor_current")
    assert 0.01 < np.std(i_m) < 0.1 and abs(np.mean(i_m) - 4.0) < 0.02


def test_tach_saturates_at_the_ad_rails() -> None:
    sim2 = make(seed=2)
    run(sim2, 0.5, current(3.0, (0.0, 0.0, 0.0)))
    # carrier 3 beyond 907.9 rpm reads at most the top code
    sim2.state = sim2.model.initial_state(omega=(0.0, 1000 * RPM))
    s = [sim2.tick() for _ in range(2)][-1]
    assert s.carrier3_speed == pytest.approx(2047 * 20.0 / 4096 * 90.793 * RPM)


def test_same_seed_same_samples() -> None:
    a = run(make(seed=9), 0.3, speed(800))
    b = run(make(seed=9), 0.3, speed(800))
    c = run(make(seed=10), 0.3, speed(800))
    assert a == b
    assert col(a, "carrier3_speed").tolist() != col(c, "carrier3_speed").tolist()


# ------------------------------------------------------------------------- hidden effects


def _steady(hidden: str | HiddenEffects | None, amps: float, seconds: float = 2.5
            ) -> tuple[float, float]:
    """Mean measured (sun, carrier3) speed over the last 0.5 s with a constant motor current."""
    out = run(make(hidden), seconds, current(amps))[-500:]
    return float(np.mean(col(out, "sun_speed"))), float(np.mean(col(out, "carrier3_speed")))


@cache
def _clean(amps: float) -> tuple[float, float]:
    return _steady(None, amps)


def test_coulomb_friction_lowers_the_steady_speed() -> None:
    s0, c0 = _clean(4.0)
    s1, c1 = _steady("coulomb", 4.0)
    assert s1 < s0 - 5.0 and c1 < c0 - 2.0


def test_stribeck_friction_lowers_speed_and_breaks_away_late() -> None:
    s0, c0 = _clean(4.0)
    s1, c1 = _steady("stribeck", 4.0)
    assert s1 < s0 - 3.0 and c1 < c0 - 1.0
    # break-away: a current below what the static friction needs leaves the output at rest
    # for longer than the clean plant and longer than with Coulomb friction at the same Fc
    strib = load_hidden("stribeck")
    coul = parse_hidden({"coulomb": {m: s.Fc for m, s in strib.stribeck.items()}})

    def start(h: HiddenEffects | None) -> int:
        out = run(make(h), 0.3, current(0.4))
        return next((i for i, s in enumerate(out) if s.omega_true[1] > 0.5), 10_000)

    assert start(strib) > start(coul) >= start(None)


def test_windage_grows_with_speed() -> None:
    s0_lo, _ = _clean(2.0)
    s1_lo, _ = _steady("windage", 2.0)
    s0_hi, _ = _clean(4.0)
    s1_hi, _ = _steady("windage", 4.0)
    assert s1_lo < s0_lo and s1_hi < s0_hi
    # quadratic drag: the relative loss grows with speed (Coulomb's would shrink)
    assert (s0_hi - s1_hi) / s0_hi > 1.3 * (s0_lo - s1_lo) / s0_lo


def test_backlash_decouples_the_output_on_reversal() -> None:
    sim = make("backlash")
    assert sim.substeps >= 2
    cmd = lambda t: current(4.0 if t < 1.0 else -4.0)  # noqa: E731
    out = run(sim, 1.6, cmd)
    steady = out[800:1000]
    rev = out[1000:1150]
    gap_steady = np.array([abs(s.output_true - s.omega_true[1]) for s in steady])
    gap_rev = np.array([abs(s.output_true - s.omega_true[1]) for s in rev])
    assert gap_steady.max() < 0.05  # in contact: the output follows carrier 3
    assert gap_rev.max() > 1.0  # the shaft crosses the gap: output and carrier part ways
    # the tachometer reads the output shaft; the clean plant's reads carrier 3 itself
    clean = run(make(None), 1.6, cmd)
    assert all(s.output_true == s.omega_true[1] for s in clean)
    twist = abs(sim.physics.bl_twist)
    hb = sim.hidden.backlash
    assert hb is not None and twist < hb.gap  # contact penetration stays small


def test_measurement_delay_shifts_the_speeds_by_whole_samples() -> None:
    cmd = lambda t: current(4.0 if (t % 0.4) < 0.2 else 1.0)  # noqa: E731
    clean = run(make(None, seed=4), 1.2, cmd)
    late = run(make("delay", seed=4), 1.2, cmd)
    shift = 4  # 4 ms at 1 kHz
    sun0, sun1 = col(clean, "sun_speed"), col(late, "sun_speed")
    assert np.array_equal(sun1[shift + 1:], sun0[1:-shift])
    c0, c1 = col(clean, "carrier3_speed"), col(late, "carrier3_speed")
    errs = [np.sqrt(np.mean((c1[10 + d:] - c0[10:len(c0) - d]) ** 2)) for d in range(8)]
    assert int(np.argmin(errs)) == shift
    # the currents are not delayed
    assert np.array_equal(col(clean, "motor_current"), col(late, "motor_current"))
    # the physics are untouched
    assert all(a.omega_true == b.omega_true for a, b in zip(clean, late, strict=True))


def test_wet_brake_engages_later_than_first_order() -> None:
    def lock_time(h: str | None) -> tuple[int, list[SampleValues]]:
        sim = make(h)
        run(sim, 1.0, speed(1500))
        out = run(sim, 1.5, speed(1500, (0.5, 0.0, 0.0)))
        return next(i for i, s in enumerate(out) if s.gear == 1), out

    t_clean, clean = lock_time(None)
    t_wet, wet = lock_time("wet_brake")
    assert t_wet > t_clean + 20
    # in the viscous phase the band drags much less: carrier 3 decelerates less at first
    dc_clean = clean[30].omega_true[1] - clean[0].omega_true[1]
    dc_wet = wet[30].omega_true[1] - wet[0].omega_true[1]
    assert abs(dc_wet) < 0.5 * abs(dc_clean)


def test_every_preset_changes_the_response() -> None:
    base = run(make(None, seed=1), 0.8, lambda t: current(4.0, (0.5 if t > 0.4 else 0.0, 0, 0)))
    for name in ("coulomb", "stribeck", "windage", "backlash", "delay", "wet_brake"):
        out = run(make(name, seed=1), 0.8,
                  lambda t: current(4.0, (0.5 if t > 0.4 else 0.0, 0, 0)))
        d = col(out, "sun_speed") - col(base, "sun_speed")
        assert np.sqrt(np.mean(d ** 2)) > 1.0, name


def test_truth_yaml_of_a_plant() -> None:
    sim = make("coulomb", period_us=2000, seed=42)
    doc = yaml.safe_load(sim.truth_yaml())
    assert doc["effects"] == ["coulomb_friction"]
    assert doc["plant"]["params"] == "physical"
    assert doc["plant"]["seed"] == 42
    assert doc["plant"]["sample_period_us"] == 2000
    assert doc["plant"]["sensors"]["tach_rpm_per_volt"] == 90.793
    assert doc["plant"]["limits"]["watchdog_timeout"] == 0.2
    assert parse_hidden(doc["hidden"]).coulomb == {"sun": 0.05, "carrier3": 0.2}


def test_bad_settings() -> None:
    with pytest.raises(PlantError, match=r"max_step: expected a number > 0 s, got 0"):
        PlantSim(params(), None, 1000, max_step=0)
    with pytest.raises(PlantError, match=r"watchdog_timeout: expected >= 0 s, got -1"):
        PlantSim(params(), None, 1000, limits=SafetyLimits(watchdog_timeout=-1))


# -- positions, protocol versions, joint load, position-dependent hidden effects ---------------

def _unwrap_positions(out: Sequence[SampleValues], cpr: tuple[int, int]) -> np.ndarray:
    from dvt_driver.link.protocol import unwrap_count
    acc: list[int] | None = None
    rows = []
    for v in out:
        assert v.counts is not None
        acc = list(v.counts) if acc is None else [unwrap_count(acc[j], v.counts[j]) for j in (0, 1)]
        rows.append([2 * math.pi * acc[j] / cpr[j] for j in (0, 1)])
    return np.asarray(rows)


def test_v2_samples_carry_encoder_counts_of_the_true_angles() -> None:
    sim = make()
    out = run(sim, 2.0, lambda t: Command(0, Mode.CURRENT, 2.0, (1.0 if t > 0.5 else 0.0, 0, 0)))
    assert sim.session_version == 2
    pos = _unwrap_positions(out, (4096, 16384))
    true = np.array([v.theta_true for v in out])
    assert true[-1, 0] > 50.0  # turned many revolutions
    # one count of resolution: the encoders floor the true angle
    assert np.all(np.abs(pos[:, 0] - true[:, 0]) <= 2 * math.pi / 4096 + 1e-9)
    assert np.all(np.abs(pos[:, 1] - true[:, 1]) <= 2 * math.pi / 16384 + 1e-9)
    frame = out[-1].to_sample()
    assert frame.counts == out[-1].counts


def test_v1_session_has_no_counts_and_a_v1_plant_refuses_hello2() -> None:
    sim = PlantSim(params(), None, 1000, 1)
    assert sim.handle(Hello(1)) == [HelloAck(1, 1000, 200000, "dvt-plant-sim 0.1")]
    assert sim.tick().counts is None and sim.tick().to_sample().counts is None
    old = PlantSim(params(), None, 1000, 1, protocol_version=1)
    assert old.handle(Hello(2)) == [Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION)]
    assert old.handle(Hello(1))[0] == HelloAck(1, 1000, 200000, "dvt-plant-sim 0.1")
    assert old.tick().counts is None
    with pytest.raises(PlantError, match="protocol_version"):
        PlantSim(params(), None, 1000, protocol_version=3)


def test_controller_reset_rezeroes_the_sun_counts_but_not_the_output_encoder() -> None:
    sim = make()
    run(sim, 1.0, Command(0, Mode.CURRENT, 2.0, (1.0, 0.0, 0.0)))
    before = sim.tick()
    assert before.counts is not None and before.counts[0] > 1000 and before.counts[1] > 100
    sim.reset_controller()
    assert isinstance(sim.handle(Hello())[0], HelloAck)
    after = sim.tick()
    assert after.counts is not None
    assert abs(after.counts[0]) < 200  # restarted near 0 (the shaft still coasts)
    assert after.counts[1] >= before.counts[1] - 5  # absolute: continues


def test_declared_arm_load_hangs_still_and_is_lifted_in_gear_3() -> None:
    from dvt_model.load import load_joint_load
    load = load_joint_load("arm-payload")
    assert load is not None
    sim = make(load=load)
    assert sim.model.rigid.M[1, 1] > load.reflected_inertia
    idle = run(sim, 0.5, Command(0, Mode.OFF, 0.0, (0.0, 0.0, 0.0)))
    assert max(abs(v.omega_true[1]) for v in idle) < 1e-6  # hanging: no gravity torque
    out = run(sim, 3.0, Command(0, Mode.SPEED, 150.0, (0.0, 0.0, 6.0)))
    theta = float(load.arm_angle(out[-1].theta_true[1]))
    assert theta > -math.pi / 2 + 0.05  # the arm rose
    truth = yaml.safe_load(sim.truth_yaml())
    assert truth["plant"]["load"]["name"] == "arm-payload"
    assert truth["plant"]["encoders"]["output_counts_per_rev"] == 16384


def test_position_dependent_hidden_presets_act_and_are_in_truth() -> None:
    cmd = Command(0, Mode.CURRENT, 0.3, (0.0, 0.0, 3.0))
    clean = np.array([v.omega_true for v in run(make("none"), 2.0, cmd)])
    for name, effect in (("gravity_arm", "gravity_load"), ("mesh_ripple", "mesh_ripple"),
                         ("position_friction", "position_friction")):
        sim = make(name)
        w = np.array([v.omega_true for v in run(sim, 2.0, cmd)])
        assert np.all(np.isfinite(w))
        assert np.max(np.abs(w - clean)) > 1e-3, name
        truth = yaml.safe_load(sim.truth_yaml())
        assert truth["effects"] == [effect] and name in truth["hidden"]
