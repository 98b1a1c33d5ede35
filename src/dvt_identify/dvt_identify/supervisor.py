"""The identifier's supervisor: alarm -> wait -> refit -> decide -> push -> watch -> keep/roll back.

A pure state machine (no ROS, no fitting). The identifier node feeds it events and performs the
:class:`Action` objects it returns; every transition also returns a :class:`Diagnostic` (one line
for ``/diagnostics``) and each finished episode a :class:`Report` (the episode record, a dict).

States (:class:`State`)::

    idle --alarm--> waiting --min_post_change_s of data--> refitting --fit_done--> (deciding)
      (deciding) --new not significantly better--> idle               [outcome "not_better"]
      (deciding) --better, but its structure at a bound--> idle        [outcome "suspect"]
      (deciding) --better--> pushing --push_done(ok)--> watching --watch_s--> idle [confirmed]
                                                         watching --worse--> rolling_back
      rolling_back --rollback_done--> idle                              [outcome "rolled_back"]

Two refit stages (:data:`STAGE_EFFECTS` first, then :data:`STAGE_FULL`): the first refit
(``stage`` of :class:`RequestFit`: ``"effects"``) comes ``min_post_change_s`` after the change,
on a few seconds of data: the caller holds the model in use's structure (its mass and damping)
and looks for the effect that changed on top of it - the parameters that change first (a
friction step, a windage) - which a few seconds determine, while the structure's own
parameters they do not. If that refit is not pushed (not better, suspect, or failed on the
data) and ``full_post_change_s`` > 0, the supervisor waits until ``full_post_change_s`` of
post-change data exist and requests the full refit (``"full"``: everything free, validated on
``full_validation_s``) in the same episode; its decision ends the episode. A refit whose
process crashed (``FitOutcome.crashed``) ends the episode at once: outcome ``refit_crashed``.

* **waiting**: the estimation data start ``settle_s`` after the alarm's estimated change time,
  but not before the detection (``stamp_s``: the estimated change time can be seconds early);
  the supervisor waits until ``min_post_change_s - settle_s`` of data after that start
  exist. Another alarm while waiting restarts the wait from its change time (the data must
  come from one regime).
* **refitting**: :class:`RequestFit` names the estimation window ``[start,
  now - validation_s]`` (at most ``max_estimation_s``, the newest part) and the validation window
  ``[now - validation_s, now]`` (the newest held-out slice), ROS time [s]; for the full stage
  ``full_validation_s`` instead of ``validation_s``. The caller fits on the
  estimation window, simulates the new and the current model on the validation window and calls
  :meth:`Supervisor.fit_done` with both error series (:class:`FitOutcome`).
* **deciding**: push only if the new model's validation error beats the current one's on the
  same slice: Diebold-Mariano (:func:`dvt_identify.uncertainty.diebold_mariano`, HAC variance,
  per-output weights ``1 / mean square of the current model's error``) one-sided p-value below
  ``alpha`` and relative loss reduction at least ``min_relative_gain``. A new model whose
  structure parameters ended at a bound their start was not at (``summary
  ["structure_at_bounds"]``, e.g. M22 at its lower bound 1e-6: a degenerate optimum the data do
  not determine) is not pushed - outcome ``suspect`` - unless its relative loss reduction is
  at least ``suspect_min_relative_gain`` (0.5: it halves the weighted held-out loss).
* **pushing**: :class:`Push` (the new parameters); the caller pushes and calls
  :meth:`~Supervisor.push_done`.
* **watching**: for ``watch_s`` after the push (ignoring the first ``watch_settle_s``), the live
  residual's RMS per output (:meth:`~Supervisor.observe`, 1-s bins) is compared with its level
  over the ``baseline_s`` before the push (post-change, old model). If some output's RMS grew by
  more than ``rollback_tolerance`` (ratio ``> 1 + tol``) - or fewer than ``min_watch_samples``
  live samples arrived, so the push cannot be verified - :class:`Rollback` restores the previous
  parameters. The ratio to the new model's validation RMS (``expected``) is reported.
* Timeouts (``fit_timeout_s``, ``push_timeout_s``) end the episode without a push (a push that
  timed out is rolled back, in case it arrived). An alarm during refitting, pushing, watching or
  rolling back is recorded and, if its change is later than the episode's estimation start,
  starts the next episode when this one ends.

Times are ROS time [s] (the residual's stamps and the node clock); residuals [rad/s].
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from dvt_identify.errors import SupervisorError
from dvt_identify.uncertainty import diebold_mariano

PREFIX = "supervisor"
"""Prefix of the identifier-node parameters of the supervisor (``supervisor.watch_s``...)."""
STAGE_EFFECTS = "effects"
"""The first refit of an episode: effects on top of the model in use, its structure held."""
STAGE_FULL = "full"
"""The second refit (if the first was not pushed): every parameter free, on a longer window."""


class State(StrEnum):
    """Supervisor states."""

    IDLE = "idle"
    WAITING = "waiting"
    REFITTING = "refitting"
    PUSHING = "pushing"
    WATCHING = "watching"
    ROLLING_BACK = "rolling_back"


@dataclass(frozen=True)
class SupervisorConfig:
    """Settings [s unless stated]; :meth:`validated` checks them (errors name
    ``supervisor.<field>`` and the value)."""

    min_post_change_s: float = 5.0
    settle_s: float = 0.5
    validation_s: float = 1.5
    full_post_change_s: float = 60.0
    full_validation_s: float = 15.0
    max_estimation_s: float = 300.0
    alpha: float = 0.05
    min_relative_gain: float = 0.1
    suspect_min_relative_gain: float = 0.5
    fit_timeout_s: float = 600.0
    push_timeout_s: float = 10.0
    watch_s: float = 60.0
    watch_settle_s: float = 2.0
    baseline_s: float = 30.0
    rollback_tolerance: float = 0.10
    min_watch_samples: int = 1000
    history_s: int = 3600
    names: tuple[str, ...] = ("sun_shaft", "carrier3")

    def validated(self) -> SupervisorConfig:
        """``self`` if admissible, else :class:`SupervisorError` naming the field."""
        def need(name: str, ok: bool, what: str) -> None:
            if not ok:
                raise SupervisorError(f"{PREFIX}.{name}: expected {what}, got "
                                      f"{getattr(self, name)!r}")

        def num(name: str) -> float:
            v = getattr(self, name)
            need(name, not isinstance(v, bool) and isinstance(v, int | float)
                 and math.isfinite(v), "a finite number")
            return float(v)

        for name in ("min_post_change_s", "validation_s", "max_estimation_s", "fit_timeout_s",
                     "push_timeout_s", "watch_s", "baseline_s"):
            need(name, num(name) > 0, "a time > 0 s")
        for name in ("settle_s", "watch_settle_s", "min_relative_gain", "rollback_tolerance",
                     "suspect_min_relative_gain", "full_post_change_s", "full_validation_s"):
            need(name, num(name) >= 0, "a number >= 0")
        need("alpha", 0 < num("alpha") < 1, "a significance level in (0, 1)")
        need("min_post_change_s", self.min_post_change_s > self.settle_s + self.validation_s,
             f"more than settle_s + validation_s = {self.settle_s + self.validation_s:g} s "
             "(some estimation data must remain)")
        if self.full_post_change_s > 0:
            need("full_post_change_s", self.full_post_change_s > max(
                self.min_post_change_s, self.settle_s + self.full_validation_s),
                f"0 (no full refit) or more than min_post_change_s = "
                f"{self.min_post_change_s:g} s and settle_s + full_validation_s = "
                f"{self.settle_s + self.full_validation_s:g} s")
            need("full_validation_s", self.full_validation_s > 0, "a time > 0 s")
        need("watch_s", self.watch_s > self.watch_settle_s,
             f"more than watch_settle_s = {self.watch_settle_s:g} s")
        need("min_watch_samples", isinstance(self.min_watch_samples, int)
             and not isinstance(self.min_watch_samples, bool) and self.min_watch_samples >= 1,
             "an integer >= 1")
        need("history_s", isinstance(self.history_s, int) and not isinstance(self.history_s, bool)
             and self.history_s >= self.baseline_s + self.watch_s + 1,
             f"an integer >= baseline_s + watch_s + 1 = {self.baseline_s + self.watch_s + 1:g}")
        need("names", bool(self.names) and len(set(self.names)) == len(self.names),
             "distinct output names")
        return self

    @classmethod
    def parameters(cls) -> dict[str, float | int]:
        """The node parameters (``supervisor.<field>`` without the prefix) and defaults."""
        d = cls()
        return {f.name: getattr(d, f.name) for f in fields(cls) if f.name != "names"}


# ------------------------------------------------------------------------------- actions
@dataclass(frozen=True)
class Diagnostic:
    """One ``/diagnostics`` line: ``level`` 0 OK, 1 WARN, 2 ERROR; ``values`` key/values."""

    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class RequestFit:
    """Fit on ``estimation`` = (t0, t1), validate on ``validation`` = (t1, t2) [s, ROS time];
    the changed outputs are ``outputs``; ``stage`` :data:`STAGE_EFFECTS` (hold the model in
    use's structure, fit the effects on top of it) or :data:`STAGE_FULL` (everything free).
    Answer with :meth:`Supervisor.fit_done`."""

    episode: int
    estimation: tuple[float, float]
    validation: tuple[float, float]
    outputs: tuple[str, ...]
    stage: str = STAGE_EFFECTS


@dataclass(frozen=True)
class Push:
    """Push ``parameters`` (the new model) to the model node in one transaction
    (:func:`dvt_identify.node.push_parameters`); answer with ``push_done``."""

    episode: int
    parameters: Mapping[str, Any]


@dataclass(frozen=True)
class Rollback:
    """Push ``parameters`` (the model before the episode) back in one transaction, like
    :class:`Push`; answer ``rollback_done``."""

    episode: int
    parameters: Mapping[str, Any]
    reason: str


@dataclass(frozen=True)
class Report:
    """The record of a finished episode (JSON-ready dict, see :class:`Supervisor`)."""

    episode: int
    record: dict[str, Any]


Action = Diagnostic | RequestFit | Push | Rollback | Report


@dataclass(frozen=True)
class FitOutcome:
    """What the caller's refit produced.

    ``new_errors`` and ``current_errors``: (N, ny) simulated output errors [rad/s] of the new
    and the current model on the validation window (same samples); ``new_parameters`` /
    ``current_parameters``: what :class:`Push` / :class:`Rollback` carry; ``summary``: what the
    refit found (changed effects/parameters, fit figures) for the report - its
    ``structure_at_bounds`` (a list of ``"M22 = 1e-06 at its lower bound 1e-06"``) makes the
    supervisor refuse the push unless it is clearly better (``suspect_min_relative_gain``);
    ``error``: non-empty if the fit failed (then the arrays may be empty); ``crashed``: the
    refit's process died (a crash, a kill) instead of answering (``error`` says how).
    """

    new_errors: ArrayLike = ()
    current_errors: ArrayLike = ()
    new_parameters: Mapping[str, Any] = field(default_factory=dict)
    current_parameters: Mapping[str, Any] = field(default_factory=dict)
    summary: Mapping[str, Any] = field(default_factory=dict)
    error: str = ""
    crashed: bool = False


# --------------------------------------------------------------------------- live residual
class ResidualHistory:
    """Per-output sums of squares of the live residual in 1-s bins (O(1) per sample)."""

    def __init__(self, outputs: int, history_s: int) -> None:
        self.outputs = outputs
        self._bins: deque[list[float]] = deque(maxlen=history_s)  # [second, n, ss_0, ss_1..]
        self.samples = 0

    def add(self, stamp_s: float, residual: Sequence[float]) -> None:
        """One residual sample (stamp [s], values [rad/s]); non-finite samples are skipped."""
        if len(residual) != self.outputs:
            raise SupervisorError(f"residual: expected {self.outputs} values, got "
                                  f"{len(residual)}")
        for v in residual:
            if not math.isfinite(v):
                return
        sec = math.floor(stamp_s)
        if not self._bins or self._bins[-1][0] != sec:
            if self._bins and sec < self._bins[-1][0]:
                return  # out of order: ignored
            self._bins.append([float(sec), 0.0, *([0.0] * self.outputs)])
        b = self._bins[-1]
        b[1] += 1.0
        for i, v in enumerate(residual):
            b[2 + i] += v * v
        self.samples += 1

    def rms(self, t0: float, t1: float) -> tuple[list[float], int]:
        """Per-output RMS [rad/s] of the samples in 1-s bins within ``[t0, t1)``, and their
        count (RMS ``nan`` without samples)."""
        n = 0.0
        ss = [0.0] * self.outputs
        lo, hi = math.floor(t0), math.floor(t1)
        for b in self._bins:
            if lo <= b[0] < hi:
                n += b[1]
                for i in range(self.outputs):
                    ss[i] += b[2 + i]
        if n == 0:
            return [math.nan] * self.outputs, 0
        return [math.sqrt(s / n) for s in ss], int(n)


# ---------------------------------------------------------------------------- supervisor
def _rms(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.sqrt(np.mean(a * a, axis=0))]


class Supervisor:
    """The state machine (see the module docstring). Methods return the actions to perform.

    The episode record (``Report.record``) holds: ``episode``, ``change_s``, ``detected_s``,
    ``outputs``, ``alarms`` (the alarms' dicts), ``estimation``/``validation`` windows,
    ``refit`` (the fit summary), ``error_before``/``error_after`` (validation RMS per output of
    the current and the new model [rad/s]), ``test`` (Diebold-Mariano figures), ``pushed``,
    ``push_s``, ``live_before``/``live_after``/``expected`` (RMS per output [rad/s]),
    ``live_ratio``, ``rolled_back``, ``outcome``, ``reason``, ``timings`` [s] and ``steps``
    (every transition: time, state, message); ``stage`` (the last refit's, :data:`STAGE_EFFECTS`
    or :data:`STAGE_FULL`) and ``stages`` (per refit: ``stage``, ``estimation``, ``validation``,
    ``refit``, ``error_before``, ``error_after``, ``test``, ``decision``, ``reason``,
    ``fit_s``); ``estimation`` ... ``test`` are the last refit's.
    """

    def __init__(self, config: SupervisorConfig | None = None) -> None:
        self.config = (config or SupervisorConfig()).validated()
        self.state = State.IDLE
        self.history = ResidualHistory(len(self.config.names), self.config.history_s)
        self.episodes = 0
        self.reports: list[dict[str, Any]] = []
        self._ep: dict[str, Any] | None = None
        self._pending: dict[str, Any] | None = None
        self._since = 0.0
        self._change = 0.0
        self._detected = 0.0
        self._push_s = 0.0
        self._fit: FitOutcome | None = None
        self._stage = STAGE_EFFECTS
        self.ignore_before_s = -math.inf
        """Alarms detected before this time [s] are ignored (the node sets its start: the
        alarm topic is latched, a restarted identifier must not refit old changes)."""
        self.ignored_alarms = 0

    # ---------------------------------------------------------------- helpers
    def _step(self, now: float, state: State, message: str, level: int = 0,
              **values: Any) -> Diagnostic:
        self.state = state
        self._since = now
        vals = {"state": state.value, **{k: str(v) for k, v in values.items()}}
        if self._ep is not None:
            vals["episode"] = str(self._ep["episode"])
            self._ep["steps"].append({"t": now, "state": state.value, "message": message})
        return Diagnostic(level, f"supervisor: {message}", vals)

    def _finish(self, now: float, outcome: str, reason: str, level: int = 0) -> list[Action]:
        ep = self._ep
        if ep is None:  # pragma: no cover - guarded by the states
            return []
        ep["outcome"] = outcome
        ep["reason"] = reason
        ep["timings"]["total_s"] = now - ep["detected_s"]
        out: list[Action] = [self._step(now, State.IDLE, f"episode {ep['episode']}: {outcome} "
                                        f"({reason})", level, outcome=outcome)]
        out.append(Report(ep["episode"], ep))
        self.reports.append(ep)
        self._ep = None
        self._fit = None
        pending, self._pending = self._pending, None
        if pending is not None and pending["change_s"] > ep["estimation_start_s"]:
            out += self.on_alarm(pending, now)
        return out

    # ----------------------------------------------------------------- events
    def observe(self, stamp_s: float, residual: Sequence[float]) -> None:
        """One live residual sample (the model node's ``/dvt/model/residual``) [s], [rad/s]."""
        self.history.add(stamp_s, residual)

    def on_alarm(self, alarm: Mapping[str, Any] | Any, now_s: float) -> list[Action]:
        """A change alarm (a :class:`dvt_model.detect.Alarm` or its dict: ``change_s``,
        ``stamp_s``, ``name``...). Starts an episode, restarts the wait, or is kept for later."""
        a = dict(alarm) if isinstance(alarm, Mapping) else dict(alarm.to_dict())
        for key in ("change_s", "stamp_s"):
            v = a.get(key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise SupervisorError(f"alarm.{key}: expected a time [s], got {v!r}")
        change = float(a["change_s"])
        name = str(a.get("name", ""))
        if float(a["stamp_s"]) < self.ignore_before_s:
            self.ignored_alarms += 1
            return [Diagnostic(0, f"supervisor: alarm on {name or '?'} detected at "
                                  f"{float(a['stamp_s']):.3f} s, before this supervisor started "
                                  f"({self.ignore_before_s:.3f} s): an earlier run's, ignored",
                               {"state": self.state.value,
                                "ignored_alarms": str(self.ignored_alarms)})]
        if self.state is State.IDLE:
            self.episodes += 1
            self._ep = {
                "episode": self.episodes, "change_s": change, "detected_s": float(a["stamp_s"]),
                "outputs": [name] if name else [], "alarms": [a],
                "estimation": None, "validation": None, "estimation_start_s": change,
                "refit": None, "error_before": None, "error_after": None, "test": None,
                "pushed": False, "push_s": None, "live_before": None, "live_after": None,
                "expected": None, "live_ratio": None, "rolled_back": False, "outcome": None,
                "reason": "", "timings": {"alarm_s": now_s}, "steps": [],
                "stage": STAGE_EFFECTS, "stages": []}
            self._change = change
            self._detected = float(a["stamp_s"])
            self._stage = STAGE_EFFECTS
            return [self._step(now_s, State.WAITING,
                               f"change on {name or '?'} at {change:.3f} s; waiting "
                               f"{self.config.min_post_change_s:g} s of post-change data",
                               change_s=f"{change:.3f}")]
        ep = self._ep
        if ep is None:  # pragma: no cover
            return []
        ep["alarms"].append(a)
        if name and name not in ep["outputs"]:
            ep["outputs"].append(name)
        if self.state is State.WAITING:
            if change >= self._change:
                self._change = change
                self._detected = float(a["stamp_s"])
            ep["estimation_start_s"] = self._change
            self._stage = STAGE_EFFECTS  # another regime: the first refit again
            return [self._step(now_s, State.WAITING,
                               f"another change on {name or '?'} at {change:.3f} s; waiting "
                               "restarts from it", change_s=f"{self._change:.3f}")]
        if self._pending is None or change > self._pending["change_s"]:
            self._pending = a
        return [Diagnostic(1, f"supervisor: alarm on {name or '?'} at {change:.3f} s during "
                              f"{self.state.value}; handled after episode {ep['episode']}",
                           {"state": self.state.value, "episode": str(ep["episode"])})]

    def tick(self, now_s: float) -> list[Action]:
        """Advance with the clock [s]: end the wait, time out, end the watch."""
        c = self.config
        ep = self._ep
        if self.state is State.WAITING and ep is not None:
            # the estimated change time can be seconds early (a CUSUM with a small k): the
            # estimation data start at the detection at the earliest
            start = max(self._change + c.settle_s, self._detected)
            full = self._stage == STAGE_FULL
            post = c.full_post_change_s if full else c.min_post_change_s
            if now_s >= start - c.settle_s + post:
                t_val = now_s - (c.full_validation_s if full else c.validation_s)
                t_est = max(start, t_val - c.max_estimation_s)
                ep["estimation"] = (t_est, t_val)
                ep["validation"] = (t_val, now_s)
                ep["stage"] = self._stage
                ep["timings"]["waiting_s"] = now_s - ep["timings"]["alarm_s"]
                ep["timings"]["fit_start_s"] = now_s
                what = ("full refit (every parameter free)" if full else
                        "refitting the effects on the model in use (its structure held)")
                return [self._step(now_s, State.REFITTING,
                                   f"{what} on [{t_est:.3f}, {t_val:.3f}] s, validating on "
                                   f"[{t_val:.3f}, {now_s:.3f}] s", stage=self._stage),
                        RequestFit(ep["episode"], (t_est, t_val), (t_val, now_s),
                                   tuple(ep["outputs"]), self._stage)]
        elif self.state is State.REFITTING and now_s - self._since > c.fit_timeout_s:
            return self._finish(now_s, "fit_timeout",
                                f"no fit result within {c.fit_timeout_s:g} s", 2)
        elif self.state is State.PUSHING and now_s - self._since > c.push_timeout_s:
            return self._rollback(now_s, "push_timeout",
                                  f"push not confirmed within {c.push_timeout_s:g} s")
        elif self.state is State.ROLLING_BACK and now_s - self._since > c.push_timeout_s:
            return self._finish(now_s, "rollback_failed",
                                f"rollback not confirmed within {c.push_timeout_s:g} s", 2)
        elif self.state is State.WATCHING and now_s >= self._push_s + c.watch_s:
            return self._judge(now_s)
        return []

    def fit_done(self, outcome: FitOutcome, now_s: float) -> list[Action]:
        """The refit's result (see :class:`FitOutcome`); decides whether to push."""
        if self.state is not State.REFITTING or self._ep is None:
            return [Diagnostic(1, f"supervisor: fit result ignored in state {self.state.value}",
                               {"state": self.state.value})]
        ep = self._ep
        ep["timings"]["fit_s"] = now_s - ep["timings"]["fit_start_s"]
        ep["refit"] = dict(outcome.summary)
        ep["error_before"] = ep["error_after"] = ep["test"] = None
        ep["stages"].append({"stage": self._stage, "estimation": ep["estimation"],
                             "validation": ep["validation"], "refit": ep["refit"],
                             "fit_s": ep["timings"]["fit_s"]})
        if outcome.crashed:
            return self._decided(now_s, "refit_crashed", outcome.error or "the refit's process "
                                 "died", 2, final=True)
        if outcome.error:
            return self._decided(now_s, "fit_failed", outcome.error, 2)
        new = np.asarray(outcome.new_errors, dtype=float)
        cur = np.asarray(outcome.current_errors, dtype=float)
        ny = len(self.config.names)
        if new.ndim != 2 or new.shape != cur.shape or new.shape[1] != ny or new.shape[0] < 10 \
                or not (np.isfinite(new).all() and np.isfinite(cur).all()):
            return self._decided(now_s, "fit_failed", f"validation errors: expected two finite "
                                 f"(N >= 10, {ny}) arrays of the same shape, got {new.shape} "
                                 f"and {cur.shape}", 2)
        ep["error_before"] = dict(zip(self.config.names, _rms(cur), strict=True))
        ep["error_after"] = dict(zip(self.config.names, _rms(new), strict=True))
        ms = np.mean(cur * cur, axis=0)
        weights = 1.0 / np.where(ms > 0, ms, 1.0)
        cmp = diebold_mariano([cur], [new], weights=weights)
        ep["test"] = {"gain": cmp.gain, "stat": cmp.stat, "p_value": cmp.p_value,
                      "relative_gain": cmp.relative_gain, "bandwidth": cmp.bandwidth,
                      "alpha": self.config.alpha}
        ep["stages"][-1].update(error_before=ep["error_before"], error_after=ep["error_after"],
                                test=ep["test"])
        better = cmp.p_value < self.config.alpha and \
            cmp.relative_gain >= self.config.min_relative_gain
        at_bound = [str(x) for x in outcome.summary.get("structure_at_bounds") or []]
        bound_note = f"; structure at a bound: {'; '.join(at_bound)}" if at_bound else ""
        if not better:
            return self._decided(now_s, "not_better",
                                 f"new model not significantly better on validation (p = "
                                 f"{cmp.p_value:.3g}, relative gain {cmp.relative_gain:.3g})"
                                 + bound_note)
        if at_bound and cmp.relative_gain < self.config.suspect_min_relative_gain:
            return self._decided(now_s, "suspect",
                                 f"new model better on validation (p = {cmp.p_value:.3g}, "
                                 f"relative gain {cmp.relative_gain:.3g}) but not pushed: its "
                                 f"structure ended at a bound ({'; '.join(at_bound)}) and the "
                                 f"gain is below suspect_min_relative_gain "
                                 f"{self.config.suspect_min_relative_gain:g}", 1)
        self._fit = outcome
        ep["stages"][-1].update(decision="push", reason="better on validation")
        return [self._step(now_s, State.PUSHING,
                           f"new model better on validation (p = {cmp.p_value:.3g}, relative "
                           f"gain {cmp.relative_gain:.3g}){bound_note}; pushing",
                           p_value=cmp.p_value),
                Push(ep["episode"], dict(outcome.new_parameters))]

    def _decided(self, now_s: float, outcome: str, reason: str, level: int = 0,
                 final: bool = False) -> list[Action]:
        """A refit that is not pushed: the episode ends with ``outcome``, unless it was the
        first stage (and not ``final``) and a full refit is configured; then the supervisor
        waits for ``full_post_change_s`` of post-change data."""
        ep = self._ep
        if ep is None:  # pragma: no cover - guarded by the states
            return []
        ep["stages"][-1].update(decision=outcome, reason=reason)
        c = self.config
        if final or self._stage == STAGE_FULL or c.full_post_change_s <= 0:
            return self._finish(now_s, outcome, reason, level)
        self._stage = STAGE_FULL
        return [self._step(now_s, State.WAITING,
                           f"first refit ({STAGE_EFFECTS}, structure held) not pushed: "
                           f"{outcome} ({reason}); waiting for {c.full_post_change_s:g} s of "
                           "post-change data for the full refit", min(level, 1),
                           stage=STAGE_FULL)]

    def push_done(self, ok: bool, now_s: float, error: str = "") -> list[Action]:
        """The push's outcome; on success the watch starts."""
        if self.state is not State.PUSHING or self._ep is None:
            return [Diagnostic(1, f"supervisor: push result ignored in state {self.state.value}",
                               {"state": self.state.value})]
        ep = self._ep
        if not ok:
            return self._finish(now_s, "push_failed", error or "push refused", 2)
        ep["pushed"] = True
        ep["push_s"] = now_s
        self._push_s = now_s
        c = self.config
        t0 = max(self._change + c.settle_s, now_s - c.baseline_s)
        before, n = self.history.rms(t0, now_s)
        ep["live_before"] = dict(zip(c.names, before, strict=True))
        ep["live_before_samples"] = n
        return [self._step(now_s, State.WATCHING,
                           f"pushed; watching the live residual for {c.watch_s:g} s")]

    def rollback_done(self, ok: bool, now_s: float, error: str = "") -> list[Action]:
        """The rollback's outcome; ends the episode."""
        if self.state is not State.ROLLING_BACK or self._ep is None:
            return [Diagnostic(1, "supervisor: rollback result ignored in state "
                                  f"{self.state.value}", {"state": self.state.value})]
        ep = self._ep
        reason = ep.pop("_rollback_reason", "")
        outcome = ep.pop("_rollback_outcome", "rolled_back")
        if not ok:
            return self._finish(now_s, "rollback_failed", error or "rollback refused", 2)
        ep["rolled_back"] = True
        return self._finish(now_s, outcome, reason, 1)

    # ---------------------------------------------------------------- watching
    def _rollback(self, now_s: float, outcome: str, reason: str) -> list[Action]:
        ep = self._ep
        if ep is None or self._fit is None:  # pragma: no cover
            return []
        ep["_rollback_reason"] = reason
        ep["_rollback_outcome"] = outcome
        return [self._step(now_s, State.ROLLING_BACK, f"rolling back: {reason}", 1),
                Rollback(ep["episode"], dict(self._fit.current_parameters), reason)]

    def _judge(self, now_s: float) -> list[Action]:
        c = self.config
        ep = self._ep
        if ep is None:  # pragma: no cover
            return []
        ep["timings"]["watch_s"] = now_s - self._push_s
        after, n = self.history.rms(self._push_s + c.watch_settle_s, now_s + 1.0)
        ep["live_after"] = dict(zip(c.names, after, strict=True))
        ep["live_after_samples"] = n
        expected = list((ep["error_after"] or {}).values())
        ep["expected"] = ep["error_after"]
        if expected:
            ep["live_vs_expected"] = dict(zip(
                c.names, [a / e if e > 0 else math.nan for a, e in zip(after, expected,
                                                                      strict=True)],
                strict=True))
        if n < c.min_watch_samples:
            return self._rollback(now_s, "rolled_back", f"only {n} live residual samples "
                                  f"after the push (< {c.min_watch_samples}); cannot verify")
        before = list(ep["live_before"].values())
        ratios = [a / b if b > 0 else (math.inf if a > 0 else 1.0)
                  for a, b in zip(after, before, strict=True)]
        ep["live_ratio"] = dict(zip(c.names, ratios, strict=True))
        worst = max(range(len(ratios)),
                    key=lambda i: ratios[i] if math.isfinite(ratios[i]) else math.inf)
        if any(math.isnan(b) for b in before):
            return self._finish(now_s, "confirmed", "no live residual before the push to "
                                "compare with; kept on the validation evidence", 1)
        if ratios[worst] > 1.0 + c.rollback_tolerance:
            return self._rollback(now_s, "rolled_back",
                                  f"live residual RMS of {c.names[worst]} rose by a factor "
                                  f"{ratios[worst]:.3g} (> 1 + {c.rollback_tolerance:g})")
        return self._finish(now_s, "confirmed", "live residual RMS ratio after/before push "
                            + ", ".join(f"{k} {v:.3g}" for k, v in ep["live_ratio"].items()))

    def status(self) -> dict[str, str]:
        """Key/values for a ``DiagnosticStatus``."""
        out = {"state": self.state.value, "episodes": str(self.episodes),
               "live_samples": str(self.history.samples)}
        if self._ep is not None:
            out["episode"] = str(self._ep["episode"])
            out["change_s"] = f"{self._ep['change_s']:.3f}"
        if self.reports:
            out["last_outcome"] = str(self.reports[-1]["outcome"])
        return out


def episode_markdown(record: Mapping[str, Any]) -> str:
    """A short human-readable summary of an episode record (``episode-N.md``)."""
    def fmt(d: Any) -> str:
        if not isinstance(d, Mapping):
            return "-"
        return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                         for k, v in d.items())

    refit_ = record.get("refit") or {}
    test = record.get("test") or {}
    lines = [f"# Episode {record.get('episode')}: {record.get('outcome')}", "",
             f"* reason: {record.get('reason')}",
             f"* change at {record.get('change_s')} s on {', '.join(record.get('outputs') or [])}"
             f" (detected {record.get('detected_s')} s, {len(record.get('alarms') or [])} "
             "alarm(s))",
             f"* estimation {record.get('estimation')}, validation {record.get('validation')}"
             f" (stage {record.get('stage', '-')})",
             "* refits: " + ("; ".join(
                 f"{st.get('stage')}: {st.get('decision')} ({st.get('reason')})"
                 for st in record.get("stages") or []) or "none"),
             f"* accepted effects: {', '.join(refit_.get('accepted') or []) or 'none'}",
             "* structure at a bound: " + ("; ".join(refit_.get("structure_at_bounds") or [])
                                          or "none"),
             "* changed parameters: " + (", ".join(
                 str(c.get("parameter")) for c in refit_.get("changed") or []) or "none"),
             f"* validation RMS before [rad/s]: {fmt(record.get('error_before'))}",
             f"* validation RMS after [rad/s]: {fmt(record.get('error_after'))}",
             f"* test: p = {test.get('p_value', '-')}, relative gain "
             f"{test.get('relative_gain', '-')} (alpha {test.get('alpha', '-')})",
             f"* pushed: {record.get('pushed')} at {record.get('push_s')}",
             f"* live RMS before / after push: {fmt(record.get('live_before'))} / "
             f"{fmt(record.get('live_after'))}; ratio {fmt(record.get('live_ratio'))}",
             f"* rolled back: {record.get('rolled_back')}",
             f"* timings [s]: {fmt(record.get('timings'))}", "", "## Steps", ""]
    lines += [f"* {st.get('t', 0.0):.3f} {st.get('state')}: {st.get('message')}"
              for st in record.get("steps") or []]
    return "\n".join(lines) + "\n"
