"""The suite's own guard: nothing a test starts outlives it (``conftest.ros_env``).

The guard finds a test's processes by the ``DVT_TEST_ID`` tag in their environment, so it finds
a grandchild whose parent died before it (re-parented, outside every process group the test
knows) as well as a direct child.
"""

from __future__ import annotations

import os
import subprocess
import time

from conftest import TAG, kill_tagged, tagged, wait_for


def test_a_tagged_child_and_an_orphaned_grandchild_are_found_and_killed():
    tag = f"hygiene-{os.getpid()}-{time.monotonic_ns()}"
    env = {**os.environ, TAG: tag}
    child = subprocess.Popen(["sleep", "60"], env=env)
    # the shell starts a sleep in the background and exits: the sleep is re-parented
    subprocess.run(["bash", "-c", "sleep 61 & disown"], env=env, check=True)
    try:
        # until both sleeps run (the shell's background child shows the shell's command line
        # until it has exec'd sleep: a loaded machine showed it)
        wait_for(lambda: sorted(c for _, c in tagged(tag)) == ["sleep 60", "sleep 61"], 5.0,
                 "both sleeps, found by their tag")
        killed = kill_tagged(tag)
        assert len(killed) == 2, killed
        assert tagged(tag) == []
        child.wait(timeout=5)
        assert child.returncode == -9
    finally:
        kill_tagged(tag)


def test_an_untagged_process_is_left_alone():
    other = subprocess.Popen(["sleep", "60"])
    try:
        assert kill_tagged(f"nobody-{os.getpid()}") == []
        assert other.poll() is None
    finally:
        other.kill()
        other.wait()
