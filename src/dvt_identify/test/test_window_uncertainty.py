"""The noise of a state-initialisation window in the reported std (:meth:`OEFit.window_meat`).

With ``init_window`` the first samples of each segment set its initial state, and their noise
moves every later residual through it; the fitted initial state absorbs that part of the
window's own residuals, so the sandwich's scores cannot see it. On a cart whose initial speed
persists through the record (M 2.5 kg, Fv 0.5 N s/m: time constant 5 s against a 3-s record,
a 3-sample window, noise 0.05 m/s), 200 records:

- with the window's term the nominal 95 % intervals of M and Fv cover the truth at a rate
  consistent with 0.95 or above and below 0.995 (two-sided 95 % Clopper-Pearson interval of
  the count; measured 197 and 198 of 200);
- without it (the term set to zero) fewer than 75 % do (measured 113 and 100 of 200): the
  std left out the window's noise, which this test would catch.

``pytest -s`` prints the counts.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scipy.stats import binomtest

from dvt_identify.data import make_segment
from dvt_identify.description import Description
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel

TRUTH = np.array([2.5, 0.5])  # M [kg], Fv [N s/m]
RUNS, N, WINDOW, NOISE = 200, 300, 3, 0.05


def _hits(desc: Description) -> np.ndarray:
    """How many of :data:`RUNS` fits' 95 % intervals hold the truth, per parameter (2,)."""
    hits = np.zeros(2)
    for i in range(RUNS):
        rng = np.random.default_rng(i)
        u = np.repeat(rng.uniform(-5, 5, N // 50 + 1), 50)[:N]
        t = np.arange(N) * 0.01
        clean = make_segment("s", t, u, np.zeros(N), desc.input_names, desc.output_names)
        y = OEModel(desc.structure).simulate(TRUTH, clean, np.array([rng.uniform(-2, 2)]))
        y = y + NOISE * rng.standard_normal(y.shape)
        seg = make_segment("s", t, u, y, desc.input_names, desc.output_names)
        f = OEFit(OEModel(desc.structure), starts=1, seed=0, init_window=WINDOW).fit([seg])
        hits += np.abs(f.theta_[:2] - TRUTH) <= 1.96 * f.std_[:2]
    return hits


def test_the_window_s_noise_is_in_the_std(cart_desc: Callable[..., Description]) -> None:
    hits = _hits(cart_desc())
    print(f"with the window's term: M {hits[0]:.0f}, Fv {hits[1]:.0f} of {RUNS} inside")
    for k in hits:
        ci = binomtest(int(k), RUNS).proportion_ci(0.95, method="exact")
        assert ci.high >= 0.95 and ci.low <= 0.995, (k, RUNS, ci)


def test_without_the_window_s_term_the_std_is_too_small(
        cart_desc: Callable[..., Description], monkeypatch: pytest.MonkeyPatch) -> None:
    def none(self: OEFit, *a: Any) -> tuple[np.ndarray, np.ndarray]:
        nf = int(self.model.free.sum())
        return np.arange(nf), np.zeros((nf, nf))
    monkeypatch.setattr(OEFit, "window_meat", none)
    hits = _hits(cart_desc())
    print(f"without it: M {hits[0]:.0f}, Fv {hits[1]:.0f} of {RUNS} inside")
    assert np.all(hits < 0.75 * RUNS)


def test_the_term_is_zero_without_a_window_and_positive_with_one(cart_desc: Callable[..., Description]) -> None:
    """Without a window the term is zero; with one it is positive semi-definite."""
    desc = cart_desc()
    rng = np.random.default_rng(0)
    u = np.repeat(rng.uniform(-5, 5, N // 50 + 1), 50)[:N]
    t = np.arange(N) * 0.01
    clean = make_segment("s", t, u, np.zeros(N), desc.input_names, desc.output_names)
    y = OEModel(desc.structure).simulate(TRUTH, clean, np.array([1.0]))
    seg = make_segment("s", t, u, y + NOISE * rng.standard_normal(y.shape), desc.input_names,
                       desc.output_names)
    for window in (0, WINDOW):
        f = OEFit(OEModel(desc.structure), starts=1, seed=0, init_window=window).fit([seg])
        cols, extra = f.window_meat(f.theta_, seg, f.x0_[0], f.weights_)
        assert list(cols) == [0, 1]
        if window == 0:
            assert not np.any(extra)
        else:
            assert np.all(np.linalg.eigvalsh(extra) >= -1e-12 * np.abs(extra).max())
            assert np.all(np.diag(extra) > 0)
