"""``dvt_model_node``: live prediction of the measured speeds (thin rclpy layer).

Subscribes ``/dvt/joint_states`` and ``/dvt/currents``, pairs them by their identical stamp
(:class:`dvt_model.recording.pairing.LivePairer`), feeds each sample to
:class:`dvt_model.predictor.Predictor` and publishes ``/dvt/model/joint_states`` (prediction)
and ``/dvt/model/residual`` (measured - predicted), stamped like the measured sample, plus
``/diagnostics`` at 1 Hz. Names and QoS are the contract's (:mod:`dvt_model.contract`).
When the measured ``/dvt/joint_states`` carries ``position`` (a protocol-version-2
controller), the prediction carries the predicted ``position`` [rad] and the residual the
position residual [rad] (measured - predicted), same names; the model's angles are anchored to
the measured ones at every anchor (:mod:`dvt_model.predictor`). Without measured positions
both messages carry ``velocity`` only, as before.

Parameters: :data:`dvt_model.contract.MODEL_PARAMETERS` (name, type, unit, meaning, default and
admissible values; the descriptions the node declares are taken from it): ``params``, ``M``,
``D``, ``motor_constant``, ``band_gain``, ``band_time_constant``, ``A``, ``B``, ``effects``,
``mode``, ``reanchor_period``, ``gap_reset``, ``load`` (the joint load on carrier 3:
``none``, ``arm``, ``arm-payload`` or a load YAML, :mod:`dvt_model.load`). All are
changeable at runtime through the standard parameter services. Every change is validated by
:func:`dvt_model.config.model_transaction` (the checks of
:func:`dvt_model.config.check_parameters`); a refused change leaves the current model
running, its reason names the parameter, the value and what is admissible, and
every refusal (including an unknown parameter name or a value of the wrong type) is counted in
``/diagnostics`` as ``rejected_parameter_changes`` (the latest reason as ``last_refusal``).

Transactions (a push or a rollback of the identifier, ``docs/interface.md`` §6): a client that
changes several parameters at once calls the standard service ``~/set_parameters_atomically``
(``rcl_interfaces/srv/SetParametersAtomically``; rclpy's
``AsyncParameterClient.set_parameters_atomically``). rclpy hands the whole set to the on-set
callback once; the node validates it together against the current values and builds one
predictor (:func:`~dvt_model.config.model_transaction`). Any refused member refuses the set:
no parameter is stored, the running predictor and the detector are untouched. An accepted set
is stored by rclpy as one parameter event, and then (post-set callback) the node swaps in the
predictor and resets the detector, once. A request is one DDS sample: a client killed while it
pushes has either delivered the whole set (applied whole, whether or not the client lives to
read the answer) or nothing. The plain ``~/set_parameters`` service (``ros2 param set``)
applies each parameter of its request as its own transaction (rclpy), validated the same way:
fine for one value, not for a model (a refused member would leave the ones before it applied).

Why the atomic service and not one structured parameter (e.g. the whole model as one JSON
string): it is what a ROS 2 engineer expects of a node whose settings belong together. Each
quantity stays an ordinary typed, described parameter (``ros2 param get/describe``, params
files, launch, parameter events per name), set together or alone through the same validation,
and there is no second representation of the same values to keep in step (one place per
concept); the standard service already means "validate together, all or nothing".

The linear model: ``A`` and ``B`` must be given together (one transaction, e.g.
``set_parameters_atomically``); setting ``A`` or ``B`` to an empty list (plain
``SetParameters`` is enough) clears the linear model: the other one is emptied in the same
transaction (a pre-set callback adds it, :func:`~dvt_model.config.partner_clears`) and the
node runs the physics again.

The change detector (``detector.*`` parameters, read-only; ``docs/loop.md``): every residual
goes through :class:`dvt_model.detect.ChangeDetector` (a whitened two-sided CUSUM per output),
as means of ``detector.block_s`` blocks (10 ms = 10 samples at 1 kHz,
:class:`~dvt_model.predictor.ResidualBlocks`): the encoder's speed quantisation makes the
per-sample sun-shaft residual a two-level pattern that no ARMA(1,1) whitening makes Gaussian
(per sample the detector raised an alarm within 0.1 s of every reference window on a clean
simulated plant); its 10-ms mean is well behaved. The alarm's ``change_s`` and ``stamp_s`` are
block starts (resolution ``block_s``). After every anchor of the model to the measurement in
simulate mode (the first sample, a stream restart, a guard re-anchor) the detector waits
``detector.settle_s`` (the anchor's error decays with the transmission's time constants) and
then learns anew (``anchor_restarts`` in its status). After a re-anchor on lost samples (a
gap beyond ``gap_reanchor`` but within ``gap_reset``: the same stream and model, inputs
unknown for a moment) it only waits ``detector.settle_s`` and keeps its reference and CUSUMs
(``gap_reanchors`` in the node's status). On an alarm the node publishes the
alarm's JSON
(:meth:`~dvt_model.detect.Alarm.to_json`: ``change_s`` the estimated change time, ``stamp_s``
the detection, ``name``, ``direction``, ``shift`` [rad/s]) on ``/dvt/model/change``
(:data:`~dvt_model.contract.MODEL_CHANGE`, reliable, transient-local, depth 10) and at once a
WARN status ``dvt_model: change detector`` on ``/diagnostics``; the detector then re-learns and
the node keeps running. Every diagnostics period carries the detector's status (``state``
learning/testing, ``alarms``, ``phi``, ``k``, ``h``, the CUSUMs per output; level WARN for
:data:`ALARM_HOLD_S` after an alarm, else OK). Every accepted change of the model's parameters
(a push or a rollback, one transaction) resets the detector once: it learns the new model's
residual first.
``detector.enabled:=false`` turns it off.

Service ``~/reset_detector`` (:data:`~dvt_model.contract.SRV_MODEL_RESET_DETECTOR`,
``std_srvs/srv/Trigger``; ``/dvt_model/reset_detector`` by default): the detector forgets its
learned reference, its CUSUMs, the residual block in progress and the latched alarm (the WARN
hold of the last alarm), and learns a new reference from the next samples (after a settling in
progress, if any). The model is not touched (no re-anchor). The answer is ``success=True`` with
a message saying what was reset, or ``success=False`` with the reason when the detector is off
(``detector.enabled:=false``); every request is logged (a reset at INFO, starting with
:data:`~dvt_model.contract.RESET_DETECTOR_LOG`). The node is a plain node, not a lifecycle node:
it answers whenever it runs. ``dvt-launch`` calls it to re-arm the detector once the machine
moves (:func:`dvt_driver.run.launch._rearm`); ``requested_resets`` in the detector's status
counts these resets (``resets`` the ones by model changes).

Latency (issue #11; ``dvt-bench model``): the two input streams are taken raw (CDR bytes,
:class:`JointStateReader`: the layout of the last message is cached, a sample costs two
``struct`` unpacks) and the prediction and residual are published raw
(:class:`JointStateWriter`: a template whose stamp and values are overwritten), so no rclpy
message object is built or converted per sample; the published messages are the ones rclpy
would send. ``main`` freezes the objects built at start-up out of the garbage collector's full
passes (tens of milliseconds with rclpy, numpy and scipy loaded). Per sample the callback then
costs about 50 us of CPU (in process, median, on the shared 2-core development machine), about
half of it the model step (:meth:`HybridModel.step <dvt_model.hybrid.HybridModel.step>`, about
25 us); the detector about 2 us (its reference window's end,
once per ``detector.learn_s``, about 2.5 ms).

The guard: the predictor never publishes a non-finite or diverging prediction; it re-anchors
to the measurement instead (:data:`dvt_model.predictor.OMEGA_GUARD`), and ``/diagnostics``
reports the count as ``guard_reanchors`` with level WARN.
"""

from __future__ import annotations

import gc
import struct
import sys
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from dvt_model import rosutil
from dvt_model.config import (
    UNSET,
    ModelTransaction,
    build_predictor,
    detector_config,
    model_key,
    model_transaction,
    partner_clears,
)
from dvt_model.contract import (
    CHANGE_QOS,
    CURRENT_NAMES,
    CURRENTS,
    DIAGNOSTICS,
    DIAGNOSTICS_QOS,
    JOINT_STATES,
    MODEL_CHANGE,
    MODEL_JOINT_STATES,
    MODEL_NODE,
    MODEL_PARAMETERS,
    MODEL_RESIDUAL,
    RESET_DETECTOR_LOG,
    SPEED_NAMES,
    SRV_MODEL_RESET_DETECTOR,
    NodeParam,
    model_reset_detector_service,
)
from dvt_model.detect import Alarm, ChangeDetector, ColourKeeper, warm_up
from dvt_model.errors import DvtModelError
from dvt_model.predictor import Predictor, ResidualBlocks
from dvt_model.recording import cdr
from dvt_model.recording.pairing import LivePairer

_REFUSABLE = (DvtModelError, ValueError, TypeError, ArithmeticError, np.linalg.LinAlgError)
"""What a parameter check may raise; each becomes a counted refusal, never a crash."""
ResetCause = Literal["request", "model", "anchor"]
"""Why the detector is reset (:meth:`ModelNode._reset_detector`)."""
ALARM_HOLD_S = 10.0
"""The periodic detector status stays WARN this long after an alarm [s, node clock]."""
DETECTOR_STATUS = f"{MODEL_NODE}: change detector"
"""Name of the detector's ``DiagnosticStatus``."""


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


# ------------------------------------------------------------- the 1 kHz streams as CDR
# The node takes and publishes the JointState streams as serialised CDR (raw subscriptions,
# raw publishing): deserialising, building and converting rclpy message objects cost about as
# much per sample as the model step (measured ~80 of ~165 us of the callback's CPU time before,
# ~10 us now); what goes over the wire is the same.
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_LE = cdr.CDR_LE[:2]
POSITION, VELOCITY, EFFORT = 0, 1, 2
"""The ``field`` of :class:`JointStateReader`: which array of a JointState it reads."""
_POSITION, _VELOCITY, _EFFORT = POSITION, VELOCITY, EFFORT


def stamp_of(raw: bytes) -> int:
    """``header.stamp`` [ns] of a serialised JointState (any encapsulation)."""
    if raw[:2] == _LE:
        sec, nanosec = _STAMP.unpack_from(raw, 4)
        return int(sec * 1_000_000_000 + nanosec)
    return rosutil.stamp_to_ns(deserialize_message(raw, JointState).header.stamp)


class JointStateReader:
    """Reads one array (``field``: position 0, velocity 1, effort 2) of serialised JointState
    messages in the order of ``wanted`` names, exactly as ``dict(zip(msg.name, array,
    strict=True))[name]`` would (a name listed twice: its last value; an array whose length is
    not the names' raises ValueError, a missing name KeyError), and the positions in the same
    order when the message carries one per name (``None`` otherwise).

    The layout of the last message (names, array lengths) is cached: a message with the same
    bytes up to its arrays costs two ``struct`` unpacks and a list. Any other layout is
    decoded with :func:`dvt_model.recording.cdr.cdr_layout` (little endian) or rclpy's
    ``deserialize_message`` (anything else).
    """

    def __init__(self, wanted: Sequence[str], field: int, positions: bool = False) -> None:
        self.wanted = tuple(wanted)
        self.field = field
        self.positions = positions
        self._size = -1
        self._head = b""
        self._head_end = 0
        self._counts = ((0, 0), (0, 0))  # (offset, count) of the velocity and effort counts
        self._values: tuple[struct.Struct, int] | None = None
        self._pos: tuple[struct.Struct, int] | None = None
        self._index: tuple[int, ...] | None = None  # None: identity
        self._error: tuple[type[Exception], str] | None = None  # this layout's error

    def _learn(self, raw: bytes) -> None:
        """Cache the layout of ``raw`` (little-endian CDR; raises as ``cdr_layout``)."""
        self._size = -1  # invalid until complete
        lay = cdr.cdr_layout(raw)
        # where each array's count lies (cdr_layout gives where its data starts)
        pos = 12
        pos += 4 + _U32.unpack_from(raw, pos)[0]  # frame_id
        pos += -(pos - 4) % 4
        pos += 4  # number of names
        for _ in lay.names:
            pos += -(pos - 4) % 4
            pos += 4 + _U32.unpack_from(raw, pos)[0]
        count_at = []
        for _, count in lay.arrays:
            pos += -(pos - 4) % 4
            count_at.append(pos)
            pos += 4
            if count:
                pos += -(pos - 4) % 8
            pos += 8 * count
        self._head_end = count_at[0] + 4
        self._head = raw[12:self._head_end]
        self._counts = ((count_at[1], lay.arrays[1][1]), (count_at[2], lay.arrays[2][1]))
        names = lay.names
        off, count = lay.arrays[self.field]
        self._error = None
        self._index = None
        if count != len(names):
            self._error = (ValueError, f"{len(names)} names but {count} values")
        else:
            last = {name: i for i, name in enumerate(names)}
            missing = [w for w in self.wanted if w not in last]
            if missing:
                self._error = (KeyError, missing[0])
            else:
                index = tuple(last[w] for w in self.wanted)
                if index != tuple(range(count)):
                    self._index = index
        self._values = (struct.Struct(f"<{count}d"), off)
        p_off, p_count = lay.arrays[_POSITION]
        self._pos = ((struct.Struct(f"<{p_count}d"), p_off)
                     if self.positions and p_count == len(names) and p_count else None)
        self._size = len(raw)

    def _fits(self, raw: bytes) -> bool:
        if len(raw) != self._size or raw[12:self._head_end] != self._head:
            return False
        (at1, n1), (at2, n2) = self._counts
        return _U32.unpack_from(raw, at1)[0] == n1 and _U32.unpack_from(raw, at2)[0] == n2

    def read(self, raw: bytes) -> tuple[list[float], list[float] | None]:
        """``(values of wanted, positions of wanted or None)`` of one serialised message."""
        if not self._fits(raw):
            if raw[:2] != _LE:
                return self._read_slow(raw)
            self._learn(raw)
        if self._error is not None:  # a new exception each time (raising one grows it)
            kind, text = self._error
            raise kind(text)
        st, off = self._values  # type: ignore[misc]
        vals = st.unpack_from(raw, off)
        index = self._index
        out = list(vals) if index is None else [vals[i] for i in index]
        pos: list[float] | None = None
        if self._pos is not None:
            pst, poff = self._pos
            p = pst.unpack_from(raw, poff)
            pos = list(p) if index is None else [p[i] for i in index]
        return out, pos

    def _read_slow(self, raw: bytes) -> tuple[list[float], list[float] | None]:
        """Another encapsulation (e.g. big endian): rclpy's own deserialisation."""
        msg = deserialize_message(raw, JointState)
        arrays = (msg.position, msg.velocity, msg.effort)
        by_name = dict(zip(msg.name, arrays[self.field], strict=True))
        out = [by_name[w] for w in self.wanted]
        pos = None
        if self.positions and len(msg.position) == len(msg.name):
            angles = dict(zip(msg.name, msg.position, strict=True))
            pos = [angles[w] for w in self.wanted]
        return out, pos


class JointStateWriter:
    """Serialised JointState messages of fixed ``names`` with ``velocity`` and optionally
    ``position`` (empty ``effort``): a template whose stamp and values are overwritten in
    place (the bytes ``rclpy`` would publish for the same message, up to padding)."""

    def __init__(self, names: Sequence[str]) -> None:
        n = len(names)
        zeros = [0.0] * n
        self._vel = bytearray(cdr.joint_state_cdr(0, names, velocity=zeros))
        self._both = bytearray(cdr.joint_state_cdr(0, names, position=zeros, velocity=zeros))
        self._vel_off = cdr.cdr_layout(bytes(self._vel)).arrays[_VELOCITY][0]
        both = cdr.cdr_layout(bytes(self._both)).arrays
        self._both_pos, self._both_vel = both[_POSITION][0], both[_VELOCITY][0]
        self._pack = struct.Struct(f"<{n}d").pack_into

    def encode(self, stamp_ns: int, velocity: Sequence[float],
               position: Sequence[float] | None = None) -> bytes:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        if position is None:
            buf = self._vel
            self._pack(buf, self._vel_off, *velocity)
        else:
            buf = self._both
            self._pack(buf, self._both_pos, *position)
            self._pack(buf, self._both_vel, *velocity)
        _STAMP.pack_into(buf, 4, sec, nanosec)
        return bytes(buf)


class ModelNode(Node):
    """The live model node (see the module docstring)."""

    def __init__(self, *, context: Context | None = None) -> None:
        super().__init__(MODEL_NODE, allow_undeclared_parameters=True, context=context)
        for spec in MODEL_PARAMETERS.values():
            self.declare_parameter(spec.name, _initial(spec), _descriptor(spec))
        self.predictor: Predictor
        self.predictor, self.model_desc = build_predictor(self._values())
        setup = detector_config(self._values())
        self.detector: ChangeDetector | None = None
        self.blocks: ResidualBlocks | None = None
        self.settle_s = 0.0
        self._settle_until = -float("inf")  # stamp [s] before which the detector waits
        self._last_stamp = -float("inf")
        self.anchor_restarts = 0
        self.keeper: ColourKeeper | None = None
        if setup is not None:
            self.settle_s = setup.settle_s
            carried = None
            if setup.colour_file:
                self.keeper = ColourKeeper(setup.colour_file, model_key(self._values()))
                carried, line, warn = self.keeper.load(setup.config)
                (self.get_logger().warning if warn else self.get_logger().info)(line)
            self.detector = ChangeDetector(setup.config, carried)
            warm_up(setup.config)
            self.blocks = ResidualBlocks(setup.block, len(SPEED_NAMES),
                                         setup.config.max_gap_s)
        self.detector_resets = 0  # resets by accepted model changes (push, rollback)
        self.requested_resets = 0  # resets through SRV_MODEL_RESET_DETECTOR
        self._alarm_at: float | None = None  # node clock [s] of the last alarm
        self.rejected = 0
        self.last_refusal = ""
        self.bad_messages = 0
        self.published = 0
        self._guard_before = 0  # guard re-anchors of the predictors replaced so far
        self._gap_before = 0  # re-anchors on lost samples of the predictors replaced so far
        self._staged: ModelTransaction | None = None  # accepted by _on_set, applied next
        self.pairer: LivePairer[bytes] = LivePairer(slots=2, max_pending=2000)
        self._speeds = JointStateReader(SPEED_NAMES, _VELOCITY, positions=True)
        self._currents = JointStateReader(CURRENT_NAMES, _EFFORT)
        self._writer = JointStateWriter(SPEED_NAMES)
        self.add_pre_set_parameters_callback(self._complete)
        self.add_on_set_parameters_callback(self._on_set)
        self.add_post_set_parameters_callback(self._apply)
        self.pub_pred = self.create_publisher(JointState, MODEL_JOINT_STATES,
                                              rosutil.SENSOR_QOS)
        self.pub_res = self.create_publisher(JointState, MODEL_RESIDUAL, rosutil.SENSOR_QOS)
        self.pub_diag = self.create_publisher(rosutil.DiagnosticArray, DIAGNOSTICS,
                                              rosutil.qos(DIAGNOSTICS_QOS))
        self.pub_change = self.create_publisher(String, MODEL_CHANGE, rosutil.qos(CHANGE_QOS))
        self.create_subscription(JointState, JOINT_STATES, lambda m: self._on_msg(m, 0),
                                 rosutil.SENSOR_QOS, raw=True)
        self.create_subscription(JointState, CURRENTS, lambda m: self._on_msg(m, 1),
                                 rosutil.SENSOR_QOS, raw=True)
        self.create_timer(1.0, self._diagnostics)
        self.create_service(Trigger, SRV_MODEL_RESET_DETECTOR, self._on_reset_detector)
        self.get_logger().info(f"model: {self.model_desc}, mode {self.predictor.mode}, change "
                               "detector " + ("on" if self.detector is not None else "off"))

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

    @staticmethod
    def _changes(params: list[Parameter]) -> dict[str, Any]:
        """A request's parameters as a change set (name -> value; unset: :data:`UNSET`)."""
        return {p.name: UNSET if p.type_ == Parameter.Type.NOT_SET else p.value
                for p in params}

    def _complete(self, params: list[Parameter]) -> list[Parameter]:
        """Pre-set callback: the A/B rule's partner joins the same transaction (emptying
        ``A`` alone empties ``B`` too, :func:`~dvt_model.config.partner_clears`)."""
        try:
            extra = partner_clears(self._values(), self._changes(params))
        except Exception as exc:  # never raise in rclpy's callback: on_set refuses the set
            self.get_logger().warning(f"parameter request not completed: {exc!r}")
            return params
        return [*params, *(Parameter(n, Parameter.Type.DOUBLE_ARRAY, []) for n in extra)]

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        """On-set callback: validate the request's whole set together (one transaction,
        :func:`~dvt_model.config.model_transaction`) and stage its predictor; nothing is
        applied here (rclpy stores the values only if every on-set callback accepts)."""
        self._staged = None
        try:
            self._staged = model_transaction(self._values(), self._changes(params),
                                             self.has_parameter)
        except _REFUSABLE as exc:
            return self._refuse(str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, params: list[Parameter]) -> None:
        """Post-set callback: rclpy stored the accepted set; run its model from now on (one
        predictor swap, one detector reset; nothing to do for non-model parameters)."""
        tx, self._staged = self._staged, None
        if tx is None:
            return
        self._guard_before += self.predictor.guard_reanchors
        self._gap_before += self.predictor.gap_anchors
        self.predictor, self.model_desc = tx.predictor, tx.description
        if self.keeper is not None:
            self.keeper.model_changed(model_key(self._values()))
        # a push or rollback: learn the new model's residual (the last alarm's WARN hold stays)
        self._reset_detector("model")
        self.get_logger().info(f"model changed ({', '.join(tx.changed)}): "
                               f"{tx.description}, mode {tx.predictor.mode}")

    def _on_msg(self, raw: Any, slot: int) -> None:
        """One serialised message (``bytes`` of a raw subscription) of ``/dvt/joint_states``
        (slot 0) or ``/dvt/currents`` (1)."""
        try:
            stamp_ns = stamp_of(raw)
        except Exception as exc:  # an undecodable message is counted, never fatal
            self._bad(f"message on slot {slot} ignored: {exc!r}")
            return
        pair = self.pairer.add(stamp_ns, slot, raw)
        if pair is not None:
            self._process(stamp_ns, pair[0], pair[1])

    def _bad(self, text: str) -> None:
        self.bad_messages += 1
        if self.bad_messages <= 5 or self.bad_messages % 1000 == 0:
            self.get_logger().warning(text)

    def _process(self, stamp_ns: int, js: bytes, cur: bytes) -> None:
        try:
            omega, theta = self._speeds.read(js)
            currents, _ = self._currents.read(cur)
            pred = self.predictor.update(stamp_ns * 1e-9, currents[0], currents[1:], omega,
                                         theta)
        except (KeyError, ValueError, struct.error, UnicodeDecodeError, DvtModelError) as exc:
            self._bad(f"sample at {stamp_ns} ns ignored: {exc!r}")
            return
        residual = pred.residual.tolist()
        encode = self._writer.encode
        if pred.position_residual is not None:
            out = encode(stamp_ns, pred.predicted.tolist(), pred.predicted_position.tolist())
            res = encode(stamp_ns, residual, pred.position_residual.tolist())
        else:
            out = encode(stamp_ns, pred.predicted.tolist())
            res = encode(stamp_ns, residual)
        self.pub_pred.publish(out)
        self.pub_res.publish(res)
        self.published += 1
        if self.blocks is not None:  # after publishing: the residual's latency comes first
            t = stamp_ns * 1e-9
            self._last_stamp = t
            if pred.anchored and self.predictor.mode == "simulate":
                if pred.lost:  # lost samples: the same stream, the reference stays
                    self.blocks.clear()
                    self._settle_until = t + self.settle_s
                else:
                    self._restart_detector(t)
            if t < self._settle_until:
                return
            block = self.blocks.add(t, residual)
            if block is not None and self.detector is not None:
                alarm = self.detector.update(block[0], block[1])
                if alarm is not None:
                    self._on_alarm(alarm)
                if self.keeper is not None:
                    error = self.keeper.after_update(self.detector)
                    if error is not None:
                        self.get_logger().warning(error)

    def _restart_detector(self, stamp: float) -> None:
        """The model was anchored to the measurement at ``stamp`` [s]: wait ``settle_s``, then
        learn anew."""
        if self._reset_detector("anchor") is not None:
            self._settle_until = stamp + self.settle_s

    def _reset_detector(self, cause: ResetCause) -> str | None:
        """Make the detector learn anew from the next samples (the one reset path of the node):
        forget its reference and CUSUMs (:meth:`ChangeDetector.reset`) and the residual block
        in progress. ``cause``: ``"request"`` (:data:`SRV_MODEL_RESET_DETECTOR`; also ends the
        latched alarm, the WARN hold of :data:`ALARM_HOLD_S`; counted as ``requested_resets``),
        ``"model"`` (an accepted model change; ``resets``) or ``"anchor"`` (an anchor of the
        model; ``anchor_restarts``, the caller then sets the settling). A settling in progress
        (``detector.settle_s`` after an anchor) is kept.

        Returns what was reset (one line), or ``None`` when the detector is off.
        """
        det, blocks = self.detector, self.blocks
        if det is None or blocks is None:
            return None
        if det.learning:
            parts = [f"the reference being learned ({100.0 * det.learn_progress:.0f} % of it)"]
        else:
            parts = ["the learned reference", "the CUSUMs"]
        det.reset()
        blocks.clear()
        parts.append("the residual block in progress")
        if cause == "request":
            if self._alarm_at is not None:
                parts.append("the latched alarm")
            self._alarm_at = None
            self.requested_resets += 1
        elif cause == "model":
            self.detector_resets += 1
        else:
            self.anchor_restarts += 1
        settling = self._last_stamp < self._settle_until
        return (f"forgot {', '.join(parts)}; learns a new reference "
                f"({det.config.learn_s:g} s of residual) from the next samples"
                + (" once the settling after the last anchor ends" if settling else ""))

    def _on_reset_detector(self, request: Trigger.Request,
                           response: Trigger.Response) -> Trigger.Response:
        """:data:`SRV_MODEL_RESET_DETECTOR`: reset the detector (:meth:`_reset_detector`) and
        say so."""
        service = model_reset_detector_service(self.get_fully_qualified_name())
        done = self._reset_detector("request")
        if done is None:
            response.success = False
            response.message = (f"{service} refused: the change detector is off "
                                "(detector.enabled is false), nothing to reset")
            self.get_logger().warning(response.message)
            return response
        response.success = True
        response.message = f"{RESET_DETECTOR_LOG} (reset {self.requested_resets}): {done}"
        self.get_logger().info(response.message)
        return response

    def _on_alarm(self, alarm: Alarm) -> None:
        """Publish an alarm on the change topic and as WARN on ``/diagnostics``."""
        self._alarm_at = self.get_clock().now().nanoseconds * 1e-9
        self.pub_change.publish(String(data=alarm.to_json()))
        message = (f"change on {alarm.name} at {alarm.change_s:.3f} (shift {alarm.shift:+.4g} "
                   f"rad/s, detected at {alarm.stamp_s:.3f})")
        self.get_logger().warning(f"change detector: {message}")
        if self.detector is not None:
            self.pub_diag.publish(rosutil.diagnostic(self, DETECTOR_STATUS, rosutil.WARN,
                                                     message, self._detector_values()))

    def _detector_values(self) -> dict[str, str]:
        det = self.detector
        if det is None:
            return {"state": "off"}
        values = det.status()
        values["resets"] = str(self.detector_resets)
        values["requested_resets"] = str(self.requested_resets)
        values["anchor_restarts"] = str(self.anchor_restarts)
        if self.keeper is not None:
            values["colour_file"] = str(self.keeper.path)
            values["colour_file_saves"] = str(self.keeper.saves)
        if det.learning and self._last_stamp < self._settle_until:
            values["state"] = "settling"
        last = det.counters.last_alarm
        if last is not None:
            values["last_alarm"] = last.to_json()
        return values

    def _position_rms(self) -> dict[str, str]:
        rms = self.predictor.position_residual_rms
        if rms is None:
            return {}
        return {"position_residual_rms_sun_shaft": f"{rms[0]:.6g}",
                "position_residual_rms_carrier3": f"{rms[1]:.6g}"}

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
            "gap_reanchors": self._gap_before + self.predictor.gap_anchors,
            "residual_rms_sun_shaft": f"{rms[0]:.6g}",
            "residual_rms_carrier3": f"{rms[1]:.6g}",
            **self._position_rms(),
            "bad_messages": self.bad_messages,
            "unpaired": self.pairer.unpaired,
            "rejected_parameter_changes": self.rejected,
            "last_refusal": self.last_refusal,
        }))
        det = self.detector
        if det is None:
            self.pub_diag.publish(rosutil.diagnostic(self, DETECTOR_STATUS, rosutil.OK,
                                                     "off (detector.enabled is false)",
                                                     {"state": "off"}))
            return
        now = self.get_clock().now().nanoseconds * 1e-9
        last = det.counters.last_alarm
        if self._alarm_at is not None and last is not None and now - self._alarm_at < ALARM_HOLD_S:
            level, text = rosutil.WARN, (f"change on {last.name} at {last.change_s:.3f} (shift "
                                         f"{last.shift:+.4g} rad/s)")
        else:
            level = rosutil.OK
            text = (("settling after an anchor" if self._last_stamp < self._settle_until
                     else "learning the residual") if det.learning else "testing") + (
                f"; {det.counters.alarms} alarm(s)" if det.counters.alarms else "")
        self.pub_diag.publish(rosutil.diagnostic(self, DETECTOR_STATUS, level, text,
                                                 self._detector_values()))


def main(args: list[str] | None = None) -> None:
    rosutil.init(args)
    try:
        node = ModelNode()
    except DvtModelError as exc:  # invalid parameters given at start-up
        print(f"dvt_model_node: {exc}", file=sys.stderr)
        if rclpy.ok():
            rclpy.shutdown()
        sys.exit(2)
    # everything built so far lives as long as the process: keep it out of the collector's
    # full passes (tens of ms with rclpy, numpy and scipy loaded, stalling the 1 kHz stream)
    gc.collect()
    gc.freeze()
    rosutil.spin(node)


if __name__ == "__main__":
    main()
