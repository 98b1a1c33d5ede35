"""The fit rate, the start guard (starts honoured, suspect optima, more starts) and the
admissibility of effects."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from dvt_identify.data import decimate, make_segment
from dvt_identify.description import load_description, parse_description
from dvt_identify.effects import SegmentView, make_effect
from dvt_identify.errors import DescriptionError
from dvt_identify.fit import OEFit
from dvt_identify.fitrate import fit_decimation, fit_segments, model_time_scales
from dvt_identify.simulation import OEModel, zoh_decimate
from dvt_identify.structures import MechanicalStructure, StateSpaceStructure

# ------------------------------------------------------------------------------- fit rate


def test_fit_decimation_follows_rate_and_dynamics() -> None:
    # the DVT at its prior: fastest pole 31.4 1/s, band lag 0.02 s -> a 5 ms step
    assert fit_decimation(1e-3, 31.4, [0.02]) == 5
    assert fit_decimation(1.0 / 999.998, 31.4, [0.02]) == 5  # a rate a hair below 1 kHz
    assert fit_decimation(1.0 / 62.5, 31.4, [0.02]) == 1     # the thesis rate: as recorded
    assert fit_decimation(5e-3, 31.4, [0.02]) == 1
    # the pole limits when there is no faster effect: 0.2 / 31.4 = 6.4 ms
    assert fit_decimation(1e-3, 31.4) == 6
    # a faster lag limits: 0.004 / 4 = 1 ms
    assert fit_decimation(1e-3, 31.4, [0.004]) == 1
    # nothing known about the dynamics: no decimation
    assert fit_decimation(1e-3, 0.0) == 1
    assert fit_decimation(float("nan"), 31.4) == 1
    # a short segment keeps MIN_FIT_SAMPLES samples
    assert fit_decimation(1e-3, 31.4, [0.02], n=2500) == 2


def test_fit_segments_chooses_per_segment_and_notes_mixed_rates() -> None:
    desc = load_description("dvt")
    model = OEModel(desc.structure, desc.make_model_effects())
    pole, taus = model_time_scales(model)
    assert pole == pytest.approx(31.36, rel=1e-2) and min(taus) == pytest.approx(0.02)
    rng = np.random.default_rng(0)

    def seg(name: str, rate: float, n: int):
        return make_segment(name, np.arange(n) / rate, rng.normal(size=(n, 4)),
                            rng.normal(size=(n, 2)), desc.input_names, desc.output_names)
    fast, slow = seg("fast", 1000.0, 20000), seg("slow", 62.5, 2000)
    out, notes = fit_segments([fast, slow], model, 0)
    assert out[0].dt == pytest.approx(5e-3) and out[1] is slow
    assert any("fast" in n and "by 5" in n for n in notes)
    assert any("different rates" in n for n in notes)
    out, _ = fit_segments([fast, slow], model, 3)   # a fixed factor, as asked
    assert out[0].dt == pytest.approx(3e-3) and out[1].dt == pytest.approx(3 / 62.5)


def test_zoh_decimation_keeps_the_held_input_where_zero_phase_leads() -> None:
    # an integrator x' = u with an input piecewise constant at the fine rate: the mean over
    # each coarse step integrates exactly; the zero-phase sample leads by half a step
    st = StateSpaceStructure(["x"], ["u"], [[0.0]], [["b"]], {"b": {"initial": 1.0}})
    model = OEModel(st)
    dt, n = 1e-3, 4000
    rng = np.random.default_rng(1)
    u = np.repeat(rng.normal(size=n // 40), 40)[:, None]
    fine = make_segment("f", np.arange(n) * dt, u, np.zeros((n, 1)), ["u"], ["x"])
    x = model.simulate(np.array([1.0]), fine, np.zeros(1))
    fine = make_segment("f", fine.t, u, x, ["u"], ["x"])
    q = 5
    good = zoh_decimate(fine, q)
    x_good = model.simulate(np.array([1.0]), good, np.zeros(1))
    assert np.max(np.abs(x_good[:, 0] - x[::q][: good.n, 0])) < 1e-12
    old = decimate(fine, q)
    x_old = model.simulate(np.array([1.0]), old, np.zeros(1))
    assert np.max(np.abs(x_old[:, 0] - x[::q][: old.n, 0])) > 1e-3


def test_description_fit_decimate_auto() -> None:
    assert load_description("dvt").preprocess.fit_decimate == 0
    base = load_description("emps")
    import yaml

    data = yaml.safe_load(base.text)
    for raw, want in (("auto", 0), (None, 0), (3, 3)):
        data["preprocess"]["fit_decimate"] = raw
        assert parse_description(data, "x.yaml").preprocess.fit_decimate == want
    for raw in ("fast", 0, 2.5, True):
        data["preprocess"]["fit_decimate"] = raw
        with pytest.raises(DescriptionError, match="fit_decimate"):
            parse_description(data, "x.yaml")


# ------------------------------------------------------------------------------- starts


def _free_2x2() -> StateSpaceStructure:
    names = ["A11", "A12", "A21", "A22", "B11", "B12", "B21", "B22"]
    return StateSpaceStructure(["w1", "w2"], ["u1", "u2"], [["A11", "A12"], ["A21", "A22"]],
                               [["B11", "B12"], ["B21", "B22"]],
                               {n: {"initial": 0.0} for n in names})


def test_starts_are_honoured() -> None:
    dt, n = 0.005, 1500
    rng = np.random.default_rng(3)
    sos = signal.butter(2, 5.0, fs=1 / dt, output="sos")
    u = signal.sosfilt(sos, rng.normal(size=(n, 2)), axis=0) * 5
    truth = np.array([-2.0, 1.5, -3.0, -4.0, 1.0, 0.0, 0.5, 2.0])
    seg0 = make_segment("s", np.arange(n) * dt, u, np.zeros((n, 2)), ["u1", "u2"],
                        ["w1", "w2"])
    y = OEModel(_free_2x2()).simulate(truth, seg0, np.zeros(2))
    seg = make_segment("s", seg0.t, u, y + 0.01 * rng.normal(size=y.shape), ["u1", "u2"],
                       ["w1", "w2"])
    for k in (1, 4, 8):
        fit = OEFit(OEModel(_free_2x2()), starts=k, seed=2).fit([seg])
        assert len(fit.starts_) >= k  # more only when the guard adds starts
        assert len(fit.starts_) == k or fit.notes_


def _brake_problem() -> tuple[OEModel, list, float]:
    """One mass with a force input and a second input through an engagement lag:
    ``M v' = -Fv v + F + kb * lag(b)``; the true lag 0.05 s."""
    st = MechanicalStructure(["v"], ["F", "b"], [["M"]], [["Fv"]], [[1.0, "kb"]],
                             {"M": {"initial": 1.0, "lower": 0.01},
                              "Fv": {"initial": 1.0, "lower": 0.0},
                              "kb": {"initial": 1.0}})
    lag = make_effect("brake_engagement", "b", ["v"], ["F", "b"]).with_initial(
        {"band_time_constant": 0.02})
    model = OEModel(st, (lag,))
    dt, n = 0.002, 4000
    t = np.arange(n) * dt
    rng = np.random.default_rng(5)
    F = np.repeat(rng.normal(size=n // 100), 100)
    b = (np.sin(2 * np.pi * 0.7 * t) > 0.3).astype(float) * 2.0
    u = np.column_stack([F, b])
    seg0 = make_segment("brake", t, u, np.zeros((n, 1)), ["F", "b"], ["v"])
    truth = np.array([0.5, 2.0, -1.5, 0.05])
    y = model.simulate(truth, seg0, np.zeros(1))
    seg = make_segment("brake", t, u, y + 0.002 * rng.normal(size=y.shape), ["F", "b"], ["v"])
    return model, [seg], 0.05


def test_a_start_at_a_bound_is_suspect_and_more_starts_recover() -> None:
    model, segs, tau = _brake_problem()
    bad = np.array([0.5, 2.0, -0.3, 10.0])  # the lag at its 10 s upper bound
    # a solver budget of one evaluation keeps the start where it is: a start stuck at a bound
    stuck = OEFit(model, starts=1, theta0=bad, more_starts=0, max_nfev=1).fit(segs)
    assert stuck.at_bounds_ == ["band_time_constant"]
    assert len(stuck.suspect_) == 1 and "band_time_constant = 10 at its bound" in stuck.suspect_[0]
    # the guard: more starts, the first with the parameter at the bound reset (to its initial
    # value 0.02 s): off the bound, a lower cost, no longer suspect, and it says so
    guarded = OEFit(model, starts=1, theta0=bad, max_nfev=1).fit(segs)
    assert any("suspect optimum" in n for n in guarded.notes_)
    assert guarded.suspect_ == [] and guarded.at_bounds_ == []
    assert guarded.theta_[3] == pytest.approx(0.02)
    assert guarded.cost_ < stuck.cost_
    # with the solver's budget the bad start reaches the optimum, not flagged
    fit = OEFit(model, starts=1, theta0=bad).fit(segs)
    assert fit.theta_[3] == pytest.approx(tau, rel=0.05)
    assert fit.suspect_ == [] and fit.at_bounds_ == []


def test_clean_fit_is_not_suspect() -> None:
    model, segs, tau = _brake_problem()
    fit = OEFit(model, starts=2).fit(segs)
    assert fit.suspect_ == [] and fit.at_bounds_ == []
    assert fit.theta_[3] == pytest.approx(tau, rel=0.05)


# ------------------------------------------------------------------------------- admissibility


def test_negative_friction_is_inadmissible_with_the_reason() -> None:
    eff = make_effect("coulomb_friction", "v", ["v"], ["F"])
    why = eff.inadmissible(np.array([-0.1, 0.0]))
    assert why is not None and "Fc" in why and ">= 0" in why
    absent = eff.inadmissible(np.array([0.0, 0.3]))
    assert absent is not None and "absent" in absent
    assert eff.inadmissible(np.array([0.1, -0.02])) is None
    # an offset beyond Fc: a negative friction in one direction
    pushes = eff.inadmissible(np.array([0.1, 0.15]))
    assert pushes is not None and "Fc- = Fc - offset = -0.05 < 0" in pushes
    delay = make_effect("measurement_delay", "v", ["v"], ["F"])
    assert "delay" in (delay.inadmissible(np.array([-1e-3])) or "")
    gain = make_effect("sensor_gain", "v", ["v"], ["F"])
    assert gain.inadmissible(np.array([0.0])) is None  # 0 is inside its range, not a limit
    assert gain.inadmissible(np.array([-0.95])) is not None   # a gain 1 + g must stay > 0
    assert "not a finite" in (eff.inadmissible(np.array([math.nan, 0.0])) or "")


def test_a_stribeck_curve_the_member_never_runs_beyond_is_inadmissible() -> None:
    """A fitted Stribeck speed is a low-speed curve only if the member runs beyond
    STRIBECK_REACH of it in at least STRIBECK_BEYOND_SHARE of the samples (the simulated
    states of the fitted model); the member's own column of the states is read."""
    from dvt_identify.effects.friction import STRIBECK_BEYOND_SHARE, STRIBECK_REACH

    eff = make_effect("stribeck_friction", "sun_shaft", ["sun_shaft", "carrier3"], ["motor"])
    n = 2000
    sun = np.linspace(-210.0, 210.0, n)  # rad/s; carrier 3 far faster: it must not count
    states = [np.column_stack([sun, 1e4 * np.ones(n)])]
    bent = eff.inadmissible_on(np.array([0.05, 134.0]), states)
    assert bent is not None and "vs = 134: " in bent and "0 % of the samples" in bent
    assert "reach 210" in bent
    assert eff.inadmissible_on(np.array([0.05, 5.0]), states) is None  # 93 % beyond 15
    # at the share: beyond REACH vs in just under / over the share of the samples
    edge = 210.0 * (1.0 - STRIBECK_BEYOND_SHARE) / STRIBECK_REACH
    assert eff.inadmissible_on(np.array([0.05, edge * 1.02]), states) is not None
    assert eff.inadmissible_on(np.array([0.05, edge * 0.98]), states) is None
    # the data-free rules still apply first, and no states leave them alone
    assert "finite" in (eff.inadmissible_on(np.array([math.nan, 5.0]), states) or "")
    assert eff.inadmissible_on(np.array([0.05, 134.0]), []) is None
    coulomb = make_effect("coulomb_friction", "sun_shaft", ["sun_shaft", "carrier3"], ["motor"])
    assert coulomb.inadmissible_on(np.array([0.05, 0.0]), states) is None


def test_compliant_backlash_is_unavailable_at_a_slow_rate() -> None:
    eff = make_effect("backlash", "carrier3", ["sun_shaft", "carrier3"], ["motor"],
                      options={"compliant": True})
    y = np.zeros((100, 2))
    u = np.zeros((100, 1))
    slow = SegmentView(1 / 12.5, u, y)
    why = eff.unavailable([SegmentView(1e-3, u, y), slow])
    assert why is not None and "12.5 Hz" in why
    assert eff.unavailable([SegmentView(1e-3, u, y), SegmentView(1 / 62.5, u, y)]) is None


def test_delay_scan_with_segments_of_different_rates() -> None:
    from dvt_identify.effects import ScoringContext

    eff = make_effect("measurement_delay", "v", ["v"], ["F"], options={"max_delay": 0.02})
    t1, t2 = np.arange(2000) * 1e-3, np.arange(100) * 0.016
    y1, y2 = np.sin(5 * t1)[:, None], np.sin(5 * t2)[:, None]
    late1 = np.sin(5 * (t1 - 0.004))[:, None]
    late2 = np.sin(5 * (t2 - 0.004))[:, None]
    ctx = ScoringContext(views=[SegmentView(1e-3, np.zeros((2000, 1)), late1),
                                SegmentView(0.016, np.zeros((100, 1)), late2)],
                         simulated=[y1, y2], weights=np.ones(1),
                         member_residual=lambda c: np.zeros(1))
    extra, start = eff.scoring_evidence(ctx)
    assert extra["best_delay_s"] == pytest.approx(0.004, abs=1.5e-3)
    assert start
