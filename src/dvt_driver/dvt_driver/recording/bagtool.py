"""``dvt-bag``: inspect and repair DVT recordings (rosbag2 directories, MCAP storage).

Usage::

    dvt-bag info PATH                 # topics, types, message counts, duration, rates
    dvt-bag recover PATH [--out DIR]  # rebuild a readable bag from a killed recording

``recover`` reads every complete chunk of the ``.mcap`` file(s) in ``PATH`` and writes a proper
bag (``metadata.yaml`` + finished ``.mcap``): in place, after renaming each broken file to
``*.mcap.broken``, or into the new directory ``--out DIR``. It prints the number of messages
recovered per topic. Exit status: 0 on success, 1 with a one-line reason on bad input.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dvt_model.errors import RecordingError
from dvt_model.recording import bag_summary, recover


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dvt-bag", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="summarise a bag: topics, counts, duration, rates")
    info.add_argument("path", help="bag directory")
    rec = sub.add_parser("recover", help="rebuild a readable bag from a killed recording")
    rec.add_argument("path", help="bag directory (or a single .mcap file)")
    rec.add_argument("--out", metavar="DIR", default=None,
                     help="write the rebuilt bag to this new directory instead of in place")
    rec.add_argument("--force", action="store_true",
                     help="rewrite even if the bag is already readable")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-bag``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "info":
            print(bag_summary(args.path).format())
            return 0
        result = recover(args.path, args.out, force=args.force)
    except RecordingError as exc:
        print(f"dvt-bag: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"dvt-bag: error: {exc}", file=sys.stderr)
        return 1
    if result.already_readable:
        print(f"{result.output}: already readable, nothing to recover "
              "(use --force to rewrite anyway)")
        return 0
    for moved in result.moved:
        print(f"kept the broken file as {moved}")
    if result.stopped:
        print(f"read until: {result.stopped} (an incomplete last chunk is expected after a kill)")
    if result.skipped:
        print(f"skipped {result.skipped} messages without a usable channel/schema")
    width = max((len(t) for t in result.counts), default=0)
    for topic, count in result.counts.items():
        print(f"  {topic:<{width}}  {count:8d} messages recovered")
    print(f"recovered {result.total} messages into {result.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
