"""The stall rule of a long recording's first start on all of it (``fit._Stall``): the solver
stops when its last few evaluations no longer lower the cost by a stated fraction of it (a cost
ragged near its optimum), not while it still makes progress, and only there. Its effect on an
hour: ``scripts/hours_breakdown.py`` (docs/identification.md §10)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.optimize import OptimizeResult

from dvt_identify import fit as fit_module
from dvt_identify.data import make_segment
from dvt_identify.description import parse_description
from dvt_identify.fit import _Stall
from dvt_identify.simulation import OEModel

_ONE_MASS: dict[str, Any] = {
    "name": "one-mass",
    "inputs": [{"name": "force", "topic": "/s/drive", "field": "effort", "joint": "x"}],
    "outputs": [{"name": "v", "topic": "/s/joint_states", "field": "velocity", "joint": "x"}],
    "structure": {"type": "mechanical", "mass": [["M"]], "damping": [["Fv"]],
                  "input_matrix": [[1.0]], "force_unit": "N", "speed_unit": "m/s",
                  "parameters": {"M": {"initial": 5.0, "lower": 0.001},
                                 "Fv": {"initial": 10.0, "lower": 0.0}}},
}


def _feed(stall: _Stall, seen: list[tuple[int, float]]) -> int | None:
    """The evaluation count at which ``stall`` stops on the accepted (nfev, cost) ``seen``."""
    for nfev, cost in seen:
        try:
            stall(OptimizeResult(nfev=nfev, cost=cost))
        except StopIteration:
            return nfev
    return None


def test_the_stall_stops_when_the_last_passes_lower_the_cost_by_less_than_its_fraction(
        ) -> None:
    # the hour's first start as measured (accepted points: evaluations, cost)
    hour = [(1, 55.9788), (2, 53.2727), (5, 53.1279), (7, 53.1258274), (8, 53.1252968),
            (9, 53.1231308), (11, 53.1216891), (18, 53.1216881), (20, 53.1216877),
            (21, 53.1216868), (24, 53.1216867), (27, 53.1216867)]
    stall = _Stall(passes=4, rtol=1e-6)
    assert _feed(stall, hour) == 18 and stall.stalled
    # steady progress of more than the fraction per evaluation: never stops
    steady = [(n, 100.0 * (1 - 2e-6) ** n) for n in range(1, 60)]
    assert _feed(_Stall(passes=4, rtol=1e-6), steady) is None


def test_only_a_long_recordings_first_start_on_all_samples_has_the_stall(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A short recording's fit never gets the callback (its figures are the plain solver's)."""
    calls: list[Any] = []
    solve = fit_module.OEFit._solve

    def seen(self: Any, *args: Any) -> Any:
        calls.append(args[5] if len(args) > 5 else None)
        return solve(self, *args)
    monkeypatch.setattr(fit_module.OEFit, "_solve", seen)
    monkeypatch.setenv("DVT_IDENTIFY_WORKERS", "1")  # every solve in this process: seen
    desc = parse_description(_ONE_MASS, "test")
    n = 4000
    t = np.arange(n) * 0.004
    force = 30 * np.sin(2 * np.pi * 0.7 * t) + 15 * np.sin(2 * np.pi * 2.3 * t)
    seg = make_segment("seg", t, force, np.zeros(n), ["force"], ["v"])
    model = OEModel(desc.structure, ())
    v = model.simulate(np.array([10.0, 20.0]), seg, np.array([0.2]))[:, 0]
    v = v + 0.01 * float(np.std(v)) * np.random.default_rng(5).normal(size=n)
    seg = make_segment("seg", t, force, v, ["force"], ["v"])
    fit_module.OEFit(model, starts=1).fit([seg])
    assert calls == [None]
    monkeypatch.setattr(fit_module, "PREFIT_SAMPLES", 1500)
    calls.clear()
    fit_module.OEFit(model, starts=1).fit([seg])
    assert calls[0] is None and isinstance(calls[1], _Stall), calls
