"""A change of the model node's parameters is one transaction (issue "the house, second pass",
item 5): the whole set is validated together and applied at once, or refused whole.

The pure core (:func:`dvt_model.config.model_transaction`, :func:`~dvt_model.config.partner_clears`)
without ROS; then the node in process (rclpy, no DDS traffic): one predictor swap and one
detector reset per accepted set, nothing at all for a refused one.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from dvt_model.config import UNSET, build_predictor, model_transaction, partner_clears
from dvt_model.contract import MODEL_PARAMETERS
from dvt_model.errors import DvtModelError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel

M_NEW = [0.0035, -0.0136, -0.0136, 0.0674]  # the 'physical' M times 1.6
D_NEW = [0.029, -0.0357, -0.0357, 0.1475]   # the 'physical' D times 2
EFFECTS_NEW = json.dumps([{"kind": "viscous", "member": [1.0, 0.0], "b": 1e-4}])
NEW = {"M": M_NEW, "D": D_NEW, "effects": EFFECTS_NEW}
A_OK = [-20.0, 1.0, 2.0, -3.0]
B_OK = [800.0, -400.0, 160.0, -47.0]
BAD_MEMBERS = [
    ("M", [1e-30, 0.0, 0.0, 1e-30], "smallest eigenvalue"),
    ("D", [-0.01, 0.0, 0.0, -0.05], "positive semi-definite"),
    ("effects", json.dumps([{"kind": "viscous", "member": [1.0, 0.0], "b": -1e-3}]),
     "effects[0].b"),
]


def _current() -> dict[str, object]:
    """The values of a node started without parameters (``None``: not set)."""
    return {name: None if spec.default == () else spec.default
            for name, spec in MODEL_PARAMETERS.items()}


def test_a_set_is_validated_together_into_one_predictor():
    tx = model_transaction(_current(), NEW)
    assert tx is not None
    assert tx.changed == ("M", "D", "effects")
    assert tx.values == {**_current(), **NEW}
    model = tx.predictor.model
    assert isinstance(model, HybridModel)
    assert np.allclose(model.rigid.M.reshape(-1), M_NEW)
    assert np.allclose(model.rigid.D.reshape(-1), D_NEW)
    assert tx.description == build_predictor({**_current(), **NEW})[1]
    assert "['D', 'M']" in tx.description and "1 force term" in tx.description


@pytest.mark.parametrize(("name", "value", "reason"), BAD_MEMBERS)
def test_one_bad_member_refuses_the_whole_set(name, value, reason):
    with pytest.raises(DvtModelError) as err:
        model_transaction(_current(), {**NEW, name: value})
    assert str(err.value).startswith(name), err.value
    assert reason in str(err.value)


def test_members_checked_together_not_one_by_one():
    """A and B are admissible together only: one by one the first would be refused."""
    with pytest.raises(DvtModelError, match="A and B: give both"):
        model_transaction(_current(), {"A": A_OK})
    tx = model_transaction(_current(), {"A": A_OK, "B": B_OK})
    assert tx is not None and isinstance(tx.predictor.model, LinearModel)


@pytest.mark.parametrize(("changes", "start"), [
    ({**NEW, "detector.learn_s": 30.0}, "detector.learn_s: read-only"),
    ({**NEW, "M": UNSET}, "M: cannot be unset"),
    ({**NEW, "brake_gain": [8.0, 8.0, 8.0]}, "brake_gain: unknown parameter"),
])
def test_read_only_unset_and_unknown_members_refuse_the_set(changes, start):
    with pytest.raises(DvtModelError) as err:
        model_transaction(_current(), changes)
    assert str(err.value).startswith(start), err.value


def test_other_declared_parameters_pass_and_change_no_model():
    assert model_transaction(_current(), {"use_sim_time": False},
                             is_declared=lambda n: n == "use_sim_time") is None
    tx = model_transaction(_current(), {"use_sim_time": False, **NEW},
                           is_declared=lambda n: n == "use_sim_time")
    assert tx is not None and tx.changed == ("M", "D", "effects")


def test_a_set_repeating_the_values_in_use_is_no_change():
    """A push sent again (its answer lost) or a rollback to the model in use changes nothing;
    one member that differs makes it a change of that member only (exactly: its last bit)."""
    applied = model_transaction(_current(), NEW)
    assert applied is not None
    in_use = applied.values
    assert model_transaction(in_use, dict(NEW)) is None
    assert model_transaction(in_use, {"M": np.array(M_NEW), "effects": EFFECTS_NEW}) is None
    nudged = [*M_NEW[:-1], float(np.nextafter(M_NEW[-1], 1.0))]
    tx = model_transaction(in_use, {**NEW, "M": nudged})
    assert tx is not None and tx.changed == ("M",)
    tx = model_transaction(in_use, {**NEW, "effects": "[]"})
    assert tx is not None and tx.changed == ("effects",)
    assert model_transaction(_current(), {"A": []}) is None  # empties what is not set


def test_emptying_a_clears_b_in_the_same_transaction():
    linear = {**_current(), "A": A_OK, "B": B_OK}
    assert partner_clears(linear, {"A": []}) == ("B",)
    assert partner_clears(linear, {"B": []}) == ("A",)
    assert partner_clears(linear, {"A": [], "B": []}) == ()
    assert partner_clears(_current(), {"A": []}) == ()  # B not set: nothing to clear
    assert partner_clears(linear, {"A": 5.0}) == ()  # not empty (refused later, not here)
    tx = model_transaction(linear, {"A": []})
    assert tx is not None and tx.changed == ("A", "B")
    assert tx.values["B"] is None and isinstance(tx.predictor.model, HybridModel)


# ------------------------------------------------------------------------ the node in process
rclpy = pytest.importorskip("rclpy")
from rclpy.parameter import Parameter  # noqa: E402

Type = Parameter.Type


@pytest.fixture
def model_node(monkeypatch):
    from rclpy.context import Context

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=150 + (os.getpid() + 7) % 70, args=["test"])
    from dvt_model.node import ModelNode

    node = ModelNode(context=ctx)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def _typed(values):
    return [Parameter(k, Type.STRING, v) if isinstance(v, str)
            else Parameter(k, Type.DOUBLE_ARRAY, v) for k, v in values.items()]


def _state(node):
    return {k: node.get_parameter(k).value for k in ("M", "D", "effects", "A", "B")}


def test_node_applies_an_atomic_set_once(model_node):
    node = model_node
    before = node.predictor
    resets = node.detector_resets
    result = node.set_parameters_atomically(_typed(NEW))
    assert result.successful, result.reason
    assert node.predictor is not before
    assert node.detector_resets == resets + 1
    assert node.model_desc == build_predictor({**_current(), **NEW})[1]
    state = _state(node)
    assert list(state["M"]) == M_NEW and list(state["D"]) == D_NEW
    assert state["effects"] == EFFECTS_NEW


def test_node_takes_a_repeated_set_as_no_change(model_node):
    node = model_node
    assert node.set_parameters_atomically(_typed(NEW)).successful
    predictor, resets = node.predictor, node.detector_resets
    result = node.set_parameters_atomically(_typed(NEW))  # the same push, sent again
    assert result.successful, result.reason
    assert node.predictor is predictor and node.detector_resets == resets


@pytest.mark.parametrize(("name", "value", "reason"), BAD_MEMBERS)
def test_node_refusing_a_member_keeps_the_old_model_whole(model_node, name, value, reason):
    node = model_node
    before, desc, state = node.predictor, node.model_desc, _state(node)
    resets = node.detector_resets
    result = node.set_parameters_atomically(_typed({**NEW, name: value}))
    assert not result.successful
    assert result.reason.startswith(name) and reason in result.reason, result.reason
    assert node.predictor is before and node.model_desc == desc
    assert _state(node) == state
    assert node.detector_resets == resets
    assert node.rejected == 1 and node.last_refusal == result.reason


def test_node_single_parameter_changes_still_validated(model_node):
    node = model_node
    before = node.predictor
    ok = node.set_parameters([Parameter("M", Type.DOUBLE_ARRAY, M_NEW)])[0]
    assert ok.successful and node.predictor is not before and node.detector_resets == 1
    before = node.predictor
    bad = node.set_parameters([Parameter("D", Type.DOUBLE_ARRAY, [-0.01, 0.0, 0.0, -0.05])])[0]
    assert not bad.successful and bad.reason.startswith("D: ")
    assert node.predictor is before and node.detector_resets == 1 and node.rejected == 1
    read_only = node.set_parameters([Parameter("detector.learn_s", Type.DOUBLE, 30.0)])[0]
    assert not read_only.successful
    assert read_only.reason.startswith("detector.learn_s: read-only")


def test_node_clears_a_and_b_in_one_transaction(model_node):
    node = model_node
    assert node.set_parameters_atomically(_typed({"A": A_OK, "B": B_OK})).successful
    assert isinstance(node.predictor.model, LinearModel)
    resets = node.detector_resets
    result = node.set_parameters([Parameter("A", Type.DOUBLE_ARRAY, [])])[0]
    assert result.successful, result.reason
    assert len(node.get_parameter("A").value) == 0 and len(node.get_parameter("B").value) == 0
    assert isinstance(node.predictor.model, HybridModel)
    assert node.detector_resets == resets + 1
