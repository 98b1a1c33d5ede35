"""Discovery across machines (pure: no rclpy): Fast DDS discovery server or static peers.

By default ROS 2 finds other nodes by multicast, which a WiFi network often drops or floods.
Two unicast answers, both in the PyPI wheels (see ``docs/multihost.md``):

* a **discovery server** (``fast-discovery-server``, shipped with the rclpy wheels): one
  process, usually on the robot, that every participant contacts; participants find each other
  through it (:func:`server_env` for the participants, :func:`server_command` to start it,
  :func:`client_profile_xml` for the same as a Fast DDS XML profile);
* **static peers**: multicast off (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) plus the
  other machines' addresses in ``ROS_STATIC_PEERS`` (:func:`static_peers_env`).

The command ``dvt-discovery`` prints these settings for a shell and starts a server::

    dvt-discovery serve [--listen 0.0.0.0] [--port 11811]     # on the robot
    eval "$(dvt-discovery env --server ROBOT_IP[:11811])"      # in each shell, both machines
    eval "$(dvt-discovery env --peers OTHER_IP[,...])"          # static peers instead
    dvt-discovery xml --server ROBOT_IP > dvt-fastdds.xml       # XML profile instead of env

Measured here (two network namespaces joined by a veth pair): with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` alone nothing crosses; adding
``ROS_DISCOVERY_SERVER`` or ``ROS_STATIC_PEERS`` makes topics cross.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

from dvt_model.contract import FASTDDS_PROFILES_ENV, FASTDDS_XML_NS, reply_wait_writers

DEFAULT_PORT = 11811
"""Fast DDS discovery server's default UDP port."""
SERVER_EXE = "fast-discovery-server"
DISCOVERY_VARS = ("ROS_DISCOVERY_SERVER", "ROS_STATIC_PEERS", "ROS_SUPER_CLIENT",
                  "ROS_AUTOMATIC_DISCOVERY_RANGE", FASTDDS_PROFILES_ENV)
"""Environment variables the settings here may set."""


class DiscoveryError(ValueError):
    """A discovery option is not admissible (the message names the option and the value)."""


@dataclass(frozen=True)
class Endpoint:
    """A discovery server's address."""

    host: str
    port: int = DEFAULT_PORT

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_endpoint(text: str, option: str = "--discovery-server",
                   default_host: str | None = None) -> Endpoint:
    """``HOST[:PORT]`` (or ``:PORT`` / ``PORT`` when ``default_host`` is given).

    Raises:
        DiscoveryError: naming ``option`` and the value.
    """
    raw = text.strip()
    host, sep, port_text = raw.rpartition(":")
    if not sep:
        if default_host is not None and raw.isdigit():
            host, port_text = default_host, raw
        else:
            host, port_text = raw, str(DEFAULT_PORT)
    if not host:
        if default_host is None:
            raise DiscoveryError(f"{option}: expected HOST[:PORT], got {text!r}")
        host = default_host
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise DiscoveryError(f"{option}: port must be 1..65535, got {text!r}")
    _check_host(host, option, text)
    return Endpoint(host, int(port_text))


def _check_host(host: str, option: str, text: str) -> None:
    try:
        ipaddress.ip_address(host)
        return
    except ValueError:
        pass
    labels = host.split(".")
    if not all(lab and len(lab) <= 63 and all(ch.isalnum() or ch == "-" for ch in lab)
               for lab in labels):
        raise DiscoveryError(f"{option}: {host!r} is not an IP address or host name "
                             f"(in {text!r})")


def parse_peers(text: str | Sequence[str], option: str = "--static-peers") -> list[str]:
    """Addresses from ``A,B;C`` (or a list of such); at least one.

    Raises:
        DiscoveryError: naming ``option`` and the bad address.
    """
    items = [text] if isinstance(text, str) else list(text)
    peers: list[str] = []
    for item in items:
        for part in item.replace(";", ",").split(","):
            p = part.strip()
            if p:
                _check_host(p, option, item)
                peers.append(p)
    if not peers:
        raise DiscoveryError(f"{option}: expected one or more addresses, got {text!r}")
    return peers


def server_env(servers: Sequence[Endpoint], super_client: bool = False) -> dict[str, str]:
    """Environment of a participant that discovers through ``servers``.

    ``ROS_DISCOVERY_SERVER`` lists them by server id (id 0 first). A super client (tools that
    inspect the whole graph, such as the launcher's monitor) receives every participant's
    endpoints; a plain client only those it matches.
    """
    if not servers:
        raise DiscoveryError("server_env: no discovery server given")
    env = {"ROS_DISCOVERY_SERVER": ";".join(str(s) for s in servers)}
    if super_client:
        env["ROS_SUPER_CLIENT"] = "TRUE"
    return env


def static_peers_env(peers: Sequence[str]) -> dict[str, str]:
    """Environment of a participant that discovers only localhost and ``peers`` (unicast)."""
    if not peers:
        raise DiscoveryError("static_peers_env: no peer given")
    return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": ";".join(peers)}


def apply_env(base: Mapping[str, str], settings: Mapping[str, str]) -> dict[str, str]:
    """``base`` with ``settings``; a server setting drops a stale ``ROS_STATIC_PEERS`` and
    vice versa, and ``ROS_LOCALHOST_ONLY`` (deprecated, overrides the range) is removed."""
    env = dict(base)
    env.pop("ROS_LOCALHOST_ONLY", None)
    if "ROS_DISCOVERY_SERVER" in settings:
        env.pop("ROS_STATIC_PEERS", None)
    if "ROS_STATIC_PEERS" in settings:
        env.pop("ROS_DISCOVERY_SERVER", None)
        env.pop("ROS_SUPER_CLIENT", None)
    env.update(settings)
    return env


def _venv_lib() -> Path:
    return Path(sys.prefix) / "lib"


def server_command(listen: Endpoint, server_id: int = 0, exe: str | None = None) -> list[str]:
    """argv of a discovery server listening on ``listen`` (host 0.0.0.0: every interface)."""
    if not 0 <= server_id <= 255:
        raise DiscoveryError(f"server id: expected 0..255, got {server_id}")
    if exe is None:
        found = Path(sys.executable).parent / SERVER_EXE
        exe = str(found) if found.exists() else SERVER_EXE
    return [exe, "-i", str(server_id), "-l", listen.host, "-p", str(listen.port)]


def server_process_env(base: Mapping[str, str], lib_dir: Path | None = None
                       ) -> dict[str, str]:
    """Environment for the server binary: the wheels' libraries on ``LD_LIBRARY_PATH`` (the
    binary in the venv's ``bin`` finds ``libfastrtps`` only there), no client settings."""
    env = {k: v for k, v in base.items() if k not in DISCOVERY_VARS}
    lib = str(lib_dir or _venv_lib())
    parts = [p for p in env.get("LD_LIBRARY_PATH", "").split(":") if p]
    if lib not in parts:
        parts.insert(0, lib)
    env["LD_LIBRARY_PATH"] = ":".join(parts)
    return env


def server_guid_prefix(server_id: int) -> str:
    """The GUID prefix Fast DDS gives server ``server_id`` (``-i``)."""
    return f"44.53.{server_id:02x}.5f.45.50.52.4f.53.49.4d.41"


def client_profile_xml(servers: Sequence[Endpoint], super_client: bool = False,
                       lease_s: float = 20.0) -> str:
    """A Fast DDS XML profile (``FASTRTPS_DEFAULT_PROFILES_FILE``) equivalent to
    :func:`server_env`, with a participant lease of ``lease_s`` seconds (a longer lease rides
    out WiFi drop-outs; the default is 20 s). Server ``i`` of ``servers`` has id ``i``.
    Hosts must be IP addresses here. The file also carries the identifier's reply wait
    (:func:`dvt_model.contract.reply_wait_writers`): a profiles file set by the user replaces
    the one the identifier would use."""
    if not servers:
        raise DiscoveryError("client_profile_xml: no discovery server given")
    if not lease_s > 0:
        raise DiscoveryError(f"lease_s: expected > 0 s, got {lease_s!r}")
    remote = []
    for i, s in enumerate(servers):
        try:
            kind = "udpv6" if ipaddress.ip_address(s.host).version == 6 else "udpv4"
        except ValueError as exc:
            raise DiscoveryError(f"client_profile_xml: {s.host!r} is not an IP address "
                                 "(an XML profile needs one)") from exc
        remote.append(
            f'            <RemoteServer prefix="{server_guid_prefix(i)}">\n'
            "              <metatrafficUnicastLocatorList>\n"
            f"                <locator><{kind}><address>{escape(s.host)}</address>"
            f"<port>{s.port}</port></{kind}></locator>\n"
            "              </metatrafficUnicastLocatorList>\n"
            "            </RemoteServer>\n")
    sec = int(lease_s)
    nsec = round((lease_s - sec) * 1e9)
    protocol = "SUPER_CLIENT" if super_client else "CLIENT"
    return (
        '<?xml version="1.0" encoding="UTF-8" ?>\n'
        f'<dds xmlns="{FASTDDS_XML_NS}">\n'
        "  <profiles>\n"
        '    <participant profile_name="dvt_discovery_client" is_default_profile="true">\n'
        "      <rtps>\n"
        "        <builtin>\n"
        "          <discovery_config>\n"
        f"            <discoveryProtocol>{protocol}</discoveryProtocol>\n"
        "            <discoveryServersList>\n"
        + "".join(remote) +
        "            </discoveryServersList>\n"
        f"            <leaseDuration><sec>{sec}</sec><nanosec>{nsec}</nanosec>"
        "</leaseDuration>\n"
        "          </discovery_config>\n"
        "        </builtin>\n"
        "      </rtps>\n"
        "    </participant>\n"
        + reply_wait_writers() +
        "  </profiles>\n"
        "</dds>\n")


def shell_exports(env: Mapping[str, str]) -> str:
    """``export NAME='value'`` lines for ``eval``."""
    def quote(v: str) -> str:
        return "'" + v.replace("'", "'\"'\"'") + "'"
    return "".join(f"export {k}={quote(v)}\n" for k, v in env.items())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-discovery`` (see the module docstring)."""
    p = argparse.ArgumentParser(prog="dvt-discovery",
                                description="discovery across machines: discovery server or "
                                            "static peers (docs/multihost.md)")
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("env", help="print the environment for a shell (eval it)")
    g = e.add_mutually_exclusive_group(required=True)
    g.add_argument("--server", action="append", metavar="HOST[:PORT]",
                   help=f"discovery server (repeat for more; default port {DEFAULT_PORT})")
    g.add_argument("--peers", metavar="A[,B...]", help="static peers (other machines)")
    e.add_argument("--super-client", action="store_true",
                   help="see the whole graph (for tools that list topics and nodes)")
    x = sub.add_parser("xml", help="print a Fast DDS XML profile for a discovery-server client")
    x.add_argument("--server", action="append", required=True, metavar="IP[:PORT]")
    x.add_argument("--super-client", action="store_true")
    x.add_argument("--lease", type=float, default=20.0, help="participant lease [s]")
    s = sub.add_parser("serve", help="run a discovery server in the foreground")
    s.add_argument("--listen", default="0.0.0.0", help="address to listen on (default any)")
    s.add_argument("--port", type=int, default=DEFAULT_PORT)
    s.add_argument("--id", type=int, default=0, help="server id (position in "
                                                     "ROS_DISCOVERY_SERVER)")
    args = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        if args.cmd == "env":
            if args.server:
                env = server_env([parse_endpoint(t, "--server") for t in args.server],
                                 args.super_client)
            else:
                env = static_peers_env(parse_peers(args.peers))
            sys.stdout.write(shell_exports(env))
        elif args.cmd == "xml":
            sys.stdout.write(client_profile_xml([parse_endpoint(t, "--server")
                                                 for t in args.server],
                                                args.super_client, args.lease))
        else:
            listen = parse_endpoint(f"{args.listen}:{args.port}", "--listen/--port")
            argv_ = server_command(listen, args.id)
            os.execve(argv_[0] if os.path.isabs(argv_[0]) else _which(argv_[0]), argv_,
                      server_process_env(os.environ))
    except DiscoveryError as exc:
        print(f"dvt-discovery: error: {exc}", file=sys.stderr)
        return 2
    return 0


def _which(name: str) -> str:
    import shutil

    found = shutil.which(name)
    if found is None:
        raise DiscoveryError(f"{name} not found next to {sys.executable} or on PATH (it comes "
                             "with the ros-jazzy-rclpy[fastrtps] wheels)")
    return found


if __name__ == "__main__":
    sys.exit(main())
