"""The packages build and test with colcon, as a lab with a ROS install would use them."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).parent / "colcon"


@pytest.mark.slow
def test_colcon_build_and_test(tmp_path):
    if not COLCON.exists():
        pytest.fail(f"{COLCON} not found: requirements-dev.txt pins colcon-common-extensions "
                    "(scripts/bootstrap.sh --dev installs it)")
    shutil.copytree(ROOT / "src", tmp_path / "src",
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    shutil.copy(ROOT / "colcon.meta", tmp_path / "colcon.meta")
    run = subprocess.run([str(COLCON), "--log-base", "log", "build", "--base-paths", "src"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    for pkg, exe in (("dvt_model", "dvt_model_node"), ("dvt_driver", "dvt_driver_node"),
                     ("dvt_identify", "dvt-identify")):
        assert (tmp_path / "install" / pkg / "lib" / pkg / exe).exists()
    share = tmp_path / "install" / "dvt_model" / "share" / "ament_index" / "resource_index"
    assert (share / "packages" / "dvt_model").exists()
    # build order from colcon.meta / package.xml: dvt_model (the base) before the two others,
    # which depend on it only
    order = [line.split()[-1] for line in run.stdout.splitlines() if line.startswith("Starting")]
    assert order.index("dvt_model") < order.index("dvt_driver")
    assert order.index("dvt_model") < order.index("dvt_identify")
    test = subprocess.run([str(COLCON), "--log-base", "log", "test", "--packages-select",
                           "dvt_model", "--return-code-on-test-failure"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert test.returncode == 0, test.stdout[-3000:] + test.stderr[-3000:]
