"""The sensor maps' residual signatures (``scoring_evidence``), each present and absent on
synthetic data: the second harmonic and the sign-change shares of a sign-blind reading, the
error at flat tops of a clipped one, the residual against the step of a quantised one, the
mean of an offset.

The reference values are closed forms: ``|sin|`` has the Fourier series ``2/pi - (4/pi) sum
cos(2 k w t) / (4 k^2 - 1)``, so against ``sin`` its second harmonic has amplitude ``4 / (3 pi)``
and power ratio ``(4 / 3 pi)^2 = 0.180``; a uniform rounding error has RMS ``q / sqrt(12)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dvt_identify.effects import ScoringContext, SegmentView, make_effect
from dvt_identify.effects.base import Effect
from dvt_identify.effects.sensors import harmonics, sign_change_shares

DT = 0.01
N = 4000
T = np.arange(N) * DT
X = np.sin(2 * np.pi * 2.0 * T)  # 2 Hz, 80 periods
NOISE = 0.01 * np.random.default_rng(0).standard_normal(N)
U = np.cos(2 * np.pi * 2.0 * T)[:, None]  # an input that takes both signs


def build(name: str, **opts: object) -> Effect:
    return make_effect(name, "v", ("v",), ("u",), "N", "m/s", options=dict(opts))


def ctx(y_meas: np.ndarray, y_sim: np.ndarray) -> ScoringContext:
    return ScoringContext(views=[SegmentView(DT, U, y_meas[:, None])],
                          simulated=[y_sim[:, None]], weights=np.ones(1),
                          member_residual=lambda c: np.zeros(N))


def num(ev: dict[str, object], key: str) -> float:
    v = ev[key]
    assert isinstance(v, (int, float)), (key, v)
    return float(v)


def test_second_harmonic_of_a_sign_blind_reading() -> None:
    ev, _ = build("sign_blind").scoring_evidence(ctx(np.abs(X) + NOISE, X))
    assert num(ev, "fundamental_hz") == pytest.approx(2.0, abs=0.05)
    assert ev["fundamental_from"] == "simulated"
    assert num(ev, "second_harmonic_ratio") == pytest.approx((4 / (3 * math.pi)) ** 2, rel=0.1)
    # the residual |x| - x holds the fundamental (amplitude 1) and the second harmonic
    assert num(ev, "residual_2f_over_f") == pytest.approx((4 / (3 * math.pi)) ** 2, rel=0.1)


@pytest.mark.parametrize("measured", [X + NOISE, 1.2 * X + NOISE,
                                      np.sin(2 * np.pi * 2.0 * T - 0.3) + NOISE],
                         ids=["clean", "gain_error", "phase_error"])
def test_no_second_harmonic_without_the_map(measured: np.ndarray) -> None:
    """Noise alone or a linear misfit (gain, phase) puts no second harmonic in the residual."""
    h = harmonics([measured], [X], DT)
    assert num(h, "fundamental_hz") == pytest.approx(2.0, abs=0.05)
    assert num(h, "second_harmonic_ratio") < 1e-3


def test_sign_change_shares_tell_sign_blind_from_reversal_errors() -> None:
    # sign-blind: the error 2|x| sits on the negative lobes, away from the sign changes
    sb = sign_change_shares([np.abs(X) - X], [X])
    assert sb["sign_changes"] == 159  # 80 periods, two changes each, the first at t = 0 not one
    assert 0.1 < sb["sample_share_near_sign_changes"] < 0.3
    assert sb["sign_change_concentration"] < 0.2
    # an error at reversals (a 3-sample kick after each sign change): concentrated there
    kick = np.zeros(N)
    for i in np.flatnonzero(np.diff(np.signbit(X).astype(np.int8))):
        kick[i + 1: i + 4] = 0.1
    rv = sign_change_shares([kick + NOISE], [X])
    assert rv["sign_change_concentration"] > 3.0
    # white noise: uniform
    wn = sign_change_shares([NOISE], [X])
    assert wn["sign_change_concentration"] == pytest.approx(1.0, abs=0.2)


def test_error_at_flat_tops_of_a_clipped_reading() -> None:
    eff = build("sensor_saturation", max_level=100.0)
    x = 3.0 * X
    clipped = np.clip(x, -2.0, 2.0)
    ev, _ = eff.scoring_evidence(ctx(clipped, x))
    assert ev["signature"] is True
    assert num(ev, "sample_share_at_flat_tops") == pytest.approx(
        1 - 2 * math.asin(2 / 3) / math.pi, abs=1 / 25)  # the time |3 sin| > 2, to a
    # sample in each half period of 25 samples
    assert num(ev, "error_share_at_flat_tops") == pytest.approx(1.0)
    assert num(ev, "simulated_beyond_share_at_flat_tops") == pytest.approx(1.0)


def test_no_flat_top_signature_for_noise_or_a_grid() -> None:
    eff = build("sensor_saturation", max_level=100.0)
    x = 3.0 * X
    ev, _ = eff.scoring_evidence(ctx(x + NOISE, x))
    assert ev["signature"] is False and num(ev, "sample_share_at_flat_tops") == 0.0
    # a quantised reading repeats its extreme grid value (13 % of the samples here) but its
    # error is not concentrated there: no flat top
    q = 0.5
    ev, _ = eff.scoring_evidence(ctx(q * np.round(x / q), x))
    assert num(ev, "share_at_max") > 0.1
    assert num(ev, "error_share_at_flat_tops") < num(ev, "sample_share_at_flat_tops")
    assert ev["signature"] is False


def test_quantisation_residual_against_the_step() -> None:
    eff = build("sensor_quantisation")
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal(N)) * 0.01
    q = 0.025
    ev, start = eff.scoring_evidence(ctx(q * np.round(x / q), x))
    assert num(ev, "grid_step") == pytest.approx(q) and start == {"quantum": pytest.approx(q)}
    assert num(ev, "residual_rms_over_step") == pytest.approx(1 / math.sqrt(12), rel=0.05)
    assert num(ev, "residual_share_within_half_step") == pytest.approx(1.0)
    # the grid is there but the model misses by far more than a step: not what limits the fit
    ev, _ = eff.scoring_evidence(ctx(q * np.round(x / q), 0.8 * x))
    assert num(ev, "residual_rms_over_step") > 2.0
    assert num(ev, "residual_share_within_half_step") < 0.5


def test_offset_mean_against_the_scatter() -> None:
    eff = build("sensor_offset")
    ev, _ = eff.scoring_evidence(ctx(X + 0.05 + NOISE, X))
    assert num(ev, "mean_residual") == pytest.approx(0.05, abs=1e-3)
    assert num(ev, "mean_residual_over_residual_std") > 4.0  # 0.05 / 0.01 = 5
    ev, _ = eff.scoring_evidence(ctx(X + NOISE, X))
    assert num(ev, "mean_residual_over_residual_std") < 0.1
