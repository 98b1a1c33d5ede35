"""A simulated belt drive read by a sign-blind pulse counter: a motor and a pulley joined by an
elastic belt, one input (the drive's command), one sensor (the pulley speed, read as ``|w|``),
short records at 50 Hz (the shape of a coupled-drives benchmark), made with the identifier's
own simulation.

The description gives scales only (every prior 1): nothing in it knows the drive. Three drives
of different modes (:data:`DRIVES`); a record is a random +-amplitude sequence switching every
1-4 samples, the speed read with 2 % white noise.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dvt_identify.data import Segment, make_segment
from dvt_identify.description import Description, parse_description
from dvt_identify.effects.sensors import first_order_lag
from dvt_identify.simulation import OEModel

Array = NDArray[np.float64]
RATE = 50.0
NOISE_SHARE = 0.02
"""White noise on the read speed, as a share of the speed's standard deviation."""
DRIVES: dict[str, dict[str, float]] = {
    "slow_belt": {"Jm": 0.05, "Jp": 0.02, "k": 3.0, "c": 0.02, "dm": 0.15},   # mode 2.3 Hz
    "stiff_belt": {"Jm": 0.02, "Jp": 0.05, "k": 20.0, "c": 0.05, "dm": 0.05},  # 5.9 Hz
    "light_pulley": {"Jm": 0.1, "Jp": 0.01, "k": 1.0, "c": 0.01, "dm": 0.3},  # 1.7 Hz
}
"""Inertias [kg m^2], belt stiffness [N m/rad] and damping, motor damping [N m s/rad]."""
AMPLITUDES = (0.5, 1.0, 1.5)
"""The command's amplitude in each of a drive's records."""


def spec(candidates: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The drive's description (every prior 1), with these candidates (default: the
    sign-blind map, a sensor offset and Coulomb friction on the motor)."""
    scale = {"initial": 1.0, "lower": 1e-6}
    return {
        "name": "belt-drive",
        "inputs": [{"name": "u", "topic": "/belt/drive", "field": "effort", "joint": "motor"}],
        "outputs": [{"name": "w_pulley", "topic": "/belt/joint_states", "field": "velocity",
                     "joint": "pulley"}],
        "structure": {
            "type": "mechanical", "members": ["motor", "pulley"],
            "mass": [["Jm", 0], [0, "Jp"]],
            "damping": [["c + dm", "-c"], ["-c", "c"]],
            "stiffness": [["k", "-k"], ["-k", "k"]],
            "input_matrix": [[1.0], [0.0]], "outputs": {"w_pulley": "pulley"},
            "parameters": {"Jm": dict(scale), "Jp": dict(scale), "k": dict(scale, lower=0.0),
                           "c": dict(scale, lower=0.0), "dm": dict(scale, lower=0.0)}},
        "candidates": candidates if candidates is not None else [
            {"effect": "sign_blind", "where": "w_pulley"},
            {"effect": "sensor_offset", "where": "w_pulley"},
            {"effect": "coulomb_friction", "where": "motor"}],
        "preprocess": {"lowpass": None, "decimate": 1, "fit_decimate": 1},
        "checks": {"min_samples": 100, "max_gap_samples": 3, "max_saturated_fraction": 0.01},
        "fit": {"starts": 3, "refit_starts": 1, "alpha": 0.01, "max_effects": 3,
                "max_tries_per_round": 3, "seed": 0},
    }


def description() -> Description:
    return parse_description(spec(), "belt-drive.yaml")


def command(n: int, amplitude: float, rng: np.random.Generator) -> Array:
    """+-``amplitude``, switching sign at random every 1-4 samples, shape (n,)."""
    u = np.empty(n)
    k = 0
    while k < n:
        hold = int(rng.integers(1, 5))
        u[k: k + hold] = amplitude * rng.choice([-1.0, 1.0])
        k += hold
    return u


def records(drive: str | dict[str, float], seed: int, n: int = 300, friction: float = 0.0,
            lag: float = 0.0, signed: bool = False) -> tuple[list[Segment], list[Array]]:
    """One record per amplitude of :data:`AMPLITUDES` (``n`` samples each, seeds ``seed``,
    ``seed + 1``, ...) of a drive of :data:`DRIVES` (or its parameters): the segments as read
    (``|w| + noise``) and the true signed pulley speeds; ``friction``: a Coulomb friction
    [N m] on the motor; ``lag``: the counter's reading through a first-order filter of this
    time constant [s] (the law of the ``sensor_lag`` effect), the noise added after it;
    ``signed``: the speed read with its sign (``w + noise``, the same noise: a counter that
    knows the direction)."""
    desc = description()
    st = desc.structure
    values = DRIVES[drive] if isinstance(drive, str) else drive
    name = drive if isinstance(drive, str) else "drive"
    theta = [values[p.name] for p in st.params]
    truth = OEModel(st, [])
    segs, speeds = [], []
    for k, amp in enumerate(AMPLITUDES):
        rng = np.random.default_rng(seed + k)
        t = np.arange(n) / RATE
        u = command(n, amp, rng)
        blank = make_segment(f"{name}-{k}", t, u, np.zeros((n, 1)), desc.input_names,
                             desc.output_names)
        model, th = truth, np.array(theta)
        if friction:
            cf = next(c for c in desc.make_candidates() if c.label() == "coulomb_friction@motor")
            model, th = OEModel(st, [cf]), np.array([*theta, friction, 0.0])
        w = model.simulate(th, blank, np.zeros(truth.nx))[:, 0]
        y = (first_order_lag(w if signed else np.abs(w), lag, 1.0 / RATE)
             + NOISE_SHARE * float(np.std(w)) * rng.standard_normal(n))
        segs.append(make_segment(blank.name, t, u, y[:, None], desc.input_names,
                                 desc.output_names))
        speeds.append(w)
    return segs, speeds


def write_npz(seg: Segment, path: Path) -> Path:
    """``seg`` as an NPZ for ``dvt-import`` (columns ``t``, ``u``, ``w``)."""
    np.savez(path, t=seg.t, u=seg.u[:, 0], w=seg.y[:, 0])
    return path


def write_description(path: Path, extra: list[dict[str, Any]] | None = None) -> Path:
    """The description (:func:`spec`), with ``extra`` candidates after the default ones."""
    d = spec()
    d["candidates"] = [*d["candidates"], *(extra or [])]
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def draw(rng: np.random.Generator) -> dict[str, float]:
    """A random drive: inertias log-uniform (motor 0.01-0.1, pulley 0.005-0.05 kg m^2), the
    belt mode uniform over 1-6 Hz with a damping ratio of 0.03-0.2, the motor's own pole
    (``dm / (Jm + Jp)``) uniform over 0.5-5 1/s."""
    jm = float(np.exp(rng.uniform(np.log(0.01), np.log(0.1))))
    jp = float(np.exp(rng.uniform(np.log(0.005), np.log(0.05))))
    red = jm * jp / (jm + jp)
    w = 2.0 * np.pi * float(rng.uniform(1.0, 6.0))
    zeta = float(rng.uniform(0.03, 0.2))
    return {"Jm": jm, "Jp": jp, "k": w * w * red, "c": 2.0 * zeta * w * red,
            "dm": float(rng.uniform(0.5, 5.0)) * (jm + jp)}

