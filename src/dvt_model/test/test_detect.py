"""The residual change detector (pure): design, false alarms, detection, re-learning."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dvt_model.detect import (
    Alarm,
    ChangeDetector,
    DetectorConfig,
    design_threshold,
    false_alarm_rate,
    reference_from_window,
    siegmund_arl,
)
from dvt_model.detect_sim import _whiten, ar1_noise, cusum_run, detection_delay, simulate_clean
from dvt_model.errors import ParameterError


@pytest.mark.parametrize(("field", "value", "needle"), [
    ("learn_s", -1.0, "detector.learn_s"),
    ("learn_s", 0.01, "at least 100 samples"),
    ("shift_sigma", 0.0, "detector.shift_sigma"),
    ("false_alarm_period_s", math.inf, "detector.false_alarm_period_s"),
    ("max_phi", 1.0, "detector.max_phi"),
    ("sample_rate_hz", True, "detector.sample_rate_hz"),
    ("max_gap_s", float("nan"), "detector.max_gap_s"),
    ("names", ("a", "a"), "detector.names"),
])
def test_config_errors_name_the_parameter(field: str, value: object, needle: str) -> None:
    with pytest.raises(ParameterError, match=needle):
        DetectorConfig(**{field: value}).validated()  # type: ignore[arg-type]


def test_siegmund_matches_known_values_and_design_inverts_it() -> None:
    # Textbook: k = 0.5, h = 4 -> ARL0 ~ 336 (Siegmund), h = 5 -> ~ 930.
    assert siegmund_arl(0.5, 4.0) == pytest.approx(336, rel=0.03)
    assert siegmund_arl(0.5, 5.0) == pytest.approx(930, rel=0.03)
    # Huge learning window -> no estimation penalty: the design is Siegmund inverted.
    h = design_threshold(0.25, 2.0 / 1e7, 10**12)
    assert 2.0 / float(siegmund_arl(0.25, h)) == pytest.approx(2.0 / 1e7, rel=0.01)
    # A short reference window needs a higher threshold for the same rate.
    assert design_threshold(0.05, 1e-8, 2000) > design_threshold(0.05, 1e-8, 10**9)
    assert false_alarm_rate(0.05, design_threshold(0.05, 1e-8, 20000), 20000) <= 1e-8


def test_reference_learns_arma_colour_of_ar1_plus_sensor_noise() -> None:
    x, _ = ar1_noise(np.random.default_rng(4), 20000, 1, 0.95, white=0.5)
    ref = reference_from_window(x[:, 0], DetectorConfig())
    assert ref.phi == pytest.approx(0.95, abs=0.02)
    assert -0.8 < ref.theta < -0.4  # the sensor noise shows up as a negative MA term
    white = reference_from_window(np.random.default_rng(5).standard_normal(20000),
                                  DetectorConfig())
    assert white.phi < 0.1 and abs(white.theta) < 0.05


def test_reference_learns_level_scale_and_colour() -> None:
    cfg = DetectorConfig()
    x, _ = ar1_noise(np.random.default_rng(3), 20000, 1, 0.9)
    r = 0.02 + 0.004 * x[:, 0]          # rad/s: level 0.02, sigma 0.004
    r[::997] += 1.0                       # spikes must not spoil the robust scale
    ref = reference_from_window(r, cfg)
    assert ref.level == pytest.approx(0.02, abs=0.001)
    assert ref.phi == pytest.approx(0.9, abs=0.03)
    assert ref.sigma == pytest.approx(0.004, rel=0.25)  # MAD of a 20 s AR(0.9) window
    assert ref.k == pytest.approx(0.25 * math.sqrt(0.1 / 1.9), rel=0.2)
    # the designed two-sided rate of both outputs is the configured one
    assert ref.arl0_s / 4 == pytest.approx(cfg.false_alarm_period_s, rel=0.02)


@pytest.mark.parametrize(("phi", "white"), [(0.0, 0.0), (0.9, 0.0), (0.95, 0.5)])
def test_no_false_alarm_in_ten_minutes_of_clean_1khz_noise(phi: float, white: float) -> None:
    # A fixed-seed regression check of the class and its vectorised twin on clean data (at a
    # design of one false alarm per 4 h, an hour without one is the likely outcome, not a
    # bound): the false-alarm *rate* is measured in test_false_alarm_rate.py (slow tier).
    # The detector class itself on 10 min of 1 kHz AR(1) residual, two outputs, 2 seeds, each
    # window whitened by its own ARMA(1, 1) as in the twin (no colour: test_detect_colour.py) ...
    cfg = DetectorConfig(colour_s=0.0)
    for seed in (11, 12):
        det = ChangeDetector(cfg)
        x, _ = ar1_noise(np.random.default_rng(seed), cfg.learn_samples + 600_000, 2, phi,
                         white)
        rows = (0.003 * x).tolist()
        alarms = [a for j, row in enumerate(rows) if (a := det.update(j * 1e-3, row))]
        assert alarms == [], alarms[:1]
        assert det.counters.tested == 600_000 - 1 or det.counters.tested == 600_000
    # ... and its vectorised twin on 6 more seeds (1 h of tested data in all).
    for seed in range(6):
        sim = simulate_clean(cfg, hours=600 / 3600, phi=phi, white=white, seed=100 + seed)
        assert sim.alarms == 0, sim


@pytest.mark.parametrize(("phi", "bound_s"), [(0.0, 1.0), (0.5, 2.5), (0.9, 10.0)])
def test_half_sigma_step_is_detected_within_a_bounded_delay(phi: float, bound_s: float) -> None:
    # Expected delays (Siegmund, ARL1 ~ (h + 1.166) / (d_z - k)): 0.12 s, 0.5 s, 2.0 s.
    for seed in range(4):
        delay, alarm = detection_delay(phi=phi, shift_sigma=0.5, seed=seed, output=seed % 2)
        assert alarm is not None and 0 < delay < bound_s, (seed, delay)
        assert alarm.output == seed % 2 and alarm.direction == 1
        change = alarm.stamp_s - delay
        assert abs(alarm.change_s - change) < max(0.5 * delay, 0.2), (alarm, change)
        assert 0.2 < alarm.shift_sigma < 1.2  # CUSUM shift estimates are biased upwards
    delay, alarm = detection_delay(phi=phi, shift_sigma=-0.5, seed=9)
    assert alarm is not None and alarm.direction == -1 and delay < bound_s


def test_class_and_vectorised_simulation_agree() -> None:
    cfg = DetectorConfig(learn_s=2.0)
    x, _ = ar1_noise(np.random.default_rng(5), 12000, 2, 0.7)
    x[6000:, 1] -= 0.8
    det = ChangeDetector(cfg)
    hit = next((j, a) for j, row in enumerate(x.tolist()) if (a := det.update(j * 1e-3, row)))
    L = cfg.learn_samples
    ref = det.counters.last_alarm
    assert ref is not None
    refs = [reference_from_window(x[:L, i], cfg) for i in range(2)]
    first = []
    for i, r in enumerate(refs):
        z, _ = _whiten(x[L:, i], (r.last_r, r.last_a), r)
        first += [cusum_run(z, r.k, r.h)[0], cusum_run(-z, r.k, r.h)[0]]
    assert L + min(f for f in first if f >= 0) == hit[0]
    assert hit[1].output == 1 and hit[1].direction == -1


def test_alarm_resets_relearns_and_keeps_running() -> None:
    cfg = DetectorConfig(learn_s=1.0)
    det = ChangeDetector(cfg)
    rng = np.random.default_rng(8)
    t = 0.0
    for _ in range(1000):
        assert det.update(t, rng.normal(0, 1e-3, 2).tolist()) is None
        t += 1e-3
    assert not det.learning and det.counters.learned == 1
    alarm = None
    while alarm is None:
        alarm = det.update(t, [5e-3 + rng.normal(0, 1e-3), rng.normal(0, 1e-3)])
        t += 1e-3
    assert det.learning and det.counters.alarms == 1 and alarm.name == "sun_shaft"
    assert alarm.shift == pytest.approx(5e-3, rel=0.5)
    for _ in range(1000):  # re-learns on the new level: no alarm on it
        assert det.update(t, [5e-3 + rng.normal(0, 1e-3), rng.normal(0, 1e-3)]) is None
        t += 1e-3
    assert not det.learning and det.counters.learned == 2
    assert det.status()["state"] == "testing" and "sun_shaft.h" in det.status()


def test_non_finite_gaps_and_bad_input() -> None:
    det = ChangeDetector(DetectorConfig(learn_s=0.1))
    with pytest.raises(ParameterError, match="residual: expected 2 values"):
        det.update(0.0, [1.0])
    for j in range(100):
        det.update(j * 1e-3, [0.001 * (j % 3), 0.0 + 1e-4 * (j % 2)])
    det.update(0.2, [math.nan, 0.0])
    det.update(5.0, [0.0, 0.0])  # 4.8 s gap
    det.update(5.001, [0.0, 0.0])
    c = det.counters
    assert c.skipped == 1 and c.gaps == 1 and c.tested == 1 and c.samples == 103


def test_a_gap_while_learning_starts_the_reference_window_again() -> None:
    """A reference window spanning a stamp gap (the model re-anchored on lost samples: the
    residual's level differs on either side) would join two levels into one slow colour (phi
    at ``max_phi``, a threshold no step reaches). The gap starts the window again: the
    reference is learned on the samples after it alone (phi 0 on white noise), and a step of
    ten noise sigmas after it alarms within 3 s (a window of 100 samples designs a high ``h``
    for four hours between false alarms: about 2000 whitened sigmas)."""
    config = DetectorConfig(learn_s=1.0, sample_rate_hz=100.0)
    rng = np.random.default_rng(11)
    det = ChangeDetector(config)
    t = 0.0
    for _ in range(60):  # 0.6 s of the window at one level
        assert det.update(t, [0.5 + rng.normal(0.0, 0.05), rng.normal(0.0, 0.05)]) is None
        t += 0.01
    t += 0.2  # a gap: the level after it is another
    for _ in range(100):  # a whole window after the gap
        assert det.update(t, [rng.normal(0.0, 0.05), rng.normal(0.0, 0.05)]) is None
        t += 0.01
    assert not det.learning and det.counters.gaps == 1
    ref = det.references[0]
    assert det.counters.learned == 1 and ref.level == pytest.approx(0.0, abs=0.02), ref
    assert ref.phi < 0.5, ref
    alarm = None
    for _ in range(300):  # a step of ten noise sigmas on the sun shaft
        alarm = alarm or det.update(t, [0.5 + rng.normal(0.0, 0.05), rng.normal(0.0, 0.05)])
        t += 0.01
    assert alarm is not None and alarm.name == "sun_shaft", det.status()


def test_alarm_json_round_trip() -> None:
    a = Alarm(stamp_s=12.5, change_s=10.25, output=1, name="carrier3", direction=-1,
              statistic=130.0, threshold=120.0, samples=2250, shift=-0.01, shift_sigma=-0.6,
              level=0.0, sigma=0.016)
    assert Alarm.from_dict(json.loads(a.to_json())) == a
    with pytest.raises(ParameterError, match="change_s"):
        Alarm.from_dict({k: v for k, v in a.to_dict().items() if k != "change_s"})
