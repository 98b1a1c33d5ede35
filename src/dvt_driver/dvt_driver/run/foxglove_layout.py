"""The Foxglove layout shipped as ``docs/foxglove/dvt-layout.json`` (:func:`build_layout`), and
the topics a layout names (:func:`layout_topics`): the bridge's channels
(:mod:`dvt_driver.run.foxglove_core`) are what the panels plot. Pure; no rclpy.

Regenerate the shipped file with ``python -c 'from dvt_driver.run.foxglove_layout import
layout_json; print(layout_json(), end="")' > docs/foxglove/dvt-layout.json``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

from dvt_driver.run.foxglove_core import ALARMS, IDENTIFY, RESIDUAL_BAND, STATE
from dvt_model.contract import (
    BRAKE_NAMES,
    CMD_GEAR,
    CURRENT_NAMES,
    CURRENTS,
    DIAGNOSTICS,
    JOINT_STATES,
    MODEL_JOINT_STATES,
    MODEL_RESIDUAL,
    SPEED_NAMES,
)

# ---------------------------------------------------------------------------------- layout
_SERIES_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def _series(value: str, label: str, color: str, **extra: Any) -> dict[str, Any]:
    return {"value": value, "enabled": True, "timestampMethod": "receiveTime", "label": label,
            "color": color, **extra}


def _plot(title: str, paths: list[dict[str, Any]], y_label: str) -> dict[str, Any]:
    return {"foxglovePanelTitle": title, "paths": paths, "showLegend": True,
            "legendDisplay": "floating", "showPlotValuesInLegend": True, "isSynced": True,
            "xAxisVal": "timestamp", "timeWindowMode": "sliding", "followingViewWidth": 20,
            "yAxisLabel": y_label, "showXAxisLabels": True, "showYAxisLabels": True}


def build_layout() -> dict[str, Any]:
    """The Foxglove layout shipped as ``docs/foxglove/dvt-layout.json`` (Foxglove's
    "Import layout" file format: ``configById`` + a mosaic ``layout`` tree).

    Panels: measured vs predicted speeds, residual with its noise band, currents, gear/band
    timeline, diagnostics summary, alarms and the identifier's result. Every series names a
    channel of :data:`~dvt_driver.run.foxglove_core.CHANNELS` by a ROS-style message path, so
    the panels on ROS topics work on a recorded bag as well.
    """
    c = _SERIES_COLORS
    speeds: list[dict[str, Any]] = []
    residual: list[dict[str, Any]] = []
    for i, name in enumerate(SPEED_NAMES):
        speeds.append(_series(f"{JOINT_STATES}.velocity[{i}]", f"{name} measured", c[2 * i]))
        speeds.append(_series(f"{MODEL_JOINT_STATES}.velocity[{i}]", f"{name} predicted",
                              c[2 * i + 1], lineStyle="dashed"))
        residual.append(_series(f"{MODEL_RESIDUAL}.velocity[{i}]", f"{name} residual", c[2 * i]))
        for edge in ("lower", "upper"):
            residual.append(_series(f"{RESIDUAL_BAND}.{edge}[{i}]", f"{name} band {edge}",
                                    c[2 * i], lineStyle="dotted", lineSize=1))
    currents = [_series(f"{CURRENTS}.effort[{i}]", name, c[i])
                for i, name in enumerate(CURRENT_NAMES)]
    angles = [_series(f"{JOINT_STATES}.position[{i}]", f"{name} angle", c[2 * i])
              for i, name in enumerate(SPEED_NAMES)]
    gear_paths = [
        {"value": f"{STATE}.gear", "label": "gear (driver)", "timestampMethod": "receiveTime"},
        {"value": f"{CMD_GEAR}.data", "label": "gear (commanded)",
         "timestampMethod": "receiveTime"},
        {"value": f"{STATE}.shifting", "label": "shifting", "timestampMethod": "receiveTime"},
        *({"value": f"{STATE}.bands_engaged[{i}]", "label": f"{name} engaged",
           "timestampMethod": "receiveTime"} for i, name in enumerate(BRAKE_NAMES)),
    ]
    config: dict[str, Any] = {
        "Plot!speeds": _plot("Speeds: measured vs predicted", speeds, "rad/s"),
        "Plot!residual": _plot("Residual and noise band", residual, "rad/s"),
        "Plot!currents": _plot("Currents", currents, "A"),
        "Plot!angles": _plot("Angles (when the driver sends them)", angles, "rad"),
        "StateTransitions!gear": {"foxglovePanelTitle": "Gear and bands", "paths": gear_paths,
                                  "isSynced": True, "showPoints": True},
        "DiagnosticSummary!diag": {"foxglovePanelTitle": "Diagnostics", "minLevel": 0,
                                   "pinnedIds": [], "hardwareIdFilter": "",
                                   "topicToRender": DIAGNOSTICS, "sortByLevel": True},
        "RosOut!alarms": {"foxglovePanelTitle": "Alarms", "searchTerms": [], "minLogLevel": 2,
                          "topicToRender": ALARMS},
        "RawMessages!identify": {"foxglovePanelTitle": "Identifier result",
                                 "topicPath": IDENTIFY, "diffEnabled": False,
                                 "diffMethod": "custom", "diffTopicPath": "",
                                 "showFullMessageForDiff": False, "expansion": "all"},
    }
    # the gear timeline gets almost 40 % of the height: its six rows (gear, commanded gear,
    # shifting, three bands) take about 55 px each
    left = {"first": "Plot!speeds", "second": {
        "first": "Plot!residual", "second": {
            "first": "Plot!currents", "second": "StateTransitions!gear", "direction": "column",
            "splitPercentage": 30},
        "direction": "column", "splitPercentage": 28},
        "direction": "column", "splitPercentage": 25}
    right = {"first": "DiagnosticSummary!diag", "second": {
        "first": "Plot!angles", "second": {
            "first": "RosOut!alarms", "second": "RawMessages!identify", "direction": "column",
            "splitPercentage": 40},
        "direction": "column", "splitPercentage": 40},
        "direction": "column", "splitPercentage": 30}
    return {"configById": config, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1},
            "layout": {"first": left, "second": right, "direction": "row",
                       "splitPercentage": 70}}


def layout_json() -> str:
    """The shipped layout's file text (stable: sorted keys, 2-space indent, final newline)."""
    return json.dumps(build_layout(), indent=2, sort_keys=True) + "\n"


_TOPIC = re.compile(r"^(/[A-Za-z0-9_/]*[A-Za-z0-9_])")
_PATH_KEYS = ("value", "topicPath", "topicToRender", "diffTopicPath")


def layout_topics(layout: Mapping[str, Any]) -> set[str]:
    """Every topic a layout's panels name (message paths, topics to render).

    Raises:
        ValueError: the layout has no ``configById`` or no ``layout`` tree.
    """
    config = layout.get("configById")
    if not isinstance(config, Mapping) or "layout" not in layout:
        raise ValueError("not a Foxglove layout: expected 'configById' and 'layout'")
    panels = _panel_ids(layout["layout"])
    missing = sorted(panels - set(config))
    if missing:
        raise ValueError(f"layout tree names panels without a config: {missing}")
    topics: set[str] = set()

    def walk(node: Any) -> None:
        if isinstance(node, Mapping):
            for k, v in node.items():
                if k in _PATH_KEYS and isinstance(v, str) and v:
                    m = _TOPIC.match(v)
                    if m is None:
                        raise ValueError(f"layout: {k}={v!r} is not a topic or message path")
                    topics.add(m.group(1))
                else:
                    walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(config)
    return topics


def _panel_ids(tree: Any) -> set[str]:
    if isinstance(tree, str):
        return {tree}
    if isinstance(tree, Mapping) and "first" in tree and "second" in tree:
        return _panel_ids(tree["first"]) | _panel_ids(tree["second"])
    raise ValueError(f"layout tree: expected a panel id or a split, got {tree!r}"[:200])
