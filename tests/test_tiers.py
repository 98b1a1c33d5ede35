"""The test tiers and the rerun budget.

``scripts/test.sh --fast`` deselects the topic-level tests by their ``ros`` marker, so every
test that starts real ROS processes or joins a ROS graph must carry it. A topic-level test is
one whose fixtures include ``ros_env`` (through ``procs``, ``rclpy_context`` or a fixture of
its own built on them): pytest's own fixture closure of every test in ``tests/`` is read from a
collection run, not guessed from the source.

Rerun on failure (``pytest.mark.flaky``, pytest-rerunfailures) is for timing-only topic-level
tests, at most two in the suite; a statistical or safety assertion never reruns.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT

_PROBE = '''
import json, os

def pytest_collection_finish(session):
    with open(os.environ["DVT_TIER_PROBE_OUT"], "w") as f:
        json.dump([[item.nodeid, sorted(item.fixturenames),
                    sorted(m.name for m in item.iter_markers())] for item in session.items], f)
'''


TEST_PATHS = ("src/dvt_model/test", "src/dvt_driver/test", "src/dvt_identify/test", "tests")
"""What ``scripts/test.sh`` runs."""


@pytest.fixture(scope="module")
def collected(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, list[str], list[str]]]:
    """Every test of :data:`TEST_PATHS` as pytest collects it: node id, fixture closure and
    marker names (pytest's own view: marks set in lists, params or conftest hooks included)."""
    tmp = tmp_path_factory.mktemp("probe")
    (tmp / "dvt_tier_probe.py").write_text(_PROBE)
    out = tmp / "items.json"
    env = {**os.environ, "DVT_TIER_PROBE_OUT": str(out),
           "PYTHONPATH": os.pathsep.join([str(tmp), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-m", "pytest", *TEST_PATHS, "--collect-only", "-q",
                        "-p", "dvt_tier_probe", "-p", "no:cacheprovider"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
                       check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    items = [(str(n), list(f), list(m)) for n, f, m in json.loads(out.read_text())]
    assert len(items) > 1000, r.stdout[-2000:]
    return items


def test_every_test_using_the_ros_fixtures_is_marked_ros(
        collected: list[tuple[str, list[str], list[str]]]) -> None:
    items = [i for i in collected if i[0].startswith("tests/")]
    assert len(items) > 50
    chains = [(nodeid, markers) for nodeid, fixtures, markers in items if "ros_env" in fixtures]
    assert len(chains) > 20  # the topic-level tests are found by their fixtures
    unmarked = [nodeid for nodeid, markers in chains if "ros" not in markers]
    assert not unmarked, f"topic-level tests without the 'ros' marker: {unmarked}"


MAX_RERUN_MARKS = 2
RERUN_ALLOWED = {"tests/test_foxglove_topics.py::test_foxglove_bridge_live_rate"}
"""Tests that may rerun: timing only (message rates through a bridge on a loaded machine), no
statistical or safety assertion."""
RERUN_CONFIG = ("pyproject.toml", "tests/conftest.py", "src/dvt_identify/test/conftest.py",
                "scripts/test.sh", ".ci/run", "pytest.ini", "setup.cfg", "tox.ini")
"""Files where a suite-wide ``--reruns`` could hide."""


def test_rerun_on_failure_is_rare_and_timing_only(
        collected: list[tuple[str, list[str], list[str]]]) -> None:
    marks = [nodeid for nodeid, _, markers in collected if "flaky" in markers]
    assert len(marks) <= MAX_RERUN_MARKS, marks
    assert set(marks) <= RERUN_ALLOWED, marks
    for name in RERUN_CONFIG:
        path = ROOT / name
        if path.is_file():
            assert "reruns" not in path.read_text(), f"{name}: a suite-wide rerun"
