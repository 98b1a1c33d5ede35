"""Linear model structures: the protocol, parametrised matrices."""

from __future__ import annotations

import numpy as np
import pytest

from dvt_identify.errors import DescriptionError
from dvt_identify.structures import (
    MechanicalStructure,
    ModelStructure,
    ParamMatrix,
    StateSpaceStructure,
)

A_TRUE = np.array([[-2.0, 1.5], [-3.0, -4.0]])
B_TRUE = np.array([[1.0, 0.0], [0.5, 2.0]])


def _free_2x2() -> StateSpaceStructure:
    names = ["A11", "A12", "A21", "A22", "B11", "B12", "B21", "B22"]
    params = {n: {"initial": 0.0} for n in names}
    return StateSpaceStructure(["w1", "w2"], ["u1", "u2"],
                               [["A11", "A12"], ["A21", "A22"]],
                               [["B11", "B12"], ["B21", "B22"]], params, speed_unit="rad/s")


def test_structures_satisfy_the_protocol_and_build_matrices() -> None:
    st = _free_2x2()
    assert isinstance(st, ModelStructure)
    a, b, f = st.matrices(np.concatenate([A_TRUE.ravel(), B_TRUE.ravel()]))
    np.testing.assert_allclose(a, A_TRUE)
    np.testing.assert_allclose(b, B_TRUE)
    np.testing.assert_allclose(f, np.eye(2))
    mech = MechanicalStructure(["v"], ["F"], [["M"]], [["Fv"]], [[2.0]],
                               {"M": {"initial": 4.0}, "Fv": 8.0})
    A, B, F = mech.matrices(np.array([4.0, 8.0]))
    assert (A[0, 0], B[0, 0], F[0, 0]) == pytest.approx((-2.0, 0.5, 0.25))


def test_param_matrix_entries_and_errors() -> None:
    pm = ParamMatrix([["-a", "2.5*b"], [1.0, "0"]], "X", ["a", "b"])
    assert pm(np.array([2.0, 4.0])) == pytest.approx(np.array([[-2.0, 10.0], [1.0, 0.0]]))
    with pytest.raises(DescriptionError, match=r"X\[0\]\[1\]: 'c' is not a number"):
        ParamMatrix([["a", "c"]], "X", ["a"])
    with pytest.raises(DescriptionError, match=r"X: expected shape \(2, 2\), got \(1, 2\)"):
        ParamMatrix([["a", "a"]], "X", ["a"], (2, 2))
