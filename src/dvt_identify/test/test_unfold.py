"""The sign of an output read sign-blind, restored for the starts (:mod:`dvt_identify.unfold`),
on simulated belt drives (``tests/belt_drive.py``: 300-sample records at 50 Hz, every prior 1)."""

from __future__ import annotations

import belt_drive
import numpy as np
import pytest

from dvt_identify.effects import make_effect
from dvt_identify.linref import unfolded_starts
from dvt_identify.simulation import OEModel
from dvt_identify.unfold import unfold


def agreement(signed: np.ndarray, truth: np.ndarray) -> float:
    """Share of the samples where the speed is at least 10 % of its largest value that carry
    the true sign."""
    big = np.abs(truth) > 0.1 * np.max(np.abs(truth))
    return float(np.mean(np.sign(signed[big]) == np.sign(truth[big])))


@pytest.mark.parametrize("drive", sorted(belt_drive.DRIVES))
def test_every_sign_is_restored_up_to_one_overall_sign(drive: str) -> None:
    """Each record of the drive gets its true sign back on every sample that matters, with
    one overall sign for all of them (the inputs tie the records together): a pattern and its
    opposite fit the data alike, so the overall sign is open."""
    segs, speeds = belt_drive.records(drive, seed=11)
    shares = [agreement(s.y[:, 0], w) for s, w in zip(unfold(segs, 0), speeds, strict=True)]
    assert all(a == 1.0 for a in shares) or all(a == 0.0 for a in shares), shares


def test_nothing_to_decide_leaves_the_segments_alone() -> None:
    """A speed that never comes near 0 has no place to change its sign: the segments come back
    as they are."""
    segs, _ = belt_drive.records("slow_belt", seed=11)
    lifted = [s.rows(0, s.n) for s in segs]
    for s in lifted:
        s.y[:, 0] = 5.0 + 0.01 * np.sin(np.arange(s.n))
    assert all(a is b for a, b in zip(unfold(lifted, 0), lifted, strict=True))


def test_the_unfolded_starts_hold_the_drive() -> None:
    """The structure mapped from a linear reference on the unfolded records (and on its mirror)
    lands within 50 % of every parameter of the drive, where the priors (every one 1) are
    off by 3x to 100x; the sign-blind map starts at its probe b = 1."""
    desc = belt_drive.description()
    st = desc.structure
    model = OEModel(st, [make_effect("sign_blind", "w_pulley", st.state_names, st.input_names,
                                     output_names=desc.output_names)])
    segs, _ = belt_drive.records("stiff_belt", seed=11)
    starts = unfolded_starts(model, segs, seed=0, max_order=4)
    truth = np.array([belt_drive.DRIVES["stiff_belt"][p.name] for p in st.params])
    near = [th for th in starts if np.all(np.abs(th[: truth.size] / truth - 1.0) < 0.5)]
    assert near, [np.round(th, 4) for th in starts]
    assert all(th[-1] == 1.0 for th in starts)
