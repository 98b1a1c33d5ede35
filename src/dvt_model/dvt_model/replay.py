"""``dvt-replay BAG [--rate X]``: publish a recorded bag's contract topics with their stamps.

The raw CDR of each message is published unchanged, so every ``header.stamp`` is the original
one and the model node (or the identifier) sees exactly what was recorded. Messages are paced
by their log times divided by ``--rate`` (``--rate 0``: as fast as possible). The
``/dvt/joint_states`` messages carry the recorded ``position`` (encoder angles) when the bag has
them, so the model node anchors its angles to the measured ones as it does live.

``--start S`` skips the first ``S`` seconds of the bag (log time from its first message) and
``--duration S`` stops after ``S`` seconds of it: a slice of a long recording, e.g. one phase
of a validation run.

Usage::

    dvt-replay BAG [--rate 1.0] [--topics /dvt/joint_states /dvt/currents]
               [--start 0] [--duration 0] [--wait-subscribers 1] [--wait-timeout 10]
               [--ros-args ...]
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

import rclpy

from dvt_model import rosutil
from dvt_model.contract import SAMPLE_TOPICS
from dvt_model.errors import BagError
from dvt_model.recording import BagMessages

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
    parser.add_argument("--start", type=float, default=0.0,
                        help="skip this many seconds of the bag (log time) [s]")
    parser.add_argument("--duration", type=float, default=0.0,
                        help="publish this many seconds of the bag from --start; 0: to its end")
    args = parser.parse_args(plain)
    for name in ("rate", "start", "duration"):
        value = getattr(args, name)
        if not (value >= 0.0 and value < float("inf")):
            print(f"dvt-replay: --{name}: expected a finite value >= 0, got {value}",
                  file=sys.stderr)
            return 2
    stop = {"flag": False}
    signal.signal(signal.SIGINT, lambda *_: stop.update(flag=True))
    signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    try:
        bag = BagMessages(args.bag)
    except BagError as exc:
        print(f"dvt-replay: cannot open bag: {exc}", file=sys.stderr)
        return 2
    node = rclpy.create_node("dvt_replay")
    try:
        types = bag.types
        missing = sorted(set(args.topics) - set(types))
        if missing:
            print(f"dvt-replay: {args.bag}: topic(s) {missing} not in bag", file=sys.stderr)
            return 2
        pubs = {}
        for topic in dict.fromkeys(args.topics):
            qos = rosutil.SENSOR_QOS if topic in DEFAULT_TOPICS else 10
            pubs[topic] = node.create_publisher(_msg_class(types[topic]), topic, qos)
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
        skip_ns = round(args.start * 1e9)
        stop_ns = round((args.start + args.duration) * 1e9) if args.duration > 0.0 else None
        first: int | None = None
        for msg in bag.messages(pubs):
            log_ns = msg.log_time_ns
            if stop["flag"]:
                break
            if first is None:
                first = log_ns
            if log_ns - first < skip_ns:
                continue
            if stop_ns is not None and log_ns - first >= stop_ns:
                break
            if t0_log is None:
                t0_log = log_ns
            if args.rate > 0.0:
                due = t0_wall + (log_ns - t0_log) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
            pubs[msg.topic].publish(msg.data)
            sent += 1
        print(f"dvt-replay: published {sent} messages from {args.bag}", file=sys.stderr)
        time.sleep(0.2)  # let the last best-effort samples leave
        return 0
    except BagError as exc:
        print(f"dvt-replay: {exc}", file=sys.stderr)
        return 2
    finally:
        bag.close()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
