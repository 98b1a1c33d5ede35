"""A script of ``scripts/`` loaded as a module, for tests of its pure functions (the scripts
are commands, not a package)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load(name: str) -> ModuleType:
    """``scripts/<name>.py`` as a module named ``name``.

    Raises:
        ImportError: no such script (the path is named).
    """
    path = ROOT / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None or not path.is_file():
        raise ImportError(f"{path}: no script to load")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
