"""The search for effects no candidate names: sparse regression of the projected residual on a
library of generic terms, proposed as an ``unlisted`` effect and accepted by the loop's tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects import Unlisted, make_effect
from dvt_identify.fit import OEFit
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.report import build_report
from dvt_identify.simulation import OEModel
from dvt_identify.unlisted import omp, search_unlisted

DT = 0.002
N = 4000
STATES = ["v"]
INPUTS = ["force"]


def description(with_library: bool = True) -> Description:
    data: dict[str, Any] = {
        "name": "synthetic",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "x"}],
        "outputs": [{"name": "v", "topic": "/s/joint_states", "field": "velocity",
                     "joint": "x"}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N m", "speed_unit": "rad/s",
                      "parameters": {"M": {"initial": 5.0, "lower": 0.001},
                                     "Fv": {"initial": 10.0, "lower": 0.0}}},
        "candidates": [
            {"effect": "coulomb_friction", "where": "v"},
            {"effect": "windage", "where": "v"},
            *([{"effect": "unlisted", "where": "v", "inputs": []}] if with_library else []),
        ],
        "fit": {"starts": 2, "refit_starts": 1, "max_effects": 2},
    }
    return parse_description(data, "test")


def bump_friction(y: np.ndarray) -> np.ndarray:
    """A tight spot: friction ``3 exp(-(wrap(theta - 1) / 0.4)^2) sign(v)`` against the motion,
    theta the integrated measured speed (a form no named candidate has)."""
    v = y[:, 0]
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * DT)])
    d = np.angle(np.exp(1j * (theta - 1.0)))
    return np.asarray(-3.0 * np.exp(-(d / 0.4) ** 2) * np.sign(v))


def make(seed: int, bump: bool) -> Segment:
    """``10 v' = -20 v + f (+ the tight spot)``: about a revolution each way between reversals
    (the sign of the speed must change for a friction to differ from a torque)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    sos = signal.butter(2, 3.0, fs=1 / DT, output="sos")
    f = (150 * np.sin(2 * np.pi * 0.3 * t + seed) + 20 * np.sin(2 * np.pi * 1.3 * t + 1)
         + 60 * signal.sosfilt(sos, rng.normal(size=N)))
    model = OEModel(description(False).structure, [])
    theta = np.array([10.0, 20.0])
    y = np.zeros((N, 1))
    for _ in range(10 if bump else 1):
        extra = bump_friction(y) if bump else np.zeros(N)
        seg = make_segment("s", t, np.column_stack([f + extra]), y, INPUTS, STATES)
        y = model.simulate(theta, seg, np.array([0.5]))
    y = y + 0.005 * np.std(y) * rng.normal(size=y.shape)
    return make_segment(f"s{seed}", t, f, y, INPUTS, STATES)


def test_omp_picks_the_true_columns_and_stops_at_the_noise() -> None:
    rng = np.random.default_rng(0)
    Z = rng.normal(size=(2000, 12))
    e = 2.0 * Z[:, 3] - 1.0 * Z[:, 7] + 0.1 * rng.normal(size=2000)
    penalty = np.log(2000) + 2 * np.log(12)
    idx, sse = omp(Z, e, 5, penalty)
    assert idx == [3, 7]
    assert sse[-1] < 0.02 * float(e @ e)
    assert omp(Z, 0.1 * rng.normal(size=2000), 5, penalty)[0] == []


def test_search_finds_position_dependent_friction_and_nothing_on_clean_data() -> None:
    lib = make_effect("unlisted", "v", STATES, INPUTS, "N m", "rad/s", options={"inputs": []})
    assert isinstance(lib, Unlisted)
    seg = make(1, bump=True)
    fit = OEFit(OEModel(description(False).structure), starts=1).fit([seg])
    sc = search_unlisted(fit, [seg], [lib])
    assert sc is not None
    eff = sc.effect
    assert isinstance(eff, Unlisted) and not eff.library
    # a friction (sign of the speed) that depends on the angle: sign(w) times cos/sin of it
    assert all(t.speed == "sign" and t.trig for t in eff.terms), eff.label()
    assert len(eff.terms) >= 2
    assert "sign(w_v)*" in str(sc.extra["formula"])
    assert sc.p_value < 1e-6
    # measured: 0.17 of the residual (the baseline absorbs the bump's mean and its speed part)
    assert sc.r2 > 0.1
    clean = make(2, bump=False)
    fit0 = OEFit(OEModel(description(False).structure), starts=1).fit([clean])
    assert search_unlisted(fit0, [clean], [lib]) is None


def test_loop_accepts_unlisted_only_when_something_is_unmodelled(tmp_path: Path) -> None:
    desc = description()
    r = identify([make(1, bump=True)], [make(5, bump=True)], desc,
                 LoopConfig.from_options(desc.fit))
    names = [d.score.effect.name for d in r.accepted]
    assert "unlisted" in names, [d.as_dict() for d in r.decisions]
    assert r.final.val.mean_fit > r.baseline.val.mean_fit
    dec = next(d for d in r.accepted if d.score.effect.name == "unlisted")
    assert dec.validation is not None and dec.validation.p_value < r.config.alpha
    assert "tau_v = " in dec.score.label and "sign(w_v)" in dec.score.label
    rep = build_report(r)
    assert "sign(w_v)" in str(rep)
    clean = identify([make(2, bump=False)], [make(6, bump=False)], desc,
                     LoopConfig.from_options(desc.fit))
    assert clean.accepted == []
