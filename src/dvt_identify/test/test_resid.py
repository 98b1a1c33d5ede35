"""Residual tests: white passes, correlated fails, Bartlett bounds valid for coloured signals."""

from __future__ import annotations

import numpy as np
from scipy import signal

from dvt_identify.resid import residual_analysis, residual_spectrum


def _coloured(x: np.ndarray, cutoff: float) -> np.ndarray:
    sos = signal.butter(2, cutoff, output="sos")
    return np.asarray(signal.sosfilt(sos, x))


def test_white_residual_independent_of_white_input_passes() -> None:
    rng = np.random.default_rng(0)
    e = rng.normal(size=(5000, 1))
    u = rng.normal(size=(5000, 1))
    (r,) = residual_analysis([e], [u], ["y"], ["u"])
    assert r.white
    assert r.independent["u"]
    assert r.ljung_box_p > 0.01
    assert r.acf[0] == 1.0
    assert r.ccf["u"].shape == (51,)


def test_coloured_residual_correlated_with_input_fails() -> None:
    rng = np.random.default_rng(1)
    u = _coloured(rng.normal(size=6000), 0.05)
    e = 0.5 * np.roll(u, 3) + 0.2 * rng.normal(size=6000)  # residual follows the input
    (r,) = residual_analysis([e[:, None]], [u[:, None]], ["y"], ["u"])
    assert not r.independent["u"]
    assert not r.white
    # peak at lag +3: the residual lags the input
    assert int(np.argmax(r.ccf["u"])) - 25 == 3


def test_bartlett_bounds_accept_independent_coloured_signals() -> None:
    """Two independent, strongly coloured signals: the white z/sqrt(N) bound rejects them
    (it assumes one is white), the Bartlett bound does not."""
    rng = np.random.default_rng(2)
    false_naive = 0
    false_bartlett = 0
    for k in range(10):
        u = _coloured(rng.normal(size=4000), 0.01)
        e = _coloured(rng.normal(size=4000), 0.01)
        (r,) = residual_analysis([e[:, None]], [u[:, None]], ["y"], ["u"])
        false_naive += int(np.max(np.abs(r.ccf["u"])) > r.ccf_bound_white)
        false_bartlett += int(not r.independent["u"])
        assert r.ccf_bound["u"] > 3 * r.ccf_bound_white, k
    assert false_naive >= 6
    assert false_bartlett <= 1


def test_segments_pool_without_crossing_boundaries() -> None:
    rng = np.random.default_rng(3)
    e1, e2 = rng.normal(size=(800, 1)), rng.normal(size=(900, 1)) + 10.0
    u1, u2 = rng.normal(size=(800, 1)), rng.normal(size=(900, 1))
    (r,) = residual_analysis([e1, e2], [u1, u2], ["y"], ["u"])
    assert r.n == 1700
    assert r.white  # the offset of segment 2 is removed per segment


def test_spectrum_finds_a_resonance() -> None:
    rng = np.random.default_rng(4)
    t = np.arange(20000) * 1e-3
    e = rng.normal(size=t.size) + 3 * np.sin(2 * np.pi * 120 * t)
    sp = residual_spectrum([e], 1e-3)
    assert abs(sp.peak_hz - 120) < 2
    assert sp.peak_ratio > 10
