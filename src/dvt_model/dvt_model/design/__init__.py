"""The transmission's design recomputed and checked (thesis ch. 1-3): ``dvt-model design``.

Pure core (no rclpy): :func:`load_design` reads a design file (the thesis's design is bundled),
:func:`design_report` recomputes the requirement, the gear train, shafts, bearings and splines
and runs the checks.
"""

from dvt_model.design.report import design_report, format_report, write_plots
from dvt_model.design.spec import Design, load_design, parse_design

__all__ = ["Design", "design_report", "format_report", "load_design", "parse_design",
           "write_plots"]
