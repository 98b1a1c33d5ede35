"""The supervisor's state machine with synthetic inputs (no ROS, no fitting): every branch."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from dvt_identify.errors import SupervisorError
from dvt_identify.supervisor import (
    STAGE_EFFECTS,
    STAGE_FULL,
    Diagnostic,
    FitOutcome,
    Push,
    Report,
    RequestFit,
    Rollback,
    State,
    Supervisor,
    SupervisorConfig,
    episode_markdown,
)

CFG = SupervisorConfig(min_post_change_s=30.0, settle_s=1.0, validation_s=10.0,
                       full_post_change_s=0.0, max_estimation_s=100.0, watch_s=20.0,
                       watch_settle_s=2.0, baseline_s=10.0, rollback_tolerance=0.1,
                       min_watch_samples=500, fit_timeout_s=50.0, push_timeout_s=5.0)
"""One refit per episode (``full_post_change_s`` 0); the two stages: ``CFG2``."""
OLD = {"effects": "old"}
NEW = {"effects": "new"}


def _alarm(change: float, stamp: float, name: str = "sun_shaft") -> dict[str, Any]:
    return {"change_s": change, "stamp_s": stamp, "name": name, "output": 0, "shift": 0.01}


def _live(sup: Supervisor, t0: float, t1: float, rms: float, seed: int = 0) -> None:
    """Live residual at 200 Hz with RMS ``rms`` on both outputs."""
    rng = np.random.default_rng(seed)
    for t in np.arange(t0, t1, 0.005):
        sup.observe(float(t), (rms * rng.standard_normal(2)).tolist())


def _fit(better: bool, n: int = 2000, seed: int = 1) -> FitOutcome:
    rng = np.random.default_rng(seed)
    cur = 0.02 * rng.standard_normal((n, 2)) + 0.01
    new = 0.01 * rng.standard_normal((n, 2)) if better else cur + 0.001 * rng.standard_normal(
        (n, 2))
    return FitOutcome(new_errors=new, current_errors=cur, new_parameters=NEW,
                      current_parameters=OLD, summary={"effects": ["coulomb_friction"]})


def _of(actions: list[Any], kind: type) -> list[Any]:
    return [a for a in actions if isinstance(a, kind)]


def _to_refit(sup: Supervisor, change: float = 100.0) -> RequestFit:
    acts = sup.on_alarm(_alarm(change, change + 2.0), change + 2.0)
    assert sup.state is State.WAITING and _of(acts, Diagnostic)
    assert sup.tick(change + 20.0) == []
    acts = sup.tick(change + 31.0)
    assert sup.state is State.REFITTING
    (req,) = _of(acts, RequestFit)
    return req


def test_windows_of_the_refit() -> None:
    sup = Supervisor(CFG)
    req = _to_refit(sup)
    # from the detection (102: later than change + settle) .. now - val
    assert req.estimation == pytest.approx((102.0, 121.0))
    assert req.validation == pytest.approx((121.0, 131.0))  # the newest 10 s, held out
    assert req.outputs == ("sun_shaft",)


def test_not_better_is_not_pushed() -> None:
    sup = Supervisor(CFG)
    _to_refit(sup)
    acts = sup.fit_done(_fit(better=False), 140.0)
    assert sup.state is State.IDLE and not _of(acts, Push)
    (rep,) = _of(acts, Report)
    r = rep.record
    assert r["outcome"] == "not_better" and r["pushed"] is False and r["rolled_back"] is False
    assert r["test"]["p_value"] >= 0.05 and r["refit"] == {"effects": ["coulomb_friction"]}
    assert r["change_s"] == 100.0 and r["detected_s"] == 102.0
    assert set(r["error_before"]) == {"sun_shaft", "carrier3"}


def test_better_is_pushed_and_confirmed() -> None:
    sup = Supervisor(CFG)
    _live(sup, 100.0, 140.0, 0.02)          # old model after the change
    _to_refit(sup)
    acts = sup.fit_done(_fit(better=True), 140.0)
    (push,) = _of(acts, Push)
    assert push.parameters == NEW and sup.state is State.PUSHING
    assert _of(sup.push_done(True, 141.0), Diagnostic) and sup.state is State.WATCHING
    _live(sup, 141.0, 162.0, 0.01, seed=2)  # new model: residual halves
    assert sup.tick(150.0) == []
    acts = sup.tick(161.5)
    (rep,) = _of(acts, Report)
    r = rep.record
    assert sup.state is State.IDLE and r["outcome"] == "confirmed"
    assert r["pushed"] and not r["rolled_back"] and r["push_s"] == 141.0
    assert r["live_ratio"]["sun_shaft"] == pytest.approx(0.5, rel=0.1)
    assert r["live_vs_expected"]["carrier3"] == pytest.approx(1.0, rel=0.15)
    assert [s["state"] for s in r["steps"]] == ["waiting", "refitting", "pushing", "watching",
                                                "idle"]
    assert r["timings"]["total_s"] == pytest.approx(161.5 - 102.0)


def test_pushed_then_worse_is_rolled_back() -> None:
    sup = Supervisor(CFG)
    _live(sup, 100.0, 140.0, 0.02)
    _to_refit(sup)
    sup.fit_done(_fit(better=True), 140.0)
    sup.push_done(True, 141.0)
    _live(sup, 141.0, 162.0, 0.03, seed=3)  # live residual got worse
    acts = sup.tick(161.5)
    (rb,) = _of(acts, Rollback)
    assert rb.parameters == OLD and "rose by a factor" in rb.reason
    assert sup.state is State.ROLLING_BACK
    acts = sup.rollback_done(True, 162.0)
    (rep,) = _of(acts, Report)
    assert rep.record["outcome"] == "rolled_back" and rep.record["rolled_back"] is True
    assert rep.record["live_ratio"]["sun_shaft"] == pytest.approx(1.5, rel=0.1)
    assert sup.state is State.IDLE


def test_no_live_data_after_push_rolls_back() -> None:
    sup = Supervisor(CFG)
    _live(sup, 100.0, 140.0, 0.02)
    _to_refit(sup)
    sup.fit_done(_fit(better=True), 140.0)
    sup.push_done(True, 141.0)
    (rb,) = _of(sup.tick(161.5), Rollback)
    assert "cannot verify" in rb.reason


def test_alarm_while_waiting_restarts_the_wait() -> None:
    sup = Supervisor(CFG)
    sup.on_alarm(_alarm(100.0, 102.0), 102.0)
    sup.on_alarm(_alarm(110.0, 111.0, "carrier3"), 111.0)
    assert sup.tick(131.0) == []  # 30 s after the first change is not enough now
    (req,) = _of(sup.tick(140.5), RequestFit)
    assert req.estimation[0] == pytest.approx(111.0)
    assert set(req.outputs) == {"sun_shaft", "carrier3"}


def test_alarm_during_refit_starts_the_next_episode() -> None:
    sup = Supervisor(CFG)
    _to_refit(sup)
    acts = sup.on_alarm(_alarm(135.0, 137.0), 137.0)
    assert _of(acts, Diagnostic)[0].level == 1 and sup.state is State.REFITTING
    acts = sup.fit_done(_fit(better=False), 140.0)
    assert [r.record["outcome"] for r in _of(acts, Report)] == ["not_better"]
    assert sup.state is State.WAITING and sup.episodes == 2
    # an alarm whose change lies before the episode's data does not start another one
    sup2 = Supervisor(CFG)
    _to_refit(sup2)
    sup2.on_alarm(_alarm(90.0, 137.0), 137.0)
    sup2.fit_done(_fit(better=False), 140.0)
    assert sup2.state is State.IDLE and sup2.episodes == 1


@pytest.mark.parametrize("where", ["fit", "push", "rollback"])
def test_timeouts(where: str) -> None:
    sup = Supervisor(CFG)
    _live(sup, 100.0, 140.0, 0.02)
    _to_refit(sup)
    if where == "fit":
        (rep,) = _of(sup.tick(131.0 + 51.0), Report)
        assert rep.record["outcome"] == "fit_timeout" and not rep.record["pushed"]
        return
    sup.fit_done(_fit(better=True), 140.0)
    acts = sup.tick(146.0)  # push not confirmed within 5 s: roll back in case it landed
    (rb,) = _of(acts, Rollback)
    assert rb.parameters == OLD and sup.state is State.ROLLING_BACK
    if where == "push":
        (rep,) = _of(sup.rollback_done(True, 147.0), Report)
        assert rep.record["outcome"] == "push_timeout"
    else:
        (rep,) = _of(sup.tick(152.0), Report)
        assert rep.record["outcome"] == "rollback_failed"
        assert _of(sup.tick(153.0), Report) == []


def test_failures_and_ignored_events() -> None:
    sup = Supervisor(CFG)
    assert _of(sup.fit_done(_fit(True), 1.0), Diagnostic)[0].level == 1  # ignored
    assert _of(sup.push_done(True, 1.0), Diagnostic)[0].level == 1
    _to_refit(sup)
    (rep,) = _of(sup.fit_done(FitOutcome(error="bag unreadable"), 140.0), Report)
    assert rep.record["outcome"] == "fit_failed" and rep.record["reason"] == "bag unreadable"
    _to_refit(sup, 200.0)
    (rep,) = _of(sup.fit_done(FitOutcome(new_errors=np.zeros((5, 2)),
                                         current_errors=np.zeros((5, 2))), 240.0), Report)
    assert rep.record["outcome"] == "fit_failed" and "N >= 10" in rep.record["reason"]
    _to_refit(sup, 300.0)
    sup.fit_done(_fit(True), 340.0)
    (rep,) = _of(sup.push_done(False, 341.0, "model node refused k"), Report)
    assert rep.record["outcome"] == "push_failed"
    assert sup.status()["last_outcome"] == "push_failed" and sup.status()["episodes"] == "3"


@pytest.mark.parametrize(("field", "value", "needle"), [
    ("watch_s", 0.0, "supervisor.watch_s"),
    ("alpha", 1.5, "supervisor.alpha"),
    ("min_post_change_s", 1.5, "supervisor.min_post_change_s"),
    ("full_post_change_s", 4.0, "supervisor.full_post_change_s"),
    ("full_validation_s", -1.0, "supervisor.full_validation_s"),
    ("min_watch_samples", 0, "supervisor.min_watch_samples"),
    ("rollback_tolerance", -0.1, "supervisor.rollback_tolerance"),
])
def test_config_errors_name_the_parameter(field: str, value: object, needle: str) -> None:
    with pytest.raises(SupervisorError, match=needle):
        SupervisorConfig(**{field: value}).validated()  # type: ignore[arg-type]


def test_bad_alarm_and_residual() -> None:
    sup = Supervisor(CFG)
    with pytest.raises(SupervisorError, match="alarm.change_s"):
        sup.on_alarm({"stamp_s": 1.0}, 1.0)
    with pytest.raises(SupervisorError, match="residual"):
        sup.observe(1.0, [0.0])


# ------------------------------------------------------------- the node's refit (pure parts)
def test_node_parameters_are_the_config_fields() -> None:
    params = SupervisorConfig.parameters()
    assert params["watch_s"] == 60.0 and params["min_watch_samples"] == 1000
    assert "names" not in params
    assert SupervisorConfig(**params).validated() == SupervisorConfig()


def test_changes_and_plain_values() -> None:
    import array

    from dvt_identify.refit import changes as _changes
    from dvt_identify.refit import plain_value

    assert plain_value(array.array("d", [1.0, 2.0])) == [1.0, 2.0]
    assert plain_value(np.array([3.0])) == [3.0] and plain_value(None) is None
    assert plain_value("x") == "x" and plain_value(True) is True
    cur = {"M": None, "D": [1.0, 0.0, 0.0, 1.0], "effects": "", "band_gain": None}
    new = {"M": [1.0, 0.0, 0.0, 2.0], "D": (1.0, 0.0, 0.0, 1.0),
           "effects": '[{"kind": "coulomb", "member": [0, 1], "Fc": 0.2}]', "band_gain": []}
    ch = {c["parameter"]: c for c in _changes(cur, new)}
    assert set(ch) == {"M", "effects"}  # D unchanged, band_gain empty both times
    assert ch["M"]["before"] is None and ch["M"]["after"] == [1.0, 0.0, 0.0, 2.0]
    assert ch["effects"]["before"] == [] and ch["effects"]["after"] == ["coulomb"]


def test_validation_errors_of_the_plants_own_model_are_small() -> None:
    from dvt_identify.refit import validation_errors
    from dvt_model.hybrid import HybridModel
    from dvt_model.params import load_parameters

    model = HybridModel.from_params(load_parameters("physical"))
    n = 2000
    t = np.arange(n) * 1e-3
    im = np.repeat([-6.0, 2.0, 8.0, 0.0], n // 4)
    ib = np.zeros((n, 3))
    r = model.simulate(t, im, ib, omega0=(0.0, 0.0))
    stamps = 1_700_000_000 * 10**9 + np.round(t * 1e9).astype(np.int64)
    cur = np.column_stack([im, ib])
    same = validation_errors({"params": "physical"}, stamps, r.omega, cur)
    other = validation_errors({"params": "thesis"}, stamps, r.omega, cur)
    assert same.shape == (n, 2) and np.sqrt(np.mean(same ** 2)) < 1e-3
    assert np.sqrt(np.mean(other ** 2)) > 100 * np.sqrt(np.mean(same ** 2))


def test_refit_names_a_window_without_data(tmp_path: Any) -> None:
    from dvt_identify.refit import refit
    from dvt_model.recording import write_run

    n = 3000
    stamps = 1_700_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 1_000_000
    bag = write_run(tmp_path / "snap", stamps, np.zeros((n, 2)), np.zeros((n, 4)))
    req = RequestFit(1, (1_700_000_010.0, 1_700_000_020.0), (1_700_000_020.0, 1_700_000_025.0),
                     ("sun_shaft",))
    out = refit(bag, req, {"params": "physical"}, tmp_path / "work")
    assert "0 estimation and 0 validation samples" in out.error
    assert out.summary["samples"] == {"estimation": 0, "validation": 0}
    missing = refit(tmp_path / "nope", req, {}, tmp_path / "work2")
    assert "BagError" in missing.error and "nope" in missing.error


def test_episode_markdown_summarises_the_record() -> None:
    sup = Supervisor(CFG)
    _live(sup, 100.0, 140.0, 0.02)
    _to_refit(sup)
    acts = sup.fit_done(_fit(better=False), 140.0)
    (rep,) = _of(acts, Report)
    md = episode_markdown(rep.record)
    assert md.startswith("# Episode 1: not_better")
    assert "accepted effects: none" in md and "* 102.000 waiting: change on sun_shaft" in md


def test_estimation_starts_after_change_plus_settle_when_detected_early() -> None:
    sup = Supervisor(CFG)
    sup.on_alarm(_alarm(100.0, 100.5), 100.5)  # detected before change + settle
    assert sup.tick(129.9) == []
    (req,) = _of(sup.tick(130.0), RequestFit)  # change + min_post_change_s
    assert req.estimation == pytest.approx((101.0, 120.0))
    sup2 = Supervisor(CFG)
    sup2.on_alarm(_alarm(100.0, 103.0), 103.0)  # change_s 3 s early: wait longer
    assert sup2.tick(131.9) == []
    (req2,) = _of(sup2.tick(132.0), RequestFit)
    assert req2.estimation == pytest.approx((103.0, 122.0))


def test_alarms_from_before_the_start_are_ignored() -> None:
    """The alarm topic is latched: a restarted identifier gets an earlier run's alarms first."""
    sup = Supervisor(CFG)
    sup.ignore_before_s = 500.0
    acts = sup.on_alarm(_alarm(100.0, 102.0), 600.0)
    assert sup.state is State.IDLE and sup.episodes == 0 and sup.ignored_alarms == 1
    (diag,) = _of(acts, Diagnostic)
    assert "before this supervisor started" in diag.message and "ignored" in diag.message
    sup.on_alarm(_alarm(600.0, 601.0), 601.0)
    assert sup.state is State.WAITING and sup.episodes == 1


# ------------------------------------------------------------------- the two refit stages
CFG2 = SupervisorConfig(min_post_change_s=5.0, settle_s=0.5, validation_s=1.5,
                        full_post_change_s=30.0, full_validation_s=10.0,
                        max_estimation_s=100.0, watch_s=20.0, watch_settle_s=2.0,
                        baseline_s=10.0, min_watch_samples=500, fit_timeout_s=50.0,
                        push_timeout_s=5.0)


def test_first_refit_holds_the_structure_then_the_full_refit_when_not_pushed() -> None:
    sup = Supervisor(CFG2)
    sup.on_alarm(_alarm(100.0, 100.1), 100.1)
    assert sup.tick(104.9) == []
    (first,) = _of(sup.tick(105.0), RequestFit)  # change + min_post_change_s
    assert first.stage == STAGE_EFFECTS
    assert first.estimation == pytest.approx((100.5, 103.5))  # change + settle .. now - 1.5
    assert first.validation == pytest.approx((103.5, 105.0))
    acts = sup.fit_done(_fit(better=False, n=1500), 108.0)
    assert sup.state is State.WAITING and not _of(acts, Report) and not _of(acts, Push)
    (diag,) = _of(acts, Diagnostic)
    assert "not_better" in diag.message and "full refit" in diag.message
    assert sup.tick(129.9) == []
    (full,) = _of(sup.tick(130.0), RequestFit)  # change + full_post_change_s
    assert full.stage == STAGE_FULL and full.episode == first.episode
    assert full.estimation == pytest.approx((100.5, 120.0))
    assert full.validation == pytest.approx((120.0, 130.0))  # full_validation_s held out
    (rep,) = _of(sup.fit_done(_fit(better=False, seed=4), 140.0), Report)
    r = rep.record
    assert r["outcome"] == "not_better" and r["stage"] == STAGE_FULL
    assert [(s["stage"], s["decision"]) for s in r["stages"]] == [
        (STAGE_EFFECTS, "not_better"), (STAGE_FULL, "not_better")]
    assert r["stages"][0]["validation"] == pytest.approx((103.5, 105.0))
    assert r["estimation"] == pytest.approx((100.5, 120.0))  # the last refit's
    md = episode_markdown(r)
    assert "* refits: effects: not_better" in md and "; full: not_better" in md


def test_a_pushed_first_refit_ends_the_episode_without_a_full_refit() -> None:
    sup = Supervisor(CFG2)
    _live(sup, 100.0, 108.0, 0.02)
    sup.on_alarm(_alarm(100.0, 100.1), 100.1)
    sup.tick(105.0)
    (push,) = _of(sup.fit_done(_fit(better=True, n=1500), 107.0), Push)
    assert push.parameters == NEW
    sup.push_done(True, 107.2)
    _live(sup, 107.2, 128.0, 0.01, seed=2)
    (rep,) = _of(sup.tick(127.5), Report)
    assert rep.record["outcome"] == "confirmed" and rep.record["stage"] == STAGE_EFFECTS
    assert [s["decision"] for s in rep.record["stages"]] == ["push"]


def test_alarm_while_waiting_for_the_full_refit_starts_over_with_the_first() -> None:
    sup = Supervisor(CFG2)
    sup.on_alarm(_alarm(100.0, 100.1), 100.1)
    sup.tick(105.0)
    sup.fit_done(_fit(better=False, n=1500), 106.0)
    assert sup.state is State.WAITING
    sup.on_alarm(_alarm(110.0, 110.2, "carrier3"), 110.2)  # another regime
    assert sup.tick(114.9) == []
    (req,) = _of(sup.tick(115.0), RequestFit)
    assert req.stage == STAGE_EFFECTS and req.estimation[0] == pytest.approx(110.5)


def test_failed_first_refit_goes_on_but_a_crashed_one_ends_the_episode() -> None:
    sup = Supervisor(CFG2)
    sup.on_alarm(_alarm(100.0, 100.1), 100.1)
    sup.tick(105.0)
    sup.fit_done(FitOutcome(error="DataError: too short"), 106.0)
    assert sup.state is State.WAITING  # the longer window may do
    (full,) = _of(sup.tick(130.0), RequestFit)
    assert full.stage == STAGE_FULL
    sup2 = Supervisor(CFG2)
    sup2.on_alarm(_alarm(100.0, 100.1), 100.1)
    sup2.tick(105.0)
    acts = sup2.fit_done(FitOutcome(error="the refit process (pid 7) died during the refit "
                                          "(killed by signal SIGKILL)", crashed=True), 106.0)
    (rep,) = _of(acts, Report)
    assert sup2.state is State.IDLE and rep.record["outcome"] == "refit_crashed"
    assert "SIGKILL" in rep.record["reason"] and not rep.record["pushed"]
    assert _of(acts, Diagnostic)[0].level == 2


def test_no_full_refit_when_it_is_off() -> None:
    sup = Supervisor(SupervisorConfig(full_post_change_s=0.0))
    sup.on_alarm(_alarm(100.0, 100.1), 100.1)
    (req,) = _of(sup.tick(105.0), RequestFit)  # the defaults: 5 s after the change
    assert req.stage == STAGE_EFFECTS
    assert req.validation[1] - req.validation[0] == pytest.approx(1.5)
    (rep,) = _of(sup.fit_done(_fit(better=False, n=1500), 107.0), Report)
    assert rep.record["outcome"] == "not_better" and len(rep.record["stages"]) == 1
