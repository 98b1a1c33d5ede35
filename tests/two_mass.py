"""A simulated two-mass drive (motor, compliant shaft, load) with one measured speed, made with
the identifier's own simulation (the worked example of docs/own_actuator.md).

``python tests/two_mass.py OUTDIR [--sign-blind]`` writes ``est.npz``, ``val.npz`` and
``test.npz`` (columns ``t``, ``torque``, ``w_motor``) for ``dvt-import``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, load_description
from dvt_identify.effects import make_effect
from dvt_identify.simulation import OEModel

Array = NDArray[np.float64]
TRUE = {"Jm": 0.01, "Jl": 0.03, "k": 20.0, "c": 0.02, "dm": 0.005, "dl": 0.01}
"""The true parameters (mode 8.22 Hz, damping ratio 0.030)."""
RATE = 200.0
NOISE = 0.02
"""White noise on the measured speed [rad/s] (about 1 % of its standard deviation)."""
SEEDS = {"est": 1, "val": 2, "test": 3}


def torque(n: int, dt: float, rng: np.random.Generator) -> Array:
    """Random steps held 0.05-0.5 s, +-0.2 N m: many speed reversals, the mode excited."""
    u = np.empty(n)
    k = 0
    while k < n:
        hold = int(rng.uniform(0.05, 0.5) / dt)
        u[k: k + hold] = rng.uniform(-0.2, 0.2)
        k += hold
    return u


def record(kind: str, seconds: float = 30.0, sign_blind: bool = False,
           desc: Description | None = None) -> Segment:
    """One record (``kind``: est, val or test; its own random input and noise)."""
    desc = desc or load_description("two-mass")
    rng = np.random.default_rng(SEEDS[kind] + (100 if sign_blind else 0))
    dt = 1.0 / RATE
    n = int(seconds * RATE)
    t = np.arange(n) * dt
    u = torque(n, dt, rng)
    st = desc.structure
    theta = np.array([TRUE[p.name] for p in st.params])
    effects = []
    if sign_blind:
        effects.append(make_effect("sign_blind", "w_motor", st.state_names, st.input_names,
                                   output_names=desc.output_names))
        theta = np.concatenate([theta, [1.0]])
    model = OEModel(st, effects)
    clean = make_segment(kind, t, u, np.zeros((n, 1)), desc.input_names, desc.output_names)
    y = model.simulate(theta, clean, np.zeros(model.nx))
    y = y + NOISE * rng.standard_normal(y.shape)
    return make_segment(kind, t, u, y, desc.input_names, desc.output_names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("out", type=Path)
    ap.add_argument("--sign-blind", action="store_true")
    ap.add_argument("--seconds", type=float, default=30.0)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    for kind in SEEDS:
        seg = record(kind, a.seconds, a.sign_blind)
        np.savez(a.out / f"{kind}.npz", t=seg.t, torque=seg.u[:, 0], w_motor=seg.y[:, 0])
        print(a.out / f"{kind}.npz")


if __name__ == "__main__":
    main()
