"""``scripts/belt_draws.py --realizations``: the calibration of reported standard deviations
against the spread of the estimates over realizations (``calibration``), on rows whose errors
are drawn with a known scale: honest std inside the 95 % band, std too small by half above it,
a realization without a finite std or not named as drawn left out."""

from __future__ import annotations

import math
from types import ModuleType
from typing import Any

import numpy as np
from script_module import load

DRAWN = ["sign_blind@w_pulley"]
TRUTH = 2.0


def _belt_draws() -> ModuleType:
    return load("belt_draws")


def _rows(n: int, actual: float, reported: float, seed: int = 0) -> list[dict[str, Any]]:
    """``n`` realizations of one parameter ``k`` (truth :data:`TRUTH`) estimated with spread
    ``actual`` and reported with std ``reported``."""
    rng = np.random.default_rng(seed)
    out = []
    for est in TRUTH + actual * rng.standard_normal(n):
        out.append({"seed": 1, "accepted": list(DRAWN), "estimate": {"k": float(est)},
                    "std": {"k": reported}, "error_in_std": {"k": (est - TRUTH) / reported}})
    return out


def test_honest_std_give_a_z_rms_inside_its_band() -> None:
    cal = _belt_draws().calibration(_rows(400, 0.1, 0.1), DRAWN)["parameters"]["k"]
    lo, hi = cal["z_rms_95_if_honest"]
    assert lo < cal["z_rms"] < hi, cal
    assert abs(cal["std_ratio"] - 1.0) < 0.1, cal
    assert cal["finite_std"] == 400


def test_std_too_small_by_half_give_a_z_rms_above_its_band() -> None:
    cal = _belt_draws().calibration(_rows(30, 0.2, 0.1), DRAWN)["parameters"]["k"]
    assert cal["z_rms"] > cal["z_rms_95_if_honest"][1], cal
    assert cal["std_ratio"] > 1.5, cal


def test_a_realization_without_a_finite_std_or_not_named_as_drawn_is_left_out() -> None:
    rows = _rows(30, 0.1, 0.1)
    rows[0]["std"]["k"] = math.inf
    rows[0]["error_in_std"]["k"] = 0.0
    rows[1]["accepted"] = []
    cal = _belt_draws().calibration(rows, DRAWN)
    assert cal["realizations"] == 30 and cal["named_as_drawn"] == 29
    k = cal["parameters"]["k"]
    assert k["finite_std"] == 28
    assert math.isfinite(k["relative_std_percent"]), k
    lo, hi = k["z_rms_95_if_honest"]
    # two-sided 95 % of sqrt(chi2(28) / 28)
    assert abs(lo - math.sqrt(15.3079 / 28)) < 1e-3 and abs(hi - math.sqrt(44.4608 / 28)) < 1e-3
