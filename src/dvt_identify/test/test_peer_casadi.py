"""The multiple-shooting peer of ``dvt-bench identify --compare``
(:mod:`dvt_identify.bench_identify.peer_casadi`): measured on the same data as the
identifier, its figures follow the data (no quoted constant), and a missing CasADi is said."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify.bench_identify import compare
from dvt_model.recording import write_run

PERIOD_US = 2000  # 500 Hz: five steps per 10 ms shooting interval, half the NLP of 1 kHz
FIT_POINTS = 1.5
"""How far (percentage points of validation fit, per output) the peer may land from the
identifier on the same pair: both fit the same grey box to the same data."""


def _bag(root: Path, name: str, seed: int) -> Path:
    """The ``ident`` experiment (neutral PRBS/multisine, speed steps, each gear locked) on the
    ``physical`` plant with the ``coulomb`` hidden preset, as a bag with its truth."""
    from dvt_driver.plant.hidden import load_hidden
    from dvt_driver.plant.offline import run_offline
    from dvt_driver.run.experiment_core import build
    from dvt_model.params import load_parameters

    exp = dataclasses.replace(build("ident", seed=seed), sample_period_us=PERIOD_US)
    run = run_offline(exp, load_parameters("physical"), load_hidden("coulomb"), seed=seed)
    stamps = (np.round(run.t / (PERIOD_US * 1e-6)).astype(np.int64) + 1000) * PERIOD_US * 1000
    truth = {"truth_version": 1, "effects": ["coulomb_friction"],
             "plant": {"params": "physical", "seed": seed}}
    return write_run(root / name, stamps, run.speeds, run.currents, truth=truth)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Estimation and validation on a plant with Coulomb friction on both members."""
    root = tmp_path_factory.mktemp("peer")
    return _bag(root, "est", 1), _bag(root, "val", 2)


@pytest.fixture(scope="module")
def compared(pair: tuple[Path, Path]) -> dict[str, Any]:
    pytest.importorskip("casadi")
    return compare.compare_one(*pair, starts=1, peer=True)


@pytest.fixture(scope="module")
def compared_clean() -> dict[str, Any]:
    """The committed pair of the README's peer row (``bags/ident-none-1`` ->
    ``bags/ident-none-val``, 1 kHz, no hidden effect: the peer is told no friction)."""
    pytest.importorskip("casadi")
    bags = Path(__file__).resolve().parents[3] / "bags"
    return compare.compare_one(bags / "ident-none-1", bags / "ident-none-val", peer=True)


def _solved(peer: dict[str, Any]) -> None:
    assert "not_run" not in peer, peer
    assert peer["status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level"), peer["status"]


@pytest.mark.peer
@pytest.mark.slow
@pytest.mark.timeout(1200)  # an identification and one peer fit (IPOPT, about 150 s)
def test_peer_fits_like_the_identifier_and_finds_M(compared_clean: dict[str, Any]) -> None:
    """Without dry friction in the plant, the peer's smoothed band signs are its only
    approximation: both fit the same grey box to the same data and land together."""
    peer = compared_clean["peer"]
    _solved(peer)
    assert peer["told"] == []
    ours = compared_clean["validation_fit_percent_free_run"]
    theirs = peer["validation_fit_percent_free_run"]
    assert set(theirs) == set(ours)
    for name in ours:
        assert abs(theirs[name] - ours[name]) <= FIT_POINTS, (name, theirs, ours)
    assert peer["M_error_percent"] <= compare.TARGET_MD_ERROR_PERCENT, peer
    assert set(compared_clean["meets_targets"]) == {"validation_fit_no_worse",
                                                    "M_D_within_2_percent", "twice_as_fast"}


@pytest.mark.peer
@pytest.mark.slow
@pytest.mark.timeout(1200)  # an identification and one peer fit (IPOPT)
def test_on_coulomb_friction_the_identifier_is_no_worse_than_the_peer(
        compared: dict[str, Any]) -> None:
    """Told the plant's Coulomb frictions, the peer (dry signs smoothed to ``tanh(s / eps)``)
    fits no better than the identifier (exact signs with a stick rule) on any output, within
    the comparison's own margin; the parameters it leaves at a bound are named."""
    peer = compared["peer"]
    _solved(peer)
    assert peer["told"] == ["coulomb_friction"]
    assert {"Fc_sun_shaft", "Fc_carrier3"} <= set(peer["parameters"])
    ours = compared["validation_fit_percent_free_run"]
    theirs = peer["validation_fit_percent_free_run"]
    assert set(theirs) == set(ours)
    for name in ours:
        assert ours[name] >= theirs[name] - compare.NO_WORSE_POINTS, (name, theirs, ours)
    assert compared["meets_targets"]["validation_fit_no_worse"]
    assert set(peer["at_bounds"]) <= set(peer["parameters"])
    summary = compare.pretty_compare({"runs": [compared], "peer_method": "peer",
                                      "load_average": {"before": [0.0], "after": [0.0]}})
    for name in peer["at_bounds"]:
        assert name in summary, summary


@pytest.mark.peer
@pytest.mark.slow
@pytest.mark.timeout(1200)  # an identification and one or two peer fits (IPOPT)
def test_peer_figures_follow_the_data(pair: tuple[Path, Path],
                                      compared: dict[str, Any]) -> None:
    """The same pair the other way round gives other figures: they are measured, not
    quoted."""
    est, val = pair
    swapped = compare.peer_row(val, est, "dvt", compare.truth_md(val))
    assert "not_run" not in swapped, swapped
    a, b = compared["peer"], swapped
    assert a["validation_fit_percent_free_run"] != b["validation_fit_percent_free_run"]
    assert a["parameters"]["M22"] != b["parameters"]["M22"]
    assert not hasattr(compare, "REFERENCE")


def test_without_casadi_the_peer_says_so(pair: tuple[Path, Path],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "casadi", None)  # what an absent package does: ImportError
    from dvt_identify.bench_identify import peer_casadi
    from dvt_identify.errors import BenchError

    assert not peer_casadi.casadi_available()
    assert compare.peer_row(*pair, "dvt", None) == {"not_run": compare.CASADI_MISSING}
    with pytest.raises(BenchError, match="casadi not installed"):
        peer_casadi.run_peer(*pair)
