"""Independent pieces of an identification on both cores: forked worker processes.

:func:`fork_map` is ``[fn(x) for x in items]`` with the items shared between this process and
``workers() - 1`` forked children (``os.fork``: a child starts with this process's memory, data
and compiled kernels included, so nothing is sent to it; only each result comes back, pickled
through a pipe). The order of the results, and so every decision taken from them, is that of
the serial loop; only the wall time changes. The simulation kernels and numpy release the GIL,
but the identifier's Python code between them holds it for half the time, so threads would not
use the second core; processes do.

``workers()`` is the ``DVT_IDENTIFY_WORKERS`` environment variable when set (``1``: serial),
else ``min(2, cpus)``; a worker never forks again (nested maps run serially in it), and a process
with other Python threads running (a ROS node's executor and worker threads) runs serially: a
forked child inherits a lock another thread held, held forever. A process
that runs several identifications side by side (a batch of bags on several workers) sets
``DVT_IDENTIFY_WORKERS=1`` so that the cores are not shared twice over.

A child that raises hands its exception back and :func:`fork_map` raises it in the parent
(the first failing item in order); a child that dies without a result (killed, out of memory)
is a :class:`~dvt_identify.errors.FitError` naming the items it held.
"""

from __future__ import annotations

import gc
import os
import pickle
import threading
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TypeVar

from dvt_identify.errors import FitError

T = TypeVar("T")
R = TypeVar("R")

ENV = "DVT_IDENTIFY_WORKERS"
"""Environment variable: worker processes of :func:`fork_map` (1: serial)."""
MAX_WORKERS = 2
"""Default ceiling on the workers (the machines this runs on have two cores)."""

_in_worker = False


def workers() -> int:
    """Processes :func:`fork_map` spreads over (this one included): ``DVT_IDENTIFY_WORKERS``,
    else ``min(2, cpus)``; 1 inside a worker, where ``os.fork`` does not exist, or while other
    Python threads run.

    Raises:
        FitError: ``DVT_IDENTIFY_WORKERS`` is not an integer >= 1 (naming its value).
    """
    raw = os.environ.get(ENV, "").strip()
    n = max(1, min(MAX_WORKERS, os.cpu_count() or 1))
    if raw:
        try:
            n = int(raw)
        except ValueError:
            n = 0
        if n < 1:
            raise FitError(f"{ENV}: expected an integer >= 1, got {raw!r}")
    if _in_worker or not hasattr(os, "fork") or threading.active_count() > 1:
        return 1
    return n


def _share(n_items: int, n_parts: int) -> list[list[int]]:
    """Item indices of each part, round robin (part 0 stays in this process)."""
    return [list(range(k, n_items, n_parts)) for k in range(n_parts)]


_INDEX = 4
"""Bytes of one item index in the work queue's pipe (:class:`_Queue`)."""


class _Queue:
    """Item indices handed out one at a time to whichever process asks first: written into
    a pipe before the forks, its write end closed, each process reading one index of
    :data:`_INDEX` bytes per item (a pipe read of a few bytes is atomic between the processes
    sharing it) until the pipe is empty. Used with costs (:func:`fork_map`): the items go out
    costliest first, so a heavy item never waits behind light ones for a busy process."""

    def __init__(self, order: Sequence[int]) -> None:
        if len(order) * _INDEX > 60000:  # below a pipe's 64 KiB buffer: written at once
            raise ValueError(f"{len(order)} items: too many for one work queue")
        self.fd, wfd = os.pipe()
        os.write(wfd, b"".join(int(i).to_bytes(_INDEX, "little") for i in order))
        os.close(wfd)

    def __iter__(self) -> Iterator[int]:
        while True:
            b = os.read(self.fd, _INDEX)
            if len(b) < _INDEX:
                return
            yield int.from_bytes(b, "little")

    def close(self) -> None:
        os.close(self.fd)


def _read_all(fd: int) -> bytes:
    chunks = []
    while True:
        b = os.read(fd, 1 << 20)
        if not b:
            break
        chunks.append(b)
    os.close(fd)
    return b"".join(chunks)


def _fork_children(fn: Callable[[T], R], items: Sequence[T],
                   parts: Sequence[Iterable[int]]) -> list[tuple[int, int]]:
    """Fork one child per part (a list of indices, or the shared :class:`_Queue`); each
    computes ``fn`` on its items and writes the pickled ``(index, ok, result)`` into its pipe.
    Returns ``(pid, read end)`` per child."""
    global _in_worker
    children: list[tuple[int, int]] = []
    for part in parts:
        r, wfd = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: compute its share, hand it back, leave without cleanup
            _in_worker = True
            os.close(r)
            code = 0
            try:
                out: list[tuple[int, bool, object]] = []
                for i in part:
                    try:
                        out.append((i, True, fn(items[i])))
                    except Exception as exc:  # handed to the parent, raised there
                        exc.add_note("in a worker process:\n" + traceback.format_exc())
                        out.append((i, False, exc))
                        break
                data = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
                view = memoryview(data)
                while view:
                    view = view[os.write(wfd, view):]
            except BaseException:  # nothing may escape a forked child
                code = 1
            finally:
                os._exit(code)
        os.close(wfd)
        children.append((pid, r))
    return children


def fork_map(fn: Callable[[T], R], items: Sequence[T], n_workers: int | None = None,
             costs: Sequence[float] | None = None) -> list[R]:
    """``[fn(x) for x in items]``, the items shared between this process and forked children
    (module docstring): round robin, or with ``costs`` (an estimate per item, any unit) taken
    one at a time from a shared queue, costliest first (:class:`_Queue`): the processes end
    together even when the estimates are rough. ``n_workers`` overrides :func:`workers`.

    Raises:
        Exception: the first exception ``fn`` raised, in item order.
        FitError: a child ended without handing back its results.
    """
    items = list(items)
    w = min(workers() if n_workers is None else max(1, int(n_workers)), len(items))
    if w <= 1:
        return [fn(x) for x in items]
    queue: _Queue | None = None
    if costs is not None:
        if len(costs) != len(items):
            raise ValueError(f"costs: expected {len(items)} values, got {len(costs)}")
        queue = _Queue(sorted(range(len(items)), key=lambda j: (-float(costs[j]), j)))
        parts: list[Iterable[int]] = [queue] * w
    else:
        parts = list(_share(len(items), w))
    # what this process holds is frozen out of the collector before the forks: a child never
    # finalises an object it inherited (a collected leftover of a C library, e.g. a ROS
    # context from an earlier test, segfaulted a forked child in its destructor)
    gc.freeze()
    try:
        children = _fork_children(fn, items, parts[1:])
    finally:
        gc.unfreeze()
    results: dict[int, tuple[bool, object]] = {}
    try:
        for i in parts[0]:
            try:
                results[i] = (True, fn(items[i]))
            except Exception as exc:  # raised below, in item order
                results[i] = (False, exc)
                break
    finally:
        for pid, r in children:
            data = _read_all(r)
            os.waitpid(pid, 0)
            try:
                got = pickle.loads(data) if data else []
            except Exception:  # a truncated result is a lost worker
                got = []
            for i, ok, val in got:
                results[i] = (ok, val)
        if queue is not None:
            queue.close()
    out_all: list[R] = []
    for i in range(len(items)):
        if i not in results:
            raise FitError(f"a worker process ended without the result of item {i} of "
                           f"{len(items)} (killed, or out of memory)")
        ok, val = results[i]
        if not ok and isinstance(val, BaseException):
            raise val
        out_all.append(val)  # type: ignore[arg-type]
    return out_all
