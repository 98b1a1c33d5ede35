"""The supervisor's refit of one episode window (pure: no rclpy; ``docs/loop.md`` section 4).

:func:`refit` reads the recorder's snapshot, splits it into the estimation and validation
parts the :class:`~dvt_identify.supervisor.RequestFit` names, runs the identification pipeline
on them (as ``dvt-identify`` does) and simulates the model in use and the new one on the
validation part with the model node's own predictor, for the supervisor's decision
(:class:`~dvt_identify.supervisor.FitOutcome`). The identifier node runs it in a process of its
own (:mod:`dvt_identify.refit_process`), never in the node's process.

**The first stage holds the structure** (:data:`~dvt_identify.supervisor.STAGE_EFFECTS`): a few
seconds after a change do not determine the structure's parameters (the mass and damping
entries ``M12, M22, D12, D22`` of the DVT: the pipeline's identifiability check says so on 3 s
of the ``watch`` excitation), and fitted free they absorb part of the change: on three
offline 1-kHz ``friction_step`` windows (3 s to fit, 1.5 s held out) the free refit named the
sun's Coulomb step correctly once in three (the other two: only carrier 3's Coulomb friction,
at twice its size, or only the sun's at twice its size), with ``M22`` anywhere from 0.0027 to
30 kg m^2. :func:`held_description` writes the description with the structure's parameters
fixed at the model in use's values (the model node's ``M`` and ``D``); the candidate effects
are then fitted on top of the model in use, and on the same three windows both Coulomb steps
were named, at 0.046-0.048 N m (sun, truth 0.05) and 0.21-0.22 N m (carrier 3, truth 0.20).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from dvt_identify.description import Description
from dvt_identify.effects import Unlisted
from dvt_identify.supervisor import STAGE_EFFECTS, FitOutcome, RequestFit
from dvt_model.presets import safe_load

MIN_WINDOW_SAMPLES = 100
"""Fewest samples of the estimation or the validation part of a snapshot."""
UNLISTED = Unlisted.name
"""The candidate entry of the term library (:mod:`dvt_identify.unlisted`), which the held
description leaves out: a few seconds after a change determine a named effect's one or two
parameters, not a library's sparse selection (measured 2026-12-06, ``friction_step`` at
250 Hz, 2.5 s fitted and 2.5 s held out, 30 windows: an ``unlisted`` term accepted in 3, one
of them a 0.95 N m sign term on carrier 3 that left the sun's residual over the next 14 s at
0.68 of the model in use's, against 0.20-0.33 for the windows that named both Coulomb steps).
The full refit (``"full"``, 30 s) keeps it."""
HELD_DESCRIPTION = "description-held.yaml"
"""File name (in the episode's directory) of the description with its structure held."""


@dataclass(frozen=True)
class RefitSettings:
    """How an episode's window is refitted (the CLI's identification, bounded):
    ``description`` (bundled name or YAML), ``augment`` (the residual-tracing loop), ``starts``
    (multi-start count, ``None``: the description's), ``fit_decimate`` (``None``: the
    description's), ``plots`` (PNG plots in the episode's report), ``from_model`` (start the
    baseline fit from the model in use, :func:`dvt_identify.pipeline.model_initial`; the
    description's initial values stay a further start), ``hold_structure`` (in the first stage,
    :data:`~dvt_identify.supervisor.STAGE_EFFECTS`, hold the structure's parameters at the
    model in use's values: :func:`held_description`; needs ``from_model``)."""

    description: str = "dvt"
    augment: bool = True
    starts: int | None = 1
    fit_decimate: int | None = None
    plots: bool = False
    from_model: bool = True
    hold_structure: bool = True

    def to_dict(self) -> dict[str, Any]:
        """The settings as JSON-ready values (:meth:`from_dict` reads them back)."""
        return {"description": self.description, "augment": self.augment,
                "starts": self.starts, "fit_decimate": self.fit_decimate, "plots": self.plots,
                "from_model": self.from_model, "hold_structure": self.hold_structure}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RefitSettings:
        """Settings from :meth:`to_dict`'s values (unknown keys are an error of the caller:
        ``TypeError``)."""
        return cls(**dict(data))


def plain_value(value: Any) -> Any:
    """A parameter value as plain Python (``array.array``/numpy/tuples as lists of floats)."""
    if isinstance(value, str | bool | int | float) or value is None:
        return value
    if isinstance(value, np.ndarray | Sequence) or hasattr(value, "tolist"):
        return [float(v) for v in value]
    return value


def validation_errors(values: Mapping[str, Any], stamps_ns: ArrayLike, speeds: ArrayLike,
                      currents: ArrayLike) -> np.ndarray:
    """Output errors (N, 2) [rad/s] = measured - predicted of the model node's predictor built
    from ``values`` (model-node parameters, as :func:`dvt_model.config.build_predictor`), run
    over the samples from the first one on, exactly as the live node computes its residual.

    Raises:
        dvt_model.errors.DvtModelError: ``values`` the model node would refuse.
    """
    from dvt_model.config import build_predictor

    predictor, _ = build_predictor(values)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    w = np.asarray(speeds, dtype=float)
    u = np.asarray(currents, dtype=float)
    out = np.empty((stamps.shape[0], 2))
    for i in range(stamps.shape[0]):
        p = predictor.update(int(stamps[i]) * 1e-9, float(u[i, 0]), u[i, 1:4], w[i])
        out[i] = p.residual
    return out


def changes(current: Mapping[str, Any], new: Mapping[str, Any]) -> list[dict[str, Any]]:
    """What the push would change: ``{"parameter", "before", "after"}`` per differing value."""
    out = []
    for key, after in new.items():
        before = current.get(key)
        if plain_value(before) in (None, [], "") and plain_value(after) in (None, [], ""):
            continue
        if key == "effects":
            def kinds(text: Any) -> list[str]:
                try:
                    return [str(t.get("kind")) for t in json.loads(str(text or "[]"))]
                except (ValueError, AttributeError):
                    return []

            if str(before or "") != str(after):
                out.append({"parameter": key, "before": kinds(before), "after": kinds(after),
                            "terms": str(after)})
            continue
        b, a = plain_value(before), plain_value(after)
        if b != a:
            out.append({"parameter": key, "before": b, "after": a})
    return out


_NAME = re.compile(r"[A-Za-z_]\w*")


def held_description(desc: Description, values: Mapping[str, float], path: str | Path
                     ) -> tuple[Path, dict[str, float]] | None:
    """Write the description ``desc`` to ``path`` with the structure's parameters that
    ``values`` names held at those values: each matrix entry of the structure that uses only
    held parameters becomes its number, and the held parameters leave the structure's
    ``parameters`` (a parameter that shares an entry with a free one stays free). Everything
    else (inputs, outputs, model effects, candidates, options) is ``desc``'s own text.

    Args:
        desc: the description the refit would use (loaded).
        values: structure parameter name -> value (the model in use's,
            :func:`dvt_identify.pipeline.model_initial`); other names are ignored.
        path: the YAML to write (its directory must exist); the pipeline loads it (a
            :class:`~dvt_identify.errors.DescriptionError` there names it).

    Returns:
        ``(path, held values)``, or ``None`` when no structure parameter can be held.
    """
    import yaml

    from dvt_identify.structures import ParamMatrix

    data = safe_load(desc.text)
    structure = data.get("structure") if isinstance(data, dict) else None
    if not isinstance(structure, dict):
        return None
    names = [p.name for p in desc.structure.params]
    hold = {n: float(values[n]) for n in names if n in values}
    matrices = {k: v for k, v in structure.items()
                if isinstance(v, list) and v and all(isinstance(r, list) for r in v)}

    def used(entry: Any) -> set[str]:
        return set(_NAME.findall(entry)) & set(names) if isinstance(entry, str) else set()

    changed = True
    while changed:  # an entry mixing held and free parameters frees its held ones
        changed = False
        for rows in matrices.values():
            for row in rows:
                for e in row:
                    u = used(e)
                    if u & set(hold) and u - set(hold):
                        for n in u & set(hold):
                            del hold[n]
                        changed = True
    if not hold:
        return None
    theta = np.array([hold.get(p.name, p.initial) for p in desc.structure.params], dtype=float)
    for key, rows in matrices.items():
        structure[key] = [[float(ParamMatrix([[e]], f"structure.{key}", names)(theta)[0, 0])
                           if used(e) and used(e) <= set(hold) else e for e in row]
                          for row in rows]
    params = structure.get("parameters")
    if isinstance(params, dict):
        structure["parameters"] = {k: v for k, v in params.items() if k not in hold}
    cands = data.get("candidates")
    dropped = []
    if isinstance(cands, list):
        dropped = [c for c in cands if isinstance(c, dict) and c.get("effect") == UNLISTED]
        data["candidates"] = [c for c in cands if c not in dropped]
    out = Path(path)
    out.write_text(f"# {desc.source} with the structure held at the model in use: "
                   f"{', '.join(f'{k} {v:.6g}' for k, v in hold.items())}\n"
                   + (f"# its {len(dropped)} `{UNLISTED}` candidate(s) left to the full refit\n"
                      if dropped else "")
                   + yaml.safe_dump(data, sort_keys=False))
    return out, hold


def refit(snapshot: str | Path, request: RequestFit, current: Mapping[str, Any],
          work_dir: str | Path, settings: RefitSettings | None = None) -> FitOutcome:
    """The refit of one episode window (pure; the node runs it in its refit process).

    Reads the snapshot bag, splits it by stamp into the estimation part
    ``[request.estimation)`` and the validation part ``[request.validation]`` (written as two
    bags under ``work_dir``, with the recorded angles when the snapshot has them), runs the
    identification pipeline on them (as ``dvt-identify``, report in ``work_dir/report``; the
    baseline fit starts from the model in use when ``settings.from_model``; in the first stage,
    ``request.stage`` :data:`~dvt_identify.supervisor.STAGE_EFFECTS`, with the structure held
    at the model in use when ``settings.hold_structure``: :func:`held_description`), builds the
    model-node push and simulates the model in use (``current``: the model node's parameter
    values) and the new one (``current`` with the push applied) on the validation part with the
    node's own predictor. The summary's ``structure_at_bounds`` lists the new model's structure
    parameters at a bound (:func:`dvt_identify.pipeline.structure_at_bounds`), ``suspect`` the
    fits' own flags (``OEFit.suspect_``), ``held`` the structure values held (if any).

    Returns:
        The :class:`FitOutcome` for :meth:`Supervisor.fit_done` (``error`` set, naming the
        problem, when the data or the fit are unusable).
    """
    from dvt_identify.description import load_description
    from dvt_identify.errors import DvtIdentifyError
    from dvt_identify.pipeline import model_initial, model_push, structure_at_bounds
    from dvt_identify.pipeline import run as run_pipeline
    from dvt_model.errors import DvtModelError
    from dvt_model.recording import read_run, write_run

    s = settings or RefitSettings()
    work = Path(work_dir)
    summary: dict[str, Any] = {"snapshot": str(snapshot), "report": str(work / "report"),
                               "stage": request.stage}
    try:
        data = read_run(snapshot)
        t = data.stamps_ns.astype(np.float64) * 1e-9
        (e0, e1), (v0, v1) = request.estimation, request.validation
        est = (t >= e0) & (t < e1)
        val = (t >= v0) & (t <= v1 + 1e-6)
        summary["samples"] = {"estimation": int(est.sum()), "validation": int(val.sum())}
        if est.sum() < MIN_WINDOW_SAMPLES or val.sum() < MIN_WINDOW_SAMPLES:
            return FitOutcome(summary=summary, error=(
                f"snapshot {snapshot}: {int(est.sum())} estimation and {int(val.sum())} "
                f"validation samples in [{e0:.3f}, {e1:.3f}] / [{v0:.3f}, {v1:.3f}] s "
                f"(need >= {MIN_WINDOW_SAMPLES} each; {data.n} samples in the snapshot)"))
        pos = data.positions
        summary["angles"] = "recorded position" if pos is not None else \
            "none recorded (integrated speeds)"
        est_bag = write_run(work / "estimation", data.stamps_ns[est], data.speeds[est],
                            data.currents[est], positions=None if pos is None else pos[est])
        val_bag = write_run(work / "validation", data.stamps_ns[val], data.speeds[val],
                            data.currents[val], positions=None if pos is None else pos[val])
        cur = {k: plain_value(v) for k, v in current.items()}
        initial: dict[str, float] | None = None
        desc = load_description(s.description)
        if s.from_model:
            try:
                initial = model_initial(desc, cur)
                summary["initial"] = {"from": "the model in use", "values": initial}
            except DvtModelError as exc:  # the description's initial values only
                summary["initial"] = {"from": "the description", "error": str(exc)}
        description = s.description
        held: dict[str, float] = {}
        if request.stage == STAGE_EFFECTS and s.hold_structure and initial:
            got = held_description(desc, initial, work / HELD_DESCRIPTION)
            if got is not None:
                path, held = got
                description = str(path)
                initial = {k: v for k, v in initial.items() if k not in held}
        summary["held"] = held
        result = run_pipeline([est_bag], [val_bag], work / "report",
                              description=description, augment=s.augment, starts=s.starts,
                              fit_decimate=s.fit_decimate, quiet=True, plots=s.plots,
                              series=False, initial=initial or None)
        summary["suspect"] = {"baseline": list(result.baseline.fit.suspect_),
                              "final": list(result.final.fit.suspect_)}
        summary["structure_at_bounds"] = structure_at_bounds(result)
        summary["baseline_fit_percent"] = dict(zip(
            result.baseline.val.output_names, result.baseline.val.fit_percent, strict=True))
        summary["final_fit_percent"] = dict(zip(
            result.final.val.output_names, result.final.val.fit_percent, strict=True))
        summary["accepted"] = [d.score.label for d in result.accepted]
        push = model_push(result, held=held or None)
        summary["not_pushed"] = push.skipped
        new = {**cur, **push.parameters}
        summary["changed"] = changes(cur, push.parameters)
        cur_err = validation_errors(cur, data.stamps_ns[val], data.speeds[val],
                                    data.currents[val])
        new_err = validation_errors(new, data.stamps_ns[val], data.speeds[val],
                                    data.currents[val])
    except (DvtIdentifyError, DvtModelError, OSError) as exc:
        return FitOutcome(summary=summary, error=f"{type(exc).__name__}: {exc}")
    return FitOutcome(new_errors=new_err, current_errors=cur_err,
                      new_parameters=dict(push.parameters),
                      current_parameters={k: cur.get(k) for k in push.parameters},
                      summary=summary)
