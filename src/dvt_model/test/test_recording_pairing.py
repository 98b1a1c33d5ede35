"""Unit tests of the one stamp pairing: pair_stamps (offline) and LivePairer (live)."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_model.contract import CURRENTS, JOINT_STATES
from dvt_model.errors import BagError
from dvt_model.recording import LivePairer, pair_stamps

T0 = 1_700_000_000_000_000_000
DT = 1_000_000  # 1 kHz [ns]


def _stamps(n: int) -> np.ndarray:
    return T0 + DT * np.arange(n, dtype=np.int64)


def test_identical_stamps_pair_exactly_and_count_unmatched() -> None:
    st = _stamps(20)
    js = np.delete(st, [3, 4])
    cu = np.delete(st, [0, 10, 19])
    p = pair_stamps({JOINT_STATES: js, CURRENTS: cu}, JOINT_STATES, exact_only=True)
    assert p.exact and p.n == 15
    np.testing.assert_array_equal(js[p.index[JOINT_STATES]], cu[p.index[CURRENTS]])
    np.testing.assert_array_equal(js[p.index[JOINT_STATES]], np.delete(st, [0, 3, 4, 10, 19]))
    assert p.unmatched == {JOINT_STATES: 3, CURRENTS: 2}
    # the default mode takes the same exact path when (nearly) every stamp is shared
    q = pair_stamps({JOINT_STATES: st, CURRENTS: np.delete(st, [5])}, JOINT_STATES)
    assert q.exact and q.n == 19 and q.unmatched == {JOINT_STATES: 1, CURRENTS: 0}


def test_nearest_stamp_within_a_quarter_sample() -> None:
    st = _stamps(100)
    offset = np.full(100, DT // 5, dtype=np.int64)  # 0.2 sample: pairs
    offset[[10, 60]] = DT // 5 * 2  # 0.4 sample: too far, those samples are dropped
    cu = st + offset
    p = pair_stamps({JOINT_STATES: st, CURRENTS: cu}, JOINT_STATES, where="bag1")
    assert not p.exact and p.n == 98
    np.testing.assert_array_equal(p.index[JOINT_STATES], np.delete(np.arange(100), [10, 60]))
    np.testing.assert_array_equal(p.index[CURRENTS], p.index[JOINT_STATES])
    assert p.unmatched == {JOINT_STATES: 2, CURRENTS: 2}


def test_failures_name_the_bag_and_the_topics() -> None:
    st = _stamps(50)
    with pytest.raises(BagError, match=rf"^/runs/b1: topics {JOINT_STATES} and {CURRENTS} "
                                       "share no header.stamp"):
        pair_stamps({JOINT_STATES: st, CURRENTS: st + 1}, JOINT_STATES, where="/runs/b1",
                    exact_only=True)
    with pytest.raises(BagError, match=rf"^/runs/b2: topics {JOINT_STATES} and {CURRENTS}: "
                                       "fewer than 50% of the samples share a stamp"):
        pair_stamps({JOINT_STATES: st, CURRENTS: st + DT // 2}, JOINT_STATES, where="/runs/b2")
    with pytest.raises(BagError, match=r"^/runs/b3: reference topic /nope not among"):
        pair_stamps({JOINT_STATES: st, CURRENTS: st}, "/nope", where="/runs/b3")


def test_live_pairer_pairs_by_identical_stamp_in_any_order() -> None:
    pairer: LivePairer[str] = LivePairer()
    assert pairer.add(T0, 0, "js0") is None
    assert pairer.add(T0 + DT, 1, "cu1") is None
    assert pairer.pending == 2
    assert pairer.add(T0, 1, "cu0") == ("js0", "cu0")
    assert pairer.add(T0 + DT, 0, "js1") == ("js1", "cu1")
    assert pairer.pending == 0 and pairer.unpaired == 0
    with pytest.raises(ValueError, match="slot: expected 0..1, got 2"):
        pairer.add(T0, 2, "x")


def test_live_pairer_bounds_pending_and_counts_unpaired() -> None:
    pairer: LivePairer[int] = LivePairer(max_pending=3)
    for i in range(5):  # partners never arrive
        assert pairer.add(T0 + i * DT, 0, i) is None
    assert pairer.pending == 3 and pairer.unpaired == 2
    assert pairer.add(T0, 1, 100) is None  # the oldest were dropped: no partner any more
    assert pairer.add(T0 + 4 * DT, 1, 104) == (4, 104)  # the newest still pair
