"""Child processes of the launcher and the benchmarks: start, watch, stop (pure: no rclpy).

:class:`Children` starts console scripts as children (each in its own session, dying with the
parent, output to ``<log dir>/<name>.log``), polls readiness with a deadline
(:meth:`Children.wait_until`: a dead child, a timeout or a signal ends the wait) and stops them
in order (:meth:`Children.stop_all`: the experiment first, then the others in reverse start
order, each with SIGINT, a bounded wait and a SIGKILL fallback; a second signal shortens the
waits). :func:`script` finds the venv's console scripts (see ROS2_ON_PIP.md); :func:`ready_line`
reads the address a child prints after ``READY`` (``dvt-plant``, ``dvt-foxglove``).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from dvt_driver.errors import LaunchError, LaunchInterruptedError
from dvt_driver.signals import StopFlag

__all__ = ["BIN", "SINGLE_THREAD_BLAS", "STOP_TIMEOUT", "Child", "Children", "ready_line", "script"]

BIN = Path(sys.executable).parent
"""Where the venv's console scripts are (next to this interpreter)."""
SINGLE_THREAD_BLAS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
"""Set in every child's environment: the nodes do linear algebra on 2x2..5x5 matrices, where
BLAS worker threads only add synchronisation; on a busy 2-core machine a threaded
``scipy.linalg.expm`` of a 4x4 matrix took 1.5-4 ms instead of 0.03 ms and made the 1 kHz plant
fall behind."""
STOP_TIMEOUT = {"experiment": 10.0, "recorder": 30.0, "ring": 30.0, "model": 10.0,
                "driver": 10.0, "plant": 10.0, "foxglove": 10.0, "discovery": 5.0,
                "identify": 15.0}
"""Longest wait for each child (by name) to exit after SIGINT before SIGKILL [s]; 10 s for a
name not listed. A recorder closes its bag in that time."""
_PR_SET_PDEATHSIG = 1


def script(name: str) -> str:
    """The venv's console script ``name`` (next to this interpreter), else from ``PATH``.

    Raises:
        LaunchError: found in neither place.
    """
    path = BIN / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    if found is None:
        raise LaunchError(f"console script {name!r} not found in {BIN} or on PATH "
                          "(is the package installed in this venv?)")
    return found


def ready_line(log: Path) -> str | None:
    """The text after ``READY`` in a child's log (its first ``READY ...`` line), ``None`` until
    it is printed."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("READY "):
            return line.split(None, 1)[1].strip()
    return None


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


@dataclass
class Child:
    """A started child process and its log."""

    name: str
    argv: list[str]
    proc: subprocess.Popen[bytes]
    log: Path
    killed: bool = False

    def alive(self) -> bool:
        """Whether the process is still running."""
        return self.proc.poll() is None

    def tail(self, n: int = 4000) -> str:
        """The last ``n`` characters of the child's output."""
        try:
            return self.log.read_text(errors="replace")[-n:]
        except OSError:
            return ""


class Children:
    """Starts children (own session, die with the parent, output to a log) and stops them.

    Args:
        logdir: where ``<name>.log`` of each child goes.
        env: the children's environment.
        stop: the process's stop flag (a signal ends every wait).
        echo: where to print ``dvt-launch: started ...`` lines (``None``: nowhere).
        stop_timeouts: child name -> longest wait after SIGINT before SIGKILL [s] (default
            :data:`STOP_TIMEOUT`; 10 s for a name not listed).
    """

    def __init__(self, logdir: Path, env: dict[str, str], stop: StopFlag,
                 echo: TextIO | None = None,
                 stop_timeouts: Mapping[str, float] | None = None) -> None:
        self.logdir = logdir
        self.env = env
        self.stop = stop
        self.echo = echo
        self.stop_timeouts = dict(STOP_TIMEOUT if stop_timeouts is None else stop_timeouts)
        self.children: list[Child] = []

    def start(self, name: str, argv: Sequence[str], env: dict[str, str] | None = None
              ) -> Child:
        """Start ``argv`` as child ``name``; output goes to ``<logdir>/<name>.log``."""
        log = self.logdir / f"{name}.log"
        with log.open("wb") as fh:
            proc = subprocess.Popen(list(argv), env=self.env if env is None else env, stdout=fh,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, preexec_fn=_die_with_parent)
        child = Child(name, list(argv), proc, log)
        self.children.append(child)
        self._say(f"started {name} (pid {proc.pid}): {shlex.join(argv)}")
        return child

    def _say(self, text: str) -> None:
        if self.echo is not None:
            print(f"dvt-launch: {text}", file=self.echo, flush=True)

    def check_alive(self) -> None:
        """Raise :class:`LaunchError` if a child (other than a finished experiment) died."""
        for c in self.children:
            if c.name != "experiment" and not c.alive():
                raise LaunchError(f"{c.name} exited with status {c.proc.returncode}; its "
                                  f"output ({c.log}):\n{c.tail()}")

    def wait_until(self, what: str, predicate: Callable[[], Any], timeout: float) -> Any:
        """Poll ``predicate`` until truthy; raises on timeout, a dead child or a signal."""
        deadline = time.monotonic() + timeout
        while True:
            if self.stop:
                raise LaunchInterruptedError(f"interrupted while waiting for {what}")
            self.check_alive()
            value = predicate()
            if value:
                return value
            if time.monotonic() > deadline:
                raise LaunchError(f"timed out after {timeout:g} s waiting for {what}")
            time.sleep(0.05)

    def stop_one(self, child: Child, timeout: float) -> int | None:
        """SIGINT, wait up to ``timeout`` s, then SIGKILL; returns the exit status."""
        if child.alive():
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.proc.pid, signal.SIGINT)
            deadline = time.monotonic() + timeout
            while child.alive() and time.monotonic() < deadline:
                if self.stop.hurry:
                    deadline = min(deadline, time.monotonic() + 1.0)
                time.sleep(0.02)
            if child.alive():
                self._say(f"{child.name} did not exit within {timeout:g} s; killing it")
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child.proc.pid, signal.SIGKILL)
                child.killed = True
                with contextlib.suppress(subprocess.TimeoutExpired):
                    child.proc.wait(timeout=5.0)
        # the process group may hold grandchildren: make sure none survives
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child.proc.pid, 0)
            os.killpg(child.proc.pid, signal.SIGKILL)
        return child.proc.returncode

    def stop_all(self) -> dict[str, int | None]:
        """Stop every child, the experiment first (it stops the motor), then the others in
        reverse start order; returns their exit statuses."""
        out: dict[str, int | None] = {}
        order = sorted(reversed(self.children), key=lambda c: c.name != "experiment")
        for child in order:
            rc = self.stop_one(child, self.stop_timeouts.get(child.name, 10.0))
            out[child.name] = rc
            self._say(f"stopped {child.name} (status {rc}{', killed' if child.killed else ''})")
        return out
