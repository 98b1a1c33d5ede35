"""Actuator descriptions: bundled EMPS, structure types, plug-in class, errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from dvt_identify.description import available_descriptions, load_description, parse_description
from dvt_identify.errors import DescriptionError
from dvt_identify.structures import MechanicalStructure, ModelStructure


def _base() -> dict[str, Any]:
    return {
        "inputs": [{"name": "motor", "topic": "/d/currents", "field": "effort",
                    "joint": "drive_motor"},
                   {"name": "brake", "topic": "/d/currents", "field": "effort",
                    "joint": "brake1"}],
        "outputs": [{"name": "sun", "topic": "/d/joint_states", "field": "velocity",
                     "joint": "sun_shaft"},
                    {"name": "carrier", "topic": "/d/joint_states", "field": "velocity",
                     "joint": "carrier3"}],
        "structure": {"type": "state_space", "A": [["A11", "A12"], ["A21", "A22"]],
                      "B": [["B11", "B12"], ["B21", "B22"]], "speed_unit": "rad/s",
                      "parameters": {n: 0.0 for n in ("A11", "A12", "A21", "A22", "B11",
                                                      "B12", "B21", "B22")}},
        "candidates": [
            {"effect": "coulomb_friction", "where": "sun"},
            {"effect": "coulomb_friction", "where": "carrier"},
            {"effect": "brake_lockup", "where": "ring", "member": {"sun": 0.2, "carrier": -1.2},
             "input": "brake"},
            {"effect": "brake_engagement", "where": "brake"},
        ],
    }


def test_bundled_emps() -> None:
    assert "emps" in available_descriptions()
    d = load_description("emps")
    assert d.input_names == ("force",) and d.output_names == ("carriage",)
    assert isinstance(d.structure, MechanicalStructure)
    assert [p.name for p in d.structure.params] == ["M", "Fv"]
    names = [c.name for c in d.make_candidates()]
    assert names[0] == "coulomb_friction" and "asymmetric_friction" in names
    assert d.inputs[0].saturation == (-351.5, 351.5)


def test_free_two_by_two_description_with_member_vector() -> None:
    d = parse_description(_base(), "t.yaml")
    c = d.make_candidates()
    assert [p.name for p in c[0].params] == ["Fc_sun", "offset_sun"]  # made unique
    assert c[2].member is not None and c[2].member == pytest.approx([0.2, -1.2])
    assert c[2].index == 1 and c[3].index == 1


def test_python_structure_plugin() -> None:
    data = _base()
    data["structure"] = {"type": "python", "class": "dvt_identify.structures:StateSpaceStructure",
                         "options": {"A": [["a", 0.0], [0.0, "a"]], "B": [[1.0, 0.0], [0.0, 1.0]],
                                     "parameters": {"a": -1.0}}}
    d = parse_description(data, "t.yaml")
    assert isinstance(d.structure, ModelStructure)
    a, _, _ = d.structure.matrices(np.array([-3.0]))
    np.testing.assert_allclose(a, -3.0 * np.eye(2))


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.pop("outputs"), r"t.yaml: missing key 'outputs'"),
    (lambda d: d["candidates"].append({"effect": "magic", "where": "sun"}),
     r"candidates\[4\].effect: 'magic' is not a candidate effect"),
    (lambda d: d["structure"].update(type="neural"), r"structure.type: expected state_space"),
    (lambda d: d["structure"].update(A=[["A11", "x"], ["A21", "A22"]]),
     r"structure.A\[0\]\[1\]: 'x' is not a number"),
    (lambda d: d["inputs"][0].update(field="current"), r"inputs\[0\].field: expected position"),
    (lambda d: d["candidates"].append({"effect": "windage", "where": "ring"}),
     r"where 'ring' is not a state/output"),
    (lambda d: d["structure"].update(type="python", **{"class": "nope.mod:X"}),
     r"structure.class: cannot import 'nope.mod:X'"),
    (lambda d: d.update(fit={"stars": 3}), r"preprocess/checks/fit"),
])
def test_description_errors_name_file_and_key(edit: Any, match: str) -> None:
    data = _base()
    edit(data)
    with pytest.raises(DescriptionError, match=match):
        parse_description(data, "t.yaml")


def test_load_from_file_and_unknown_name(tmp_path: Path) -> None:
    p = tmp_path / "act.yaml"
    p.write_text(yaml.safe_dump(_base()))
    assert load_description(p).output_names == ("sun", "carrier")
    with pytest.raises(DescriptionError, match="no bundled description of that name"):
        load_description("no_such_actuator")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(DescriptionError, match="not valid YAML"):
        load_description(bad)
