"""SerialLink against a real pseudo-terminal pair (os.openpty + tty.setraw), no mocks.

The test plays the device on the pty master; the link opens a symlink to the slave, the way the
simulated plant publishes its port, so the device can vanish and come back under the same path.
"""

from __future__ import annotations

import os
import re
import select
import time
import tty
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dvt_driver.errors import LinkError, ProtocolError
from dvt_driver.link.protocol import (
    Ack,
    Command,
    Config,
    FrameDecoder,
    FrameType,
    Hello,
    HelloAck,
    Message,
    Mode,
    Sample,
    Status,
    encode,
)
from dvt_driver.link.serial_link import LinkState, LinkStats, SerialLink

WAIT = 5.0  # s: generous upper bound for any single wait; tests poll with a deadline


class PtyDevice:
    """The device end of a pty pair, reachable by the link through ``path`` (a symlink)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tmp = path.with_suffix(".tmp")
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(os.ttyname(self.slave))
        os.replace(tmp, path)
        self.decoder = FrameDecoder()
        self.open = True

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.master, view)
            view = view[n:]

    def send(self, *msgs: Message) -> None:
        self.write(b"".join(encode(m) for m in msgs))

    def receive(self, count: int, timeout: float = WAIT) -> list[Message]:
        """Messages the host sent, until ``count`` arrived or ``timeout`` passed."""
        out: list[Message] = []
        deadline = time.monotonic() + timeout
        while len(out) < count:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                out += self.decoder.feed(os.read(self.master, 4096))
        return out

    def vanish(self) -> None:
        """Close both ends: the pts node disappears, the link's next I/O fails."""
        if self.open:
            os.close(self.master)
            os.close(self.slave)
            self.open = False


@pytest.fixture
def device(tmp_path: Path) -> Iterator[PtyDevice]:
    dev = PtyDevice(tmp_path / "dvt-tty")
    yield dev
    dev.vanish()


@pytest.fixture
def link(device: PtyDevice) -> Iterator[SerialLink]:
    lk = SerialLink(str(device.path), 921600, write_timeout=0.2)
    lk.open()
    yield lk
    lk.close()


def collect(link: SerialLink, count: int, timeout: float = WAIT) -> list[Message]:
    """Messages read from the link until ``count`` arrived or ``timeout`` passed."""
    out: list[Message] = []
    deadline = time.monotonic() + timeout
    while len(out) < count and time.monotonic() < deadline:
        out += link.read_messages(0.05)
    return out


def sample(seq: int) -> Sample:
    return Sample(seq, 1000 * seq, 0.5 * seq, -1.0, 2.0, (0.0, 0.25, 0.0),
                  Status.ENABLED | Status.BRAKE2)


# ------------------------------------------------------------------------------------------


def test_round_trip_both_directions(device: PtyDevice, link: SerialLink) -> None:
    assert link.state is LinkState.CONNECTED and link.connected
    hello = Hello()
    cmd = Command(1, Mode.CURRENT, 1.5, (0.0, 0.5, 0.0))
    cfg = Config(2, 1000)
    assert link.send(hello) and link.send(cmd) and link.send(cfg)
    assert device.receive(3) == [hello, cmd, cfg]
    assert device.decoder.frames_bad == 0  # the lone 0x00 sent on open is an empty frame

    replies: list[Message] = [HelloAck(1, 1000, 100_000, "pty-device"),
                              Ack(FrameType.COMMAND, 1), Ack(FrameType.CONFIG, 2)]
    replies += [sample(i) for i in range(50)]  # ~2 kB: fits any pty buffer
    device.send(*replies)
    assert collect(link, len(replies)) == replies
    stats = link.stats
    assert isinstance(stats, LinkStats)
    assert stats.frames_good == len(replies)
    assert (stats.frames_bad, stats.crc_errors, stats.lost_samples, stats.resets) == (0, 0, 0, 0)
    assert stats.bytes_received == sum(len(encode(m)) for m in replies)


def test_read_messages_times_out_empty(link: SerialLink) -> None:
    assert link.read_messages(0.0) == []
    assert link.read_messages(0.02) == []
    assert link.state is LinkState.CONNECTED


def test_partial_frame_is_completed_by_a_later_read(device: PtyDevice, link: SerialLink) -> None:
    frame = encode(sample(1))
    device.write(frame[:20])
    assert link.read_messages(0.05) == []
    device.write(frame[20:])
    assert collect(link, 1) == [sample(1)]


def test_garbage_between_frames(device: PtyDevice, link: SerialLink) -> None:
    garbage = bytes(range(1, 200)) + b"\x00" + b"\xff\xfe\x00\x00"
    device.write(encode(sample(0)) + garbage + encode(sample(1)) + b"\x42\x43\x00"
                 + encode(sample(2)))
    assert collect(link, 3) == [sample(0), sample(1), sample(2)]
    stats = link.stats
    assert stats.frames_good == 3
    assert stats.frames_bad == 3  # two garbage fragments + "\x42\x43"
    assert stats.bytes_discarded == 199 + 2 + 2
    assert stats.lost_samples == 0


def test_truncated_frame_is_dropped_and_counted_as_lost(
        device: PtyDevice, link: SerialLink) -> None:
    frames = [encode(sample(i)) for i in range(10)]
    frames[3] = frames[3][:-12] + b"\x00"  # the end of sample 3 is lost, delimiter arrives
    device.write(b"".join(frames))
    got = collect(link, 9)
    assert got == [sample(i) for i in range(10) if i != 3]
    stats = link.stats
    assert stats.frames_bad == 1 and stats.lost_samples == 1


def test_controller_reset_is_reported(device: PtyDevice, link: SerialLink) -> None:
    device.send(sample(100), sample(101), sample(0), sample(1))
    assert len(collect(link, 4)) == 4
    assert link.stats.resets == 1 and link.stats.lost_samples == 0


def test_send_refuses_unencodable_messages_without_writing(
        device: PtyDevice, link: SerialLink) -> None:
    with pytest.raises(ProtocolError, match=r"Command\.setpoint: must be finite"):
        link.send(Command(1, Mode.SPEED, float("nan"), (0.0, 0.0, 0.0)))
    assert link.send(Hello())
    assert device.receive(1) == [Hello()]
    assert link.stats.write_errors == 0


def test_device_vanishes_and_comes_back(
        tmp_path: Path, device: PtyDevice, link: SerialLink) -> None:
    device.send(sample(0), sample(1))
    assert collect(link, 2) == [sample(0), sample(1)]

    device.vanish()
    # the next read notices: no exception, state DISCONNECTED, counted
    assert collect(link, 1, timeout=1.0) == []
    assert link.state is LinkState.DISCONNECTED
    assert link.stats.disconnects == 1
    assert link.last_error is not None and str(device.path) in link.last_error
    assert link.send(Hello()) is False
    assert link.stats.write_errors == 1
    assert link.read_messages(0.01) == []

    # while the device is gone, reopening fails quietly
    assert link.reopen() is False
    assert link.state is LinkState.DISCONNECTED
    assert link.last_error is not None and "cannot open" in link.last_error
    with pytest.raises(LinkError, match="cannot open"):
        link.open()

    # the device comes back under the same path
    again = PtyDevice(device.path)
    try:
        assert link.reopen() is True
        assert link.state is LinkState.CONNECTED
        assert link.stats.reconnects == 1
        assert link.send(Hello())
        assert again.receive(1) == [Hello()]
        again.send(sample(5), sample(6))
        assert collect(link, 2) == [sample(5), sample(6)]
        stats = link.stats
        # samples 2..4 were produced while we were away: counted as lost, not as a reset
        assert (stats.lost_samples, stats.resets, stats.frames_good) == (3, 0, 4)
    finally:
        again.vanish()


def test_write_timeout_when_device_does_not_read(device: PtyDevice) -> None:
    link = SerialLink(str(device.path), write_timeout=0.05)
    link.open()
    try:
        cmd = Command(1, Mode.OFF, 0.0, (0.0, 0.0, 0.0))
        ok = True
        for _ in range(100_000):  # the pty buffer holds a few kB: fills long before that
            ok = link.send(cmd)
            if not ok:
                break
        assert not ok
        assert link.stats.write_errors == 1
        assert link.state is LinkState.CONNECTED  # a slow device is not a vanished one
        assert link.last_error is not None and "timed out" in link.last_error
    finally:
        link.close()


def test_close_and_context_manager(device: PtyDevice) -> None:
    with SerialLink(str(device.path)) as lk:
        assert lk.connected
        assert lk.send(Hello())
    assert lk.state is LinkState.CLOSED
    assert lk.send(Hello()) is False
    assert lk.read_messages(0.0) == []
    lk.close()  # idempotent
    assert device.receive(1) == [Hello()]


def test_open_errors_name_the_port(tmp_path: Path) -> None:
    missing = tmp_path / "no-such-tty"
    lk = SerialLink(str(missing))
    with pytest.raises(LinkError, match=re.escape(str(missing))):
        lk.open()
    assert lk.state is LinkState.CLOSED
    assert lk.reopen() is False
    assert lk.state is LinkState.DISCONNECTED


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"port": ""}, "port"),
    ({"port": "/dev/x", "baud": 0}, "baud"),
    ({"port": "/dev/x", "baud": 9600.5}, "baud"),
    ({"port": "/dev/x", "write_timeout": 0}, "write_timeout"),
    ({"port": "/dev/x", "write_timeout": float("inf")}, "write_timeout"),
])
def test_constructor_validates_arguments(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(LinkError, match=match):
        SerialLink(**kwargs)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_read_timeout_is_validated(link: SerialLink, bad: float) -> None:
    with pytest.raises(LinkError, match="timeout"):
        link.read_messages(bad)
