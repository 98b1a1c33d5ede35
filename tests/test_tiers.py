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
import re
import subprocess
import sys
from pathlib import Path

from conftest import ROOT

_PROBE = '''
import json, os

def pytest_collection_finish(session):
    with open(os.environ["DVT_TIER_PROBE_OUT"], "w") as f:
        json.dump([[item.nodeid, sorted(item.fixturenames),
                    sorted(m.name for m in item.iter_markers())] for item in session.items], f)
'''


def test_every_test_using_the_ros_fixtures_is_marked_ros(tmp_path: Path) -> None:
    (tmp_path / "dvt_tier_probe.py").write_text(_PROBE)
    out = tmp_path / "items.json"
    env = {**os.environ, "DVT_TIER_PROBE_OUT": str(out),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-m", "pytest", "tests", "--collect-only", "-q",
                        "-p", "dvt_tier_probe", "-p", "no:cacheprovider"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
                       check=False)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    items = json.loads(out.read_text())
    assert len(items) > 50, r.stdout[-2000:]
    chains = [(nodeid, markers) for nodeid, fixtures, markers in items if "ros_env" in fixtures]
    assert len(chains) > 20  # the topic-level tests are found by their fixtures
    unmarked = [nodeid for nodeid, markers in chains if "ros" not in markers]
    assert not unmarked, f"topic-level tests without the 'ros' marker: {unmarked}"


MAX_RERUN_MARKS = 2
RERUN_ALLOWED = {"tests/test_foxglove_topics.py"}
"""Files whose one test may rerun: timing only (message rates through a bridge on a loaded
machine), no statistical or safety assertion."""


def test_rerun_on_failure_is_rare_and_timing_only() -> None:
    marks = []
    for path in sorted([*ROOT.glob("tests/*.py"), *ROOT.glob("src/*/test/*.py")]):
        text = path.read_text()
        rel = path.relative_to(ROOT).as_posix()
        marks += [rel for _ in re.finditer(r"^\s*@pytest\.mark\.flaky\b|^pytestmark.*flaky",
                                           text, re.MULTILINE)]
    assert len(marks) <= MAX_RERUN_MARKS, marks
    assert set(marks) <= RERUN_ALLOWED, marks
    assert "--reruns" not in (ROOT / "pyproject.toml").read_text()
