"""The test figure's spread over the estimation data (:mod:`dvt_identify.spread`), pure.

A cart (``M v' = F - Fv v``, M 2.5 kg, random force steps, white noise 0.002 m/s) recorded for
20 s at 100 Hz, fitted as the final model would be, its test figure on a second record:

- stationary (Fv 4 N s/m throughout): the refits on either half score on the test record
  within 10 % of the whole fit's RMSE (the halves describe the same cart);
- the damping drifts from 3 to 5 N s/m over the estimation record (the test record at 4): each
  half's refit misses the test record by more than twice the whole fit's RMSE (measured: 4.2
  and 3.8 times; the whole fit sits near the mean damping): the spread shows what a single
  figure hides. A spread that refitted nothing would fail here.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description
from dvt_identify.errors import DataError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.reference import LinearReference
from dvt_identify.series import evaluate_test
from dvt_identify.simulation import OEModel
from dvt_identify.spread import figure_spread

M = 2.5


@pytest.fixture
def desc(cart_desc: Callable[..., Description]) -> Description:
    """The cart (the shared toy of conftest), no candidate."""
    return cart_desc(candidates=[])


def record(desc: Description, name: str, seed: int, fv: tuple[float, float], n: int = 2000
           ) -> Segment:
    """``n`` samples at 100 Hz; the damping goes linearly from ``fv[0]`` to ``fv[1]``."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-5, 5, n // 50 + 1), 50)[:n]
    dt = 0.01
    d = np.linspace(fv[0], fv[1], n)
    v = np.zeros(n)
    for k in range(1, n):  # exact zero-order hold of each step
        a = np.exp(-d[k - 1] / M * dt)
        v[k] = a * v[k - 1] + (1 - a) * u[k - 1] / d[k - 1]
    y = v + 0.002 * rng.standard_normal(n)
    return make_segment(name, np.arange(n) * dt, u, y, desc.input_names, desc.output_names)


def _final(desc: Description, est: Segment) -> OEFit:
    return OEFit(OEModel(desc.structure), starts=1, seed=0).fit([est])


def test_a_stationary_record_gives_a_narrow_spread(desc: Description) -> None:
    fit = _final(desc, record(desc, "est", 1, (4.0, 4.0)))
    test = [record(desc, "test", 2, (4.0, 4.0))]
    sp = figure_spread(fit, test)
    assert [name for name, _ in sp.parts] == ["first half", "second half"]
    # the final model's own figure is the test figure (the same scoring)
    same = evaluate_test(fit, fit, test).final
    assert sp.final.rmse[0] == pytest.approx(same.rmse[0], rel=1e-12)
    for _, f in sp.parts:
        assert f.rmse[0] == pytest.approx(sp.final.rmse[0], rel=0.1), (f.rmse, sp.final.rmse)
    lo, hi = sp.rmse_range(0)
    assert lo <= sp.final.rmse[0] <= hi
    assert "first half" in sp.statement and "second half" in sp.statement


def test_a_drifting_record_shows_its_spread(desc: Description) -> None:
    fit = _final(desc, record(desc, "est", 1, (3.0, 5.0)))
    sp = figure_spread(fit, [record(desc, "test", 2, (4.0, 4.0))])
    whole = sp.final.rmse[0]
    halves = [f.rmse[0] for _, f in sp.parts]
    assert min(halves) > 2.0 * whole, (halves, whole)
    d = sp.as_dict()
    assert d["rmse_range"]["v"] == [whole, max(halves)]  # type: ignore[index]


def test_bad_arguments_are_refused(desc: Description) -> None:
    fit = _final(desc, record(desc, "est", 1, (4.0, 4.0), n=400))
    with pytest.raises(DataError, match="parts"):
        figure_spread(fit, [record(desc, "test", 2, (4.0, 4.0))], parts=1)
    with pytest.raises(DataError, match="no test segments"):
        figure_spread(fit, [])
    with pytest.raises(DataError, match="too few"):
        figure_spread(fit, [record(desc, "test", 2, (4.0, 4.0))], parts=5)


def _reference(desc: Description, est: Segment) -> LinearReference:
    val = record(desc, "val", 3, (4.0, 4.0))
    return LinearReference(max_order=2, seed=0).fit([est], [val])


@pytest.mark.parametrize("drift", [False, True])
def test_the_linear_reference_spreads_alike(desc: Description, drift: bool) -> None:
    """The reference's own figure is its test figure; refined on each half (warm, its order
    kept), it is narrow on the stationary cart (within 10 %) and misses by more than twice its
    whole figure on the drifting one."""
    est = record(desc, "est", 1, (3.0, 5.0) if drift else (4.0, 4.0))
    fit, ref = _final(desc, est), _reference(desc, est)
    test = [record(desc, "test", 2, (4.0, 4.0))]
    sp = figure_spread(fit, test, reference=ref)
    assert sp.reference is not None
    own = evaluate_test(fit, fit, test, reference=ref).reference
    assert own is not None
    assert sp.reference.rmse[0] == pytest.approx(own.rmse[0], rel=1e-12)
    assert [name for name, _ in sp.reference_parts] == ["first half", "second half"]
    halves = [f.rmse[0] for _, f in sp.reference_parts if not isinstance(f, str)]
    assert len(halves) == 2
    if drift:
        assert min(halves) > 2.0 * sp.reference.rmse[0], (halves, sp.reference.rmse)
    else:
        assert halves == pytest.approx([sp.reference.rmse[0]] * 2, rel=0.1)
    assert "linear reference" in sp.statement
    d = sp.as_dict()
    assert d["reference_rmse_range"]["v"] == [  # type: ignore[index]
        min(sp.reference.rmse[0], *halves), max(sp.reference.rmse[0], *halves)]


def test_a_reference_part_that_fails_is_named_not_raised(
        desc: Description, monkeypatch: pytest.MonkeyPatch) -> None:
    """A refinement that fails leaves that part unscored, with the reason in the statement
    and the JSON; the physical model's spread stands."""
    est = record(desc, "est", 1, (4.0, 4.0))
    fit, ref = _final(desc, est), _reference(desc, est)

    def fails(self: LinearReference, est: object) -> LinearReference:
        raise FitError("LinearReference.refit on ['est@block1']: order 1: the start cannot "
                       "be simulated")
    monkeypatch.setattr(LinearReference, "refit", fails)
    sp = figure_spread(fit, [record(desc, "test", 2, (4.0, 4.0))], reference=ref)
    assert len(sp.parts) == 2
    assert all(isinstance(f, str) for _, f in sp.reference_parts)
    assert "Not scored: linear reference on the first half: LinearReference.refit" in sp.statement
    d = sp.as_dict()
    assert d["reference_parts"][0]["not_scored"].startswith("LinearReference.refit")  # type: ignore[index]


def test_a_warm_refit_keeps_the_order_and_the_optimum(desc: Description) -> None:
    """Refined on its own estimation data the reference stays where it was (warm start at
    its optimum); on a half it keeps its order and counts its parameters again."""
    est = record(desc, "est", 1, (4.0, 4.0))
    ref = _reference(desc, est)
    same = ref.refit([est])
    assert same.order_ == ref.order_ and same.orders_ == []
    np.testing.assert_allclose(same.model_.poles_s(), ref.model_.poles_s(), rtol=1e-3)
    half = ref.refit([est.rows(0, est.n // 2)])
    assert half.order_ == ref.order_
    assert half.n_estimated_ == ref.n_estimated_
    with pytest.raises(DataError, match="output_names"):
        ref.refit([make_segment("x", np.arange(10) * 0.01, np.zeros(10), np.zeros(10),
                                ("force",), ("w",))])
