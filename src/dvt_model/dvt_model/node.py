"""``dvt_model_node``: live prediction of the measured speeds (thin rclpy layer).

Subscribes ``/dvt/joint_states`` and ``/dvt/currents``, pairs them by their identical stamp
(:class:`dvt_model.recording.pairing.LivePairer`), feeds each sample to
:class:`dvt_model.predictor.Predictor` and publishes ``/dvt/model/joint_states`` (prediction)
and ``/dvt/model/residual`` (measured - predicted), stamped like the measured sample, plus
``/diagnostics`` at 1 Hz. Names and QoS are the contract's (:mod:`dvt_model.contract`).

Parameters: :data:`dvt_model.contract.MODEL_PARAMETERS` (name, type, unit, meaning, default and
admissible values; the descriptions the node declares are taken from it): ``params``, ``M``,
``D``, ``motor_constant``, ``band_gain``, ``band_time_constant``, ``A``, ``B``, ``effects``,
``mode``, ``reanchor_period``, ``gap_reset``. All are changeable at runtime through the standard
parameter services. Every change is validated by :func:`dvt_model.config.build_predictor`
(the same checks as :func:`dvt_model.config.check_parameters`); a refused change leaves the
current model running, its reason names the parameter, the value and what is admissible, and
every refusal (including an unknown parameter name or a value of the wrong type) is counted in
``/diagnostics`` as ``rejected_parameter_changes`` (the latest reason as ``last_refusal``).

The linear model: ``A`` and ``B`` must be given together (``SetParametersAtomically``, e.g.
``ros2 param load`` or a parameter client's ``set_parameters_atomically``); setting ``A`` or
``B`` to an empty list (plain ``SetParameters`` is enough) clears the linear model: the node
then empties the other one as well and runs the physics again.

The guard: the predictor never publishes a non-finite or diverging prediction; it re-anchors
to the measurement instead (:data:`dvt_model.predictor.OMEGA_GUARD`), and ``/diagnostics``
reports the count as ``guard_reanchors`` with level WARN.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from dvt_model import rosutil
from dvt_model.config import build_predictor
from dvt_model.contract import (
    CURRENT_NAMES,
    CURRENTS,
    DIAGNOSTICS,
    DIAGNOSTICS_QOS,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    MODEL_NODE,
    MODEL_PARAMETERS,
    MODEL_RESIDUAL,
    SPEED_NAMES,
    NodeParam,
    short_repr,
)
from dvt_model.errors import DvtModelError
from dvt_model.predictor import Predictor
from dvt_model.recording.pairing import LivePairer

_REFUSABLE = (DvtModelError, ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError)
"""What a parameter check may raise; each becomes a counted refusal, never a crash."""


def _descriptor(spec: NodeParam) -> ParameterDescriptor:
    unit = f" [{spec.unit}]" if spec.unit != "-" else ""
    return ParameterDescriptor(
        description=f"{spec.description}{unit}",
        additional_constraints=f"admissible: {spec.admissible}",
        # type checks are the contract's (in the on-set callback), so that a value of the
        # wrong type is refused with a reason naming the parameter and counted
        dynamic_typing=True)


def _initial(spec: NodeParam) -> Any:
    """The declared default: an empty list default is 'not set' (rclpy cannot type ``[]``)."""
    return None if spec.default == () else spec.default


def _is_empty(value: Any) -> bool:
    return value is None or (not isinstance(value, str) and len(value) == 0)


class ModelNode(Node):
    """The live model node (see the module docstring)."""

    def __init__(self) -> None:
        super().__init__(MODEL_NODE, allow_undeclared_parameters=True)
        for spec in MODEL_PARAMETERS.values():
            self.declare_parameter(spec.name, _initial(spec), _descriptor(spec))
        self.predictor: Predictor
        self.predictor, self.model_desc = build_predictor(self._values())
        self.rejected = 0
        self.last_refusal = ""
        self.bad_messages = 0
        self.published = 0
        self._guard_before = 0  # guard re-anchors of the predictors replaced so far
        self._clear_next: str | None = None
        self.pairer: LivePairer[JointState] = LivePairer(slots=2, max_pending=2000)
        self.add_on_set_parameters_callback(self._on_set)
        self.add_post_set_parameters_callback(self._after_set)
        self.pub_pred = self.create_publisher(JointState, MODEL_JOINT_STATES,
                                              rosutil.SENSOR_QOS)
        self.pub_res = self.create_publisher(JointState, MODEL_RESIDUAL, rosutil.SENSOR_QOS)
        self.pub_diag = self.create_publisher(rosutil.DiagnosticArray, DIAGNOSTICS,
                                              rosutil.qos(DIAGNOSTICS_QOS))
        self.create_subscription(JointState, JOINT_STATES, lambda m: self._on_msg(m, 0),
                                 rosutil.SENSOR_QOS)
        self.create_subscription(JointState, CURRENTS, lambda m: self._on_msg(m, 1),
                                 rosutil.SENSOR_QOS)
        self.create_timer(1.0, self._diagnostics)
        self.get_logger().info(f"model: {self.model_desc}, mode {self.predictor.mode}")

    @property
    def guard_reanchors(self) -> int:
        """Guard re-anchors since the node started (all predictors)."""
        return self._guard_before + self.predictor.guard_reanchors

    def _values(self) -> dict[str, Any]:
        """The current model parameters (``None`` = not set, i.e. the default)."""
        return {name: self.get_parameter_or(name, Parameter(name)).value
                for name in MODEL_PARAMETERS}

    def _refuse(self, reason: str) -> SetParametersResult:
        self.rejected += 1
        self.last_refusal = reason
        self.get_logger().warning(f"parameter change refused: {reason}")
        return SetParametersResult(successful=False, reason=reason)

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        changes: dict[str, Any] = {}
        for p in params:
            if p.name in MODEL_PARAMETERS:
                if p.type_ == Parameter.Type.NOT_SET:
                    return self._refuse(f"{p.name}: cannot be unset: expected "
                                        f"{MODEL_PARAMETERS[p.name].admissible}")
                changes[p.name] = p.value
            elif not self.has_parameter(p.name):
                name = p.name if len(p.name) <= 100 else short_repr(p.name)
                return self._refuse(f"{name}: unknown parameter of the model node "
                                    f"(expected one of {list(MODEL_PARAMETERS)})")
        if not changes:
            return SetParametersResult(successful=True)  # e.g. use_sim_time
        values = {**self._values(), **changes}
        clear: str | None = None
        for key, other in (("A", "B"), ("B", "A")):
            if (key in changes and _is_empty(changes[key]) and other not in changes
                    and not _is_empty(values[other])):
                values[other], clear = None, other  # emptying one clears the linear model
        try:
            predictor, desc = build_predictor(values)
        except _REFUSABLE as exc:
            return self._refuse(str(exc))
        self._guard_before += self.predictor.guard_reanchors
        self.predictor, self.model_desc = predictor, desc
        self._clear_next = clear
        self.get_logger().info(f"model changed: {desc}, mode {predictor.mode}")
        return SetParametersResult(successful=True)

    def _after_set(self, params: list[Parameter]) -> None:
        clear, self._clear_next = self._clear_next, None
        if clear is not None:
            self.set_parameters([Parameter(clear, Parameter.Type.DOUBLE_ARRAY, [])])

    def _on_msg(self, msg: JointState, slot: int) -> None:
        stamp_ns = rosutil.stamp_to_ns(msg.header.stamp)
        pair = self.pairer.add(stamp_ns, slot, msg)
        if pair is not None:
            self._process(stamp_ns, pair[0], pair[1])

    def _process(self, stamp_ns: int, js: JointState, cur: JointState) -> None:
        try:
            speeds = dict(zip(js.name, js.velocity, strict=True))
            currents = dict(zip(cur.name, cur.effort, strict=True))
            omega = [speeds[n] for n in SPEED_NAMES]
            im = currents[CURRENT_NAMES[0]]
            ib = [currents[n] for n in CURRENT_NAMES[1:]]
            pred = self.predictor.update(stamp_ns * 1e-9, im, ib, omega)
        except (KeyError, ValueError, DvtModelError) as exc:
            self.bad_messages += 1
            if self.bad_messages <= 5 or self.bad_messages % 1000 == 0:
                self.get_logger().warning(f"sample at {stamp_ns} ns ignored: {exc!r}")
            return
        self.pub_pred.publish(rosutil.joint_state(stamp_ns, SPEED_NAMES,
                                                  velocity=pred.predicted))
        self.pub_res.publish(rosutil.joint_state(stamp_ns, SPEED_NAMES,
                                                 velocity=pred.residual))
        self.published += 1

    def _diagnostics(self) -> None:
        rms = self.predictor.residual_rms
        guard = self.guard_reanchors
        level = rosutil.OK if self.bad_messages == 0 and guard == 0 else rosutil.WARN
        message = self.model_desc + (f"; {guard} guard re-anchor(s): the model diverged"
                                     if guard else "")
        self.pub_diag.publish(rosutil.diagnostic(self, MODEL_NODE, level, message, {
            "mode": self.predictor.mode,
            "samples": self.predictor.samples,
            "published": self.published,
            "anchors": self.predictor.anchors,
            "guard_reanchors": guard,
            "residual_rms_sun_shaft": f"{rms[0]:.6g}",
            "residual_rms_carrier3": f"{rms[1]:.6g}",
            "bad_messages": self.bad_messages,
            "unpaired": self.pairer.unpaired,
            "rejected_parameter_changes": self.rejected,
            "last_refusal": self.last_refusal,
        }))


def main(args: list[str] | None = None) -> None:
    rosutil.init(args)
    try:
        node = ModelNode()
    except DvtModelError as exc:  # invalid parameters given at start-up
        print(f"dvt_model_node: {exc}", file=sys.stderr)
        if rclpy.ok():
            rclpy.shutdown()
        sys.exit(2)
    rosutil.spin(node)


if __name__ == "__main__":
    main()
