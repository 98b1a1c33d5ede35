"""``dvt-launch``'s command line: its options, checked before anything starts (pure: no rclpy).

:func:`parse_args` exits with status 2 and a message naming the option and the value for a bad
argument (argparse's convention); :func:`experiment_of` and :func:`rate_of` derive what the
options imply. The options are described in :mod:`dvt_driver.system.launch` and by
``dvt-launch sim --help``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dvt_driver.errors import DvtDriverError, ExperimentError
from dvt_driver.run import discovery
from dvt_model.contract import DEFAULT_RECORD_TOPICS

__all__ = [
    "IDENTIFY_DIR",
    "REALTIME_CHILDREN",
    "SUPERVISE_RING_MINUTES",
    "experiment_of",
    "parse_args",
    "rate_of",
    "realtime_priorities",
    "ros_params",
]

SUPERVISE_RING_MINUTES = 10.0
"""Ring length ``--supervise`` implies without ``--ring-minutes`` [min]: the supervisor's
default wait (60 s of post-change data) plus a refit, with margin (``docs/loop.md`` §4)."""
IDENTIFY_DIR = "identify"
"""Sub-directory of the log directory that ``--supervise`` gives the identifier as
``output_dir`` (its episode reports ``episodes/episode-N.json`` / ``.md`` go there)."""
REALTIME_CHILDREN = {"plant": 0, "driver": 0, "model": 1, "experiment": -1, "recorder": -1,
                     "ring": -1}
"""The children ``--realtime P`` runs at a real-time priority (``SCHED_RR``), as offsets from
``P``: the sample path (plant, driver, model node) at ``P``; the experiment (its commands and
keep-alives: the controller's watchdog trips after 0.2 s without one) and the recorders (their
snapshot and flush work never delays a sample) one below. Everything else (the identifier and
its refit process, the bridge, the launcher) stays in the normal scheduler."""


def realtime_priorities(priority: int | None) -> dict[str, int]:
    """Child name -> ``SCHED_RR`` priority for ``--realtime priority`` (empty: off)."""
    if not priority:
        return {}
    return {name: max(1, priority + off) for name, off in REALTIME_CHILDREN.items()}


def _param(text: str, option: str) -> list[str]:
    if ":=" not in text or text.startswith(":="):
        raise argparse.ArgumentTypeError(f"{option}: expected NAME:=VALUE, got {text!r}")
    return ["-p", text]


def ros_params(items: Sequence[str], option: str) -> list[str]:
    """``--ros-args`` parameter arguments (``-p NAME:=VALUE`` each) of ``--<node>-param``
    ``items``; ``option`` names the option in the error."""
    out: list[str] = []
    for it in items:
        out += _param(it, option)
    return out


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    """Parse ``dvt-launch`` arguments."""
    from dvt_driver.run.experiment_core import available

    p = argparse.ArgumentParser(prog="dvt-launch",
                                description="start the DVT chain as processes, wait until it is "
                                            "ready, stop it cleanly")
    sub = p.add_subparsers(dest="mode", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--params", default="physical",
                        help="transmission parameter set of the model node (and of the plant "
                             "in sim); default physical")
    common.add_argument("--rate", type=float, default=None,
                        help="controller sample rate [Hz] (default: the experiment's, else "
                             "1000)")
    common.add_argument("--record", metavar="DIR", default=None,
                        help="record to this bag directory (must not exist)")
    common.add_argument("--record-topics", nargs="+", default=None, metavar="TOPIC",
                        help=f"topics/patterns to record (default {list(DEFAULT_RECORD_TOPICS)})")
    common.add_argument("--compression", choices=("none", "zstd"), default="zstd",
                        help="MCAP chunk compression of the recording (default zstd)")
    common.add_argument("--experiment", default=None, help=f"run one of {available()}")
    common.add_argument("--experiment-seed", type=int, default=0,
                        help="seed of the experiment's random signals (default 0)")
    common.add_argument("--experiment-set", action="append", default=[], metavar="NAME=VALUE",
                        help="experiment builder setting, passed as dvt-experiment --set "
                             "(repeatable)")
    common.add_argument("--duration", type=float, default=None,
                        help="run time [s] without --experiment (default: until Ctrl-C); with "
                             "--experiment an upper bound")
    common.add_argument("--no-model", action="store_true", help="do not start dvt_model_node")
    common.add_argument("--driver-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_driver_node parameter (repeatable)")
    common.add_argument("--model-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_model_node parameter (repeatable)")
    common.add_argument("--record-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt-recorder parameter (repeatable)")
    common.add_argument("--log-dir", default=None,
                        help="where the children's output goes (default: a new temp dir)")
    common.add_argument("--no-check", action="store_true",
                        help="do not read the recorded bag back at the end")
    common.add_argument("--max-missing", type=int, default=None, metavar="N",
                        help="exit with status 4 if the bag misses (or cannot align) more "
                             "than N samples inside the recording (default: report only)")
    common.add_argument("--foxglove", action="store_true",
                        help="start dvt-foxglove, the Foxglove WebSocket bridge "
                             "(docs/foxglove.md)")
    common.add_argument("--foxglove-port", type=int, default=None,
                        help="its WebSocket port (default 8765)")
    common.add_argument("--foxglove-host", default=None,
                        help="its listen address (default 127.0.0.1; 0.0.0.0 for every "
                             "interface)")
    common.add_argument("--foxglove-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt-foxglove parameter, e.g. rate_hz:=50 (repeatable)")
    common.add_argument("--ring-minutes", type=float, default=None, metavar="M",
                        help="also run a rolling recorder keeping the last M minutes "
                             "(snapshots on request, docs/loop.md)")
    common.add_argument("--ring-dir", default=None, metavar="DIR",
                        help="its ring directory (default <log dir>/ring; may exist)")
    common.add_argument("--ring-segment-seconds", type=float, default=10.0, metavar="S",
                        help="length of one ring segment [s] (default 10)")
    common.add_argument("--supervise", action="store_true",
                        help="also run dvt_identify_node with its supervisor (alarm -> refit "
                             "-> push -> watch -> keep or roll back, docs/loop.md); implies "
                             f"--ring-minutes {SUPERVISE_RING_MINUTES:g} unless given; episode "
                             f"reports in <log dir>/{IDENTIFY_DIR}/episodes")
    common.add_argument("--identify-param", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra dvt_identify_node parameter, e.g. "
                             "supervisor.min_post_change_s:=20 (repeatable; needs --supervise)")
    common.add_argument("--episodes", type=int, default=None, metavar="N",
                        help="end the run after N episode reports (needs --supervise; exit "
                             "status 5 if fewer when the run ends otherwise)")
    common.add_argument("--realtime", type=int, default=None, metavar="P",
                        help="run the 1 kHz chain (plant, driver, model node; the recorders at "
                             "P-1) at real-time priority P (SCHED_RR, 1..98): no other process "
                             "delays a sample; needs the right to (root, CAP_SYS_NICE or an "
                             "rtprio limit, ulimit -r); without it a warning and the normal "
                             "scheduler")
    common.add_argument("--start-discovery-server", default=None, metavar="[IP:]PORT",
                        help="start a Fast DDS discovery server (e.g. 0.0.0.0:11811) and use it "
                             "(docs/multihost.md)")
    common.add_argument("--discovery-server", action="append", default=[],
                        metavar="HOST[:PORT]",
                        help="discover through this Fast DDS discovery server (repeatable)")
    common.add_argument("--static-peers", default=None, metavar="A[,B...]",
                        help="discover only localhost and these machines (unicast)")
    sim = sub.add_parser("sim", parents=[common], help="simulated plant on a pseudo-terminal")
    sim.add_argument("--hidden", default="none",
                     help="hidden-effects preset or YAML file of the plant (default none)")
    sim.add_argument("--seed", type=int, default=0, help="plant noise seed (default 0)")
    sim.add_argument("--change-at", action="append", default=[], metavar="T:SPEC",
                     help="plant change: at plant time T [s] the changes of SPEC (preset or "
                          "hidden-effects YAML; a preset without a schedule is a step to its "
                          "friction), passed to dvt-plant (repeatable)")
    sim.add_argument("--change-file", default=None, metavar="PATH",
                     help="change applied by the plant on SIGHUP (forwarded by the launcher)")
    sim.add_argument("--plant-arg", action="append", default=[], metavar="ARG",
                     help="extra dvt-plant argument, e.g. --plant-arg=--crc-error-rate=0.01")
    hw = sub.add_parser("hw", parents=[common], help="real controller on a serial port")
    hw.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0")
    hw.add_argument("--baud", type=int, default=None, help="line rate (driver default 921600)")
    args = p.parse_args(list(argv))
    if args.rate is not None and not 0 < args.rate <= 2000:
        p.error(f"--rate: expected 0 < HZ <= 2000, got {args.rate}")
    if args.realtime is not None and not 1 <= args.realtime <= 98:
        p.error(f"--realtime: expected a priority 1..98, got {args.realtime}")
    if args.duration is not None and not args.duration > 0:
        p.error(f"--duration: expected a number > 0 s, got {args.duration}")
    for opt in ("driver_param", "model_param", "record_param", "foxglove_param",
                "identify_param"):
        for it in getattr(args, opt):
            try:
                _param(it, "--" + opt.replace("_", "-"))
            except argparse.ArgumentTypeError as exc:
                p.error(str(exc))
    if args.experiment is not None:
        try:
            experiment_of(args)
        except ExperimentError as exc:
            p.error(f"--experiment: {exc}")
    elif args.experiment_set:
        p.error("--experiment-set needs --experiment")
    try:
        args.discovery_env = _discovery(args)
    except discovery.DiscoveryError as exc:
        p.error(str(exc))
    if (args.foxglove_port is not None or args.foxglove_host is not None
            or args.foxglove_param) and not args.foxglove:
        p.error("--foxglove-port/--foxglove-host/--foxglove-param need --foxglove")
    if args.foxglove_port is not None and not 0 <= args.foxglove_port <= 65535:
        p.error(f"--foxglove-port: expected 0..65535, got {args.foxglove_port}")
    if not args.supervise and (args.identify_param or args.episodes is not None):
        p.error("--identify-param/--episodes need --supervise")
    if args.supervise and args.no_model:
        p.error("--supervise needs the model node (its residual and change alarms); drop "
                "--no-model")
    if args.episodes is not None and args.episodes < 1:
        p.error(f"--episodes: expected an integer >= 1, got {args.episodes}")
    if args.supervise and args.ring_minutes is None:
        args.ring_minutes = SUPERVISE_RING_MINUTES
    if args.ring_minutes is not None and not (0 < args.ring_minutes <= 24 * 60):
        p.error(f"--ring-minutes: expected 0 < M <= 1440, got {args.ring_minutes}")
    if args.ring_minutes is not None and not (
            0 < args.ring_segment_seconds <= args.ring_minutes * 60):
        p.error(f"--ring-segment-seconds: expected 0 < S <= ring minutes * 60, got "
                f"{args.ring_segment_seconds}")
    if args.ring_dir is not None and args.ring_minutes is None:
        p.error("--ring-dir needs --ring-minutes")
    if args.mode == "sim":
        from dvt_driver.plant.server import parse_change_at

        for text in args.change_at:
            try:
                parse_change_at(text)
            except DvtDriverError as exc:
                p.error(str(exc))
    if args.record is not None and Path(args.record).exists():
        p.error(f"--record: {args.record} already exists (a recording never overwrites)")
    return args


def _discovery(args: argparse.Namespace) -> dict[str, str]:
    """The discovery environment of the children (empty: the default discovery)."""
    chosen = [o for o, v in (("--start-discovery-server", args.start_discovery_server),
                             ("--discovery-server", args.discovery_server),
                             ("--static-peers", args.static_peers)) if v]
    if "--static-peers" in chosen and len(chosen) > 1:
        raise discovery.DiscoveryError(f"{' and '.join(chosen)}: choose a discovery server "
                                       "or static peers, not both")
    servers = [discovery.parse_endpoint(t, "--discovery-server") for t in args.discovery_server]
    args.discovery_listen = None
    if args.start_discovery_server:
        listen = discovery.parse_endpoint(args.start_discovery_server,
                                          "--start-discovery-server", default_host="0.0.0.0")
        args.discovery_listen = listen
        host = "127.0.0.1" if listen.host in ("0.0.0.0", "::") else listen.host
        servers.insert(0, discovery.Endpoint(host, listen.port))
    if servers:
        return discovery.server_env(servers)
    if args.static_peers:
        return discovery.static_peers_env(discovery.parse_peers(args.static_peers))
    return {}


def experiment_of(args: argparse.Namespace) -> Any:
    """The experiment ``args`` asks for (built as ``dvt-experiment`` will build it)."""
    from dvt_driver.run.experiment import parse_settings
    from dvt_driver.run.experiment_core import build

    return build(args.experiment, seed=args.experiment_seed,
                 **parse_settings(args.experiment_set))


def rate_of(args: argparse.Namespace) -> float:
    """The controller rate [Hz]: ``--rate``, else the experiment's, else 1000."""
    if args.rate is not None:
        return float(args.rate)
    if args.experiment is not None:
        return 1e6 / experiment_of(args).sample_period_us
    return 1000.0
