"""Parameter files: bundled sets load, bad files are refused with key and value named."""

import pytest
import yaml

from dvt_model.errors import ParameterError
from dvt_model.params import available_parameter_sets, load_parameters, parse_parameters


def test_bundled_sets():
    assert {"thesis", "thesis-derivation", "physical"} <= set(available_parameter_sets())
    p = load_parameters("thesis")
    assert p.stages[2].ring == 123
    assert load_parameters("thesis-derivation").stages[2].ring == 122
    assert p.motor_constant == pytest.approx(0.3732)
    assert p.b_carrier == (0.0075, 0.0075, 0.0075)


def _base():
    from importlib import resources
    text = (resources.files("dvt_model") / "param_sets" / "thesis.yaml").read_text()
    return yaml.safe_load(text)


@pytest.mark.parametrize(("edit", "match"), [
    (lambda d: d["stages"][2].update(ring=12), r"stages\[2\]\.ring: 12 teeth"),
    (lambda d: d["stages"][0].update(sun=0), r"stages\[0\]\.sun: expected a positive integer, got 0"),
    (lambda d: d["inertia"].update(sun=-1.0), r"inertia\.sun: expected a number > 0, got -1\.0"),
    (lambda d: d["inertia"].update(carrier=[1, 2]), r"inertia\.carrier: expected a list of 3"),
    (lambda d: d.update(motor_constant="x"), r"motor_constant: expected a number, got 'x'"),
    (lambda d: d.update(motor_constant=float("nan")), r"motor_constant: expected a finite"),
    (lambda d: d.update(lumping="other"), r"lumping: expected 'thesis' or 'complete'"),
    (lambda d: d.update(bogus=1), r"bogus: unknown key"),
    (lambda d: d["brake"].pop("time_constant"), r"brake\.time_constant: missing"),
    (lambda d: d["damping"].update(carrier=[0.1, -0.1, 0.1]),
     r"damping\.carrier\[1: expected a number >= 0, got -0\.1"),
])
def test_bad_values_name_key_and_value(edit, match):
    data = _base()
    edit(data)
    with pytest.raises(ParameterError, match=match):
        parse_parameters(data, source="bad.yaml")


def test_bad_files(tmp_path):
    with pytest.raises(ParameterError, match="unknown parameter set 'nope'"):
        load_parameters("nope")
    bad = tmp_path / "broken.yaml"
    bad.write_text("stages: [\n")
    with pytest.raises(ParameterError, match="broken.yaml: not valid YAML"):
        load_parameters(bad)
    missing = tmp_path / "missing.yaml"
    with pytest.raises(ParameterError, match="missing.yaml: cannot read"):
        load_parameters(missing)
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n")
    with pytest.raises(ParameterError, match="list.yaml: expected a mapping"):
        load_parameters(top)


def test_file_round_trip(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(_base()))
    assert load_parameters(path).stages == load_parameters("thesis").stages
