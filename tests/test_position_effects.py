"""Position-dependent effects the plant hides: the default dvt description names the cause where
it acts (or, for a form no candidate has, an ``unlisted`` term of the right form on the right
member), recovers the plant's drawn values within the reported uncertainty, and the validation
error falls; a clean plant accepts nothing.

Runs: the offline runner (:func:`dvt_driver.plant.offline.record_offline`, no ROS) drives the
``ident`` experiment once for estimation and once, with other experiment and noise seeds, for
validation, per hidden preset; they are made once per session. The plant's magnitudes,
reduction, stage, angles and phases are drawn from the preset's distributions with draw seed
:data:`DRAW` (:mod:`dvt_driver.plant.hidden.draw`); the validation run is the same drawn plant
(read back from the estimation run's ``truth.yaml``, which only the tests read). The
identifier runs the description's full loop (up to ``max_effects`` = 3 rounds).

Tolerance rule (each test repeats it): ``|estimate - truth| <= 3 std``, ``std`` the reported
standard deviation of the estimate (:meth:`OEFit.parameter_std`, the HAC sandwich covariance
of the output-error fit; for a derived quantity, first-order propagation of the parameters'
std). Where the model's form differs from the plant's (the friction bump as a short Fourier
series), a stated bound with its reason. About 2.5 min on 2 cores.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from recorded import PLANT_MEMBER, truth_effects, within

from dvt_driver.plant.hidden import HiddenEffects, load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.plant.settings import SensorConfig
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.effects import Unlisted, make_effect
from dvt_identify.effects.base import SegmentView
from dvt_identify.effects.position import mesh_orders
from dvt_identify.loop import IdentificationResult, LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_model.params import load_parameters

PARAMS = "physical"
BAGS = Path(__file__).resolve().parents[1] / "bags"
DRAW = 31
"""Draw seed of every preset's plant (also the estimation run's noise seed)."""


@pytest.fixture(scope="session")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Path]]:
    """Estimation and validation run per preset (made lazily, cached for the session)."""
    return {}


def _run(runs: dict[str, tuple[Path, Path]], root: Path, preset: str) -> tuple[Path, Path]:
    if preset not in runs:
        params = load_parameters(PARAMS)
        est = record_offline(root / f"{preset}-est", build("ident", seed=21), params,
                             load_hidden(preset, draw=DRAW), seed=31)
        # the same drawn plant, from the truth the estimation run wrote
        val = record_offline(root / f"{preset}-val", build("ident", seed=121), params,
                             truth_effects(est), seed=131)
        runs[preset] = (est, val)
    return runs[preset]


_RESULTS: dict[tuple[Path, str], tuple[IdentificationResult, HiddenEffects]] = {}


def _identify(runs: dict[str, tuple[Path, Path]], root: Path, preset: str
              ) -> tuple[IdentificationResult, HiddenEffects]:
    """The description's loop with its own ``max_effects`` (3 rounds) on the preset's runs;
    the result and the drawn truth (once per session and preset)."""
    if (root, preset) not in _RESULTS:
        _RESULTS[root, preset] = _identify_now(runs, root, preset)
    return _RESULTS[root, preset]


def _identify_now(runs: dict[str, tuple[Path, Path]], root: Path, preset: str
                  ) -> tuple[IdentificationResult, HiddenEffects]:
    est_bag, val_bag = _run(runs, root, preset)
    desc = load_description("dvt")
    est = load_segments([est_bag], desc)
    val = load_segments([val_bag], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate)
    assert cfg.max_effects >= 3
    truth = truth_effects(est_bag)
    assert truth.draw is not None and truth.draw["seed"] == DRAW  # a draw, not the nominal
    return identify(est, val, desc, cfg, check=chk), truth


@pytest.fixture(scope="session")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("position_runs")


def _validation_falls(r: IdentificationResult) -> None:
    assert r.final.val.mean_fit > r.baseline.val.mean_fit
    for d in r.accepted:
        assert d.validation is not None
        assert d.validation.gain > 0 and d.validation.p_value < r.config.alpha, d.as_dict()


@pytest.mark.slow
def test_gravity_arm_is_named_with_its_reduction_amplitude_and_phase(
        runs: dict[str, tuple[Path, Path]], root: Path) -> None:
    """The drawn arm (reduction, size, mass, angle at the encoder's zero) is accepted in 3
    rounds, on carrier 3, and leaves no drift; the reduction and the coefficient ``b`` of
    ``a cos(theta_c3 / N) + b sin(theta_c3 / N)`` are each within 3 reported std of the truth
    (``b`` from the plant's own torque law: the torque at ``theta_c3 = N pi / 2``; ``a``: a
    test below; that it is the only effect accepted: the next test)."""
    r, truth = _identify(runs, root, "gravity_arm")
    load = truth.gravity_arm
    assert load is not None
    arm = [d for d in r.accepted if d.score.label == "gravity_load@carrier3"]
    assert len(arm) == 1, [d.as_dict() for d in r.decisions]
    assert arm[0].score.effect.where == "carrier3"
    _validation_falls(r)
    # the unmodelled arm may read as a drift of M22 on the baseline (windows of different
    # angle coverage): with the arm accepted, nothing drifts
    assert r.drift is not None and r.drift.drifting == [], r.drift.summary()
    p, sd = r.final.parameters(), r.final.fit.parameter_std()
    n_true = load.stage.reduction
    b_true = load.carrier3_torque(0.5 * math.pi * n_true, 1.0)
    within("reduction", p["reduction"], sd["reduction"], n_true)
    within("gravity_b", p["gravity_b"], sd["gravity_b"], b_true)
    assert arm[0].score.extra["angle_source"]


@pytest.mark.slow
def test_gravity_arm_is_the_only_accepted_effect(
        runs: dict[str, tuple[Path, Path]], root: Path) -> None:
    """Nothing but the arm is accepted in 3 rounds (the plant has nothing else). Round 1 may
    take a stand-in for the arm (here an ``unlisted`` sun term): once the arm is accepted the
    loop's recheck must take it out again (``loop._recheck``)."""
    r, _ = _identify(runs, root, "gravity_arm")
    assert [d.score.label for d in r.accepted] == ["gravity_load@carrier3"], [
        d.as_dict() for d in r.decisions]


@pytest.mark.slow
def test_gravity_arm_cos_coefficient_is_the_plants(
        runs: dict[str, tuple[Path, Path]], root: Path) -> None:
    """``a`` of ``a cos(theta_c3 / N) + b sin(theta_c3 / N)`` within 3 reported std of the
    plant's torque at ``theta_c3 = 0``.

    A strict xfail until 2026-12-05: 0.600326 against the drawn 0.59869 (+0.27 %) at 3.55 of
    a 0.000461 std. The offset is unchanged; it is the plant-model difference traced in
    docs/identification.md (Tests: the measured current's error, its intersample weight and
    the 5-ms decimation; ``scripts/gravity_bias.py``). What changed is the std: its Bartlett
    window (:func:`dvt_identify.uncertainty.covariance_bandwidth`) now sees the scores' slow
    correlation, 0.000588, so the offset is 2.8 std: near the bound, as a known bias of about
    1.5-2 std (mean offset over five recordings +0.00081 N m) makes it."""
    r, truth = _identify(runs, root, "gravity_arm")
    load = truth.gravity_arm
    assert load is not None and "gravity_load@carrier3" in [d.score.label for d in r.accepted]
    p, sd = r.final.parameters(), r.final.fit.parameter_std()
    within("gravity_a", p["gravity_a"], sd["gravity_a"], load.carrier3_torque(0.0, 1.0))


@pytest.mark.slow
def test_mesh_ripple_is_named_at_the_sun_tooth_order(
        runs: dict[str, tuple[Path, Path]], root: Path) -> None:
    """The drawn ripple (amplitude, the stage whose sun teeth are its order, phase) is the one
    accepted effect in 3 rounds, on the sun shaft's own angle (the plant's ripple is periodic
    in ``theta_sun``, not in a mesh angle) at the drawn stage's sun tooth order; amplitude
    ``hypot(a, b)`` and phase ``atan2(a, b)`` of ``a cos + b sin`` within 3 std each (the std
    propagated to first order from the reported std of ``a`` and ``b``)."""
    r, truth = _identify(runs, root, "mesh_ripple")
    ripple = truth.mesh_ripple
    assert ripple is not None
    assert [d.score.label for d in r.accepted] == ["periodic_disturbance@sun_shaft"], [
        d.as_dict() for d in r.decisions]
    _validation_falls(r)
    teeth = load_parameters(PARAMS).stages[ripple.stage - 1].sun
    assert float(teeth) in mesh_orders(PARAMS)
    p, sd = r.final.parameters(), r.final.fit.parameter_std()
    assert p["order_sun_shaft"] == teeth
    assert p["mesh_stage_sun_shaft"] == 0  # the sun-shaft angle, not a mesh angle
    a, b = p["a_sun_shaft"], p["b_sun_shaft"]
    sa, sb = sd["a_sun_shaft"], sd["b_sun_shaft"]
    amp = math.hypot(a, b)
    within("amplitude", amp, math.hypot(a * sa, b * sb) / amp, ripple.amplitude)
    phase = math.atan2(a, b)
    dphase = (phase - ripple.phase + math.pi) % (2 * math.pi) - math.pi
    within("phase", ripple.phase + dphase, math.hypot(b * sa, a * sb) / amp ** 2, ripple.phase)


def _friction_terms(r: IdentificationResult, member: str
                    ) -> list[tuple[str, float, float, float]]:
    """The final model's friction terms against member ``member``'s motion: ``(trig, order,
    level, std)`` with ``level`` the friction [N m] (a torque ``k sign(w) T`` is a friction
    ``-k T``), ``trig`` ``""`` for a level that does not depend on the angle (the Coulomb
    ``Fc`` or an unlisted ``sign(w)`` term), else ``cos``/``sin`` of ``order`` times the angle."""
    p, sd = r.final.parameters(), r.final.fit.parameter_std()
    out = []
    if f"Fc_{member}" in p:
        out.append(("", 0.0, p[f"Fc_{member}"], sd[f"Fc_{member}"]))
    for eff in r.final.effects:
        if not (isinstance(eff, Unlisted) and eff.member_name == member):
            continue
        for term, spec in zip(eff.terms, eff.params, strict=True):
            if term.speed == "sign" and term.input < 0 and not term.mesh:
                out.append((term.trig, term.order, -p[spec.name], sd[spec.name]))
    return out


@pytest.mark.slow
def test_position_friction_is_an_unlisted_friction_in_the_carrier3_angle(
        runs: dict[str, tuple[Path, Path]], root: Path) -> None:
    """The drawn tight spot (height, angle, width) on carrier 3: no named candidate has a
    friction that depends on the angle, so the library search proposes one on carrier 3 (every
    kept term a friction, ``sign(w_carrier3)`` times cos/sin of its angle or alone, at least one
    with the angle), and nothing on another member is accepted in 3 rounds. Where it acts: the
    fitted friction-vs-angle profile peaks within half the bump's width of the drawn centre (a
    stated bound: the model is a three-order Fourier series of a Gaussian bump, which places the
    peak but not the height); its mean (the angle-free levels: Coulomb ``Fc`` and any plain
    ``sign`` term) is within 3 std of the bump's mean ``amplitude * width * sqrt(pi) / (2 pi)``,
    the std the reported ones of those levels added in quadrature."""
    r, truth = _identify(runs, root, "position_friction")
    (member,) = truth.position_friction
    bump = truth.position_friction[member]
    where = PLANT_MEMBER[member]
    unl = [d for d in r.accepted if d.score.effect.name == "unlisted"]
    assert unl, [d.as_dict() for d in r.decisions]
    assert all(d.score.effect.where == where for d in r.accepted), [
        d.score.label for d in r.accepted]
    eff = unl[0].score.effect
    assert isinstance(eff, Unlisted)
    assert eff.member_name == where
    assert all(t.speed == "sign" and t.input < 0 for t in eff.terms), eff.label()
    assert any(t.trig for t in eff.terms), eff.label()
    formula = str(unl[0].score.extra["formula"])
    assert formula.startswith(f"tau_{where} = ") and f"sign(w_{where})*" in formula
    assert f"th_{where}" in formula and "N m" in formula
    _validation_falls(r)
    terms = _friction_terms(r, where)
    theta = np.linspace(-math.pi, math.pi, 3601)
    profile = np.zeros_like(theta)
    for trig, order, level, _ in terms:
        profile += level * (np.ones_like(theta) if not trig else
                            np.cos(order * theta) if trig == "cos" else np.sin(order * theta))
    peak = float(theta[int(np.argmax(profile))])
    off = (peak - bump.center + math.pi) % (2 * math.pi) - math.pi
    assert abs(off) <= 0.5 * bump.width, (peak, bump)
    flat = [(level, std) for trig, _, level, std in terms if not trig]
    assert flat, f"no angle-free friction level on {where}: {terms}"
    within(f"mean friction on {where}", sum(v for v, _ in flat),
           math.sqrt(sum(e * e for _, e in flat)),
           bump.amplitude * bump.width * math.sqrt(math.pi) / (2 * math.pi))


@pytest.mark.slow
def test_gravity_arm_is_found_from_the_priors_when_the_baseline_bends(
        tmp_path: Path) -> None:
    """The drawn arm recorded without sensor noise (the encoders' and A/D quantisation stay):
    the baseline bends so far that the drift check flags it, so round 1 tries only the effects
    in a member's angle, and the arm's score against that residual picks a wrong reduction.
    The refit also starts from every parameter's prior with each scanned reduction
    (``loop._prior_starts``): the arm is accepted, alone, with its reduction within 1 % of the
    drawn one (a stated bound: the scan starts it 5x off; without sensor noise the reported
    std is far below the model's known offset, ``scripts/gravity_bias.py``) and nothing
    drifts. Before these starts nothing was accepted here (validation fit 84.35 %)."""
    params = load_parameters(PARAMS)
    sensors = dataclasses.replace(SensorConfig(), tach_noise=0.0, motor_current_noise=0.0,
                                  brake_current_noise=0.0)
    hidden = load_hidden("gravity_arm", draw=DRAW)
    est_bag = record_offline(tmp_path / "est", build("ident", seed=21), params, hidden,
                             seed=31, sensors=sensors)
    val_bag = record_offline(tmp_path / "val", build("ident", seed=121), params, hidden,
                             seed=131, sensors=sensors)
    desc = load_description("dvt")
    est = load_segments([est_bag], desc)
    val = load_segments([val_bag], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    r = identify(est, val, desc, LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate),
                 check=chk)
    first = [d for d in r.decisions if d.round == 1]
    assert first and all(d.score.effect.depends_on_angle() for d in first), [
        d.score.label for d in first]  # the drift path: only effects in an angle
    assert [d.score.label for d in r.accepted] == ["gravity_load@carrier3"], [
        d.as_dict() for d in r.decisions]
    assert r.accepted[0].round == 1
    _validation_falls(r)
    assert r.drift is not None and r.drift.drifting == [], r.drift.summary()
    load = hidden.gravity_arm
    assert load is not None
    n = r.final.parameters()["reduction"]
    assert abs(n / load.stage.reduction - 1.0) <= 0.01, (n, load.stage.reduction)


@pytest.mark.slow
def test_clean_recordings_accept_nothing_with_the_position_candidates() -> None:
    """The committed clean recording with its validation recording: the new default
    candidates (gravity, periodic, the unlisted search) accept nothing in 3 rounds."""
    desc = load_description("dvt")
    est = load_segments([BAGS / "ident-none-1"], desc)
    val = load_segments([BAGS / "ident-none-val"], desc)
    chk = identifiability.check(desc, est)
    desc = identifiability.apply(desc, chk)
    cfg = LoopConfig.from_options(desc.fit, desc.preprocess.fit_decimate)
    assert cfg.max_effects >= 3
    r = identify(est, val, desc, cfg, check=chk)
    assert r.accepted == []
    assert r.final is r.baseline
    labels = {s.effect.name for s in r.rounds[0]}
    assert {"gravity_load", "periodic_disturbance"} <= labels


def test_no_prior_is_a_nominal_or_drawn_plant_value() -> None:
    """The description's priors and scan lists for the effects the plant hides are not the
    plant's values: the Stribeck candidates carry no speed (the scorer scans it from the data),
    the gravity scan (ISO 3 R5 preferred numbers) holds neither the nominal reduction nor a
    drawn one, and the compliant backlash's default gap grid does not hold the nominal gap."""
    desc = load_description("dvt")
    nominal = load_hidden("gravity_arm").gravity_arm
    assert nominal is not None
    drawn = [load_hidden("gravity_arm", draw=s).gravity_arm for s in range(200)]
    for c in desc.candidates:
        if c.effect == "stribeck_friction":
            assert "vs" not in c.options, c
        if c.effect == "gravity_load":
            scan = [float(n) for n in c.options["reductions"]]
            assert nominal.stage.reduction not in scan, scan
            assert not any(d is not None and d.stage.reduction in scan for d in drawn), scan
    spline = make_effect("backlash", "carrier3", ("sun_shaft", "carrier3"),
                         ("motor", "brake1", "brake2", "brake3"), options={"compliant": True})
    backlash = load_hidden("backlash").backlash
    assert backlash is not None
    view = SegmentView(1e-3, np.zeros((10, 4)), np.zeros((10, 2)))
    gap_name = spline.params[0].name
    gaps = {v[gap_name] for _, v in spline.variants(view)}
    assert gaps and backlash.gap not in gaps, gaps


NOT_DRAWN = {"g", "efficiency", "velocity_eps", "stage"}
"""Leaves of a position preset that a draw keeps: constants of physics and of the plant's
numerics, and the ripple's stage (discrete: the identifier tries every stage)."""


def _leaves(m: object, path: str = "") -> dict[str, object]:
    if isinstance(m, dict):
        out: dict[str, object] = {}
        for k, v in m.items():
            out.update(_leaves(v, f"{path}.{k}" if path else str(k)))
        return out
    return {path: m}


def test_the_drawn_plants_differ_from_the_nominal_presets() -> None:
    """The draws the tests use are draws: every drawn magnitude, length, angle and reduction
    differs from the preset's fixed (nominal) value, and the arm's drawn reduction is not one
    of the reductions the description scans, so no value the identifier could carry as a
    prior or a scan point is the truth by construction."""
    for preset in ("gravity_arm", "mesh_ripple", "position_friction"):
        drawn = _leaves(load_hidden(preset, draw=DRAW).to_mapping())
        nominal = _leaves(load_hidden(preset).to_mapping())
        assert drawn.keys() == nominal.keys(), preset
        same = [k for k in drawn if drawn[k] == nominal[k]
                and k.rsplit(".", 1)[-1] not in NOT_DRAWN]
        assert not same, (preset, same)
    arm = load_hidden("gravity_arm", draw=DRAW).gravity_arm
    assert arm is not None
    scanned = [c.options["reductions"] for c in load_description("dvt").make_candidates()
               if c.name == "gravity_load"]
    assert scanned and all(arm.stage.reduction not in r for r in scanned), scanned
