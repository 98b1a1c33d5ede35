"""EMPS scored by its benchmark's own rules: simulated position, 20-sample initialisation window.

Protocol (the ``nonlinear_benchmarks`` split of EMPS): input ``vir`` (drive force
``F = gtau * vir`` [N]), output the motor position ``qm`` [m]; estimate on DATA_EMPS
(``emps_estimation.npz``), test on DATA_EMPS_PULSES (``emps_validation.npz``). On the test record
the model may use the first 20 samples of ``qm`` to set its initial state; it is then simulated
open loop from ``vir`` over the whole record and the figure is the RMS of the position error over
the samples after the window, in mm.

Model: ``descriptions/emps-position.yaml``, the EMPS drive with the position as a state
(``q' = v``, ``M v' = F - Fv v + effects``), with the friction effects that the identification
loop accepted on the velocity data (``report.json`` of ``dvt-identify``, option ``--report``;
default: Coulomb friction with offset, then direction-dependent viscous friction). Every model
is fitted on the estimation record only, for the benchmark's output
(:func:`dvt_identify.benchmarks.fit_for_output`: simulated position, initial state from the same
20-sample window as the test). Also printed, all simulated and scored the same way: the published
IDIM-LS parameters (symmetric and asymmetric friction), the velocity loop's final model, two
variants of the fit criterion, and, as a diagnostic only (not a benchmark result), the same
structure fitted on the test record, with the friction levels of each half cycle of both records.

    .venv/bin/python examples/emps/benchmark.py [--data DIR] [--report REPORT.json] [--out DIR]

Writes ``benchmark.json`` and ``benchmark.md`` to ``--out`` when given; prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from dvt_identify.benchmarks import fit_for_output, protocol_score_model
from dvt_identify.data import Segment
from dvt_identify.description import Description, load_description
from dvt_identify.effects import Effect
from dvt_identify.metrics import fit_percent
from dvt_identify.simulation import OEModel

Array = NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("EMPS_DIR", str(ROOT.parent / "shared" / "data" / "emps")))
N_INIT = 20
POS, VEL = 0, 1
DEFAULT_EFFECTS = ("coulomb_friction", "asymmetric_friction")
START_FACTORS = (1.0, 0.7, 0.9, 1.1, 1.3)
"""Starts of the benchmark fit: the equation-error start scaled by each factor; the fit with
the lowest estimation figure is kept (the position criterion has several local optima). A model
without effects is linear in the state and has one optimum: it gets the first start only."""

# Published figures (test RMS of the simulated position, mm): Champneys et al. 2024, "Baseline
# results for selected nonlinear system identification benchmarks".
PUBLISHED: tuple[tuple[str, float], ...] = (
    ("LTI state space (Champneys et al. 2024)", 5.53),
    ("polynomial NARX (Champneys et al. 2024)", 5.17),
    ("best known, SOTA (Champneys et al. 2024)", 2.64),
)
# IDIM-LS parameters of the benchmark authors (description PDF section 3.4 and 4.2), in this
# model's parameters: M, Fv, Fc, offset[, dFv] (Fv+- = Fv +- dFv, Fc+- = Fc +- offset).
IDIM_SYM = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
IDIM_ASYM = {"M": 95.1540, "Fv": (166.7061 + 240.4236) / 2, "dFv": (166.7061 - 240.4236) / 2,
             "Fc": (20.1440 + 20.6277) / 2, "offset": (20.1440 - 20.6277) / 2}


def load_record(path: Path, name: str) -> Segment:
    """A record as a segment: input ``F = gtau * vir`` [N], states ``(qm, v)``; ``v`` as in
    run.sh (zero-phase 4th-order Butterworth at 100 Hz on ``qm``, then central differences). Only
    the position enters the benchmark figure; ``v`` is for velocity figures and the fit variant
    that also weighs it."""
    d = np.load(path)
    t = np.asarray(d["t"], float)
    dt = float(np.mean(np.diff(t)))
    q = np.asarray(d["qm"], float)
    sos = signal.butter(4, 100.0, fs=1.0 / dt, output="sos")
    v = np.gradient(signal.sosfiltfilt(sos, q), dt)
    force = float(d["gtau"]) * np.asarray(d["vir"], float)
    return Segment(name, t - t[0], force[:, None], np.column_stack([q, v]), ("force",),
                   ("position", "carriage"), dt)


def accepted_effects(report: Path | None) -> tuple[list[str], str]:
    """Names of the effects the velocity loop accepted (in order), and where they came from."""
    if report is None:
        return list(DEFAULT_EFFECTS), "default (Coulomb with offset, asymmetric viscous)"
    rep = json.loads(report.read_text())
    names = [str(e["name"]) for e in rep.get("effects", []) if e.get("accepted")]
    return names, f"accepted by the velocity loop ({report})"


def loop_parameters(report: Path | None) -> dict[str, float] | None:
    """Final parameters of the velocity loop (``report.json``), or ``None``."""
    if report is None:
        return None
    rep = json.loads(report.read_text())
    return {str(k): float(v) for k, v in rep["final"]["parameters"].items()}


def build(desc: Description, names: Sequence[str]) -> OEModel:
    """The position structure with the named candidate effects, in that order."""
    cands: dict[str, Effect] = {e.name: e for e in desc.make_candidates()}
    missing = [n for n in names if n not in cands]
    if missing:
        raise SystemExit(f"benchmark.py: effects {missing} are not candidates of "
                         f"{desc.source}")
    return OEModel(desc.structure, [cands[n] for n in names])


def theta_of(model: OEModel, values: dict[str, float]) -> Array:
    """Parameter vector from values by name (missing ones: their initial value)."""
    return np.array([values.get(s.name, s.initial) for s in model.specs], dtype=float)


def equation_error_start(model: OEModel, seg: Segment) -> Array:
    """Start values by linear least squares of the inverse model on the estimation record
    (``F = M a + Fv v + Fc sign v + offset + dFv |v|`` on 20 Hz zero-phase filtered signals,
    samples with ``|v| > 0.01`` m/s); parameters without a linear column keep their initial
    value. Clipped into the bounds."""
    sos = signal.butter(4, 20.0, fs=1.0 / seg.dt, output="sos")
    q = signal.sosfiltfilt(sos, seg.y[:, POS])
    f = signal.sosfiltfilt(sos, seg.u[:, 0])
    v = np.gradient(q, seg.dt)
    a = np.gradient(v, seg.dt)
    cols = {"M": a, "Fv": v, "Fc": np.sign(v), "offset": np.ones_like(v), "dFv": np.abs(v)}
    names = [n for n in model.names if n in cols]
    keep = np.abs(v) > 0.01
    keep[: seg.n // 50] = keep[-seg.n // 50:] = False
    X = np.column_stack([cols[n][keep] for n in names])
    coef, *_ = np.linalg.lstsq(X, f[keep], rcond=None)
    theta = model.initial()
    for n, c in zip(names, coef, strict=True):
        theta[model.names.index(n)] = c
    lo = np.array([s.lower for s in model.specs])
    hi = np.array([s.upper for s in model.specs])
    return np.asarray(np.clip(theta, lo, hi), dtype=float)


def bounds(model: OEModel) -> tuple[Array, Array]:
    return (np.array([s.lower for s in model.specs], dtype=float),
            np.array([s.upper for s in model.specs], dtype=float))


@dataclass
class Row:
    """One line of the table."""

    label: str
    fitted_on: str
    params: dict[str, float]
    test_rms_mm: float
    est_rms_mm: float | None
    test_vel_fit: float | None
    record_diff_mm: float | None = None
    benchmark: bool = True
    seconds: float = 0.0
    starts: list[dict[str, float]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"label": self.label, "fitted_on": self.fitted_on, "parameters": self.params,
                "test_rms_mm": self.test_rms_mm, "estimation_rms_mm": self.est_rms_mm,
                "test_velocity_fit_percent": self.test_vel_fit,
                "record_difference_rms_mm": self.record_diff_mm,
                "benchmark_result": self.benchmark, "seconds": self.seconds,
                "starts": self.starts}


def score(model: OEModel, theta: Array, est: Segment, val: Segment, label: str,
          fitted_on: str, benchmark: bool = True, seconds: float = 0.0) -> Row:
    """The protocol figure on the test record (and on the estimation record), and the
    velocity fit % of the same simulation on the test record."""
    t = protocol_score_model(model, theta, val, POS, N_INIT, model.nx)
    e = protocol_score_model(model, theta, est, POS, N_INIT, model.nx)
    vs = model.simulate(theta, val, t.x0)[:, VEL]
    vfit = float(fit_percent(val.y[N_INIT:, VEL], vs[N_INIT:])[0])
    # Both records follow the same reference (qg) and their positions differ by at most the
    # pulses' 0.13 mm: the difference of the two error signals is what the model does with the
    # difference between the records (the pulses and the force the test record needed).
    n = min(val.n, est.n)
    d = ((t.y_sim[:n] - val.y[:n, POS]) - (e.y_sim[:n] - est.y[:n, POS]))[N_INIT:]
    return Row(label, fitted_on, model.parameters(theta), 1e3 * t.rms, 1e3 * e.rms, vfit,
               1e3 * float(np.sqrt(np.mean(d * d))), benchmark, seconds)


def friction_by_half_cycle(seg: Segment, parts: int = 8) -> list[dict[str, float]]:
    """Inverse-model LS per part of the record (``parts`` equal parts; with the EMPS reference
    each part is one direction of travel): ``F = M a + Fv v + Fc sign v`` on 20 Hz filtered
    signals, samples with ``|v| > 0.01`` m/s. Returns M, Fv, Fc and the direction per part."""
    sos = signal.butter(4, 20.0, fs=1.0 / seg.dt, output="sos")
    q = signal.sosfiltfilt(sos, seg.y[:, POS])
    f = signal.sosfiltfilt(sos, seg.u[:, 0])
    v = np.gradient(q, seg.dt)
    a = np.gradient(v, seg.dt)
    edges = np.linspace(0, seg.n, parts + 1).astype(int)
    out = []
    for i in range(parts):
        s = slice(edges[i] + 100, edges[i + 1] - 100)
        keep = np.abs(v[s]) > 0.01
        X = np.column_stack([a[s], v[s], np.sign(v[s])])[keep]
        coef, *_ = np.linalg.lstsq(X, f[s][keep], rcond=None)
        out.append({"part": float(i), "direction": float(np.sign(np.median(v[s][keep]))),
                    "M": float(coef[0]), "Fv": float(coef[1]), "Fc": float(coef[2])})
    return out


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


def run(data: Path, report: Path | None, say: Any) -> dict[str, Any]:
    """Every row of the benchmark table (see the module docstring)."""
    est = load_record(data / "emps_estimation.npz", "DATA_EMPS")
    val = load_record(data / "emps_validation.npz", "DATA_EMPS_PULSES")
    desc = load_description("emps-position")
    names, source = accepted_effects(report)
    say(f"effects: {', '.join(names) or 'none'} ({source})")
    rows: list[Row] = []
    final_model: OEModel | None = None
    final_theta: Array | None = None
    # ours: fitted for the benchmark's output, one row per accepted effect, in the loop's order
    for k in range(len(names) + 1):
        model = build(desc, names[:k])
        lo, hi = bounds(model)
        t0 = time.monotonic()
        eq = equation_error_start(model, est)
        fits = []
        for f in START_FACTORS if k else START_FACTORS[:1]:
            fit = fit_for_output(model, est, np.clip(eq * f, lo, hi), lo, hi, POS, N_INIT,
                                 model.nx)
            fits.append((f, fit))
        best = min(fits, key=lambda ff: ff[1].rms)[1]
        label = "ours: " + (" + ".join(["inertia + viscous", *names[:k]]))
        row = score(model, best.theta, est, val, label, "estimation (position)",
                    seconds=time.monotonic() - t0)
        # every start's estimation and test figures: the spread of the test figure among
        # near-equivalent estimation optima (selection is by the estimation figure only)
        row.starts = [{"factor": f, "estimation_rms_mm": 1e3 * ft.rms,
                       "test_rms_mm": 1e3 * protocol_score_model(model, ft.theta, val, POS,
                                                                 N_INIT, model.nx).rms}
                      for f, ft in fits]
        rows.append(row)
        say(f"{label}: test {row.test_rms_mm:.2f} mm, estimation {row.est_rms_mm:.2f} mm "
            f"(best of {len(fits)} starts, {row.seconds:.1f} s)")
        final_model, final_theta = model, best.theta
    if final_model is None or final_theta is None:  # pragma: no cover - the loop runs once
        raise SystemExit("benchmark.py: nothing fitted")
    lo, hi = bounds(final_model)
    # the same criterion with the velocity weighed in (OEFit's weighting by std)
    t0 = time.monotonic()
    both = fit_for_output(final_model, est, final_theta, lo, hi, POS, N_INIT, final_model.nx,
                          also=(VEL,))
    rows.append(score(final_model, both.theta, est, val,
                      "variant: position + velocity criterion", "estimation (q, v)",
                      seconds=time.monotonic() - t0))
    # references, simulated and scored the same way
    sym = build(desc, ["coulomb_friction"])
    rows.append(score(sym, theta_of(sym, IDIM_SYM), est, val,
                      "published IDIM-LS (Janot et al.)", "estimation (authors)"))
    if "dFv" in final_model.names:
        asym = final_model
    else:
        asym = build(desc, ["coulomb_friction", "asymmetric_friction"])
    rows.append(score(asym, theta_of(asym, IDIM_ASYM), est, val,
                      "published asymmetric IDIM-LS (Janot et al.)", "estimation (authors)"))
    loop = loop_parameters(report)
    if loop is not None:
        rows.append(score(final_model, theta_of(final_model, loop), est, val,
                          "velocity loop's final model (report.json)", "estimation (velocity)"))
    # diagnostic, not a benchmark result: the same structure fitted on the test record
    t0 = time.monotonic()
    orc = fit_for_output(final_model, val, final_theta, lo, hi, POS, N_INIT, final_model.nx)
    rows.append(score(final_model, orc.theta, est, val,
                      "diagnostic: same structure fitted on the test record", "TEST (position)",
                      benchmark=False, seconds=time.monotonic() - t0))
    drift = {"estimation": friction_by_half_cycle(est), "test": friction_by_half_cycle(val)}
    return {"protocol": {"input": "vir (force gtau*vir, N)", "output": "qm (m)",
                         "estimation": "DATA_EMPS", "test": "DATA_EMPS_PULSES",
                         "n_init": N_INIT, "n_scored": val.n - N_INIT, "unit": "mm"},
            "effects": names, "effects_source": source,
            "rows": [r.as_dict() for r in rows],
            "published": [{"label": lab, "test_rms_mm": v} for lab, v in PUBLISHED],
            "friction_by_half_cycle": drift,
            "steady_force_difference": steady_force_difference(data)}


def _fmt(x: float | None, nd: int = 2) -> str:
    return "-" if x is None else f"{x:.{nd}f}"


def markdown(res: dict[str, Any]) -> str:
    """The table (and the friction levels per half cycle) as markdown."""
    lines = ["| model | fitted on | M [kg] | Fv+ / Fv- [N s/m] | Fc+ / Fc- [N] | "
             "test RMS [mm] | est. RMS [mm] | test vel. fit % | test - est. error [mm] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in res["rows"]:
        p = r["parameters"]
        fvp, fvm = p.get("Fv+", p.get("Fv")), p.get("Fv-", p.get("Fv"))
        fcp, fcm = p.get("Fc+", p.get("Fc")), p.get("Fc-", p.get("Fc"))
        fv = "-" if fvp is None else f"{fvp:.1f} / {fvm:.1f}"
        fc = "-" if fcp is None else f"{fcp:.2f} / {fcm:.2f}"
        lines.append(f"| {r['label']} | {r['fitted_on']} | {_fmt(p.get('M'))} | {fv} | {fc} | "
                     f"**{_fmt(r['test_rms_mm'])}** | {_fmt(r['estimation_rms_mm'])} | "
                     f"{_fmt(r['test_velocity_fit_percent'])} | "
                     f"{_fmt(r['record_difference_rms_mm'])} |")
    for p in res["published"]:
        lines.append(f"| {p['label']} | estimation | | | | {p['test_rms_mm']:.2f} | | | |")
    lines += ["", "Friction per half cycle (inverse-model LS, |v| > 0.01 m/s):", "",
              "| part | direction | est. Fv | est. Fc | test Fv | test Fc |",
              "|---|---|---|---|---|---|"]
    for e, t in zip(res["friction_by_half_cycle"]["estimation"],
                    res["friction_by_half_cycle"]["test"], strict=True):
        lines.append(f"| {int(e['part'])} | {'+' if e['direction'] > 0 else '-'} | "
                     f"{e['Fv']:.1f} | {e['Fc']:.2f} | {t['Fv']:.1f} | {t['Fc']:.2f} |")
    lines += ["", "Force the test record needed minus the estimation record's, same reference, "
              ">= 150 ms from a pulse edge (mean per quarter of the record):", "",
              "| quarter | + travel [N] | - travel [N] |", "|---|---|---|"]
    for q in res["steady_force_difference"]:
        lines.append(f"| {int(q['part'])} | {q['plus_N']:+.2f} | {q['minus_N']:+.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="folder with the EMPS records")
    ap.add_argument("--report", type=Path, default=None,
                    help="report.json of dvt-identify on the velocity data (effects, final model)")
    ap.add_argument("--out", type=Path, default=None, help="write benchmark.json/.md here")
    args = ap.parse_args(argv)
    for f in ("emps_estimation.npz", "emps_validation.npz"):
        if not (args.data / f).is_file():
            print(f"benchmark.py: error: {args.data / f} not found (--data or EMPS_DIR)",
                  file=sys.stderr)
            return 2

    def say(msg: str) -> None:
        print(f"[emps benchmark] {msg}", file=sys.stderr, flush=True)

    res = run(args.data, args.report, say)
    md = markdown(res)
    print(md)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "benchmark.json").write_text(json.dumps(res, indent=1) + "\n")
        (args.out / "benchmark.md").write_text(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
