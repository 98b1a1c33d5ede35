"""``dvt_model_node``: live prediction of the measured speeds (thin rclpy layer).

Subscribes ``/dvt/joint_states`` and ``/dvt/currents``, pairs them by their identical stamp,
feeds each sample to :class:`dvt_model.predictor.Predictor` and publishes
``/dvt/model/joint_states`` (prediction) and ``/dvt/model/residual`` (measured - predicted),
stamped like the measured sample, plus ``/diagnostics`` at 1 Hz.

Parameters (all changeable at runtime through the standard parameter services; an invalid
combination is refused with a reason and the node keeps its current model):

- ``params`` (string, default ``physical``): bundled parameter set or YAML file.
- ``M``, ``D`` (double[4], row-major, default empty): override the set's mass and damping
  matrices (M must be symmetric positive definite).
- ``motor_constant`` (double, 0 = the set's value) [N m/A].
- ``A``, ``B`` (double[4] and double[4] or double[8], default empty): run the linear model
  ``omega' = A omega + B u`` instead of the hybrid physics (both must be given).
- ``effects`` (string, JSON list, default empty): identified effect terms
  (:mod:`dvt_model.terms`: Coulomb, Stribeck, windage, viscous force terms on a member;
  output delay and gain), pushed by the identifier node.
- ``mode`` (``simulate`` | ``reanchor``), ``reanchor_period`` [s], ``gap_reset`` [s]:
  see :mod:`dvt_model.predictor`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from dvt_model import rosutil
from dvt_model.dynamics import check_mass_matrix, rigid_model
from dvt_model.errors import DvtModelError, ModelError
from dvt_model.hybrid import HybridModel
from dvt_model.linear import LinearModel, check_matrix
from dvt_model.params import load_parameters
from dvt_model.predictor import Predictor
from dvt_model.terms import parse_terms

_PARAMS = ("params", "M", "D", "motor_constant", "brake_gain", "brake_time_constant", "A", "B",
           "effects", "mode", "reanchor_period", "gap_reset")


def _band_values(values: dict[str, Any], key: str, unit: str) -> tuple[float, float, float] | None:
    """Three positive finite per-band values of parameter ``key``, or ``None`` when empty."""
    raw = list(values.get(key) or [])
    if not raw:
        return None
    arr = np.asarray(raw, dtype=float).reshape(-1)
    if arr.shape != (3,):
        raise ModelError(f"{key}: expected 3 values (bands 1, 2, 3) [{unit}], got {len(raw)}")
    if not (np.all(np.isfinite(arr)) and np.all(arr > 0.0)):
        raise ModelError(f"{key}: expected finite values > 0 [{unit}], got {arr.tolist()}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def build_predictor(values: dict[str, Any]) -> tuple[Predictor, str]:
    """Validate parameter values and build a predictor; raises DvtModelError with a reason."""
    params = load_parameters(str(values["params"]))
    rigid = rigid_model(params)
    changes: dict[str, Any] = {}
    for key in ("M", "D"):
        raw = list(values.get(key) or [])
        if raw:
            mat = check_matrix(np.asarray(raw, dtype=float).reshape(-1), key, (4,)).reshape(2, 2)
            if key == "M":
                check_mass_matrix(mat, "M")
            changes[key] = mat
    km = float(values.get("motor_constant") or 0.0)
    if km < 0.0 or not np.isfinite(km):
        raise ModelError(f"motor_constant: expected >= 0 N m/A, got {km!r}")
    if km > 0.0:
        changes["motor_constant"] = km
    if changes:
        rigid = dataclasses.replace(rigid, **changes)
    brake = params.brake
    band_gain = _band_values(values, "brake_gain", "N m/A")
    band_tau = _band_values(values, "brake_time_constant", "s")
    if band_gain is not None or band_tau is not None:
        brake = dataclasses.replace(brake, band_gain=band_gain, band_time_constant=band_tau)
        changes.update({k: True for k, v in (("brake_gain", band_gain),
                                             ("brake_time_constant", band_tau)) if v is not None})
    a_raw, b_raw = list(values.get("A") or []), list(values.get("B") or [])
    mode = str(values.get("mode", "simulate"))
    model: HybridModel | LinearModel
    if a_raw or b_raw:
        if not (a_raw and b_raw):
            raise ModelError("A and B: give both (4 and 4 or 8 values) or neither")
        A = check_matrix(np.asarray(a_raw, dtype=float), "A", (4,)).reshape(2, 2)
        if len(b_raw) not in (4, 8):
            raise ModelError(f"B: expected 4 or 8 values (2x2 or 2x4), got {len(b_raw)}")
        B = check_matrix(np.asarray(b_raw, dtype=float), "B", (len(b_raw),)).reshape(2, -1)
        model = LinearModel(A, B)
        desc = f"linear A,B (2x{B.shape[1]})"
    terms = parse_terms(str(values.get("effects") or ""))
    if (a_raw or b_raw) and terms.forces:
        raise ModelError("effects: force terms need the physical model (clear A and B)")
    if not (a_raw or b_raw):
        model = HybridModel(rigid, brake,
                            extra_force=terms.extra_force if terms.forces else None)
        desc = f"hybrid physics '{params.name}'" + (f" with {sorted(changes)}" if changes else "")
    if not terms.empty:
        desc += f" + {len(terms.forces)} force term(s), delay {terms.delay:g} s"
    predictor = Predictor(model, brake, mode=mode,  # type: ignore[arg-type]
                          reanchor_period=float(values.get("reanchor_period", 1.0)),
                          gap_reset=float(values.get("gap_reset", 0.5)),
                          output_delay=terms.delay, output_gain=terms.gains)
    return predictor, desc


class ModelNode(Node):
    """The live model node."""

    def __init__(self) -> None:
        super().__init__("dvt_model")
        self.declare_parameter("params", "physical", ParameterDescriptor(
            description="bundled parameter set (thesis, thesis-derivation, physical) or YAML path"))
        self.declare_parameter("M", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="mass matrix override [kg m^2], 4 values row-major; empty = from params"))
        self.declare_parameter("D", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="damping matrix override [N m s], 4 values row-major"))
        self.declare_parameter("motor_constant", 0.0, ParameterDescriptor(
            description="drive-motor constant K_M [N m/A]; 0 = the parameter set's value",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10.0)]))
        self.declare_parameter("brake_gain", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="static torque per brake-motor ampere of bands 1-3 [N m/A], 3 values; "
                        "empty = the parameter set's band law"))
        self.declare_parameter("brake_time_constant", Parameter.Type.DOUBLE_ARRAY,
                               ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="engagement time constant of bands 1-3 [s], 3 values; empty = the "
                        "parameter set's"))
        self.declare_parameter("A", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="identified state matrix [1/s], 4 values row-major (with B)"))
        self.declare_parameter("B", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description="identified input matrix, 4 (2x2) or 8 (2x4) values row-major"))
        self.declare_parameter("effects", "", ParameterDescriptor(
            description="identified effect terms, JSON list (see dvt_model.terms)"))
        self.declare_parameter("mode", "simulate", ParameterDescriptor(
            description="simulate (free run, output-error residual) or reanchor"))
        self.declare_parameter("reanchor_period", 1.0, ParameterDescriptor(
            description="seconds between re-anchors in reanchor mode",
            floating_point_range=[FloatingPointRange(from_value=0.001, to_value=3600.0)]))
        self.declare_parameter("gap_reset", 0.5, ParameterDescriptor(
            description="a stamp gap longer than this [s] re-anchors the model",
            floating_point_range=[FloatingPointRange(from_value=0.001, to_value=3600.0)]))
        self.predictor, self.model_desc = build_predictor(self._values({}))
        self.rejected = 0
        self.bad_messages = 0
        self.unpaired = 0
        self.published = 0
        self._pending: dict[int, tuple[JointState | None, JointState | None]] = {}
        self.add_on_set_parameters_callback(self._on_set)
        self.pub_pred = self.create_publisher(JointState, rosutil.MODEL_JOINT_STATES,
                                              rosutil.SENSOR_QOS)
        self.pub_res = self.create_publisher(JointState, rosutil.MODEL_RESIDUAL,
                                             rosutil.SENSOR_QOS)
        self.pub_diag = self.create_publisher(rosutil.DiagnosticArray, rosutil.DIAGNOSTICS, 10)
        self.create_subscription(JointState, rosutil.JOINT_STATES,
                                 lambda m: self._on_msg(m, 0), rosutil.SENSOR_QOS)
        self.create_subscription(JointState, rosutil.CURRENTS,
                                 lambda m: self._on_msg(m, 1), rosutil.SENSOR_QOS)
        self.create_timer(1.0, self._diagnostics)
        self.get_logger().info(f"model: {self.model_desc}, mode {self.predictor.mode}")

    def _values(self, overrides: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in _PARAMS:
            if name in overrides:
                out[name] = overrides[name]
            else:
                param = self.get_parameter_or(name, Parameter(name, value=[]))
                out[name] = param.value if param.value is not None else []
        return out

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        overrides = {p.name: p.value for p in params if p.name in _PARAMS}
        if not overrides:
            return SetParametersResult(successful=True)
        try:
            predictor, desc = build_predictor(self._values(overrides))
        except (DvtModelError, ValueError, TypeError) as exc:
            self.rejected += 1
            self.get_logger().warning(f"parameter change refused: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        self.predictor, self.model_desc = predictor, desc
        self.get_logger().info(f"model changed: {desc}, mode {predictor.mode}")
        return SetParametersResult(successful=True)

    def _on_msg(self, msg: JointState, slot: int) -> None:
        key = rosutil.stamp_to_ns(msg.header.stamp)
        pair = list(self._pending.pop(key, (None, None)))
        pair[slot] = msg
        if pair[0] is None or pair[1] is None:
            self._pending[key] = (pair[0], pair[1])
            if len(self._pending) > 2000:
                oldest = min(self._pending)
                del self._pending[oldest]
                self.unpaired += 1
            return
        self._process(key, pair[0], pair[1])

    def _process(self, stamp_ns: int, js: JointState, cur: JointState) -> None:
        try:
            speeds = dict(zip(js.name, js.velocity, strict=True))
            currents = dict(zip(cur.name, cur.effort, strict=True))
            omega = [speeds[n] for n in rosutil.SPEED_NAMES]
            im = currents["drive_motor"]
            ib = [currents[n] for n in rosutil.CURRENT_NAMES[1:]]
            pred = self.predictor.update(stamp_ns * 1e-9, im, ib, omega)
        except (KeyError, ValueError, DvtModelError) as exc:
            self.bad_messages += 1
            if self.bad_messages <= 5 or self.bad_messages % 1000 == 0:
                self.get_logger().warning(f"sample at {stamp_ns} ns ignored: {exc!r}")
            return
        self.pub_pred.publish(rosutil.joint_state(stamp_ns, rosutil.SPEED_NAMES,
                                                  velocity=pred.predicted))
        self.pub_res.publish(rosutil.joint_state(stamp_ns, rosutil.SPEED_NAMES,
                                                 velocity=pred.residual))
        self.published += 1

    def _diagnostics(self) -> None:
        rms = self.predictor.residual_rms
        level = rosutil.OK if self.bad_messages == 0 else rosutil.WARN
        self.pub_diag.publish(rosutil.diagnostic(self, "dvt_model", level, self.model_desc, {
            "mode": self.predictor.mode,
            "samples": self.predictor.samples,
            "published": self.published,
            "anchors": self.predictor.anchors,
            "residual_rms_sun_shaft": f"{rms[0]:.6g}",
            "residual_rms_carrier3": f"{rms[1]:.6g}",
            "bad_messages": self.bad_messages,
            "unpaired": self.unpaired,
            "rejected_parameter_changes": self.rejected,
        }))


def main(args: list[str] | None = None) -> None:
    rosutil.init(args)
    node = ModelNode()
    rosutil.spin(node)


if __name__ == "__main__":
    main()
