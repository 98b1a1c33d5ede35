"""Shared fixtures for topic-level tests: real rclpy processes, isolated per test.

Every test gets its own ``ROS_DOMAIN_ID`` with localhost-only discovery; processes are
started from the venv's console scripts and always terminated (SIGINT, then SIGKILL) at
teardown; waits poll with a deadline instead of sleeping.

Nothing a test starts outlives it: every process started under a test's ROS environment carries
``DVT_TEST_ID`` (a tag unique to the test) in its environment, so its children and grandchildren
do too, also when a launcher dies before them and they are re-parented. After the test's own
teardown, :func:`ros_env` looks for live processes with that tag (``/proc/*/environ``), kills
them and fails the test naming them: a leftover node on a domain keeps loading the two shared
cores (and can answer another test's services) for the rest of the suite.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DOMAINS = 140
"""The tests' ``ROS_DOMAIN_ID`` range is 1..DOMAINS; the benchmarks' own graphs use 150 and up
(``dvt_model.bench``, ``dvt_driver.run.bench``), so a test never shares a domain with them."""
_domain = itertools.count((os.getpid() % 28) * 5)
_test_ids = itertools.count(1)
TAG = "DVT_TEST_ID"
"""Environment variable that marks every process a test starts (and their descendants)."""


def tagged(tag: str) -> list[tuple[int, str]]:
    """Live processes whose environment carries ``DVT_TEST_ID=tag``: (pid, command line).

    Reads ``/proc/<pid>/environ`` (own processes, or all as root); zombies (already exited,
    not yet reaped) have an empty environment and are not listed."""
    needle = f"{TAG}={tag}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            env = (entry / "environ").read_bytes().split(b"\0")
            if needle not in env:
                continue
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # gone meanwhile, or not ours to read
            continue
        found.append((int(entry.name), cmd.strip()))
    return found


def kill_tagged(tag: str, grace: float = 3.0) -> list[str]:
    """SIGKILL every live process tagged ``tag`` (:func:`tagged`) and wait up to ``grace``
    seconds for them to go; returns their command lines (empty: none outlived the test)."""
    left = tagged(tag)
    for pid, _ in left:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + grace
    while tagged(tag) and time.monotonic() < deadline:
        time.sleep(0.05)
    return [f"pid {pid}: {cmd[:200]}" for pid, cmd in left]


def script(name: str) -> str:
    """Absolute path of a console script installed in the venv."""
    path = BIN / name
    if not path.exists():
        found = shutil.which(name)
        if found is None:
            raise FileNotFoundError(f"console script {name!r} not found in {BIN} or PATH")
        return found
    return str(path)


def wait_for(predicate: Callable[[], Any], timeout: float, what: str,
             interval: float = 0.05) -> Any:
    """Poll ``predicate`` until it returns a truthy value; fail the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.1f} s waiting for {what}")
        time.sleep(interval)


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, str]]:
    """Environment for an isolated ROS graph; also applied to this test process. At teardown
    (after ``procs`` stopped its processes) any process still tagged with this test's
    ``DVT_TEST_ID`` is killed and the test fails naming it."""
    domain = str(next(_domain) % DOMAINS + 1)
    tag = f"{os.getpid()}-{next(_test_ids)}"
    env = dict(os.environ)
    env.update({
        "ROS_DOMAIN_ID": domain,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        TAG: tag,
    })
    env.pop("ROS_LOCALHOST_ONLY", None)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv(TAG, tag)
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    yield env
    left = kill_tagged(tag)
    if left:
        pytest.fail(f"{len(left)} process(es) outlived the test (killed now): "
                    + "; ".join(left), pytrace=False)


class Procs:
    """Starts console scripts and guarantees they are stopped."""

    def __init__(self, env: dict[str, str], logdir: Path) -> None:
        self.env = env
        self.logdir = logdir
        self.procs: list[tuple[subprocess.Popen[bytes], Path]] = []

    def start(self, name: str, *args: str, env: dict[str, str] | None = None
              ) -> subprocess.Popen[bytes]:
        log = self.logdir / f"{name}-{len(self.procs)}.log"
        fh = log.open("wb")
        proc = subprocess.Popen([script(name), *args], env=env or self.env, stdout=fh,
                                stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append((proc, log))
        return proc

    def log(self, proc: subprocess.Popen[bytes]) -> str:
        for p, log in self.procs:
            if p is proc:
                return log.read_text(errors="replace")
        return ""

    def stop(self, proc: subprocess.Popen[bytes], timeout: float = 10.0) -> int:
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
        return proc.returncode

    def stop_all(self) -> None:
        for proc, _ in reversed(self.procs):
            self.stop(proc)


@pytest.fixture
def procs(ros_env: dict[str, str], tmp_path: Path, request: pytest.FixtureRequest
          ) -> Iterator[Procs]:
    """Process starter bound to this test's isolated ROS environment."""
    p = Procs(ros_env, tmp_path)
    yield p
    p.stop_all()
    if request.node.rep_call.failed if hasattr(request.node, "rep_call") else False:
        for proc, log in p.procs:
            sys.stderr.write(f"--- {log.name} (rc={proc.returncode})\n{log.read_text()[-4000:]}\n")


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    rep = yield
    setattr(item, "rep_" + rep.when, rep)
    return rep


@pytest.fixture
def rclpy_context(ros_env: dict[str, str]) -> Iterator[Any]:
    """An initialised rclpy context in this test process (domain from ``ros_env``)."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    try:
        yield ctx
    finally:
        rclpy.shutdown(context=ctx)
