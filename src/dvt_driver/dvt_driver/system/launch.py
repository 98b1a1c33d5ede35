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
                   [--realtime P]
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
   ``/dvt/model/change`` and ``/dvt/model/residual`` and publishes the episode records on
   ``/dvt/identify/episode`` (:data:`dvt_model.contract.IDENTIFY_EPISODE`). With an experiment,
   once it moves the machine (its first ``phase`` line; before the ring and the identifier
   start) the launcher re-arms the model node's change detector (it calls the model node's
   ``/dvt_model/reset_detector`` service, std_srvs/Trigger: the detector forgets its reference
   and learns anew from the next samples), so that the reference residual is learned on the
   running machine and not at standstill (a reference learned at rest alarms when the motion
   starts). The launcher receives every episode record on the contract's topic (it reads no
   file of the identifier) and prints it (``episode N: OUTCOME ...``); ``--episodes N`` ends
   the run after the N-th. When the run ends otherwise with fewer records, the launcher waits
   at most :data:`EPISODE_DRAIN_S` for a record still on its way;

6. ``dvt-foxglove`` if ``--foxglove`` (the Foxglove WebSocket bridge, ``docs/foxglove.md``;
   ready when it prints ``READY ws://...``);

A changing plant (sim): the ``--hidden`` preset may carry a schedule (``wear``,
``oil_warmup``, ``payload_added``, ``friction_step``); ``--change-at T:SPEC`` (repeatable) and
``--change-file PATH`` are passed to ``dvt-plant``, and a SIGHUP to the launcher is forwarded to
the plant (it then applies the change in ``--change-file`` at once). The plant writes every
change it applies with its times into ``truth.yaml`` (copied into the bag when recording).

The model node gets ``detector.sample_rate_hz`` = the controller rate (unless
``--model-param`` sets it), so that its detector's 10-ms blocks hold 10 ms at any ``--rate``.

``--realtime P`` (``docs/loop.md`` §4): each child of the sample path is put in the real-time
scheduler right after it starts (``SCHED_RR``; its interpreter has started no thread yet, the
threads it starts later inherit the policy): the model node at P+1, plant and driver at P, the
experiment and the recorders at P-1 (:func:`~dvt_driver.system.launch_args.realtime_priorities`).
With it the identifier's refit process gets niceness -10 (:data:`REALTIME_REFIT_NICE`,
``supervisor.refit_nice``, unless ``--identify-param`` sets it): a process of the normal
scheduler cannot delay a real-time one, and the refit then comes before other jobs.
Without the right to real-time scheduling (root, ``CAP_SYS_NICE`` or an ``rtprio`` limit) one
warning, and everything runs in the normal scheduler (the refit at its default niceness 19).

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
:func:`dvt_model.recording.read_run` (:func:`~dvt_driver.system.bagcheck.check_bag`).

Across machines (``docs/multihost.md``, :mod:`dvt_driver.run.discovery`):
``--start-discovery-server [IP:]PORT`` starts a Fast DDS discovery server first (child
``discovery``) and makes every participant a client of it (at 127.0.0.1 unless IP is given and
not 0.0.0.0); ``--discovery-server HOST[:PORT]`` joins a server running elsewhere;
``--static-peers A,B`` uses unicast discovery of the listed machines instead. The launcher's own
monitor is a super client (it inspects the whole graph).

Children get the launcher's environment (plus single-threaded BLAS, see
:data:`dvt_driver.run.processes.SINGLE_THREAD_BLAS`) and are the venv's own console scripts
(see ROS2_ON_PIP.md); their output goes to ``--log-dir`` (default a new
``/tmp/dvt-launch-*``).

Modules: this one (the orchestration), :mod:`~dvt_driver.system.launch_args` (the options),
:mod:`dvt_driver.run.processes` (children), :mod:`~dvt_driver.system.monitor` (the launcher's
rclpy node) and :mod:`~dvt_driver.system.bagcheck` (the recording's sidecars and check).

Exit status: 0 success; 1 a process failed to start or died (or the bag does not read back);
2 bad arguments; 4 the bag misses more samples than ``--max-missing``, or does not hold the whole
experiment; 5 fewer than ``--episodes`` episode reports when the run ended; 130 interrupted;
otherwise the experiment's own non-zero status.
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import os
import shlex
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

from dvt_driver.errors import LaunchError, LaunchInterruptedError
from dvt_driver.run import discovery
from dvt_driver.run.processes import SINGLE_THREAD_BLAS, Child, Children, ready_line, script
from dvt_driver.signals import StopFlag
from dvt_driver.system.bagcheck import finish_recording
from dvt_driver.system.launch_args import (
    IDENTIFY_DIR,
    SUPERVISE_RING_MINUTES,
    parse_args,
    rate_of,
    realtime_priorities,
    ros_params,
)
from dvt_driver.system.monitor import Monitor
from dvt_model.contract import (
    CMD_GEAR,
    COMMAND_TOPICS,
    DEFAULT_RECORD_TOPICS,
    IDENTIFY_EPISODE,
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
)
from dvt_model.recording import TRUTH_FILE

__all__ = [
    "DETECTOR_RATE",
    "EPISODE_DRAIN_S",
    "IDENTIFY_DIR",
    "READY_TIMEOUT",
    "REARM_TIMEOUT",
    "RING_NODE",
    "SUPERVISE_RING_MINUTES",
    "episode_line",
    "launch",
    "main",
    "parse_args",
]

READY_TIMEOUT = {"plant": 30.0, "driver": 30.0, "model": 30.0, "recorder": 30.0,
                 "ring": 30.0, "experiment": 30.0, "foxglove": 30.0, "discovery": 10.0,
                 "identify": 60.0}
"""Longest wait for each child to become ready [s]."""
RING_NODE = "dvt_recorder_ring"
"""Node name of the rolling recorder ``dvt-launch --ring-minutes`` starts."""
REARM_TIMEOUT = 30.0
"""Longest wait for the experiment's first phase, and for the model node's reset service to
appear and answer, when the launcher re-arms the change detector [s] (a loaded model node
answers its services after its queued samples)."""
EPISODE_DRAIN_S = 2.0
"""Longest wait [s], when the run ends with fewer than ``--episodes`` records while the
identifier still runs, for a record already published but not yet received."""
RECORDED_DVT_TOPICS = (*SAMPLE_TOPICS, *MODEL_TOPICS)
"""The high-rate streams a recording must hold (checked after the run)."""
DETECTOR_RATE = "detector.sample_rate_hz"
"""The model node's detector parameter the launcher sets to the controller rate."""

REFIT_NICE = "supervisor.refit_nice"
"""The identifier's parameter: the niceness of its refit process (default 19)."""
REALTIME_REFIT_NICE = -10
"""The refit's niceness (and its session's, ``/proc/<pid>/autogroup``) when the chain got
``--realtime`` priority: a process of the normal scheduler cannot delay a real-time one, so the
refit need not wait behind other jobs; it stays below the chain. Measured on this 2-core
machine with other jobs using 1.0-1.1 cores (load average 8-15), the first refit (1.4-2.2 s of
CPU): 9-16 s at niceness 0 (a session's fair share among the other jobs' sessions), 2.8 s at
-10."""


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


class _Realtime:
    """``--realtime``: puts a started child in the real-time scheduler (``SCHED_RR`` at its
    priority, :func:`~dvt_driver.system.launch_args.realtime_priorities`), right after its
    start: its interpreter has started no thread yet, and the threads it starts later (DDS,
    executors) inherit the policy. Without the right to (``EPERM``), one warning and the
    normal scheduler for every child."""

    def __init__(self, priority: int | None, say: Callable[[str], None]) -> None:
        self.priorities = realtime_priorities(priority)
        self.say = say
        self.denied = False
        self.applied: dict[str, int] = {}

    def __call__(self, child: Child) -> None:
        prio = self.priorities.get(child.name)
        if prio is None or self.denied:
            return
        try:
            os.sched_setscheduler(child.proc.pid, os.SCHED_RR, os.sched_param(prio))
        except PermissionError as exc:
            self.denied = True
            self.say(f"warning: --realtime: no right to real-time scheduling ({exc.strerror}); "
                     "the chain runs in the normal scheduler (allow it: root, CAP_SYS_NICE or "
                     "an rtprio limit in /etc/security/limits.conf)")
            return
        except (ProcessLookupError, OSError) as exc:  # it died at once: check_alive says so
            self.say(f"warning: --realtime: {child.name}: {exc}")
            return
        self.applied[child.name] = prio
        self.say(f"{child.name} (pid {child.proc.pid}) at real-time priority {prio} "
                 "(SCHED_RR)")


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
    """``--supervise`` while the run lasts: prints every episode record the identifier
    publishes on :data:`~dvt_model.contract.IDENTIFY_EPISODE` (received by the monitor) and says
    when ``--episodes`` are done."""

    def __init__(self, args: argparse.Namespace, monitor: Monitor,
                 say: Callable[[str], None]) -> None:
        self.args = args
        self.monitor = monitor
        self.say = say
        self.count = 0

    def done(self) -> bool:
        """Whether ``--episodes`` records arrived."""
        return self.args.episodes is not None and self.count >= self.args.episodes

    def poll(self) -> bool:
        """Print what arrived; ``True`` when ``--episodes`` records arrived (the run should
        end)."""
        records, bad = self.monitor.take_episodes()
        for text in bad:
            self.say(f"warning: {IDENTIFY_EPISODE}: a message that is not an episode record: "
                     f"{text}")
        for record in records:
            self.count += 1
            where = record.get("directory")
            self.say(episode_line(record) + (f" (report {where})" if where else ""))
        if records and self.done():
            self.say(f"{self.count} episode report(s): --episodes {self.args.episodes} done")
        return self.done()

    def drain(self, timeout: float, identifier_alive: Callable[[], bool]) -> None:
        """Wait at most ``timeout`` [s] for records on their way while fewer than
        ``--episodes`` arrived and the identifier runs."""
        deadline = time.monotonic() + timeout
        while (self.args.episodes is not None and not self.poll() and identifier_alive()
               and time.monotonic() < deadline):
            time.sleep(0.05)


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

    rate = rate_of(args)
    record = Path(args.record).resolve() if args.record else None
    topics = list(args.record_topics or DEFAULT_RECORD_TOPICS)
    truth = logdir / TRUTH_FILE
    identify_dir = logdir / IDENTIFY_DIR
    status = 0
    monitor: Monitor | None = None
    started = time.time()
    exp_status: int | None = None
    ident: Child | None = None
    say(f"logs in {logdir}")
    plant_pid: dict[str, int] = {}
    realtime = _Realtime(getattr(args, "realtime", None), say)

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
        monitor = Monitor(episodes=args.supervise)
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
            realtime(plant)
            plant_pid["pid"] = plant.proc.pid
            port = kids.wait_until("the plant's READY line",
                                   lambda: ready_line(plant.log), READY_TIMEOUT["plant"])
            say(f"plant ready on {port}")
        else:
            port = args.port
        # 2. driver
        driver_params = ["-p", f"port:={port}", "-p", "autostart:=true",
                         "-p", f"sample_rate_hz:={rate:g}"]
        if args.mode == "hw" and args.baud is not None:
            driver_params += ["-p", f"baud:={args.baud}"]
        realtime(kids.start("driver", [script("dvt_driver_node"), "--ros-args", *driver_params,
                                       *ros_params(args.driver_param, "--driver-param")]))
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
            realtime(kids.start("model", [script("dvt_model_node"), "--ros-args", *mine,
                                          *ros_params(args.model_param, "--model-param")]))
            kids.wait_until("the model node's /dvt/model/joint_states",
                            lambda: (monitor is not None
                                     and monitor.counts[MODEL_JOINT_STATES] > 0),
                            READY_TIMEOUT["model"])
            say("model node publishing")
        # the sample counts have done their work: drop the 1 kHz subscriptions now, before the
        # recorders, the detector's reference and the identifier (dropping them later, with
        # the identifier up, went with a 0.33-s stall of the chain in every 1-kHz episode run)
        monitor.quiet()
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
            realtime(exp)
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
            realtime(kids.start("recorder", [
                script("dvt-recorder"), "--ros-args", *remap, "-p", f"output:={record}",
                "-p", f"topics:=[{','.join(shlex.quote(t) for t in topics)}]",
                "-p", f"compression:={args.compression}",
                *ros_params(args.record_param, "--record-param")]))
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
            realtime(kids.start("ring", [
                script("dvt-recorder"), "--ros-args", "-r", f"__node:={RING_NODE}",
                "-p", f"output:={ring_dir}",
                "-p", f"topics:=[{','.join(shlex.quote(t) for t in ring_topics)}]",
                "-p", f"compression:={args.compression}",
                "-p", f"ring_minutes:={float(args.ring_minutes)!r}",  # a double, never '1'
                "-p", f"ring_segment_seconds:={float(args.ring_segment_seconds)!r}",
                *ros_params(args.record_param, "--record-param")]))
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
            if realtime.applied and REFIT_NICE not in given:
                # the sample path is real-time: no niceness of the refit can delay it, so the
                # refit runs ahead of other jobs, still below the chain
                own_id += ["-p", f"{REFIT_NICE}:={REALTIME_REFIT_NICE}"]
            ident = kids.start("identify", [
                script("dvt_identify_node"), "--ros-args", "-p", "supervisor.enabled:=true",
                *own_id, *ros_params(args.identify_param, "--identify-param")])
            kids.wait_until(f"dvt_identify_node's subscriptions on {MODEL_CHANGE} and "
                            f"{MODEL_RESIDUAL} and its publisher on {IDENTIFY_EPISODE}",
                            lambda: monitor is not None and all(
                                monitor.subscribed(IDENTIFY_NODE, t)
                                for t in (MODEL_CHANGE, MODEL_RESIDUAL))
                            and monitor.published(IDENTIFY_NODE, IDENTIFY_EPISODE),
                            READY_TIMEOUT["identify"])
            say(f"identifier supervising the loop; episode records on {IDENTIFY_EPISODE}, "
                f"reports in {identify_dir}/episodes")
        if args.foxglove:
            fox_args: list[str] = []
            if args.foxglove_port is not None:
                fox_args += ["-p", f"port:={args.foxglove_port}"]
            if args.foxglove_host is not None:
                fox_args += ["-p", f"host:={args.foxglove_host}"]
            fox = kids.start("foxglove", [script("dvt-foxglove"), "--ros-args", *fox_args,
                                          *ros_params(args.foxglove_param,
                                                       "--foxglove-param")])
            url = kids.wait_until("dvt-foxglove's READY line", lambda: ready_line(fox.log),
                                  READY_TIMEOUT["foxglove"])
            say(f"Foxglove: open a Foxglove WebSocket connection to {url}")
        monitor.quiet()
        # run
        deadline = time.monotonic() + args.duration if args.duration else None
        loop = _Supervision(args, monitor, say) if args.supervise else None
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
        if loop is not None and ident is not None and status == 0:
            loop.drain(EPISODE_DRAIN_S, ident.alive)
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
        status = finish_recording(args, record, logdir, rate, started, statuses, exp_status,
                                  status, say)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-launch``; returns the exit status."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    return launch(args)


if __name__ == "__main__":
    sys.exit(main())
