"""One look for every figure of the identifier and the demo: colours, line widths, legends, units.

The convention (defined here once, imported by every plotting function):

* **measured** data: black, thin, drawn *on top* of the predictions (``zorder`` 3), so a
  prediction that matches it shows as a coloured halo and never hides it;
* **before** (the baseline model, the model node's prior): orange (``tab:orange``);
* **after** (the final model, the identified and pushed model): blue (``tab:blue``);
* accepted candidates green, the others grey; bounds light grey (band) and grey (lines);
* signal pairs of one model (step and Bode plots) take :data:`CHANNELS`, never a model colour.

Legends go outside the axes (:func:`legend_outside`), to the right, so they never cover data.
Axis labels always carry a unit in brackets (:func:`label`, :func:`psd_unit`,
:func:`lag_label`); a dimensionless quantity says so (``[1]``).

Pure: no matplotlib import here (the functions take an ``Axes`` and return keyword arguments).
"""

from __future__ import annotations

import math
from typing import Any

MEASURED = "black"
"""Colour of measured data."""
BEFORE = "tab:orange"
"""Colour of the model before identification (baseline, prior)."""
AFTER = "tab:blue"
"""Colour of the model after identification (final, pushed)."""
ACCEPTED = "tab:green"
"""Colour of an accepted candidate."""
OTHER = "0.6"
"""Colour of a candidate that was not accepted."""
CHANNELS = ("tab:purple", "tab:brown", "tab:cyan", "tab:olive", "tab:pink", "tab:red",
            "tab:gray")
"""Colours of signal pairs (input -> output) in a figure that compares no models: none of them
is a model colour, so no channel reads as "before" or "after"."""
BAND = "0.85"
"""Fill colour of a confidence band."""
BOUND = "0.45"
"""Colour of a bound drawn as a line."""

MEASURED_LW = 0.6
"""Line width of measured data (thin: the predictions under it stay visible)."""
MODEL_LW = 1.3
"""Line width of a model's prediction (wider than the measured trace on top of it)."""
RESIDUAL_LW = 0.7
"""Line width of a residual trace."""
LEGEND_FONTSIZE = 8
"""Font size of legends."""
LEGEND_WIDTH_IN = 2.3
"""Right margin [inch] a figure keeps for legends outside its axes."""

DIMENSIONLESS = "1"
"""Unit text of a dimensionless quantity (a correlation coefficient, a share)."""


def measured(label: str | None = "measured") -> dict[str, Any]:
    """Line keywords of measured data (black, thin, on top)."""
    return {"color": MEASURED, "lw": MEASURED_LW, "zorder": 3, "label": label}


def before(label: str | None = "before") -> dict[str, Any]:
    """Line keywords of the model before identification (orange, under the measured trace)."""
    return {"color": BEFORE, "lw": MODEL_LW, "zorder": 2, "label": label}


def after(label: str | None = "after") -> dict[str, Any]:
    """Line keywords of the model after identification (blue, over ``before``)."""
    return {"color": AFTER, "lw": MODEL_LW, "zorder": 2.5, "label": label}


def residual(which: str, label: str | None = None) -> dict[str, Any]:
    """Line keywords of a residual trace: ``which`` is ``before`` or ``after`` (the smaller
    residual of the final model is drawn over the baseline's)."""
    if which not in ("before", "after"):
        raise ValueError(f"which: expected before or after, got {which!r}")
    return {"color": BEFORE if which == "before" else AFTER, "lw": RESIDUAL_LW,
            "zorder": 2 if which == "before" else 2.5, "label": label}


def legend_outside(ax: Any, **kw: Any) -> Any:
    """A legend to the right of ``ax``, outside the data area (keep
    :data:`LEGEND_WIDTH_IN` of right margin); extra keywords go to ``ax.legend``."""
    opts: dict[str, Any] = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0),
                            "borderaxespad": 0.0, "fontsize": LEGEND_FONTSIZE,
                            "frameon": False}
    opts.update(kw)
    return ax.legend(**opts)


def label(quantity: str, unit: str) -> str:
    """Axis label ``quantity [unit]``; an empty unit is written ``[unit not given]`` (a
    description without units), never left out."""
    return f"{quantity} [{unit.strip() or 'unit not given'}]"


def psd_unit(unit: str) -> str:
    """Unit of a power spectral density of a signal in ``unit``: ``(rad/s)²/Hz``."""
    u = unit.strip()
    if not u:
        return "(unit not given)²/Hz"
    return f"({u})²/Hz" if any(c in u for c in " /*·^") else f"{u}²/Hz"


def per_input_unit(unit: str, input_unit: str = "") -> str:
    """Unit of a response to a unit input: ``rad/s per A`` (``per unit input`` when the input's
    unit is not known)."""
    u = unit.strip() or "unit not given"
    return f"{u} per {input_unit.strip()}" if input_unit.strip() else f"{u} per unit input"


def rate_text(dt: float) -> str:
    """Sample rate of a sample period [s] in plain words: ``1 kHz``, ``62.5 Hz``."""
    if not (math.isfinite(dt) and dt > 0):
        return "unknown rate"
    hz = 1.0 / dt
    return f"{hz / 1000:.4g} kHz" if hz >= 1000 else f"{hz:.4g} Hz"


def lag_label(dt: float | None) -> str:
    """Label of a lag axis in samples with the sample period and rate:
    ``lag [samples; 1 sample = 1 ms at 1 kHz]``."""
    if dt is None or not (math.isfinite(dt) and dt > 0):
        return "lag [samples; sample rate not known]"
    step = f"{1e3 * dt:.4g} ms" if dt < 1.0 else f"{dt:.4g} s"
    return f"lag [samples; 1 sample = {step} at {rate_text(dt)}]"
