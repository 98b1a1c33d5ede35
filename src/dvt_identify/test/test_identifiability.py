"""The check before fitting on the two-mass drive (tests/two_mass.py, one motor-speed sensor, a
free common angle): a declared model effect is kept and its influence measured away from its
null; the initial states are marginalised, so only parameters in a null direction get an
infinite predicted std; the DVT's experiments come from its descriptions.
"""

from __future__ import annotations

import copy
import importlib.resources
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import two_mass
import yaml

from dvt_identify import identifiability
from dvt_identify.advice import experiment_for
from dvt_identify.cli import main
from dvt_identify.data import JointStateSeries, Segment, write_jointstate_bag
from dvt_identify.description import load_description, parse_description
from dvt_identify.effects import make_effect
from dvt_identify.effects.base import SegmentView


def two_mass_spec() -> dict[str, Any]:
    """The bundled two-mass description as a fresh dict."""
    text = (importlib.resources.files("dvt_identify") / "descriptions"
            / "two-mass.yaml").read_text()
    spec: dict[str, Any] = yaml.safe_load(text)
    return spec


def declare(spec: dict[str, Any], effect: str) -> dict[str, Any]:
    """``spec`` with ``effect`` on the motor speed declared under ``model_effects`` (and no
    longer a candidate)."""
    out = copy.deepcopy(spec)
    out["model_effects"] = [{"effect": effect, "where": "w_motor"}]
    out["candidates"] = [c for c in spec["candidates"] if c["effect"] != effect]
    return out


def write_bag(path: Path, seg: Segment) -> Path:
    """``seg`` (torque in, motor speed out) as the bag the two-mass description reads."""
    stamps = (10**9 + np.round(seg.t * 1e9)).astype(np.int64)
    return write_jointstate_bag(path, {
        "/twomass/joint_states": JointStateSeries(stamps, ("motor",), velocity=seg.y[:, :1]),
        "/twomass/drive": JointStateSeries(stamps, ("motor",), effort=seg.u[:, :1]),
    })


def by_name(chk: identifiability.Identifiability) -> dict[str, identifiability.ParameterCheck]:
    return {p.name: p for p in chk.parameters}


# (a) a declared effect is kept ------------------------------------------------------------

def test_a_declared_sensor_gain_is_kept_and_its_scale_direction_stated() -> None:
    """A sensor gain at its prior 0 changes nothing, yet it acts: it is kept (apply leaves it
    in the model), its influence at the probe is measured, and the check states first that it
    and the structure's scale are still fitted but not determined (with one torque input and
    one speed sensor, a gain moves the output exactly like scaling every mass, damper and
    spring)."""
    desc = parse_description(declare(two_mass_spec(), "sensor_gain"), "tm-gain.yaml")
    chk = identifiability.check(desc, [two_mass.record("est")])
    assert chk.removed_effects == []
    assert [e.label() for e in identifiability.apply(desc, chk).make_model_effects()] == [
        "sensor_gain@w_motor"]
    assert chk.influence["sensor_gain@w_motor"] > identifiability.NO_INFLUENCE \
        * chk.residual_level
    p = by_name(chk)
    assert not p["gain_w_motor"].fixed and p["gain_w_motor"].probe == pytest.approx(0.1)
    for name in ("Jm", "Jl", "k", "c", "dm", "dl", "gain_w_motor"):
        assert math.isinf(p[name].predicted_relative_std), name
        assert "only together with" in p[name].reason
    head = chk.summary()
    assert head[1].startswith("Still fitted, their values not to be trusted:") \
        and "gain_w_motor" in head[1]


def test_a_probe_values_are_neutral_and_non_zero() -> None:
    """Each effect at its null is probed at a value of meaningful size: its own probe where it
    has one (sign-blind b = 1, saturation at the measured top), else 100 finite-difference
    steps within its bounds; a prior away from the null is kept."""
    desc = load_description("two-mass")
    seg = two_mass.record("est", seconds=5.0)
    view = SegmentView(seg.dt, seg.u, seg.y)

    def probe(effect: str, **options: object) -> float:
        eff = make_effect(effect, "w_motor", desc.state_names, desc.input_names,
                          options=dict(options), output_names=desc.output_names)
        return float(identifiability.probe_values(eff, view)[0])

    assert probe("sign_blind") == 1.0
    assert probe("sensor_gain") == pytest.approx(0.1)
    assert probe("measurement_delay", max_delay=0.02) == pytest.approx(0.02)
    assert probe("sensor_saturation") == pytest.approx(float(np.max(np.abs(seg.y))))
    assert probe("sensor_offset") == pytest.approx(0.1)
    gain = make_effect("sensor_gain", "w_motor", desc.state_names, desc.input_names,
                       output_names=desc.output_names).with_initial({"gain": -0.2})
    assert identifiability.probe_values(gain, view)[0] == pytest.approx(-0.2)


# (b) finite figures with a free angle ------------------------------------------------------

def test_b_check_on_two_mass_gives_finite_figures_and_determines_the_shaft(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dvt-identify --check`` on a two-mass bag: every parameter has a finite predicted std
    (the common angle, which no speed sees, is marginalised), the shaft's stiffness and
    damping are determined, and every figure is printed."""
    path = tmp_path / "two-mass.yaml"
    path.write_text(yaml.safe_dump(two_mass_spec(), sort_keys=False))
    bag = write_bag(tmp_path / "est", two_mass.record("est"))
    assert main([str(bag), "--check", "--out", str(tmp_path / "chk"), "--description",
                 str(path)]) == 0
    out = capsys.readouterr().out
    rep = json.loads((tmp_path / "chk" / "check.json").read_text())
    q = {p["name"]: p for p in rep["parameters"]}
    assert all(p["predicted_relative_std"] is not None for p in q.values()), q
    assert q["c"]["determined"] and q["k"]["determined"]
    for name in ("Jm", "Jl", "k", "c", "dm", "dl"):
        assert f"  {name}: " in out and "infinite" not in out


def stiff_records(monkeypatch: pytest.MonkeyPatch) -> tuple[dict[str, Any], list[Segment]]:
    """A stiff shaft (k 2000 N m/rad, mode 82 Hz) sampled at 1 kHz for 8 s, and its
    description (priors near the truth): the initial angles then weigh far more in the
    information than the damping does."""
    monkeypatch.setitem(two_mass.TRUE, "k", 2000.0)
    monkeypatch.setattr(two_mass, "RATE", 1000.0)
    spec = two_mass_spec()
    spec["structure"]["parameters"]["k"]["initial"] = 1500.0
    desc = parse_description(spec, "stiff.yaml")
    return spec, [two_mass.record("est", seconds=8.0, desc=desc)]


def test_b_a_stiff_shaft_keeps_finite_figures_for_every_parameter(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """No parameter of the stiff two-mass drive lies in a null direction of the marginal
    information, so none gets an infinite predicted std (an eigen-decomposition of the whole
    information matrix with the initial states put the damping's weak directions under its
    tolerance together with the free angle and reported them all infinite)."""
    spec, est = stiff_records(monkeypatch)
    desc = parse_description(spec, "stiff.yaml")
    chk = identifiability.check(desc, est)
    figs = {p.name: p.predicted_relative_std for p in chk.parameters}
    assert all(math.isfinite(v) for v in figs.values()), figs
    assert by_name(chk)["k"].determined


def test_b_a_duplicated_parameter_is_still_infinite(monkeypatch: pytest.MonkeyPatch) -> None:
    """A damper ``dx`` in parallel with ``dm`` (another prior) moves the outputs exactly as
    ``dm`` does: both get an infinite predicted std and name each other; every other parameter
    keeps a finite figure."""
    spec, est = stiff_records(monkeypatch)
    spec["structure"]["damping"] = [["c + dm + dx", "-c"], ["-c", "c + dl"]]
    spec["structure"]["parameters"]["dx"] = {"initial": 0.004, "lower": 0.0}
    chk = identifiability.check(parse_description(spec, "stiff-dup.yaml"), est)
    p = by_name(chk)
    assert math.isinf(p["dm"].predicted_relative_std) and "together with dx" in p["dm"].reason
    assert math.isinf(p["dx"].predicted_relative_std) and "together with dm" in p["dx"].reason
    rest = {n: q.predicted_relative_std for n, q in p.items() if n not in ("dm", "dx")}
    assert all(math.isfinite(v) for v in rest.values()), rest


# (d) the DVT's experiments live in its descriptions ----------------------------------------

@pytest.mark.parametrize("name", ["dvt", "dvt-position", "dvt-thesis"])
def test_d_dvt_descriptions_name_their_experiments(name: str) -> None:
    table = load_description(name).experiments
    assert experiment_for("band_gain_ring2", table) == (
        "dvt-experiment ident_shifts",
        "band 2 engaging against a slipping ring (gain and lag show only while the band slips)")
    assert experiment_for("td_brakes", table) == (
        "dvt-experiment ident_shifts", "band engagements against slipping rings")
    for param in ("M22", "A11"):  # the mass entries, and the catch-all for the rest
        row = experiment_for(param, table)
        assert row is not None and row[0] == "dvt-experiment ident"


# (e) the Fisher rule taken again at the fitted values ----------------------------------------

def scale_only(spec: dict[str, Any]) -> dict[str, Any]:
    """``spec`` with every structure prior 1 (a description that gives scales only): the
    two-mass drive's zeros then cancel its mode (from the motor torque to the motor speed,
    ``1 / (s + 2)``)."""
    out = copy.deepcopy(spec)
    for p in out["structure"]["parameters"].values():
        p["initial"] = 1.0
    return out


def noise_level(seg: Segment) -> float:
    """The simulated sensor noise over the output's standard deviation."""
    return two_mass.NOISE / float(np.std(seg.y[:, 0]))


def test_e_a_degenerate_prior_is_revised_at_the_fitted_values() -> None:
    """At every prior 1 the check finds the shaft in a null direction (infinite figures);
    taken again at the drive's values with the fit's residual level it determines what the
    priors hid, each with its reason at the priors kept, and gives the others the verdict at
    the fit (a finite figure)."""
    desc = parse_description(scale_only(two_mass_spec()), "ones.yaml")
    est = [two_mass.record("est", desc=desc)]
    pre = identifiability.check(desc, est)
    hidden = {p.name for p in pre.parameters if p.kind == "null"}
    assert {"Jl", "k", "c"} <= hidden, [(p.name, p.kind) for p in pre.parameters]
    post = identifiability.at_fit(pre, desc, est, two_mass.TRUE, noise_level(est[0]))
    p = by_name(post)
    assert {"Jl", "k", "c"} <= set(post.revised), post.revised
    for name in post.revised:
        assert p[name].determined and p[name].predicted_relative_std < 1.0
        assert post.revised[name] == by_name(pre)[name].reason
        assert p[name].prior == 1.0
    assert all(math.isfinite(q.predicted_relative_std) for q in post.parameters)
    assert not post.undetermined or "Determined at the fitted values" in post.headline()[-1]


def test_e_a_duplicated_parameter_stays_undetermined_at_the_fit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """What no value can separate stays undetermined at the fitted values: the parallel
    dampers ``dm`` and ``dx`` keep their infinite figures and are not revised."""
    spec, est = stiff_records(monkeypatch)
    spec["structure"]["damping"] = [["c + dm + dx", "-c"], ["-c", "c + dl"]]
    spec["structure"]["parameters"]["dx"] = {"initial": 0.004, "lower": 0.0}
    desc = parse_description(spec, "stiff-dup.yaml")
    pre = identifiability.check(desc, est)
    post = identifiability.at_fit(pre, desc, est, {**two_mass.TRUE, "dx": 0.002},
                                  noise_level(est[0]))
    p = by_name(post)
    assert "dm" not in post.revised and "dx" not in post.revised
    assert math.isinf(p["dm"].predicted_relative_std) and not p["dm"].determined
    assert math.isinf(p["dx"].predicted_relative_std) and not p["dx"].determined


def test_e_the_report_takes_the_verdict_at_the_fit(tmp_path: Path) -> None:
    """``dvt-identify`` on a scale-only two-mass description: the fit recovers the drive, and
    the report no longer calls the parameters the priors hid "not to be trusted": they are
    listed as determined at the fitted values (report.json ``determined_at_fit``, a table in
    report.md), and no warning names them."""
    spec = scale_only(two_mass_spec())
    path = tmp_path / "ones.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    desc = parse_description(spec, str(path))
    est = write_bag(tmp_path / "est", two_mass.record("est", seconds=10.0, desc=desc))
    val = write_bag(tmp_path / "val", two_mass.record("val", seconds=10.0, desc=desc))
    assert main([str(est), "--validate", str(val), "--out", str(tmp_path / "rep"),
                 "--description", str(path), "--no-plots"]) == 0
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    revised = rep["identifiability"]["determined_at_fit"]
    assert {"Jl", "k", "c"} <= set(revised), revised
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "**Determined at the fitted values**" in md
    for name in revised:
        assert not any(w.startswith(f"{name}: not determined") for w in rep["warnings"]), (
            rep["warnings"])
