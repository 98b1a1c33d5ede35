"""Plot helpers of the report: the min/max envelope keeps every peak; log labels without mathtext."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.report import _log_label, envelope


@pytest.mark.parametrize("n,bins", [(60_000, 1210), (1001, 7), (2421, 1210), (10, 50)])
def test_envelope_keeps_extremes_of_every_run(n: int, bins: int) -> None:
    rng = np.random.default_rng(n)
    t = np.arange(n) * 1e-3
    y = np.cumsum(rng.normal(size=n))
    y[n // 3] = 1e3  # a one-sample spike
    y[-1] = -1e3  # and one at the very end
    te, ye = envelope(t, y, bins)
    if n <= 2 * bins:
        assert te is t and ye is y
        return
    assert te.size <= 2 * bins
    assert np.all(np.diff(te) >= 0)  # time order
    idx = np.rint(te / 1e-3).astype(int)
    np.testing.assert_array_equal(ye, y[idx])  # real samples at their own times
    assert ye.max() == 1e3 and ye.min() == -1e3
    k = -(-n // bins)
    for start in range(0, n, k):  # every run's min and max are kept
        run = y[start:start + k]
        inside = ye[(idx >= start) & (idx < start + k)]
        assert inside.max() == run.max() and inside.min() == run.min()


def test_log_labels_are_plain_text() -> None:
    assert _log_label(r"$\mathdefault{10^{-3}}$") == "10⁻³"
    assert _log_label(r"$\mathdefault{10^{12}}$") == "10¹²"
    assert _log_label(r"$\mathdefault{2\times10^{1}}$") == "2×10¹"
    assert _log_label(r"$\mathdefault{-10^{0}}$") == "-10⁰"
    assert _log_label(r"$\mathdefault{0}$") == "0"
    assert _log_label("") == ""
    assert _log_label("0.1") == "0.1"
