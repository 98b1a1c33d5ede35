"""Topic level: a core-simulated bag is replayed into the live model node (real processes)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from conftest import wait_for
from dvt_model import rosutil
from dvt_model.bagio import write_run
from dvt_model.hybrid import HybridModel
from dvt_model.params import load_parameters

pytestmark = pytest.mark.ros
NOISE = 0.2  # rad/s, measurement noise added to the simulated speeds


def _simulated_bag(path, seconds=3.0, seed=1):
    params = load_parameters("physical")
    model = HybridModel.from_params(params)
    n = int(seconds * 1000)
    t = np.arange(n) * 1e-3
    im = 4.0 + 3.0 * np.sign(np.sin(2 * np.pi * 0.7 * t))
    ib = np.zeros((n, 3))
    ib[n // 2:, 0] = 0.5
    r = model.simulate(t, im, ib, omega0=(60.0, 12.0))
    rng = np.random.default_rng(seed)
    speeds = r.omega + rng.normal(0.0, NOISE, r.omega.shape)
    currents = np.column_stack([im, ib])
    stamps = (1_700_000_000 * 10**9 + np.round(t * 1e9)).astype(np.int64)
    return write_run(path, stamps, speeds, currents)


class _Listener:
    def __init__(self, ctx):
        self.node = rclpy.create_node("test_listener", context=ctx)
        self.exe = SingleThreadedExecutor(context=ctx)
        self.exe.add_node(self.node)
        self.residuals: list[tuple[int, list[float]]] = []
        self.predicted = 0
        self.node.create_subscription(JointState, rosutil.MODEL_RESIDUAL, self._res,
                                      rosutil.SENSOR_QOS)
        self.node.create_subscription(JointState, rosutil.MODEL_JOINT_STATES, self._pred,
                                      rosutil.SENSOR_QOS)

    def _res(self, msg):
        self.residuals.append((rosutil.stamp_to_ns(msg.header.stamp), list(msg.velocity)))

    def _pred(self, msg):
        self.predicted += 1

    def spin_for(self, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.exe.spin_once(timeout_sec=0.02)

    def spin_until(self, pred, timeout, what):
        def check():
            self.exe.spin_once(timeout_sec=0.02)
            return pred()
        return wait_for(check, timeout, what, interval=0.0)

    def set_param(self, name, value):
        cli = self.node.create_client(SetParameters, "/dvt_model/set_parameters")
        self.spin_until(lambda: cli.service_is_ready(), 10.0, "parameter service")
        pv = ParameterValue()
        if isinstance(value, str):
            pv.type, pv.string_value = ParameterType.PARAMETER_STRING, value
        else:
            pv.type, pv.double_array_value = ParameterType.PARAMETER_DOUBLE_ARRAY, list(value)
        fut = cli.call_async(SetParameters.Request(parameters=[ParameterMsg(name=name, value=pv)]))
        self.spin_until(fut.done, 10.0, f"set {name}")
        return fut.result().results[0]


def test_replayed_bag_residual_at_noise_level(procs, rclpy_context, tmp_path):
    bag = _simulated_bag(tmp_path / "run")
    listener = _Listener(rclpy_context)
    node = procs.start("dvt_model_node", "--ros-args", "-p", "params:=physical")
    listener.spin_until(lambda: listener.node.count_publishers(rosutil.MODEL_RESIDUAL) > 0,
                        20.0, "model node publishers")
    replay = procs.start("dvt-replay", str(bag), "--rate", "1.0", "--wait-subscribers", "1")
    listener.spin_until(lambda: replay.poll() is not None, 60.0, "replay to finish")
    assert replay.returncode == 0, procs.log(replay)
    listener.spin_for(0.5)
    assert node.poll() is None
    res = np.array([v for _, v in listener.residuals])
    assert len(res) > 0.95 * 3000  # best-effort transport may drop a handful
    stamps = [s for s, _ in listener.residuals]
    assert stamps == sorted(stamps)
    rms = np.sqrt(np.mean(res[200:] ** 2, axis=0))
    # exact model, noise on the measurement only: residual RMS is the noise level
    assert np.all(rms < 1.5 * NOISE), rms
    assert np.all(rms > 0.5 * NOISE), rms


def test_runtime_parameter_change_and_refusal(procs, rclpy_context, tmp_path):
    bag = _simulated_bag(tmp_path / "run", seconds=1.5)
    listener = _Listener(rclpy_context)
    node = procs.start("dvt_model_node")
    ok = listener.set_param("params", "thesis")
    assert ok.successful, ok.reason
    bad = listener.set_param("M", [0.001665, -0.0059856, -0.0059856, 0.0028709])
    assert not bad.successful
    assert "not positive definite" in bad.reason
    bad_shape = listener.set_param("A", [1.0, 2.0, 3.0])
    assert not bad_shape.successful and "A" in bad_shape.reason
    unknown = listener.set_param("params", "no-such-set")
    assert not unknown.successful and "unknown parameter set" in unknown.reason
    bad_bands = listener.set_param("brake_gain", [8.0, 8.0])
    assert not bad_bands.successful
    assert "brake_gain: expected 3 values (bands 1, 2, 3) [N m/A], got 2" in bad_bands.reason
    bad_tau = listener.set_param("brake_time_constant", [0.02, 0.0, 0.02])
    assert not bad_tau.successful and "expected finite values > 0 [s]" in bad_tau.reason
    good = listener.set_param("brake_time_constant", [0.02, 0.02, 0.02])
    assert good.successful, good.reason
    assert node.poll() is None
    # the accepted change took effect: 'thesis' inertias differ from the plant -> larger residual
    replay = procs.start("dvt-replay", str(bag), "--rate", "1.0", "--wait-subscribers", "1")
    listener.spin_until(lambda: replay.poll() is not None, 60.0, "replay to finish")
    listener.spin_for(0.5)
    res = np.array([v for _, v in listener.residuals])
    assert len(res) > 1000
    rms_thesis = np.sqrt(np.mean(res[200:] ** 2, axis=0))
    assert rms_thesis[0] > 3 * NOISE, rms_thesis
    # and back to the right model: residual returns to the noise level
    assert listener.set_param("params", "physical").successful
    listener.residuals.clear()
    replay = procs.start("dvt-replay", str(bag), "--rate", "1.0", "--wait-subscribers", "1")
    listener.spin_until(lambda: replay.poll() is not None, 60.0, "replay to finish")
    listener.spin_for(0.5)
    res = np.array([v for _, v in listener.residuals])
    rms = np.sqrt(np.mean(res[200:] ** 2, axis=0))
    assert np.all(rms < 1.5 * NOISE), rms
