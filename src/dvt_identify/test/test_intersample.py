"""Signals between samples (``dvt_identify.data.intersample``): a measured current held at its
interval means, an encoder's interval-mean speed compared with the model half a period earlier,
the description keys that say so, and the rate guard that keeps the simulation's convention
where the samples do not resolve the dynamics."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dvt_identify.data import (
    HOLDS,
    SAMPLINGS,
    Segment,
    SignalSpec,
    held_inputs,
    intersample,
    make_segment,
)
from dvt_identify.description import load_description
from dvt_identify.errors import DataError, DescriptionError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.fitrate import model_time_scales, resolves_intersample
from dvt_identify.simulation import OEModel, lag_outputs, zoh_decimate

DT = 1e-3


def _specs(hold: str = "zoh", sampling: str = "instant"
           ) -> tuple[list[SignalSpec], list[SignalSpec]]:
    return ([SignalSpec("force", "/emps/drive", "effort", "carriage", hold=hold)],
            [SignalSpec("carriage", "/emps/joint_states", "velocity", "carriage",
                        sampling=sampling)])


def _segment(u: np.ndarray, y: np.ndarray | None = None) -> Segment:
    t = np.arange(u.size) * DT
    return make_segment("seg", t, u, np.zeros_like(u) if y is None else y, ("force",),
                        ("carriage",))


def test_a_linear_input_is_held_at_the_mean_of_its_line_over_each_interval() -> None:
    t = np.arange(50) * DT
    u = 3.0 + 200.0 * t  # a current ramp, sampled
    seg = intersample(_segment(u), *_specs(hold="linear"))
    assert seg.input_hold == ("linear",)
    np.testing.assert_array_equal(seg.u[:, 0], u)  # the samples stay as measured
    held = held_inputs(seg)[:, 0]
    np.testing.assert_allclose(held[:-1], 3.0 + 200.0 * (t[:-1] + 0.5 * DT), rtol=1e-12)
    assert held[-1] == u[-1]
    assert any("held linear" in n for n in seg.notes), seg.notes
    # a held command is held as sampled
    assert held_inputs(intersample(_segment(u), *_specs()))[0, 0] == u[0]


def test_decimating_a_linear_input_gives_each_coarse_steps_exact_mean() -> None:
    t = np.arange(400) * DT
    u = np.sin(40.0 * t)
    seg = intersample(_segment(u), *_specs(hold="linear"))
    q = 5
    coarse = zoh_decimate(seg, q)
    assert coarse.input_hold is None  # step means, held as they are
    # the mean over [t_k, t_k + q dt) of the line through the fine samples (trapezoids)
    want = [float(np.mean(0.5 * (u[k:k + q] + u[k + 1:k + q + 1])))
            for k in range(0, 400 - q, q)]
    np.testing.assert_allclose(coarse.u[: len(want), 0], want, rtol=1e-12)


def test_an_interval_output_lags_half_a_period_and_the_model_is_compared_that_much_earlier(
        ) -> None:
    seg = intersample(_segment(np.ones(30)), *_specs(sampling="interval"))
    assert seg.output_lag == (0.5 * DT,)
    t = np.arange(30) * DT
    y = (2.0 * t)[:, None]
    lagged = lag_outputs(y, seg.output_lag, DT)
    np.testing.assert_allclose(lagged[1:, 0], 2.0 * (t[1:] - 0.5 * DT), rtol=1e-12)
    assert lagged[0, 0] == y[0, 0]
    # tangents (N, ny, P) alike, column by column
    ty = np.stack([y, 3.0 * y], axis=2)
    lt = lag_outputs(ty, seg.output_lag, DT)
    np.testing.assert_allclose(lt[:, :, 1], 3.0 * lagged, rtol=1e-12)
    assert lag_outputs(y, None, DT) is y
    with pytest.raises(FitError, match="exceeds the step"):
        lag_outputs(y, (2.0 * DT,), DT)


def test_a_fit_on_encoder_speeds_recovers_the_model_with_the_lag_and_not_without() -> None:
    """A first-order carriage ``M v' = F - Fv v`` simulated finely; its 'encoder' speed is the
    mean over each 1-ms period ending at the sample. The fit with ``sampling: interval``
    recovers ``M`` and ``Fv`` to 0.5 %; the same fit reading the samples as instantaneous
    is further off (the half-period lag taken for dynamics)."""
    m_true, fv_true = 2.0, 60.0  # time constant 33 ms
    fine = 20
    n = 3000
    rng = np.random.default_rng(3)
    u_coarse = np.repeat(rng.choice([-20.0, 20.0], size=n // 25), 25)[:n]
    h = DT / fine
    v = 0.0
    enc = np.zeros(n)
    for k in range(1, n):
        acc = 0.0
        for _ in range(fine):
            a = np.exp(-fv_true / m_true * h)
            v_new = a * v + (1.0 - a) * u_coarse[k - 1] / fv_true
            acc += 0.5 * (v + v_new)
            v = v_new
        enc[k] = acc / fine
    desc = load_description("emps")
    model = OEModel(desc.structure)
    got = {}
    for sampling in SAMPLINGS:
        seg = intersample(_segment(u_coarse, enc), *_specs(sampling=sampling))
        fit = OEFit(model, starts=1, theta0=np.array([1.0, 30.0])).fit([seg])
        p = fit.parameters()
        got[sampling] = (p["M"], p["Fv"])
    m, fv = got["interval"]
    assert m == pytest.approx(m_true, rel=5e-3) and fv == pytest.approx(fv_true, rel=5e-3)
    m0, _ = got["instant"]
    assert abs(m0 - m_true) > 2.0 * abs(m - m_true), got


def test_the_description_says_hold_for_inputs_and_sampling_for_outputs(tmp_path: Path) -> None:
    text = load_description("emps").text
    ok = text.replace("    saturation: [-351.5, 351.5]", "    saturation: [-351.5, 351.5]\n"
                      "    hold: linear", 1)
    ok = ok.replace("    field: velocity\n    joint: carriage",
                    "    field: velocity\n    joint: carriage\n    sampling: interval", 1)
    (tmp_path / "ok.yaml").write_text(ok)
    d = load_description(tmp_path / "ok.yaml")
    assert d.inputs[0].hold == "linear" and d.outputs[0].sampling == "interval"
    assert set(HOLDS) == {"zoh", "linear"}
    bad_value = ok.replace("hold: linear", "hold: cubic")
    (tmp_path / "bad_value.yaml").write_text(bad_value)
    with pytest.raises(DescriptionError, match=r"inputs\[0\]\.hold: expected one of "
                                               r"\['zoh', 'linear'\], got 'cubic'"):
        load_description(tmp_path / "bad_value.yaml")
    wrong_side = ok.replace("sampling: interval", "hold: linear")
    (tmp_path / "wrong_side.yaml").write_text(wrong_side)
    with pytest.raises(DescriptionError, match=r"outputs\[0\]\.hold: 'linear' is for inputs"):
        load_description(tmp_path / "wrong_side.yaml")


def test_specs_that_do_not_match_the_segment_are_refused_by_name() -> None:
    seg = replace(_segment(np.ones(5)), input_names=("force",))
    specs_in = [SignalSpec("current", "/x", "effort", "m", hold="linear")]
    with pytest.raises(DataError, match=r"seg: intersample: signal specs \['current'\]"):
        intersample(seg, specs_in, _specs()[1])
    with pytest.raises(DataError, match="input_hold: expected 1 of"):
        replace(seg, input_hold=("cubic",))
    with pytest.raises(DataError, match="output_lag: expected 1 lags"):
        replace(seg, output_lag=(-1.0,))


def test_only_samples_that_resolve_the_dynamics_say_anything_between_them() -> None:
    """The DVT's model (fastest pole about 31 1/s, band lags 20 ms): at 1 kHz the fit step it
    needs spans several samples; at the thesis's 62.5 Hz one sample is most of a band lag."""
    desc = load_description("dvt")
    scales = model_time_scales(OEModel(desc.structure, desc.make_model_effects()))
    assert resolves_intersample(1e-3, *scales)
    assert not resolves_intersample(0.016, *scales)
