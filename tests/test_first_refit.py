"""The live loop's first refit after a friction step (``tests/first_refit_run.py``): it names
Coulomb friction on the sun shaft and on carrier 3 near the plant's values and pushes the
in-use M and D unchanged; whether it names anything more is a rate over plants, tested over
ten of them with the bound it states."""

from __future__ import annotations

import json
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from first_refit_run import first_refit, friction_step_bag, refit_row

from dvt_identify.metrics import rate_upper_bound

BOTH = {"coulomb_friction@sun_shaft", "coulomb_friction@carrier3"}
"""The plant's two Coulomb steps, as the identifier names them."""


def test_first_refit_names_both_coulomb_steps_on_a_few_seconds(tmp_path: Path) -> None:
    """2.5 s to fit, 1.5 s held out, 0.5 s after the step (seed 1): with the structure held at
    the model in use the refit names Coulomb friction on the sun shaft and on carrier 3, near
    the plant's values, pushes the in-use M and D unchanged, and its residual falls."""
    from dvt_model.config import resolve

    bag, change = friction_step_bag(tmp_path, 1)
    out = first_refit(bag, change, tmp_path / "work")
    assert not out.error, out.error
    s = out.summary
    assert s["stage"] == "effects" and set(s["held"]) == {"M11", "M12", "M22", "D11", "D12",
                                                          "D22"}
    assert set(s["accepted"]) >= BOTH, s["accepted"]
    terms = json.loads(out.new_parameters["effects"])
    fc = {tuple(t["member"]): t["Fc"] for t in terms if t["kind"] == "coulomb"}
    assert fc[(1.0, 0.0)] == pytest.approx(0.05, rel=0.3), fc
    assert fc[(0.0, 1.0)] == pytest.approx(0.20, rel=0.3), fc
    np.testing.assert_allclose(np.reshape(out.new_parameters["M"], (2, 2)),
                               resolve({"params": "physical"}).rigid.M, rtol=1e-9)
    rms_new = np.sqrt(np.mean(np.asarray(out.new_errors) ** 2, axis=0))
    rms_cur = np.sqrt(np.mean(np.asarray(out.current_errors) ** 2, axis=0))
    assert np.all(rms_new < 0.3 * rms_cur), (rms_cur, rms_new)


SEEDS = range(1, 11)
"""Plants (experiment and noise seeds) of the rate test."""
MAX_EXTRA = 2
"""Most of the :data:`SEEDS` refits that may name a term beyond the two Coulomb steps
(measured 2026-11-27: 1 of 10, an ``unlisted`` sun term on seed 8; with the motor current held
linear and the sun speed an interval mean, ``docs/identification.md`` section 2, also 1 of 10:
a windage on the sun on seed 1; 2026-12-06, the ``unlisted`` library left to the full refit,
``dvt_identify.refit.UNLISTED``: 0 of 10)."""


@pytest.mark.slow
def test_first_refits_name_both_coulomb_steps_and_rarely_more(tmp_path: Path) -> None:
    """Over ten plants the first refit names both Coulomb steps every time and a further term
    in at most :data:`MAX_EXTRA` of them (printed with the 95 % Clopper-Pearson upper bound on
    the rate: ten short refits bound it loosely, and the bound is what the test states)."""
    # spawned workers: by this point the test process holds rclpy/DDS threads of earlier
    # tests, and a forked child of a multi-threaded process can crash
    with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(refit_row, SEEDS, [str(tmp_path)] * len(SEEDS)))
    extra = [(seed, sorted(set(acc) - BOTH)) for seed, acc, _ in rows if set(acc) - BOTH]
    n = len(rows)
    print(f"\nfirst refits naming more than the two Coulomb steps: {len(extra)} of {n} "
          f"(95 % upper bound on the rate {100 * rate_upper_bound(len(extra), n):.0f} %): "
          f"{extra}")
    assert all(not err for _, _, err in rows), rows
    assert all(set(acc) >= BOTH for _, acc, _ in rows), rows
    assert len(extra) <= MAX_EXTRA, extra
