"""``dvt-replay BAG [--rate X]``: publish a recorded bag's contract topics with their stamps.

The raw CDR of each message is published unchanged, so every ``header.stamp`` is the original
one and the model node (or the identifier) sees exactly what was recorded. Messages are paced
by their log times divided by ``--rate`` (``--rate 0``: as fast as possible).

Usage::

    dvt-replay BAG [--rate 1.0] [--topics /dvt/joint_states /dvt/currents]
               [--wait-subscribers 1] [--wait-timeout 10] [--ros-args ...]
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from rosbags.rosbag2 import Reader

from dvt_model import rosutil
from dvt_model.contract import SAMPLE_TOPICS

DEFAULT_TOPICS = SAMPLE_TOPICS
"""The contract's two topics of one controller sample."""


def _msg_class(msgtype: str) -> Any:
    pkg, _, name = msgtype.split("/")
    module = __import__(f"{pkg}.msg", fromlist=[name])
    return getattr(module, name)


def main(argv: list[str] | None = None) -> int:
    args_in = sys.argv[1:] if argv is None else argv
    rosutil.init(["dvt-replay", *args_in])
    plain = rclpy.utilities.remove_ros_args(["dvt-replay", *args_in])[1:]
    parser = argparse.ArgumentParser(prog="dvt-replay", description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--rate", type=float, default=1.0,
                        help="playback speed factor; 0 publishes as fast as possible")
    parser.add_argument("--topics", nargs="+", default=list(DEFAULT_TOPICS))
    parser.add_argument("--wait-subscribers", type=int, default=0,
                        help="wait until each topic has this many subscribers")
    parser.add_argument("--wait-timeout", type=float, default=10.0)
    parser.add_argument("--start-delay", type=float, default=0.0,
                        help="seconds to wait after discovery before the first message")
    args = parser.parse_args(plain)
    if args.rate < 0.0:
        print(f"dvt-replay: --rate: expected >= 0, got {args.rate}", file=sys.stderr)
        return 2
    stop = {"flag": False}
    signal.signal(signal.SIGINT, lambda *_: stop.update(flag=True))
    signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    try:
        reader = Reader(args.bag)
        reader.open()
    except Exception as exc:  # rosbags raises several types; all mean "cannot read"
        print(f"dvt-replay: {args.bag}: cannot open bag: {exc}", file=sys.stderr)
        return 2
    node = rclpy.create_node("dvt_replay")
    try:
        conns = [c for c in reader.connections if c.topic in args.topics]
        missing = sorted(set(args.topics) - {c.topic for c in conns})
        if missing:
            print(f"dvt-replay: {args.bag}: topic(s) {missing} not in bag", file=sys.stderr)
            return 2
        pubs = {}
        for c in conns:
            qos = rosutil.SENSOR_QOS if c.topic in DEFAULT_TOPICS else 10
            pubs[c.topic] = node.create_publisher(_msg_class(c.msgtype), c.topic, qos)
        deadline = time.monotonic() + args.wait_timeout
        while args.wait_subscribers > 0 and not stop["flag"]:
            if all(p.get_subscription_count() >= args.wait_subscribers for p in pubs.values()):
                break
            if time.monotonic() > deadline:
                print(f"dvt-replay: no subscribers after {args.wait_timeout} s",
                      file=sys.stderr)
                return 3
            time.sleep(0.02)
        time.sleep(args.start_delay)
        sent = 0
        t0_wall = time.monotonic()
        t0_log: int | None = None
        for conn, log_ns, raw in reader.messages(connections=conns):
            if stop["flag"]:
                break
            if t0_log is None:
                t0_log = log_ns
            if args.rate > 0.0:
                due = t0_wall + (log_ns - t0_log) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
            pubs[conn.topic].publish(bytes(raw))
            sent += 1
        print(f"dvt-replay: published {sent} messages from {args.bag}", file=sys.stderr)
        time.sleep(0.2)  # let the last best-effort samples leave
        return 0
    finally:
        reader.close()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
