"""``dvt_identify_node``: refit on request and push the result to the live model node.

Requests (either):

- service ``/dvt/identify/run`` (std_srvs/Trigger): identify on the bags in the parameters
  ``estimation_bags`` / ``validation_bags``;
- topic ``/dvt/identify/request`` (std_msgs/String): a JSON object
  ``{"estimation": [BAG, ...], "validation": [BAG, ...]}`` naming the bags.

The identification (:func:`dvt_identify.pipeline.run`: baseline fit, residual tracing, augmentation,
report in ``output_dir``) runs in a worker thread; the service answers at once ("started" or why
not). When it ends, the accepted model is pushed to ``model_node`` (``M``, ``D``,
``effects``, ...; see :mod:`dvt_identify.push`) in one transaction through its standard
``~/set_parameters_atomically`` service (:func:`push_parameters`): applied whole or not at all,
so the live residual on ``/dvt/model/residual`` reflects the refitted model. A JSON summary goes to
``/dvt/identify/result`` (latched) and a status to ``/diagnostics``.

With ``supervisor.enabled`` the node also closes the loop by itself (``docs/loop.md`` §3-4):
change alarms on ``/dvt/model/change`` and the live residual on ``/dvt/model/residual`` feed
the pure :class:`dvt_identify.supervisor.Supervisor`; its actions are performed here: a
snapshot request to the rolling recorder, the refit of the window in a process of its own at
the lowest priority (:class:`dvt_identify.refit_process.RefitWorker` running
:func:`dvt_identify.refit.refit`; started warm with the node, killed when the supervisor stops
waiting for it, a crash reported as the episode's outcome ``refit_crashed``, reaped when the
node stops), the push / rollback (each one transaction,
:func:`push_parameters`), every step on ``/diagnostics`` (``dvt_identify: supervisor``), and
per episode ``episode-N.json`` / ``.md`` in ``output_dir/episodes`` plus the record on
``/dvt/identify/episode``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import queue
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from dvt_identify import supervisor as sv
from dvt_identify.errors import DvtIdentifyError, SupervisorError
from dvt_identify.pipeline import model_push, run
from dvt_identify.push import RESEND_S
from dvt_identify.refit import RefitSettings, plain_value
from dvt_identify.refit_process import DEFAULT_NICE, RefitWorker
from dvt_model import rosutil
from dvt_model.contract import (
    CHANGE_QOS,
    DIAGNOSTICS,
    IDENTIFY_EPISODE,
    IDENTIFY_NODE,
    IDENTIFY_REQUEST,
    IDENTIFY_RESULT,
    MODEL_CHANGE,
    MODEL_NODE,
    MODEL_PARAMETERS,
    MODEL_RESIDUAL,
    RECORDER_SNAPSHOT_REQUEST,
    RECORDER_SNAPSHOT_RESULT,
    REPLY_WAIT_SERVICES,
    SNAPSHOT_REQUEST_QOS,
    SPEED_NAMES,
    SRV_IDENTIFY_RUN,
    answer_of,
)
from dvt_model.node import VELOCITY, JointStateReader, stamp_of

LATCHED = rosutil.LATCHED_QOS
"""QoS of the result: a late subscriber still gets the last one (the contract's LATCHED_QOS)."""
SUPERVISOR_DIAG = "dvt_identify: supervisor"
"""``/diagnostics`` status name of the supervisor's steps."""
TICK_PERIOD = 0.1
"""Seconds between supervisor ticks (10 Hz; each also polls the refit process, which costs a
queue check)."""
PARAMETER_TIMEOUT = 30.0
"""Seconds to wait for the model node's parameters (it answers after its queued samples)."""
_PARAM_TYPES = {"double": Parameter.Type.DOUBLE, "double_array": Parameter.Type.DOUBLE_ARRAY,
                "string": Parameter.Type.STRING, "bool": Parameter.Type.BOOL,
                "integer": Parameter.Type.INTEGER}


def model_parameter(name: str, value: Any) -> Parameter:
    """A typed rclpy parameter for the model node (an empty or ``None`` array/string is "not
    set": an empty typed value, which the model node takes as its default)."""
    spec = MODEL_PARAMETERS.get(name)
    kind = _PARAM_TYPES.get(str(spec.type)) if spec is not None else None
    if kind is None:
        return Parameter(name, value=value)
    if kind is Parameter.Type.DOUBLE_ARRAY:
        return Parameter(name, kind, [float(v) for v in (value or [])])
    if kind is Parameter.Type.STRING:
        return Parameter(name, kind, "" if value is None else str(value))
    if kind is Parameter.Type.DOUBLE:
        return Parameter(name, kind, float(value))
    if kind is Parameter.Type.BOOL:
        return Parameter(name, kind, bool(value))
    return Parameter(name, kind, int(value))


def push_parameters(client: AsyncParameterClient, values: Mapping[str, Any],
                    timeout: float = 10.0, service_timeout: float = 5.0) -> dict[str, Any]:
    """Set the model node's parameters ``values`` (name -> value, :func:`model_parameter`
    types them) in ONE transaction: the standard ``~/set_parameters_atomically`` service. The
    node validates the set together and applies it whole (one predictor, one detector reset)
    or refuses it whole (nothing changes); a push or a rollback is never half applied
    (``docs/interface.md`` §6).

    The caller's executor must spin ``client``'s node in another thread (this polls).

    Args:
        client: a parameter client of the model node.
        values: the parameters to set together.
        timeout: seconds to wait for the answer (a busy model node answers after the samples
            queued before the call) [s]; unanswered, the set is sent again every
            ``min(RESEND_S, timeout / 3)`` s (:func:`dvt_model.contract.answer_of`: a lost
            reply; the node takes a repeated set as no change).
        service_timeout: seconds to wait for the node's parameter services [s].

    Returns:
        ``{"node": <model node name>, **values}``.

    Raises:
        DvtIdentifyError: no parameter services, no answer within ``timeout`` (the set may
            still be applied whole later), or the node refused the set (its reason; nothing
            was applied).
    """
    node_name = client.remote_node_name
    if not client.wait_for_services(timeout_sec=service_timeout):
        raise DvtIdentifyError(f"model node {node_name!r} has no parameter services (not "
                               "running?)")
    params = [model_parameter(k, v) for k, v in values.items()]
    try:  # sent again when its answer is lost (answer_of): a repeated set is no change
        response, _ = answer_of(lambda: client.set_parameters_atomically(params), timeout,
                                min(RESEND_S, timeout / 3))
    except TimeoutError as exc:
        raise DvtIdentifyError(f"model node {node_name!r} did not answer "
                               f"set_parameters_atomically: {exc} (the push may still be "
                               "applied, whole)") from None
    if response is None:
        raise DvtIdentifyError(f"model node {node_name!r}: set_parameters_atomically failed "
                               "(no response)")
    if not response.result.successful:
        raise DvtIdentifyError(f"model node refused {sorted(values)} (nothing applied): "
                               f"{response.result.reason}")
    return {"node": node_name, **values}


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
        self.pub_diag = self.create_publisher(rosutil.DiagnosticArray, DIAGNOSTICS, 10)
        self.create_service(Trigger, SRV_IDENTIFY_RUN, self._on_run)
        self.create_subscription(String, IDENTIFY_REQUEST, self._on_request, 10)
        self.create_timer(1.0, self._diagnostics)
        self.param_client = AsyncParameterClient(self, str(self.get_parameter("model_node").value))
        self.supervisor: sv.Supervisor | None = None
        self._setup_supervisor()

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

    def _push(self, values: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
        """Push (or roll back) the model node's parameters in one transaction
        (:func:`push_parameters`); called in a worker thread."""
        return push_parameters(self.param_client, values, timeout=timeout)

    # -- supervisor ---------------------------------------------------------------------
    def _setup_supervisor(self) -> None:
        """Declare ``supervisor.*``; when enabled, build the supervisor and wire its topics.

        Raises:
            SupervisorError: a parameter out of range (naming ``supervisor.<name>``).
        """
        p = sv.PREFIX
        enabled = bool(self.declare_parameter(f"{p}.enabled", False, ParameterDescriptor(
            description="run the self-closing loop (alarm -> refit -> push -> watch)",
            read_only=True)).value)
        def declare(name: str, default: Any, what: str) -> Any:
            # dynamic typing: `-p supervisor.watch_s:=60` (an integer) is a time, too; the
            # checks below (and SupervisorConfig.validated) name a value of the wrong kind
            return self.declare_parameter(f"{p}.{name}", default, ParameterDescriptor(
                description=what, read_only=True, dynamic_typing=True)).value

        values: dict[str, Any] = {}
        for name, default in sv.SupervisorConfig.parameters().items():
            values[name] = declare(name, default, f"supervisor {name} (docs/loop.md §3)")
        starts = declare("starts", 1, "multi-start count of the refit (0: the description's)")
        decim = declare("fit_decimate", 0, "decimation of the refit (0: the description's)")
        from_model = declare("from_model", True, "the refit starts from the model in use (then "
                             "from the description's prior); false: the prior only")
        timeout = declare("snapshot_timeout_s", 60.0, "seconds after the window's end to wait "
                          "for the recorder's snapshot")
        lag = declare("max_data_lag_s", 30.0, "the supervisor's clock is the newest residual "
                      "stamp, but at most this far behind the node clock [s]")
        hold = declare("hold_structure", True, "the first refit of an episode holds the "
                       "structure (M, D) at the model in use and fits the effects on top; "
                       "false: every refit frees everything")
        nice = declare("refit_nice", DEFAULT_NICE, "niceness of the refit process and of its "
                       "session's autogroup, -20..19 (19: the lowest priority, the chain comes "
                       "first; below the node's own: only with the right to)")
        for name, v in (("starts", starts), ("fit_decimate", decim)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise SupervisorError(f"{p}.{name}: expected an integer >= 0, got {v!r}")
        if isinstance(nice, bool) or not isinstance(nice, int) or not -20 <= nice <= 19:
            raise SupervisorError(f"{p}.refit_nice: expected an integer -20..19, got {nice!r}")
        for name, v in (("from_model", from_model), ("hold_structure", hold)):
            if not isinstance(v, bool):
                raise SupervisorError(f"{p}.{name}: expected true or false, got {v!r}")
        if isinstance(timeout, bool) or not isinstance(timeout, int | float) \
                or not (math.isfinite(timeout) and timeout > 0):
            raise SupervisorError(f"{p}.snapshot_timeout_s: expected a time > 0 s, got "
                                  f"{timeout!r}")
        self.snapshot_timeout_s = float(timeout)
        if isinstance(lag, bool) or not isinstance(lag, int | float) \
                or not (math.isfinite(lag) and lag >= 0):
            raise SupervisorError(f"{p}.max_data_lag_s: expected a time >= 0 s, got {lag!r}")
        self.max_data_lag_s = float(lag)
        self._newest_stamp = -math.inf
        self._sup_clock = -math.inf
        try:
            config = sv.SupervisorConfig(**values).validated()
        except TypeError as exc:  # pragma: no cover - parameter types are the declared ones
            raise SupervisorError(f"{p}: {exc}") from exc
        self.refit_settings = RefitSettings(
            description=str(self.get_parameter("description").value),
            augment=bool(self.get_parameter("augment").value),
            starts=int(starts) or None, fit_decimate=int(decim) or None,
            from_model=from_model, hold_structure=hold)
        self.refit_worker: RefitWorker | None = None
        if not enabled:
            return
        self.supervisor = sv.Supervisor(config)
        # the alarm topic is latched (transient local): alarms of an earlier run arrive first
        wall = self.get_clock().now().nanoseconds * 1e-9
        self.supervisor.ignore_before_s = wall - self.max_data_lag_s
        self.session = f"{IDENTIFY_NODE}-{time.time_ns()}"
        self.bad_alarms = 0
        self.episode_dirs: dict[int, Path] = {}
        self._snapshot_wait: dict[str, tuple[sv.RequestFit, Path, float]] = {}
        self._done: queue.SimpleQueue[Callable[[float], list[sv.Action]]] = queue.SimpleQueue()
        self._current: _Reader | None = None
        self._job: tuple[sv.RequestFit, Path, Path] | None = None  # waits for _current
        self._residual_reader = JointStateReader(SPEED_NAMES, VELOCITY)
        # the refit's process, started now: it imports the fit's code while nothing happens
        out_dir = Path(str(self.get_parameter("output_dir").value))
        self.refit_worker = RefitWorker(out_dir / "refit-process.log", nice=int(nice),
                                        warm=self.refit_settings.to_dict())
        try:
            self.refit_worker.start()
        except OSError as exc:  # the first refit tries again and reports what fails
            self.get_logger().error(f"refit process not started: {exc}")
        self.pub_snapshot = self.create_publisher(String, RECORDER_SNAPSHOT_REQUEST,
                                                  rosutil.qos(SNAPSHOT_REQUEST_QOS))
        self.pub_episode = self.create_publisher(String, IDENTIFY_EPISODE, rosutil.qos(CHANGE_QOS))
        self.create_subscription(String, MODEL_CHANGE, self._on_alarm, rosutil.qos(CHANGE_QOS))
        # raw: the 1 kHz residual costs two struct unpacks per sample, not a message object
        self.create_subscription(JointState, MODEL_RESIDUAL, self._on_residual,
                                 rosutil.SENSOR_QOS, raw=True)
        self.create_subscription(String, RECORDER_SNAPSHOT_RESULT, self._on_snapshot,
                                 rosutil.qos(CHANGE_QOS))
        self.create_timer(TICK_PERIOD, self._tick)
        self.get_logger().info(f"supervisor enabled: {config}; refit process pid "
                               f"{self.refit_worker.pid} at niceness {nice}")

    def _now(self) -> float:
        """The supervisor's clock [s]: the data time (the newest residual stamp) while the
        residual flows, never more than ``supervisor.max_data_lag_s`` behind the node clock
        (timeouts run when the data stop), never backwards. On a loaded host the model node
        (and a replay) fall seconds behind the wall clock; windows and watch in data time
        still hold the data they name."""
        wall = self.get_clock().now().nanoseconds * 1e-9
        self._sup_clock = max(self._sup_clock, self._newest_stamp, wall - self.max_data_lag_s)
        return self._sup_clock

    def _on_alarm(self, msg: String) -> None:
        if self.supervisor is None:
            return
        try:
            alarm = json.loads(msg.data)
            if not isinstance(alarm, dict):
                raise SupervisorError(f"alarm: expected a JSON object, got {msg.data[:80]!r}")
            actions = self.supervisor.on_alarm(alarm, self._now())
        except (ValueError, SupervisorError) as exc:
            self.bad_alarms += 1
            self.get_logger().warning(f"bad alarm on {MODEL_CHANGE} ignored: {exc}")
            return
        self._perform(actions)

    def _on_residual(self, raw: bytes) -> None:
        """One serialised residual (a raw subscription: read as the model node reads its
        inputs, :class:`dvt_model.node.JointStateReader`)."""
        if self.supervisor is None:
            return
        try:
            stamp = stamp_of(raw) * 1e-9
            residual, _ = self._residual_reader.read(raw)
            self.supervisor.observe(stamp, residual)
            if stamp > self._newest_stamp and math.isfinite(stamp):
                self._newest_stamp = stamp
        except (KeyError, ValueError, struct.error, UnicodeDecodeError, SupervisorError):
            return  # a malformed residual sample is skipped (counted by the model node)

    def _tick(self) -> None:
        if self.supervisor is None:
            return
        now = self._now()
        while not self._done.empty():
            self._perform(self._done.get()(now))
        for ident, (_req, _, deadline) in list(self._snapshot_wait.items()):
            if now > deadline:
                del self._snapshot_wait[ident]
                self._perform(self.supervisor.fit_done(sv.FitOutcome(error=(
                    f"no snapshot result from the recorder for {ident!r} within "
                    f"{self.snapshot_timeout_s:g} s after the window's end (is dvt-recorder "
                    "running with ring_minutes > 0?)")), now))
        self._refit_step(now)
        self._perform(self.supervisor.tick(now))
        self._refit_step(self._now())

    def _refit_step(self, now: float) -> None:
        """Hand the waiting job to the refit process once the model in use is read, take its
        answer, and kill it when the supervisor no longer waits for one (``fit_timeout_s``)."""
        sup, worker = self.supervisor, self.refit_worker
        if sup is None or worker is None:
            return
        if worker.busy and sup.state is not sv.State.REFITTING:
            worker.cancel()
            self.get_logger().warning(f"refit process killed: the supervisor stopped waiting "
                                      f"for its result (state {sup.state.value})")
        if self._job is not None and self._current is None:  # (read at the request, normally)
            self._current = _Reader(self._get_model_parameters)
        if self._job is not None and self._current is not None and self._current.done():
            req, snapshot, work = self._job
            self._job = None
            try:
                current = self._current.result()
                worker.submit(snapshot, req, current, work, self.refit_settings.to_dict())
            except Exception as exc:  # the model in use unreadable, no process: the outcome
                self._perform(sup.fit_done(sv.FitOutcome(error=(
                    f"{type(exc).__name__}: {exc}")), now))
                return
            self.get_logger().info(f"refit of episode {req.episode} ({req.stage}) handed to "
                                   f"the refit process (pid {worker.pid})")
        outcome = worker.poll()
        if outcome is not None:
            seconds = time.monotonic() - (worker.job_started_s or time.monotonic())
            summary = {**outcome.summary, "refit_seconds": seconds,
                       "refit_process": {"pid": worker.proc.pid if worker.proc else None,
                                         "nice": worker.nice, "started": worker.started,
                                         "crashes": worker.crashes}}
            if outcome.crashed:
                self.get_logger().error(outcome.error)
                worker.start()  # a new process warms up for the next episode
            self._perform(sup.fit_done(dataclasses.replace(outcome, summary=summary), now))

    def _perform(self, actions: list[sv.Action]) -> None:
        sup = self.supervisor
        if sup is None:
            return
        for a in actions:
            if isinstance(a, sv.Diagnostic):
                # one call site per severity (rclpy refuses another severity at a call site)
                if a.level >= rosutil.ERROR:
                    self.get_logger().error(a.message)
                elif a.level == rosutil.WARN:
                    self.get_logger().warning(a.message)
                else:
                    self.get_logger().info(a.message)
                self.pub_diag.publish(rosutil.diagnostic(
                    self, SUPERVISOR_DIAG, a.level, a.message, {**a.values, **sup.status()}))
            elif isinstance(a, sv.RequestFit):
                self._request_snapshot(a)
            elif isinstance(a, sv.Push):
                self._start_push(a.parameters, rollback=False)
            elif isinstance(a, sv.Rollback):
                self._start_push(a.parameters, rollback=True)
            elif isinstance(a, sv.Report):
                self._write_episode(a)

    def _episode_dir(self, episode: int) -> Path:
        d = self.episode_dirs.get(episode)
        if d is None:
            base = Path(str(self.get_parameter("output_dir").value)) / "episodes"
            d = base / f"episode-{episode}"
            k = 1
            while d.exists() or d.with_suffix(".json").exists():  # an earlier node's episode
                k += 1
                d = base / f"episode-{episode}-{k}"
            self.episode_dirs[episode] = d
        return d

    def _require_supervisor(self) -> sv.Supervisor:
        """The supervisor; only its own actions call this, so it exists unless misused."""
        if self.supervisor is None:
            raise DvtIdentifyError("supervisor action without a supervisor "
                                   "(parameter supervisor.enabled is false)")
        return self.supervisor

    def _request_snapshot(self, req: sv.RequestFit) -> None:
        sup = self._require_supervisor()
        now = self._now()
        # each refit of the episode (its stage) has its own snapshot, bags and report
        work = self._episode_dir(req.episode) / req.stage
        if self.pub_snapshot.get_subscription_count() == 0:
            self._perform(sup.fit_done(sv.FitOutcome(error=(
                f"no recorder subscribed to {RECORDER_SNAPSHOT_REQUEST} (start dvt-recorder "
                "with ring_minutes > 0)")), now))
            return
        work.mkdir(parents=True, exist_ok=True)
        # the model in use (and what a rollback restores) is read while the snapshot is made
        self._current = _Reader(self._get_model_parameters)
        ident = f"{self.session}/episode-{req.episode}/{req.stage}"
        out = work / "snapshot"
        self._snapshot_wait[ident] = (req, work, req.validation[1] + self.snapshot_timeout_s)
        self.pub_snapshot.publish(String(data=json.dumps(
            {"from": req.estimation[0], "to": req.validation[1], "out": str(out.resolve()),
             "id": ident})))
        self.get_logger().info(f"snapshot {ident}: [{req.estimation[0]:.3f}, "
                               f"{req.validation[1]:.3f}] s requested -> {out}")

    def _on_snapshot(self, msg: String) -> None:
        sup = self.supervisor
        if sup is None:
            return
        try:
            data = json.loads(msg.data)
            ident = data.get("id") if isinstance(data, dict) else None
        except ValueError:
            return
        if not isinstance(ident, str) or ident not in self._snapshot_wait:
            return  # another client's (or an earlier session's latched) result
        req, work, _ = self._snapshot_wait.pop(ident)
        if not data.get("ok"):
            self._perform(sup.fit_done(sv.FitOutcome(error=(
                f"snapshot {ident} failed: {data.get('error')}")), self._now()))
            return
        if data.get("truncated"):
            self.get_logger().warning(f"snapshot {ident}: the window starts before the ring's "
                                      "oldest segment (truncated)")
        worker = self.refit_worker
        if self._job is not None or (worker is not None and worker.busy):
            self._perform(sup.fit_done(sv.FitOutcome(error="busy: the previous refit is still "
                                                     "running"), self._now()))
            return
        self._job = (req, Path(str(data.get("out"))), work)
        self._refit_step(self._now())

    def _get_model_parameters(self) -> dict[str, Any]:
        """The model node's current parameter values (``None``: not set), read through its
        parameter services; called in a worker thread."""
        if not self.param_client.wait_for_services(timeout_sec=5.0):
            raise DvtIdentifyError(f"model node {self.param_client.remote_node_name!r} has no "
                                   "parameter services (not running?)")
        names = list(MODEL_PARAMETERS)
        future = self.param_client.get_parameters(names)
        deadline = time.monotonic() + PARAMETER_TIMEOUT
        while not future.done():
            if time.monotonic() > deadline:
                raise DvtIdentifyError(f"model node did not answer get_parameters within "
                                       f"{PARAMETER_TIMEOUT:g} s")
            time.sleep(0.01)
        values = future.result().values
        return {n: plain_value(Parameter.from_parameter_msg(
            rosutil_parameter(n, v)).value) for n, v in zip(names, values, strict=True)}

    def _start_push(self, values: Mapping[str, Any], rollback: bool) -> None:
        sup = self._require_supervisor()

        def work() -> None:
            try:  # the supervisor's push_timeout_s bounds the wait (a busy model node
                # answers its parameter services after the samples queued before the call)
                self._push(dict(values), timeout=sup.config.push_timeout_s)
                ok, error = True, ""
            except DvtIdentifyError as exc:
                ok, error = False, str(exc)
            except Exception as exc:  # never take the node down
                ok, error = False, f"{type(exc).__name__}: {exc}"
            done = sup.rollback_done if rollback else sup.push_done
            self._done.put(lambda now: done(ok, now, error))

        threading.Thread(target=work, daemon=True, name="dvt-push").start()

    def _write_episode(self, report: sv.Report) -> None:
        record = report.record
        work = self._episode_dir(report.episode)
        record["directory"] = str(work)
        text = json.dumps(record, indent=2, default=_json_default, allow_nan=True)
        try:
            work.parent.mkdir(parents=True, exist_ok=True)
            (work.parent / f"{work.name}.json").write_text(text + "\n")
            (work.parent / f"{work.name}.md").write_text(sv.episode_markdown(record))
        except OSError as exc:
            self.get_logger().error(f"episode report {work}.json not written: {exc}")
        self.pub_episode.publish(String(data=text))
        self.get_logger().info(f"episode {report.episode}: {record.get('outcome')} -> "
                               f"{work.parent / (work.name + '.json')}")

    def on_shutdown_hook(self) -> None:
        """Stop and reap the refit process (:func:`dvt_model.rosutil.spin` calls this when the
        node stops; :meth:`destroy_node` too)."""
        worker = getattr(self, "refit_worker", None)
        if worker is not None:
            worker.close()

    def destroy_node(self) -> None:
        self.on_shutdown_hook()
        super().destroy_node()

    def _diagnostics(self) -> None:
        level = {"failed": rosutil.ERROR}.get(self.state, rosutil.OK)
        values: dict[str, Any] = {"state": self.state, "runs": self.runs}
        for key in ("baseline_fit_percent", "final_fit_percent", "accepted", "error", "report"):
            if key in self.last:
                values[key] = self.last[key]
        self.pub_diag.publish(rosutil.diagnostic(self, IDENTIFY_NODE, level, self.state,
                                                 values))
        if self.supervisor is not None:
            worker = self.refit_worker
            refit = {} if worker is None else {
                "refit_process_pid": worker.pid, "refit_process_nice": worker.nice,
                "refit_process_ready": worker.ready,
                "refit_processes_started": worker.started, "refit_crashes": worker.crashes}
            self.pub_diag.publish(rosutil.diagnostic(
                self, SUPERVISOR_DIAG, rosutil.OK, f"supervisor: {self.supervisor.state.value}",
                {**self.supervisor.status(), "bad_alarms": self.bad_alarms, **refit}))


class _Reader:
    """Runs ``fn`` in a thread at once; :meth:`result` waits for its value (or raises its
    exception)."""

    def __init__(self, fn: Callable[[], dict[str, Any]]) -> None:
        self._value: dict[str, Any] = {}
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(fn,), daemon=True,
                                        name="dvt-get-parameters")
        self._thread.start()

    def _run(self, fn: Callable[[], dict[str, Any]]) -> None:
        try:
            self._value = fn()
        except BaseException as exc:  # handed to the caller of result()
            self._error = exc

    def done(self) -> bool:
        """Whether the value (or the exception) is there: :meth:`result` will not wait."""
        return not self._thread.is_alive()

    def result(self) -> dict[str, Any]:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def rosutil_parameter(name: str, value: Any) -> Any:
    """A ``rcl_interfaces/Parameter`` message from a ``ParameterValue`` (for
    :meth:`Parameter.from_parameter_msg`)."""
    from rcl_interfaces.msg import Parameter as ParameterMsg

    return ParameterMsg(name=name, value=value)


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, tuple | set):
        return list(obj)
    return str(obj)


def main(args: list[str] | None = None) -> None:
    rosutil.init(args, reply_wait=REPLY_WAIT_SERVICES)
    try:
        node = IdentifyNode()
    except SupervisorError as exc:  # invalid supervisor.* parameters given at start-up
        print(f"dvt_identify_node: {exc}", file=sys.stderr)
        if rclpy.ok():
            rclpy.shutdown()
        sys.exit(2)
    rosutil.spin(node)


if __name__ == "__main__":
    main()
