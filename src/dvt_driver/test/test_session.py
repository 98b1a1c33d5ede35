"""Controller session state machine (dvt_driver.link.session): pure, fake clock, no ROS, no port.

Covers the handshake, HELLO retry and give-up, a version mismatch, CONFIG acked / NACKed /
expired, the stream timeout, the keep-alive rate, reconnect timing and a controller reset.
"""

from __future__ import annotations

import itertools
import math

import pytest

from dvt_driver.errors import SessionError
from dvt_driver.link.protocol import (
    PROTOCOL_VERSION,
    Ack,
    Command,
    Config,
    FrameType,
    Hello,
    HelloAck,
    Mode,
    Nack,
    NackReason,
    Sample,
    Status,
)
from dvt_driver.link.session import Actions, LogLevel, Session, SessionState, SessionTiming

PERIOD_US = 1000
TIMING = SessionTiming(sample_period_us=PERIOD_US, keepalive_period=0.02)


def hello_ack(period_us: int = PERIOD_US, version: int = PROTOCOL_VERSION) -> HelloAck:
    return HelloAck(version, period_us, 200_000, "plant-test")


def sample(seq: int, t_us: int | None = None) -> Sample:
    return Sample(seq, seq * PERIOD_US if t_us is None else t_us, 1.0, 0.3, 0.0,
                  (0.0, 0.0, 0.0), Status(0))


def hellos(acts: Actions) -> list[Hello]:
    return [m for m in acts.send if isinstance(m, Hello)]


def configs(acts: Actions) -> list[Config]:
    return [m for m in acts.send if isinstance(m, Config)]


def send_all(s: Session, acts: Actions, now: float) -> None:
    """What the node does with frames it wrote."""
    for m in acts.send:
        s.sent(m, now)


def command(s: Session, now: float) -> Command:
    """Build and 'send' a COMMAND as the node does."""
    cmd = Command(s.next_seq(), Mode.OFF, 0.0, (0.0, 0.0, 0.0))
    s.sent(cmd, now)
    return cmd


def streaming(t: float = 0.0, timing: SessionTiming = TIMING) -> Session:
    """A session that has said HELLO and got the answer (same period: no CONFIG)."""
    s = Session(timing, name="/dev/test")
    s.link_opened(t)
    assert hellos(s.poll(t, active=False))
    acts = s.on_message(hello_ack(), t)
    assert s.state is SessionState.STREAMING and s.config_ok and not configs(acts)
    return s


# -- handshake ---------------------------------------------------------------------------------

def test_handshake_hello_then_streaming() -> None:
    s = Session(TIMING, name="/dev/test")
    assert s.state is SessionState.LINK_DOWN and not s.open
    acts = s.link_opened(0.0)
    assert acts.changed and s.state is SessionState.HELLO
    acts = s.poll(0.0, active=True)
    assert [type(m) for m in acts.send] == [Hello] and acts.send[0] == Hello(PROTOCOL_VERSION)
    assert not acts.command  # no session yet: nothing commanded
    acts = s.on_message(hello_ack(), 0.003)
    assert s.open and s.hello_ack is not None and s.hello_ack.firmware_id == "plant-test"
    assert any("plant-test" in text for _, text in acts.logs)
    # the first poll after the handshake sends a COMMAND at once (when active)
    assert s.poll(0.004, active=True).command
    # samples keep the session open and are counted
    for i in range(5):
        assert not s.on_sample(sample(i), 0.005 + i * 1e-3).duplicate
    assert s.samples == 5


def test_sample_opens_the_session_without_hello_ack() -> None:
    # after a reconnect the controller may still be streaming: its samples open the session
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    acts = s.on_sample(sample(100), 0.01)
    assert s.open and acts.changed
    assert s.poll(0.01, active=True).command  # the host's state goes out at once


# -- HELLO retry and give-up ---------------------------------------------------------------------

def test_hello_retry_then_give_up_to_the_slow_rate() -> None:
    t = TIMING
    s = Session(t, name="/dev/test")
    s.link_opened(0.0)
    sent_at = []
    now = 0.0
    while now < 3.0:
        acts = s.poll(now, active=True)
        if hellos(acts):
            sent_at.append(now)
        assert not acts.command
        if any(level is LogLevel.ERROR for level, _ in acts.logs):
            give_up_at = now
        now = round(now + 0.001, 6)
    gaps = [b - a for a, b in itertools.pairwise(sent_at)]
    fast = gaps[:t.hello_attempts - 1]
    assert all(g == pytest.approx(t.hello_interval, abs=1.5e-3) for g in fast)
    assert all(g == pytest.approx(t.hello_slow_interval, abs=1.5e-3)
               for g in gaps[t.hello_attempts - 1:])
    assert s.hello_give_ups == 1 and s.hellos == len(sent_at)
    assert give_up_at == pytest.approx(sent_at[t.hello_attempts - 1], abs=1e-9)
    # an answer at last: the session opens and the fast retry is armed again for next time
    s.on_message(hello_ack(), now)
    assert s.open


# -- version mismatch --------------------------------------------------------------------------

def test_version_mismatch_refuses_and_retries_slowly() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=True)
    acts = s.on_message(hello_ack(version=PROTOCOL_VERSION + 1), 0.01)
    assert s.state is SessionState.REFUSED and s.hello_refused and not s.open
    assert any(level is LogLevel.ERROR and "protocol" in text for level, text in acts.logs)
    assert not hellos(s.poll(0.5, active=True))
    assert not hellos(s.poll(0.01 + TIMING.hello_refused_interval - 0.01, active=True))
    assert hellos(s.poll(0.01 + TIMING.hello_refused_interval, active=True))
    # a re-flashed controller answers with our version: session open, refusal cleared
    s.on_message(hello_ack(), 6.0)
    assert s.open and not s.hello_refused


def test_hello_nack_refuses() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    # the NACK of HELLO(2) is negotiation: HELLO(1) at once, not counted as a NACK
    acts = s.on_message(Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION), 0.01)
    assert hellos(acts) == [Hello(1)] and s.state is SessionState.HELLO and s.nacks == 0
    # the NACK of HELLO(1): no version left, refused
    s.on_message(Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION), 0.02)
    assert s.state is SessionState.REFUSED and s.nacks == 1
    assert s.nacks_by_reason == {"UNSUPPORTED_VERSION": 1}
    # the slow retry offers the newest version again (a re-flashed controller)
    assert hellos(s.poll(0.02 + TIMING.hello_refused_interval, active=False)) == [Hello(2)]


# -- version negotiation -------------------------------------------------------------------------

def test_v2_controller_negotiates_v2_with_counts_per_rev() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    assert hellos(s.poll(0.0, active=False)) == [Hello(PROTOCOL_VERSION)] == [Hello(2)]
    assert s.protocol_version is None and s.counts_per_rev is None
    acts = s.on_message(HelloAck(2, PERIOD_US, 200_000, "v2", 4096, 16384), 0.01)
    assert s.open and s.protocol_version == 2 and s.counts_per_rev == (4096, 16384)
    assert any("4096/16384 counts/rev" in text for _, text in acts.logs)
    assert s.version_fallbacks == 0 and s.nacks == 0


def test_v1_controller_answering_hello2_with_nack_gets_hello1_and_streams_speeds_only() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    assert hellos(s.poll(0.0, active=False)) == [Hello(2)]
    acts = s.on_message(Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION), 0.001)
    assert hellos(acts) == [Hello(1)] and s.offered_version == 1
    s.on_message(HelloAck(1, PERIOD_US, 200_000, "v1"), 0.002)
    assert s.open and s.protocol_version == 1 and s.counts_per_rev is None
    assert s.version_fallbacks == 1 and s.nacks == 0 and not s.hello_refused
    # a new link offers version 2 again
    s.link_lost(1.0)
    s.link_opened(1.1)
    assert hellos(s.poll(1.1, active=False)) == [Hello(2)]


def test_controller_may_answer_an_older_version_it_speaks() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    s.on_message(HelloAck(1, PERIOD_US, 0, "old"), 0.01)  # answers HELLO(2) with 1
    assert s.open and s.protocol_version == 1 and s.counts_per_rev is None


def test_version_above_the_offer_or_unknown_is_refused() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    s.on_message(Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION), 0.001)
    s.on_message(HelloAck(2, PERIOD_US, 0, "liar", 1, 1), 0.002)  # we offered 1
    assert s.state is SessionState.REFUSED and not s.open
    s2 = Session(TIMING)
    s2.link_opened(0.0)
    s2.poll(0.0, active=False)
    s2.on_message(HelloAck(0, PERIOD_US, 0, "zero"), 0.01)
    assert s2.state is SessionState.REFUSED


def test_sample_before_hello_ack_opens_without_known_version() -> None:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    s.on_sample(Sample(0, 0, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0), (1, 2)), 0.01)
    assert s.open and s.protocol_version is None and s.counts_per_rev is None


# -- CONFIG --------------------------------------------------------------------------------------

def _configuring() -> tuple[Session, Config]:
    s = Session(TIMING)
    s.link_opened(0.0)
    s.poll(0.0, active=False)
    acts = s.on_message(hello_ack(period_us=16_000), 0.01)  # the controller's own period
    (cfg,) = configs(acts)
    assert cfg.sample_period_us == PERIOD_US and not s.config_ok and s.open
    send_all(s, acts, 0.01)
    return s, cfg


def test_config_acked() -> None:
    s, cfg = _configuring()
    acts = s.on_message(Ack(FrameType.CONFIG, cfg.seq), 0.02)
    assert s.config_ok and not s.config_refused and not s.pending and s.acks == 1
    assert any("sample period set" in text for _, text in acts.logs)
    assert not configs(s.poll(1.0, active=False)) and s.unanswered == 0


def test_config_nacked_is_not_retried() -> None:
    s, cfg = _configuring()
    acts = s.on_message(Nack(FrameType.CONFIG, cfg.seq, NackReason.INVALID_VALUE), 0.02)
    assert s.config_refused and not s.config_ok and not s.pending
    assert any(level is LogLevel.ERROR and "1000 µs" in text for level, text in acts.logs)
    for k in range(1, 30):
        s.on_sample(sample(k), 0.02 + k * 0.05)
        assert not configs(s.poll(0.02 + k * 0.05, active=False))
    assert s.open


def test_config_expired_counts_unanswered_and_is_sent_again() -> None:
    s, cfg = _configuring()
    a = TIMING.answer_timeout
    s.on_sample(sample(1), 0.2)
    assert not configs(s.poll(0.2, active=False))
    s.on_sample(sample(2), 0.01 + a)
    assert not configs(s.poll(0.01 + a, active=False))  # not yet: exactly at the timeout
    s.on_sample(sample(3), 0.02 + a)
    acts = s.poll(0.02 + a, active=False)
    (again,) = configs(acts)
    assert s.unanswered == 1 and again.seq != cfg.seq
    assert again.sample_period_us == PERIOD_US
    send_all(s, acts, 0.02 + a)
    s.on_message(Ack(FrameType.CONFIG, again.seq), 0.03 + a)
    assert s.config_ok and not s.pending


def test_command_answers_are_matched_and_expire() -> None:
    s = streaming()
    c1, c2 = command(s, 0.0), command(s, 0.01)
    assert s.commands_sent == 2 and len(s.pending) == 2
    s.on_message(Ack(FrameType.COMMAND, c1.seq), 0.002)
    s.on_message(Nack(FrameType.COMMAND, c2.seq, NackReason.INVALID_VALUE), 0.012)
    assert not s.pending and s.acks == 1 and s.nacks == 1
    c3 = command(s, 0.02)
    s.on_sample(sample(1), 0.3)
    s.poll(0.3, active=False)
    assert s.unanswered == 0
    s.on_sample(sample(2), 0.53)
    s.poll(0.53, active=False)
    assert s.unanswered == 1 and (FrameType.COMMAND, c3.seq) not in s.pending


def test_command_gap_is_the_longest_interval_of_one_active_run() -> None:
    """``command_gap_max`` [s]: the longest interval between two COMMANDs while active; an
    inactive spell or a lost link starts a new run (the pause between runs is not a gap)."""
    s = streaming()
    s.poll(0.0, active=True)
    command(s, 0.0)
    command(s, 0.02)
    command(s, 0.07)  # 50 ms
    assert s.command_gap_max == pytest.approx(0.05)
    s.poll(0.08, active=False)
    s.poll(5.0, active=True)
    command(s, 5.0)  # after 4.93 s inactive: a new run
    command(s, 5.03)
    assert s.command_gap_max == pytest.approx(0.05)
    s.link_lost(5.04, "unplugged")
    command(s, 9.0)
    assert s.command_gap_max == pytest.approx(0.05)
    command(s, 9.2)
    assert s.command_gap_max == pytest.approx(0.2)


# -- stream timeout ------------------------------------------------------------------------------

def test_stream_timeout_closes_the_session_and_says_hello() -> None:
    s = streaming()
    assert TIMING.stream_timeout_s == 0.25  # max(0.25 s, 20 periods of 1 ms)
    for k in range(10):
        s.on_sample(sample(k), k * 1e-3)
    last = 9e-3
    acts = s.poll(last + 0.25, active=True)
    assert s.open and s.stream_timeouts == 0 and not hellos(acts)
    acts = s.poll(last + 0.2501, active=True)
    assert not s.open and s.state is SessionState.HELLO and s.stream_timeouts == 1
    assert hellos(acts) and not acts.command  # HELLO at once, nothing commanded meanwhile
    assert any("no sample" in text for _, text in acts.logs)
    assert SessionTiming(sample_period_us=16_000, keepalive_period=0.02).stream_timeout_s \
        == pytest.approx(0.32)


def test_not_ready_nack_closes_the_session() -> None:
    s = streaming()
    c = command(s, 0.0)
    s.on_message(Nack(FrameType.COMMAND, c.seq, NackReason.NOT_READY), 0.001)
    assert s.state is SessionState.HELLO
    assert hellos(s.poll(0.001, active=True))


# -- keep-alive ----------------------------------------------------------------------------------

def _commands_in(s: Session, t0: float, t1: float, *, active: bool = True,
                 shifting: bool = False) -> list[float]:
    out = []
    now, k = t0, 0
    while now < t1:
        s.on_sample(sample(1000 + k), now)
        if s.poll(now, active=active, shifting=shifting).command:
            command(s, now)
            out.append(now)
        k += 1
        now = round(t0 + k * 1e-3, 9)
    return out


def test_keepalive_rate_and_immediate_commands() -> None:
    s = streaming()
    sent = _commands_in(s, 0.0, 1.0)
    assert len(sent) == pytest.approx(1.0 / TIMING.keepalive_period, abs=1)
    assert all(b - a == pytest.approx(0.02, abs=1.1e-3) for a, b in itertools.pairwise(sent))
    # a new command goes out at once, and the keep-alive counts from there
    s.request_command()
    assert s.poll(1.0005, active=True).command
    assert not s.poll(1.01, active=True).command
    assert s.poll(1.0005 + 0.02, active=True).command
    assert s.poll(1.03, active=True, urgent=True).command


def test_shift_rate_and_nothing_while_inactive() -> None:
    s = streaming()
    assert len(_commands_in(s, 0.0, 0.1, shifting=True)) == pytest.approx(0.1 / 0.005, abs=1)
    s.request_command()
    assert not _commands_in(s, 0.2, 1.0, active=False)  # inactive: nothing, not even requested
    assert s.poll(1.0, active=True).command  # activation: keep-alive resumes at once


def test_time_to_next() -> None:
    s = streaming()
    s.on_sample(sample(1), 0.0)
    assert s.poll(0.0, active=True).command
    assert s.time_to_next(0.005, active=True) == pytest.approx(0.015)
    assert s.time_to_next(0.005, active=False) == pytest.approx(0.245)  # the stream deadline
    s.link_lost(0.1)
    assert s.time_to_next(0.1, active=True) == 0.0  # reopen at once


# -- reconnect -----------------------------------------------------------------------------------

def _outage(s: Session, lost_at: float, back_at: float, step: float = 1e-4
            ) -> tuple[float, list[float]]:
    """Drive the session through a device outage in ``step`` increments; returns when the
    link was reopened and the reopen attempt times."""
    attempts = []
    s.link_lost(lost_at, "read failed")
    now = lost_at
    while True:
        acts = s.poll(now, active=True)
        if acts.reopen:
            attempts.append(now)
            if now >= back_at:
                s.link_opened(now)
                return now, attempts
            s.reopen_failed(now, "no such file")
        now = round(now + step, 9)


def test_reconnect_within_50_ms_of_the_device_coming_back() -> None:
    for back_after in (0.0, 0.003, 0.011, 0.05, 0.2, 0.2137, 1.0, 7.77):
        s = streaming()
        opened, attempts = _outage(s, 1.0, 1.0 + back_after)
        assert attempts[0] == 1.0  # the first attempt is immediate
        assert opened - (1.0 + back_after) <= 0.05 + 1e-9, back_after
    # back-off: 10, 20, 40, 40, ... ms between attempts
    s = streaming()
    _, attempts = _outage(s, 0.0, 1.0)
    gaps = [b - a for a, b in itertools.pairwise(attempts)]  # on a 0.1 ms grid
    assert gaps[:4] == pytest.approx([0.01, 0.02, 0.04, 0.04], abs=2e-4)
    assert max(gaps) <= 0.04 + 2e-4


def test_reconnect_says_hello_at_once_and_logs_are_bounded() -> None:
    s = streaming()
    acts = s.link_lost(5.0, "read failed")
    assert acts.changed and s.state is SessionState.LINK_DOWN and not s.open
    assert not s.link_lost(5.001).logs  # idempotent
    logs = list(acts.logs)
    now = 5.0
    while now < 35.0:  # 30 s away: ~750 attempts, a handful of log lines
        a = s.poll(now, active=True)
        assert not a.send and not a.command
        if a.reopen:
            logs += s.reopen_failed(now, "no such file").logs
        now = round(now + 1e-3, 6)
    assert s.reopen_attempts > 700 and len(logs) <= 5
    logs += s.link_opened(now).logs
    assert "reconnected" in logs[-1][1]
    acts = s.poll(now, active=True)
    assert hellos(acts) and s.state is SessionState.HELLO
    s.on_sample(sample(50_000), now + 0.001)
    assert s.open and s.poll(now + 0.001, active=True).command


def test_pending_answers_are_forgotten_when_the_link_goes() -> None:
    s = streaming()
    command(s, 0.0)
    s.link_lost(0.01)
    s.link_opened(0.02)
    s.poll(1.0, active=False)
    assert s.unanswered == 0


# -- controller reset ----------------------------------------------------------------------------

def test_controller_reset_and_duplicates() -> None:
    s = streaming()
    for k in range(100, 110):
        assert not s.on_sample(sample(k), k * 1e-3).reset
    dup = s.on_sample(sample(109), 0.2)
    assert dup.duplicate and s.duplicates == 1 and s.samples == 10
    acts = s.on_sample(sample(0, 0), 0.21)  # sequence and clock start over
    assert acts.reset and acts.changed and not acts.duplicate
    (cfg,) = configs(acts)  # the controller lost its period: CONFIG again
    assert cfg.sample_period_us == PERIOD_US and not s.config_ok
    assert s.poll(0.21, active=True).command  # the safe state goes out at once
    assert s.samples == 11 and s.open


def test_first_sample_is_never_a_reset() -> None:
    s = streaming()
    assert not s.on_sample(sample(5), 0.0).reset


# -- settings ------------------------------------------------------------------------------------

def test_timing_is_validated() -> None:
    with pytest.raises(SessionError, match="sample_period_us"):
        SessionTiming(sample_period_us=0, keepalive_period=0.02)
    with pytest.raises(SessionError, match="keepalive_period"):
        SessionTiming(sample_period_us=1000, keepalive_period=math.nan)
    with pytest.raises(SessionError, match="hello_attempts"):
        SessionTiming(sample_period_us=1000, keepalive_period=0.02, hello_attempts=0)
    t = SessionTiming(sample_period_us=1000, keepalive_period=0.02, reconnect_interval=0.5)
    assert t.reconnect_max == 0.5  # never faster than asked
