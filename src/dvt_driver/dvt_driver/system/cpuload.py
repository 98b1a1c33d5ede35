"""Who used the CPU during a benchmark run: the chain's processes and everything else (pure, no
rclpy; Linux ``/proc``).

:class:`CpuSampler` reads every process's CPU time (``/proc/<pid>/stat``, user + system) at the
start and the end of a run (and every ``period`` seconds between, so that processes that come
and go are counted) and splits it into the processes descended from ``root`` (the launcher:
the chain and the refit process) and the others (other jobs on a shared machine, whose load the
timing figures suffer from). A benchmark, not a control: it changes nothing.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["CpuSampler"]

_TICK = os.sysconf("SC_CLK_TCK")


@dataclass
class _Proc:
    ppid: int
    cpu_s: float
    label: str
    nice: int
    sched: str = ""

    @property
    def priority(self) -> str:
        """``nice N``, or the real-time policy and priority (``rr 10``)."""
        return self.sched or f"nice {self.nice}"


_POLICIES = {1: "fifo", 2: "rr", 5: "idle"}


def _label(pid: int) -> str:
    """A short name: the console script or ``-m`` module of a Python process (with its first
    argument), else the program."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    words = [a.decode(errors="replace") for a in argv if a]
    if not words:
        return "?"
    if Path(words[0]).name.startswith("python"):
        words = words[1:] or ["python"]
        if words[0] in ("-m", "-c") and len(words) > 1:
            return f"python {words[0]} {words[1][:40]}"
    name = Path(words[0]).name
    arg = next((w for w in words[1:] if not w.startswith("-")), "")
    return f"{name} {Path(arg).name}".strip()[:60] if name.startswith(("pytest", "python")) \
        else name[:60]


def _snapshot() -> dict[int, _Proc]:
    out: dict[int, _Proc] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        pid = int(entry.name)
        policy = int(fields[38]) if len(fields) > 38 else 0
        sched = (f"{_POLICIES.get(policy, policy)} {fields[37]}" if policy in (1, 2)
                 else _POLICIES.get(policy, ""))
        out[pid] = _Proc(ppid=int(fields[1]), cpu_s=(int(fields[11]) + int(fields[12])) / _TICK,
                         label="", nice=int(fields[16]), sched=str(sched))
    return out


class CpuSampler:
    """CPU time of ``root``'s descendants and of the other processes between :meth:`start`
    and :meth:`stop` (see the module docstring).

    Args:
        root: the pid whose process tree is "the chain" (set it with :meth:`set_root` once
            known).
        period: seconds between samples.
    """

    def __init__(self, root: int | None = None, period: float = 2.0) -> None:
        self.root = root
        self.period = period
        self._first: dict[int, _Proc] = {}
        self._last: dict[int, _Proc] = {}
        self._chain: set[int] = set()
        self._labels: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = 0.0
        self._t1 = 0.0
        self._load0 = 0.0
        self.figures: dict[str, Any] = {}
        """What :meth:`stop` returned (the caller keeps it here)."""

    def set_root(self, root: int) -> None:
        """The pid whose descendants are the chain."""
        self.root = root

    def start(self) -> None:
        """Take the first sample and keep sampling in a daemon thread."""
        self._t0 = time.monotonic()
        self._load0 = os.getloadavg()[0]
        self._first = _snapshot()
        self._last = dict(self._first)
        self._thread = threading.Thread(target=self._run, daemon=True, name="dvt-cpu-sampler")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._sample()

    def _sample(self) -> None:
        now = _snapshot()
        for pid, p in now.items():
            self._first.setdefault(pid, _Proc(p.ppid, 0.0, "", p.nice, p.sched))
            if pid not in self._labels:
                self._labels[pid] = _label(pid)
        self._last.update(now)
        if self.root is not None:
            tree = {self.root}
            grew = True
            while grew:
                grew = False
                for pid, p in now.items():
                    if p.ppid in tree and pid not in tree:
                        tree.add(pid)
                        grew = True
            self._chain |= tree

    def stop(self) -> dict[str, Any]:
        """Stop sampling; the figures: ``seconds``, ``load_average_1min`` at the start and the
        end, ``chain_cpu_percent`` (per process label of the chain, 100 = one core, with its
        priority: ``nice N`` or ``rr P``), ``others_cpu_percent`` (all other processes
        together) and ``others_top`` (the five busiest other processes: label, CPU %,
        priority)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with contextlib.suppress(Exception):
            self._sample()
        self._t1 = time.monotonic()
        wall = max(self._t1 - self._t0, 1e-9)
        me = os.getpid()
        chain: dict[str, list[float]] = {}
        others: list[tuple[float, str, str]] = []
        total_others = 0.0
        for pid, last in self._last.items():
            first = self._first.get(pid)
            used = last.cpu_s - (first.cpu_s if first is not None else 0.0)
            if used <= 0.0 or pid == me:
                continue
            label = self._labels.get(pid) or "?"
            if pid in self._chain:
                entry = chain.setdefault(f"{label} ({last.priority})", [0.0])
                entry[0] += used
            else:
                total_others += used
                others.append((used, label, last.priority))
        others.sort(reverse=True)
        return {"seconds": round(wall, 1),
                "load_average_1min": {"start": round(self._load0, 2),
                                      "end": round(os.getloadavg()[0], 2)},
                "chain_cpu_percent": {k: round(100.0 * v[0] / wall, 1)
                                      for k, v in sorted(chain.items(),
                                                         key=lambda kv: -kv[1][0])},
                "others_cpu_percent": round(100.0 * total_others / wall, 1),
                "others_top": [{"process": lab, "cpu_percent": round(100.0 * u / wall, 1),
                                "priority": pr} for u, lab, pr in others[:5]]}
