"""The one PRBS generator (dvt_model.excitation)."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_model.errors import SimulationError
from dvt_model.excitation import prbs


def test_prbs_is_a_maximum_length_sequence_chosen_by_seed_and_stream() -> None:
    order = 7
    n = 2 ** order - 1
    x = prbs(2 * n, order, seed=5)
    assert set(np.unique(x)) == {-1.0, 1.0}
    np.testing.assert_array_equal(x[:n], x[n:])  # period 2^order - 1
    assert x[:n].sum() == 1.0  # one more +1 than -1 over a period
    # circular autocorrelation is -1/n off the zero lag: a flat spectrum
    r = np.array([np.dot(x[:n], np.roll(x[:n], k)) for k in range(1, n)]) / n
    np.testing.assert_allclose(r, -1.0 / n)
    np.testing.assert_array_equal(prbs(50, 8, 0, 100), prbs(255, 8, 0, 100)[:50])
    assert not np.array_equal(prbs(255, 8, 0, 100), prbs(255, 8, 0, 101))  # another stream


def test_prbs_refuses_an_order_outside_3_to_24() -> None:
    with pytest.raises(SimulationError, match="PRBS order: expected 3..24, got 2"):
        prbs(10, 2, seed=0)
    with pytest.raises(SimulationError, match="got 25"):
        prbs(10, 25, seed=0)
