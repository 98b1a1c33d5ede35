"""ClockMapper: controller clock -> host time, robust to latency spikes, drift and resets."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_driver.errors import ClockError
from dvt_driver.link.clock import ClockMapper

OFFSET = 1_700_000_000 * 10**9  # ns: host time at controller t = 0


def _run(mapper: ClockMapper, t_us: np.ndarray, latency_ns: np.ndarray, offset: int = OFFSET,
         rate: float = 1.0) -> np.ndarray:
    """Map samples taken at controller times ``t_us`` received after ``latency_ns``;
    the host clock is ``offset + rate * t``."""
    out = []
    for t, lat in zip(t_us, latency_ns, strict=True):
        host = offset + round(rate * t * 1000) + int(lat)
        out.append(mapper.map(int(t), host))
    return np.array(out, dtype=np.int64)


def test_constant_latency_maps_to_sample_instant_plus_min_latency() -> None:
    m = ClockMapper()
    t = np.arange(1, 3001) * 1000
    stamps = _run(m, t, np.full(t.size, 300_000))
    np.testing.assert_array_equal(stamps, OFFSET + t * 1000 + 300_000)
    assert m.offset_ns == OFFSET + 300_000
    assert m.guarded == 0


def test_latency_spikes_do_not_move_the_stamps() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(1, 5001) * 1000
    lat = 200_000 + rng.exponential(100_000, t.size)  # jitter above a sharp floor
    lat[::97] += 20_000_000  # 20 ms stalls
    lat[0] = 200_000  # the floor is seen at once
    m = ClockMapper(window=1.0)
    stamps = _run(m, t, lat)
    err = stamps - (OFFSET + t * 1000)
    # every stamp within the floor latency plus the smallest jitter seen in a 1 s window
    assert err.min() >= 200_000
    assert err.max() < 200_000 + 20_000
    assert np.all(np.diff(stamps) > 0)


def test_initial_overestimate_is_slewed_down_without_going_backwards() -> None:
    t = np.arange(1, 201) * 1000
    lat = np.full(t.size, 100_000)
    lat[:10] = 5_000_000  # the first samples come in late (start-up), then the floor appears
    m = ClockMapper(max_slew=0.5)
    stamps = _run(m, t, lat)
    d = np.diff(stamps)
    assert np.all(d > 0)
    assert d.min() >= 500_000 - 1  # at least (1 - max_slew) of the 1 ms period
    # converged to the floor once the 4.9 ms excess has been slewed off at 0.5 ms/sample
    np.testing.assert_array_equal(stamps[40:], OFFSET + t[40:] * 1000 + 100_000)


@pytest.mark.parametrize("ppm", [-100.0, 100.0])
def test_drift_is_followed_within_window_times_drift(ppm: float) -> None:
    rate = 1.0 + ppm * 1e-6  # host seconds per controller second
    t = np.arange(1, 20_001) * 1000  # 20 s at 1 kHz
    m = ClockMapper(window=2.0)
    stamps = _run(m, t, np.full(t.size, 250_000), rate=rate)
    host_instant = OFFSET + np.round(rate * t * 1000).astype(np.int64)
    err = stamps - host_instant  # the stamp minus the true sample instant in host time
    assert np.all(np.diff(stamps) > 0)
    assert err.max() <= 250_000 + 1
    assert err.min() >= 250_000 - 2.0 * abs(ppm) * 1e-6 * 1e9 - 1000  # lag <= window * drift


def test_reset_reestimates_and_stamps_keep_increasing() -> None:
    m = ClockMapper()
    t1 = np.arange(1, 1001) * 1000
    s1 = _run(m, t1, np.full(t1.size, 300_000))
    # controller restarts 0.4 s later (host time), its clock begins again at 0
    restart_host = OFFSET + 1_400_000_000
    m.reset()
    t2 = np.arange(0, 1000) * 1000
    s2 = _run(m, t2, np.full(t2.size, 300_000), offset=restart_host)
    assert m.resets == 1
    np.testing.assert_array_equal(s2, restart_host + t2 * 1000 + 300_000)
    assert s2[0] > s1[-1]


def test_clock_going_back_is_a_reset_and_stamps_never_decrease() -> None:
    m = ClockMapper()
    a = m.map(5_000_000, OFFSET + 5_000_000_000)
    # a restart whose new offset maps into the past (host clock stepped back, say)
    b = m.map(1000, OFFSET + 1_000_000)
    assert m.resets == 1
    assert b == a + 1 and m.guarded == 1
    c = m.map(2000, OFFSET + 2_000_000)
    assert c == a + 2


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ClockError, match="window"):
        ClockMapper(window=0.0)
    with pytest.raises(ClockError, match="max_slew"):
        ClockMapper(max_slew=1.0)
    m = ClockMapper()
    with pytest.raises(ClockError, match="t_us"):
        m.map(-1, 0)
    with pytest.raises(ClockError, match="host_ns"):
        m.map(1, 1.5)  # type: ignore[arg-type]
