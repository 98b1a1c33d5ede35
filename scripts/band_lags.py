"""Each band's gain and engagement lag as the identifier's baseline fits them, at a chosen fit
decimation (the figures of ``docs/identification.md`` on the band lags).

Records the shift-rich experiment (``ident_shifts``) offline on the plant preset ``bands`` as
``tests/test_band_spread.py`` does (estimation seed 31, validation 131; ``--draw`` another
plant), identifies the ``dvt`` description's baseline (no candidate) with ``preprocess.
fit_decimate`` replaced by each ``--fit-decimate`` given (0: the description's own, ``auto``),
and prints per band the plant's value, the estimate and its reported std. ``--own-model``
then also replaces the fitted outputs by the identifier's own model at the plant's band values
(the other parameters as fitted, Gaussian noise of the fit's residual size per output, seed 5)
and refits from the same starts on the same grid: does the fit find the lag its model has?
``--where`` says where in the recording each lag's estimate comes from: the fit's cost with
that band's lag put back to the plant's value (every other parameter as fitted) minus the
fit's own, split into the engagements (from each rise of the band's current, 0.7 s), the
releases (from each fall, 0.8 s: the spin-up that follows, whose speeds carry the release's
effect) and the rest. ``--noise-free`` records without the tachometer's and the currents'
noise (the encoders' and A/D quantisation stay). ``--no-intersample`` identifies without the
description's ``hold: linear`` (motor current) and ``sampling: interval`` (sun speed), as the
identifier did before (:func:`dvt_identify.data.intersample`). The fit at 1 kHz
(``--fit-decimate 1``) takes about 7 minutes on one core, the default (5) about 2.

Usage::

    .venv/bin/python scripts/band_lags.py [--fit-decimate 0 2 1] [--draw SEED] [--own-model]
        [--where] [--noise-free] [--no-intersample]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

from dvt_driver.plant.hidden import load_hidden
from dvt_driver.plant.offline import record_offline
from dvt_driver.plant.settings import SensorConfig
from dvt_driver.run.experiment_core import build
from dvt_identify import identifiability
from dvt_identify.description import load_description
from dvt_identify.fit import OEFit
from dvt_identify.loop import LoopConfig, identify
from dvt_identify.pipeline import load_segments
from dvt_model.params import load_parameters


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit-decimate", type=int, nargs="+", default=[0])
    ap.add_argument("--draw", type=int, default=None, help="plant draw seed (default: fixed)")
    ap.add_argument("--own-model", action="store_true",
                    help="also refit on the identifier's own model at the plant's band values")
    ap.add_argument("--noise-free", action="store_true",
                    help="record with the tachometer, motor- and brake-current noise at 0")
    ap.add_argument("--where", action="store_true",
                    help="split each lag's cost difference into engagements, releases, rest")
    ap.add_argument("--no-intersample", action="store_true",
                    help="the dvt description without its hold and sampling keys (the motor "
                         "current held as sampled, the sun speed read at the sample)")
    a = ap.parse_args()
    seed = 31 if a.draw is None else a.draw
    hidden = load_hidden("bands", draw=a.draw)
    if hidden.bands is None or hidden.bands.gain is None or hidden.bands.time_constant is None:
        print("band_lags: the preset 'bands' drew no band values", file=sys.stderr)
        return 1
    params = load_parameters("physical")
    sensors = (dataclasses.replace(SensorConfig(), tach_noise=0.0, motor_current_noise=0.0,
                                   brake_current_noise=0.0) if a.noise_free else None)
    tmp = Path(tempfile.mkdtemp(prefix="dvt-band-lags-"))
    est = record_offline(tmp / "est", build("ident_shifts", seed=seed), params, hidden,
                         seed=seed, sensors=sensors)
    val = record_offline(tmp / "val", build("ident_shifts", seed=seed + 100), params, hidden,
                         seed=seed + 100, sensors=sensors)
    desc0 = load_description("dvt")
    if a.no_intersample:
        desc0 = load_description(without_intersample(desc0.text, tmp))
    e, v = load_segments([est], desc0), load_segments([val], desc0)
    chk = identifiability.check(desc0, e)
    desc = identifiability.apply(desc0, chk)
    for q in a.fit_decimate:
        cfg = LoopConfig.from_options(desc.fit, q if q > 0 else desc.preprocess.fit_decimate)
        r = identify(e, v, desc, dataclasses.replace(cfg, max_effects=0), check=chk)
        fit = r.baseline.fit
        truth = {}
        for k in (1, 2, 3):
            truth[f"band_gain_ring{k}"] = hidden.bands.gain[k - 1]
            truth[f"band_time_constant_brake{k}"] = hidden.bands.time_constant[k - 1]
        vf = " / ".join(f"{v:.2f}" for v in r.baseline.val.fit_percent) + " %"
        _show(f"fit_decimate {q or 'auto'}: fit step {r.fit_dt * 1e3:g} ms, validation fit "
              f"{vf}", fit, truth)
        if a.where:
            _where(fit, truth)
        if a.own_model:
            _show("  the same fit on the identifier's own model at the plant's band values",
                  _refit_on_own_model(fit, truth), truth)
    return 0


def _show(title: str, fit: OEFit, truth: dict[str, float], fmt: str = ".4g",
          unit: str | None = None, relative: bool = False) -> None:
    """Each parameter of ``truth``: the plant's value, the fit's with its reported std and the
    offset in std (values in format ``fmt``; with ``unit``, the offset in that unit too; with
    ``relative``, in per cent of the plant's value)."""
    p, sd = fit.parameters(), fit.parameter_std()
    print(title)
    for name, t in truth.items():
        off = (p[name] - t) / sd[name] if sd[name] > 0 else float("inf")
        also = "" if unit is None else f", {p[name] - t:+{fmt}} {unit}"
        if relative and t != 0:
            also += f", {100 * (p[name] / t - 1):+.3f} %"
        print(f"  {name:28s} plant {t:{fmt}}  fit {p[name]:{fmt}} +- {sd[name]:.2g}"
              f"  ({off:+.1f} std{also})", flush=True)


def without_intersample(text: str, where: Path) -> Path:
    """The ``dvt`` description ``text`` without ``hold: linear`` on the motor current and
    ``sampling: interval`` on the sun speed (:func:`dvt_identify.data.intersample`): the
    simulation's own convention, written to ``where``."""
    path = where / "dvt-no-intersample.yaml"
    path.write_text(drop_intersample(text, hold=True, sampling=True))
    return path


def drop_intersample(text: str, hold: bool, sampling: bool) -> str:
    """The ``dvt`` description ``text`` with the motor current held as sampled (``hold``: no
    ``hold: linear``) and the sun speed read as instantaneous (``sampling``: no ``sampling:
    interval``)."""
    for on, key in ((hold, ", hold: linear}"), (sampling, ",\n     sampling: interval}")):
        if on:
            if text.count(key) != 1:
                raise SystemExit("the dvt description's motor or sun_shaft line changed")
            text = text.replace(key, "}")
    return text


ENGAGED_S = 0.7
"""Span after a rise of a band's current counted as its engagement [s] (``ident_shifts``'
``engaged``)."""
RELEASED_S = 0.8
"""Span after a fall of a band's current counted as its release [s]."""


def _where(fit: OEFit, truth: dict[str, float]) -> None:
    """Per band: the weighted cost with its lag at the plant's value minus the fit's, split
    into engagements, releases and the rest (module docstring)."""
    m = fit.model
    for k in (1, 2, 3):
        name = f"band_time_constant_brake{k}"
        theta = np.array(fit.theta_, dtype=float)
        theta[list(m.names).index(name)] = truth[name]
        parts = {"engagements": 0.0, "releases": 0.0, "rest": 0.0}
        for seg, x0 in zip(fit.segments_, fit.x0_, strict=True):
            r0 = (seg.y - m.simulate(fit.theta_, seg, x0)) / fit.weights_
            r1 = (seg.y - m.simulate(theta, seg, x0)) / fit.weights_
            d = np.nansum(r1 * r1 - r0 * r0, axis=1)
            on = seg.u[:, list(seg.input_names).index(f"brake{k}")] > 0.01
            t = seg.t
            engage = np.zeros(seg.n, dtype=bool)
            release = np.zeros(seg.n, dtype=bool)
            for e in np.flatnonzero(np.diff(on.astype(int)) != 0) + 1:
                span = ENGAGED_S if on[e] else RELEASED_S
                (engage if on[e] else release)[(t >= t[e]) & (t < t[e] + span)] = True
            parts["engagements"] += float(d[engage].sum())
            parts["releases"] += float(d[release & ~engage].sum())
            parts["rest"] += float(d[~engage & ~release].sum())
        total = sum(parts.values())
        print(f"  {name}: cost at the plant's lag minus the fit's {total:.3g}: "
              + ", ".join(f"{n} {v:.3g}" for n, v in parts.items()), flush=True)


def _refit_on_own_model(fit: OEFit, truth: dict[str, float]) -> OEFit:
    """``fit`` repeated on its segments with the outputs its model gives at ``truth`` (the
    other parameters as fitted) plus noise of the fit's residual size."""
    m = fit.model
    theta = np.array(fit.theta_, dtype=float)
    for name, value in truth.items():
        theta[list(m.names).index(name)] = value
    rng = np.random.default_rng(5)
    segs = []
    for seg, x0 in zip(fit.segments_, fit.x0_, strict=True):
        sd = np.nanstd(seg.y - m.simulate(fit.theta_, seg, x0), axis=0)
        y = m.simulate(theta, seg, x0) + rng.standard_normal(seg.y.shape) * sd
        segs.append(dataclasses.replace(seg, y=y))
    return copy.copy(fit).fit(segs)


if __name__ == "__main__":
    sys.exit(main())
