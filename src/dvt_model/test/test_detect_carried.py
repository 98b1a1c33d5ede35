"""A colour carried from an earlier run ("The first minute" in docs/loop.md), pure: what the
detector does with it, when its own colour replaces it, and what a bad carried colour gives."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from dvt_model.detect import (
    CARRIED_FORMAT,
    CarriedColour,
    ChangeDetector,
    ColourKeeper,
    DetectorConfig,
)
from dvt_model.errors import ParameterError

RATE = 100.0  # Hz: the model node's detector rate (10-ms blocks)


def config(colour_s: float = 120.0) -> DetectorConfig:
    return DetectorConfig(sample_rate_hz=RATE, colour_s=colour_s, colour_lag_s=1.0).validated()


def coloured(rng: np.random.Generator, n: int, pole: float = 0.97) -> np.ndarray:
    """``(n, 2)`` AR(1) of ``pole`` (a 0.33-s time constant at 100 Hz) plus white noise of the
    same variance: a 20-s window's ARMA(1, 1) whitens it, a carried AR(p) too."""
    slow = lfilter([1.0], [1.0, -pole], rng.standard_normal((n + 2000, 2))
                   * np.sqrt(1 - pole ** 2), axis=0)[2000:]
    return 0.01 * np.asarray(slow + rng.standard_normal((n, 2)))


def run(det: ChangeDetector, x: np.ndarray, t0: float = 0.0) -> list[tuple[int, bool, bool]]:
    """Feed ``x``; ``(sample, colour_carried, learning)`` wherever either changes."""
    seen = [(-1, det.colour_carried, det.learning)]
    for j, row in enumerate(x.tolist()):
        det.update(t0 + j / RATE, row)
        if (det.colour_carried, det.learning) != seen[-1][1:]:
            seen.append((j, det.colour_carried, det.learning))
    return seen


def earlier_run(seed: int = 1) -> CarriedColour:
    det = ChangeDetector(config())
    run(det, coloured(np.random.default_rng(seed), round(130 * RATE)))
    carried = det.carry("model-a")
    assert carried is not None
    return carried


def test_only_a_colour_on_the_full_history_is_carried() -> None:
    det = ChangeDetector(config())
    x = coloured(np.random.default_rng(2), round(130 * RATE))
    run(det, x[: round(100 * RATE)])
    assert det.colour_in_use and not det.colour_complete and det.carry() is None  # 60 s of 120
    run(det, x[round(100 * RATE):], 100.0)
    carried = det.carry("model-a")
    assert carried is not None and carried.model == "model-a"
    assert carried.samples == round(120 * RATE) and carried.order_max == config().colour_order_max
    assert carried.names == tuple(config().names) and carried.sample_rate_hz == RATE
    assert all(0 < len(c) <= carried.order_max for c in carried.coef)
    assert ChangeDetector(config()).carry() is None  # nothing learned yet


def test_a_carried_colour_whitens_the_first_window_until_the_own_history_is_full() -> None:
    """From the first reference window the samples are whitened by the carried colour
    (``ar_order`` > 0, ``h`` designed over the window's own long-run ratio); the own partial
    colours (60 s) do not replace it; the own full one (120 s) starts a new window."""
    carried = earlier_run()
    det = ChangeDetector(config(), carried)
    assert det.colour_carried and det.status()["colour_carried"] == "true"
    seen = run(det, coloured(np.random.default_rng(3), round(150 * RATE)))
    # learning 20 s, testing with the carried colour, the own full colour at 120 s: a new
    # window (learning) without the carried one, testing again 20 s later
    assert seen == [(-1, True, True), (round(20 * RATE) - 1, True, False),
                    (round(120 * RATE) - 1, False, True),
                    (round(140 * RATE) - 1, False, False)], seen
    assert det.colour_complete and det.status()["colour_carried"] == "false"
    assert det.counters.colour_fits == 1  # only the full one: no partial colour was fitted
    own = det.carry("model-a")
    assert own is not None and own != carried and own.samples == round(120 * RATE)


def test_the_carried_colours_threshold_is_designed_on_each_window() -> None:
    """Each window it whitens allows for the slow colour the carried colour leaves there
    (``lam``): a colour carried from a white run leaves the slow part of this one, and its
    thresholds rise above those of a colour carried from a run like this one."""
    right = earlier_run()
    white = replace(right, coef=((), ()))
    x = coloured(np.random.default_rng(4), round(30 * RATE))
    dets = [ChangeDetector(config(), c) for c in (right, white)]
    for det in dets:
        run(det, x)
        assert not det.learning and det.colour_in_use
    lam_right = [r.lam for r in dets[0].references]
    lam_white = [r.lam for r in dets[1].references]
    assert all(w > 2.0 * r for w, r in zip(lam_white, lam_right, strict=True)), (
        lam_right, lam_white)
    assert all(r.order > 0 for r in dets[0].references)


def test_an_alarm_keeps_the_carried_colour() -> None:
    det = ChangeDetector(config(), earlier_run())
    x = coloured(np.random.default_rng(5), round(60 * RATE))
    x[round(30 * RATE):, 1] += 0.2  # a 14-sigma step on carrier 3 after 30 s (the colour
    # leaves it a gain of about 0.14: whitened, 2.4 innovation sigma)
    run(det, x)
    assert det.counters.alarms >= 1 and det.colour_carried


def test_the_file_round_trip_and_its_errors_name_path_and_field(tmp_path: Path) -> None:
    carried = earlier_run()
    path = tmp_path / "colour.json"
    carried.save(path)
    assert CarriedColour.load(path) == carried
    assert not (tmp_path / "colour.json.tmp").exists()
    doc = json.loads(path.read_text())
    assert doc["format"] == CARRIED_FORMAT
    bad: list[tuple[object, str]] = [
        ({**doc, "format": "other/1"}, "format: expected 'dvt-detector-colour/1', got 'other/1'"),
        ({k: v for k, v in doc.items() if k != "samples"}, "field 'samples' missing"),
        ({**doc, "coef": [doc["coef"][0]]}, "coef: expected 2 coefficient lists"),
        ({**doc, "coef": [[0.5, 0.6], []]}, r"coef\[sun_shaft\]: not stationary"),
        ({**doc, "coef": [[float("nan")], []]}, r"coef\[sun_shaft\]: expected at most"),
        ({**doc, "samples": 0}, "samples: expected a positive integer, got 0"),
        ({**doc, "sample_rate_hz": "fast"}, "sample_rate_hz: expected a positive number"),
        ([1, 2], "expected a JSON object, got list")]
    for data, needle in bad:
        path.write_text(json.dumps(data))
        with pytest.raises(ParameterError, match=needle) as err:
            CarriedColour.load(path)
        assert str(path) in str(err.value)
    path.write_text("{not json")
    with pytest.raises(ParameterError, match="cannot read a carried colour"):
        CarriedColour.load(path)
    with pytest.raises(ParameterError, match="cannot read a carried colour"):
        CarriedColour.load(tmp_path / "missing.json")


def test_a_colour_of_other_settings_or_another_model_is_refused() -> None:
    carried = earlier_run()
    cfg = config()
    assert carried.mismatch(cfg, "model-a") is None
    assert "the model in use 'model-b'" in str(carried.mismatch(cfg, "model-b"))
    assert "sample_rate_hz 100" in str(carried.mismatch(replace(cfg, sample_rate_hz=50.0)))
    assert "order_max" in str(carried.mismatch(replace(cfg, colour_lag_s=0.5)))
    assert "fitted on less than detector.colour_s" in str(
        carried.mismatch(replace(cfg, colour_s=300.0)))
    assert "learns no colour" in str(carried.mismatch(replace(cfg, colour_s=0.0)))
    with pytest.raises(ParameterError, match="carried colour: outputs"):
        ChangeDetector(replace(cfg, names=("a", "b", "c")), carried)


# -- the keeper: the file between runs (the model node's detector.colour_file) ------------------

def test_the_keeper_writes_the_own_full_colour_and_the_next_start_carries_it(
        tmp_path: Path) -> None:
    path = tmp_path / "colour.json"
    cfg = config()
    keeper = ColourKeeper(path, "model-a")
    carried, line, warn = keeper.load(cfg)
    assert carried is None and "no colour carried yet" in line and str(path) in line
    assert not warn
    det = ChangeDetector(cfg)
    x = coloured(np.random.default_rng(6), round(190 * RATE))
    written = []  # (sample, saves) whenever a file is written
    for j, row in enumerate(x.tolist()):
        det.update(j / RATE, row)
        assert keeper.after_update(det) is None
        if not written or keeper.saves != written[-1][1]:
            written.append((j, keeper.saves))
    # the colour fits at 60, 120, 180 s; the full one (120 s of history) from 120 s on
    assert written == [(0, 0), (round(120 * RATE) - 1, 1), (round(180 * RATE) - 1, 2)], written
    carried, line, warn = ColourKeeper(path, "model-a").load(cfg)
    assert carried == det.carry("model-a") and "colour carried in" in line and not warn
    nxt = ChangeDetector(cfg, carried)
    assert nxt.colour_carried
    # a carried colour in use is not written again: nothing new
    again = ColourKeeper(path, "model-a")
    for j, row in enumerate(x[: round(70 * RATE)].tolist()):
        nxt.update(j / RATE, row)
        again.after_update(nxt)
    assert again.saves == 0 and nxt.counters.colour_fits == 0


def test_the_keeper_writes_nothing_until_the_new_model_had_colour_s(tmp_path: Path) -> None:
    """After a model change the colour still holds the old model's residual for up to
    ``colour_s``: no file until the new model has run that long."""
    path = tmp_path / "colour.json"
    cfg = config()
    keeper = ColourKeeper(path, "model-a")
    det = ChangeDetector(cfg)
    x = coloured(np.random.default_rng(7), round(300 * RATE))
    for j, row in enumerate(x.tolist()):
        t = j / RATE
        if j == round(130 * RATE):  # a push at 130 s (after the first file)
            det.reset()
            keeper.model_changed("model-b")
            saves = keeper.saves
        det.update(t, row)
        keeper.after_update(det)
        if 130 * RATE <= j < 250 * RATE - 1:  # 120 s of model b (its two chunks, the one
            # in progress at the push dropped): nothing written for it before
            assert keeper.saves == saves, j
    assert saves == 1 and keeper.saves > saves
    assert CarriedColour.load(path).model == "model-b"


def test_the_keeper_says_why_a_file_is_not_used_and_keeps_it(tmp_path: Path) -> None:
    path = tmp_path / "colour.json"
    earlier_run().save(path)
    text = path.read_text()
    carried, line, warn = ColourKeeper(path, "model-b").load(config())
    assert carried is None and warn and "not used, learning the colour anew" in line
    assert "the model in use 'model-b'" in line and str(path) in line
    path.write_text("{}")
    carried, line, warn = ColourKeeper(path, "model-a").load(config())
    assert carried is None and warn and "format" in line and str(path) in line
    assert path.read_text() == "{}"  # left as it is
    path.write_text(text)
    bad_dir = tmp_path / "missing-dir" / "colour.json"
    keeper = ColourKeeper(bad_dir, "model-a")
    det = ChangeDetector(config())
    errors = []
    for j, row in enumerate(coloured(np.random.default_rng(8), round(125 * RATE)).tolist()):
        det.update(j / RATE, row)
        err = keeper.after_update(det)
        if err is not None:
            errors.append(err)
    assert len(errors) == 1 and "cannot write the colour" in errors[0] and str(bad_dir) in errors[0]
    assert keeper.saves == 0 and det.carry() is not None  # the detector goes on


def test_the_keepers_path_expands_the_home_directory(monkeypatch: pytest.MonkeyPatch,
                                                      tmp_path: Path) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    keeper = ColourKeeper("~/colour.json", "model-a")
    assert keeper.path == tmp_path / "colour.json"


def test_each_chunk_measures_the_carried_colour_again_without_a_new_window() -> None:
    """At each chunk's end while the colour is carried (60 and 120 s of 180), the ratio its
    whitening leaves is measured again on that chunk (60 s, out of sample) and the reference in
    use is whitened again with it: testing goes on (no new window), the threshold changes."""
    cfg = config(180.0)
    carried = replace(earlier_run(), samples=cfg.colour_samples)
    det = ChangeDetector(cfg, carried)
    x = coloured(np.random.default_rng(9), round(130 * RATE))
    seen = []  # (sample, learning, lam per output) at each chunk end
    for j, row in enumerate(x.tolist()):
        det.update(j / RATE, row)
        if j in (round(60 * RATE) - 2, round(60 * RATE) - 1, round(120 * RATE) - 1):
            seen.append((j, det.learning, [r.lam for r in det.references],
                         [r.h for r in det.references]))
    before, at60, at120 = seen
    assert not at60[1] and not at120[1]  # testing throughout
    assert at60[3] != before[3] and at120[3] != at60[3]  # whitened again: other thresholds
    assert det.colour_carried and det.counters.learned == 1  # the one window after the start
