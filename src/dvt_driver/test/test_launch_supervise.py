"""Unit tests of ``dvt-launch --supervise`` (argument handling, episode reports) and of the
``watch`` experiment it runs (pure: no ROS, no processes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dvt_driver.errors import ExperimentError
from dvt_driver.run.experiment_core import Gear, MotorCurrent, build
from dvt_driver.system.bench_loop import (
    LIVE_SUPERVISOR,
    REALTIME_PRIORITY,
    SNAPSHOT_MARGIN_S,
    chain_figures,
    episode_launch_args,
    episode_reports,
    live_supervisor,
)
from dvt_driver.system.cpuload import CpuSampler
from dvt_driver.system.launch import episode_line
from dvt_driver.system.launch_args import (
    IDENTIFY_DIR,
    SUPERVISE_RING_MINUTES,
    parse_args,
    realtime_priorities,
)


def test_supervise_implies_a_ring_and_keeps_a_given_one() -> None:
    args = parse_args(["sim", "--supervise"])
    assert args.supervise and args.ring_minutes == SUPERVISE_RING_MINUTES
    assert parse_args(["sim", "--supervise", "--ring-minutes", "3"]).ring_minutes == 3.0
    args = parse_args(["sim", "--supervise", "--episodes", "2",
                       "--identify-param", "supervisor.watch_s:=15.0"])
    assert args.episodes == 2 and args.identify_param == ["supervisor.watch_s:=15.0"]
    assert parse_args(["sim"]).ring_minutes is None


@pytest.mark.parametrize(("argv", "message"), [
    (["sim", "--episodes", "1"], "--identify-param/--episodes need --supervise"),
    (["sim", "--identify-param", "a:=1"], "--identify-param/--episodes need --supervise"),
    (["sim", "--supervise", "--no-model"], "--supervise needs the model node"),
    (["sim", "--supervise", "--episodes", "0"], "--episodes: expected an integer >= 1, got 0"),
    (["sim", "--supervise", "--identify-param", "watch"],
     "--identify-param: expected NAME:=VALUE, got 'watch'"),
    (["sim", "--experiment", "watch", "--experiment-set", "duration=-1"],
     "watch: duration: expected 0 < S <= 86400 s, got -1"),
])
def test_supervise_refuses_bad_arguments(argv: list[str], message: str,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        parse_args(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_episode_reports_are_found_in_episode_order(tmp_path: Path) -> None:
    base = tmp_path / "episodes"
    base.mkdir()
    for name in ("episode-10", "episode-2", "episode-1-2", "episode-1"):
        (base / f"{name}.json").write_text(json.dumps({"episode": 1}))
    (base / "episode-1.md").write_text("# not a report\n")
    assert [p.stem for p in episode_reports(tmp_path)] == [
        "episode-1", "episode-1-2", "episode-2", "episode-10"]
    assert episode_reports(tmp_path / "nowhere") == []


def test_episode_line_names_outcome_times_and_push() -> None:
    line = episode_line({"episode": 1, "outcome": "confirmed", "reason": "ratio 0.3",
                         "change_s": 12.5, "detected_s": 12.75, "outputs": ["sun_shaft"],
                         "pushed": True, "push_s": 40.0, "rolled_back": False,
                         "live_ratio": {"sun_shaft": 0.31, "carrier3": 0.5}})
    assert line.startswith("episode 1: confirmed (ratio 0.3); change at 12.500 s, detected at "
                           "12.750 s on sun_shaft; pushed True at 40.000 s")
    assert "live RMS ratio sun_shaft 0.31, carrier3 0.5" in line
    assert "pushed False at - s" in episode_line({"pushed": False})


def test_episode_launch_args_parse_and_configure_the_loop(tmp_path: Path) -> None:
    argv = episode_launch_args(tmp_path / "run", rate=250.0, change_at=40.0, duration=150.0)
    args = parse_args(argv)
    assert args.supervise and args.experiment == "watch" and args.rate == 250.0
    assert args.change_at == ["40:friction_step"] and args.params == "physical"
    assert args.ring_minutes >= 150.0 / 60.0  # the ring holds the whole run (the figure's)
    given = dict(kv.split(":=", 1) for kv in args.identify_param)
    assert given["supervisor.fit_decimate"] == "2"  # the refit at about 100 Hz
    for k, v in live_supervisor(250.0).items():
        assert float(given[f"supervisor.{k}"]) == v
    assert IDENTIFY_DIR == "identify"


def test_watch_repeats_neutral_excitation_for_the_duration() -> None:
    e = build("watch", seed=3, duration=40.0)
    assert e.duration == pytest.approx(41.5)  # + the 1.5 s stop
    labels = [p.label for p in e.phases]
    assert labels[:4] == ["neutral-prbs", "neutral-multisine", "neutral-prbs",
                          "neutral-multisine"] and labels[-1] == "stop"
    assert e.phases[-2].end == pytest.approx(40.0)  # the last cycle cut at the duration
    assert not any(isinstance(s.command, Gear) and s.command.gear for s in e.steps)
    # fresh signals every cycle: the second PRBS switches at other times than the first
    def switches(t0: float, t1: float) -> list[float]:
        return [round(s.t - t0, 6) for s in e.steps
                if isinstance(s.command, MotorCurrent) and t0 <= s.t < t1]
    first, second = switches(0.0, 6.0), switches(11.0, 17.0)
    assert first and second and first != second
    assert build("watch", seed=3, duration=40.0).steps == e.steps  # deterministic


def test_watch_with_gears_and_its_errors() -> None:
    e = build("watch", duration=30.0, gears=[1, 2])
    assert [p.label for p in e.phases][:6] == ["neutral-prbs", "neutral-multisine",
                                               "gear1-shift", "gear1-prbs", "gear2-shift",
                                               "gear2-prbs"]
    gears = [s.command.gear for s in e.steps if isinstance(s.command, Gear)]
    assert gears[:4] == [0, 1, 2, 0]  # back to neutral for the next cycle
    with pytest.raises(ExperimentError, match="watch: gears: expected gears 1..3, got 4"):
        build("watch", gears=[4])
    with pytest.raises(ExperimentError, match="watch: clock: expected a time > 0 s, got 0"):
        build("watch", clock=0)
    with pytest.raises(ExperimentError, match="duration: expected 0 < S <= 86400 s"):
        build("watch", duration=float("nan"))


# ------------------------------------------------------------------ --realtime, the figures
def test_realtime_priorities_put_the_sample_path_first() -> None:
    assert realtime_priorities(None) == {} and realtime_priorities(0) == {}
    prio = realtime_priorities(10)
    assert prio["model"] == 11 and prio["plant"] == prio["driver"] == 10
    assert prio["ring"] == prio["recorder"] == prio["experiment"] == 9
    assert "identify" not in prio and "foxglove" not in prio  # the normal scheduler
    assert realtime_priorities(1)["ring"] == 1  # never below the lowest real-time priority
    assert parse_args(["sim", "--realtime", "20"]).realtime == 20
    assert parse_args(["sim"]).realtime is None


@pytest.mark.parametrize("value", ["0", "99", "-3"])
def test_realtime_out_of_range_is_refused(value: str, capsys: pytest.CaptureFixture[str]
                                          ) -> None:
    with pytest.raises(SystemExit) as exc:
        parse_args(["sim", "--realtime", value])
    assert exc.value.code == 2
    assert f"--realtime: expected a priority 1..98, got {value}" in capsys.readouterr().err


def test_episode_runs_are_real_time_at_1khz_with_a_short_snapshot_margin(tmp_path: Path
                                                                          ) -> None:
    args = parse_args(episode_launch_args(tmp_path / "run"))
    assert args.rate == 1000.0 and args.realtime == REALTIME_PRIORITY
    given = dict(kv.split(":=", 1) for kv in args.record_param)
    assert float(given["snapshot_margin_s"]) == SNAPSHOT_MARGIN_S
    assert parse_args(episode_launch_args(tmp_path / "r2", realtime=None)).realtime is None


def test_chain_figures_count_drops_gaps_and_latency() -> None:
    period = 1e-3
    stamps = 100.0 + np.arange(2000) * period
    stamps = np.delete(stamps, np.arange(500, 505))  # 5 samples the chain lost
    lat = np.full(stamps.size, 0.2)
    lat[:20] = 5.0  # 1 % slow
    lat[100:103] = np.nan  # 3 the model node dropped
    f = chain_figures(stamps, lat, 100.0, 102.0, period)
    assert f["samples"] == 1995 and f["chain_missing"] == 5 and f["model_dropped"] == 3
    assert f["model_latency_ms"]["p50"] == pytest.approx(0.2)
    assert f["model_latency_ms"]["max"] == pytest.approx(5.0)
    assert f["model_latency_ms"]["p99"] > 0.2  # the slow 1 % reaches the 99th percentile
    half = chain_figures(stamps, lat, 100.0, 100.4, period)  # before the gap
    assert half["chain_missing"] == 0 and half["samples"] == 400
    empty = chain_figures(stamps, lat, 200.0, 201.0, period)
    assert empty["samples"] == 0 and empty["model_latency_ms"]["p99"] is None


def test_cpu_sampler_tells_the_chain_from_the_others() -> None:
    import subprocess
    import sys
    import time

    sampler = CpuSampler(period=0.2)
    sampler.start()
    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\n"
    chain = subprocess.Popen([sys.executable, "-c", burn])
    sampler.set_root(chain.pid)
    other = subprocess.Popen([sys.executable, "-c", burn])
    chain.wait(timeout=30)
    other.wait(timeout=30)
    time.sleep(0.3)
    f = sampler.stop()
    labels = list(f["chain_cpu_percent"])
    assert len(labels) == 1 and labels[0].startswith("python -c"), f
    assert f["others_cpu_percent"] > 0.0 and f["seconds"] > 0.5
    assert any(o["process"].startswith("python -c") for o in f["others_top"]), f


def test_live_windows_hold_enough_samples_for_the_refit_at_any_rate() -> None:
    from dvt_identify.description import load_description

    need = load_description("dvt").checks.min_samples
    assert live_supervisor(1000.0) == LIVE_SUPERVISOR
    assert LIVE_SUPERVISOR["min_post_change_s"] == 4.0
    assert LIVE_SUPERVISOR["validation_s"] == 1.0
    for rate in (100.0, 250.0, 500.0, 1000.0, 2000.0):
        sup = live_supervisor(rate)
        est = sup["min_post_change_s"] - sup["settle_s"] - sup["validation_s"]
        assert sup["validation_s"] * rate >= need and est * rate >= need, (rate, sup)
    assert live_supervisor(250.0)["validation_s"] == 2.5  # 1 s: 250 samples, too few
