"""The held-current scenario of the change detector's offline tests (dvt_driver.plant.offline)."""

from __future__ import annotations

import numpy as np

from dvt_driver.link.protocol import Hello, Status
from dvt_driver.plant.core import PlantSim
from dvt_driver.plant.offline import KEEP_ALIVE_SAMPLES, held_current, predicted_held_current
from dvt_model.params import load_parameters


def test_held_current_keeps_the_motor_on_in_neutral_until_the_end() -> None:
    params = load_parameters("physical")
    plant = PlantSim(params, None, seed=1)
    predicted = predicted_held_current(plant, params, 4.0, 0.6, 0.2)
    # the watchdog (0.2 s) would stop the motor after 200 samples without a keep-alive
    assert KEEP_ALIVE_SAMPLES < 200
    out = list(predicted)
    t = np.array([s for s, _ in out])
    assert t[0] >= 0.2 and t[0] - 0.2 < 1.5e-3  # the node starts at lead_s
    assert t[-1] <= 0.6 and 0.6 - t[-1] < 1.5e-3  # and stops at until_s
    assert np.all(np.diff(t) > 0)
    # the first sample anchors the model, the stamps are the plant's
    assert out[0][1].anchored and not any(p.anchored for _, p in out[1:])
    assert [p.stamp for _, p in out] == t.tolist()
    assert np.all(np.isfinite(np.array([p.residual for _, p in out])))


def test_held_current_refreshes_the_set_point_within_the_watchdog() -> None:
    plant = PlantSim(load_parameters("physical"), None, seed=2)
    plant.handle(Hello())
    samples = list(held_current(plant, 2.0, 1.0))
    assert len(samples) in (1000, 1001)
    bits = [Status(v.status) for v in samples[5:]]
    assert all(Status.ENABLED in b and Status.WATCHDOG not in b for b in bits)
    assert all(b & (Status.BRAKE1 | Status.BRAKE2 | Status.BRAKE3) == 0 for b in bits)
    assert abs(np.mean([v.motor_current for v in samples[100:]]) - 2.0) < 0.05
