"""One randomised clean plant of ``tests/test_false_effects.py`` (a module of its own,
importable by name from ``tests/`` (pytest's ``pythonpath``), so that spawned worker processes
can run it).

A case is a seed, a sample rate and a sensor-noise scale. The plant has no hidden effect; its
physical parameters are drawn per seed (every member inertia times a log-uniform factor in
[1/1.5, 1.5], every damping in [1/2, 2]; each band's gain and engagement lag from the plant
preset ``bands``, :data:`BANDS_DRAW` + seed: the identifier's priors, the thesis values, are
then off, its band priors 8.0 N m/A and 20 ms included), its sensors' noise scaled. Two
independent runs of the ``ident`` experiment (its own experiment and noise seeds each) are
recorded offline at the case's rate, and
``dvt_identify.pipeline.run`` identifies the first validated on the second with the CLI's
set-up (the default ``dvt`` description, its loop settings, no override).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.plant.settings import SensorConfig
from dvt_driver.run.experiment_core import build
from dvt_identify import pipeline
from dvt_model.params import load_parameters

BANDS_DRAW = 20_000
"""The band brakes of case ``seed`` are the ``bands`` preset's draw ``BANDS_DRAW + seed``."""
INERTIA_SPREAD = 1.5
DAMPING_SPREAD = 2.0
NOISE_SCALES = (0.5, 1.0, 2.0)


def case(seed: int) -> tuple[float, float]:
    """The case of ``seed``: (sample rate [Hz], sensor-noise scale): even seeds 1 kHz, odd ones
    62.5 Hz (the thesis rate); noise 0.5, 1 and 2 times the bench's in turn."""
    return (1000.0 if seed % 2 == 0 else 62.5), NOISE_SCALES[(seed // 2) % len(NOISE_SCALES)]


def drawn_parameters(seed: int, root: Path) -> tuple[Path, dict[str, Any]]:
    """The ``physical`` parameter set with its inertias and dampings drawn for ``seed``,
    written to ``root``; returns the file and the drawn factors."""
    from importlib import resources

    text = (resources.files("dvt_model") / "param_sets" / "physical.yaml").read_text()
    data = yaml.safe_load(text)
    rng = np.random.default_rng(10_000 + seed)
    factors: dict[str, Any] = {}

    def draw(spread: float, shape: int | None = None) -> Any:
        f = np.exp(rng.uniform(-np.log(spread), np.log(spread), shape))
        return f.tolist() if shape else float(f)
    for key, spread in (("inertia", INERTIA_SPREAD), ("damping", DAMPING_SPREAD)):
        for member, v in data[key].items():
            if isinstance(v, list):
                f = draw(spread, len(v))
                data[key][member] = [float(a) * b for a, b in zip(v, f, strict=True)]
            else:
                f = draw(spread)
                data[key][member] = float(v) * f
            factors[f"{key}.{member}"] = f
    data["name"] = f"physical-drawn-{seed}"
    path = root / f"params-{seed}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, factors


def one_seed(seed: int, tmp: str) -> dict[str, Any]:
    """Identify clean case ``seed`` (module docstring); the figures."""
    t0 = time.monotonic()
    root = Path(tmp) / f"case-{seed}"
    root.mkdir(parents=True, exist_ok=True)
    rate, noise = case(seed)
    ppath, factors = drawn_parameters(seed, root)
    bands = load_hidden("bands", draw=BANDS_DRAW + seed)
    if bands.bands is None:
        raise RuntimeError("the bands preset drew no band law")
    factors["bands"] = bands.bands.to_mapping()
    params = load_parameters(str(ppath))
    base = SensorConfig()
    sensors = dataclasses.replace(base, tach_noise=base.tach_noise * noise,
                                  motor_current_noise=base.motor_current_noise * noise,
                                  brake_current_noise=base.brake_current_noise * noise)
    period = round(1e6 / rate)

    def run(name: str, s: int) -> Path:
        exp = dataclasses.replace(build("ident", seed=s), sample_period_us=period)
        return record_offline(root / name, exp, params, bands, seed=s + 500, sensors=sensors)
    est, val = run("est", seed), run("val", seed + 1000)
    res = pipeline.run([est], [val], root / "out", "dvt", quiet=True, plots=False,
                       series=False)
    return {"seed": seed, "rate_hz": rate, "noise_scale": noise,
            "accepted": [d.score.label for d in res.accepted],
            "tried": [(d.score.label, d.accepted, round(d.explained_share, 3)
                       if d.explained_share == d.explained_share else None)
                      for d in res.decisions],
            "val_fit": [round(v, 2) for v in res.baseline.val.fit_percent],
            "stopped": next((n for n in res.notes if "augment loop stopped" in n), ""),
            "factors": factors, "seconds": round(time.monotonic() - t0, 1)}
