"""``dvt-launch``: start the DVT chain as processes, wait until it is ready, stop it cleanly.

Usage::

    dvt-launch sim [--hidden PRESET|FILE] [--params NAME] [--rate HZ] [--seed N]
                   [--record DIR] [--experiment NAME] [--experiment-seed N]
                   [--experiment-set NAME=VALUE ...] [--duration S]
                   [--driver-param NAME:=VALUE ...] [--model-param NAME:=VALUE ...]
                   [--record-param NAME:=VALUE ...] [--record-topics T ...]
                   [--compression zstd|none] [--max-missing N] [--no-model] [--log-dir DIR]
                   [--ring-minutes M] [--ring-dir DIR] [--ring-segment-seconds S]
                   [--change-at T:SPEC ...] [--change-file PATH]
                   [--supervise] [--identify-param NAME:=VALUE ...] [--episodes N]
                   [--foxglove] [--foxglove-port P] [--foxglove-host H] [--foxglove-param N:=V]
                   [--start-discovery-server [IP:]PORT] [--discovery-server HOST[:PORT] ...]
                   [--static-peers A[,B...]]
    dvt-launch hw  --port /dev/ttyUSB0 [--baud B] [--rate HZ] [--params NAME] [--record DIR]
                   [--experiment NAME] [--duration S] [...]

``sim`` starts, in this order and each only once the previous one is up:

1. ``dvt-plant`` (the simulated controller on a pseudo-terminal; ready when it prints
   ``READY <link>``), with ``--hidden``, ``--params``, ``--rate``, ``--seed`` and
   ``--truth-out``;
2. ``dvt_driver_node`` with ``port:=<link>``, ``autostart:=true`` and ``sample_rate_hz``
   (ready when samples arrive on ``/dvt/joint_states``);
3. ``dvt_model_node`` with ``params`` (ready when it publishes ``/dvt/model/joint_states``);
4. ``dvt-experiment NAME`` if ``--experiment`` (its controller rate is the default of
   ``--rate``); it waits for the driver and, when recording, for the recorder's subscriptions
   (sample and command topics), so the bag holds the whole experiment;
5. ``dvt-recorder`` with ``output:=DIR`` if ``--record``, once the experiment's command
   publishers exist (ready when it subscribes to the recorded DVT topics);

5b. a second ``dvt-recorder`` in rolling mode if ``--ring-minutes M`` (node
   ``dvt_recorder_ring``; ring directory ``--ring-dir``, default ``<log dir>/ring``; segments
   of ``--ring-segment-seconds``, default 10; the recorded topics plus ``/dvt/model/change``):
   it keeps the last M minutes and answers snapshot requests on ``/dvt/recorder/snapshot``
   (``docs/loop.md``). When a normal recording runs beside it, the normal recorder's snapshot
   topics are remapped to ``/dvt/recorder/bag/snapshot[_result]`` so that only the ring answers;

5c. ``dvt_identify_node`` with its supervisor if ``--supervise`` (the self-closing loop,
   ``docs/loop.md``; implies ``--ring-minutes 10`` unless a ring is given, and needs the model
   node): ``supervisor.enabled:=true``, ``output_dir:=<log dir>/identify`` (its episode reports
   ``episodes/episode-N.json`` / ``.md`` go there) and the ``--identify-param NAME:=VALUE``
   items (e.g. ``supervisor.min_post_change_s:=20``); ready when it subscribes to
   ``/dvt/model/change`` and ``/dvt/model/residual``. With an experiment, once it moves the
   machine (its first ``phase`` line; before the ring and the identifier start) the launcher
   re-arms the model node's change detector (it calls the model node's
   ``/dvt_model/reset_detector`` service, std_srvs/Trigger: the detector forgets its reference
   and learns anew from the next samples), so that the reference residual is learned on the
   running machine and not at standstill (a reference learned at rest alarms when the motion
   starts). Each new episode report is printed
   (``episode N: OUTCOME ...``); ``--episodes N`` ends the run after the N-th;

6. ``dvt-foxglove`` if ``--foxglove`` (the Foxglove WebSocket bridge, ``docs/foxglove.md``;
   ready when it prints ``READY ws://...``);

A changing plant (sim): the ``--hidden`` preset may carry a schedule (``wear``,
``oil_warmup``, ``payload_added``, ``friction_step``); ``--change-at T:SPEC`` (repeatable) and
``--change-file PATH`` are passed to ``dvt-plant``, and a SIGHUP to the launcher is forwarded to
the plant (it then applies the change in ``--change-file`` at once). The plant writes every
change it applies with its times into ``truth.yaml`` (copied into the bag when recording).

The model node gets ``detector.sample_rate_hz`` = the controller rate (unless
``--model-param`` sets it), so that its detector's 10-ms blocks hold 10 ms at any ``--rate``.

then the run ends with the experiment, or after ``--duration`` seconds, or after ``--episodes``
episode reports, or on Ctrl-C. ``hw``
does the same against a real controller on ``--port`` (no plant, no truth).

Shutdown, also on Ctrl-C (SIGINT) or SIGTERM at any point: the experiment is stopped first (it
stops the motor), then the others in reverse start order (recorder, model node, driver, plant),
each with SIGINT, a bounded wait and a SIGKILL fallback; a second Ctrl-C shortens the waits.
Children run in their own sessions (a terminal's Ctrl-C reaches only the launcher, which then
stops them in order) and get SIGTERM from the kernel if the launcher dies. When recording,
``truth.yaml`` (the plant's hidden effects) and ``run.yaml`` (how the run was made) are written
into the bag directory after the recorder has closed the bag, and the bag is checked with
:func:`dvt_model.recording.read_run`.

Across machines (``docs/multihost.md``, :mod:`dvt_driver.run.discovery`):
``--start-discovery-server [IP:]PORT`` starts a Fast DDS discovery server first (child
``discovery``) and makes every participant a client of it (at 127.0.0.1 unless IP is given and
not 0.0.0.0); ``--discovery-server HOST[:PORT]`` joins a server running elsewhere;
``--static-peers A,B`` uses unicast discovery of the listed machines instead. The launcher's own
monitor is a super client (it inspects the whole graph).

Children get the launcher's environment (plus single-threaded BLAS, see
:data:`SINGLE_THREAD_BLAS`) and are the venv's own console scripts (see ROS2_ON_PIP.md); their
output goes to ``--log-dir`` (default a new ``/tmp/dvt-launch-*``).

Exit status: 0 success; 1 a process failed to start or died (or the bag does not read back);
2 bad arguments; 4 the bag misses more samples than ``--max-missing``, or does not hold the whole
experiment; 5 fewer than ``--episodes`` episode reports when the run ended; 130 interrupted;
otherwise the experiment's own non-zero status.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import fnmatch
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import yaml

from dvt_driver.errors import ExperimentError, LaunchError, LaunchInterruptedError
from dvt_driver.run import discovery
from dvt_driver.signals import StopFlag
from dvt_model.contract import (
    CMD_GEAR,
    COMMAND_PATTERN,
    COMMAND_TOPICS,
    DEFAULT_RECORD_TOPICS,
    IDENTIFY_NODE,
    JOINT_STATES,
    MODEL_CHANGE,
    MODEL_JOINT_STATES,
    MODEL_NODE,
    MODEL_RESIDUAL,
    MODEL_TOPICS,
    RECORDER_SNAPSHOT_REQUEST,
    RECORDER_SNAPSHOT_RESULT,
    SAMPLE_TOPICS,
    model_reset_detector_service,
)

BIN = Path(sys.executable).parent
READY_TIMEOUT = {"plant": 30.0, "driver": 30.0, "model": 30.0, "recorder": 30.0,
                 "ring": 30.0, "experiment": 30.0, "foxglove": 30.0, "discovery": 10.0,
                 "identify": 60.0}
"""Longest wait for each child to become ready [s]."""
STOP_TIMEOUT = {"experiment": 10.0, "recorder": 30.0, "ring": 30.0, "model": 10.0,
                "driver": 10.0, "plant": 10.0, "foxglove": 10.0, "discovery": 5.0,
                "identify": 15.0}
"""Longest wait for each child to exit after SIGINT before SIGKILL [s]."""
RING_NODE = "dvt_recorder_ring"
"""Node name of the rolling recorder ``dvt-launch --ring-minutes`` starts."""
SUPERVISE_RING_MINUTES = 10.0
"""Ring length ``--supervise`` implies without ``--ring-minutes`` [min]: the supervisor's
default wait (60 s of post-change data) plus a refit, with margin (``docs/loop.md`` §4)."""
REARM_TIMEOUT = 30.0
"""Longest wait for the experiment's first phase, and for the model node's reset service to
appear and answer, when the launcher re-arms the change detector [s] (a loaded model node
answers its services after its queued samples)."""
IDENTIFY_DIR = "identify"
"""Sub-directory of the log directory that ``--supervise`` gives the identifier as
``output_dir`` (episode reports in ``<log dir>/identify/episodes``)."""
RECORDED_DVT_TOPICS = (*SAMPLE_TOPICS, *MODEL_TOPICS)
"""The high-rate streams a recording must hold (checked after the run)."""
_PR_SET_PDEATHSIG = 1
SINGLE_THREAD_BLAS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
"""Set in every child's environment: the nodes do linear algebra on 2x2..5x5 matrices, where
BLAS worker threads only add synchronisation; on a busy 2-core machine a threaded
``scipy.linalg.expm`` of a 4x4 matrix took 1.5-4 ms instead of 0.03 ms and made the 1 kHz plant
fall behind."""


def script(name: str) -> str:
    """The venv's console script ``name`` (next to this interpreter), else from ``PATH``."""
    path = BIN / name
    if path.exists():
        return str(path)
    import shutil

    found = shutil.which(name)
    if found is None:
        raise LaunchError(f"console script {name!r} not found in {BIN} or on PATH "
                          "(is the package installed in this venv?)")
    return found


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
    """Starts children (own session, die with the parent, output to a log) and stops them."""

    def __init__(self, logdir: Path, env: dict[str, str], stop: StopFlag,
                 echo: TextIO | None = None) -> None:
        self.logdir = logdir
        self.env = env
        self.stop = stop
        self.echo = echo
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
            rc = self.stop_one(child, STOP_TIMEOUT.get(child.name, 10.0))
            out[child.name] = rc
            self._say(f"stopped {child.name} (status {rc}{', killed' if child.killed else ''})")
        return out


class Monitor:
    """A small rclpy node in the launcher: counts samples and inspects the graph.

    Subscriptions are dropped once the chain is ready, so the launcher costs no CPU at 1 kHz.
    """

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState

        from dvt_model import rosutil

        self.ctx = Context()
        rclpy.init(context=self.ctx,
                   signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node("dvt_launch", context=self.ctx)
        self.counts: dict[str, int] = {}
        self.subs: list[Any] = []
        for topic in (JOINT_STATES, MODEL_JOINT_STATES):
            self.counts[topic] = 0
            self.subs.append(self.node.create_subscription(
                JointState, topic, self._counter(topic), rosutil.SENSOR_QOS))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self._quit = threading.Event()
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._spin, name="dvt-launch-monitor",
                                       daemon=True)
        self.thread.start()

    def _counter(self, topic: str) -> Callable[[Any], None]:
        def cb(msg: Any) -> None:
            self.counts[topic] += 1
        return cb

    def _spin(self) -> None:
        while not self._quit.is_set():
            try:
                with self._lock:
                    self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # context shut down under us
                return

    def subscribed(self, node_name: str, topic: str) -> bool:
        """Whether node ``node_name`` has a subscription on ``topic``."""
        with self._lock:
            infos = self.node.get_subscriptions_info_by_topic(topic)
        return any(i.node_name == node_name for i in infos)

    def published(self, node_name: str, topic: str) -> bool:
        """Whether node ``node_name`` has a publisher on ``topic``."""
        with self._lock:
            infos = self.node.get_publishers_info_by_topic(topic)
        return any(i.node_name == node_name for i in infos)

    def rearm_detector(self, model_node: str, timeout: float,
                       interrupted: Callable[[], bool] = lambda: False) -> str:
        """Make the model node's change detector learn anew: call its reset service
        (``/<model_node>/reset_detector``, std_srvs/srv/Trigger,
        :data:`dvt_model.contract.SRV_MODEL_RESET_DETECTOR`).

        Waits at most ``timeout`` [s] in all for the service to appear and answer. Returns the
        node's answer (what was reset). Raises :class:`LaunchError` naming the node and the
        service when the service does not appear or answer within ``timeout``, or refuses
        (``success=False``, e.g. the detector is off: its reason), and
        :class:`LaunchInterruptedError` as soon as ``interrupted()`` is true (a signal).
        """
        from std_srvs.srv import Trigger

        service = model_reset_detector_service(model_node)
        deadline = time.monotonic() + timeout
        with self._lock:
            client = self.node.create_client(Trigger, service)

        def ready() -> bool:
            with self._lock:
                return bool(client.service_is_ready())

        def check_interrupted() -> None:
            if interrupted():
                raise LaunchInterruptedError(f"interrupted while calling {service} of model "
                                             f"node {model_node!r}")

        try:
            while not ready():
                check_interrupted()
                if time.monotonic() > deadline:
                    raise LaunchError(f"model node {model_node!r} offers no service {service} "
                                      f"within {timeout:g} s (is it running under that name?)")
                time.sleep(0.05)
            with self._lock:
                future = client.call_async(Trigger.Request())
            while not future.done():
                check_interrupted()
                if time.monotonic() > deadline:
                    raise LaunchError(f"model node {model_node!r} did not answer {service} "
                                      f"within {timeout:g} s")
                time.sleep(0.02)
            failure = future.exception()
            answer = future.result() if failure is None else None
            if answer is None:
                raise LaunchError(f"model node {model_node!r}: the call of {service} failed "
                                  f"({failure!r})")
            if not answer.success:
                raise LaunchError(f"model node {model_node!r} refused {service}: "
                                  f"{answer.message}")
            return str(answer.message)
        finally:
            with self._lock:
                self.node.destroy_client(client)

    def quiet(self) -> None:
        """Drop the sample subscriptions (readiness is established)."""
        with self._lock:
            for sub in self.subs:
                self.node.destroy_subscription(sub)
            self.subs.clear()

    def close(self) -> None:
        """Stop the spin thread and shut the context down."""
        self._quit.set()
        self.thread.join(timeout=2.0)
        with contextlib.suppress(Exception):
            self.executor.shutdown(timeout_sec=1.0)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
        with contextlib.suppress(Exception):
            self.ctx.try_shutdown()


DETECTOR_RATE = "detector.sample_rate_hz"
"""The model node's detector parameter the launcher sets to the controller rate."""


def episode_reports(directory: Path) -> list[Path]:
    """The episode reports (``episode-N.json``, also ``episode-N-K.json`` of a later node)
    under ``<directory>/episodes``, in episode order."""
    def key(p: Path) -> tuple[int, ...]:
        return tuple(int(x) for x in p.stem.split("-")[1:] if x.isdigit())

    base = directory / "episodes"
    return sorted(base.glob("episode-*.json"), key=key) if base.is_dir() else []


def episode_line(record: dict[str, Any]) -> str:
    """One line about an episode report (outcome, change and detection times [s], push)."""
    def num(key: str) -> str:
        v = record.get(key)
        return f"{v:.3f}" if isinstance(v, int | float) else "-"

    live = record.get("live_ratio") or {}
    return (f"episode {record.get('episode')}: {record.get('outcome')} ({record.get('reason')}); "
            f"change at {num('change_s')} s, detected at {num('detected_s')} s on "
            f"{', '.join(record.get('outputs') or []) or '?'}; pushed {record.get('pushed')} "
            f"at {num('push_s')} s, rolled back {record.get('rolled_back')}"
            + (f"; live RMS ratio {', '.join(f'{k} {v:.3g}' for k, v in live.items())}"
               if live else ""))


def _rearm(exp: Child, monitor: Monitor, kids: Children, say: Callable[[str], None]) -> None:
    """Once the experiment moves the machine (its first ``phase`` line), make the model node's
    change detector learn its reference anew (:meth:`Monitor.rearm_detector`): a reference
    learned at standstill alarms as soon as the motion starts. Done before the ring and the
    identifier start, so that neither sees an alarm of the standstill reference; the detector
    learns anew from the next samples (the model is not re-anchored). A failure (no answer
    within :data:`REARM_TIMEOUT`, a refusal) is a warning naming the node and the service (the
    loop still runs)."""
    try:
        kids.wait_until("the experiment's first phase", lambda: "phase " in exp.tail(20000)
                        or not exp.alive(), REARM_TIMEOUT)
        if not exp.alive():
            return
        answer = monitor.rearm_detector(MODEL_NODE, REARM_TIMEOUT,
                                        interrupted=lambda: bool(kids.stop))
        say(f"experiment moving: the model node's change detector re-armed (it learns its "
            f"reference on the running machine): {answer}")
    except LaunchInterruptedError:
        raise
    except LaunchError as exc:
        say(f"warning: the change detector was not re-armed: {exc}")


class _Supervision:
    """``--supervise`` while the run lasts: prints every new episode report and says when
    ``--episodes`` are done."""

    def __init__(self, args: argparse.Namespace, directory: Path,
                 say: Callable[[str], None]) -> None:
        self.args = args
        self.directory = directory
        self.say = say
        self.seen: set[Path] = set()
        self.count = 0

    def poll(self) -> bool:
        """One check; ``True`` when ``--episodes`` reports exist (the run should end)."""
        for path in episode_reports(self.directory):
            if path in self.seen:
                continue
            try:
                record = json.loads(path.read_text())
            except (OSError, ValueError):
                continue  # being written: read at the next poll
            self.seen.add(path)
            self.count += 1
            self.say(f"{episode_line(record)} -> {path}")
        if self.args.episodes is not None and self.count >= self.args.episodes:
            self.say(f"{self.count} episode report(s): --episodes {self.args.episodes} done")
            return True
        return False


def _param(text: str, option: str) -> list[str]:
    if ":=" not in text or text.startswith(":="):
        raise argparse.ArgumentTypeError(f"{option}: expected NAME:=VALUE, got {text!r}")
    return ["-p", text]


def _ros_params(items: Sequence[str], option: str) -> list[str]:
    out: list[str] = []
    for it in items:
        out += _param(it, option)
    return out


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    """Parse ``dvt-launch`` arguments."""
    from dvt_driver.run.experiment_core import available

    p = argparse.ArgumentParser(prog="dvt-launch", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="mode", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--params", default="physical",
                        help="transmission parameter set of the model node (and of the plant "
                             "in sim); default physical")
    common.add_argument("--rate", type=float, default=None,
                        help="controller sample rate [Hz] (default: the experiment's, else "
                             "1000)")
    common.add_argument("--record", metavar="DIR", default=None,
                        help="record to this bag directory (must not exist)")
    common.add_argument("--record-topics", nargs="+", default=None, metavar="TOPIC",
                        help=f"topics/patterns to record (default {list(DEFAULT_RECORD_TOPICS)})")
    common.add_argument("--compression", choices=("none", "zstd"), default="zstd",
                        help="MCAP chunk compression of the recording (default zstd)")
    common.add_argument("--experiment", default=None, help=f"run one of {available()}")
    common.add_argument("--experiment-seed", type=int, default=0,
                        help="seed of the experiment's random signals (default 0)")
    common.add_argument("--experiment-set", action="append", default=[], metavar="NAME=VALUE",
                        help="experiment builder setting, passed as dvt-experiment --set "
                             "(repeatable)")
    common.add_argument("--duration", type=float, default=None,
                        help="run time [s] without --experiment (default: until Ctrl-C); with "
                             "--experiment an upper bound")
    common.add_argument("--no-model", action="store_true", help="do not start dvt_model_node")
    common.add_argument("--driver-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_driver_node parameter (repeatable)")
    common.add_argument("--model-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_model_node parameter (repeatable)")
    common.add_argument("--record-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt-recorder parameter (repeatable)")
    common.add_argument("--log-dir", default=None,
                        help="where the children's output goes (default: a new temp dir)")
    common.add_argument("--no-check", action="store_true",
                        help="do not read the recorded bag back at the end")
    common.add_argument("--max-missing", type=int, default=None, metavar="N",
                        help="exit with status 4 if the bag misses (or cannot align) more "
                             "than N samples inside the recording (default: report only)")
    common.add_argument("--foxglove", action="store_true",
                        help="start dvt-foxglove, the Foxglove WebSocket bridge "
                             "(docs/foxglove.md)")
    common.add_argument("--foxglove-port", type=int, default=None,
                        help="its WebSocket port (default 8765)")
    common.add_argument("--foxglove-host", default=None,
                        help="its listen address (default 127.0.0.1; 0.0.0.0 for every "
                             "interface)")
    common.add_argument("--foxglove-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt-foxglove parameter, e.g. rate_hz:=50 (repeatable)")
    common.add_argument("--ring-minutes", type=float, default=None, metavar="M",
                        help="also run a rolling recorder keeping the last M minutes "
                             "(snapshots on request, docs/loop.md)")
    common.add_argument("--ring-dir", default=None, metavar="DIR",
                        help="its ring directory (default <log dir>/ring; may exist)")
    common.add_argument("--ring-segment-seconds", type=float, default=10.0, metavar="S",
                        help="length of one ring segment [s] (default 10)")
    common.add_argument("--supervise", action="store_true",
                        help="also run dvt_identify_node with its supervisor (alarm -> refit "
                             "-> push -> watch -> keep or roll back, docs/loop.md); implies "
                             f"--ring-minutes {SUPERVISE_RING_MINUTES:g} unless given; episode "
                             f"reports in <log dir>/{IDENTIFY_DIR}/episodes")
    common.add_argument("--identify-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_identify_node parameter, e.g. "
                             "supervisor.min_post_change_s:=20 (repeatable; needs --supervise)")
    common.add_argument("--episodes", type=int, default=None, metavar="N",
                        help="end the run after N episode reports (needs --supervise; exit "
                             "status 5 if fewer when the run ends otherwise)")
    common.add_argument("--start-discovery-server", default=None, metavar="[IP:]PORT",
                        help="start a Fast DDS discovery server (e.g. 0.0.0.0:11811) and use it "
                             "(docs/multihost.md)")
    common.add_argument("--discovery-server", action="append", default=[],
                        metavar="HOST[:PORT]",
                        help="discover through this Fast DDS discovery server (repeatable)")
    common.add_argument("--static-peers", default=None, metavar="A[,B...]",
                        help="discover only localhost and these machines (unicast)")
    sim = sub.add_parser("sim", parents=[common], help="simulated plant on a pseudo-terminal")
    sim.add_argument("--hidden", default="none",
                     help="hidden-effects preset or YAML file of the plant (default none)")
    sim.add_argument("--seed", type=int, default=0, help="plant noise seed (default 0)")
    sim.add_argument("--change-at", action="append", default=[], metavar="T:SPEC",
                     help="plant change: at plant time T [s] the changes of SPEC (preset or "
                          "hidden-effects YAML; a preset without a schedule is a step to its "
                          "friction), passed to dvt-plant (repeatable)")
    sim.add_argument("--change-file", default=None, metavar="PATH",
                     help="change applied by the plant on SIGHUP (forwarded by the launcher)")
    sim.add_argument("--plant-arg", action="append", default=[], metavar="ARG",
                     help="extra dvt-plant argument, e.g. --plant-arg=--crc-error-rate=0.01")
    hw = sub.add_parser("hw", parents=[common], help="real controller on a serial port")
    hw.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0")
    hw.add_argument("--baud", type=int, default=None, help="line rate (driver default 921600)")
    args = p.parse_args(list(argv))
    if args.rate is not None and not 0 < args.rate <= 2000:
        p.error(f"--rate: expected 0 < HZ <= 2000, got {args.rate}")
    if args.duration is not None and not args.duration > 0:
        p.error(f"--duration: expected a number > 0 s, got {args.duration}")
    for opt in ("driver_param", "model_param", "record_param", "foxglove_param",
                "identify_param"):
        for it in getattr(args, opt):
            try:
                _param(it, "--" + opt.replace("_", "-"))
            except argparse.ArgumentTypeError as exc:
                p.error(str(exc))
    if args.experiment is not None:
        try:
            _experiment(args)
        except ExperimentError as exc:
            p.error(f"--experiment: {exc}")
    elif args.experiment_set:
        p.error("--experiment-set needs --experiment")
    try:
        args.discovery_env = _discovery(args)
    except discovery.DiscoveryError as exc:
        p.error(str(exc))
    if (args.foxglove_port is not None or args.foxglove_host is not None
            or args.foxglove_param) and not args.foxglove:
        p.error("--foxglove-port/--foxglove-host/--foxglove-param need --foxglove")
    if args.foxglove_port is not None and not 0 <= args.foxglove_port <= 65535:
        p.error(f"--foxglove-port: expected 0..65535, got {args.foxglove_port}")
    if not args.supervise and (args.identify_param or args.episodes is not None):
        p.error("--identify-param/--episodes need --supervise")
    if args.supervise and args.no_model:
        p.error("--supervise needs the model node (its residual and change alarms); drop "
                "--no-model")
    if args.episodes is not None and args.episodes < 1:
        p.error(f"--episodes: expected an integer >= 1, got {args.episodes}")
    if args.supervise and args.ring_minutes is None:
        args.ring_minutes = SUPERVISE_RING_MINUTES
    if args.ring_minutes is not None and not (0 < args.ring_minutes <= 24 * 60):
        p.error(f"--ring-minutes: expected 0 < M <= 1440, got {args.ring_minutes}")
    if args.ring_minutes is not None and not (
            0 < args.ring_segment_seconds <= args.ring_minutes * 60):
        p.error(f"--ring-segment-seconds: expected 0 < S <= ring minutes * 60, got "
                f"{args.ring_segment_seconds}")
    if args.ring_dir is not None and args.ring_minutes is None:
        p.error("--ring-dir needs --ring-minutes")
    if args.mode == "sim":
        from dvt_driver.errors import DvtDriverError
        from dvt_driver.plant.server import parse_change_at

        for text in args.change_at:
            try:
                parse_change_at(text)
            except DvtDriverError as exc:
                p.error(str(exc))
    if args.record is not None and Path(args.record).exists():
        p.error(f"--record: {args.record} already exists (a recording never overwrites)")
    return args


def _discovery(args: argparse.Namespace) -> dict[str, str]:
    """The discovery environment of the children (empty: the default discovery)."""
    chosen = [o for o, v in (("--start-discovery-server", args.start_discovery_server),
                             ("--discovery-server", args.discovery_server),
                             ("--static-peers", args.static_peers)) if v]
    if "--static-peers" in chosen and len(chosen) > 1:
        raise discovery.DiscoveryError(f"{' and '.join(chosen)}: choose a discovery server "
                                       "or static peers, not both")
    servers = [discovery.parse_endpoint(t, "--discovery-server") for t in args.discovery_server]
    args.discovery_listen = None
    if args.start_discovery_server:
        listen = discovery.parse_endpoint(args.start_discovery_server,
                                          "--start-discovery-server", default_host="0.0.0.0")
        args.discovery_listen = listen
        host = "127.0.0.1" if listen.host in ("0.0.0.0", "::") else listen.host
        servers.insert(0, discovery.Endpoint(host, listen.port))
    if servers:
        return discovery.server_env(servers)
    if args.static_peers:
        return discovery.static_peers_env(discovery.parse_peers(args.static_peers))
    return {}


def _ready_line(log: Path) -> str | None:
    """The address after ``READY`` in a child's log (dvt-foxglove), if printed yet."""
    return _plant_link(log)


def _plant_link(log: Path) -> str | None:
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("READY "):
            return line.split(None, 1)[1].strip()
    return None


def _experiment(args: argparse.Namespace) -> Any:
    """The experiment ``args`` asks for (built as ``dvt-experiment`` will build it)."""
    from dvt_driver.run.experiment import parse_settings
    from dvt_driver.run.experiment_core import build

    return build(args.experiment, seed=args.experiment_seed,
                 **parse_settings(args.experiment_set))


def _rate_of(args: argparse.Namespace) -> float:
    if args.rate is not None:
        return float(args.rate)
    if args.experiment is not None:

        return 1e6 / _experiment(args).sample_period_us
    return 1000.0


def first_command_time(path: Path) -> int | None:
    """Log time [ns] of the first ``/dvt/cmd/*`` message in the bag (the experiment's t = 0:
    every experiment sends its first command at t = 0), ``None`` if there is none."""
    from rosbags.rosbag2 import Reader

    try:
        with Reader(path) as reader:
            conns = [c for c in reader.connections if fnmatch.fnmatchcase(c.topic, COMMAND_PATTERN)]
            for _, log_time, _ in reader.messages(connections=conns):
                return int(log_time)
    except Exception:  # a bag that does not read is reported by check_bag
        return None
    return None


def check_bag(path: Path, rate: float) -> dict[str, Any]:
    """Read a recording back and measure its completeness.

    Returns ``samples`` (aligned pairs), ``duration_s``, ``rate_hz`` (median), ``unmatched``
    (stamps in only one of the two topics), ``unmatched_inside`` (those between the first and
    the last aligned sample: the ones at the ends only mean the recorder subscribed to, or left,
    the two topics a few samples apart), ``missing`` (samples missing between consecutive
    aligned stamps, from the nominal period ``1 / rate``: lost samples, or a forward step of the
    driver's stamp mapping), ``step_ms`` (smallest and largest stamp step), ``topics`` and
    ``bytes`` (size on disk).
    """
    from dvt_model.recording import read_run, read_topic_series, sample_period

    run = read_run(path)
    inside = 0
    if run.n:
        lo, hi = int(run.stamps_ns[0]), int(run.stamps_ns[-1])
        for topic in SAMPLE_TOPICS:
            st = read_topic_series(path, topic).stamps_ns
            st = st[(st >= lo) & (st <= hi)]
            inside += int(st.size - np.isin(st, run.stamps_ns).sum())
    period = sample_period(run)
    size = sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    steps = np.diff(run.stamps_ns) * 1e-9
    missing = int(np.sum(np.maximum(np.round(steps * rate) - 1.0, 0.0))) if steps.size else 0
    return {"samples": run.n, "duration_s": round(run.duration, 3),
            "rate_hz": round(1.0 / period, 2) if period > 0 else None,
            "unmatched": run.unmatched, "unmatched_inside": inside, "missing": missing,
            "step_ms": [round(float(steps.min()) * 1e3, 3), round(float(steps.max()) * 1e3, 3)]
            if steps.size else [],
            "first_stamp_ns": int(run.stamps_ns[0]) if run.n else None,
            "last_stamp_ns": int(run.stamps_ns[-1]) if run.n else None,
            "topics": list(run.topics), "bytes": size}


def launch(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """Run the chain described by ``args`` (see the module docstring); returns the status."""
    stop = StopFlag(escalate=False).install()  # a 2nd signal hurries the shutdown
    logdir = Path(args.log_dir) if args.log_dir else Path(tempfile.mkdtemp(prefix="dvt-launch-"))
    logdir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    env.update(SINGLE_THREAD_BLAS)
    denv = getattr(args, "discovery_env", None) or {}
    if denv:
        env = discovery.apply_env(env, denv)
        # the monitor (this process) inspects the whole graph: a super client
        own = discovery.apply_env(os.environ, denv)
        if "ROS_DISCOVERY_SERVER" in denv:
            own["ROS_SUPER_CLIENT"] = "TRUE"
        os.environ.clear()
        os.environ.update(own)
    kids = Children(logdir, env, stop, echo=out)

    def say(text: str) -> None:
        print(f"dvt-launch: {text}", file=out, flush=True)

    rate = _rate_of(args)
    record = Path(args.record).resolve() if args.record else None
    topics = list(args.record_topics or DEFAULT_RECORD_TOPICS)
    truth = logdir / "truth.yaml"
    identify_dir = logdir / IDENTIFY_DIR
    status = 0
    monitor: Monitor | None = None
    started = time.time()
    exp_status: int | None = None
    say(f"logs in {logdir}")
    plant_pid: dict[str, int] = {}

    def forward_hup(signum: int, frame: object) -> None:
        pid = plant_pid.get("pid")
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGHUP)

    main_thread = threading.current_thread() is threading.main_thread()
    old_hup = signal.signal(signal.SIGHUP, forward_hup) if main_thread else None
    try:
        if getattr(args, "discovery_listen", None) is not None:
            listen = args.discovery_listen
            dsrv = kids.start("discovery", discovery.server_command(listen),
                              env=discovery.server_process_env(env))
            kids.wait_until("the discovery server's 'Server is running' line",
                            lambda: "Server is running" in dsrv.tail(),
                            READY_TIMEOUT["discovery"])
            say(f"discovery server on {listen}")
        if denv:
            say("discovery: " + " ".join(f"{k}={v}" for k, v in denv.items()))
        monitor = Monitor()
        # 1. plant or port
        if args.mode == "sim":
            changes = [f"--change-at={c}" for c in args.change_at]
            if args.change_file is not None:
                changes.append(f"--change-file={Path(args.change_file).resolve()}")
            plant = kids.start("plant", [
                script("dvt-plant"), "--link", str(logdir / "plant.tty"),
                "--params", args.params, "--hidden", args.hidden, "--rate", f"{rate:g}",
                "--seed", str(args.seed), "--truth-out", str(truth), *changes,
                *args.plant_arg])
            plant_pid["pid"] = plant.proc.pid
            port = kids.wait_until("the plant's READY line",
                                   lambda: _plant_link(plant.log), READY_TIMEOUT["plant"])
            say(f"plant ready on {port}")
        else:
            port = args.port
        # 2. driver
        driver_params = ["-p", f"port:={port}", "-p", "autostart:=true",
                         "-p", f"sample_rate_hz:={rate:g}"]
        if args.mode == "hw" and args.baud is not None:
            driver_params += ["-p", f"baud:={args.baud}"]
        kids.start("driver", [script("dvt_driver_node"), "--ros-args", *driver_params,
                              *_ros_params(args.driver_param, "--driver-param")])
        kids.wait_until("samples on /dvt/joint_states",
                        lambda: monitor is not None and monitor.counts[JOINT_STATES] > 0,
                        READY_TIMEOUT["driver"])
        say("driver active, samples flowing")
        # 3. model node
        if not args.no_model:
            # the model node's prior is the plant's parameter set unless --model-param names one
            given = {kv.split(":=", 1)[0].strip() for kv in args.model_param}
            mine: list[str] = [] if "params" in given else ["-p", f"params:={args.params}"]
            if DETECTOR_RATE not in given:  # 10-ms detector blocks at any controller rate
                mine += ["-p", f"{DETECTOR_RATE}:={float(rate)!r}"]
            kids.start("model", [script("dvt_model_node"), "--ros-args", *mine,
                                 *_ros_params(args.model_param, "--model-param")])
            kids.wait_until("the model node's /dvt/model/joint_states",
                            lambda: (monitor is not None
                                     and monitor.counts[MODEL_JOINT_STATES] > 0),
                            READY_TIMEOUT["model"])
            say("model node publishing")
        # 4. the experiment, then the recorder. The experiment waits for the driver and (when
        # the commands are recorded) for the recorder itself. The recorder starts once the
        # command topics exist, so that it creates all its subscriptions in its first graph scan
        # (creating subscriptions later stalls it for ~80 ms, long enough to drop samples).
        exp: Child | None = None
        records_cmds = record is not None and any(
            fnmatch.fnmatchcase(CMD_GEAR, pat) for pat in topics)
        if args.experiment is not None:
            exp = kids.start("experiment", [
                script("dvt-experiment"), args.experiment, "--seed", str(args.experiment_seed),
                *[f"--set={kv}" for kv in args.experiment_set],
                "--subscribers", "2" if records_cmds else "1",
                *(["--recorder", "dvt_recorder"] if record is not None else [])])
            if records_cmds:
                started_exp = exp

                def commands_published() -> bool:
                    if not started_exp.alive():
                        raise LaunchError(f"the experiment exited with status "
                                          f"{started_exp.proc.returncode}:\n{started_exp.tail()}")
                    return monitor is not None and all(
                        monitor.published("dvt_experiment", t) for t in COMMAND_TOPICS)

                kids.wait_until("the experiment's command publishers", commands_published,
                                READY_TIMEOUT["experiment"])
        ring = args.ring_minutes is not None
        if record is not None:
            # beside a ring, only the ring answers snapshot requests
            remap = ["-r", f"{RECORDER_SNAPSHOT_REQUEST}:=/dvt/recorder/bag/snapshot",
                     "-r", f"{RECORDER_SNAPSHOT_RESULT}:=/dvt/recorder/bag/snapshot_result"
                     ] if ring else []
            kids.start("recorder", [
                script("dvt-recorder"), "--ros-args", *remap, "-p", f"output:={record}",
                "-p", f"topics:=[{','.join(shlex.quote(t) for t in topics)}]",
                "-p", f"compression:={args.compression}",
                *_ros_params(args.record_param, "--record-param")])
        if record is not None:
            needed = [t for t in RECORDED_DVT_TOPICS
                      if any(fnmatch.fnmatchcase(t, pat) for pat in topics)
                      and not (args.no_model and t in MODEL_TOPICS)]
            kids.wait_until(f"the recorder's subscriptions on {needed}",
                            lambda: monitor is not None and all(
                                monitor.subscribed("dvt_recorder", t) for t in needed),
                            READY_TIMEOUT["recorder"])
            say(f"recording to {record}")
        if args.supervise and exp is not None:
            _rearm(exp, monitor, kids, say)
        if ring:
            ring_dir = Path(args.ring_dir).resolve() if args.ring_dir else logdir / "ring"
            ring_topics = [*topics, *([] if MODEL_CHANGE in topics else [MODEL_CHANGE])]
            kids.start("ring", [
                script("dvt-recorder"), "--ros-args", "-r", f"__node:={RING_NODE}",
                "-p", f"output:={ring_dir}",
                "-p", f"topics:=[{','.join(shlex.quote(t) for t in ring_topics)}]",
                "-p", f"compression:={args.compression}",
                "-p", f"ring_minutes:={float(args.ring_minutes)!r}",  # a double, never '1'
                "-p", f"ring_segment_seconds:={float(args.ring_segment_seconds)!r}",
                *_ros_params(args.record_param, "--record-param")])
            ring_needed = [t for t in RECORDED_DVT_TOPICS
                           if any(fnmatch.fnmatchcase(t, pat) for pat in ring_topics)
                           and not (args.no_model and t in MODEL_TOPICS)]
            kids.wait_until(f"the ring recorder's subscriptions on {ring_needed}",
                            lambda: monitor is not None and all(
                                monitor.subscribed(RING_NODE, t) for t in ring_needed),
                            READY_TIMEOUT["ring"])
            say(f"rolling recording of the last {args.ring_minutes:g} min in {ring_dir} "
                f"(snapshots on {RECORDER_SNAPSHOT_REQUEST})")
        if args.supervise:
            given = {kv.split(":=", 1)[0].strip() for kv in args.identify_param}
            own_id = [] if "output_dir" in given else ["-p", f"output_dir:={identify_dir}"]
            kids.start("identify", [
                script("dvt_identify_node"), "--ros-args", "-p", "supervisor.enabled:=true",
                *own_id, *_ros_params(args.identify_param, "--identify-param")])
            kids.wait_until(f"dvt_identify_node's subscriptions on {MODEL_CHANGE} and "
                            f"{MODEL_RESIDUAL}",
                            lambda: monitor is not None and all(
                                monitor.subscribed(IDENTIFY_NODE, t)
                                for t in (MODEL_CHANGE, MODEL_RESIDUAL)),
                            READY_TIMEOUT["identify"])
            say(f"identifier supervising the loop; episode reports in {identify_dir}/episodes")
        if args.foxglove:
            fox_args: list[str] = []
            if args.foxglove_port is not None:
                fox_args += ["-p", f"port:={args.foxglove_port}"]
            if args.foxglove_host is not None:
                fox_args += ["-p", f"host:={args.foxglove_host}"]
            fox = kids.start("foxglove", [script("dvt-foxglove"), "--ros-args", *fox_args,
                                          *_ros_params(args.foxglove_param,
                                                       "--foxglove-param")])
            url = kids.wait_until("dvt-foxglove's READY line", lambda: _ready_line(fox.log),
                                  READY_TIMEOUT["foxglove"])
            say(f"Foxglove: open a Foxglove WebSocket connection to {url}")
        monitor.quiet()
        # run
        deadline = time.monotonic() + args.duration if args.duration else None
        loop = _Supervision(args, identify_dir, say) if args.supervise else None
        if exp is not None:
            say(f"running experiment {args.experiment} (log {exp.log})")
            while exp.alive():
                if stop:
                    raise LaunchInterruptedError("interrupted during the experiment")
                if deadline is not None and time.monotonic() > deadline:
                    say(f"--duration {args.duration:g} s reached; stopping the experiment")
                    break
                kids.check_alive()
                if loop is not None and loop.poll():
                    break
                time.sleep(0.1)
            if not exp.alive():
                exp_status = exp.proc.returncode
                for line in exp.tail(2000).splitlines()[-3:]:
                    say(f"experiment: {line}")
                if exp_status != 0:
                    say(f"experiment exited with status {exp_status}")
                    status = exp_status if exp_status is not None else 1
        else:
            say("running " + (f"for {args.duration:g} s" if deadline else "until Ctrl-C"))
            while deadline is None or time.monotonic() < deadline:
                if stop:
                    raise LaunchInterruptedError("interrupted")
                kids.check_alive()
                if loop is not None and loop.poll():
                    break
                time.sleep(0.1)
        if loop is not None and args.episodes is not None and loop.count < args.episodes \
                and status == 0:
            say(f"error: {loop.count} episode report(s) when the run ended, --episodes "
                f"{args.episodes} asked for")
            status = 5
    except LaunchInterruptedError as exc:
        say(f"{exc}; shutting down")
        status = 130
    except LaunchError as exc:
        say(f"error: {exc}")
        status = 1
    finally:
        if monitor is not None:
            monitor.quiet()
        statuses = kids.stop_all()
        if monitor is not None:
            monitor.close()
        stop.restore()
        if main_thread:
            signal.signal(signal.SIGHUP, old_hup)
    if record is not None and record.exists():
        status = _finish_recording(args, record, truth, rate, started, statuses, exp_status,
                                   status, say)
    return status


def _finish_recording(args: argparse.Namespace, record: Path, truth: Path, rate: float,
                      started: float, statuses: dict[str, int | None], exp_status: int | None,
                      status: int, say: Callable[[str], None]) -> int:
    """Write ``truth.yaml`` and ``run.yaml`` into the bag and check it; returns the status."""
    if not (record / "metadata.yaml").exists():
        say(f"error: {record} has no metadata.yaml (the recorder did not close the bag; "
            f"`dvt-bag recover {record}` restores what was written)")
        return status or 1
    if args.mode == "sim":
        if truth.exists():
            (record / "truth.yaml").write_text(truth.read_text())
        else:
            say(f"warning: the plant wrote no {truth}; the bag has no truth.yaml")
    run: dict[str, Any] = {
        "made_by": "dvt-launch " + shlex.join(sys.argv[1:] if sys.argv[1:] else [args.mode]),
        "mode": args.mode,
        "started_unix": round(started, 3),
        "sample_rate_hz": rate,
        "params": args.params,
        "hidden": getattr(args, "hidden", None),
        "plant_seed": getattr(args, "seed", None),
        "plant_changes": list(getattr(args, "change_at", [])),
        "experiment": None,
        "exit_status": {k: v for k, v in statuses.items()},
    }
    if args.experiment is not None:
        run["experiment"] = _experiment(args).to_mapping()
        run["experiment_status"] = exp_status
        run["experiment_start_ns"] = first_command_time(record)
    if not args.no_check:
        try:
            run["check"] = c = check_bag(record, rate)
            say(f"bag {record}: {c['samples']} samples over {c['duration_s']} s "
                f"({c['rate_hz']} Hz), {c['unmatched']} unmatched ({c['unmatched_inside']} "
                f"inside), {c['missing']} missing between stamps, stamp steps {c['step_ms']} "
                f"ms, {c['bytes'] / 1e6:.2f} MB")
            if args.max_missing is not None and \
                    c["missing"] + c["unmatched_inside"] > args.max_missing:
                say(f"error: more than --max-missing {args.max_missing} samples missing or "
                    "unmatched inside the recording")
                status = status or 4
            start = run.get("experiment_start_ns")
            if args.experiment is not None:
                end = None if start is None else \
                    start + round(run["experiment"]["duration_s"] * 1e9)
                inside = (start is not None and end is not None
                          and c["first_stamp_ns"] <= start and end <= c["last_stamp_ns"])
                c["experiment_inside"] = inside
                if not inside:
                    say("error: the recording does not hold the whole experiment (first "
                        f"command at {start} ns, samples {c['first_stamp_ns']}.."
                        f"{c['last_stamp_ns']} ns)")
                    status = status or 4
        except Exception as exc:  # report, keep the bag
            say(f"error: the recorded bag does not read back: {exc}")
            run["check"] = {"error": str(exc)}
            status = status or 1
    (record / "run.yaml").write_text(yaml.safe_dump(run, sort_keys=False))
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-launch``; returns the exit status."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    return launch(args)


if __name__ == "__main__":
    sys.exit(main())
