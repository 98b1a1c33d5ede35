"""The interface contract in one place (pure: no rclpy).

Everything two parts of the suite must agree on lives here and is imported, never retyped:
topic and service names, joint names, the QoS of each stream (as data; :mod:`dvt_model.rosutil`
turns it into rclpy profiles), and the schema of the effect terms the identifier pushes to the
model node, with their physical admissibility (:func:`validate_effects`).

The human-readable contract is ``../shared/INTERFACE.md`` plus the project's ``docs/``; this
module is its executable form. Units are SI, conventions REP-103.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from dvt_model.errors import ContractError
from dvt_model.laws import LAWS, TERM_LAWS, TORQUE_MAX

# --------------------------------------------------------------------------- topics and names
JOINT_STATES = "/dvt/joint_states"
"""Measured speeds [rad/s] (``velocity``) of :data:`SPEED_NAMES`, one message per sample;
``position`` [rad] (unwrapped encoder angles) when the controller measures them (protocol
version 2, ``docs/interface.md``), else empty."""
CURRENTS = "/dvt/currents"
"""Measured winding currents [A] (``effort``) of :data:`CURRENT_NAMES`, same stamp."""
MODEL_JOINT_STATES = "/dvt/model/joint_states"
"""The model node's prediction (``velocity``; ``position`` when the measurement carries
positions), stamped like the measured sample."""
MODEL_RESIDUAL = "/dvt/model/residual"
"""Measured - predicted (``velocity``; ``position`` [rad] when the measurement carries
positions), stamped like the measured sample."""
DIAGNOSTICS = "/diagnostics"
MODEL_CHANGE = "/dvt/model/change"
"""The model node's change alarms (``std_msgs/String``, JSON of
:meth:`dvt_model.detect.Alarm.to_dict`: ``stamp_s`` detection and ``change_s`` estimated change
time [s, the residual's stamps, host ROS time], ``name``/``output``, ``direction``, ``shift``
[rad/s], ...), QoS :data:`CHANGE_QOS`."""
RECORDER_SNAPSHOT_REQUEST = "/dvt/recorder/snapshot"
"""Snapshot requests to ``dvt-recorder`` in rolling mode (``std_msgs/String`` JSON
``{"from", "to", "out", "id"}``), QoS :data:`SNAPSHOT_REQUEST_QOS`."""
RECORDER_SNAPSHOT_RESULT = "/dvt/recorder/snapshot_result"
"""``dvt-recorder``'s snapshot answers (``std_msgs/String`` JSON), QoS :data:`CHANGE_QOS`
(reliable, transient-local, depth 10)."""

CMD_MOTOR_CURRENT = "/dvt/cmd/motor_current"
CMD_SUN_SPEED = "/dvt/cmd/sun_speed"
CMD_BRAKE_CURRENTS = "/dvt/cmd/brake_currents"
CMD_GEAR = "/dvt/cmd/gear"
COMMAND_TOPICS: tuple[str, ...] = (CMD_MOTOR_CURRENT, CMD_SUN_SPEED, CMD_BRAKE_CURRENTS, CMD_GEAR)
COMMAND_PATTERN = "/dvt/cmd/*"
SRV_DRIVER_STOP = "/dvt/driver/stop"
SRV_DRIVER_RELEASE_BRAKES = "/dvt/driver/release_brakes"

IDENTIFY_REQUEST = "/dvt/identify/request"
IDENTIFY_RESULT = "/dvt/identify/result"
SRV_IDENTIFY_RUN = "/dvt/identify/run"
FASTDDS_PROFILES_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
"""Fast DDS 2.x (the Jazzy wheels) reads its XML profiles from the file this variable names."""
FASTDDS_XML_NS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"
"""The XML namespace of a Fast DDS profiles document."""
FASTDDS_DEFAULT_REPLY_WAIT_S = 0.1
"""Fast DDS's default ``max_blocking_time`` of a reliable writer, s: how long ``rmw_fastrtps``
lets a service's reply wait for the client's response reader without a profile."""
REPLY_WAIT_S = 2.0
"""How long a service of a node that is not real-time (the identifier) waits for the client's
response reader to be matched before it drops the reply, s (``rmw_fastrtps`` waits the response
writer's ``max_blocking_time``, :data:`FASTDDS_DEFAULT_REPLY_WAIT_S` by default;
:func:`dvt_model.rosutil.init`).

Budget, measured with ``scripts/service_lag.py`` (a fresh participant per call, through a
discovery server across two network namespaces): the server had to wait for the reader in 4 of
40 calls (up to 69 ms) on a quiet machine and in 5 of 60 (up to 70 ms) with both cores busy,
against the default 100 ms; a red fresh-clone run lost the identifier's reply this way. 2 s is
29x the worst wait measured, and a client that has really gone blocks the identifier's executor
(not its worker) for at most that long. Real-time nodes (driver, model node) keep the default:
a wait there would stall their samples."""
IDENTIFY_EPISODE = "/dvt/identify/episode"
"""The identifier's supervisor episode reports (``std_msgs/String`` JSON, ``docs/loop.md``),
QoS :data:`CHANGE_QOS` (the last 10 for a late subscriber)."""

SAMPLE_TOPICS: tuple[str, ...] = (JOINT_STATES, CURRENTS)
"""The two topics of one controller sample (identical ``header.stamp``)."""
MODEL_TOPICS: tuple[str, ...] = (MODEL_JOINT_STATES, MODEL_RESIDUAL)
DEFAULT_RECORD_TOPICS: tuple[str, ...] = (*SAMPLE_TOPICS, *MODEL_TOPICS, COMMAND_PATTERN,
                                          DIAGNOSTICS)
"""What a recording holds by default (patterns allowed)."""

JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
SPEED_NAMES: tuple[str, ...] = ("sun_shaft", "carrier3")
CURRENT_NAMES: tuple[str, ...] = ("drive_motor", "brake1", "brake2", "brake3")
BRAKE_NAMES: tuple[str, ...] = CURRENT_NAMES[1:]

DRIVER_NODE = "dvt_driver"
MODEL_NODE = "dvt_model"
IDENTIFY_NODE = "dvt_identify"
RECORDER_NODE = "dvt_recorder"

SRV_MODEL_RESET_DETECTOR = "~/reset_detector"
"""The model node's service (``std_srvs/srv/Trigger``, private name) that makes its change
detector learn anew (:func:`model_reset_detector_service`)."""


def reply_topic(service: str) -> str:
    """The DDS topic of ``service``'s replies, as ``rmw_fastrtps`` names it (and looks up an
    XML profile by): ``rr`` + the absolute service name + ``Reply``.

    Raises:
        ContractError: ``service`` is not an absolute name.
    """
    if not service.startswith("/") or service.startswith("//") or any(
            ch.isspace() or ch in '<>&"' for ch in service):
        raise ContractError(f"service: expected an absolute ROS name such as "
                            f"'/dvt/identify/run', got {service!r}")
    return f"rr{service}Reply"


class Pending(Protocol):
    """What :func:`answer_of` needs of a request's future (rclpy's ``Future`` and
    ``concurrent.futures.Future`` both have it)."""

    def done(self) -> bool: ...

    def result(self) -> Any: ...


def answer_of(send: Callable[[], Pending], timeout: float, resend_after: float,
              poll: float = 0.01, wait: Callable[[float], object] = time.sleep
              ) -> tuple[Any, int]:
    """The answer to an idempotent service request, sent again when no answer came within
    ``resend_after`` seconds; the first request answered wins.

    A DDS service reply can be lost while the request was served: the server's reply writer
    may not yet have matched a new client's reply reader when the answer is written, and
    ``rmw_fastrtps`` waits the writer's ``max_blocking_time`` for it, then drops it
    (:data:`FASTDDS_DEFAULT_REPLY_WAIT_S` in the real-time nodes, which keep it: a longer wait
    would stall their samples). A request whose repetition changes nothing (a read, a refusal,
    a parameter set that repeats the values in use, which the model node takes as no change)
    is safe to send again.

    Args:
        send: sends the request once and returns its future.
        timeout: total seconds to wait for an answer [s].
        resend_after: seconds without an answer before the request is sent again [s].
        poll: seconds between looks at the futures [s].
        wait: called with ``poll`` between looks: ``time.sleep`` while another thread spins
            the client's node, or one spin of its executor.

    Returns:
        ``(result, sends)``: the first answered future's result and how many requests were
        sent.

    Raises:
        TimeoutError: no answer within ``timeout`` (the message gives the number of sends).
        ValueError: ``timeout``, ``resend_after`` or ``poll`` not > 0.
    """
    if not (timeout > 0 and resend_after > 0 and poll > 0):
        raise ValueError(f"answer_of: expected timeout, resend_after and poll > 0 s, got "
                         f"timeout={timeout!r}, resend_after={resend_after!r}, poll={poll!r}")
    start = time.monotonic()
    futures = [send()]
    last = start
    while True:
        for future in futures:
            if future.done():
                return future.result(), len(futures)
        now = time.monotonic()
        if now - start > timeout:
            raise TimeoutError(f"no answer within {timeout:g} s to {len(futures)} request(s)")
        if now - last >= resend_after:
            futures.append(send())
            last = now
        wait(poll)


REPLY_WAIT_SERVICES: tuple[str, ...] = (SRV_IDENTIFY_RUN,)
"""Services whose replies wait :data:`REPLY_WAIT_S` (those of the identifier)."""


def reply_wait_writers(services: Sequence[str] = REPLY_WAIT_SERVICES,
                       wait_s: float = REPLY_WAIT_S) -> str:
    """Fast DDS XML ``<data_writer>`` profiles under which the reply writer of each of
    ``services`` waits up to ``wait_s`` seconds for the client's response reader (see
    :data:`REPLY_WAIT_S`); the elements of a ``<profiles>`` block.

    Raises:
        ContractError: no service, a relative name, or ``wait_s`` not in (0, 3600] s.
    """
    if not services:
        raise ContractError("reply wait: no service given")
    if not (isinstance(wait_s, (int, float)) and math.isfinite(wait_s) and 0 < wait_s <= 3600):
        raise ContractError(f"reply wait: expected 0 < wait_s <= 3600 s, got {wait_s!r}")
    sec = int(wait_s)
    nanosec = round((wait_s - sec) * 1e9)
    return "".join(
        f'    <data_writer profile_name="{reply_topic(s)}">\n'
        "      <qos><reliability><kind>RELIABLE</kind>"
        f"<max_blocking_time><sec>{sec}</sec><nanosec>{nanosec}</nanosec></max_blocking_time>"
        "</reliability></qos>\n"
        "    </data_writer>\n" for s in services)


def reply_wait_profile(services: Sequence[str] = REPLY_WAIT_SERVICES,
                       wait_s: float = REPLY_WAIT_S) -> str:
    """A whole Fast DDS XML profiles document of :func:`reply_wait_writers`.

    Raises:
        ContractError: as :func:`reply_wait_writers`.
    """
    return ('<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<dds xmlns="{FASTDDS_XML_NS}">\n'
            f"  <profiles>\n{reply_wait_writers(services, wait_s)}  </profiles>\n</dds>\n")


def model_reset_detector_service(node_name: str = MODEL_NODE) -> str:
    """Absolute name of :data:`SRV_MODEL_RESET_DETECTOR` of the model node ``node_name`` (in
    the root namespace), e.g. ``/dvt_model/reset_detector``."""
    return f"/{node_name.strip('/')}/{SRV_MODEL_RESET_DETECTOR.removeprefix('~/')}"


RESET_DETECTOR_LOG = "change detector reset on request"
"""Start of the model node's INFO log line (and service answer) of every reset through
:data:`SRV_MODEL_RESET_DETECTOR` (the text ``dvt-bench loop`` looks for in the node's log to
find the launcher's re-arm)."""


# --------------------------------------------------------------------------------- QoS as data
@dataclass(frozen=True)
class QosSpec:
    """A QoS profile as data: history depth, reliability and durability."""

    depth: int
    reliability: Literal["best_effort", "reliable"]
    durability: Literal["volatile", "transient_local"] = "volatile"


GAP_RESET_S = 0.5
"""Default stamp gap [s] beyond which the model node's stream has restarted (``gap_reset``):
the model re-anchors and the change detector learns anew."""
GAP_REANCHOR_S = 0.005
"""Default stamp gap [s] of lost samples beyond which the model re-anchors but the detector
keeps its reference (``gap_reanchor``). Without it a burst of lost samples leaves the free
run on held inputs. Measured on the ident-backlash validation run (1 kHz, one 8-s slice, 12
burst positions per length, ``scripts/lost_bursts.py``), the most the sun's residual RMS
over the slice rose, run through on held inputs: 4-5 ms lost 0.1 %, 9 ms 1.8 %, 14 ms 1.24
times, 19 ms 1.30, 49 ms 2.37, 99 ms 3.80, 299 ms 4.64 times; re-anchored (this default): at
most 4.8 %.
A step must also exceed 2.5 times the previous one (``dvt_model.predictor.GAP_PERIODS``), so a
stream slower than 200 Hz still runs free."""

SENSOR_QOS = QosSpec(depth=1000, reliability="best_effort")
"""High-rate streams (publishers and subscribers): a deep queue absorbs bursts; a best-effort
subscription matches both best-effort and reliable publishers."""
COMMAND_QOS = QosSpec(depth=10, reliability="reliable")
"""Commands to the driver: every command counts."""
LATCHED_QOS = QosSpec(depth=1, reliability="reliable", durability="transient_local")
"""Results a late subscriber must still get (the identifier's result)."""
DIAGNOSTICS_QOS = QosSpec(depth=10, reliability="reliable")
CHANGE_QOS = QosSpec(depth=10, reliability="reliable", durability="transient_local")
"""Events a late subscriber must still get, the last 10 of them: the model node's change alarms
(:data:`MODEL_CHANGE`) and the recorder's snapshot results."""
SNAPSHOT_REQUEST_QOS = QosSpec(depth=10, reliability="reliable")
"""Snapshot requests to the recorder (every request counts; not latched: a restarted recorder
must not serve old requests again)."""


# ------------------------------------------------------------------------ effect-term schema
@dataclass(frozen=True)
class TermParam:
    """One numeric field of an effect term.

    ``lo``/``hi`` are the admissible range; ``lo_open``/``hi_open`` make a bound strict.
    """

    name: str
    unit: str
    lo: float
    hi: float
    lo_open: bool = False
    hi_open: bool = False
    default: float | None = None
    doc: str = ""

    def check(self, value: Any, where: str) -> float:
        """The value as a float, or :class:`ContractError` naming ``where``, field and value."""
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value):
            raise ContractError(f"{where}.{self.name}: expected a finite number [{self.unit}], "
                                f"got {short_repr(value)}")
        v = float(value)
        below = v <= self.lo if self.lo_open else v < self.lo
        above = v >= self.hi if self.hi_open else v > self.hi
        if below or above:
            raise ContractError(
                f"{where}.{self.name}: {v!r} [{self.unit}] is not admissible: expected "
                f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                f"{')' if self.hi_open else ']'}" + (f" ({self.doc})" if self.doc else ""))
        return v


@dataclass(frozen=True)
class TermChoice:
    """One enumerated (string) field of an effect term: the admissible values and the default
    (``None``: the field is required)."""

    name: str
    choices: tuple[str, ...]
    default: str | None = None
    doc: str = ""

    def check(self, value: Any, where: str) -> str:
        """The value, or :class:`ContractError` naming ``where``, field, value and choices."""
        if not isinstance(value, str) or value not in self.choices:
            raise ContractError(f"{where}.{self.name}: expected one of {list(self.choices)}, "
                                f"got {short_repr(value)}" + (f" ({self.doc})" if self.doc
                                                              else ""))
        return value


@dataclass(frozen=True)
class TermKind:
    """A kind of effect term: a generalised force on a member, or an output transform."""

    kind: str
    params: tuple[TermParam, ...]
    member: bool
    """True: a force on the member ``member . omega`` (field ``member``, 2 numbers)."""
    output: bool = False
    """True: the term names an output index (field ``output``)."""
    doc: str = ""
    choices: tuple[TermChoice, ...] = ()
    """The term's enumerated string fields."""
    driving: bool = False
    """True: the law is a torque *on* the member (generalised torque ``+member * tau``, the
    identifier's exogenous-force sign); False: a resisting force (``-member * F(v)``)."""
    angle: bool = False
    """True: the law depends on an angle ``theta_a = angle . theta``; the optional field
    ``angle`` (2 numbers) is its form, by default the member's (e.g. a mesh ripple on the sun
    shaft locked to the sun's angle relative to its carrier)."""

    def param(self, name: str) -> TermParam:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def fields(self) -> tuple[str, ...]:
        """Every field the kind takes besides ``kind``."""
        return (*(("member",) if self.member else ()), *(("angle",) if self.angle else ()),
                *(("output",) if self.output else ()),
                *(p.name for p in self.params), *(c.name for c in self.choices))


MAX_MEMBER = 1.0e3
"""Largest admissible |member coefficient| (a member speed is a small combination of speeds)."""
MAX_EFFECT_TERMS = 32
"""Most effect terms the model node takes (each costs time in every 1 kHz step)."""
MAX_EFFECTS_JSON = 64 * 1024
"""Longest ``effects`` JSON text [characters]."""
DEFAULT_EPS = 0.5
"""Default smoothing speed of the sign in force laws [rad/s] (:func:`dvt_model.laws.sign_eps`)."""

_EPS = TermParam("eps", "rad/s", 1e-6, 1e3, default=DEFAULT_EPS,
                 doc="speed below which the sign is smoothed")
_TORQUE_MAX = TORQUE_MAX
_MAX_REDUCTION = 1e6
"""Largest admissible ``reduction`` of a ``gravity`` term [1]."""
_MAX_ORDER = 1e4
"""Largest admissible angle order [1/rev] (a mesh order is a tooth count, below 200)."""
_MAX_COEFFICIENT = 1e6
"""Largest admissible |k| of a ``library`` term (its unit depends on the factors)."""
_MAX_CURRENT = 1e3
"""Largest admissible ``dead_zone`` half-width [A]."""
"""Largest admissible |k| of a ``library`` term (its unit depends on the factors)."""
_ORDER = TermParam("order", "1/rev", 0.0, _MAX_ORDER,
                   doc="angle order per member revolution, >= 0")
LIBRARY_SPEED_FACTORS: tuple[str, ...] = ("", "sign", "abs_sq", "cube", "lin", "abs")
"""Speed factors of a ``library`` term: 1, ``sign_eps(v)``, ``|v| v``, ``v^3``, ``v``,
``|v|``."""
LIBRARY_INPUT_POWERS: tuple[str, ...] = ("", "abs_sq", "cube")
"""Powers of a ``library`` term's input ``u``: ``u``, ``|u| u``, ``u^3``."""
LIBRARY_TRIG: tuple[str, ...] = ("", "cos", "sin")
"""Angle factors of a ``library`` term: 1, ``cos(order theta_a)``, ``sin(order theta_a)``."""



def _law_kind(name: str) -> TermKind:
    """The term kind of a speed law of :data:`dvt_model.laws.LAWS` (its parameters, plus the
    sign's ``eps`` for a dry law)."""
    law = LAWS[name]
    params = tuple(TermParam(p.name, p.unit, p.lower, p.upper, lo_open=p.lo_open,
                             default=p.default, doc=p.doc) for p in law.params)
    return TermKind(law.name, params + ((_EPS,) if law.dry else ()), member=True, doc=law.doc)


EFFECT_TERMS: dict[str, TermKind] = {k.kind: k for k in (
    *(_law_kind(name) for name in TERM_LAWS),
    TermKind("delay", (
        TermParam("seconds", "s", 0.0, 1.0, doc="measurement delay"),),
        member=False, doc="outputs delayed by whole samples"),
    TermKind("gain", (
        TermParam("gain", "1", -0.5, 1.0, lo_open=True,
                  doc="relative sensor scale error: output scaled by 1 + gain > 0.5"),),
        member=False, output=True, doc="output scaled by 1 + gain"),
    # position-dependent terms: a torque ON the member (driving sign, like the identifier's
    # exogenous forces), theta_a = angle . theta their angle [rad] (default: the member's)
    TermKind("gravity", (
        TermParam("a", "N m", -_TORQUE_MAX, _TORQUE_MAX, doc="cosine amplitude"),
        TermParam("b", "N m", -_TORQUE_MAX, _TORQUE_MAX, doc="sine amplitude"),
        TermParam("reduction", "1", 0.0, _MAX_REDUCTION, lo_open=True, default=1.0,
                  doc="member turns per turn of the loaded shaft, > 0")),
        member=True, driving=True, angle=True,
        doc="a cos(theta_a / reduction) + b sin(theta_a / reduction)"),
    TermKind("angle_periodic", (
        TermParam("a", "N m", -_TORQUE_MAX, _TORQUE_MAX, doc="cosine amplitude"),
        TermParam("b", "N m", -_TORQUE_MAX, _TORQUE_MAX, doc="sine amplitude"),
        _ORDER), member=True, driving=True, angle=True,
        doc="a cos(order theta_a) + b sin(order theta_a)"),
    TermKind("library", (
        TermParam("k", "N m per unit of the factors", -_MAX_COEFFICIENT, _MAX_COEFFICIENT,
                  doc="coefficient"),
        dataclasses.replace(_ORDER, default=0.0,
                            doc="angle order per member revolution, >= 0 (ignored without "
                                "trig)"),
        _EPS), member=True, driving=True, angle=True,
        choices=(TermChoice("speed", LIBRARY_SPEED_FACTORS, default="",
                            doc="speed factor S(v): '' 1, 'sign' sign_eps(v), 'abs_sq' |v| v, "
                                "'cube' v^3, 'lin' v, 'abs' |v|"),
                 TermChoice("trig", LIBRARY_TRIG, default="",
                            doc="angle factor T: '' 1, 'cos' cos(order theta_a), 'sin' "
                                "sin(order theta_a)"),
                 TermChoice("input", ("", *CURRENT_NAMES), default="",
                            doc="input factor u [A]: '' 1, else that current of "
                                "/dvt/currents"),
                 TermChoice("input_power", LIBRARY_INPUT_POWERS, default="",
                            doc="power P(u) of the input: '' u, 'abs_sq' |u| u, 'cube' u^3 "
                                "(ignored without input)")),
        doc="k S(v) T(order theta_a) P(u)"),
    # lost motion (dvt_model.backlash): on an input current, or between a member and its sensor
    TermKind("dead_zone", (
        TermParam("delta", "A", 0.0, _MAX_CURRENT, doc="half-width of the dead zone, >= 0"),),
        member=False,
        choices=(TermChoice("input", CURRENT_NAMES,
                            doc="the current of /dvt/currents it acts on"),),
        doc="u - clip(u, -delta, delta) on the named current, before the model"),
    TermKind("play", (
        TermParam("delta", "rad", 0.0, 1.0, doc="half-width of the play, in [0, 1]"),),
        member=False, output=True,
        doc="the output's speed read through rigid play of +-delta in its angle"),
    TermKind("spline_play", (
        TermParam("gap", "rad", 0.0, 1.0, doc="total play, in [0, 1]"),
        TermParam("wn", "rad/s", 10.0, 1e4, doc="contact frequency sqrt(k / J_load)"),
        TermParam("zeta", "1", 1e-3, 2.0, doc="contact damping ratio")),
        member=False, output=True,
        doc="the output is a load driven by its member through a compliant spline with play"),
)}
"""Every effect term the model node understands, by ``kind``.

Force terms act on a member ``m`` (field ``member``, 2 numbers over ``(sun_shaft, carrier3)``):
its speed is ``v = m . omega`` [rad/s] and a torque ``tau`` on it is the generalised torque
``m * tau``. ``coulomb``, ``stribeck``, ``windage`` and ``viscous`` are resisting laws ``F(v)``
(generalised torque ``-m * F(v)``); ``gravity``, ``angle_periodic`` and ``library``
(:attr:`TermKind.driving`) are torques *on* the member (``+m * tau``), the sign of the
identifier's exogenous member forces (``dvt_identify.effects.base``), and depend on the angle
``theta_a = a . theta`` [rad] with ``a`` the optional field ``angle`` (default ``m``: the
member's own angle; ``theta`` the model's angles, anchored to the measured positions).
``sign_eps(v) = tanh(v / eps)``. The model node holds each torque over a step ``dt`` of its
simulation; the angle factors are then their means over the angle interval ``[theta_a,
theta_a + (a . omega) dt]`` (a ripple faster than the step does not alias), as the
identifier's are over the measured interval.

Lost motion (:mod:`dvt_model.backlash`): ``dead_zone`` acts on a current of ``/dvt/currents``
before the model sees it (everything in the model, band torques included, sees the
transformed current); ``play`` and ``spline_play`` map the predicted speed of output
``output`` to what its sensor reads behind rigid play or a compliant spline to a load, before
the output ``delay`` and ``gain``."""

ANGLE_TERM_KINDS: tuple[str, ...] = ("gravity", "angle_periodic", "library")
"""Kinds whose law the model node evaluates on the angles (and inputs): the driving torques."""
OUTPUT_PLAY_KINDS: tuple[str, ...] = ("play", "spline_play")
"""Kinds that map a member's speed to what its sensor reads through lost motion (at most one
per output)."""


def term_needs_angle(term: Mapping[str, Any]) -> bool:
    """Whether a (validated) term's value depends on its angle: ``gravity``,
    ``angle_periodic`` and a ``library`` term with a ``trig`` factor. Its phase is then only
    right live when the angle it was identified on was the measured position (the model
    node's angles are anchored to the measured ones)."""
    kind = term.get("kind")
    return kind in ("gravity", "angle_periodic") or (kind == "library"
                                                      and bool(term.get("trig")))


def _form(raw: Any, where: str, n_outputs: int) -> list[float]:
    """A member (or angle) form: ``n_outputs`` finite numbers, not all zero, each at most
    :data:`MAX_MEMBER`; else :class:`ContractError` naming ``where`` and the value."""
    ok = (isinstance(raw, Sequence) and not isinstance(raw, str) and len(raw) == n_outputs
          and all(not isinstance(v, bool) and isinstance(v, int | float)
                  and math.isfinite(v) and abs(v) <= MAX_MEMBER for v in raw))
    if not ok or not any(float(v) != 0.0 for v in raw):
        raise ContractError(f"{where}: expected {n_outputs} finite numbers, not all "
                            f"zero, each |m| <= {MAX_MEMBER:g}, got {short_repr(raw)}")
    return [float(v) for v in raw]


def validate_term(entry: Any, where: str = "effects[0]",
                  n_outputs: int = len(SPEED_NAMES)) -> dict[str, Any]:
    """Check one effect term and return it normalised (defaults filled, floats; enumerated
    fields as their string).

    Raises:
        ContractError: naming ``where``, the field and the value.
    """
    if not isinstance(entry, Mapping):
        raise ContractError(f"{where}: expected an object, got {short_repr(entry)}")
    kind = entry.get("kind")
    spec = EFFECT_TERMS.get(kind) if isinstance(kind, str) else None
    if spec is None:
        raise ContractError(f"{where}.kind: expected one of {sorted(EFFECT_TERMS)}, "
                            f"got {short_repr(kind)}")
    allowed = {"kind", *spec.fields}
    unknown = sorted(set(entry) - allowed)
    if unknown:
        raise ContractError(f"{where}: unknown field(s) {short_repr(unknown)} for kind {kind!r} "
                            f"(expected {sorted(allowed)})")
    out: dict[str, Any] = {"kind": kind}
    if spec.member:
        out["member"] = _form(entry.get("member"), f"{where}.member", n_outputs)
    if spec.angle and "angle" in entry:
        out["angle"] = _form(entry["angle"], f"{where}.angle", n_outputs)
    if spec.output:
        o = entry.get("output")
        if isinstance(o, bool) or not isinstance(o, int) or not 0 <= o < n_outputs:
            raise ContractError(f"{where}.output: expected an output index 0..{n_outputs - 1}, "
                                f"got {short_repr(o)}")
        out["output"] = int(o)
    for p in spec.params:
        if p.name in entry:
            out[p.name] = p.check(entry[p.name], where)
        elif p.default is not None:
            out[p.name] = p.default
        else:
            raise ContractError(f"{where}.{p.name}: missing (kind {kind!r} needs "
                                f"{[q.name for q in spec.params if q.default is None]})")
    for c in spec.choices:
        if c.name in entry:
            out[c.name] = c.check(entry[c.name], where)
        elif c.default is not None:
            out[c.name] = c.default
        else:
            raise ContractError(f"{where}.{c.name}: missing (kind {kind!r}: one of "
                                f"{list(c.choices)})")
    return out


def validate_effects(data: str | Sequence[Any] | None, n_outputs: int = len(SPEED_NAMES)
                     ) -> list[dict[str, Any]]:
    """Check the model node's ``effects`` (JSON text or decoded list); '' / None: no terms.

    Also checks the list as a whole: at most :data:`MAX_EFFECT_TERMS` terms, at most one
    ``delay``, one ``gain`` and one ``play``/``spline_play`` per output, and one ``dead_zone``
    per input.

    Raises:
        ContractError: naming the entry index, the field and the value.
    """
    if data is None:
        return []
    if isinstance(data, str):
        if len(data) > MAX_EFFECTS_JSON:
            raise ContractError(f"effects: {len(data)} characters of JSON, at most "
                                f"{MAX_EFFECTS_JSON} allowed")
        if not data.strip():
            return []
        try:
            data = json.loads(data)
        except json.JSONDecodeError as exc:
            raise ContractError(f"effects: not valid JSON: {exc}") from exc
    if not isinstance(data, list | tuple):
        raise ContractError(f"effects: expected a JSON list, got {type(data).__name__}")
    if len(data) > MAX_EFFECT_TERMS:
        raise ContractError(f"effects: {len(data)} terms, at most {MAX_EFFECT_TERMS} allowed")
    terms = [validate_term(e, f"effects[{i}]", n_outputs) for i, e in enumerate(data)]
    delays = [i for i, t in enumerate(terms) if t["kind"] == "delay"]
    if len(delays) > 1:
        raise ContractError(f"effects: more than one delay term (entries {delays})")
    outs = [t["output"] for t in terms if t["kind"] == "gain"]
    if len(outs) != len(set(outs)):
        raise ContractError(f"effects: more than one gain term for one output ({outs})")
    plays = [t["output"] for t in terms if t["kind"] in OUTPUT_PLAY_KINDS]
    if len(plays) != len(set(plays)):
        raise ContractError(f"effects: more than one play or spline_play term for one output "
                            f"({plays})")
    zones = [t["input"] for t in terms if t["kind"] == "dead_zone"]
    if len(zones) != len(set(zones)):
        raise ContractError(f"effects: more than one dead_zone term for one input ({zones})")
    return terms


def effects_json(terms: Sequence[Mapping[str, Any]]) -> str:
    """The ``effects`` parameter text for ``terms``, validated first (what the node takes)."""
    return json.dumps(validate_effects(list(terms)))


# ------------------------------------------------------------- model-node parameter schema
ParamType = Literal["string", "double", "double_array", "bool"]

_MAX_REPR = 80


def short_repr(value: Any, limit: int = _MAX_REPR) -> str:
    """``repr(value)`` cut to ``limit`` characters (error messages must stay short even for a
    10 MB parameter value); a cut repr ends with ``... (N chars)``."""
    if isinstance(value, str) and len(value) > 4 * limit:
        return f"{value[:limit]!r}... ({len(value)} chars)"
    if isinstance(value, list | tuple) and len(value) > limit:
        head = repr(list(value[:4]))[:-1]
        return f"{head}, ...] ({len(value)} values)"
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} chars)"


@dataclass(frozen=True)
class NodeParam:
    """One parameter of the model node: ROS type, unit, meaning, default and admissible values.

    For ``double`` the bounds apply to the value, for ``double_array`` to every element, and
    ``sizes`` lists the admissible lengths (an empty list always means "not set"; the
    parameter's own ``description`` says what that falls back to). ``lo_open``/``hi_open``
    make a bound strict. ``choices`` restricts a string, ``max_chars`` bounds its length.
    Checks across values (symmetric positive definite M, stable A, ...) are
    :func:`dvt_model.config.check_parameters`'s.
    """

    name: str
    type: ParamType
    unit: str
    description: str
    default: str | float | bool | tuple[float, ...]
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    sizes: tuple[int, ...] = ()
    choices: tuple[str, ...] = ()
    max_chars: int = 4096

    @property
    def admissible(self) -> str:
        """Human-readable admissible values, e.g. ``4 numbers in [-1000, 1000] [kg m^2]``."""
        rng = ""
        if self.lo is not None and self.hi is not None:
            rng = (f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                   f"{')' if self.hi_open else ']'}")
        unit = f" [{self.unit}]" if self.unit and self.unit != "-" else ""
        if self.type == "double":
            return f"a number in {rng}{unit}"
        if self.type == "bool":
            return "true or false"
        if self.type == "double_array":
            sizes = " or ".join(str(s) for s in self.sizes)
            return f"an empty list or {sizes} numbers, each in {rng}{unit}"
        if self.choices:
            return f"one of {list(self.choices)}"
        return f"a string of at most {self.max_chars} characters"

    def _in_range(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def check(self, value: Any) -> str | float | bool | tuple[float, ...]:
        """The value normalised (str, float or tuple of floats), or :class:`ContractError`
        whose message starts with the parameter name and gives the value and what is admissible.

        ``None`` (a ROS parameter that is not set) is the default.
        """
        if value is None:
            return self.default
        bad = ContractError(f"{self.name}: {short_repr(value)} is not admissible: expected "
                            f"{self.admissible}")
        if self.type == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.type == "string":
            if not isinstance(value, str):
                raise bad
            if len(value) > self.max_chars:
                raise ContractError(f"{self.name}: {len(value)} characters, at most "
                                    f"{self.max_chars} allowed")
            if self.choices and value not in self.choices:
                raise bad
            return value
        if self.type == "double":
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value) or not self._in_range(float(value)):
                raise bad
            return float(value)
        if isinstance(value, str | bytes) or not isinstance(value, Sequence):
            raise bad
        n = len(value)
        if n == 0:
            return ()
        if n not in self.sizes:
            raise ContractError(f"{self.name}: {n} values is not admissible: expected "
                                f"{self.admissible}")
        out: list[float] = []
        for i, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) \
                    or not self._in_range(float(v)):
                raise ContractError(f"{self.name}[{i}]: {short_repr(v)} is not admissible: "
                                    f"expected {self.admissible}")
            out.append(float(v))
        return tuple(out)


DETECTOR_PREFIX = "detector"
"""Prefix of the model node's change-detector parameters (``detector.learn_s``, ...)."""
PARAMS_DEFAULT = "physical"
LOAD_DEFAULT = "none"
"""Default joint load of the model node: none (the transmission alone)."""
M_MIN_EIGENVALUE = 1e-9
"""Smallest admissible eigenvalue of M [kg m^2]. The smallest inertia the model carries is the
sun shaft with the motor rotor, about 3e-5 kg m^2 (M's eigenvalues are 4e-4 and 4e-2 kg m^2 in
the bundled sets); 1e-9 kg m^2 is a 1 mm steel pin. Below it the mechanical time constants
M/D fall far under the 1 ms sample period and the prediction is numerically meaningless
(M = 1e-30 I made the node publish NaN)."""
M_MAX_CONDITION = 1e8
"""Largest admissible condition number of M (the bundled sets: about 100). Beyond 1e8 a solve
with M loses more than half of the double precision digits."""
MATRIX_ENTRY_MAX = 1e3
"""Largest admissible |entry| of M [kg m^2] and D [N m s] (the bundled sets: below 0.2)."""
A_ENTRY_MAX = 1e6
"""Largest admissible |entry| of A [1/s] (the bundled sets: below 100)."""
B_ENTRY_MAX = 1e6
"""Largest admissible |entry| of B (the bundled sets with the thesis's inputs: below 1000)."""

MODEL_PARAMETERS: dict[str, NodeParam] = {p.name: p for p in (
    NodeParam("params", "string", "-",
              "bundled parameter set (physical, thesis, thesis-derivation) or a YAML file path",
              PARAMS_DEFAULT),
    NodeParam("M", "double_array", "kg m^2",
              "mass matrix override, 4 values row-major, symmetric positive definite "
              f"(smallest eigenvalue >= {M_MIN_EIGENVALUE:g}, condition number <= "
              f"{M_MAX_CONDITION:g}); empty = the parameter set's",
              (), lo=-MATRIX_ENTRY_MAX, hi=MATRIX_ENTRY_MAX, sizes=(4,)),
    NodeParam("D", "double_array", "N m s",
              "damping matrix override, 4 values row-major, symmetric positive semi-definite; "
              "empty = the parameter set's",
              (), lo=-MATRIX_ENTRY_MAX, hi=MATRIX_ENTRY_MAX, sizes=(4,)),
    NodeParam("motor_constant", "double", "N m/A",
              "drive-motor constant K_M; 0 = the parameter set's value", 0.0, lo=0.0, hi=10.0),
    NodeParam("band_gain", "double_array", "N m/A",
              "static torque per brake-motor ampere of bands 1-3 (BrakeParams.band_gain), "
              "3 values > 0; empty = the parameter set's band law",
              (), lo=0.0, hi=1e3, lo_open=True, sizes=(3,)),
    NodeParam("band_time_constant", "double_array", "s",
              "engagement time constant of bands 1-3 (BrakeParams.band_time_constant), 3 values "
              "> 0; empty = the parameter set's", (), lo=0.0, hi=10.0, lo_open=True, sizes=(3,)),
    NodeParam("A", "double_array", "1/s",
              "identified state matrix of the linear model omega' = A omega + B u, 4 values "
              "row-major, stable (every eigenvalue with negative real part); set together with "
              "B; an empty A or B clears the linear model (both)",
              (), lo=-A_ENTRY_MAX, hi=A_ENTRY_MAX, sizes=(4,)),
    NodeParam("B", "double_array", "rad/s^2 per input unit",
              "identified input matrix, 4 (2x2: motor current, band-1 torque) or 8 (2x4) values "
              "row-major; set together with A; empty clears the linear model",
              (), lo=-B_ENTRY_MAX, hi=B_ENTRY_MAX, sizes=(4, 8)),
    NodeParam("effects", "string", "-",
              f"identified effect terms, JSON list of at most {MAX_EFFECT_TERMS} terms "
              f"(dvt_model.contract.EFFECT_TERMS: {', '.join(EFFECT_TERMS)}); empty = none",
              "", max_chars=MAX_EFFECTS_JSON),
    NodeParam("mode", "string", "-",
              "simulate (free run, output-error residual) or reanchor (re-anchor periodically)",
              "simulate", choices=("simulate", "reanchor")),
    NodeParam("reanchor_period", "double", "s", "seconds between re-anchors in reanchor mode",
              1.0, lo=0.001, hi=3600.0),
    NodeParam("gap_reset", "double", "s",
              "a stamp gap longer than this is a stream restart: the model re-anchors and the "
              "change detector learns anew", GAP_RESET_S, lo=0.001, hi=3600.0),
    NodeParam("gap_reanchor", "double", "s",
              "a stamp gap longer than this and than 2.5 times the previous step (lost "
              "samples: the inputs are unknown) re-anchors the model; the change detector "
              "keeps its reference and skips detector.settle_s", GAP_REANCHOR_S,
              lo=0.001, hi=3600.0),
    NodeParam("load", "string", "-",
              "joint load on carrier 3 (dvt_model.load): none, arm (the thesis's 71 in, 200 lb "
              "arm on a 100:1 stage), arm-payload (with its 240 lb payload) or a load YAML "
              "path (output_stage: reduction, efficiency; arm: length, mass, payload, "
              "zero_angle); needs the physical model", LOAD_DEFAULT, max_chars=4096),
    # the change detector (dvt_model.detect.DetectorConfig; docs/loop.md section 1). Read-only
    # at runtime: the node refuses a change (restart it with other values).
    NodeParam(f"{DETECTOR_PREFIX}.enabled", "bool", "-",
              "run the change detector on every residual (alarms on /dvt/model/change and "
              "/diagnostics); read-only", True),
    NodeParam(f"{DETECTOR_PREFIX}.sample_rate_hz", "double", "Hz",
              "nominal sample rate (converts the false-alarm period to samples); read-only",
              1000.0, lo=0.0, hi=100000.0, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.block_s", "double", "s",
              "the detector tests the mean residual of consecutive blocks of this length "
              "(round(block_s * sample_rate_hz) samples; 0 = every sample): averaging removes "
              "the encoder's quantisation pattern, which is not the noise the CUSUM is designed "
              "for; read-only", 0.01, lo=0.0, hi=1.0),
    NodeParam(f"{DETECTOR_PREFIX}.settle_s", "double", "s",
              "after every anchor of the model to the measurement (the first sample, a stream "
              "restart, a guard re-anchor; not the periodic ones of reanchor mode) the detector "
              "waits this long, then learns anew: the anchor's error decays with the "
              "transmission's time constants (slowest 0.58 s in the bundled sets); read-only",
              3.0, lo=0.0, hi=600.0),
    NodeParam(f"{DETECTOR_PREFIX}.learn_s", "double", "s",
              "reference window after a start, a model change or an alarm (at least 100 "
              "samples); read-only", 20.0, lo=0.0, hi=3600.0, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.shift_sigma", "double", "-",
              "step of the residual to detect, in residual standard deviations; read-only",
              0.5, lo=0.0, hi=20.0, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.false_alarm_period_s", "double", "s",
              "designed mean time between false alarms on a clean plant (all outputs, both "
              "directions); read-only", 14400.0, lo=0.0, hi=1.0e9, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.max_gap_s", "double", "s",
              "a stamp step longer than this is a gap (the whitening skips a sample); "
              "read-only", 0.05, lo=0.0, hi=60.0, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.max_phi", "double", "-",
              "upper clip of the residual's learned AR(1) coefficient; read-only", 0.995,
              lo=0.0, hi=1.0, hi_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.colour_s", "double", "s",
              "residual history the detector learns the residual's colour from (an AR "
              "whitening by AIC, kept across alarms and model changes, refitted every minute); "
              "in the first minute it whitens each reference window by its own ARMA(1, 1), "
              "then by a colour on the history it has, fully from colour_s on; "
              "0 = never; read-only", 300.0, lo=0.0, hi=86400.0),
    NodeParam(f"{DETECTOR_PREFIX}.colour_lag_s", "double", "s",
              "longest lag of that whitening (at most half of learn_s is used); read-only", 3.0,
              lo=0.0, hi=600.0, lo_open=True),
    NodeParam(f"{DETECTOR_PREFIX}.colour_file", "string", "-",
              "file that carries the residual's colour to the next start of the same model "
              "(written once a minute when the colour has colour_s of this model's residual; "
              "read at start: the first reference window is then whitened by it); empty = "
              "none; read-only", "", max_chars=4096),
)}
"""Every parameter of the model node (:data:`MODEL_NODE`), by name, in declaration order."""
DETECTOR_PARAMETERS: tuple[str, ...] = tuple(
    n for n in MODEL_PARAMETERS if n.startswith(DETECTOR_PREFIX + "."))
"""The detector's parameters (read-only in the node: a change is refused)."""
