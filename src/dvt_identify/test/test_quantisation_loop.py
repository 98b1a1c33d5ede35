"""The loop on a quantising sensor: a cart (``M v' = F - Fv v``, M 2.5 kg, Fv 4 N s/m, random
force steps) whose speed is read on a 0.05 m/s grid (about 50 levels over its range; white
noise of 0.002 m/s before the rounding). The quantisation map is accepted with the right step
and nothing else; on the same cart read without the grid nothing is accepted.

Tolerances: the step is within 3 of its reported standard deviations. The rounding makes the
output piecewise constant in the mass and the damping, so their sandwich standard deviations
are not determined there (reported as inf); they are checked against a stated 1 %, which the
clean variant meets with standard deviations of about 0.02 %.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.simulation import OEModel

STEP = 0.05
"""Grid step of the sensor [m/s]."""
TRUE = {"M": 2.5, "Fv": 4.0}
CANDIDATES = [{"effect": "sensor_quantisation", "where": "v"},
              {"effect": "sensor_saturation", "where": "v", "max_level": 1000.0},
              {"effect": "sensor_offset", "where": "v"},
              {"effect": "sign_blind", "where": "v"}]
CFG = LoopConfig(starts=1, refit_starts=1, drift_windows=0)


def record(desc: Description, name: str, seed: int, step: float, n: int = 1500) -> Segment:
    """15 s at 100 Hz; the speed read on a grid of ``step`` (0: no grid)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-5, 5, n // 50 + 1), 50)[:n]
    t = np.arange(n) * 0.01
    clean = make_segment(name, t, u, np.zeros(n), desc.input_names, desc.output_names)
    y = OEModel(desc.structure).simulate(np.array([TRUE["M"], TRUE["Fv"]]), clean, np.zeros(1))
    y = y + 0.002 * rng.standard_normal(y.shape)
    if step:
        y = step * np.round(y / step)
    return make_segment(name, t, u, y, desc.input_names, desc.output_names)


def run(cart_desc: Callable[..., Description], step: float) -> IdentificationResult:
    """The loop on the cart (the shared toy, conftest) with :data:`CANDIDATES`."""
    desc = cart_desc(candidates=CANDIDATES)
    return identify([record(desc, "est", 1, step)], [record(desc, "val", 2, step)], desc, CFG)


def test_quantising_sensor_is_found_with_its_step_and_nothing_else(
        cart_desc: Callable[..., Description]) -> None:
    res = run(cart_desc, STEP)
    assert [d.score.label for d in res.accepted] == ["sensor_quantisation@v"]
    dec = res.accepted[0]
    assert dec.validation is not None and dec.validation.p_value < 1e-6
    # the step is recovered by the evidence, read from the data's values (the grid they sit
    # on); the fit starts the map's quantum there and barely moves it (a piecewise-constant
    # map): it stays at the evidence's step, with a finite reported std
    ev = dec.score.extra
    assert ev["grid_step"] == pytest.approx(STEP, rel=1e-6) and ev["share_on_grid"] == 1.0
    par, std = res.final.parameters(), res.final.fit.parameter_std()
    assert par["quantum"] == pytest.approx(ev["grid_step"], rel=1e-3), par["quantum"]
    assert math.isfinite(std["quantum"]) and std["quantum"] > 0.0, std["quantum"]
    for name, value in TRUE.items():
        assert par[name] == pytest.approx(value, rel=0.01), name
    # the other maps were tried on the quantised model's residual and refused
    assert {d.score.label for d in res.decisions if not d.accepted} <= {
        "sensor_offset@v", "sensor_saturation@v", "sign_blind@v"}


def test_clean_sensor_accepts_nothing(cart_desc: Callable[..., Description]) -> None:
    res = run(cart_desc, 0.0)
    assert res.accepted == []
    par, std = res.final.parameters(), res.final.fit.parameter_std()
    for name, value in TRUE.items():
        assert abs(par[name] - value) < 3 * std[name], name
        assert std[name] / value < 0.01
