"""Identification report: ``report.json`` (the data, :mod:`.data`), ``report.md``
(:mod:`.markdown`) and the PNG plots (:mod:`.plots`); :func:`write_report` writes all three.

The names below are the report's public interface (and the ones the tests use).
"""

from __future__ import annotations

from dvt_identify.report.data import (
    MAX_RELATIVE_STD,
    PEAK_RATIO,
    STRUCTURED_SHARE,
    at_bounds,
    build_report,
    build_warnings,
    multistart_summary,
    ranked_effects,
    relative_std,
    remaining_summary,
    residual_floors,
    stage_dict,
    suspect,
    time_clock_warnings,
)
from dvt_identify.report.markdown import _lr_cell, build_markdown, write_report
from dvt_identify.report.plots import (
    _log_label,
    envelope,
    plot_candidates,
    plot_fits,
    plot_linear,
    plot_residuals,
    plot_spectrum,
)

__all__ = [
    "MAX_RELATIVE_STD", "PEAK_RATIO", "STRUCTURED_SHARE", "_log_label", "_lr_cell",
    "at_bounds", "build_markdown", "build_report", "build_warnings", "envelope",
    "multistart_summary", "plot_candidates", "plot_fits", "plot_linear", "plot_residuals",
    "plot_spectrum", "ranked_effects", "relative_std", "remaining_summary", "residual_floors",
    "stage_dict", "suspect", "time_clock_warnings", "write_report",
]
