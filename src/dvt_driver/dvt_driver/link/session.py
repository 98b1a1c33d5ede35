"""The controller session as a pure state machine (no rclpy, no threads, no serial I/O).

:class:`Session` decides *what* the driver says to the controller and *when*; the driver node's
I/O thread feeds it with explicit time (``now`` [s] on any monotonic clock) and events, and
executes the :class:`Actions` it returns. Nothing here sleeps, reads or writes a port, so every
timing rule is unit-tested with a fake clock (``test/test_session.py``).

States (:class:`SessionState`)::

    LINK_DOWN --link_opened--> HELLO --HELLO_ACK (our version) or a sample--> STREAMING
        ^                        |  ^                                           |
        |                        |  +--- stream timeout / NACK NOT_READY -------+
        |                        +--HELLO_ACK (other version) / NACK HELLO--> REFUSED
        +------------------------- link_lost (from any state) ----------------+

* **LINK_DOWN** - the port is gone. :meth:`Session.poll` asks for a reopen (``reopen``) at once
  and then every ``reconnect_interval`` (10 ms by default), backing off by doubling to at most
  ``reconnect_max_interval`` (40 ms): a device that comes back is open again within 50 ms.
  Report the outcome with :meth:`Session.link_opened` or :meth:`Session.reopen_failed`. The log
  is bounded: the first failure, then one line per ``reopen_log_period`` (10 s).
* **HELLO** - the port is open, no session yet: a HELLO at once, retried every
  ``hello_interval`` (0.1 s); after ``hello_attempts`` (10) unanswered HELLOs the session gives
  up the fast retry (logged once as an error, ``hello_give_ups``) and says HELLO every
  ``hello_slow_interval`` (0.5 s).
* **Version negotiation** - HELLO offers the newest version (:data:`PROTOCOL_VERSION`, 2). A
  controller answers HELLO_ACK with the version it will speak (at most the offered one); a
  controller that does not speak the offered version NACKs it ``UNSUPPORTED_VERSION`` and the
  session offers the next older version at once (2 -> 1; counted in ``version_fallbacks``,
  not in ``nacks``). :attr:`Session.protocol_version` is the negotiated version and
  :attr:`Session.counts_per_rev` the encoders' resolution (version 2), or ``None``. Every new
  link or closed session offers the newest version again.
* **REFUSED** - the controller refused every version we speak (NACK of HELLO(1)), or answered a
  version we do not speak or did not offer: HELLO every ``hello_refused_interval`` (5 s) in
  case it is re-flashed.
* **STREAMING** - the session is open. A HELLO_ACK whose sample period differs from ours is
  followed by CONFIG (the period); CONFIG is matched with its ACK (``config_ok``) or NACK
  (``config_refused``, not retried). Every CONFIG/COMMAND without ACK/NACK after
  ``answer_timeout`` (0.5 s) counts as ``unanswered``; an unanswered CONFIG is sent again. No
  sample for ``stream_timeout`` (``max(0.25 s, 20 periods)``) or a NACK ``NOT_READY`` closes the
  session (``stream_timeouts``) and HELLO starts again at once. While the node is *active*,
  :meth:`Session.poll` asks for a COMMAND (``command``) every ``keepalive_period``
  (``shift_send_period``, 5 ms, while a gear shift ramps the brakes), and at once after
  :meth:`Session.request_command`, when the session opens (HELLO_ACK or a first sample) or
  after a controller reset.
* **Controller reset** (sequence number or clock went back, :class:`SequenceTracker`): the
  sample carries ``reset`` (the node clears the clock mapping and tells the supervisor), CONFIG
  is sent again and a COMMAND is requested at once. Exact duplicate samples carry
  ``duplicate`` (drop them).

Sequence numbers of CONFIG and COMMAND come from :meth:`Session.next_seq`; call
:meth:`Session.sent` for every frame actually written so its answer is expected. The class is
not thread-safe: the node calls it under one lock.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from dvt_driver.errors import SessionError
from dvt_driver.link.protocol import (
    MIN_PROTOCOL_VERSION,
    PROTOCOL_VERSION,
    SUPPORTED_VERSIONS,
    Ack,
    Command,
    Config,
    FrameType,
    Hello,
    HelloAck,
    Message,
    Nack,
    NackReason,
    Sample,
    SequenceTracker,
)

__all__ = ["Actions", "LogLevel", "Session", "SessionState", "SessionTiming"]


class SessionState(enum.Enum):
    """State of a :class:`Session` (module docstring)."""

    LINK_DOWN = "link_down"  #: the port is not open; reopen attempts are scheduled
    HELLO = "hello"  #: port open, saying HELLO until the controller answers
    REFUSED = "refused"  #: the controller refused our protocol version
    STREAMING = "streaming"  #: session open, samples flow


class LogLevel(enum.IntEnum):
    """Severity of a log line in :attr:`Actions.logs`."""

    INFO = 20
    WARN = 30
    ERROR = 40


@dataclass(frozen=True, slots=True)
class SessionTiming:
    """The session's timing (all [s] unless stated).

    Attributes:
        sample_period_us: the sample period to set with CONFIG [µs], > 0.
        keepalive_period: COMMAND period while active, > 0.
        reconnect_interval: first pause between reopen attempts of a vanished port, > 0.
        reconnect_max_interval: longest pause between reopen attempts (the back-off doubles the
            pause up to this), >= ``reconnect_interval`` (raised to it if smaller).
        reopen_log_period: at most one "still away" log line per this period, > 0.
        hello_interval: pause between the first HELLO attempts, > 0.
        hello_attempts: fast HELLO attempts before giving up the fast retry, >= 1.
        hello_slow_interval: pause between HELLO attempts after giving up, > 0.
        hello_refused_interval: pause between HELLO attempts after a version refusal, > 0.
        answer_timeout: a CONFIG/COMMAND without ACK/NACK after this is unanswered, > 0.
        stream_timeout: no sample for this long closes the session, > 0; ``None``:
            ``max(0.25, 20 * sample period)``.
        shift_send_period: COMMAND period while a gear shift ramps the brakes, > 0.
    """

    sample_period_us: int
    keepalive_period: float
    reconnect_interval: float = 0.01
    reconnect_max_interval: float = 0.04
    reopen_log_period: float = 10.0
    hello_interval: float = 0.1
    hello_attempts: int = 10
    hello_slow_interval: float = 0.5
    hello_refused_interval: float = 5.0
    answer_timeout: float = 0.5
    stream_timeout: float | None = None
    shift_send_period: float = 0.005

    def __post_init__(self) -> None:
        if (isinstance(self.sample_period_us, bool) or not isinstance(self.sample_period_us, int)
                or self.sample_period_us <= 0):
            raise SessionError(f"sample_period_us: expected a positive integer [µs], got "
                               f"{self.sample_period_us!r}")
        if (isinstance(self.hello_attempts, bool) or not isinstance(self.hello_attempts, int)
                or self.hello_attempts < 1):
            raise SessionError(f"hello_attempts: expected an integer >= 1, got "
                               f"{self.hello_attempts!r}")
        for name in ("keepalive_period", "reconnect_interval", "reconnect_max_interval",
                     "reopen_log_period", "hello_interval", "hello_slow_interval",
                     "hello_refused_interval", "answer_timeout", "stream_timeout",
                     "shift_send_period"):
            value = getattr(self, name)
            if value is None and name == "stream_timeout":
                continue
            if (isinstance(value, bool) or not isinstance(value, int | float)
                    or not math.isfinite(value) or value <= 0):
                raise SessionError(f"{name}: expected a finite number > 0 s, got {value!r}")

    @property
    def stream_timeout_s(self) -> float:
        """The effective stream timeout [s]."""
        if self.stream_timeout is not None:
            return float(self.stream_timeout)
        return max(0.25, 20.0 * self.sample_period_us * 1e-6)

    @property
    def reconnect_max(self) -> float:
        """The effective longest pause between reopen attempts [s]."""
        return max(self.reconnect_interval, self.reconnect_max_interval)


@dataclass(slots=True)
class Actions:
    """What the caller must do now, returned by every :class:`Session` event method.

    Attributes:
        send: HELLO / CONFIG frames to write now, in order; report each written one with
            :meth:`Session.sent`.
        command: build a COMMAND from the supervisor and send it now (sequence number from
            :meth:`Session.next_seq`, then :meth:`Session.sent`).
        reopen: try to reopen the port now; report with :meth:`Session.link_opened` or
            :meth:`Session.reopen_failed`.
        reset: (:meth:`Session.on_sample`) the controller was reset: clear the clock mapping and
            switch the motor off until a new command.
        duplicate: (:meth:`Session.on_sample`) an exact duplicate sample: drop it.
        changed: something the diagnostics should report at once (state change, refusal).
        logs: ``(level, text)`` lines for the log.
    """

    send: list[Message] = field(default_factory=list)
    command: bool = False
    reopen: bool = False
    reset: bool = False
    duplicate: bool = False
    changed: bool = False
    logs: list[tuple[LogLevel, str]] = field(default_factory=list)

    def log(self, level: LogLevel, text: str) -> None:
        """Add a log line."""
        self.logs.append((level, text))


class Session:
    """The controller session (module docstring). Starts in ``LINK_DOWN``; call
    :meth:`link_opened` once the port is open.

    Args:
        timing: the :class:`SessionTiming`.
        name: the port's name, used in log lines.
    """

    def __init__(self, timing: SessionTiming, name: str = "controller") -> None:
        self.timing = timing
        self.name = name
        self.state = SessionState.LINK_DOWN
        self.tracker = SequenceTracker()
        self.hello_ack: HelloAck | None = None
        self.hello_refused = False
        self.config_ok = False
        self.config_refused = False
        self._offer = PROTOCOL_VERSION  # the version the next HELLO offers
        self.version_fallbacks = 0  # HELLO NACKed, an older version offered instead
        # counters (cumulative; ints, read by the diagnostics)
        self.hellos = 0
        self.hello_give_ups = 0
        self.samples = 0
        self.duplicates = 0
        self.stream_timeouts = 0
        self.acks = 0
        self.nacks = 0
        self.nacks_by_reason: dict[str, int] = {}
        self.unanswered = 0
        self.commands_sent = 0
        self.command_gap_max = 0.0  # [s] longest interval between two COMMANDs of one active run
        self._last_command_at: float | None = None
        self.reopen_attempts = 0
        self.last_reopen_error = ""
        # schedule
        self.pending: dict[tuple[int, int], float] = {}  # (frame type, seq) -> sent at [s]
        self._seq = 0
        self._hellos_on_link = 0  # HELLOs since the link (re)opened or the session closed
        self._next_hello = 0.0
        self._next_command = 0.0
        self._want_command = False
        self._last_sample_time: float | None = None
        self._next_reopen = -math.inf
        self._reopen_delay = timing.reconnect_interval
        self._down_since: float | None = None
        self._down_attempts = 0
        self._next_reopen_log = 0.0

    # -- properties ------------------------------------------------------------------------

    @property
    def open(self) -> bool:
        """Whether the session is open (``STREAMING``)."""
        return self.state is SessionState.STREAMING

    @property
    def link_up(self) -> bool:
        """Whether the port is open (any state but ``LINK_DOWN``)."""
        return self.state is not SessionState.LINK_DOWN

    @property
    def offered_version(self) -> int:
        """The protocol version the next HELLO offers."""
        return self._offer

    @property
    def protocol_version(self) -> int | None:
        """The negotiated protocol version while the session is open (from its HELLO_ACK;
        ``None`` when closed, or when it opened on a sample before any HELLO_ACK)."""
        if not self.open or self.hello_ack is None:
            return None
        return self.hello_ack.protocol_version

    @property
    def counts_per_rev(self) -> tuple[int, int] | None:
        """``(sun, output)`` encoder counts per revolution of an open version-2 session (0 =
        that encoder is absent), else ``None`` (version 1: speeds only)."""
        version = self.protocol_version
        ack = self.hello_ack
        if version is None or version < 2 or ack is None:
            return None
        return ack.sun_counts_per_rev, ack.output_counts_per_rev

    def next_seq(self) -> int:
        """The next CONFIG/COMMAND sequence number (16 bit, wraps)."""
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def request_command(self) -> None:
        """Ask for a COMMAND at the next :meth:`poll` (a new command arrived)."""
        self._want_command = True

    def time_to_next(self, now: float, *, active: bool) -> float:
        """Seconds [s] from ``now`` until the next scheduled action (>= 0; ``inf`` if none)."""
        t = self.timing
        due = [math.inf]
        if self.state is SessionState.LINK_DOWN:
            due.append(self._next_reopen)
        elif self.state is SessionState.STREAMING:
            if self._last_sample_time is not None:
                due.append(self._last_sample_time + t.stream_timeout_s)
            if active:
                due.append(math.inf if not self._want_command else now)
                due.append(self._next_command)
        else:
            due.append(self._next_hello)
        if self.pending and self.state is not SessionState.LINK_DOWN:
            due.append(min(self.pending.values()) + t.answer_timeout)
        return max(0.0, min(due) - now)

    # -- link events -----------------------------------------------------------------------

    def link_opened(self, now: float) -> Actions:
        """The port is open (first open or a successful reopen): say HELLO at once."""
        acts = Actions(changed=True)
        if self._down_since is not None and self.reopen_attempts > 0:
            acts.log(LogLevel.INFO, f"link reconnected: {self.name} (away "
                                    f"{now - self._down_since:.3f} s, "
                                    f"{self._down_attempts} reopen attempts)")
        self.state = SessionState.HELLO
        self._offer = PROTOCOL_VERSION
        self._down_since = None
        self._down_attempts = 0
        self._reopen_delay = self.timing.reconnect_interval
        self._hellos_on_link = 0
        self._next_hello = now
        self._last_sample_time = None
        self.pending.clear()
        return acts

    def link_lost(self, now: float, reason: str = "") -> Actions:
        """The port failed (or was found closed): reopen it at once, then on the back-off
        schedule. Idempotent while the link is down."""
        acts = Actions()
        if self.state is SessionState.LINK_DOWN:
            return acts
        self.state = SessionState.LINK_DOWN
        self.config_ok = False
        self.pending.clear()
        self._last_sample_time = None
        self._last_command_at = None
        self._down_since = now
        self._down_attempts = 0
        self._reopen_delay = self.timing.reconnect_interval
        self._next_reopen = now
        self._next_reopen_log = now + self.timing.reopen_log_period
        acts.changed = True
        acts.log(LogLevel.WARN, f"link lost: {reason or self.name}; reopening every "
                                f"{self.timing.reconnect_interval * 1e3:g}.."
                                f"{self.timing.reconnect_max * 1e3:g} ms")
        return acts

    def reopen_failed(self, now: float, reason: str = "") -> Actions:
        """A reopen attempt failed at ``now``: schedule the next one (back-off)."""
        acts = Actions()
        self.state = SessionState.LINK_DOWN
        if self._down_since is None:
            self._down_since = now
            self._next_reopen_log = now + self.timing.reopen_log_period
        self.reopen_attempts += 1
        self._down_attempts += 1
        self.last_reopen_error = reason
        self._next_reopen = now + self._reopen_delay
        self._reopen_delay = min(2.0 * self._reopen_delay, self.timing.reconnect_max)
        if now >= self._next_reopen_log:
            self._next_reopen_log = now + self.timing.reopen_log_period
            acts.log(LogLevel.WARN, f"{self.name} still away after {now - self._down_since:.1f} "
                                    f"s ({self._down_attempts} reopen attempts): {reason}")
        return acts

    # -- time ------------------------------------------------------------------------------

    def poll(self, now: float, *, active: bool, shifting: bool = False,
             urgent: bool = False) -> Actions:
        """What is due at ``now``: a reopen attempt, HELLO, a CONFIG re-send, a COMMAND.

        Args:
            now: the time [s].
            active: the node is active (COMMANDs are sent only then).
            shifting: a gear shift is ramping the brakes (COMMAND every ``shift_send_period``).
            urgent: send a COMMAND now if the session is open (same as :meth:`request_command`).
        """
        acts = Actions()
        t = self.timing
        if self.state is SessionState.LINK_DOWN:
            if now >= self._next_reopen:
                acts.reopen = True
                self._next_reopen = now + self._reopen_delay  # until the outcome is reported
            return acts
        if (self.state is SessionState.STREAMING and self._last_sample_time is not None
                and now - self._last_sample_time > t.stream_timeout_s):
            self._close(now)
            self.stream_timeouts += 1
            acts.changed = True
            acts.log(LogLevel.WARN, f"no sample for {t.stream_timeout_s:g} s: saying HELLO again")
        if self.state is not SessionState.STREAMING and now >= self._next_hello:
            self._say_hello(now, acts)
        if self.pending:
            self._expire(now, acts)
        if not active:
            self._want_command = False  # nothing is sent while inactive
            self._last_command_at = None  # the next COMMAND starts a new run of keep-alives
        elif self.open and (urgent or self._want_command or now >= self._next_command):
            acts.command = True
            self._want_command = False
            self._next_command = now + (t.shift_send_period if shifting else t.keepalive_period)
        return acts

    def sent(self, msg: Message, now: float) -> None:
        """``msg`` was written at ``now``: expect its answer (CONFIG, COMMAND)."""
        if isinstance(msg, Command):
            self.commands_sent += 1
            if self._last_command_at is not None:
                self.command_gap_max = max(self.command_gap_max, now - self._last_command_at)
            self._last_command_at = now
            self.pending[(FrameType.COMMAND, msg.seq)] = now
        elif isinstance(msg, Config):
            self.pending[(FrameType.CONFIG, msg.seq)] = now

    # -- received frames -------------------------------------------------------------------

    def on_sample(self, sample: Sample, now: float) -> Actions:
        """A sample arrived at ``now``; see :attr:`Actions.duplicate` and :attr:`Actions.reset`."""
        acts = Actions()
        upd = self.tracker.update(sample.seq, sample.t_us)
        if upd.duplicate:
            self.duplicates += 1
            acts.duplicate = True
            return acts
        self._last_sample_time = now
        if self.state is not SessionState.STREAMING:
            self.state = SessionState.STREAMING  # the controller streams: the session is open
            self._hellos_on_link = 0
            self._want_command = True
            acts.changed = True
        if upd.reset and self.samples > 0:
            acts.reset = True
            acts.changed = True
            self._send_config(acts)
            self._want_command = True
        self.samples += 1
        return acts

    def on_message(self, msg: Message, now: float) -> Actions:
        """A reply (HELLO_ACK, ACK, NACK) arrived at ``now``; samples go to :meth:`on_sample`;
        anything else (a controller never sends it) is ignored."""
        acts = Actions()
        if isinstance(msg, Sample):
            return self.on_sample(msg, now)
        if isinstance(msg, HelloAck):
            self._on_hello_ack(msg, now, acts)
        elif isinstance(msg, Ack):
            self.pending.pop((int(msg.ref_type), msg.ref_seq), None)
            self.acks += 1
            if msg.ref_type == FrameType.CONFIG:
                if not self.config_ok or self.config_refused:
                    acts.log(LogLevel.INFO,
                             f"sample period set to {self.timing.sample_period_us} µs")
                self.config_ok = True
                self.config_refused = False
        elif isinstance(msg, Nack):
            self._on_nack(msg, now, acts)
        return acts

    # -- internals -------------------------------------------------------------------------

    def _close(self, now: float) -> None:
        """Close the session (the link stays up): HELLO again at once."""
        self.state = SessionState.HELLO
        self._offer = PROTOCOL_VERSION
        self._last_sample_time = None
        self._last_command_at = None
        self._hellos_on_link = 0
        self._next_hello = now

    def _say_hello(self, now: float, acts: Actions) -> None:
        t = self.timing
        self.hellos += 1
        self._hellos_on_link += 1
        self.config_ok = False
        if self.hello_refused:
            interval = t.hello_refused_interval
        elif self._hellos_on_link < t.hello_attempts:
            interval = t.hello_interval
        else:
            interval = t.hello_slow_interval
            if self._hellos_on_link == t.hello_attempts:
                self.hello_give_ups += 1
                acts.changed = True
                acts.log(LogLevel.ERROR, f"{self.name}: no answer to {t.hello_attempts} HELLOs; "
                                         f"retrying every {t.hello_slow_interval:g} s")
        self._next_hello = now + interval
        if self.hellos == 1 or self.hellos % 20 == 0:
            acts.log(LogLevel.INFO, f"HELLO to {self.name} (attempt {self.hellos})")
        acts.send.append(Hello(self._offer))

    def _send_config(self, acts: Actions) -> None:
        self.config_ok = False
        acts.send.append(Config(self.next_seq(), self.timing.sample_period_us))

    def _expire(self, now: float, acts: Actions) -> None:
        old = [k for k, sent in self.pending.items() if now - sent > self.timing.answer_timeout]
        resend = False
        for key in old:
            del self.pending[key]
            self.unanswered += 1
            if key[0] == FrameType.CONFIG:
                resend = True
        if resend and self.open and not self.config_ok and not self.config_refused:
            self._send_config(acts)

    def _on_hello_ack(self, msg: HelloAck, now: float, acts: Actions) -> None:
        acts.changed = True
        if msg.protocol_version not in SUPPORTED_VERSIONS or msg.protocol_version > self._offer:
            self.state = SessionState.REFUSED
            self.hello_refused = True
            self._last_sample_time = None
            self._next_hello = now + self.timing.hello_refused_interval
            acts.log(LogLevel.ERROR, f"controller speaks protocol {msg.protocol_version}, "
                                     f"not {self._offer} (we speak {list(SUPPORTED_VERSIONS)}): "
                                     "session closed")
            self._offer = PROTOCOL_VERSION
            return
        first = self.hello_ack is None or not self.open
        self.hello_ack = msg
        self.hello_refused = False
        self.state = SessionState.STREAMING
        self._hellos_on_link = 0
        self._last_sample_time = now
        if first:
            wd = msg.watchdog_timeout_us * 1e-6
            counts = (f"encoders {msg.sun_counts_per_rev}/{msg.output_counts_per_rev} counts/rev"
                      if msg.protocol_version >= 2 else "speeds only, no positions")
            acts.log(LogLevel.INFO, f"controller '{msg.firmware_id}': protocol "
                                    f"{msg.protocol_version} ({counts}), period "
                                    f"{msg.sample_period_us} µs, watchdog {wd:g} s")
            keep = self.timing.keepalive_period
            if wd > 0 and keep > wd / 3:
                acts.log(LogLevel.WARN,
                         f"keep-alive period {keep:g} s is too slow for the controller's "
                         f"{wd:g} s watchdog (send at least 3 per timeout)")
        if msg.sample_period_us != self.timing.sample_period_us:
            self._send_config(acts)
        else:
            self.config_ok = True
        self._want_command = True

    def _on_nack(self, msg: Nack, now: float, acts: Actions) -> None:
        if (msg.ref_type == FrameType.HELLO and msg.reason == NackReason.UNSUPPORTED_VERSION
                and self._offer > MIN_PROTOCOL_VERSION and not self.open):
            # negotiation, not a failure: offer the next older version at once
            offered = self._offer
            self._offer = max(v for v in SUPPORTED_VERSIONS if v < offered)
            self.version_fallbacks += 1
            self.state = SessionState.HELLO
            acts.changed = True
            acts.log(LogLevel.INFO, f"controller does not speak protocol {offered}: offering "
                                    f"{self._offer}")
            self._say_hello(now, acts)
            return
        self.pending.pop((int(msg.ref_type), msg.ref_seq), None)
        self.nacks += 1
        key = msg.reason.name
        self.nacks_by_reason[key] = self.nacks_by_reason.get(key, 0) + 1
        acts.changed = True
        if msg.ref_type == FrameType.HELLO:
            self.state = SessionState.REFUSED
            self.hello_refused = True
            self._last_sample_time = None
            self._next_hello = now + self.timing.hello_refused_interval
            acts.log(LogLevel.ERROR, "controller refused HELLO: unsupported protocol version "
                                     f"{self._offer} (we speak {list(SUPPORTED_VERSIONS)})")
            self._offer = PROTOCOL_VERSION
        elif msg.reason == NackReason.NOT_READY:
            if self.open:
                acts.log(LogLevel.WARN, "controller lost the session (NOT_READY): saying HELLO "
                                        "again")
            self._close(now)
        elif msg.ref_type == FrameType.CONFIG:
            self.config_refused = True
            acts.log(LogLevel.ERROR, f"controller refused sample period "
                                     f"{self.timing.sample_period_us} µs ({key})")
        elif self.nacks <= 20 or self.nacks % 100 == 0:
            acts.log(LogLevel.WARN, f"controller refused COMMAND {msg.ref_seq}: {key}")
