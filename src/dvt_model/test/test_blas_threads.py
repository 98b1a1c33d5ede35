"""BLAS runs on one thread in every process that imports a dvt package, whatever was imported
first (``dvt_model.one_blas_thread``), and a user's own setting wins.

Why it matters: with numpy loaded before the packages (a test runner, ``sensor_msgs``), BLAS
used to start two threads, and two threads' last bits moved identifications to other local
optima (``docs/identification.md``, Tests). Each case runs in a fresh interpreter: what a
process loaded first is the point.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from dvt_model import BLAS_THREAD_VARIABLES

CHILD = """
import json, sys
{first}
import {package}
import numpy
from threadpoolctl import threadpool_info
print(json.dumps([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]))
"""


def _blas_threads(first: str, package: str, env: dict[str, str]) -> list[int]:
    base = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", CHILD.format(first=first, package=package)],
                         capture_output=True, text=True, timeout=120, env={**base, **env},
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("package", ["dvt_model", "dvt_driver", "dvt_identify"])
@pytest.mark.parametrize("first", ["", "import numpy", "import numpy, scipy.linalg"])
def test_blas_holds_one_thread_whatever_came_first(first: str, package: str) -> None:
    threads = _blas_threads(first, package, {})
    assert threads and all(n == 1 for n in threads), (first, package, threads)


def test_the_users_own_thread_count_wins() -> None:
    """``OPENBLAS_NUM_THREADS`` set by the user is kept, with numpy loaded first or not (this
    machine has 2 cores: 2 threads are what OpenBLAS would start anyway, so the case also
    shows the limit is not applied blindly)."""
    for first in ("", "import numpy"):
        assert _blas_threads(first, "dvt_identify", {"OPENBLAS_NUM_THREADS": "2"}) == [2]
