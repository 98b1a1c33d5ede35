"""Topic level: ``dvt-launch --supervise`` takes the identifier's episodes from the contract's
topic (:data:`dvt_model.contract.IDENTIFY_EPISODE`), not from the identifier's files.

A real rclpy node named like the identifier publishes episode records with the contract's QoS
(one before the launcher's monitor exists: a late subscriber still gets it, one after, and one
message that is not a record); the launcher's :class:`~dvt_driver.system.monitor.Monitor` and
its supervision loop must print both records in order, warn about the bad message (and not
stop), and end the run at ``--episodes 2``. The records name report directories that do not
exist: nothing is read from disk.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import pytest

from conftest import wait_for
from dvt_driver.system.launch import _Supervision
from dvt_driver.system.monitor import Monitor
from dvt_model import rosutil
from dvt_model.contract import CHANGE_QOS, IDENTIFY_EPISODE, IDENTIFY_NODE

pytestmark = pytest.mark.ros


def _record(n: int, outcome: str) -> str:
    return json.dumps({"episode": n, "outcome": outcome, "reason": "test", "change_s": 10.0 * n,
                       "detected_s": 10.0 * n + 0.5, "outputs": ["sun_shaft"], "pushed": True,
                       "push_s": 10.0 * n + 5.0, "rolled_back": outcome == "rolled_back",
                       "directory": f"/nonexistent/identify/episodes/episode-{n}"})


def test_the_launcher_reads_episodes_from_the_contract_topic(rclpy_context: Any) -> None:
    import rclpy
    from std_msgs.msg import String

    node = rclpy.create_node(IDENTIFY_NODE, context=rclpy_context)
    pub = node.create_publisher(String, IDENTIFY_EPISODE, rosutil.qos(CHANGE_QOS))
    pub.publish(String(data=_record(1, "confirmed")))  # before the launcher subscribes
    lines: list[str] = []
    monitor = Monitor(episodes=True)
    try:
        wait_for(lambda: monitor.published(IDENTIFY_NODE, IDENTIFY_EPISODE), 20.0,
                 "the monitor to see the identifier's episode publisher")
        loop = _Supervision(argparse.Namespace(episodes=2), monitor, lines.append)
        wait_for(lambda: loop.count == 1 or loop.poll(), 20.0, "the latched first record")
        assert not loop.poll()  # one of two
        pub.publish(String(data="[not, a, record"))
        pub.publish(String(data=_record(2, "rolled_back")))
        wait_for(loop.poll, 20.0, "the second record")
    finally:
        monitor.close()
        node.destroy_node()
    assert loop.count == 2
    episodes = [ln for ln in lines if ln.startswith("episode ")]
    assert episodes[0].startswith("episode 1: confirmed (test); change at 10.000 s, detected at "
                                  "10.500 s on sun_shaft; pushed True at 15.000 s")
    assert episodes[0].endswith("(report /nonexistent/identify/episodes/episode-1)")
    assert episodes[1].startswith("episode 2: rolled_back (test)")
    assert any(ln.startswith(f"warning: {IDENTIFY_EPISODE}: a message that is not an episode "
                             "record: not JSON") for ln in lines), lines
    assert lines[-1] == "2 episode report(s): --episodes 2 done"
