"""Advice from the user's description, never the DVT's, and a declared sensor map fitted: the
two-mass drive of tests/two_mass.py through bags, ``dvt-identify --check`` and the whole
pipeline.
"""

from __future__ import annotations

import copy
import importlib.resources
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import two_mass
import yaml

from dvt_identify import pipeline
from dvt_identify.cli import main
from dvt_identify.data import JointStateSeries, Segment, write_jointstate_bag
from dvt_identify.description import parse_description
from dvt_identify.errors import DescriptionError

OWN = [{"parameters": "^d(?P<side>[ml])$", "run": "torque ramps held 20 s each way",
        "excites": "the damper to ground on side {side}"}]


def two_mass_spec(**extra: Any) -> dict[str, Any]:
    text = (importlib.resources.files("dvt_identify") / "descriptions"
            / "two-mass.yaml").read_text()
    spec: dict[str, Any] = yaml.safe_load(text)
    spec.update(copy.deepcopy(extra))
    return spec


def write_bag(path: Path, seg: Segment) -> Path:
    stamps = (10**9 + np.round(seg.t * 1e9)).astype(np.int64)
    return write_jointstate_bag(path, {
        "/twomass/joint_states": JointStateSeries(stamps, ("motor",), velocity=seg.y[:, :1]),
        "/twomass/drive": JointStateSeries(stamps, ("motor",), effort=seg.u[:, :1]),
    })


@pytest.fixture(scope="module")
def est_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_bag(tmp_path_factory.mktemp("tm") / "est", two_mass.record("est"))


def run_check(tmp_path: Path, bag: Path, spec: dict[str, Any],
              capsys: pytest.CaptureFixture[str]) -> tuple[str, dict[str, Any]]:
    path = tmp_path / "desc.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    assert main([str(bag), "--check", "--out", str(tmp_path / "chk"), "--description",
                 str(path)]) == 0
    return capsys.readouterr().out, json.loads((tmp_path / "chk" / "check.json").read_text())


# (c) the description's own experiments, else generic advice --------------------------------

def test_c_own_experiments_give_the_advice(tmp_path: Path, est_bag: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    out, rep = run_check(tmp_path, est_bag, two_mass_spec(experiments=OWN), capsys)
    q = {p["name"]: p for p in rep["parameters"]}
    assert rep["not_determined"] == ["dm", "dl"]
    assert (q["dm"]["experiment"], q["dm"]["purpose"], q["dm"]["advice_from"]) == (
        "torque ramps held 20 s each way", "the damper to ground on side m", "description")
    assert q["dl"]["purpose"] == "the damper to ground on side l"
    assert rep["experiments"] == ["torque ramps held 20 s each way"]
    assert out.strip().splitlines()[-1] == "enough: no, record torque ramps held 20 s each way"
    assert "dvt-experiment" not in out


def test_c_without_experiments_the_advice_is_generic(tmp_path: Path, est_bag: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """No ``experiments`` section: the advice names the pole the damper moves, the band that
    excites it and how much longer a record would have to be; never a DVT command."""
    out, rep = run_check(tmp_path, est_bag, two_mass_spec(), capsys)
    assert "dvt-experiment" not in out and "dvt-experiment" not in json.dumps(rep)
    assert rep["experiments"] == [] and len(rep["advice"]) == 2
    dm = next(p for p in rep["parameters"] if p["name"] == "dm")
    assert dm["advice_from"] == "generic"
    assert "below" in dm["experiment"] and "Hz" in dm["experiment"]
    assert "x as long" in dm["experiment"] and "time constant" in dm["purpose"]
    assert out.splitlines()[0].startswith("The recording does not determine 2 of 6 parameters")
    assert out.strip().splitlines()[-1] == "enough: no, see the advice above"


@pytest.mark.parametrize(("rows", "message"), [
    ("not a list", "experiments: expected a list"),
    ([{"parameters": "^(M", "run": "x", "excites": "y"}],
     "experiments[0].parameters: '^(M' is not a regular expression"),
    ([{"parameters": "^M$", "excites": "y"}], "experiments[0]: missing key 'run'"),
    ([{"parameters": "^M$", "run": "", "excites": "y"}],
     "experiments[0].run: expected a non-empty text, got ''"),
    ([{"parameters": "^M$", "run": "x", "excites": "y", "when": "z"}],
     "experiments[0]: unknown key(s) ['when']"),
    ([{"parameters": "^M(?P<n>\\d)$", "run": "x", "excites": "band {k}"}],
     "experiments[0].excites: 'band {k}' names 'k' that is not a named group"),
])
def test_c_experiments_are_validated_on_load(rows: object, message: str) -> None:
    with pytest.raises(DescriptionError) as exc:
        parse_description(two_mass_spec(experiments=rows), "mine.yaml")
    assert str(exc.value).startswith("mine.yaml: experiments")
    assert message in str(exc.value), str(exc.value)


# (a) a declared sensor map is fitted, and the report says what is not determined first ----

@pytest.mark.slow
def test_a_declared_sign_blind_sensor_is_kept_fitted_and_reported(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The user declares the sign-blind map of the motor-speed sensor under ``model_effects``
    (prior b = 0, where it has no influence): the whole pipeline keeps and fits it (b near 1),
    the report opens with what the recording does not determine, with generic advice."""
    spec = two_mass_spec(model_effects=[{"effect": "sign_blind", "where": "w_motor"}],
                         candidates=[], fit={"starts": 1, "refit_starts": 1})
    path = tmp_path / "tm-sign-blind.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    est = write_bag(tmp_path / "est", two_mass.record("est", sign_blind=True))
    val = write_bag(tmp_path / "val", two_mass.record("val", sign_blind=True))
    res = pipeline.run([est], [val], tmp_path / "out", str(path), augment=False, quiet=True,
                       plots=False, series=False)
    assert res.identifiability is not None and res.identifiability.removed_effects == []
    assert [e.label() for e in res.final.effects] == ["sign_blind@w_motor"]
    assert res.final.parameters()["sign_blind_w_motor"] == pytest.approx(1.0, abs=0.02)
    assert res.final.val.fit_percent[0] > 95.0
    md = (tmp_path / "out" / "report.md").read_text()
    assert "dvt-experiment" not in md
    assert md.index("## Is this recording enough?") < md.index("## Summary")
    # before fitting dm and dl (the dampers to ground) read as barely excited; taken again at
    # the fit with its own residual (identifiability.at_fit) dl is determined, dm still not
    assert "**Still fitted, not to be trusted:** dm." in md
    assert "**Determined at the fitted values**" in md and "| dl | " in md
    err = capsys.readouterr().err
    assert "[dvt-identify] check: The recording does not determine 2 of 7 parameters" in err
