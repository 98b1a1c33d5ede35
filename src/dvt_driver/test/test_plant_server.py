"""``dvt-plant`` as a process on a real pseudo-terminal, spoken to with pyserial (no mocks):
hello, real-time samples, CONFIG, fault injection counts, disconnect/reconnect, reset."""

from __future__ import annotations

import itertools
import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import serial
import yaml

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
    Nack,
    NackReason,
    Sample,
    SequenceTracker,
    Status,
    encode,
)
from dvt_driver.link.serial_link import LinkState, SerialLink
from dvt_driver.plant.hidden import load_hidden

WAIT = 10.0  # s: upper bound of any single wait (tests poll with a deadline)


def _plant_script() -> str:
    path = Path(sys.executable).parent / "dvt-plant"
    if not path.exists():
        pytest.fail(f"console script {path} not installed (scripts/bootstrap.sh installs it)")
    return str(path)


class Plant:
    """A running ``dvt-plant`` process."""

    def __init__(self, tmp: Path, *args: str) -> None:
        self.link = tmp / "dvt-tty"
        self.proc = subprocess.Popen([_plant_script(), "--link", str(self.link), *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self._readline(WAIT)
        assert line == f"READY {self.link}", (line, self.proc.stderr.read()
                                                if self.proc.poll() is not None
                                                and self.proc.stderr else "")

    def _readline(self, timeout: float) -> str:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return self.proc.stdout.readline().strip() if ready else ""

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self) -> dict[str, int | float]:
        """SIGINT, wait for the exit, return the STATS it printed."""
        self.proc.send_signal(signal.SIGINT)
        out, err = self.proc.communicate(timeout=WAIT)
        assert self.proc.returncode == 0, err
        stats = [ln for ln in out.splitlines() if ln.startswith("STATS ")]
        assert stats, (out, err)
        result: dict[str, int | float] = json.loads(stats[-1][6:])
        return result

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def plants(tmp_path: Path) -> Iterator[Callable[..., Plant]]:
    started: list[Plant] = []

    def start(*args: str) -> Plant:
        p = Plant(tmp_path, *args)
        started.append(p)
        return p

    yield start
    for p in started:
        p.kill()


class Client:
    """pyserial on the plant's link with a FrameDecoder and a SequenceTracker."""

    def __init__(self, link: Path) -> None:
        self.port = serial.Serial(str(link), 921600, timeout=0)
        self.port.reset_input_buffer()
        self.port.write(b"\x00")
        self.decoder = FrameDecoder()
        self.tracker = SequenceTracker()
        self.samples: list[Sample] = []
        self.others: list[Message] = []

    def send(self, msg: Message) -> None:
        self.port.write(encode(msg))

    def pump(self, seconds: float, until: Callable[[], bool] | None = None,
             keepalive: Message | None = None) -> None:
        deadline = time.monotonic() + seconds
        next_ka = 0.0
        while time.monotonic() < deadline:
            if keepalive is not None and time.monotonic() >= next_ka:
                self.send(keepalive)
                next_ka = time.monotonic() + 0.05
            ready, _, _ = select.select([self.port.fileno()], [], [], 0.02)
            if ready:
                for m in self.decoder.feed(self.port.read(4096)):
                    if isinstance(m, Sample):
                        self.samples.append(m)
                        self.tracker.update(m.seq, m.t_us)
                    else:
                        self.others.append(m)
            if until is not None and until():
                return

    def quiet(self, seconds: float = 0.3) -> None:
        """Read until nothing arrived for ``seconds`` (bounded by WAIT)."""
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            n = self.decoder.frames_good + self.decoder.frames_bad
            self.pump(seconds)
            if self.decoder.frames_good + self.decoder.frames_bad == n:
                return
        pytest.fail("the plant did not go quiet")

    def close(self) -> None:
        self.port.close()


def test_hello_samples_in_real_time_and_config(plants: Callable[..., Plant]) -> None:
    plant = plants("--seed", "1")
    assert plant.link.is_symlink() and os.readlink(plant.link).startswith("/dev/pts/")
    c = Client(plant.link)
    c.pump(1.0)
    assert c.samples == [], "samples before HELLO"
    c.send(Hello())
    c.pump(WAIT, until=lambda: any(isinstance(m, HelloAck) for m in c.others))
    assert c.others[0] == HelloAck(2, 1000, 200000, "dvt-plant-sim 0.1", 4096, 16384)
    cmd = Command(1, Mode.SPEED, 100.0, (0.0, 0.0, 0.0))
    t0 = time.monotonic()
    c.pump(2.0, keepalive=cmd)
    wall = time.monotonic() - t0
    s = c.samples
    assert len(s) > 500
    assert all(b.seq - a.seq == 1 for a, b in itertools.pairwise(s))
    assert all(b.t_us - a.t_us == 1000 for a, b in itertools.pairwise(s))
    assert c.tracker.lost == 0 and c.decoder.frames_bad == 0
    # paced in real time: the controller clock never runs ahead of the wall clock; the lower
    # bound is loose because a loaded 2-core machine may delay the plant (it catches up later)
    span = (s[-1].t_us - s[0].t_us) * 1e-6
    assert 0.25 * wall < span < 1.05 * wall + 0.05
    assert Ack(FrameType.COMMAND, 1) in c.others
    assert s[-1].status & Status.ENABLED
    assert abs(s[-1].sun_speed - 100.0) < 5.0
    assert all(x.counts is not None for x in s)  # version 2: every sample carries counts
    assert s[-1].counts is not None and s[-1].counts[0] > 4096  # the sun turned
    # the thesis's 16 ms serial period, set over the line
    c.send(Config(2, 16000))
    c.pump(WAIT, until=lambda: Ack(FrameType.CONFIG, 2) in c.others)
    n = len(c.samples)
    c.pump(WAIT, until=lambda: len(c.samples) >= n + 12, keepalive=cmd)
    steps = [b.t_us - a.t_us for a, b in zip(c.samples[n - 1:], c.samples[n:], strict=False)]
    # the sample in progress when the CONFIG came still ends after 1 ms, then 16 ms
    assert len(steps) >= 12 and set(steps[2:]) == {16000}, steps
    c.close()
    stats = plant.stop()
    assert stats["tx_overruns"] == 0 and stats["host_overruns"] == 0
    assert stats["frames_bad_in"] == 0
    assert stats["commands_accepted"] >= 30
    assert 0.0 < stats["cpu_fraction"] < 1.0
    assert not plant.link.exists() and not plant.link.is_symlink()


def test_fault_injection_is_seen_by_the_decoder(plants: Callable[..., Plant]) -> None:
    plant = plants("--seed", "7", "--fault-corrupt", "0.02", "--fault-drop", "0.02",
                   "--fault-garbage", "0.02")
    c = Client(plant.link)
    c.send(Hello())
    c.pump(2.0)
    plant.signal(signal.SIGUSR2)  # controller reset: the stream stops until the next HELLO
    c.quiet()
    c.close()
    stats = plant.stop()
    injected = int(stats["corrupted"]) + int(stats["dropped"]) + int(stats["garbage"])
    assert stats["corrupted"] > 0 and stats["dropped"] > 0 and stats["garbage"] > 0
    assert stats["tx_overruns"] == 0 and stats["host_overruns"] == 0 and stats["resets"] == 1
    # every damaged frame costs exactly one bad frame, every garbage burst one more
    assert c.decoder.frames_bad == injected
    assert sum(c.decoder.errors_by_reason.values()) == injected
    # corrupted and shortened samples are lost (one at either end of the stream cannot be seen
    # as a gap), garbage costs no sample
    lost_expected = int(stats["corrupted"]) + int(stats["dropped"])
    assert lost_expected - 2 <= c.tracker.lost <= lost_expected
    assert len(c.samples) + c.tracker.lost == c.samples[-1].seq - c.samples[0].seq + 1


def test_reconnect_after_sigusr1(plants: Callable[..., Plant]) -> None:
    plant = plants("--seed", "3", "--fault-disconnect-for", "0.5")
    link = SerialLink(str(plant.link), write_timeout=0.2)
    link.open()
    got: list[Message] = []

    def collect(pred: Callable[[], bool]) -> None:
        deadline = time.monotonic() + WAIT
        while not pred() and time.monotonic() < deadline:
            got.extend(link.read_messages(0.05))
        assert pred()

    assert link.send(Hello())
    collect(lambda: sum(isinstance(m, Sample) for m in got) >= 100)
    plant.signal(signal.SIGUSR1)
    collect(lambda: link.state is LinkState.DISCONNECTED)
    last_before = [m for m in got if isinstance(m, Sample)][-1].seq
    got.clear()
    assert link.stats.disconnects == 1
    assert not link.reopen()  # the device is away for 0.5 s: the link path is gone
    deadline = time.monotonic() + WAIT
    while not link.reopen():
        assert time.monotonic() < deadline, link.last_error
        time.sleep(0.05)
    assert link.send(Hello())
    collect(lambda: any(isinstance(m, HelloAck) for m in got)
            and sum(isinstance(m, Sample) for m in got) >= 100)
    after = [m for m in got if isinstance(m, Sample)]
    assert after[0].seq > last_before + 300  # the controller kept running while away
    stats = link.stats
    assert stats.reconnects == 1 and stats.resets == 0
    assert stats.lost_samples >= 300
    link.close()
    pstats = plant.stop()
    assert pstats["disconnects"] == 1


def test_controller_reset_restarts_sequence_and_session(plants: Callable[..., Plant]) -> None:
    plant = plants("--seed", "4")
    c = Client(plant.link)
    c.send(Hello())
    c.pump(WAIT, until=lambda: len(c.samples) >= 200)
    plant.signal(signal.SIGUSR2)
    c.quiet()
    n = len(c.samples)
    c.send(Command(5, Mode.CURRENT, 1.0, (0.0, 0.0, 0.0)))
    c.pump(WAIT, until=lambda: len(c.others) >= 2)
    assert c.others[-1].ref_seq == 5 and c.others[-1].reason.name == "NOT_READY"  # type: ignore[union-attr]
    c.send(Hello())
    c.pump(WAIT, until=lambda: len(c.samples) >= n + 50)
    assert c.samples[n].seq == 0 and c.samples[n - 1].seq >= 199
    assert c.tracker.resets == 1
    c.close()
    assert plant.stop()["resets"] == 1


def test_scheduled_faults_truth_file_and_duration(tmp_path: Path,
                                                  plants: Callable[..., Plant]) -> None:
    truth = tmp_path / "truth.yaml"
    plant = plants("--hidden", "windage", "--seed", "5", "--truth-out", str(truth),
                   "--duration", "0.8", "--fault-disconnect-at", "0.2",
                   "--fault-disconnect-for", "0.1", "--fault-reset-at", "0.4")
    out, err = plant.proc.communicate(timeout=WAIT)
    assert plant.proc.returncode == 0, err
    stats = json.loads(out.splitlines()[-1][6:])
    assert stats["disconnects"] == 1 and stats["resets"] == 1
    assert 700 <= stats["samples_produced"] <= 900
    doc = yaml.safe_load(truth.read_text())
    assert doc["effects"] == ["windage"]
    # the preset's magnitudes drawn from --seed, the draw recorded
    assert doc["hidden"] == load_hidden("windage", draw=5).to_mapping()
    assert doc["hidden"] != load_hidden("windage").to_mapping()
    assert doc["hidden_draw"]["seed"] == 5 and not doc["hidden_draw"]["fixed"]
    assert doc["plant"]["seed"] == 5 and doc["plant"]["sample_period_us"] == 1000


def test_the_draw_is_apart_from_the_noise_seed(tmp_path: Path,
                                               plants: Callable[..., Plant]) -> None:
    """One actuator recorded twice: ``--draw`` sets the hidden magnitudes, ``--seed`` the
    noise; two noise seeds with one draw are the same plant."""
    docs = []
    for seed in ("5", "6"):
        truth = tmp_path / f"truth-{seed}.yaml"
        plant = plants("--hidden", "coulomb", "--draw", "3", "--seed", seed,
                       "--truth-out", str(truth), "--duration", "0.2")
        _, err = plant.proc.communicate(timeout=WAIT)
        assert plant.proc.returncode == 0, err
        docs.append(yaml.safe_load(truth.read_text()))
    assert docs[0]["hidden"] == docs[1]["hidden"] == load_hidden("coulomb", draw=3).to_mapping()
    assert docs[0]["hidden"] != load_hidden("coulomb", draw=5).to_mapping()
    assert [d["plant"]["seed"] for d in docs] == [5, 6]
    assert all(d["hidden_draw"]["seed"] == 3 for d in docs)


@pytest.mark.parametrize(("args", "message"), [
    (["--hidden", "nope"], "unknown hidden-effects preset 'nope'"),
    (["--params", "nope"], "unknown parameter set 'nope'"),
    (["--baud", "115200"], "1000 µs is shorter than one sample frame on a 115200 baud line"),
    (["--fault-corrupt", "1.5"], "--fault-corrupt: expected a probability 0..1, got 1.5"),
    (["--period-us", "10"], "expected 500..1000000 µs, got 10"),
    (["--draw", "3", "--hidden-fixed"], "--draw 3 and --hidden-fixed: give one"),
])
def test_bad_arguments_exit_2_with_a_message(tmp_path: Path, args: list[str],
                                             message: str) -> None:
    proc = subprocess.run([_plant_script(), "--link", str(tmp_path / "x"), *args],
                          capture_output=True, text=True, timeout=WAIT)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert not (tmp_path / "x").exists()


def test_nobody_reading_loses_samples_like_a_line_and_a_new_client_gets_fresh_ones(
        plants: Callable[..., Plant]) -> None:
    plant = plants("--seed", "6")
    c = Client(plant.link)
    c.send(Hello())
    c.pump(WAIT, until=lambda: len(c.samples) >= 100)
    c.close()
    last = c.samples[-1].seq
    time.sleep(3.0)  # the session stays open: 3000 samples stream into a pty nobody reads
    c2 = Client(plant.link)  # flushes what piled up
    c2.pump(WAIT, until=lambda: len(c2.samples) >= 50)
    assert c2.samples[0].seq > last + 2000  # fresh samples, not a backlog
    assert c2.tracker.lost == 0
    c2.close()
    stats = plant.stop()
    assert stats["host_overruns"] > 0 and stats["tx_overruns"] == 0


def test_an_existing_file_is_never_replaced_by_the_link(tmp_path: Path) -> None:
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me")
    proc = subprocess.run([_plant_script(), "--link", str(victim)], capture_output=True,
                          text=True, timeout=WAIT)
    assert proc.returncode == 2
    assert "exists and is not a symlink" in proc.stderr
    assert victim.read_text() == "keep me"


def test_plant_serves_version_1_when_asked(plants: Callable[..., Plant]) -> None:
    """``dvt-plant --protocol-version 1`` is an old controller: HELLO(2) is NACKed, HELLO(1)
    answered, samples carry no counts (the frames are the 43-byte version-1 SAMPLE)."""
    plant = plants("--seed", "2", "--protocol-version", "1", "--load", "arm")
    c = Client(plant.link)
    c.send(Hello(2))
    c.pump(WAIT, until=lambda: bool(c.others))
    assert c.others[0] == Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION)
    assert c.samples == []
    c.send(Hello(1))
    c.pump(WAIT, until=lambda: len(c.samples) > 50)
    assert HelloAck(1, 1000, 200000, "dvt-plant-sim 0.1") in c.others
    assert all(x.counts is None for x in c.samples)
    c.close()
    plant.stop()


def test_plant_refuses_an_unknown_load(tmp_path: Path) -> None:
    proc = subprocess.run([_plant_script(), "--link", str(tmp_path / "l"), "--load", "piano"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and "piano" in proc.stderr


def test_a_watchdog_trip_is_told_apart_from_the_plants_own_stall(
        plants: Callable[..., Plant]) -> None:
    """Two trips of the controller's watchdog (0.2 s): one from the host's silence (no keep-
    alive for 0.5 s while the plant runs), one from the plant's own stall (SIGSTOP for 0.5 s
    while the host keeps sending: the plant reads the waiting commands, then catches up with a
    burst longer than the timeout). Only the second counts in
    ``watchdog_trips_in_catch_up``, the count ``tests/test_driver_topics.py`` excuses; the
    first heard the whole silence (``host_silence_max_ms``)."""
    plant = plants("--seed", "1")
    c = Client(plant.link)
    c.send(Hello())
    c.pump(WAIT, until=lambda: any(isinstance(m, HelloAck) for m in c.others))
    cmd = Command(1, Mode.CURRENT, 0.5, (0.0, 0.0, 0.0))
    c.pump(0.5, keepalive=cmd)
    c.pump(0.5)  # the host's silence: a trip while the plant runs
    c.pump(0.5, keepalive=cmd)
    plant.signal(signal.SIGSTOP)  # the plant's own stall, the host keeps sending
    try:
        c.pump(0.5, keepalive=cmd)
    finally:
        plant.signal(signal.SIGCONT)
    c.pump(0.5, keepalive=cmd)
    c.close()
    stats = plant.stop()
    assert stats["watchdog_trips"] == 2, stats
    assert stats["watchdog_trips_in_catch_up"] == 1, stats
    assert stats["max_burst"] >= 180, stats
    assert 180 <= stats["host_silence_max_ms"] <= 260, stats
