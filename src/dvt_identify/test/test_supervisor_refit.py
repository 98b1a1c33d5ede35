"""The supervisor's refit (docs/loop.md section 3): it starts from the model in use (the
description's initial values kept as a further start), keeps the recorded angles in the
snapshot's estimation/validation bags, and a new model whose structure ended at a bound is not
pushed unless clearly better."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify.description import load_description
from dvt_identify.errors import DescriptionError
from dvt_identify.pipeline import model_initial
from dvt_identify.refit import RefitSettings, refit
from dvt_identify.supervisor import (
    STAGE_FULL,
    FitOutcome,
    RequestFit,
    State,
    Supervisor,
    SupervisorConfig,
)
from dvt_model.recording import read_run, write_run

PERIOD_US = 4000  # 250 Hz, the live loop's rate


# ------------------------------------------------------------------ initial-value override
def test_with_initial_overrides_structure_and_bands_and_keeps_the_prior() -> None:
    desc = load_description("dvt")
    prior = desc.initial_values()
    new = desc.with_initial({"M22": 0.03, "D11": 0.02, "band_gain_ring2": 6.5,
                             "band_time_constant_brake1": 0.05})
    vals = new.initial_values()
    assert vals["M22"] == 0.03 and vals["D11"] == 0.02
    assert vals["band_gain_ring2"] == 6.5 and vals["band_time_constant_brake1"] == 0.05
    assert vals["M11"] == prior["M11"] and vals["band_gain_ring1"] == prior["band_gain_ring1"]
    assert desc.initial_values() == prior  # the original is untouched
    assert new.prior_starts == (prior,)
    first, second = new.start_values()
    names = list(vals)
    assert first[names.index("M22")] == 0.03 and second[names.index("M22")] == prior["M22"]
    # a band dropped later (unexcited) drops its names from the starts, too
    fewer = dataclasses.replace(new, model_effects=new.model_effects[:3])
    assert all(v.shape == (6 + 3,) for v in fewer.start_values())
    assert desc.with_initial({}) .prior_starts == ()


@pytest.mark.parametrize(("values", "needle"), [
    ({"M33": 1.0}, "unknown parameter(s) ['M33']"),
    ({"band_gain": 1.0}, "unknown parameter(s) ['band_gain']"),
    ({"M22": math.nan}, "initial value of M22: expected a finite number, got nan"),
    ({"D12": math.inf}, "initial value of D12: expected a finite number, got inf"),
    ({"M11": "0.1"}, "initial value of M11: expected a finite number, got '0.1'"),
    ({"M11": True}, "initial value of M11: expected a finite number, got True"),
    ({"M22": -1.0}, "initial value of M22: -1.0 outside its bounds [1e-06, inf]"),
    ({"band_gain_ring1": -2.0}, "initial value of band_gain_ring1: -2.0 outside"),
])
def test_with_initial_refuses_bad_values(values: dict[str, Any], needle: str) -> None:
    with pytest.raises(DescriptionError) as err:
        load_description("dvt").with_initial(values)
    assert needle in str(err.value)


def test_model_initial_maps_the_model_node_parameters() -> None:
    from dvt_model.config import resolve

    desc = load_description("dvt")
    cfg = resolve({"params": "physical"})
    got = model_initial(desc, {"params": "physical"})
    assert got["M11"] == pytest.approx(cfg.rigid.M[0, 0])
    assert got["M12"] == pytest.approx(cfg.rigid.M[0, 1])
    assert got["D22"] == pytest.approx(cfg.rigid.D[1, 1])
    assert got["band_gain_ring3"] == pytest.approx(cfg.brake.gains[2])
    assert got["band_time_constant_brake2"] == pytest.approx(cfg.brake.time_constants[1])
    pushed = model_initial(desc, {"params": "physical", "M": [0.002, -0.005, -0.005, 0.03],
                                  "D": [0.03, -0.04, -0.04, 0.12],
                                  "band_gain": [5.0, 6.0, 7.0],
                                  "band_time_constant": [0.01, 0.02, 0.03]})
    assert (pushed["M22"], pushed["D12"]) == (0.03, -0.04)
    assert [pushed[f"band_gain_ring{b}"] for b in (1, 2, 3)] == [5.0, 6.0, 7.0]
    assert pushed["band_time_constant_brake3"] == 0.03
    desc.with_initial(pushed)  # admissible as it is


# ----------------------------------------------------------------------- the refit itself
@pytest.fixture(scope="module")
def refitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, FitOutcome]:
    """The ``ident`` experiment (neutral PRBS/multisine, speed steps, each gear locked) on the
    ``physical`` plant without hidden effects, i.e. data of the model in use, 250 Hz, with the
    encoder angles, as a snapshot bag; refitted with 1 start, no augment loop."""
    from dvt_driver.plant.offline import run_offline
    from dvt_driver.run.experiment_core import build
    from dvt_model.params import load_parameters

    exp = dataclasses.replace(build("ident", seed=0), sample_period_us=PERIOD_US)
    run = run_offline(exp, load_parameters("physical"), None, seed=0)
    assert np.isfinite(run.positions).all()
    stamps = (np.round(run.t / (PERIOD_US * 1e-6)).astype(np.int64) + 1000) * PERIOD_US * 1000
    root = tmp_path_factory.mktemp("refit")
    bag = write_run(root / "snapshot", stamps, run.speeds, run.currents,
                    positions=run.positions)
    t = stamps * 1e-9
    req = RequestFit(1, (float(t[0]) + 1.0, float(t[-1]) - 2.0),
                     (float(t[-1]) - 2.0, float(t[-1])), ("sun_shaft",), STAGE_FULL)
    out = refit(bag, req, {"params": "physical"}, root / "work",
                RefitSettings(augment=False, starts=1, fit_decimate=2))
    assert not out.error, out.error
    return bag, root / "work", out


def test_snapshot_bags_keep_the_positions(refitted: tuple[Path, Path, FitOutcome],
                                          tmp_path: Path) -> None:
    bag, work, out = refitted
    data = read_run(bag)
    assert data.positions is not None and data.positions.shape == (data.n, 2)
    assert out.summary["angles"] == "recorded position"
    for part in ("estimation", "validation"):
        got = read_run(work / part)
        assert got.positions is not None
        k = np.searchsorted(data.stamps_ns, got.stamps_ns)
        np.testing.assert_array_equal(got.positions, data.positions[k])
    # a recording without positions reads as None (and its refit bags have none)
    plain = write_run(tmp_path / "plain", data.stamps_ns[:200], data.speeds[:200],
                      data.currents[:200])
    assert read_run(plain).positions is None


def test_refit_reproduces_the_model_in_use(refitted: tuple[Path, Path, FitOutcome]) -> None:
    """Data of the model in use, 1 start: the refit starts from the in-use values and returns
    its M and D (within 10 %: encoder-quantised speeds, the plant's hybrid lock-ups)."""
    from dvt_model.config import resolve

    _, _, out = refitted
    assert out.summary["initial"]["from"] == "the model in use"
    cfg = resolve({"params": "physical"})
    assert out.summary["initial"]["values"]["M22"] == pytest.approx(cfg.rigid.M[1, 1])
    M = np.asarray(out.new_parameters["M"]).reshape(2, 2)
    D = np.asarray(out.new_parameters["D"]).reshape(2, 2)
    np.testing.assert_allclose(M, cfg.rigid.M, rtol=0.1)
    np.testing.assert_allclose(D, cfg.rigid.D, rtol=0.1)
    assert out.summary["structure_at_bounds"] == []
    assert out.summary["suspect"] == {"baseline": [], "final": []}


def test_baseline_fit_runs_the_in_use_start(refitted: tuple[Path, Path, FitOutcome],
                                            tmp_path: Path) -> None:
    from dvt_identify.pipeline import run as run_pipeline

    _, work, _ = refitted
    inuse = model_initial(load_description("dvt"), {"params": "physical"})
    res = run_pipeline([work / "estimation"], [work / "validation"], tmp_path / "r",
                       augment=False, starts=1, fit_decimate=4, quiet=True, plots=False,
                       series=False, initial=inuse)
    names = list(res.baseline.fit.model.names)
    want = [inuse[n] for n in names[:6]]
    assert any(np.allclose(st.start[:6], want) for st in res.baseline.fit.starts_)
    assert res.description.initial_values()["M22"] == inuse["M22"]
    assert res.description.prior_starts[0]["M22"] == 0.0286546  # the thesis prior, kept


# --------------------------------------------------------------- refusal at a bound
def _outcome(gain: float, at_bounds: list[str], n: int = 2000) -> FitOutcome:
    rng = np.random.default_rng(3)
    cur = rng.standard_normal((n, 2))
    return FitOutcome(new_errors=cur * math.sqrt(1.0 - gain), current_errors=cur,
                      new_parameters={"M": [1.0, 0.0, 0.0, 1e-6]},
                      current_parameters={"M": None},
                      summary={"structure_at_bounds": at_bounds})


def _refitting(sup: Supervisor) -> None:
    sup.on_alarm({"change_s": 100.0, "stamp_s": 100.1, "name": "sun_shaft"}, 100.1)
    sup.tick(200.0)
    assert sup.state is State.REFITTING


@pytest.mark.parametrize(("gain", "pushed"), [(0.3, False), (0.7, True)])
def test_structure_at_a_bound_is_not_pushed_unless_clearly_better(gain: float,
                                                                  pushed: bool) -> None:
    bound = ["M22 = 1e-06 at its lower bound 1e-06"]
    one = SupervisorConfig(full_post_change_s=0.0)  # one refit: its decision ends the episode
    sup = Supervisor(one)
    _refitting(sup)
    acts = sup.fit_done(_outcome(gain, bound), 201.0)
    if pushed:
        assert sup.state is State.PUSHING
        assert "structure at a bound: M22" in acts[0].message
    else:
        assert sup.state is State.IDLE
        rec = sup.reports[-1]
        assert rec["outcome"] == "suspect" and not rec["pushed"]
        assert "M22 = 1e-06 at its lower bound" in rec["reason"]
        assert "suspect_min_relative_gain 0.5" in rec["reason"]
        assert acts[0].level == 1 and acts[0].values["outcome"] == "suspect"
    # the same gain without a bound: pushed
    sup2 = Supervisor(one)
    _refitting(sup2)
    sup2.fit_done(_outcome(gain, []), 201.0)
    assert sup2.state is State.PUSHING
    # never pushed at a bound when the threshold is above any possible gain
    sup3 = Supervisor(SupervisorConfig(suspect_min_relative_gain=1.5, full_post_change_s=0.0))
    _refitting(sup3)
    sup3.fit_done(_outcome(gain, bound), 201.0)
    assert sup3.reports[-1]["outcome"] == "suspect"


def test_suspect_threshold_is_validated() -> None:
    from dvt_identify.errors import SupervisorError

    with pytest.raises(SupervisorError, match="supervisor.suspect_min_relative_gain"):
        SupervisorConfig(suspect_min_relative_gain=-0.1).validated()


# ------------------------------------------------------- the first stage: structure held
def test_held_description_fixes_the_structure_at_the_model_in_use(tmp_path: Path) -> None:
    from dvt_identify.refit import held_description
    from dvt_model.config import resolve

    inuse = model_initial(load_description("dvt"), {"params": "physical"})
    got = held_description(load_description("dvt"), inuse, tmp_path / "held.yaml")
    assert got is not None
    path, held = got
    assert set(held) == {"M11", "M12", "M22", "D11", "D12", "D22"}
    desc = load_description(path)
    assert [p.name for p in desc.structure.params] == []  # nothing of M, D left to fit
    _, _, minv = desc.structure.matrices(np.zeros(0))
    np.testing.assert_allclose(np.linalg.inv(minv), resolve({"params": "physical"}).rigid.M)
    # the named candidates stay; the term library is left to the full refit
    full = [c.label() for c in load_description("dvt").make_candidates()]
    first = [c.label() for c in desc.make_candidates()]
    assert first == [c for c in full if not c.startswith("unlisted@")], (full, first)
    assert len(first) < len(full)
    # an entry that mixes a held parameter with a free one keeps both free
    text = load_description("dvt").text.replace("mass: [[M11, M12], [M12, M22]]",
                                                 'mass: [["M11 + 0.5*M12", M12], [M12, M22]]')
    assert "M11 + 0.5*M12" in text
    (tmp_path / "mixed.yaml").write_text(text)
    values = {k: v for k, v in inuse.items() if k != "M12"}
    got2 = held_description(load_description(tmp_path / "mixed.yaml"), values,
                            tmp_path / "held2.yaml")
    assert got2 is not None
    assert set(got2[1]) == {"M22", "D11", "D12", "D22"}  # M11 shares an entry with M12
    assert {p.name for p in load_description(got2[0]).structure.params} == {"M11", "M12"}
    assert held_description(load_description("dvt"), {}, tmp_path / "none.yaml") is None
