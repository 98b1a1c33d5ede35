"""Coverage of the identifier's reported parameter uncertainty, measured statistically (slow).

The claim: ``OEFit.std_`` (the HAC sandwich standard deviations, :mod:`dvt_identify.uncertainty`)
gives 95 % intervals ``theta_hat +/- 1.96 std`` that contain the true parameters in 95 % of
records. Checked here against the *nominal* truth (the values the records were simulated with)
on structures that are right (the fitted model is the simulating one), with the identifier's
offline pieces (:class:`~dvt_identify.simulation.OEModel`, :class:`~dvt_identify.fit.OEFit`,
the description's number of starts) and the record of ``dvt-bench identify --monte-carlo``
(:func:`~dvt_identify.bench_identify.monte_carlo.mc_input`: the ``dvt`` description's rigid
two-DOF structure, 10 s at 500 Hz, a PRBS of +-2.5 A on the drive motor, output noise 5 % of
each output's standard deviation, white or AR(1) 0.9 per sample (:func:`coloured_noise`)).

Every run draws its own noise (seeds ``[SEED, case, run]``, fixed before the first run); the
runs are independent, so the number of runs whose interval holds the truth is binomial. The
test prints, per case and parameter, the coverage with its two-sided 95 % Clopper-Pearson
interval, the mean and variance of ``z = (theta_hat - theta) / std`` (a calibrated ``std``
gives variance 1) and the pooled coverage over the parameters (not independent within a run:
a figure, not a test), and asserts for every parameter that the data are consistent with the
coverage the test claims (the Clopper-Pearson interval meets the claimed range):

- linear model (the ``--monte-carlo`` case), white and AR(0.9) noise: 0.90-0.95. With 100 runs
  84 to 99 inside pass: a ``std`` reported 35 % too small (true coverage 0.80) fails with
  probability 0.8, one reported 50 % too large (coverage 0.997) with probability 0.7.
- the same with a Coulomb friction on the sun shaft (0.05 N m; with offset, true offset 0),
  modelled: 0.80-0.95 (100 runs: 72 to 99 inside). With AR(0.9) noise the intervals of the mass
  and damping entries are somewhat too narrow (var z 1.15-1.8; coverage 0.90-0.96 here, 0.83-0.91
  in a probe of 100 runs with other seeds): the claim the data support there is "at least 0.80",
  not 0.95.

The truth is not the description's priors, where every fit starts (:func:`_truth`: every mass
and damping entry 44-69 % off them); the test also fails when a prior lies within 3 median
reported std of the truth (the offset excepted: its truth is 0 like its prior). Until
2026-12-06 the truth was the priors themselves.

Measured by this test (seed 2026, 100 runs per case; 2026-12-06, truth off the priors, which
lie 5.8-91 median std away): linear, white 0.94-0.97 per parameter (pooled 0.960), AR(0.9)
0.92-0.96 (0.945); with the friction, white 0.95-0.97 (0.961), AR(0.9) 0.90-0.96 (0.944).
Before, with the truth at the priors (2026-12-05): linear white 0.94-0.97 (0.955), AR(0.9)
0.90-0.94 (0.922); with the friction, white 0.94-0.97 (0.951), AR(0.9) 0.90-0.96 (0.919).

The fit changed while this test was written (a helper optimising ``dvt_identify``): the same
friction case with AR(0.9) noise covered the mass and damping entries in only 0.59-0.64 of 100
runs before (var z 20-200: a few fits far off), 0.83-0.91 after.
"""

from __future__ import annotations

import gc
import math
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.stats import beta

from dvt_identify.bench_identify.monte_carlo import coloured_noise, mc_input
from dvt_identify.description import load_description
from dvt_identify.effects import make_effect
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel

pytestmark = pytest.mark.timeout(900)

Array = NDArray[np.float64]
SEED = 2026  # fixed before the first run; never tuned to pass
NOISE = 0.05  # output noise std / noise-free output std
FC_SUN = 0.05  # N m: Coulomb friction on the sun shaft (the friction_step preset's magnitude)
LINEAR_CLAIM = (0.90, 0.95)  # coverage the data must be consistent with: linear model
FRICTION_CLAIM = (0.80, 0.95)  # ... and with a modelled Coulomb friction
DESC = load_description("dvt")
MASS_SCALE = (1.3, 1.2)  # the truth's mass matrix: S M S, S = diag(MASS_SCALE), M the prior's
DAMPING_SCALE = (0.8, 0.7)  # ... and its damping T D T, T = diag(DAMPING_SCALE)


@dataclass(frozen=True)
class Case:
    """One Monte Carlo case: ``friction`` adds a modelled Coulomb friction (with offset, true
    offset 0) on the sun shaft to the truth and to the fitted model; ``ar`` the noise's AR(1)
    coefficient per sample (0: white)."""

    label: str
    friction: bool
    ar: float
    runs: int


def _model(friction: bool) -> OEModel:
    st = DESC.structure
    effects = ((make_effect("coulomb_friction", st.state_names[0], st.state_names,
                            st.input_names, options={"offset": True}),) if friction else ())
    return OEModel(st, effects)


def _truth(case: Case) -> tuple[OEModel, Any, Array, Array]:
    """The model, the input record, the nominal parameters and the noise-free outputs.

    The nominal values are not the description's priors (where every fit starts): the mass
    matrix is the prior's ``S M S`` with ``S = diag(MASS_SCALE)``, the damping ``T D T`` with
    ``T = diag(DAMPING_SCALE)`` (congruences: both stay symmetric positive definite), which
    moves every entry by 44-69 % (M12 x 1.56, D12 x 0.56)."""
    model = _model(case.friction)
    seg = mc_input(DESC, 10.0, 500.0, seed=0)
    theta = model.initial()
    names = list(model.names)
    for prefix, (a, b) in (("M", MASS_SCALE), ("D", DAMPING_SCALE)):
        for entry, f in (("11", a * a), ("12", a * b), ("22", b * b)):
            theta[names.index(prefix + entry)] *= f
    if case.friction:
        theta[list(model.names).index("Fc")] = FC_SUN
    return model, seg, theta, model.simulate(theta, seg, np.zeros(model.nx))


def _fit_one(job: tuple[Case, int, int]) -> tuple[list[float], list[float]]:
    """One run (in a worker): noise, fit; the estimates and their reported std."""
    case, index, run = job
    model, seg, _, y_clean = _truth(case)
    sigma = NOISE * np.std(y_clean, axis=0)
    rng = np.random.default_rng([SEED, index, run])
    y = y_clean + coloured_noise(rng, y_clean.shape, sigma, case.ar)
    fit = OEFit(model, starts=DESC.fit.starts, seed=run).fit([replace(seg, y=y)])
    return fit.theta_.tolist(), fit.std_.tolist()


def clopper_pearson(k: int, n: int, conf: float = 0.95) -> tuple[float, float]:
    """Exact two-sided ``conf`` interval of a binomial proportion with ``k`` of ``n``."""
    a = 1.0 - conf
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def _consistent(k: int, n: int, claim: tuple[float, float]) -> bool:
    """Whether ``k`` of ``n`` intervals inside is consistent with a coverage in ``claim``: the
    two-sided 95 % Clopper-Pearson interval meets it."""
    lo, hi = clopper_pearson(k, n)
    return hi >= claim[0] and lo <= claim[1]


def _coverage(cases: list[Case], claim: tuple[float, float]) -> list[str]:
    """Run ``cases`` on two worker processes; print the figures; the parameters whose
    coverage is not consistent with ``claim`` (empty: all consistent)."""
    jobs = [(case, i, r) for i, case in enumerate(cases) for r in range(case.runs)]
    gc.freeze()  # a forked worker never finalises what it inherited (a ROS
    # context left by an earlier test segfaulted one in its destructor)
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        results = list(pool.map(_fit_one, jobs, chunksize=4))
    gc.unfreeze()
    misses: list[str] = []
    start = 0
    for case in cases:
        model, _, theta, _ = _truth(case)
        part = results[start:start + case.runs]
        start += case.runs
        est = np.array([p[0] for p in part])
        std = np.array([p[1] for p in part])
        names = [n for n, f in zip(model.names, model.free, strict=True) if f]
        z = ((est - theta) / std)[:, model.free]
        inside = np.abs(z) <= 1.96
        # every fit starts at the priors: they must lie well outside the intervals
        prior_z = ((model.initial() - theta) / np.median(std, axis=0))[model.free]
        far = np.abs(prior_z) > 3.0
        if case.friction:  # the offset's truth is 0 like its prior; the friction's is not
            far[names.index("offset")] = True
        print(f"\n{case.label}: {case.runs} runs, coverage of the 95 % intervals of the nominal "
              "values (Clopper-Pearson 95 %), z = error / reported std")
        for j, name in enumerate(names):
            k = int(inside[:, j].sum())
            lo, hi = clopper_pearson(k, case.runs)
            print(f"  {name:7s} {k:3d}/{case.runs} = {k / case.runs:.3f} ({lo:.3f}-{hi:.3f})  "
                  f"mean z {z[:, j].mean():+.2f}  var z {z[:, j].var(ddof=1):6.2f}")
            if not _consistent(k, case.runs, claim):
                misses.append(f"{case.label}: {name} covered in {k}/{case.runs} "
                              f"(95 % {lo:.3f}-{hi:.3f}), not consistent with {claim}")
        print(f"  pooled  {inside.mean():.3f} of {inside.size} intervals; the priors "
              f"{np.round(np.abs(prior_z), 1).tolist()} median std off the truth")
        misses += [f"{case.label}: {name}'s prior only {abs(pz):.1f} std off the truth"
                   for name, pz, ok in zip(names, prior_z, far, strict=True) if not ok]
    return misses


def test_clopper_pearson_is_the_exact_binomial_interval() -> None:
    assert clopper_pearson(95, 100) == (pytest.approx(0.8872, abs=1e-4),
                                        pytest.approx(0.9836, abs=1e-4))
    assert clopper_pearson(0, 10)[0] == 0.0 and clopper_pearson(10, 10)[1] == 1.0
    assert clopper_pearson(10, 10)[0] == pytest.approx(0.025 ** 0.1, rel=1e-9)


def test_the_criterion_rejects_intervals_too_narrow_or_too_wide() -> None:
    # of 100 runs, 84 to 99 inside are consistent with 0.90-0.95, 83 and 100 are not
    def consistent(k: int) -> bool:
        return _consistent(k, 100, LINEAR_CLAIM)
    assert [k for k in range(101) if consistent(k)] == list(range(84, 100))
    assert [k for k in range(101) if _consistent(k, 100, FRICTION_CLAIM)] == list(range(72, 100))
    # the power figures of the module docstring: the true coverage of a std reported 35 % too
    # small / 50 % too large, and the probability that 100 runs fail the criterion
    from scipy.stats import binom, norm

    for scale, p_fail in ((0.65, 0.8), (1.5, 0.7)):
        p = 2 * norm.cdf(1.96 * scale) - 1
        fail = sum(binom.pmf(k, 100, p) for k in range(101) if not consistent(k))
        assert fail == pytest.approx(p_fail, abs=0.1), (scale, p, fail)


@pytest.mark.slow  # 200 fits on two worker processes
def test_95_intervals_of_the_linear_model_cover_its_nominal_values() -> None:
    misses = _coverage([Case("linear two-DOF model, white noise", False, 0.0, 100),
                        Case("linear two-DOF model, AR(0.9) noise", False, 0.9, 100)],
                       LINEAR_CLAIM)
    assert not misses, "\n".join(misses)


@pytest.mark.slow  # 200 fits on two worker processes
def test_95_intervals_with_a_modelled_coulomb_friction_cover_at_least_80_percent() -> None:
    misses = _coverage([Case("two-DOF model + Coulomb friction on the sun, white noise",
                             True, 0.0, 100),
                        Case("two-DOF model + Coulomb friction on the sun, AR(0.9) noise",
                             True, 0.9, 100)], FRICTION_CLAIM)
    assert not misses, "\n".join(misses)


def test_a_run_is_reproducible() -> None:
    # the same job gives the same estimates (the seeds fix the noise and the starts)
    case = Case("linear", False, 0.9, 1)
    assert _fit_one((case, 1, 3)) == _fit_one((case, 1, 3))
    assert math.isfinite(sum(_fit_one((case, 1, 4))[1]))
