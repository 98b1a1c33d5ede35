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
from collections.abc import Callable, Sequence
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


def _read_all(fd: int) -> bytes:
    chunks = []
    while True:
        b = os.read(fd, 1 << 20)
        if not b:
            break
        chunks.append(b)
    os.close(fd)
    return b"".join(chunks)


def _fork_children(fn: Callable[[T], R], items: Sequence[T], parts: Sequence[list[int]]
                   ) -> list[tuple[int, int, list[int]]]:
    """Fork one child per part; each computes ``fn`` on its items and writes the pickled
    results into its pipe. Returns ``(pid, read end, part)`` per child."""
    global _in_worker
    children: list[tuple[int, int, list[int]]] = []
    for part in parts:
        r, wfd = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: compute its share, hand it back, leave without cleanup
            _in_worker = True
            os.close(r)
            code = 0
            try:
                out: list[tuple[bool, object]] = []
                for i in part:
                    try:
                        out.append((True, fn(items[i])))
                    except Exception as exc:  # handed to the parent, raised there
                        exc.add_note("in a worker process:\n" + traceback.format_exc())
                        out.append((False, exc))
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
        children.append((pid, r, part))
    return children


def fork_map(fn: Callable[[T], R], items: Sequence[T], n_workers: int | None = None
             ) -> list[R]:
    """``[fn(x) for x in items]``, the items shared round robin between this process and
    forked children (module docstring). ``n_workers`` overrides :func:`workers`.

    Raises:
        Exception: the first exception ``fn`` raised, in item order.
        FitError: a child ended without handing back its results.
    """
    items = list(items)
    w = min(workers() if n_workers is None else max(1, int(n_workers)), len(items))
    if w <= 1:
        return [fn(x) for x in items]
    parts = _share(len(items), w)
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
        for pid, r, part in children:
            data = _read_all(r)
            os.waitpid(pid, 0)
            try:
                got = pickle.loads(data) if data else []
            except Exception:  # a truncated result is a lost worker
                got = []
            for i, res in zip(part, got, strict=False):
                results[i] = res
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
