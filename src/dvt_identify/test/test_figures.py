"""The report's figures read honestly: every axis labelled with a unit, one colour convention
(measured / before / after, :mod:`dvt_identify.style`), the measured trace on top, legends
outside the data, a spectrum marker only where the report's text names a peak, a linear 0-100 %
candidates axis, lags with their sample period and rate.

The figures are inspected, not drawn: each plot function gets a ``save`` that looks at the
figure's axes and closes it (matplotlib Agg, set by the report module).
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import signal

from dvt_identify import report, style
from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects import make_effect
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.simulation import OEModel

DT = 0.002
N = 1500
UNIT = re.compile(r"\[[^\]]+\]")


def _description() -> Description:
    sig = {"topic": "/s/joint_states", "field": "velocity", "joint": "x"}
    data: dict[str, Any] = {
        "name": "synthetic",
        "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "x"}],
        "outputs": [{"name": "v", **sig}],
        "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                      "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                      "parameters": {"M": {"initial": 5.0, "lower": 0.001},
                                     "Fv": {"initial": 10.0, "lower": 0.0}}},
        "candidates": [{"effect": "coulomb_friction", "where": "v"},
                       {"effect": "sensor_gain", "where": "v"}],
        "fit": {"starts": 1, "refit_starts": 1, "max_effects": 1},
    }
    return parse_description(data, "test")


def _segment(seed: int, fc: float) -> Segment:
    rng = np.random.default_rng(seed)
    t = np.arange(N) * DT
    sos = signal.butter(2, 3.0, fs=1 / DT, output="sos")
    f = 30 * np.sin(2 * np.pi * 0.7 * t + seed) + 60 * signal.sosfilt(sos, rng.normal(size=N))
    desc = _description()
    model = OEModel(desc.structure, [make_effect("coulomb_friction", "v", ["v"], ["force"])])
    seg = make_segment(f"seg{seed}", t, f, np.zeros(N), ["force"], ["v"])
    y = model.simulate(np.array([10.0, 20.0, fc, 1.0]), seg, np.array([0.2]))
    y = y + 0.01 * np.std(y) * rng.normal(size=y.shape)
    return make_segment(f"seg{seed}", t, f, y, ["force"], ["v"])


@pytest.fixture(scope="module")
def result() -> IdentificationResult:
    desc = _description()
    res = identify([_segment(1, 6.0)], [_segment(2, 6.0)], desc,
                   replace(LoopConfig.from_options(desc.fit), max_effects=1))
    assert res.final is not res.baseline  # the Coulomb term is accepted: before and after
    return res


class _Inspect:
    """A ``save`` for the plot functions: keeps the figures' facts, draws nothing."""

    def __init__(self) -> None:
        self.figs: dict[str, list[Any]] = {}

    def __call__(self, fig: Any, path: Path) -> Path:
        import matplotlib.pyplot as plt

        self.figs[path.name] = list(fig.axes)
        plt.close(fig)
        return path


@pytest.fixture(scope="module")
def figs(result: IdentificationResult, tmp_path_factory: pytest.TempPathFactory
         ) -> dict[str, list[Any]]:
    """Axes of every figure, by file name."""
    out = tmp_path_factory.mktemp("figs")
    ins = _Inspect()
    report.plot_fits(result, out, ins)
    report.plot_residuals(result, out, ins)
    report.plot_spectrum(result, out, ins)
    report.plot_candidates(result, out, ins)
    report.plot_linear(result, out, ins)
    return ins.figs


def test_every_axis_has_a_unit(figs: dict[str, list[Any]]) -> None:
    assert set(figs) == {"fit_v.png", "resid_v.png", "spectrum_v.png", "candidates.png",
                         "linear_step_bode.png"}
    for name, axes in figs.items():
        for ax in axes:
            if name != "candidates.png":  # the candidates' y axis holds their names
                assert UNIT.search(ax.get_ylabel()), (name, ax.get_title(), ax.get_ylabel())
        bottom = axes[-1]
        assert UNIT.search(bottom.get_xlabel()), (name, bottom.get_xlabel())
    fit = figs["fit_v.png"]
    assert fit[0].get_ylabel() == "v [m/s]" and fit[1].get_ylabel().endswith("[m/s]")
    assert figs["spectrum_v.png"][0].get_ylabel() == "PSD [(m/s)²/Hz]"
    lag = figs["resid_v.png"][-1].get_xlabel()
    assert "1 sample = 2 ms" in lag and "500 Hz" in lag
    assert "m/s per" in figs["linear_step_bode.png"][1].get_ylabel()


def _line(ax: Any, label_start: str) -> Any:
    return next(ln for ln in ax.get_lines() if str(ln.get_label()).startswith(label_start))


def test_one_colour_convention_and_the_measured_trace_on_top(figs: dict[str, list[Any]]
                                                             ) -> None:
    top, res = figs["fit_v.png"]
    measured, base, final = _line(top, "measured"), _line(top, "baseline"), _line(top, "final")
    assert measured.get_color() == style.MEASURED
    assert base.get_color() == style.BEFORE and final.get_color() == style.AFTER
    assert measured.get_zorder() > max(base.get_zorder(), final.get_zorder())
    assert measured.get_linewidth() < min(base.get_linewidth(), final.get_linewidth())
    assert _line(res, "baseline").get_color() == style.BEFORE
    assert _line(res, "final").get_color() == style.AFTER
    spec = figs["spectrum_v.png"][0]
    assert _line(spec, "baseline").get_color() == style.BEFORE
    assert _line(spec, "final").get_color() == style.AFTER
    acf = figs["resid_v.png"][0]
    assert _line(acf, "baseline").get_color() == style.BEFORE
    # the step/Bode channels never take a model colour
    for ln in figs["linear_step_bode.png"][0].get_lines():
        assert ln.get_color() not in (style.BEFORE, style.AFTER, style.MEASURED)


def test_legends_outside_the_data(figs: dict[str, list[Any]]) -> None:
    for name, axes in figs.items():
        for ax in axes:
            leg = ax.get_legend()
            if leg is None:
                continue
            anchor = leg.get_bbox_to_anchor().transformed(ax.transAxes.inverted())
            assert anchor.x0 >= 1.0, (name, ax.get_title())


def test_spectrum_marker_only_where_the_text_names_a_peak(result: IdentificationResult,
                                                          figs: dict[str, list[Any]]) -> None:
    spec = figs["spectrum_v.png"][0]
    text = " ".join(report.remaining_summary(result))
    marker = [ln for ln in spec.get_lines() if str(ln.get_label()).startswith("peak")]
    named = "validation residual spectrum has a peak" in text
    assert bool(marker) == named
    if not named:
        assert "no p" in spec.get_title()  # "no prominent peak" / "no peak above the noise"


def test_candidates_on_a_linear_0_to_100_percent_axis(figs: dict[str, list[Any]]) -> None:
    for ax in figs["candidates.png"]:
        assert ax.get_xscale() == "linear" and ax.get_xlim() == (0.0, 100.0)
        assert ax.get_xlabel().endswith("[%]")


def test_style_labels() -> None:
    assert style.psd_unit("rad/s") == "(rad/s)²/Hz" and style.psd_unit("m") == "m²/Hz"
    assert style.label("x", "") == "x [unit not given]"
    assert style.lag_label(1e-3) == "lag [samples; 1 sample = 1 ms at 1 kHz]"
    assert style.lag_label(0.016) == "lag [samples; 1 sample = 16 ms at 62.5 Hz]"
    assert "not known" in style.lag_label(None)
    assert style.per_input_unit("rad/s", "A") == "rad/s per A"
    with pytest.raises(ValueError):
        style.residual("during")


class _Stream:
    def __init__(self, tty: bool) -> None:
        self.tty, self.text = tty, ""

    def write(self, text: str) -> int:
        self.text += text
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty


@pytest.mark.parametrize("tty", [True, False])
def test_identifier_progress_one_line_on_a_terminal_nothing_otherwise(tty: bool) -> None:
    """``dvt-identify``'s progress (:class:`dvt_identify.pipeline.TerminalProgress`): milestones
    stay as lines, the rest rewrites one status line with the candidates counted."""
    from dvt_identify.pipeline import TerminalProgress
    from dvt_model.progress import CLEAR, ProgressLine

    s = _Stream(tty)
    say = TerminalProgress(ProgressLine(s, "[i] ", min_interval=0.0, width=200))
    say("baseline fit: 1 estimation segment(s), 100 samples, 2 start(s)")
    say("start 1/2: cost 3 after 40 evaluations, 1.0 s")
    say("baseline: validation fit v 90 %")
    say("round 1: scoring 2 candidate(s)")
    say("  score coulomb_friction@v   R2  35.1 %  (0.0 s)")
    say("  score windage@v   R2  0.6 %  (0.0 s)")
    say("round 1: ACCEPTED coulomb_friction@v")
    if not tty:
        assert s.text == ""
        return
    kept = [ln.rsplit(CLEAR, 1)[-1] for ln in s.text.split("\n")[:-1]]
    assert kept == ["[i] baseline: validation fit v 90 %", "[i] round 1: ACCEPTED coulomb_friction@v"]
    assert CLEAR + "[i] baseline fit; start 1/2: cost 3" in s.text
    assert CLEAR + "[i] round 1: scored 2/2 (100 %): windage@v R2 0.6 %" in s.text
