"""Mass, damping and input matrices, physical parameters and the arm requirement."""

import numpy as np
import pytest

from dvt_model.dynamics import check_mass_matrix, physical_from_identified, rigid_model
from dvt_model.errors import ModelError
from dvt_model.params import load_parameters
from dvt_model.requirements import baseline_requirement


def test_thesis_derivation_matrices_to_printed_digits():
    m = rigid_model(load_parameters("thesis-derivation"))
    # printed: M = [.001665 -.0059856; -.0059856 .028709]
    assert m.M[0, 0] == pytest.approx(0.001665, abs=5e-7)
    assert m.M[0, 1] == pytest.approx(-0.0059856, abs=5e-8)
    assert m.M[1, 1] == pytest.approx(0.028709, abs=5e-7)
    # printed: D = [.0265 -.04604; -.04604 .1180]
    assert m.D[0, 0] == pytest.approx(0.0265, abs=5e-5)
    assert m.D[0, 1] == pytest.approx(-0.04604, abs=5e-6)
    # D22 = 0.118079...: the thesis truncates it to .1180 (rounded it would be .1181)
    assert 0.1180 <= m.D[1, 1] < 0.1181
    # brake coupling -.492 / 1.492
    Q = m.Q(1)
    assert Q[:, 0].tolist() == [1.0, 0.0]
    assert Q[:, 1] == pytest.approx([-0.492, 1.492], abs=5e-4)


def test_thesis_printed_M22_slip_is_indefinite():
    printed = np.array([[0.001665, -0.0059856], [-0.0059856, 0.0028709]])
    with pytest.raises(ModelError, match="not positive definite"):
        check_mass_matrix(printed)


@pytest.mark.parametrize("name", ["thesis", "thesis-derivation", "physical"])
def test_model_is_consistent(name):
    m = rigid_model(load_parameters(name))
    check_mass_matrix(m.M)
    assert np.allclose(m.D, m.D.T)
    assert np.all(np.linalg.eigvalsh(m.D) >= 0)
    assert np.allclose(m.A, -np.linalg.solve(m.M, m.D))
    assert np.allclose(m.M @ m.B(2), m.Q(2))
    # passive: all eigenvalues of A in the open left half plane
    assert np.all(np.linalg.eigvals(m.A).real < 0)


def test_physical_from_identified_thesis_eq_4_98():
    A = np.array([[-1.4532, 2.5443], [-0.061856, -0.060044]])
    B = np.array([[2690.5, -911.31], [229.32, -10.956]])
    q = np.array([[0.3732, -0.492], [0.0, 1.492]])
    r = physical_from_identified(A, B, q)
    # printed J = [.0006057 -.005469; -.001906 .02236]; 4-digit inputs give 0.2 % spread
    assert pytest.approx(np.array([[0.0006057, -0.005469], [-0.001906, 0.02236]]),
                                rel=3e-3) == r.J
    assert r.b_thesis == pytest.approx(
        np.array([[-0.00054134, 0.00187], [0.0013866, -0.00619]]), rel=3e-3)
    assert np.allclose(r.D, -r.b_thesis)


def test_physical_from_identified_shape_errors():
    with pytest.raises(ModelError, match=r"A: expected shape \(2, 2\), got \(3, 2\)"):
        physical_from_identified(np.zeros((3, 2)), np.eye(2), np.eye(2))
    with pytest.raises(ModelError, match="B: singular"):
        physical_from_identified(np.eye(2), np.zeros((2, 2)), np.eye(2))


def test_round_trip_physical_from_model():
    m = rigid_model(load_parameters("thesis-derivation"))
    q = m.Q(1)
    r = physical_from_identified(m.A, m.B(1), q)
    assert np.allclose(r.J, m.M)
    assert np.allclose(r.D, m.D)


def test_arm_requirement_eq_1_1():
    req = baseline_requirement()
    assert req.torque == pytest.approx(3181.0, abs=2.0)
    assert req.torque < 3200.0
    assert req.power == pytest.approx(req.torque * 1.0)
    with pytest.raises(ValueError, match="length"):
        baseline_requirement(length=0.0)


def test_complete_variant_changes_a_and_b():
    t = rigid_model(load_parameters("thesis"))
    p = rigid_model(load_parameters("physical"))
    # the complete lumping is heavier on the output side and changes A markedly
    assert p.M[1, 1] > t.M[1, 1]
    assert np.linalg.norm(p.A - t.A) / np.linalg.norm(t.A) > 0.2
