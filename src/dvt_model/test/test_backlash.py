"""Lost motion in the live model: the laws (:mod:`dvt_model.backlash`), the contract's
``dead_zone``/``play``/``spline_play`` terms and the predictor that applies them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dvt_model.backlash import OutputPlay, OutputSpline, dead_zone, play, spline_substeps
from dvt_model.config import build_predictor
from dvt_model.contract import validate_effects
from dvt_model.errors import ContractError, SimulationError
from dvt_model.predictor import Predictor
from dvt_model.terms import parse_terms

DT = 1e-3


def test_dead_zone_is_zero_inside_and_shifted_outside() -> None:
    assert dead_zone(0.3, 0.5) == 0.0 and dead_zone(-0.5, 0.5) == 0.0
    assert dead_zone(2.0, 0.5) == pytest.approx(1.5) and dead_zone(-2.0, 0.5) == -1.5
    u = np.array([-3.0, -0.1, 0.0, 0.2, 4.0])
    assert np.array_equal(dead_zone(u, 0.25), u - np.clip(u, -0.25, 0.25))
    assert np.array_equal(dead_zone(u, 0.0), u)


def test_play_drags_the_sensed_angle_at_the_edge_only() -> None:
    assert play(0.0, 0.05, 0.1) == 0.0  # within the play: the sensor stays
    assert play(0.0, 0.25, 0.1) == pytest.approx(0.15)  # dragged at the upper edge
    assert play(0.15, -0.2, 0.1) == pytest.approx(-0.1)  # reversed through the gap


def test_output_play_stands_still_for_the_gap_after_a_reversal() -> None:
    """Constant speed, then reversed: the sensed speed is the member's in contact and 0 while
    the member crosses the whole play (2 delta / |w|)."""
    delta, w = 0.01, 2.0
    m = OutputPlay(delta)
    m.reset()
    speeds = [m.sensed_speed(w if k < 100 else -w, DT) for k in range(300)]
    # at the start the gap is centred: delta / w = 5 ms before the contact
    assert speeds[:4] == [0.0] * 4 and speeds[20:100] == pytest.approx([w] * 80)
    still = [k for k in range(100, 300) if speeds[k] == 0.0]
    assert len(still) == pytest.approx(2 * delta / w / DT, abs=1), still
    assert speeds[150:] == pytest.approx([-w] * 150)
    assert m.sensed_speed(3.0, 0.0) == 3.0  # no interval: the member's speed, state kept


def test_output_spline_follows_in_contact_and_stands_in_the_gap() -> None:
    gap, wn, zeta = 0.02, 400.0, 0.3
    m = OutputSpline(gap, wn, zeta)
    w = 2.0
    first = m.sensed_speed(w, 0.0)
    assert first == w  # the first sample after a reset: the load moves with the member
    fwd = [m.sensed_speed(w, DT) for _ in range(300)]
    assert fwd[-1] == pytest.approx(w, rel=1e-3)  # in contact, settled
    back = [m.sensed_speed(-w, DT) for _ in range(300)]
    # after the reversal the load coasts through the gap (about gap / (w + w_L) ~ 5 ms,
    # the member having reversed) before the contact on the other flank reverses it
    assert max(back[:3]) > 0.5 * w
    # then it goes with the member again: a contact that cannot pull leaves it rattling in the
    # gap (restitution exp(-pi zeta / sqrt(1 - zeta^2)) = 0.37 per impact, ever longer free
    # flights), but it never leaves the member by more than the gap: over T = 0.2 s its mean
    # speed is the member's within gap / T (plus the sampling of the impacts)
    assert abs(float(np.mean(back[-200:])) + w) <= gap / 0.2 + 0.01
    assert spline_substeps(DT, wn) == 2 and spline_substeps(5e-3, wn) == 10
    assert spline_substeps(1e-3, 1e4) % 2 == 0


@pytest.mark.parametrize(("terms", "match"), [
    ([{"kind": "dead_zone", "delta": 0.1}], r"effects\[0\]\.input: missing"),
    ([{"kind": "dead_zone", "input": "motor", "delta": 0.1}],
     r"effects\[0\]\.input: expected one of \['drive_motor', 'brake1', 'brake2', 'brake3'\], "
     r"got 'motor'"),
    ([{"kind": "dead_zone", "input": "brake1", "delta": -0.1}], r"effects\[0\]\.delta: -0\.1"),
    ([{"kind": "play", "output": 2, "delta": 0.01}], r"effects\[0\]\.output: expected an "
     r"output index 0\.\.1, got 2"),
    ([{"kind": "play", "output": 1, "delta": 2.0}], r"effects\[0\]\.delta: 2\.0 \[rad\]"),
    ([{"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 1.0, "zeta": 0.1}],
     r"effects\[0\]\.wn: 1\.0 \[rad/s\] is not admissible: expected \[10, 10000\]"),
    ([{"kind": "play", "output": 1, "delta": 0.01},
      {"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 300.0, "zeta": 0.1}],
     r"more than one play or spline_play term for one output \(\[1, 1\]\)"),
    ([{"kind": "dead_zone", "input": "brake2", "delta": 0.1},
      {"kind": "dead_zone", "input": "brake2", "delta": 0.2}],
     r"more than one dead_zone term for one input \(\['brake2', 'brake2'\]\)"),
])
def test_lost_motion_terms_are_validated(terms: list[dict[str, object]], match: str) -> None:
    with pytest.raises(ContractError, match=match):
        validate_effects(json.dumps(terms))


def test_terms_parse_lost_motion() -> None:
    t = parse_terms([{"kind": "dead_zone", "input": "brake3", "delta": 0.2},
                     {"kind": "spline_play", "output": 1, "gap": 0.02, "wn": 300.0,
                      "zeta": 0.1}])
    assert t.dead_zones == (0.0, 0.0, 0.0, 0.2) and t.has_lost_motion and not t.empty
    maps = t.output_maps()
    assert maps[0] is None and isinstance(maps[1], OutputSpline)
    assert maps[1] is not t.output_maps()[1]  # a fresh state per predictor
    assert not parse_terms([]).has_lost_motion


def _inputs(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps [s], a drive current through zero [A] and band 1 pulsed [A]."""
    t = np.arange(n) * DT
    im = 3.0 * np.sin(2 * np.pi * 2.0 * t)
    ib = np.zeros((n, 3))
    ib[n // 2:, 0] = 0.6 + 0.1 * np.sin(2 * np.pi * 5.0 * t[n // 2:])
    return t, im, ib


def test_a_dead_zone_is_the_model_fed_the_transformed_currents() -> None:
    n = 1500
    t, im, ib = _inputs(n)
    measured = np.column_stack([40.0 * np.sin(2 * np.pi * t), 5.0 * np.cos(2 * np.pi * t)])
    zone = [{"kind": "dead_zone", "input": "drive_motor", "delta": 0.8},
            {"kind": "dead_zone", "input": "brake1", "delta": 0.65}]
    with_zone, desc = build_predictor({"effects": json.dumps(zone)})
    plain, _ = build_predictor({})
    assert "dead zone on drive_motor, brake1" in desc
    for k in range(n):
        a = with_zone.update(float(t[k]), float(im[k]), ib[k], measured[k])
        b = plain.update(float(t[k]), float(dead_zone(im[k], 0.8)),
                         [float(dead_zone(ib[k, 0], 0.65)), 0.0, 0.0], measured[k])
        assert np.array_equal(a.predicted, b.predicted), k
    # the zone did something: the model without it predicts otherwise
    free, _ = build_predictor({})
    for k in range(n):
        c = free.update(float(t[k]), float(im[k]), ib[k], measured[k])
    assert not np.allclose(c.predicted, a.predicted)


def test_output_play_maps_the_predicted_speed_and_restarts_at_an_anchor() -> None:
    n = 1200
    t, im, ib = _inputs(n)
    measured = np.zeros((n, 2))
    delta = 0.02
    with_play, desc = build_predictor({"effects": json.dumps(
        [{"kind": "play", "output": 1, "delta": delta}]), "gap_reset": 0.1})
    plain, _ = build_predictor({"gap_reset": 0.1})
    assert "play on carrier3" in desc
    ref = OutputPlay(delta)
    gap_at = 700  # a stamp gap > gap_reset: both re-anchor, the play starts again
    stamps = t + np.where(np.arange(n) >= gap_at, 0.5, 0.0)
    for k in range(n):
        a = with_play.update(float(stamps[k]), float(im[k]), ib[k], measured[k])
        b = plain.update(float(stamps[k]), float(im[k]), ib[k], measured[k])
        if b.anchored:
            ref.reset()
        step = 0.0 if b.anchored else float(stamps[k] - stamps[k - 1])
        assert a.predicted[0] == b.predicted[0]
        assert a.predicted[1] == pytest.approx(ref.sensed_speed(float(b.predicted[1]), step),
                                               abs=1e-12), k
    assert with_play.anchors == 2


def test_predictor_refuses_bad_lost_motion_arguments() -> None:
    pred, _ = build_predictor({})
    with pytest.raises(SimulationError, match=r"input_dead_zone: expected 4 finite numbers "
                                              r">= 0 \[A\], got \[0\.1, -1\.0\]"):
        Predictor(pred.model, pred.brake, input_dead_zone=(0.1, -1.0))
    with pytest.raises(SimulationError, match=r"output_maps: expected one per output \(2\), "
                                              r"got 1"):
        Predictor(pred.model, pred.brake, output_maps=(None,))  # type: ignore[arg-type]
    assert math.isfinite(pred.update(0.0, 1.0, [0, 0, 0], [1.0, 0.5]).predicted[0])
