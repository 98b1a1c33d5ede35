"""``dvt-plant``: the simulated DVT controller on a pseudo-terminal, in real time.

The process *is* the motor/brake controller for tests and the demo. It opens a pty pair
(``os.openpty``, raw mode), publishes the slave device under a symlink (``--link``, default
``/tmp/dvt-plant-<pid>``), keeps the slave open so clients may close and reopen it, and speaks
the binary protocol (``docs/protocol.md``) on the master while :class:`PlantSim` runs the
transmission physics in real time:

* samples are produced on an absolute-deadline schedule (``start + t_us``; no drift). If the
  process falls behind (scheduling, a stop signal) it still produces every sample, with the
  correct sequence numbers and clock, as fast as it can until it has caught up;
* the pty does not throttle, so the plant paces its output to the line: a frame is handed to
  the pty when a real ``--baud`` 8N1 line would start sending it (10 bits per byte). Frames
  wait in a transmit buffer of ``--tx-buffer`` bytes (default 64 KiB, 0.7 s of line time: it
  absorbs the burst after a scheduling stall of the plant itself); a sample that does not fit
  is dropped (``tx_overruns``, visible to the host as a sequence gap), as a UART's buffer
  overflows on a line too slow for the sample rate. The line has no flow control: when no
  client reads and the pty buffer is full, frames are lost on the host side
  (``host_overruns``); a client that opens the port flushes the stale bytes
  (``SerialLink.open`` does);
* samples stream after the first accepted HELLO, until a controller reset.

``--protocol-version 1`` makes it an old controller (speeds only: it NACKs HELLO(2), answers
HELLO(1), sends SAMPLE frames without counts); the default speaks versions 1 and 2.
``--load none|arm|arm-payload|<load.yaml>`` puts a declared joint load on carrier 3
(:mod:`dvt_model.load`; written into ``truth.yaml`` under ``plant.load``). A ``--hidden``
preset's distributions (magnitudes, reductions, orders) are drawn from ``--seed`` (a random
draw without it; :mod:`dvt_driver.plant.hidden.draw`), the values and the draw written into
``truth.yaml`` (``hidden``, ``hidden_draw``); ``--hidden-fixed`` takes the preset's nominal plant.

Fault injection (for tests), on SAMPLE frames only so that a session can always be
established: ``--fault-corrupt P`` flips one byte of a frame (never into 0x00) with probability
``P`` per frame, ``--fault-drop P`` deletes one byte of a frame (never the delimiter),
``--fault-garbage P`` inserts a burst of 1-16 random non-zero bytes and a delimiter before a
frame (a bad frame for the host, the sample itself intact). A frame is either corrupted or
loses a byte, never both, so the host sees exactly ``corrupted + dropped + garbage`` bad frames
and ``corrupted + dropped`` lost samples.

``--fault-disconnect-at S`` (or ``SIGUSR1`` at any time) pulls the cable: the pty pair is closed
(the client's next read fails), the symlink disappears for ``--fault-disconnect-for`` seconds,
then a new pty pair is opened and the symlink points at the new slave. The controller keeps
running (session, sequence and clock continue; samples produced meanwhile are lost).
``--fault-reset-at S`` (or ``SIGUSR2``) restarts the controller: sequence number and clock
restart at 0, outputs off, the session is closed until the next HELLO.

A changing plant (:mod:`dvt_driver.plant.hidden`, ``changes``): a schedule in the ``--hidden``
preset or file, plus ``--change-at T:SPEC`` (repeatable: at plant time ``T`` [s after start]
the changes of ``SPEC``, a preset or hidden-effects YAML; a preset without ``changes`` such as
``coulomb`` is a step to its friction, :func:`~dvt_driver.plant.hidden.changes_from_spec`),
and at runtime ``SIGHUP``, which reads ``--change-file PATH`` (one change as YAML, the keys of a
``changes`` entry without ``at``: ``coulomb``, ``windage``, ``damping_scale``, ``load``,
``ramp``, ``note``) and applies it now; an unreadable or invalid file is reported on stderr and
changes nothing. Every change the plant starts is printed on stderr (``dvt-plant: change at
plant time ...``) and written into ``--truth-out`` at once (``changes_applied``: ``at_s`` plant
time, ``unix_s`` host wall-clock time of the sample at which it took effect, the change).

On start it prints ``READY <link path>`` (flushed) on stdout; on SIGINT/SIGTERM it stops, removes
its symlink and prints ``STATS <json>`` (counters, CPU use) on stdout, then exits 0.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import select
import signal
import sys
import time
import tty
from collections import deque
from pathlib import Path
from types import FrameType as PyFrame
from typing import Any

import numpy as np
import yaml

from dvt_driver.errors import DvtDriverError
from dvt_driver.link.protocol import (
    DEFAULT_BAUD,
    PROTOCOL_VERSION,
    SUPPORTED_VERSIONS,
    FrameDecoder,
    Message,
    encode,
)
from dvt_driver.plant.core import (
    DEFAULT_SAMPLE_PERIOD_US,
    PlantSim,
    SafetyLimits,
)
from dvt_driver.plant.hidden import (
    Change,
    changes_from_spec,
    load_hidden,
    parse_change,
    random_draw,
)
from dvt_model.errors import DvtModelError
from dvt_model.load import available_loads, load_joint_load
from dvt_model.params import load_parameters
from dvt_model.presets import safe_load

__all__ = ["FaultInjector", "PlantServer", "PtyPort", "build_parser", "main"]

_READ_CHUNK = 4096
_MAX_CATCH_UP = 200  # samples produced in one go before the loop serves I/O again
_OWN_STALL = 0.9
"""A watchdog trip counts in ``watchdog_trips_in_catch_up`` (the plant's own) unless the plant
had been reading the line and finding no command for at least this share of the watchdog
timeout: a command is stamped with the controller clock when the plant reads it, so a plant
that was behind its schedule then, or that stopped reading (a stall, a catch-up burst), ages
the command by time in which the host may well have sent more. ``host_silence_max_ms`` is the
longest such reading-and-finding-nothing before a trip."""


class PtyPort:
    """A pseudo-terminal pair whose slave is published under a symlink.

    Args:
        link: symlink path to (re)point at the slave device.
    """

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master: int | None = None
        self.slave: int | None = None
        self.slave_name = ""

    @property
    def is_open(self) -> bool:
        """Whether a pty pair is open."""
        return self.master is not None

    def open(self) -> None:
        """Open a new pty pair (raw mode, non-blocking master) and point the symlink at it.

        Raises:
            OSError: no pty available, or ``link`` exists and is not a symlink (never replaced).
        """
        if self.link.exists() and not self.link.is_symlink():
            raise FileExistsError(f"{self.link} exists and is not a symlink; not replacing it")
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        self.slave_name = os.ttyname(slave)
        tmp = self.link.with_name(self.link.name + ".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(self.slave_name)
        os.replace(tmp, self.link)

    def close(self, *, unlink: bool = True) -> None:
        """Close the pair (clients see the device vanish); remove the symlink if ours."""
        if unlink:
            with contextlib.suppress(OSError):
                if self.link.is_symlink() and os.readlink(self.link) == self.slave_name:
                    self.link.unlink()
        for fd in (self.master, self.slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = None


class FaultInjector:
    """Damages outgoing SAMPLE frames with given probabilities (see the module docstring).

    Args:
        corrupt, drop, garbage: probabilities per frame, 0..1.
        seed: random seed (``None``: random).
    """

    def __init__(self, corrupt: float = 0.0, drop: float = 0.0, garbage: float = 0.0,
                 seed: int | None = None) -> None:
        for name, p in (("corrupt", corrupt), ("drop", drop), ("garbage", garbage)):
            if not (math.isfinite(p) and 0.0 <= p <= 1.0):
                raise DvtDriverError(f"--fault-{name}: expected a probability 0..1, got {p!r}")
        self.p_corrupt, self.p_drop, self.p_garbage = corrupt, drop, garbage
        self.rng = np.random.default_rng(seed)
        self.corrupted = 0
        self.dropped = 0
        self.garbage = 0

    @property
    def active(self) -> bool:
        """Whether any fault is enabled."""
        return self.p_corrupt > 0.0 or self.p_drop > 0.0 or self.p_garbage > 0.0

    def apply(self, frame: bytes) -> bytes:
        """``frame`` (with its delimiter), possibly damaged."""
        rng = self.rng
        out = bytearray(frame)
        if self.p_corrupt > 0.0 and rng.random() < self.p_corrupt:
            i = int(rng.integers(0, len(out) - 1))
            flip = int(rng.integers(1, 256))
            if out[i] ^ flip == 0:
                flip ^= 0x01
            out[i] ^= flip
            self.corrupted += 1
        elif self.p_drop > 0.0 and rng.random() < self.p_drop:
            del out[int(rng.integers(0, len(out) - 1))]
            self.dropped += 1
        if self.p_garbage > 0.0 and rng.random() < self.p_garbage:
            n = int(rng.integers(1, 17))
            junk = bytes(rng.integers(1, 256, size=n, dtype=np.uint8).tolist())
            out[0:0] = junk + b"\x00"
            self.garbage += 1
        return bytes(out)


class PlantServer:
    """Serves a :class:`PlantSim` on a :class:`PtyPort` in real time (see the module docstring).

    Args:
        sim: the simulated controller + transmission.
        port: the pty (opened by :meth:`run`).
        baud: line rate to pace the output to [bit/s].
        faults: fault injector for SAMPLE frames.
        tx_buffer: transmit buffer [bytes].
        truth_out: where to write ``truth.yaml`` (``None``: nowhere).
        disconnect_at, reset_at: scheduled faults [s after start] (``None``: never).
        disconnect_for: how long the device stays away on a disconnect [s].
        duration: stop after this long [s] (``None``: until a signal).
        change_file: the change applied on :meth:`request_change` (SIGHUP), or ``None``.
    """

    def __init__(self, sim: PlantSim, port: PtyPort, *, baud: int = DEFAULT_BAUD,
                 faults: FaultInjector | None = None, tx_buffer: int = 65536,
                 truth_out: Path | None = None, disconnect_at: float | None = None,
                 disconnect_for: float = 0.2, reset_at: float | None = None,
                 duration: float | None = None, change_file: Path | None = None) -> None:
        self.sim = sim
        self.port = port
        self.bytes_per_s = baud / 10.0
        self.faults = faults if faults is not None else FaultInjector()
        self.tx_buffer = tx_buffer
        self.truth_out = truth_out
        self.disconnect_at = disconnect_at
        self.disconnect_for = disconnect_for
        self.reset_at = reset_at
        self.duration = duration
        self.change_file = change_file
        self._want_change = False
        self._n_applied = 0
        self.decoder = FrameDecoder(synced=False)
        self._tx: deque[tuple[float, bytes]] = deque()  # (line start time, frame)
        self._line_end = 0.0  # when the emulated line finishes the last queued frame
        self._stop = False
        self._want_disconnect = False
        self._want_reset = False
        self._port_back_at: float | None = None
        self._written_period = -1
        self.counters: dict[str, int] = {
            "samples_produced": 0, "samples_sent": 0, "samples_lost_offline": 0,
            "tx_overruns": 0, "host_overruns": 0, "frames_received": 0, "replies_sent": 0,
            "disconnects": 0, "resets": 0, "max_burst": 0, "late_samples": 0,
            "watchdog_trips_in_catch_up": 0, "host_silence_max_ms": 0,
            "changes_applied": 0, "change_requests_refused": 0,
        }

    # ---------------------------------------------------------------- control from outside
    def request_stop(self) -> None:
        """Stop the loop at its next iteration (signal-safe)."""
        self._stop = True

    def request_disconnect(self) -> None:
        """Pull the cable at the next iteration (signal-safe)."""
        self._want_disconnect = True

    def request_reset(self) -> None:
        """Restart the controller at the next iteration (signal-safe)."""
        self._want_reset = True

    def request_change(self) -> None:
        """Apply the change of ``change_file`` at the next iteration (signal-safe)."""
        self._want_change = True

    # ---------------------------------------------------------------- helpers
    def _read_change(self) -> None:
        """Read ``change_file`` and add its change at the present plant time."""
        if self.change_file is None:
            print("dvt-plant: SIGHUP ignored: no --change-file given", file=sys.stderr,
                  flush=True)
            self.counters["change_requests_refused"] += 1
            return
        where = str(self.change_file)
        try:
            data = safe_load(self.change_file.read_text(encoding="utf-8"))
            if isinstance(data, dict) and "at" in data:
                raise DvtDriverError(f"{where}.at: not allowed (a --change-file change applies "
                                     f"at once), got {data['at']!r}")
            change = parse_change(data, where, at=round(self.sim.physics_time, 6))
        except (OSError, yaml.YAMLError, DvtDriverError, DvtModelError) as exc:
            print(f"dvt-plant: change refused: {exc}", file=sys.stderr, flush=True)
            self.counters["change_requests_refused"] += 1
            return
        self.sim.add_change(change)

    def _note_changes(self, sample_wall: float) -> None:
        """Stamp newly applied changes with the wall-clock time and rewrite the truth."""
        applied = self.sim.changes_applied
        if len(applied) == self._n_applied:
            return
        for entry in applied[self._n_applied:]:
            entry["unix_s"] = round(sample_wall, 6)
            print(f"dvt-plant: change at plant time {entry['at_s']:.3f} s (unix "
                  f"{sample_wall:.3f}): {json.dumps(entry['change'])}", file=sys.stderr,
                  flush=True)
        self.counters["changes_applied"] += len(applied) - self._n_applied
        self._n_applied = len(applied)
        self._write_truth(force=True)

    def _write_truth(self, force: bool = False) -> None:
        if self.truth_out is None or (
                not force and self._written_period == self.sim.sample_period_us):
            return
        self._written_period = self.sim.sample_period_us
        tmp = self.truth_out.with_name(self.truth_out.name + ".tmp")
        tmp.write_text(self.sim.truth_yaml(), encoding="utf-8")
        os.replace(tmp, self.truth_out)

    def _queue(self, frame: bytes, at: float, *, sample: bool) -> None:
        """Queue ``frame``, available at time ``at`` [monotonic s], on the emulated line.

        The line starts a frame at ``max(at, end of the previous frame)`` whatever the plant's
        own scheduling; a sample that would overflow the transmit buffer at ``at`` is dropped.
        """
        if not self.port.is_open:
            if sample:
                self.counters["samples_lost_offline"] += 1
            return
        backlog = max(0.0, self._line_end - at) * self.bytes_per_s  # bytes waiting at ``at``
        if sample and backlog + len(frame) > self.tx_buffer:
            self.counters["tx_overruns"] += 1
            return
        start = max(at, self._line_end)
        self._line_end = start + len(frame) / self.bytes_per_s
        self._tx.append((start, frame))
        if sample:
            self.counters["samples_sent"] += 1

    def _flush(self, now: float) -> None:
        """Hand every frame whose line start time has come to the pty."""
        master = self.port.master
        if master is None:
            self._tx.clear()
            return
        while self._tx and self._tx[0][0] <= now:
            _start, frame = self._tx.popleft()
            try:
                n = os.write(master, frame)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                print(f"dvt-plant: write failed: {exc}", file=sys.stderr, flush=True)
                continue
            if n < len(frame):
                # a serial line has no flow control: with the host's receive buffer (the pty)
                # full, the rest of the frame is lost on the host side
                self.counters["host_overruns"] += 1

    def _read(self) -> None:
        master = self.port.master
        if master is None:
            return
        while True:
            try:
                data = os.read(master, _READ_CHUNK)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open (cannot happen while we hold it)
                    return
                raise
            if not data:
                return
            for msg in self.decoder.feed(data):
                self._handle(msg)
            if len(data) < _READ_CHUNK:
                return

    def _handle(self, msg: Message) -> None:
        self.counters["frames_received"] += 1
        now = time.monotonic()
        for reply in self.sim.handle(msg):
            self._queue(encode(reply), now, sample=False)
            self.counters["replies_sent"] += 1
        self._write_truth()

    def _disconnect(self, now: float) -> None:
        self.counters["disconnects"] += 1
        print("dvt-plant: disconnect (pty closed)", file=sys.stderr, flush=True)
        self.port.close()
        self._tx.clear()
        self._port_back_at = now + max(0.0, self.disconnect_for)
        self.decoder.reset(synced=False)

    def _reconnect(self, now: float) -> None:
        try:
            self.port.open()
        except OSError as exc:
            print(f"dvt-plant: cannot reopen the pty: {exc}; retrying", file=sys.stderr,
                  flush=True)
            self._port_back_at = now + 0.5
            return
        self._port_back_at = None
        self._line_end = 0.0
        print(f"dvt-plant: reconnected on {self.port.slave_name}", file=sys.stderr, flush=True)

    # ---------------------------------------------------------------- main loop
    def run(self) -> dict[str, Any]:
        """Serve until stopped; returns the statistics (also printed by :func:`main`)."""
        sim = self.sim
        if not self.port.is_open:
            self.port.open()
        self._write_truth()
        print(f"READY {self.port.link}", flush=True)
        cpu0 = time.process_time()
        start = time.monotonic()
        anchor_wall, anchor_us = start, sim.t_us
        disconnect_at = self.disconnect_at
        reset_at = self.reset_at
        command_read_at = time.monotonic()  # [s] when the plant last read a command
        read_at = command_read_at  # [s] when it last read the line
        try:
            while not self._stop:
                now = time.monotonic()
                elapsed = now - start
                if self.duration is not None and elapsed >= self.duration:
                    break
                if disconnect_at is not None and elapsed >= disconnect_at:
                    disconnect_at = None
                    self._want_disconnect = True
                if reset_at is not None and elapsed >= reset_at:
                    reset_at = None
                    self._want_reset = True
                if self._want_disconnect:
                    self._want_disconnect = False
                    if self.port.is_open:
                        self._disconnect(now)
                if self._port_back_at is not None and now >= self._port_back_at:
                    self._reconnect(now)
                accepted = sim.commands_accepted
                self._read()
                read_at = now
                if sim.commands_accepted != accepted:
                    command_read_at = now
                # produce every due sample (absolute deadlines)
                deadline = anchor_wall + (sim.t_us - anchor_us) * 1e-6
                produced = 0
                while now >= deadline and produced < _MAX_CATCH_UP:
                    if self._want_reset:
                        self._want_reset = False
                        self.counters["resets"] += 1
                        print("dvt-plant: controller reset", file=sys.stderr, flush=True)
                        sim.reset_controller()
                        anchor_wall, anchor_us = deadline, sim.t_us
                    if self._want_change:
                        self._want_change = False
                        self._read_change()
                    streaming = sim.session_open
                    n_applied = len(sim.changes_applied)
                    trips = sim.watchdog_trips
                    values = sim.tick()
                    if sim.watchdog_trips != trips:
                        silence = read_at - command_read_at
                        self.counters["host_silence_max_ms"] = max(
                            self.counters["host_silence_max_ms"], round(silence * 1e3))
                        if silence < _OWN_STALL * sim.limits.watchdog_timeout:
                            # the plant did not listen long enough to hear the host's silence:
                            # it was behind or stalled, and catches up in a burst
                            self.counters["watchdog_trips_in_catch_up"] += 1
                    if len(sim.changes_applied) != n_applied:  # wall time of this sample
                        self._note_changes(time.time() - (time.monotonic() - deadline))
                    self.counters["samples_produced"] += 1
                    if streaming:
                        frame = encode(values.to_sample())
                        if self.faults.active:
                            frame = self.faults.apply(frame)
                        self._queue(frame, deadline, sample=True)
                    produced += 1
                    deadline = anchor_wall + (sim.t_us - anchor_us) * 1e-6
                if produced > 1:  # behind schedule: caught up with a burst
                    self.counters["late_samples"] += produced - 1
                    self.counters["max_burst"] = max(self.counters["max_burst"], produced)
                now = time.monotonic()
                self._flush(now)
                wake = deadline
                if self._tx:
                    wake = min(wake, self._tx[0][0])
                if self._port_back_at is not None:
                    wake = min(wake, self._port_back_at)
                timeout = max(0.0, wake - time.monotonic())
                master = self.port.master
                if master is not None:
                    select.select([master], [], [], timeout)
                elif timeout > 0.0:
                    time.sleep(timeout)
        finally:
            self.port.close()
        wall = time.monotonic() - start
        cpu = time.process_time() - cpu0
        stats: dict[str, Any] = dict(self.counters)
        stats.update({
            "corrupted": self.faults.corrupted, "dropped": self.faults.dropped,
            "garbage": self.faults.garbage, "frames_bad_in": self.decoder.frames_bad,
            "commands_accepted": sim.commands_accepted, "commands_refused": sim.commands_refused,
            "overspeed_trips": sim.trips, "watchdog_trips": sim.watchdog_trips,
            "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
            "cpu_fraction": round(cpu / wall, 4) if wall > 0 else 0.0,
            "substeps": sim.substeps, "sample_period_us": sim.sample_period_us,
        })
        return stats


# ---------------------------------------------------------------------------------------------
# command line


def build_parser() -> argparse.ArgumentParser:
    """The ``dvt-plant`` argument parser."""
    p = argparse.ArgumentParser(
        prog="dvt-plant",
        description="Simulated DVT motor/brake controller on a pseudo-terminal (real time).")
    p.add_argument("--link", type=Path, default=None,
                   help="symlink to create for the pty slave (default /tmp/dvt-plant-<pid>)")
    p.add_argument("--params", default="physical",
                   help="transmission parameter set: bundled name or YAML path (default physical)")
    p.add_argument("--hidden", default="none",
                   help="hidden effects: preset name (none, coulomb, stribeck, windage, backlash, "
                        "delay, wet_brake, gravity_arm, mesh_ripple, position_friction) or YAML "
                        "path (default none); a preset's distributions are drawn from --draw, "
                        "else --seed (a random draw without either), the draw written into "
                        "--truth-out")
    p.add_argument("--draw", type=int, default=None,
                   help="seed of the hidden magnitudes' draw, apart from --seed's noise: the "
                        "same actuator recorded twice takes one --draw and two --seed")
    p.add_argument("--hidden-fixed", action="store_true",
                   help="use the preset's fixed draw (each distribution's 'fixed' value, the "
                        "nominal plant) instead of drawing it from the seed")
    p.add_argument("--load", default="none",
                   help=f"declared joint load on carrier 3: {' | '.join(available_loads())} or a "
                        "load YAML path (dvt_model.load; default none)")
    p.add_argument("--protocol-version", type=int, default=PROTOCOL_VERSION,
                   choices=list(SUPPORTED_VERSIONS),
                   help=f"newest protocol version the controller speaks (default "
                        f"{PROTOCOL_VERSION}; 1 = an old controller: speeds only, no counts)")
    rate = p.add_mutually_exclusive_group()
    rate.add_argument("--rate", type=float, default=None, help="sample rate [Hz] (default 1000)")
    rate.add_argument("--period-us", type=int, default=None,
                      help="sample period [µs] (16000 = the thesis's 16 ms serial limit)")
    p.add_argument("--seed", type=int, default=None, help="random seed (sensor noise, faults)")
    p.add_argument("--truth-out", type=Path, default=None, help="write truth.yaml here")
    p.add_argument("--baud", type=int, default=DEFAULT_BAUD,
                   help=f"line rate to pace the output to [bit/s] (default {DEFAULT_BAUD})")
    p.add_argument("--tx-buffer", type=int, default=65536,
                   help="transmit buffer [bytes] (default 65536, 0.7 s of a 921600 baud line)")
    p.add_argument("--watchdog-ms", type=float, default=SafetyLimits().watchdog_timeout * 1e3,
                   help="command watchdog [ms], 0 = none (default 200)")
    p.add_argument("--max-step", type=float, default=0.001,
                   help="longest physics sub-step [s] (default 0.001)")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: run until SIGINT/SIGTERM)")
    p.add_argument("--fault-corrupt", type=float, default=0.0, metavar="P",
                   help="probability per SAMPLE frame of flipping a byte")
    p.add_argument("--fault-drop", type=float, default=0.0, metavar="P",
                   help="probability per SAMPLE frame of dropping a byte")
    p.add_argument("--fault-garbage", type=float, default=0.0, metavar="P",
                   help="probability per SAMPLE frame of a garbage burst before it")
    p.add_argument("--fault-disconnect-at", type=float, default=None, metavar="S",
                   help="close and reopen the pty S seconds after start (also: SIGUSR1)")
    p.add_argument("--fault-disconnect-for", type=float, default=0.2, metavar="S",
                   help="how long the device stays away on a disconnect [s] (default 0.2)")
    p.add_argument("--fault-reset-at", type=float, default=None, metavar="S",
                   help="controller reset S seconds after start (also: SIGUSR2)")
    p.add_argument("--change-at", action="append", default=[], metavar="T:SPEC",
                   help="at plant time T [s] apply the changes of SPEC (preset or hidden-effects "
                        "YAML; its 'changes' shifted to start at T, else a step to its "
                        "coulomb/windage/damping_scale); repeatable")
    p.add_argument("--change-file", type=Path, default=None, metavar="PATH",
                   help="on SIGHUP apply the change in this YAML file at once (keys of a "
                        "'changes' entry without 'at')")
    return p


def parse_change_at(text: str) -> list[Change]:
    """The changes of one ``--change-at T:SPEC`` (errors name the option and the value)."""
    t_text, sep, spec = text.partition(":")
    try:
        t = float(t_text)
    except ValueError:
        t = math.nan
    if not sep or not spec or not (math.isfinite(t) and t >= 0):
        raise DvtDriverError(f"--change-at: expected T:SPEC with T >= 0 s and SPEC a preset or "
                             f"YAML path, got {text!r}")
    try:
        return changes_from_spec(spec, t)
    except DvtDriverError as exc:
        raise DvtDriverError(f"--change-at {text}: {exc}") from exc


def _period_us(args: argparse.Namespace) -> int:
    if args.period_us is not None:
        return int(args.period_us)
    if args.rate is not None:
        if not (math.isfinite(args.rate) and args.rate > 0):
            raise DvtDriverError(f"--rate: expected a positive number of Hz, got {args.rate!r}")
        return round(1e6 / args.rate)
    return DEFAULT_SAMPLE_PERIOD_US


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``dvt-plant``; returns the exit status (0 ok, 2 bad arguments)."""
    args = build_parser().parse_args(argv)
    try:
        params = load_parameters(args.params)
        if args.hidden_fixed and args.draw is not None:
            raise DvtDriverError(f"--draw {args.draw} and --hidden-fixed: give one (a drawn "
                                 "plant or the preset's nominal one)")
        draw = None if args.hidden_fixed else (
            args.draw if args.draw is not None else
            args.seed if args.seed is not None else random_draw())
        hidden = load_hidden(args.hidden, draw=draw)
        extra_changes = [c for text in args.change_at for c in parse_change_at(text)]
        load = load_joint_load(args.load)
        if not (math.isfinite(args.watchdog_ms) and args.watchdog_ms >= 0):
            raise DvtDriverError(f"--watchdog-ms: expected a number >= 0, got {args.watchdog_ms!r}")
        if args.baud <= 0:
            raise DvtDriverError(f"--baud: expected a positive integer, got {args.baud!r}")
        if args.tx_buffer < 64:
            raise DvtDriverError(f"--tx-buffer: expected at least 64 bytes, got {args.tx_buffer!r}")
        for name in ("fault_disconnect_at", "fault_reset_at", "duration"):
            v = getattr(args, name)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise DvtDriverError(f"--{name.replace('_', '-')}: expected a number >= 0 s, "
                                     f"got {v!r}")
        limits = SafetyLimits(watchdog_timeout=args.watchdog_ms * 1e-3)
        sim = PlantSim(params, hidden, _period_us(args), args.seed, limits=limits,
                       max_step=args.max_step, baud=args.baud, load=load,
                       protocol_version=args.protocol_version)
        for change in extra_changes:
            sim.add_change(change)
        faults = FaultInjector(args.fault_corrupt, args.fault_drop, args.fault_garbage,
                               None if args.seed is None else args.seed + 1)
    except (DvtDriverError, DvtModelError) as exc:
        print(f"dvt-plant: {exc}", file=sys.stderr, flush=True)
        return 2
    link = args.link if args.link is not None else Path(f"/tmp/dvt-plant-{os.getpid()}")
    port = PtyPort(link)
    server = PlantServer(sim, port, baud=args.baud, faults=faults, tx_buffer=args.tx_buffer,
                         truth_out=args.truth_out, disconnect_at=args.fault_disconnect_at,
                         disconnect_for=args.fault_disconnect_for, reset_at=args.fault_reset_at,
                         duration=args.duration, change_file=args.change_file)

    def on_stop(signum: int, frame: PyFrame | None) -> None:
        server.request_stop()

    def on_usr1(signum: int, frame: PyFrame | None) -> None:
        server.request_disconnect()

    def on_usr2(signum: int, frame: PyFrame | None) -> None:
        server.request_reset()

    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGUSR1, on_usr1)
    signal.signal(signal.SIGUSR2, on_usr2)

    def on_hup(signum: int, frame: PyFrame | None) -> None:
        server.request_change()

    signal.signal(signal.SIGHUP, on_hup)
    try:
        port.open()
    except OSError as exc:
        print(f"dvt-plant: cannot create the pty or the link {link}: {exc}", file=sys.stderr,
              flush=True)
        return 2
    stats = server.run()
    with contextlib.suppress(BrokenPipeError):
        print("STATS " + json.dumps(stats, sort_keys=True), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
