"""``--select-on cv``: effects chosen by cross-validation, leave-one-bag-out across the
estimation bags or across contiguous blocks of a single one; the test bags take no part.

The toy is the cart of ``conftest.py`` (``M v' = F - Fv v``, M 2.5 kg, Fv 4 N s/m, random
force steps, 1 % noise), read with or without a constant sensor offset of 0.3 m/s (about a
third of the speed's standard deviation) and with one candidate, ``sensor_offset``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest

from dvt_identify import pipeline
from dvt_identify.data import Segment
from dvt_identify.description import Description
from dvt_identify.errors import DataError
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.stages import bag_of, cv_folds

CFG = LoopConfig(starts=1, refit_starts=1, drift_windows=0)
OFFSET = 0.3
Record = Callable[..., Segment]


def bags(record: Record, d: Description, offset: float, seeds: Sequence[int] = (11, 12)
         ) -> list[Segment]:
    return [record(d, f"est{k}", s, offset=offset) for k, s in enumerate(seeds)]


def test_folds_keep_the_pieces_of_a_bag_together(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    d = cart_desc()
    a, b = bags(cart_record, d, 0.0)
    pieces = [a, *[cart_record(d, f"{b.name}#{k}", 20 + k) for k in (1, 2)]]
    assert bag_of("run/bag#2") == "run/bag" and bag_of("run/bag") == "run/bag"
    assert cv_folds(pieces) == [[0], [1, 2]]


def test_cv_accepts_a_true_offset_out_of_fold(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    d = cart_desc()
    est = bags(cart_record, d, OFFSET)
    res = identify(est, [], d, CFG, cross_validate=True)
    assert res.selection == "cv"
    assert [dec.score.label for dec in res.accepted] == ["sensor_offset@v"]
    dec = res.accepted[0]
    assert dec.validation is not None and dec.validation.p_value < 1e-6
    assert "out-of-fold (leave-one-bag-out) fit" in dec.reason
    # the reported model is the refit on all estimation bags ...
    assert [s.name for s in res.final.fit.segments_] == ["est0", "est1"]
    par, std = res.final.parameters(), res.final.fit.parameter_std()
    assert abs(par["sensor_offset"] - OFFSET) < 3 * std["sensor_offset"]
    # ... and each "validation" simulation comes from the fold fit that never saw that bag
    for stage in (res.baseline, res.final):
        assert len(stage.folds) == 2
        for k, ff in enumerate(stage.folds):
            assert [s.name for s in ff.segments_] == [f"est{1 - k}"]
            x0 = ff.estimate_x0(est[k])
            np.testing.assert_allclose(stage.val_pred[k],
                                       ff.model.simulate(ff.theta_, est[k], x0), atol=1e-9)
    # out of fold, the offset removes nearly all of the baseline's error
    assert res.final.val.mean_fit > 95.0 > res.baseline.val.mean_fit


def test_cv_rejects_an_offset_that_is_not_there(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    d = cart_desc()
    res = identify(bags(cart_record, d, 0.0), [], d, CFG, cross_validate=True)
    assert res.accepted == []
    assert res.final is res.baseline and res.baseline.val.mean_fit > 95.0


def test_cv_rejects_an_offset_of_one_bag_only(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    """An offset in one bag and not in the other: on all estimation bags LR and BIC pass (a
    mean offset of half the size explains much), but out of fold the offset fitted on one bag
    makes the other worse, so the cross-validated test refuses it."""
    d = cart_desc()
    est = [cart_record(d, "est0", 11, offset=OFFSET), cart_record(d, "est1", 12)]
    res = identify(est, [], d, CFG, cross_validate=True)
    assert res.accepted == []
    dec, = res.decisions
    assert dec.score.label == "sensor_offset@v"
    assert dec.lr > dec.lr_threshold and dec.delta_bic < 0
    assert dec.validation is not None and dec.validation.p_value > 0.5
    assert dec.val_fit_after < dec.val_fit_before
    assert "not significantly better" in dec.reason


def test_cv_needs_two_bags_and_no_validation_data(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    d = cart_desc()
    one, two = bags(cart_record, d, 0.0)
    pieces = [one, cart_record(d, "est0#2", 5)]  # one bag split at a gap is still one bag
    with pytest.raises(DataError, match=r"--select-on cv: .*at least 2 estimation bags, got 1"):
        identify(pieces, [], d, CFG, cross_validate=True)
    with pytest.raises(DataError, match="takes no validation segments"):
        identify([one, two], [two], d, CFG, cross_validate=True)


def test_one_record_is_cross_validated_over_contiguous_blocks(
        cart_desc: Callable[..., Description], cart_record: Record) -> None:
    """A single short record (600 samples): the folds are its contiguous blocks, each
    simulated by the model fitted on the others; the true offset is accepted out of fold and
    the reported model is fitted on the whole record."""
    from dvt_identify.series import block_split

    d = cart_desc()
    rec = cart_record(d, "only", 11, n=600, offset=OFFSET)
    blocks = block_split([rec])
    assert [b.name for b in blocks] == [f"only@block{k}" for k in range(1, 6)]
    assert sum(b.n for b in blocks) == rec.n and cv_folds(blocks) == [[k] for k in range(5)]
    res = identify(blocks, [], d, CFG, cross_validate=True)
    assert res.selection == "cv" and len(res.final.folds) == 5
    assert [dec.score.label for dec in res.accepted] == ["sensor_offset@v"]
    par, std = res.final.parameters(), res.final.fit.parameter_std()
    assert abs(par["sensor_offset"] - OFFSET) < 3 * std["sensor_offset"]
    with pytest.raises(DataError, match="too few for cross-validation over blocks"):
        block_split([cart_record(d, "tiny", 12, n=150)])


def test_cv_selection_never_reads_the_test_bags(
        traced_pipeline: tuple[list[str], dict[str, float], Path], tmp_path: Path) -> None:
    """The validation and test bags are read only after every choice (the trace), and what
    they hold (here an offset of 1 m/s the estimation bags do not have) changes nothing but the
    test figure."""
    events, offsets, d = traced_pipeline
    runs = []
    for k, test_offset in enumerate((0.0, 1.0)):
        events.clear()
        offsets.update({"val": test_offset, "test": test_offset})
        res = pipeline.run([tmp_path / "est0", tmp_path / "est1"], [tmp_path / "val"],
                           tmp_path / f"out{k}", str(d), quiet=True, plots=False,
                           test_bags=[tmp_path / "test"], select_on="cv", series=False)
        assert events[events.index("choices made") - 1] == "identify: est0,est1 | "
        assert events.index("read val") > events.index("choices made")
        assert events.index("read test") > events.index("choices made")
        assert res.selection == "cv" and res.test is not None
        assert res.test.bags == ["val", "test"]
        runs.append(res)
    assert [dec.as_dict() for dec in runs[0].decisions] == [
        dec.as_dict() for dec in runs[1].decisions]
    assert runs[0].final.parameters() == runs[1].final.parameters()
    assert runs[0].accepted == [] and runs[1].test.final.mean_fit < 50.0
    rep = json.loads((tmp_path / "out0" / "report.json").read_text())
    assert rep["selection"]["chosen_on"].startswith(
        "leave-one-bag-out cross-validation across the 2 estimation bags")
    assert "selection figures" in rep["selection"]["validation_figures"]
    assert "no part" in rep["selection"]["test_figures"]
    md = (tmp_path / "out0" / "report.md").read_text()
    assert "Effects chosen on leave-one-bag-out cross-validation" in md
    assert "## Test (took no part in any choice)" in md
