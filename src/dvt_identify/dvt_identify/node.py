"""``dvt_identify_node``: refit on request and push the result to the live model node.

Requests (either):

- service ``/dvt/identify/run`` (std_srvs/Trigger): identify on the bags in the parameters
  ``estimation_bags`` / ``validation_bags``;
- topic ``/dvt/identify/request`` (std_msgs/String): a JSON object
  ``{"estimation": [BAG, ...], "validation": [BAG, ...]}`` naming the bags.

The identification (:func:`dvt_identify.pipeline.run`: baseline fit, residual tracing, augmentation,
report in ``output_dir``) runs in a worker thread; the service answers at once ("started" or why
not). When it ends, the accepted model is pushed to ``model_node`` through its standard
parameter services (``M``, ``D``, ``effects``; see :mod:`dvt_identify.push`), so the live
residual on ``/dvt/model/residual`` reflects the refitted model. A JSON summary goes to
``/dvt/identify/result`` (latched) and a status to ``/diagnostics``.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import String
from std_srvs.srv import Trigger

from dvt_identify.errors import DvtIdentifyError
from dvt_identify.pipeline import model_push, run
from dvt_model import rosutil
from dvt_model.contract import (
    IDENTIFY_NODE,
    IDENTIFY_REQUEST,
    IDENTIFY_RESULT,
    MODEL_NODE,
    SRV_IDENTIFY_RUN,
)

LATCHED = rosutil.LATCHED_QOS
"""QoS of the result: a late subscriber still gets the last one (the contract's LATCHED_QOS)."""


class IdentifyNode(Node):
    """Identification on request (see module docstring)."""

    def __init__(self) -> None:
        super().__init__(IDENTIFY_NODE)
        self.declare_parameter("description", "dvt", ParameterDescriptor(
            description="actuator description: bundled name or YAML path"))
        self.declare_parameter("estimation_bags", [""], ParameterDescriptor(
            description="bag directories to fit (service request)"))
        self.declare_parameter("validation_bags", [""], ParameterDescriptor(
            description="bag directories to validate on (never fitted)"))
        self.declare_parameter("output_dir", "identify-out", ParameterDescriptor(
            description="report directory (one sub-directory per run)"))
        self.declare_parameter("augment", True, ParameterDescriptor(
            description="run the residual-tracing augment loop after the baseline"))
        self.declare_parameter("push", True, ParameterDescriptor(
            description="push the accepted model to model_node"))
        self.declare_parameter("model_node", MODEL_NODE, ParameterDescriptor(
            description="name of the model node whose parameters are set"))
        self.state = "idle"
        self.last: dict[str, Any] = {}
        self.runs = 0
        self._worker: threading.Thread | None = None
        self._lock = threading.Lock()
        self.pub_result = self.create_publisher(String, IDENTIFY_RESULT, LATCHED)
        self.pub_diag = self.create_publisher(rosutil.DiagnosticArray, rosutil.DIAGNOSTICS, 10)
        self.create_service(Trigger, SRV_IDENTIFY_RUN, self._on_run)
        self.create_subscription(String, IDENTIFY_REQUEST, self._on_request, 10)
        self.create_timer(1.0, self._diagnostics)
        self.param_client = AsyncParameterClient(self, str(self.get_parameter("model_node").value))

    # -- requests -----------------------------------------------------------------------
    def _bags(self, name: str) -> list[str]:
        return [b for b in self.get_parameter(name).value or [] if b]

    def _on_run(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        ok, why = self.start(self._bags("estimation_bags"), self._bags("validation_bags"))
        response.success, response.message = ok, why
        return response

    def _on_request(self, msg: String) -> None:
        try:
            data = json.loads(msg.data)
            est = [str(b) for b in data["estimation"]]
            val = [str(b) for b in data["validation"]]
        except (ValueError, KeyError, TypeError) as exc:
            self.get_logger().warning(f"bad request on {IDENTIFY_REQUEST} ({exc!r}): "
                                      'expected {"estimation": [...], "validation": [...]}')
            return
        ok, why = self.start(est, val)
        if not ok:
            self.get_logger().warning(f"request refused: {why}")

    def start(self, est: list[str], val: list[str]) -> tuple[bool, str]:
        """Start a run in the worker thread; returns (started, message)."""
        if not est or not val:
            return False, "need at least one estimation and one validation bag"
        missing = [b for b in est + val if not Path(b).exists()]
        if missing:
            return False, f"no such bag: {missing[0]}"
        with self._lock:
            if self._worker is not None and self._worker.is_alive():
                return False, "busy: an identification is running"
            self.runs += 1
            out = Path(str(self.get_parameter("output_dir").value)) / f"run-{self.runs:03d}"
            self._worker = threading.Thread(target=self._work, args=(est, val, out),
                                            daemon=True)
            self.state = "running"
            self._worker.start()
        self.get_logger().info(f"identification started: {est} validated on {val} -> {out}")
        return True, f"started: report in {out}"

    # -- work ---------------------------------------------------------------------------
    def _work(self, est: list[str], val: list[str], out: Path) -> None:
        t0 = time.monotonic()
        summary: dict[str, Any] = {"estimation": est, "validation": val, "report": str(out)}
        try:
            result = run(est, val, out, description=str(self.get_parameter("description").value),
                         augment=bool(self.get_parameter("augment").value), quiet=True)
            summary["baseline_fit_percent"] = dict(zip(
                result.baseline.val.output_names, result.baseline.val.fit_percent, strict=True))
            summary["final_fit_percent"] = dict(zip(
                result.final.val.output_names, result.final.val.fit_percent, strict=True))
            summary["accepted"] = [d.score.label for d in result.accepted]
            if bool(self.get_parameter("push").value):
                push = model_push(result)
                summary["pushed"] = self._push(push.parameters)
                summary["not_pushed"] = push.skipped
            self.state = "done"
        except DvtIdentifyError as exc:
            summary["error"] = str(exc)
            self.state = "failed"
            self.get_logger().error(f"identification failed: {exc}")
        except Exception as exc:  # a worker must never take the node down
            summary["error"] = f"{type(exc).__name__}: {exc}"
            self.state = "failed"
            self.get_logger().error(f"identification failed: {summary['error']}")
        summary["seconds"] = time.monotonic() - t0
        self.last = summary
        self.pub_result.publish(String(data=json.dumps(summary)))
        self.get_logger().info(f"identification {self.state}: {json.dumps(summary)}")

    def _push(self, values: dict[str, Any]) -> dict[str, Any]:
        if not self.param_client.wait_for_services(timeout_sec=5.0):
            raise DvtIdentifyError(f"model node {self.param_client.remote_node_name!r} has no "
                                   "parameter services (not running?)")
        params = [Parameter(k, value=v) for k, v in values.items()]
        future = self.param_client.set_parameters(params)
        deadline = time.monotonic() + 10.0
        while not future.done():
            if time.monotonic() > deadline:
                raise DvtIdentifyError("model node did not answer set_parameters within 10 s")
            time.sleep(0.01)
        results = future.result().results
        refused = [f"{p.name}: {r.reason}" for p, r in zip(params, results, strict=True)
                   if not r.successful]
        if refused:
            raise DvtIdentifyError(f"model node refused: {'; '.join(refused)}")
        return {"node": self.param_client.remote_node_name, **values}

    def _diagnostics(self) -> None:
        level = {"failed": rosutil.ERROR}.get(self.state, rosutil.OK)
        values: dict[str, Any] = {"state": self.state, "runs": self.runs}
        for key in ("baseline_fit_percent", "final_fit_percent", "accepted", "error", "report"):
            if key in self.last:
                values[key] = self.last[key]
        self.pub_diag.publish(rosutil.diagnostic(self, IDENTIFY_NODE, level, self.state,
                                                 values))


def main(args: list[str] | None = None) -> None:
    rosutil.init(args)
    rosutil.spin(IdentifyNode())


if __name__ == "__main__":
    main()
