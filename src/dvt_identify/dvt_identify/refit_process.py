"""The supervisor's refit in a process of its own, at a lower priority (pure: no rclpy).

A refit is seconds of numerical work. In a thread of the identifier node it took a whole core
at the chain's priority, and at 1 kHz the chain (plant, driver, model node, recorder) dropped
samples on the two cores while it ran. :class:`RefitWorker` runs :func:`dvt_identify.refit.refit`
in a child process (``python -m dvt_identify.refit_process``) at the scheduling priority
``nice`` (19: it gets what the chain leaves; the kernel preempts it whenever a chain process
wakes up), set by the parent right after the start and by the child before it imports
anything. The child runs in a session of its own, and with the kernel's session autogroups
(``/proc/sys/kernel/sched_autogroup_enabled``) a niceness counts only within the session:
against other sessions' processes (the chain's, other jobs') the session's own niceness
decides, ``/proc/<pid>/autogroup``. Both are set (:func:`set_priority`); a niceness below the
current one needs the right to (root or ``CAP_SYS_NICE``), else the child keeps the one it has
and its log says so.

* **Warm.** The child is started ahead of the first job (:meth:`RefitWorker.start`): it imports
  the identification code and, given the refit's settings (``warm``), refits 3 s of simulated
  data once (:func:`warm_up`: the fit's compiled code, ``numba``'s, is built then; after a change
  of that code the first refit cost 8.9 s of CPU instead of 1.6), while the loop waits for data,
  so a job costs the fit, not imports and compilation. It serves one job at a time, and the next
  one in the same process.
* **Protocol.** One JSON line per job on the child's stdin (:func:`job_line`), one JSON line per
  answer on its stdout (``{"id": ..., "outcome": ...}``, :func:`outcome_to_dict`); everything
  else the child writes (the pipeline's warnings) goes to its log file. A reader thread in the
  parent takes the answers; :meth:`RefitWorker.poll` never blocks.
* **Bounded and reaped.** :meth:`RefitWorker.cancel` (the supervisor gave up: ``fit_timeout_s``,
  the node stops) kills the child's process group and waits for it (bounded); a child that dies
  during a job (a crash, the OOM killer, a signal) is reaped and reported by :meth:`poll` as a
  :class:`~dvt_identify.supervisor.FitOutcome` with ``crashed`` set and the exit status and
  the end of its log in ``error``; the next job starts a new child. The child dies with its
  parent (``PR_SET_PDEATHSIG``) and exits at the end of its stdin.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, replace
from pathlib import Path
from typing import IO, Any

import numpy as np

from dvt_identify.errors import SupervisorError
from dvt_identify.supervisor import FitOutcome, RequestFit

__all__ = ["DEFAULT_NICE", "RefitWorker", "job_line", "main", "outcome_from_dict",
           "outcome_to_dict", "set_priority", "warm_up"]

DEFAULT_NICE = 19
"""Niceness of the refit process: the lowest priority (the chain runs at 0)."""
STOP_TIMEOUT_S = 5.0
"""Longest wait for the child to exit after a signal (then SIGKILL, then the same again) [s]."""
WARM_MODULES = ("dvt_identify.refit", "dvt_identify.pipeline", "dvt_identify.loop",
                "dvt_identify.reference", "dvt_identify.linref", "dvt_identify.report",
                "dvt_model.config", "dvt_model.recording", "scipy.optimize", "scipy.stats",
                "scipy.signal")
"""What the child imports before its first job."""
_PR_SET_PDEATHSIG = 1
_READY = "READY"


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, tuple | set):
        return list(obj)
    return str(obj)


def outcome_to_dict(outcome: FitOutcome) -> dict[str, Any]:
    """A :class:`FitOutcome` as JSON-ready values (:func:`outcome_from_dict` reads them)."""
    return {"new_errors": np.asarray(outcome.new_errors, dtype=float).tolist(),
            "current_errors": np.asarray(outcome.current_errors, dtype=float).tolist(),
            "new_parameters": dict(outcome.new_parameters),
            "current_parameters": dict(outcome.current_parameters),
            "summary": dict(outcome.summary), "error": outcome.error,
            "crashed": outcome.crashed}


def outcome_from_dict(data: Mapping[str, Any]) -> FitOutcome:
    """The :class:`FitOutcome` of :func:`outcome_to_dict`'s values.

    Raises:
        SupervisorError: not such a mapping (naming the field).
    """
    try:
        return FitOutcome(new_errors=np.asarray(data["new_errors"], dtype=float),
                          current_errors=np.asarray(data["current_errors"], dtype=float),
                          new_parameters=dict(data["new_parameters"]),
                          current_parameters=dict(data["current_parameters"]),
                          summary=dict(data["summary"]), error=str(data["error"]),
                          crashed=bool(data.get("crashed", False)))
    except (KeyError, TypeError, ValueError) as exc:
        raise SupervisorError(f"refit answer: not a fit outcome ({exc!r})") from exc


def job_line(ident: int, snapshot: str | Path, request: RequestFit,
             current: Mapping[str, Any], work_dir: str | Path,
             settings: Mapping[str, Any]) -> str:
    """One job for the child: JSON on one line (``settings``:
    :meth:`dvt_identify.refit.RefitSettings.to_dict`)."""
    return json.dumps({"id": ident, "snapshot": str(snapshot), "request": asdict(request),
                       "current": dict(current), "work_dir": str(work_dir),
                       "settings": dict(settings)}, default=_json_default) + "\n"


def _request(data: Mapping[str, Any]) -> RequestFit:
    return RequestFit(episode=int(data["episode"]),
                      estimation=(float(data["estimation"][0]), float(data["estimation"][1])),
                      validation=(float(data["validation"][0]), float(data["validation"][1])),
                      outputs=tuple(str(o) for o in data["outputs"]), stage=str(data["stage"]))


def _status_text(code: int) -> str:
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by signal {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit status {code}"


class RefitWorker:
    """The refit process (see the module docstring). Not thread-safe: one caller thread.

    Args:
        log_path: the child's log (appended; its stderr and stray stdout).
        nice: the child's niceness, -20..19 (below the parent's: only with the right to).
        env: the child's environment (default: this process's).
        python: the interpreter (default: this one, the venv's).
        warm: the refit's settings (:meth:`dvt_identify.refit.RefitSettings.to_dict`): the
            child refits simulated data with them once before it serves (:func:`warm_up`);
            ``None``: imports only.
    """

    def __init__(self, log_path: str | Path, nice: int = DEFAULT_NICE,
                 env: Mapping[str, str] | None = None, python: str = sys.executable,
                 warm: Mapping[str, Any] | None = None) -> None:
        if isinstance(nice, bool) or not isinstance(nice, int) or not -20 <= nice <= 19:
            raise SupervisorError(f"refit niceness: expected an integer -20..19, got {nice!r}")
        self.log_path = Path(log_path)
        self.nice = nice
        self.env = dict(os.environ if env is None else env)
        self.python = python
        self.warm = dict(warm) if warm is not None else None
        self.proc: subprocess.Popen[bytes] | None = None
        self._answers: queue.SimpleQueue[dict[str, Any] | None] = queue.SimpleQueue()
        self._ready = threading.Event()
        self._job: int | None = None
        self._next = 0
        self.started = 0
        """Child processes started so far."""
        self.crashes = 0
        """Jobs whose child died before answering."""
        self.job_started_s: float | None = None

    # ------------------------------------------------------------------ the child
    @property
    def pid(self) -> int | None:
        """The running child's pid, ``None`` without one."""
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None

    @property
    def busy(self) -> bool:
        """Whether a job is out (submitted, not yet answered by :meth:`poll`)."""
        return self._job is not None

    def start(self) -> None:
        """Start the child unless it runs (it warms up while idle)."""
        if self.proc is not None and self.proc.poll() is None:
            return
        self._reap()
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                [self.python, "-m", "dvt_identify.refit_process", "--nice", str(self.nice),
                 "--parent", str(os.getpid()),
                 *(["--warm", json.dumps(self.warm)] if self.warm is not None else [])],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, env=self.env,
                start_new_session=True)
        # at once (the child sets it too, after its interpreter started)
        set_priority(self.nice, self.proc.pid)
        self.started += 1
        self._answers = queue.SimpleQueue()
        self._ready = threading.Event()
        stdout = self.proc.stdout
        threading.Thread(target=self._read, args=(stdout, self._answers, self._ready),
                         daemon=True, name="dvt-refit-reader").start()

    @property
    def ready(self) -> bool:
        """Whether the running child is warm (its code imported, its priority set, bound to
        die with this process)."""
        return self._ready.is_set() and self.pid is not None

    @staticmethod
    def _read(stream: IO[bytes] | None, answers: queue.SimpleQueue[dict[str, Any] | None],
              ready: threading.Event) -> None:
        """The reader thread: the READY line, then every JSON object line of the child's
        stdout, then ``None``."""
        if stream is None:
            answers.put(None)
            return
        with contextlib.suppress(OSError, ValueError):
            for raw in stream:
                line = raw.decode(errors="replace").strip()
                if line == _READY:
                    ready.set()
                if not line.startswith("{"):
                    continue
                with contextlib.suppress(ValueError):
                    msg = json.loads(line)
                    if isinstance(msg, dict):
                        answers.put(msg)
        answers.put(None)

    # ------------------------------------------------------------------ jobs
    def submit(self, snapshot: str | Path, request: RequestFit, current: Mapping[str, Any],
               work_dir: str | Path, settings: Mapping[str, Any]) -> int:
        """Send one refit job (starting the child if needed); returns its id.

        Raises:
            SupervisorError: a job is already out, or the child cannot take it.
        """
        if self._job is not None:
            raise SupervisorError("refit process busy: the previous refit is still running")
        self.start()
        proc = self.proc
        if proc is None or proc.stdin is None:  # pragma: no cover - start() made one
            raise SupervisorError("refit process not running")
        self._next += 1
        line = job_line(self._next, snapshot, request, current, work_dir, settings)
        try:
            proc.stdin.write(line.encode())
            proc.stdin.flush()
        except OSError as exc:  # it died while idle: a new one takes the job
            self._reap()
            self.start()
            if self.proc is None or self.proc.stdin is None:  # pragma: no cover
                raise SupervisorError(f"refit process not running ({exc})") from exc
            self.proc.stdin.write(line.encode())
            self.proc.stdin.flush()
        self._job = self._next
        self.job_started_s = time.monotonic()
        return self._next

    def poll(self) -> FitOutcome | None:
        """The answer of the job that is out, once it is there (a crashed child's answer is a
        ``crashed`` outcome naming how it ended); ``None`` while it runs or with no job out."""
        if self._job is None:
            return None
        while True:
            try:
                msg = self._answers.get_nowait()
            except queue.Empty:
                break
            if msg is None:  # the child closed its stdout: it is gone
                return self._crashed()
            if msg.get("id") == self._job:
                self._job = None
                try:
                    return outcome_from_dict(msg.get("outcome") or {})
                except SupervisorError as exc:
                    return FitOutcome(error=str(exc))
        if self.proc is None or self.proc.poll() is not None:
            return self._crashed()
        return None

    def _crashed(self) -> FitOutcome:
        self._job = None
        self.crashes += 1
        code = self._reap()
        pid = self.proc.pid if self.proc is not None else None
        tail = self.log_tail()
        return FitOutcome(crashed=True, error=(
            f"the refit process (pid {pid}) died during the refit ({_status_text(code)})"
            + (f"; its log {self.log_path} ends: {tail}" if tail else "")))

    def log_tail(self, chars: int = 600) -> str:
        """The end of the child's log, one line (empty if none)."""
        try:
            text = self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""
        return " | ".join(line.strip() for line in text.splitlines() if line.strip())

    def cancel(self) -> bool:
        """Abandon the job that is out: kill the child (its process group) and reap it; the
        next job starts a new child. Returns whether a job was out."""
        was = self._job is not None
        self._job = None
        if was:
            self._kill()
        return was

    # ------------------------------------------------------------------ stopping
    def _kill(self) -> None:
        proc = self.proc
        if proc is None:
            return
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
        self._reap()

    def _reap(self) -> int:
        """Wait (bounded) for the child to be gone and close its pipes; its exit code."""
        proc = self.proc
        if proc is None:
            return 0
        try:
            code = proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            code = proc.wait(timeout=STOP_TIMEOUT_S)
        for stream in (proc.stdin, proc.stdout):
            if stream is not None:
                with contextlib.suppress(OSError):
                    stream.close()
        return int(code)

    def close(self) -> None:
        """Stop the child (end of its stdin; after :data:`STOP_TIMEOUT_S`, or at once with a
        job out, SIGKILL of its group) and reap it. Idempotent."""
        proc = self.proc
        if proc is None:
            return
        if self._job is not None:
            self.cancel()
        elif proc.poll() is None and proc.stdin is not None:
            with contextlib.suppress(OSError):
                proc.stdin.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=STOP_TIMEOUT_S)
        self._kill()
        self.proc = None


# ------------------------------------------------------------------ the child's side
def set_priority(nice: int, pid: int = 0) -> tuple[int, str]:
    """Give process ``pid`` (0: this one) the niceness ``nice``, and its session's autogroup
    the same (``/proc/<pid>/autogroup``, when the kernel has autogroups; the refit process is
    alone in its session). Returns the niceness now and what could not be set ("" if
    everything was)."""
    problems = []
    try:
        os.setpriority(os.PRIO_PROCESS, pid, nice)
    except OSError as exc:
        problems.append(f"niceness {nice}: {exc.strerror}")
    group = Path(f"/proc/{pid or os.getpid()}/autogroup")
    if group.exists():
        try:
            group.write_text(f"{nice}\n")
        except OSError as exc:
            problems.append(f"autogroup niceness {nice}: {exc.strerror}")
    try:
        now = os.getpriority(os.PRIO_PROCESS, pid)
    except OSError:
        now = nice
    return now, "; ".join(problems)


def _die_with(parent: int) -> None:
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if parent and os.getppid() != parent:  # the parent died before the prctl
        os._exit(3)


def _serve(proto: IO[str]) -> int:
    """Answer job lines from stdin until its end."""
    from dvt_identify.refit import RefitSettings, refit

    for line in sys.stdin:
        if not line.strip():
            continue
        ident: Any = None
        cpu0, wall0 = time.process_time(), time.monotonic()
        try:
            job = json.loads(line)
            ident = job["id"]
            outcome = refit(job["snapshot"], _request(job["request"]), job["current"],
                            job["work_dir"], RefitSettings.from_dict(job["settings"]))
        except Exception as exc:  # an answer, never a dead child (a crash is the kernel's)
            outcome = FitOutcome(error=f"refit: {type(exc).__name__}: {exc}")
        # its CPU time: what the refit cost, apart from what it waited for a core
        outcome = replace(outcome, summary={
            **outcome.summary, "refit_cpu_seconds": round(time.process_time() - cpu0, 3),
            "refit_process_seconds": round(time.monotonic() - wall0, 3),
            "refit_niceness": os.getpriority(os.PRIO_PROCESS, 0)})
        proto.write(json.dumps({"id": ident, "outcome": outcome_to_dict(outcome)},
                               default=_json_default) + "\n")
        proto.flush()
    return 0


def warm_up(settings: Mapping[str, Any]) -> str:
    """Refit 3 s of the ``physical`` model's simulated response to a PRBS motor current with
    Coulomb friction on both outputs (1 kHz, the DVT's topics) once with ``settings`` (the
    first stage: the structure held; the augment loop scores and fits the candidates): the
    fit's compiled code and caches are built now, not in the first episode. Returns what happened
    (one line; a description that does not fit the DVT's data says so, and the child serves
    anyway)."""
    import tempfile

    from dvt_identify.refit import RefitSettings, refit
    from dvt_identify.supervisor import STAGE_EFFECTS
    from dvt_model.hybrid import HybridModel
    from dvt_model.params import load_parameters
    from dvt_model.recording import write_run
    from dvt_model.terms import parse_terms

    t0 = time.monotonic()
    n = 3000
    t = np.arange(n) * 1e-3
    rng = np.random.default_rng(0)
    im = np.repeat(rng.choice([-2.5, 2.5], size=n // 30 + 1), 30)[:n]
    ib = np.zeros((n, 3))
    friction = parse_terms([{"kind": "coulomb", "member": [1.0, 0.0], "Fc": 0.05},
                            {"kind": "coulomb", "member": [0.0, 1.0], "Fc": 0.2}])
    sim = HybridModel.from_params(load_parameters("physical"),
                                  extra_force=friction.extra_force).simulate(t, im, ib)
    speeds = sim.omega + 0.05 * rng.standard_normal(sim.omega.shape)
    base = 1_000_000_000
    stamps = base * 10**9 + np.round(t * 1e9).astype(np.int64)
    with tempfile.TemporaryDirectory(prefix="dvt-refit-warm-") as tmp:
        bag = write_run(Path(tmp) / "snapshot", stamps, speeds, np.column_stack([im, ib]))
        req = RequestFit(0, (base + 0.1, base + 2.0), (base + 2.0, base + 2.99), ("sun_shaft",),
                         STAGE_EFFECTS)
        out = refit(bag, req, {"params": "physical"}, Path(tmp) / "work",
                    RefitSettings.from_dict(settings))
    return (f"warm-up refit in {time.monotonic() - t0:.1f} s"
            + (f" (it failed, the child serves anyway: {out.error[:200]})" if out.error else
               f" (accepted {out.summary.get('accepted')})"))


def main(argv: list[str] | None = None) -> int:
    """The child: lower the priority, die with the parent, warm up, serve jobs."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m dvt_identify.refit_process")
    p.add_argument("--nice", type=int, default=DEFAULT_NICE)
    p.add_argument("--parent", type=int, default=0)
    p.add_argument("--warm", default=None, help="the refit's settings (JSON): warm up with them")
    a = p.parse_args(argv)
    nice, problem = set_priority(a.nice)
    _die_with(a.parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops it (stdin, SIGKILL)
    # the protocol gets the real stdout; anything else written to stdout goes to the log
    proto = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    t0 = time.monotonic()
    for module in WARM_MODULES:  # the warm-up: the fit's code, imported while idle
        importlib.import_module(module)
    done = f"imports in {time.monotonic() - t0:.1f} s"
    if a.warm:
        try:
            done += "; " + warm_up(json.loads(a.warm))
        except Exception as exc:  # a warm-up is an optimisation: the child serves anyway
            done += f"; warm-up refit failed ({type(exc).__name__}: {exc})"
    print(f"refit process {os.getpid()}: niceness {nice}"
          + (f" (not set: {problem})" if problem else "") + f", warm: {done}",
          file=sys.stderr, flush=True)
    proto.write(_READY + "\n")
    proto.flush()
    return _serve(proto)


if __name__ == "__main__":
    sys.exit(main())
