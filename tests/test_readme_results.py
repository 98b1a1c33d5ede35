"""Figures with provenance: the README's results table is exactly what ``scripts/results.py
table`` renders from ``docs/results/*.json``, and each of those files names the command, the
commit and the date that produced its figures."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

from script_module import load

ROOT = Path(__file__).resolve().parents[1]


def _results() -> ModuleType:
    return load("results")


def test_the_readme_table_is_rendered_from_the_result_files() -> None:
    res = _results()
    text = (ROOT / "README.md").read_text()
    block = text.split(res.BEGIN, 1)[1].split(res.END, 1)[0].strip()
    assert block == res.table(), "run scripts/results.sh table (or the named command)"


def test_every_result_file_names_its_command_commit_and_date() -> None:
    files = sorted((ROOT / "docs" / "results").glob("*.json"))
    assert files
    for path in files:
        doc = json.loads(path.read_text())
        for key in ("name", "command", "commit", "date", "machine", "figures"):
            assert doc.get(key), f"{path}: no {key}"
        assert doc["name"] == path.stem, path


def test_the_readme_stays_short() -> None:
    assert (ROOT / "README.md").stat().st_size <= 15_000
