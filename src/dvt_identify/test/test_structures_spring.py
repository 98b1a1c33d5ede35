"""Mechanical structures with springs and hidden states (SpringMechanicalStructure)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from dvt_identify.data import make_segment
from dvt_identify.description import load_description, parse_description
from dvt_identify.effects import make_effect
from dvt_identify.errors import DescriptionError, FitError
from dvt_identify.fit import OEFit
from dvt_identify.simulation import OEModel
from dvt_identify.structures import (
    ParamMatrix,
    SpringMechanicalStructure,
    initial_state,
    output_matrix,
    output_names,
)

PARAMS = {"Jm": 0.01, "Jl": 0.03, "k": 20.0, "c": 0.02, "dm": 0.005, "dl": 0.01}


def two_mass(outputs: dict[str, str] | None = None,
             names: tuple[str, ...] = ("w_motor",)) -> SpringMechanicalStructure:
    return SpringMechanicalStructure(
        ["motor", "load"], names, ["torque"], [["Jm", 0], [0, "Jl"]],
        [["c + dm", "-c"], ["-c", "c + dl"]], [["k", "-k"], ["-k", "k"]], [[1.0], [0.0]],
        dict(PARAMS), outputs if outputs is not None else {"w_motor": "motor"})


def test_param_matrix_entries_may_be_sums() -> None:
    pm = ParamMatrix([["c + dm", "-c"], ["2*k - 0.5", "1e-3"]], "D", ["c", "dm", "k"])
    th = np.array([0.2, 0.05, 3.0])
    assert np.allclose(pm(th), [[0.25, -0.2], [5.5, 1e-3]])
    assert np.allclose(ParamMatrix([["-0.5k"]], "X", ["k"])(np.array([4.0])), [[-2.0]])
    with pytest.raises(DescriptionError, match=r"D\[0\]\[0\]: 'c \+ zz'"):
        ParamMatrix([["c + zz"]], "D", ["c"])
    with pytest.raises(DescriptionError, match="not a number or a sum"):
        ParamMatrix([["c dm"]], "D", ["c", "dm"])


def test_matrices_are_the_second_order_system() -> None:
    st = two_mass()
    th = np.array([PARAMS[p.name] for p in st.params])
    A, B, F = st.matrices(th)
    M = np.diag([0.01, 0.03])
    K = np.array([[20.0, -20.0], [-20.0, 20.0]])
    D = np.array([[0.025, -0.02], [-0.02, 0.03]])
    Mi = np.linalg.inv(M)
    assert st.state_names == ("motor_angle", "load_angle", "motor", "load")
    want = np.block([[np.zeros((2, 2)), np.eye(2)], [-Mi @ K, -Mi @ D]])
    assert np.allclose(A, want)
    assert np.allclose(B, np.array([[0.0], [0.0], [100.0], [0.0]]))
    assert np.allclose(F[2:, 2:], Mi) and not np.any(F[:2]) and not np.any(F[:, :2])
    C = output_matrix(st)
    assert C is not None and np.array_equal(C, [[0, 0, 1, 0]])
    assert output_names(st) == ("w_motor",)
    # the mode: wn^2 = k (1/Jm + 1/Jl) (light damping: the damped pair is within 0.1 %)
    md = st.modes(th)
    assert len(md) == 1
    assert md[0]["frequency_hz"] == pytest.approx(math.sqrt(20 * (100 + 100 / 3)) / (2 * math.pi),
                                                  rel=1e-3)
    assert 0.02 < md[0]["damping_ratio"] < 0.04
    assert st.physical(th)["mode1_frequency_hz"] == md[0]["frequency_hz"]


def test_outputs_map_any_subset_of_states_with_exact_errors() -> None:
    st = two_mass({"q_load": "load_angle", "w_motor": "motor"}, ("w_motor", "q_load"))
    assert np.array_equal(st.output_matrix(), [[0, 0, 1, 0], [0, 1, 0, 0]])
    x0 = initial_state(st, np.array([3.0, 0.5]))
    assert np.allclose(x0, [0.5, 0.5, 3.0, 3.0])  # hidden ones at the measured mean
    with pytest.raises(DescriptionError, match=r"\['belt'\] are not states"):
        two_mass({"w_motor": "belt"})
    with pytest.raises(DescriptionError, match=r"missing \['w_motor'\]"):
        two_mass({})
    with pytest.raises(DescriptionError, match=r"stiffness: expected shape \(2, 2\), got \(1, 1\)"):
        SpringMechanicalStructure(["a", "b"], ["a"], ["u"], [["m", 0], [0, "m"]],
                                  [[0, 0], [0, 0]], [["k"]], [[1.0], [0.0]],
                                  {"m": 1.0, "k": 1.0})
    # a structure without hidden states has C = I
    assert output_matrix(load_description("emps").structure) is None


def test_model_simulates_outputs_through_c_and_checks_x0() -> None:
    st = two_mass()
    model = OEModel(st)
    n = 400
    t = np.arange(n) * 0.005
    seg = make_segment("s", t, np.where(t < 1.0, 0.1, 0.0), np.zeros(n), ["torque"], ["w_motor"])
    th = np.array([PARAMS[p.name] for p in st.params])
    x, y = model.simulate_states(th, seg, np.zeros(4))
    assert x.shape == (n, 4) and y.shape == (n, 1)
    assert np.array_equal(y[:, 0], x[:, 2])
    # the motor angle is the integral of its speed (trapezoid rule against the exact hold:
    # its error is of order dt^2 x the acceleration's change, below 1e-3 rad here)
    trap = np.concatenate([[0.0], np.cumsum(0.5 * (x[1:, 2] + x[:-1, 2])) * 0.005])
    assert np.max(np.abs(x[:, 0] - trap)) < 1e-3
    with pytest.raises(FitError, match=r"x0: expected shape \(4,\), got \(1,\)"):
        model.simulate(th, seg, np.zeros(1))


def test_fit_estimates_hidden_initial_states() -> None:
    """A short record that starts with the shaft wound up and the load moving: the fit
    recovers the parameters and the hidden initial states (load speed, shaft twist)."""
    st = two_mass()
    model = OEModel(st)
    rng = np.random.default_rng(5)
    dt = 0.005
    n = 2000
    u = np.repeat(rng.uniform(-0.2, 0.2, n // 40), 40)
    seg = make_segment("s", np.arange(n) * dt, u, np.zeros(n), ["torque"], ["w_motor"])
    th = np.array([PARAMS[p.name] for p in st.params])
    x0 = np.array([0.01, 0.0, 0.5, 2.0])
    y = model.simulate(th, seg, x0) + 0.01 * rng.standard_normal((n, 1))
    seg = make_segment("s", seg.t, u, y, ["torque"], ["w_motor"])
    fit = OEFit(model, starts=2).fit([seg])
    got = fit.theta_
    std = fit.std_
    for i, p in enumerate(st.params):
        assert abs(got[i] - PARAMS[p.name]) < 4 * std[i] + 1e-9, (p.name, got[i], std[i])
    # the twist (q_m - q_l) and both speeds are observable; the common angle is not
    est = fit.x0_[0]
    assert est[0] - est[1] == pytest.approx(0.01, abs=1e-3)
    assert est[2:] == pytest.approx([0.5, 2.0], abs=0.05)


def _desc(extra: dict[str, object]) -> dict[str, object]:
    raw = yaml.safe_load(load_description("two-mass").text)
    raw.update(extra)
    return dict(raw)


def test_description_builds_effects_on_members_and_outputs() -> None:
    desc = load_description("two-mass")
    assert desc.state_names == ("motor_angle", "load_angle", "motor", "load")
    assert desc.output_names == ("w_motor",)
    fx = {e.label(): e for e in desc.make_candidates()}
    assert fx["sign_blind@w_motor"].index == 0  # an output index
    assert np.array_equal(fx["coulomb_friction@load"].require_member(), [0, 0, 0, 1])  # speed
    assert fx["measurement_delay@w_motor"].index == 0
    # a member vector by state name
    d2 = parse_description(_desc({"candidates": [
        {"effect": "coulomb_friction", "where": "load", "member": {"motor": 1, "load": -1}}]}),
        "x.yaml")
    assert np.array_equal(d2.make_candidates()[0].require_member(), [0, 0, 1, -1])
    # an output effect on a hidden state is refused with the outputs named
    with pytest.raises(DescriptionError, match="'load' is not a measured output"):
        make_effect("sign_blind", "load", desc.state_names, desc.input_names,
                    output_names=desc.output_names)


def test_parameter_clashes_are_refused_on_loading_with_the_names() -> None:
    raw = _desc({"candidates": [{"effect": "measurement_delay", "where": "w_motor"}]})
    st = raw["structure"]
    assert isinstance(st, dict)
    st["parameters"]["delay"] = 0.001
    st["damping"] = [["c + dm + 0*delay", "-c"], ["-c", "c + dl"]]
    with pytest.raises(DescriptionError,
                       match=r"duplicate parameter names: delay \(structure, "
                             r"measurement_delay@w_motor\)"):
        parse_description(raw, "clash.yaml")


def test_spring_to_ground_with_a_measured_angle() -> None:
    """One mass on a spring to ground, only its angle measured (its speed hidden): the fit
    recovers m, d, k and the hidden initial speed."""
    desc = parse_description({
        "name": "pendulum",
        "inputs": [{"name": "u", "topic": "/p/drive", "field": "effort", "joint": "p"}],
        "outputs": [{"name": "q", "topic": "/p/joint_states", "field": "position",
                     "joint": "p"}],
        "structure": {"type": "mechanical", "members": ["arm"], "mass": [["m"]],
                      "damping": [["d"]], "stiffness": [["k"]], "input_matrix": [[1.0]],
                      "outputs": {"q": "arm_angle"},
                      "parameters": {"m": {"initial": 0.8, "lower": 0.01},
                                     "d": {"initial": 0.3, "lower": 0.0},
                                     "k": {"initial": 30.0, "lower": 0.0}}}}, "p.yaml")
    st = desc.structure
    assert st.state_names == ("arm_angle", "arm")
    model = OEModel(st)
    rng = np.random.default_rng(3)
    n, dt = 3000, 0.005
    u = np.repeat(rng.uniform(-1, 1, n // 60 + 1), 60)[:n]
    seg = make_segment("s", np.arange(n) * dt, u, np.zeros(n), ["u"], ["q"])
    true = np.array([1.0, 0.5, 40.0])
    y = model.simulate(true, seg, np.array([0.0, 0.4])) + 1e-4 * rng.standard_normal((n, 1))
    seg = make_segment("s", seg.t, u, y, ["u"], ["q"])
    fit = OEFit(model, starts=2).fit([seg])
    for i in range(3):
        assert abs(fit.theta_[i] - true[i]) < 4 * fit.std_[i], (i, fit.theta_, fit.std_)
    assert fit.x0_[0][1] == pytest.approx(0.4, abs=0.02)
    # |lambda| of the pair is the undamped natural frequency sqrt(k / m)
    assert fit.parameters()["mode1_frequency_hz"] == pytest.approx(
        math.sqrt(40.0) / (2 * math.pi), rel=1e-2)
