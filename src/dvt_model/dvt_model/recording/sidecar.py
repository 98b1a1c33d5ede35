"""The YAML files of a recording: one reader (and writer) for each (pure).

* ``metadata.yaml``: rosbag2's description of the bag (:func:`read_metadata`; :func:`is_bag`
  says whether a directory is a finished bag);
* ``truth.yaml``: the simulated plant's hidden truth, beside a recording or in
  ``dvt-launch``'s log directory (:func:`read_truth`, :func:`parse_truth` for the text the plant
  produces, :func:`write_truth`; :func:`changes_applied` lists the changes the plant applied);
* ``run.yaml``: how ``dvt-launch`` made the run (:func:`read_run_info`, :func:`write_run_info`).

Every error is a :class:`~dvt_model.errors.BagError` naming the file and what is wrong with it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from dvt_model.errors import BagError
from dvt_model.presets import safe_load
from dvt_model.recording.layout import METADATA_FILE, RUN_FILE, TRUTH_FILE

__all__ = [
    "changes_applied",
    "is_bag",
    "parse_truth",
    "read_metadata",
    "read_run_info",
    "read_truth",
    "write_run_info",
    "write_truth",
]


def _mapping(text: str, source: str | Path) -> dict[str, Any]:
    """The top-level mapping of YAML ``text`` (empty text: ``{}``); ``source`` names it in
    errors."""
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        raise BagError(f"{source}: invalid YAML: {exc}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BagError(f"{source}: expected a mapping at top level, got {type(data).__name__}")
    return data


def _read(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise BagError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    return _mapping(text, path)


def _write(f: Path, data: Mapping[str, Any]) -> Path:
    f.write_text(yaml.safe_dump(dict(data), sort_keys=False), encoding="utf-8")
    return f


def _read_optional(f: Path) -> dict[str, Any] | None:
    """The mapping in file ``f``, ``None`` if there is no such file."""
    return _read(f) if f.exists() else None


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` is a bag directory its writer finished (it holds ``metadata.yaml``)."""
    p = Path(path)
    return p.is_dir() and (p / METADATA_FILE).is_file()


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of bag directory ``path``'s
    ``metadata.yaml`` (storage identifier, file paths, topics, compression, ...).

    Raises:
        BagError: no ``metadata.yaml``, unreadable, invalid YAML, or no
            ``rosbag2_bagfile_information`` mapping in it.
    """
    f = Path(path) / METADATA_FILE
    if not f.is_file():
        raise BagError(f"{path}: not a finished bag directory: {METADATA_FILE} is missing")
    info = _read(f).get("rosbag2_bagfile_information")
    if not isinstance(info, dict):
        raise BagError(f"{f}: no 'rosbag2_bagfile_information' mapping")
    return info


def parse_truth(text: str, source: str | Path = "truth.yaml") -> dict[str, Any]:
    """The mapping of ``truth.yaml`` text (as :meth:`PlantSim.truth_yaml` produces it);
    ``source`` names it in errors.

    Raises:
        BagError: invalid YAML or not a mapping.
    """
    return _mapping(text, source)


def read_truth(path: str | Path) -> dict[str, Any] | None:
    """The ``truth.yaml`` in directory ``path`` (a simulated recording, or ``dvt-launch``'s log
    directory where the plant writes it), or ``None`` if there is none.

    Raises:
        BagError: the file is unreadable, invalid YAML or not a mapping.
    """
    return _read_optional(Path(path) / TRUTH_FILE)


def write_truth(path: str | Path, truth: Mapping[str, Any]) -> Path:
    """Write ``truth`` as ``truth.yaml`` into directory ``path``; returns the file."""
    return _write(Path(path) / TRUTH_FILE, truth)


def changes_applied(truth: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    """The changes the plant applied, in order (``changes_applied`` of a truth mapping: each
    ``{"at_s": plant time [s], "unix_s": host time [s] (from dvt-plant), "change": ...}``);
    ``[]`` without a truth or a change.

    Raises:
        BagError: ``changes_applied`` is not a list of mappings.
    """
    if truth is None:
        return []
    applied = truth.get("changes_applied") or []
    if not isinstance(applied, list) or not all(isinstance(a, dict) for a in applied):
        raise BagError(f"truth.yaml: changes_applied: expected a list of mappings, got "
                       f"{applied!r}")
    return list(applied)


def read_run_info(path: str | Path) -> dict[str, Any] | None:
    """The ``run.yaml`` in directory ``path`` (how ``dvt-launch`` made the recording), or
    ``None`` if there is none.

    Raises:
        BagError: the file is unreadable, invalid YAML or not a mapping.
    """
    return _read_optional(Path(path) / RUN_FILE)


def write_run_info(path: str | Path, info: Mapping[str, Any]) -> Path:
    """Write ``info`` as ``run.yaml`` into directory ``path``; returns the file."""
    return _write(Path(path) / RUN_FILE, info)
