"""EMPS scored by its benchmark's own rules, recomputed independently of ``dvt-identify``.

Protocol (the ``nonlinear_benchmarks`` split of EMPS): input ``vir`` (drive force
``F = gtau * vir`` [N]), output the motor position ``qm`` [m]; estimate on DATA_EMPS
(``emps_estimation.npz``), test on DATA_EMPS_PULSES (``emps_validation.npz``). On the test record
the model may use the first 20 samples of ``qm`` to set its initial state; it is then simulated
open loop from ``vir`` over the whole record and the figure is the RMS of the position error over
the samples after the window, in mm.

``examples/emps/run.sh`` makes the figure with the tool, chosen on the estimation record only::

    dvt-identify emps_estimation --select-on holdout --test emps_validation --init-window 20 \\
        --description emps-position --out OUT

This script reads that run's ``report.json`` and, from the records themselves:

- recomputes the tool's test figure for its final model with the benchmark module's own protocol
  code (:func:`dvt_identify.benchmarks.protocol_score_model`: Gauss-Newton initial state on the
  window, then the open-loop simulation): the two must agree;
- simulates the published IDIM-LS parameters (Janot et al.) the same way, with the exact sign and
  stick rule as in the authors' Simulink model (the reproduction of their figure);
- lists the published baselines (Champneys et al. 2024) beside the tool's model and its linear
  reference;
- measures how the two records differ away from the pulse transients (force the test record
  needed minus the estimation record's, by direction of travel): what no model fitted on the
  estimation record alone can know;
- refits the tool's chosen structure on the test record itself (the same fit for the position,
  :func:`dvt_identify.benchmarks.fit_for_output`, started from the tool's parameters) and scores
  it there: an in-sample bound, no benchmark entry, that separates what the structure can
  describe from what the records' difference costs;
- fits the chosen structure by the same criterion on the whole estimation record, its halves
  and its quarters, and scores each fit on the test record: how far the figure moves with the
  part of the estimation record the friction levels come from (no choice uses the test); the
  tool's linear reference, fitted on each part alone, beside it.

    .venv/bin/python examples/emps/benchmark.py --report OUT/report.json [--data DIR] [--out DIR]

Writes ``benchmark.json`` and ``benchmark.md`` to ``--out`` when given; prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.benchmarks import fit_for_output, protocol_score_model
from dvt_identify.data import Segment, make_segment
from dvt_identify.description import load_description
from dvt_identify.effects import Unlisted
from dvt_identify.errors import DvtIdentifyError
from dvt_identify.reference import LinearReference
from dvt_identify.simulation import OEModel

Array = NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("EMPS_DIR", str(ROOT.parent / "shared" / "data" / "emps")))
N_INIT = 20

# Published figures (test RMS of the simulated position, mm): Champneys et al. 2024, "Baseline
# results for selected nonlinear system identification benchmarks".
PUBLISHED: tuple[tuple[str, float], ...] = (
    ("LTI state space (Champneys et al. 2024)", 5.53),
    ("polynomial NARX (Champneys et al. 2024)", 5.17),
    ("best known, SOTA (Champneys et al. 2024)", 2.64),
)
IDIM_SYM = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
"""IDIM-LS parameters of the benchmark authors (description PDF section 3.4)."""


def load_record(path: Path, name: str) -> Segment:
    """A record as a segment of the ``emps-position`` description: input ``F = gtau * vir``
    [N], output ``qm`` [m]."""
    d = np.load(path)
    t = np.asarray(d["t"], float)
    u = float(d["gtau"]) * np.asarray(d["vir"], float)
    return make_segment(name, t - t[0], u[:, None], np.asarray(d["qm"], float)[:, None],
                        ("force",), ("position",))


def tool_model(report: dict[str, Any], exact_sign: bool = False) -> tuple[OEModel, Array]:
    """The model and parameters of ``report.json``'s final model, built from the bundled
    ``emps-position`` description and the accepted effects (``exact_sign``: the dry laws
    without their sign smoothing)."""
    desc = load_description(report["description"]["source"].split(" ")[0])
    accepted = [e for e in report["effects"] if e.get("accepted") and e["name"] != "none"]
    cands = {c.label(): c for c in desc.make_candidates()}
    values = report["final"]["parameters"]
    effects = []
    for e in accepted:
        c = cands[f"{e['name']}@{e['where']}"]
        if isinstance(c, Unlisted):  # the accepted terms of the library (named as in it)
            idx = [i for i, p in enumerate(c.params) if p.name in values]
            c = c.subset(idx, np.array([float(values[c.params[i].name]) for i in idx]))
        if exact_sign and "eps" in c.options:
            c.options["eps"] = 0.0
        effects.append(c)
    model = OEModel(desc.structure, effects)
    return model, np.array([float(values[n]) for n in model.names])


def idim_model() -> tuple[OEModel, Array]:
    """The published IDIM-LS model: Coulomb friction with offset, exact sign and stick rule."""
    desc = load_description("emps-position")
    c = next(c for c in desc.make_candidates() if c.name == "coulomb_friction")
    c.options["eps"] = 0.0
    model = OEModel(desc.structure, [c])
    return model, np.array([IDIM_SYM[n] for n in model.names])


def steady_force_difference(data: Path, guard: int = 150, parts: int = 4
                            ) -> list[dict[str, float]]:
    """Force the test record needed minus the force the estimation record needed at the same
    time, by direction of travel, on samples at least ``guard`` samples from any pulse edge.

    Both records follow the same reference and their positions differ by at most the pulses'
    0.13 mm, so away from the pulse transients a non-zero difference is a change of the plant
    (friction) between the two experiments. Direction: sign of the estimation record's velocity
    (50-sample mean of the difference of ``qm``), ``|v| > 0.02`` m/s. One entry per ``parts``
    equal part of the record: mean difference [N] for ``+`` and ``-`` travel."""
    e = np.load(data / "emps_estimation.npz")
    v = np.load(data / "emps_validation.npz")
    n = min(len(e["vir"]), len(v["vir"]))
    df = float(v["gtau"]) * (np.asarray(v["vir"], float)[:n] - np.asarray(e["vir"], float)[:n])
    pulses = np.asarray(v["pulses_N"], float)[:n]
    edges = np.flatnonzero(np.diff(pulses) != 0) + 1
    far = np.ones(n, dtype=bool)
    for k in edges:
        far[max(0, k - guard): k + guard + 1] = False
    dt = float(np.mean(np.diff(np.asarray(e["t"], float))))
    vel = np.convolve(np.gradient(np.asarray(e["qm"], float)[:n], dt), np.ones(50) / 50,
                      mode="same")
    out = []
    bounds_ = np.linspace(0, n, parts + 1).astype(int)
    for i in range(parts):
        s = slice(bounds_[i], bounds_[i + 1])
        up = far[s] & (vel[s] > 0.02)
        down = far[s] & (vel[s] < -0.02)
        out.append({"part": float(i), "plus_N": float(np.mean(df[s][up])),
                    "minus_N": float(np.mean(df[s][down])),
                    "samples": float(up.sum() + down.sum())})
    return out


def run(data: Path, report: dict[str, Any]) -> dict[str, Any]:
    """The benchmark's figures (module docstring)."""
    est = load_record(data / "emps_estimation.npz", "emps_estimation")
    test = load_record(data / "emps_validation.npz", "emps_validation")
    rows: list[dict[str, Any]] = []

    def score(label: str, model: OEModel, theta: Array) -> dict[str, Any]:
        t = protocol_score_model(model, theta, test, 0, N_INIT, model.nx)
        e = protocol_score_model(model, theta, est, 0, N_INIT, model.nx)
        row = {"label": label, "test_rms_mm": 1e3 * t.rms, "est_rms_mm": 1e3 * e.rms,
               "n_init": t.n_init, "n_scored": t.n_scored}
        rows.append(row)
        return row
    m, th = tool_model(report)
    ours = score("dvt-identify, chosen on the estimation record (recomputed)", m, th)
    tool_test = report["test"]["final"]["rmse"]["position"] * 1e3
    ref = (report["test"].get("linear_reference") or {}).get("rmse", {}).get("position")
    if ref is not None:
        rows.append({"label": "dvt-identify's linear reference (same data, same protocol)",
                     "test_rms_mm": 1e3 * float(ref), "est_rms_mm": None})
    mi, ti = idim_model()
    score("published IDIM-LS (Janot et al.), simulated here, no refit", mi, ti)
    bound = test_record_bound(m, th, test, est)
    order = (report.get("linear_reference") or {}).get("order")
    spread = part_fits(m, th, est, test, int(order) if order else None)
    for label, v in PUBLISHED:
        rows.append({"label": label, "test_rms_mm": v, "est_rms_mm": None})
    return {"protocol": {"input": "vir (force gtau * vir, N)", "output": "qm (m)",
                         "estimation": "emps_estimation.npz", "test": "emps_validation.npz",
                         "n_init": N_INIT, "n_scored": ours["n_scored"]},
            "rows": rows, "tool_test_rms_mm": tool_test,
            "recomputed_minus_tool_mm": ours["test_rms_mm"] - tool_test,
            "accepted": [f"{e['name']}@{e['where']}" for e in report["effects"]
                         if e.get("accepted") and e["name"] != "none"],
            "records_agree": report.get("records_agree"),
            "steady_force_difference": steady_force_difference(data),
            "test_record_bound": bound, "part_fits": spread}


def test_record_bound(model: OEModel, theta: Array, test: Segment, est: Segment
                      ) -> dict[str, Any]:
    """The tool's structure refitted on the test record (module docstring): its test RMS [mm]
    (in sample: fitted on the record it is scored on, no benchmark entry), the RMS of the same
    parameters on the estimation record [mm] (the reverse direction), and the refitted
    parameters beside the tool's."""
    lo = np.array([s.lower for s in model.specs])
    hi = np.array([s.upper for s in model.specs])
    fit = fit_for_output(model, test, np.clip(theta, lo, hi), lo, hi, 0, N_INIT, model.nx)
    back = protocol_score_model(model, fit.theta, est, 0, N_INIT, model.nx)
    return {"label": "the tool's structure refitted on the test record (in sample, no "
                     "benchmark entry)",
            "test_rms_mm": 1e3 * fit.rms, "est_rms_mm": 1e3 * back.rms, "nfev": fit.nfev,
            "parameters": dict(zip(model.names, map(float, fit.theta), strict=True)),
            "tool_parameters": dict(zip(model.names, map(float, theta), strict=True))}


PARTS: tuple[tuple[str, float, float], ...] = (
    ("first 70 % (where the tool's choice was fitted)", 0.0, 0.7),
    ("whole record (the tool's final fit)", 0.0, 1.0),
    ("first half", 0.0, 0.5), ("second half", 0.5, 1.0),
    ("quarter 1", 0.0, 0.25), ("quarter 2", 0.25, 0.5), ("quarter 3", 0.5, 0.75),
    ("quarter 4", 0.75, 1.0))
"""Parts of the estimation record (name, start and end as fractions of its samples) that
:func:`part_fits` fits the chosen structure on."""


def linear_part(seg: Segment, test: Segment, order: int) -> dict[str, Any]:
    """The black-box linear reference of the tool's order fitted on ``seg`` alone
    (:class:`dvt_identify.reference.LinearReference`, output error, the same 20-sample
    initial-state window; orders up to ``order``, chosen on ``seg`` itself: no other data) and
    scored on the test record like the tool's reference [mm]; or why it has no figure."""
    try:
        ref = LinearReference(max_order=order, init_window=N_INIT, seed=0).fit([seg], [seg])
        pred = ref.predict(test, N_INIT)
    except DvtIdentifyError as exc:
        return {"linear_not_scored": str(exc)}
    err = pred[N_INIT:, 0] - test.y[N_INIT:, 0]
    return {"linear_order": ref.order_,
            "linear_test_rms_mm": 1e3 * float(np.sqrt(np.mean(err ** 2)))}


def part_fits(model: OEModel, theta: Array, est: Segment, test: Segment,
              linear_order: int | None = None) -> dict[str, Any]:
    """How far the test figure moves with the part of the estimation record the parameters come
    from: the tool's chosen structure fitted by the benchmark's own criterion
    (:func:`dvt_identify.benchmarks.fit_for_output`, started from the tool's parameters) on the
    whole estimation record, its halves and its quarters (:data:`PARTS`), each scored on the
    part itself (in sample), on the whole estimation record and on the test record [mm]; with
    ``linear_order`` (the tool's reference's), the linear reference fitted on the same part
    beside it (:func:`linear_part`). No choice uses the test record; the tool chooses the
    effects with fits on the first 70 % (the last 30 % held out) and then refits the chosen
    model on the whole record (:func:`dvt_identify.loop.refit_whole`). Returns the rows and
    the test figures' range."""
    lo = np.array([s.lower for s in model.specs])
    hi = np.array([s.upper for s in model.specs])
    n = est.t.size
    rows: list[dict[str, Any]] = []
    for name, fa, fb in PARTS:
        a, b = round(fa * n), round(fb * n)
        seg = est.rows(a, b, name=f"{est.name}[{a}:{b}]", from_zero=True)
        fit = fit_for_output(model, seg, np.clip(theta, lo, hi), lo, hi, 0, N_INIT,
                             model.nx)
        on_est = protocol_score_model(model, fit.theta, est, 0, N_INIT, model.nx)
        on_test = protocol_score_model(model, fit.theta, test, 0, N_INIT, model.nx)
        rows.append({"part": name, "samples": [a, b], "in_sample_rms_mm": 1e3 * fit.rms,
                     "est_rms_mm": 1e3 * on_est.rms, "test_rms_mm": 1e3 * on_test.rms,
                     "parameters": dict(zip(model.names, map(float, fit.theta), strict=True)),
                     **(linear_part(seg, test, linear_order) if linear_order else {})})
    t = [r["test_rms_mm"] for r in rows]
    out: dict[str, Any] = {"rows": rows, "test_min_mm": min(t), "test_max_mm": max(t)}
    lin = [r for r in rows if "linear_test_rms_mm" in r]
    if lin:
        out["linear_test_min_mm"] = min(r["linear_test_rms_mm"] for r in lin)
        out["linear_test_max_mm"] = max(r["linear_test_rms_mm"] for r in lin)
        out["physical_better_on"] = [r["part"] for r in lin
                                     if r["test_rms_mm"] < r["linear_test_rms_mm"]]
        out["linear_better_on"] = [r["part"] for r in lin
                                   if r["linear_test_rms_mm"] <= r["test_rms_mm"]]
    return out


def markdown(res: dict[str, Any]) -> str:
    """The table and the record difference as Markdown."""
    lines = ["# EMPS by its benchmark's protocol", "",
             f"Simulated position on the test record after a {N_INIT}-sample state-"
             f"initialisation window, RMS over {res['protocol']['n_scored']} samples.", "",
             "| model | test RMS [mm] | estimation RMS [mm] |", "|---|---|---|"]
    for r in res["rows"]:
        est = "-" if r.get("est_rms_mm") is None else f"{r['est_rms_mm']:.2f}"
        lines.append(f"| {r['label']} | {r['test_rms_mm']:.2f} | {est} |")
    lines += ["", f"Accepted effects: {', '.join(res['accepted']) or 'none'}. The tool's own "
              f"figure {res['tool_test_rms_mm']:.3f} mm; recomputed here "
              f"{res['tool_test_rms_mm'] + res['recomputed_minus_tool_mm']:.3f} mm.", "",
              "Force the test record needed minus the estimation record's, away from the "
              "pulse edges [N]:", "", "| quarter | + travel | - travel |", "|---|---|---|"]
    for d in res["steady_force_difference"]:
        lines.append(f"| {int(d['part']) + 1} | {d['plus_N']:+.2f} | {d['minus_N']:+.2f} |")
    b = res.get("test_record_bound")
    if b:
        lines += ["", f"The tool's structure refitted on the test record itself (in sample, no "
                  f"benchmark entry): test RMS {b['test_rms_mm']:.2f} mm, the same parameters "
                  f"on the estimation record {b['est_rms_mm']:.2f} mm. What separates it from "
                  "the chosen model's figure is the records' difference, not the structure."]
    sp = res.get("part_fits")
    if sp:
        lines += ["", "The chosen structure fitted by the benchmark's criterion on parts of the "
                  "estimation record (no choice on the test record) [mm]:", "",
                  "| part | in sample | whole estimation record | test | linear reference "
                  "fitted on the part, test |", "|---|---|---|---|---|"]
        for r in sp["rows"]:
            lin = ("-" if "linear_test_rms_mm" not in r
                   else f"{r['linear_test_rms_mm']:.2f} (order {r['linear_order']})")
            lines.append(f"| {r['part']} | {r['in_sample_rms_mm']:.2f} | "
                         f"{r['est_rms_mm']:.2f} | {r['test_rms_mm']:.2f} | {lin} |")
        lines += ["", f"The test figure ranges over {sp['test_min_mm']:.2f}-"
                  f"{sp['test_max_mm']:.2f} mm with the part the friction levels come from: an "
                  "open-loop position simulation turns a fraction of a newton into millimetres."]
        if "linear_better_on" in sp:
            lines += ["", f"Fitted on the same part, the linear reference ranges over "
                      f"{sp['linear_test_min_mm']:.2f}-{sp['linear_test_max_mm']:.2f} mm. It "
                      f"scores better on {', '.join(sp['linear_better_on']) or 'none'}; the "
                      f"physical model on {', '.join(sp['physical_better_on']) or 'none'}."]
    ag = res.get("records_agree")
    if ag:
        lines += ["", ag["statement"]]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--report", type=Path, required=True,
                    help="report.json of the dvt-identify run (run.sh writes it)")
    ap.add_argument("--data", type=Path, default=DATA, help="folder with the EMPS .npz records")
    ap.add_argument("--out", type=Path, help="write benchmark.json and benchmark.md here")
    a = ap.parse_args(argv)
    for f in ("emps_estimation.npz", "emps_validation.npz"):
        if not (a.data / f).is_file():
            print(f"benchmark.py: error: {a.data / f} not found (--data or EMPS_DIR)",
                  file=sys.stderr)
            return 2
    try:
        report = json.loads(a.report.read_text())
    except (OSError, ValueError) as exc:
        print(f"benchmark.py: error: {a.report}: {exc}", file=sys.stderr)
        return 2
    res = run(a.data, report)
    md = markdown(res)
    print(md)
    if a.out:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "benchmark.json").write_text(json.dumps(res, indent=2) + "\n")
        (a.out / "benchmark.md").write_text(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
