"""The model node's fast per-sample paths give exactly what the plain paths gave (issue #11).

- the node reads and writes the 1 kHz JointState streams as CDR bytes
  (:class:`~dvt_model.node.JointStateReader`, :class:`~dvt_model.node.JointStateWriter`):
  the same values, names and stamps as rclpy's own (de)serialisation, the same errors;
- :class:`~dvt_model.predictor.Predictor` (plain-float checks, no state copies) predicts
  bit-identically to stepping the model directly; the linear model's last-step shortcut
  returns the cached discretisation;
- the node in process (no DDS traffic: its own domain, nobody listening) publishes the
  predictor's residuals bit for bit and its change detector ends with the statistics of a
  detector fed the same residual blocks directly.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from dvt_model.brake import band_torques
from dvt_model.contract import CURRENT_NAMES, SPEED_NAMES
from dvt_model.detect import ChangeDetector
from dvt_model.hybrid import CROSSING_GRID, HybridModel
from dvt_model.linear import LinearModel
from dvt_model.params import load_parameters
from dvt_model.predictor import Predictor, ResidualBlocks

rclpy = pytest.importorskip("rclpy")
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from dvt_model import rosutil  # noqa: E402
from dvt_model.node import JointStateReader, JointStateWriter, stamp_of  # noqa: E402

T0 = 1_700_000_000_123_456_789


@pytest.fixture(scope="module")
def params():
    return load_parameters("physical")


def _msg(names, velocity=None, effort=None, position=None, stamp=T0):
    m = rosutil.joint_state(stamp, names, velocity=velocity, effort=effort)
    if position is not None:
        m.position = [float(x) for x in position]
    return serialize_message(m)


def _plain(raw, wanted, field):
    """What the node did before: rclpy message, dicts by name."""
    m = deserialize_message(raw, JointState)
    arr = (m.position, m.velocity, m.effort)[field]
    by_name = dict(zip(m.name, arr, strict=True))
    vals = [by_name[n] for n in wanted]
    pos = None
    if field == 1 and len(m.position) == len(m.name):
        angles = dict(zip(m.name, m.position, strict=True))
        pos = [angles[n] for n in wanted]
    return vals, pos


@pytest.mark.parametrize("names,vel,pos", [
    (SPEED_NAMES, (100.0, 20.0), None),
    (SPEED_NAMES, (-1.5e-300, float("nan")), (0.25, -3.0)),
    (("carrier3", "extra", "sun_shaft"), (1.0, 2.0, 3.0), (7.0, 8.0, 9.0)),
    (("sun_shaft", "carrier3", "sun_shaft"), (1.0, 2.0, 3.0), None),  # last one wins
    (SPEED_NAMES, (4.0, 5.0), (1.0,)),  # positions not one per name: ignored
])
def test_reader_reads_what_the_rclpy_message_held(names, vel, pos) -> None:
    reader = JointStateReader(SPEED_NAMES, 1, positions=True)
    raw = _msg(names, velocity=vel, position=pos)
    for _ in range(2):  # learning the layout, then the cached layout
        got = reader.read(raw)
        want = _plain(raw, SPEED_NAMES, 1)
        np.testing.assert_array_equal(got[0], want[0])
        assert (got[1] is None) == (want[1] is None)
        if want[1] is not None:
            np.testing.assert_array_equal(got[1], want[1])
    assert stamp_of(raw) == T0


def test_reader_errors_and_layout_changes() -> None:
    reader = JointStateReader(CURRENT_NAMES, 2)
    good = _msg(CURRENT_NAMES, effort=(4.0, 0.0, 0.5, 0.0))
    assert reader.read(good) == ([4.0, 0.0, 0.5, 0.0], None)
    with pytest.raises(KeyError, match="brake3"):
        reader.read(_msg(CURRENT_NAMES[:3], effort=(1.0, 2.0, 3.0)))
    with pytest.raises(ValueError):
        reader.read(_msg(CURRENT_NAMES, effort=(1.0, 2.0, 3.0)))
    # same size and names, but the velocity array where the effort was: not the cached layout
    with pytest.raises(ValueError):
        reader.read(_msg(CURRENT_NAMES, velocity=(4.0, 0.0, 0.5, 0.0)))
    assert reader.read(_msg(CURRENT_NAMES, effort=(1.0, 2.0, 3.0, 4.0), stamp=T0 + 1)) == (
        [1.0, 2.0, 3.0, 4.0], None)


def test_reader_big_endian_falls_back() -> None:
    from dvt_model.contract import JOINT_STATE_TYPE
    from dvt_model.recording.cdr import joint_state_cdr, typestore

    ts = typestore()
    le = joint_state_cdr(T0, SPEED_NAMES, velocity=(3.0, -4.0), position=(1.0, 2.0))
    be = bytes(ts.serialize_cdr(ts.deserialize_cdr(le, JOINT_STATE_TYPE), JOINT_STATE_TYPE,
                                little_endian=False))
    assert be[:2] != le[:2]
    assert JointStateReader(SPEED_NAMES, 1, positions=True).read(be) == (
        [3.0, -4.0], [1.0, 2.0])
    assert stamp_of(be) == T0


def test_writer_gives_the_message_rosutil_built() -> None:
    writer = JointStateWriter(SPEED_NAMES)
    for stamp, vel, pos in ((T0, [1.5, -2.5], None), (T0 + 999, [0.1, 0.2], [3.0, -4.0]),
                            (T0 + 2, [7.0, 8.0], None)):
        got = deserialize_message(writer.encode(stamp, vel, pos), JointState)
        want = rosutil.joint_state(stamp, SPEED_NAMES, velocity=vel)
        if pos is not None:
            want.position = pos
        assert got == want


def _stream(params, n=1500, seed=3):
    model = HybridModel.from_params(params)
    t = np.arange(n) * 1e-3
    im = 3.0 + 2.0 * np.sin(2 * np.pi * 1.5 * t)
    ib = np.zeros((n, 3))
    ib[600:, 0] = 0.5  # a band engages and locks its ring
    r = model.simulate(t, im, ib, omega0=(50.0, 10.0))
    rng = np.random.default_rng(seed)
    return t, im, ib, r.omega + 0.2 * rng.standard_normal(r.omega.shape), r.theta


def test_predictor_is_bit_identical_to_stepping_the_model(params) -> None:
    t, im, ib, meas, theta = _stream(params)
    model = HybridModel.from_params(params)
    p = Predictor(HybridModel.from_params(params), params.brake)
    ring = model.ring_speeds(meas[0])
    cap = np.where(np.abs(ring) < 0.5, band_torques(params.brake, ib[0]), 0.0)
    state = model.initial_state(meas[0], t=t[0], capacity=cap, theta=theta[0])
    for k in range(len(t)):
        if k:
            state = model.step(state, t[k] - t[k - 1], im[k - 1], ib[k - 1])
        pred = p.update(t[k], im[k], ib[k].tolist(), meas[k].tolist(), theta[k].tolist())
        assert np.array_equal(pred.predicted, state.omega)
        assert np.array_equal(pred.residual, meas[k] - state.omega)
        assert np.array_equal(pred.predicted_position, state.theta)
        assert pred.position_residual is not None
        assert np.array_equal(pred.position_residual, theta[k] - state.theta)
        assert pred.gear == state.gear
    assert p.anchors == 1 and p.guard_reanchors == 0


def test_linear_last_step_shortcut_returns_the_discretisation(params) -> None:
    rig = HybridModel.from_params(params).rigid
    lin = LinearModel(rig.A, rig.B(1) @ np.diag([rig.motor_constant, 1.0]))
    plain = LinearModel(lin.A, lin.B)  # the rounded-key cache only, as before
    for dt in (1e-3, 1e-3, 2e-3, 1e-3 + 1e-16, 1e-3 + 1e-16, 2e-3, 1e-3):
        a, b = lin.discretise(dt)
        plain._last = None
        a0, b0 = plain.discretise(dt)
        assert np.array_equal(a, a0) and np.array_equal(b, b0)


@pytest.fixture
def model_node(monkeypatch):
    from rclpy.context import Context

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=150 + os.getpid() % 70,
               args=["test", "--ros-args", "-p", "detector.learn_s:=2.0",
                     "-p", "detector.settle_s:=0.1"])
    from dvt_model.node import ModelNode

    node = ModelNode(context=ctx)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_node_publishes_the_predictor_residuals_and_detects_as_directly(params,
                                                                        model_node) -> None:
    node = model_node
    sent: list[bytes] = []
    predicted: list[bytes] = []
    node.pub_res.publish = sent.append
    node.pub_pred.publish = predicted.append
    t, im, ib, meas, theta = _stream(params, n=3000)
    with_pos = np.arange(len(t)) >= 300  # positions measured from sample 300 (an anchor)
    for k in range(len(t)):
        stamp = T0 + k * 1_000_000
        cur = _msg(CURRENT_NAMES, effort=[im[k], *ib[k]], stamp=stamp)
        js = _msg(SPEED_NAMES, velocity=meas[k], stamp=stamp,
                  position=theta[k] if with_pos[k] else None)
        node._on_msg(cur, 1) if k % 2 else node._on_msg(js, 0)
        node._on_msg(js, 0) if k % 2 else node._on_msg(cur, 1)
    assert node.published == len(t) and node.bad_messages == 0

    # the node's model: the crossing grid of build_predictor
    p = Predictor(HybridModel.from_params(params, crossing_grid=CROSSING_GRID), params.brake)
    setup = node.blocks
    assert setup is not None and node.detector is not None
    blocks = ResidualBlocks(setup.size, 2, setup.max_gap_s)
    det = ChangeDetector(node.detector.config)
    settle_until = -float("inf")
    for k in range(len(t)):
        stamp = T0 + k * 1_000_000
        pred = p.update(stamp * 1e-9, im[k], ib[k], meas[k], theta[k] if with_pos[k] else None)
        got = deserialize_message(sent[k], JointState)
        out = deserialize_message(predicted[k], JointState)
        assert list(got.velocity) == pred.residual.tolist()
        assert list(out.velocity) == pred.predicted.tolist()
        if pred.position_residual is None:
            assert len(got.position) == 0 and len(out.position) == 0
        else:
            assert list(got.position) == pred.position_residual.tolist()
            assert list(out.position) == pred.predicted_position.tolist()
        assert rosutil.stamp_to_ns(got.header.stamp) == stamp and list(got.name) == list(
            SPEED_NAMES)
        ts = stamp * 1e-9
        if pred.anchored:
            det.reset()
            blocks.clear()
            settle_until = ts + node.settle_s
        if ts < settle_until:
            continue
        block = blocks.add(ts, pred.residual.tolist())
        if block is not None:
            det.update(block[0], block[1])
    assert det.counters == node.detector.counters
    assert det.counters.tested > 0  # learned, then tested
    assert det.statistics() == node.detector.statistics()
    assert det.references == node.detector.references
