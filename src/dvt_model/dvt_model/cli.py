"""``dvt-model``: describe a parameter set (ratios, speed relations, M, D, Q, A, B).

Usage::

    dvt-model describe [--params NAME_OR_FILE] [--gear G] [--json]
    dvt-model compare [--params NAME_OR_FILE] [--against NAME_OR_FILE] [--json]
    dvt-model requirement [--json]
    dvt-model design [--design FILE.yaml] [--json] [--plots DIR] [--strict]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

from dvt_model.brake import static_torque
from dvt_model.design import design_report, format_report, load_design, write_plots
from dvt_model.dynamics import rigid_model
from dvt_model.errors import DvtModelError
from dvt_model.kinematics import kinematics, stage_ratio
from dvt_model.params import available_parameter_sets, load_parameters
from dvt_model.requirements import baseline_requirement


def _rows(mat: Any) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.atleast_2d(np.asarray(mat, dtype=float))]


def describe(params_name: str, gear: int = 1) -> dict[str, Any]:
    """JSON-ready description of a parameter set (see module docstring)."""
    params = load_parameters(params_name)
    kin = kinematics(params)
    model = rigid_model(params)
    A = model.A
    eig = np.linalg.eigvals(A)
    brake_1A = float(static_torque(params.brake, 0.125))
    return {
        "params": params.name,
        "lumping": params.lumping,
        "gear_ratios": {str(g): float(kin.gear_ratio(g)) for g in (1, 2, 3)},
        "gear_ratios_exact": {str(g): str(kin.gear_ratio(g)) for g in (1, 2, 3)},
        "stage_ratios": [float(stage_ratio(s.sun, s.ring)) for s in params.stages],
        "speed_relations": {m: v for m, v in kin.as_strings().items()
                            if not m.endswith(("_abs", "_rel"))},
        "speed_relations_note": "member speed = a*omega_sun + b*omega_carrier3 as [a, b]; planet "
                                "speeds in the thesis convention (positive opposite to the sun)",
        "gear": gear,
        "M": _rows(model.M),
        "D": _rows(model.D),
        "Q": _rows(model.Q(gear)),
        "A": _rows(A),
        "B": _rows(model.B(gear)),
        "B_thesis_inputs": _rows(model.B_thesis(brake_1A, gear)),
        "eigenvalues_A": [float(x) for x in np.sort(eig.real)] if np.all(eig.imag == 0)
        else [[float(x.real), float(x.imag)] for x in eig],
        "motor_constant": params.motor_constant,
        "brake_static_torque_at_0.125A": brake_1A,
        "brake_time_constant": params.brake.time_constant,
        "band_gains": [float(g) for g in params.brake.gains],
        "band_time_constants": [float(t) for t in params.brake.time_constants],
    }


def compare(params_name: str, against: str) -> dict[str, Any]:
    """How much ``params_name`` changes A and B relative to ``against`` (relative Frobenius)."""
    a, b = describe(params_name), describe(against)
    out: dict[str, Any] = {"params": a["params"], "against": b["params"]}
    for key in ("M", "D", "A", "B"):
        x, y = np.asarray(a[key]), np.asarray(b[key])
        out[f"{key}_relative_change"] = float(np.linalg.norm(x - y) / np.linalg.norm(y))
        out[key] = {"params": a[key], "against": b[key]}
    out["eigenvalues_A"] = {"params": a["eigenvalues_A"], "against": b["eigenvalues_A"]}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dvt-model", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("describe", help="ratios, speed relations, M, D, Q, A, B")
    d.add_argument("--params", default="thesis",
                   help=f"bundled set {available_parameter_sets()} or a YAML file")
    d.add_argument("--gear", type=int, default=1, choices=(1, 2, 3),
                   help="band whose brake torque is the second input of Q and B")
    d.add_argument("--json", action="store_true", help="print JSON")
    c = sub.add_parser("compare", help="relative change of M, D, A, B between two sets")
    c.add_argument("--params", default="physical")
    c.add_argument("--against", default="thesis")
    c.add_argument("--json", action="store_true")
    r = sub.add_parser("requirement", help="thesis eq. 1.1-1.3: T_max and power of the arm")
    r.add_argument("--json", action="store_true")
    de = sub.add_parser("design", help="thesis ch. 1-3 recomputed and checked: requirement, "
                        "gears, shafts, bearings, splines")
    de.add_argument("--design", default=None, help="design YAML (default: the bundled thesis "
                    "design, dvt_model/design/thesis.yaml)")
    de.add_argument("--json", action="store_true", help="print the machine-readable report")
    de.add_argument("--plots", default=None, metavar="DIR",
                    help="write the requirement curves (figures 3-4) as PNG into DIR")
    de.add_argument("--strict", action="store_true", help="exit 1 if a check fails")
    args = parser.parse_args(argv)
    if args.cmd == "design":
        return _design(args.design, args.json, args.plots, args.strict)
    try:
        if args.cmd == "describe":
            out = describe(args.params, args.gear)
        elif args.cmd == "compare":
            out = compare(args.params, args.against)
        else:
            req = baseline_requirement()
            out = {"inertia_kg_m2": req.inertia, "gravity_torque_Nm": req.gravity_torque,
                   "inertial_torque_Nm": req.inertial_torque, "T_max_Nm": req.torque,
                   "power_W_at_1_rad_s": req.power}
    except DvtModelError as exc:
        print(f"dvt-model: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        for key, value in out.items():
            print(f"{key}: {value}")
    return 0


def _finite(value: Any) -> Any:
    """``value`` with non-finite floats as ``None`` (strict JSON)."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _design(path: str | None, as_json: bool, plots: str | None, strict: bool) -> int:
    """``dvt-model design``: 0 = report printed (1 with ``--strict`` and a failed check),
    2 = invalid design file."""
    try:
        rep = design_report(load_design(path))
        written = write_plots(rep, plots) if plots else []
    except DvtModelError as exc:
        print(f"dvt-model: {exc}", file=sys.stderr)
        return 2
    if as_json:
        print(json.dumps(_finite(rep), indent=2, allow_nan=False))
    else:
        print(format_report(rep))
        for p in written:
            print(f"wrote {p}")
    return 1 if strict and rep["summary"]["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
