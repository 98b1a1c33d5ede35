"""Excitation signals shared by the experiments and the benchmarks (pure).

:func:`prbs` is the one maximum-length binary sequence generator: the driver's experiments
(:func:`dvt_driver.run.experiment_core.prbs_signal`) and the identifier's Monte Carlo benchmark
(:mod:`dvt_identify.bench_identify`) both draw from it, so the same seed and stream give the
same sequence everywhere.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.signal import max_len_seq

from dvt_model.errors import SimulationError

__all__ = ["PRBS_ORDERS", "prbs"]

PRBS_ORDERS = range(3, 25)
"""Shift-register lengths :func:`prbs` accepts (3..24)."""


def prbs(n_bits: int, order: int, seed: int, stream: int = 0) -> NDArray[np.float64]:
    """``n_bits`` values of a maximum-length binary sequence in {-1, +1}, shape (n_bits,).

    The sequence has period ``2**order - 1`` (flat spectrum up to about 0.44 / clock period);
    ``seed`` and ``stream`` choose its starting state (``numpy`` generator seeded with
    ``[seed & 0xFFFFFFFF, stream]``: independent signals of one experiment use other streams).

    Raises:
        SimulationError: ``order`` outside 3..24 (``PRBS order: expected 3..24, got ...``).
    """
    if order not in PRBS_ORDERS:
        raise SimulationError(f"PRBS order: expected 3..24, got {order}")
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(stream)])
    state = rng.integers(0, 2, order)
    if not state.any():
        state[0] = 1
    seq, _ = max_len_seq(order, state=state, length=n_bits)
    return np.asarray(seq, dtype=np.float64) * 2.0 - 1.0
