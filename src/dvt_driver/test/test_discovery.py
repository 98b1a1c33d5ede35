"""Discovery configuration (pure): endpoints, environments, the server command, XML profile,
the ``dvt-discovery`` command and ``dvt-launch``'s discovery options."""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from dvt_driver.run import discovery as d


def test_parse_endpoint() -> None:
    assert d.parse_endpoint("10.0.0.2") == d.Endpoint("10.0.0.2", 11811)
    assert d.parse_endpoint("robot.local:12000") == d.Endpoint("robot.local", 12000)
    assert d.parse_endpoint("12000", default_host="0.0.0.0") == d.Endpoint("0.0.0.0", 12000)
    assert d.parse_endpoint(":12000", default_host="0.0.0.0") == d.Endpoint("0.0.0.0", 12000)
    assert str(d.Endpoint("1.2.3.4", 5)) == "1.2.3.4:5"
    for bad, needle in (("1.2.3.4:0", "port"), ("1.2.3.4:x", "port"), (":5", "HOST"),
                        ("bad host!:5", "not an IP address")):
        with pytest.raises(d.DiscoveryError, match=needle) as exc:
            d.parse_endpoint(bad, "--discovery-server")
        assert "--discovery-server" in str(exc.value)


def test_parse_peers() -> None:
    assert d.parse_peers("10.0.0.1, 10.0.0.2;robot") == ["10.0.0.1", "10.0.0.2", "robot"]
    assert d.parse_peers(["a", "b,c"]) == ["a", "b", "c"]
    with pytest.raises(d.DiscoveryError, match="--static-peers"):
        d.parse_peers(" , ")
    with pytest.raises(d.DiscoveryError, match="not an IP"):
        d.parse_peers("10.0.0.1,a b")


def test_environments() -> None:
    servers = [d.Endpoint("10.0.0.1"), d.Endpoint("10.0.0.9", 12000)]
    assert d.server_env(servers) == {"ROS_DISCOVERY_SERVER": "10.0.0.1:11811;10.0.0.9:12000"}
    assert d.server_env(servers[:1], super_client=True)["ROS_SUPER_CLIENT"] == "TRUE"
    assert d.static_peers_env(["a", "b"]) == {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                                              "ROS_STATIC_PEERS": "a;b"}
    with pytest.raises(d.DiscoveryError):
        d.server_env([])
    with pytest.raises(d.DiscoveryError):
        d.static_peers_env([])
    base = {"ROS_LOCALHOST_ONLY": "1", "ROS_STATIC_PEERS": "x", "PATH": "/bin"}
    env = d.apply_env(base, d.server_env(servers[:1]))
    assert env == {"PATH": "/bin", "ROS_DISCOVERY_SERVER": "10.0.0.1:11811"}
    env = d.apply_env({"ROS_DISCOVERY_SERVER": "x", "ROS_SUPER_CLIENT": "TRUE"},
                      d.static_peers_env(["a"]))
    assert "ROS_DISCOVERY_SERVER" not in env and "ROS_SUPER_CLIENT" not in env


def test_server_command_and_env(tmp_path: Path) -> None:
    argv = d.server_command(d.Endpoint("0.0.0.0", 11811), 0, exe="fds")
    assert argv == ["fds", "-i", "0", "-l", "0.0.0.0", "-p", "11811"]
    default = d.server_command(d.Endpoint("127.0.0.1", 1))
    assert default[0].endswith("fast-discovery-server")
    with pytest.raises(d.DiscoveryError, match="server id"):
        d.server_command(d.Endpoint("a"), 300)
    env = d.server_process_env({"LD_LIBRARY_PATH": "/x", "ROS_DISCOVERY_SERVER": "a:1",
                                "HOME": "/root"}, lib_dir=tmp_path)
    assert env == {"LD_LIBRARY_PATH": f"{tmp_path}:/x", "HOME": "/root"}
    assert d.server_process_env({"LD_LIBRARY_PATH": str(tmp_path)}, lib_dir=tmp_path) == {
        "LD_LIBRARY_PATH": str(tmp_path)}


def test_client_profile_xml_parses_and_lists_the_servers() -> None:
    text = d.client_profile_xml([d.Endpoint("10.0.0.1"), d.Endpoint("fe80::1", 12000)],
                                super_client=True, lease_s=30.5)
    root = ET.fromstring(text)
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    cfg = root.find("f:profiles/f:participant/f:rtps/f:builtin/f:discovery_config", ns)
    assert cfg is not None
    assert cfg.findtext("f:discoveryProtocol", namespaces=ns) == "SUPER_CLIENT"
    servers = cfg.findall("f:discoveryServersList/f:RemoteServer", ns)
    assert [s.get("prefix") for s in servers] == [d.server_guid_prefix(0),
                                                  d.server_guid_prefix(1)]
    assert servers[1].find(".//f:udpv6/f:address", ns) is not None
    assert cfg.findtext("f:leaseDuration/f:sec", namespaces=ns) == "30"
    assert cfg.findtext("f:leaseDuration/f:nanosec", namespaces=ns) == "500000000"
    with pytest.raises(d.DiscoveryError, match="IP address"):
        d.client_profile_xml([d.Endpoint("robot.local")])
    with pytest.raises(d.DiscoveryError, match="lease"):
        d.client_profile_xml([d.Endpoint("10.0.0.1")], lease_s=0)


def test_shell_exports_quote() -> None:
    assert d.shell_exports({"A": "x;y", "B": "it's"}) == \
        "export A='x;y'\nexport B='it'\"'\"'s'\n"


def test_cli_env_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert d.main(["env", "--server", "10.0.0.1", "--server", "10.0.0.2:5"]) == 0
    assert capsys.readouterr().out == \
        "export ROS_DISCOVERY_SERVER='10.0.0.1:11811;10.0.0.2:5'\n"
    assert d.main(["env", "--peers", "10.0.0.1"]) == 0
    assert "ROS_STATIC_PEERS='10.0.0.1'" in capsys.readouterr().out
    assert d.main(["xml", "--server", "10.0.0.1"]) == 0
    assert "<discoveryProtocol>CLIENT<" in capsys.readouterr().out
    assert d.main(["env", "--server", "10.0.0.1:99999"]) == 2
    assert "--server: port" in capsys.readouterr().err


def test_launch_discovery_options() -> None:
    from dvt_driver.system.launch_args import parse_args

    a = parse_args(["sim", "--start-discovery-server", "11888"])
    assert a.discovery_env == {"ROS_DISCOVERY_SERVER": "127.0.0.1:11888"}
    assert a.discovery_listen == d.Endpoint("0.0.0.0", 11888)
    a = parse_args(["sim", "--start-discovery-server", "10.0.0.1:11811",
                    "--discovery-server", "10.0.0.2"])
    assert a.discovery_env == {"ROS_DISCOVERY_SERVER": "10.0.0.1:11811;10.0.0.2:11811"}
    a = parse_args(["sim", "--static-peers", "10.0.0.2"])
    assert a.discovery_env["ROS_STATIC_PEERS"] == "10.0.0.2"
    assert parse_args(["sim"]).discovery_env == {}
    for bad in (["--static-peers", "a", "--discovery-server", "b"],
                ["--discovery-server", "a:0"], ["--foxglove-port", "5"],
                ["--foxglove", "--foxglove-param", "nope"]):
        with pytest.raises(SystemExit):
            parse_args(["sim", *bad])


def test_discovery_server_binary_runs() -> None:
    """The wheels' server binary starts with the environment :func:`server_process_env`
    makes (its help exits at once)."""
    argv = d.server_command(d.Endpoint("127.0.0.1"))
    if not Path(argv[0]).exists():
        pytest.fail(f"{argv[0]} is not installed next to {sys.executable} (the pinned "
                    "Fast DDS wheels of requirements.txt bring it)")
    import os

    r = subprocess.run([argv[0], "-h"], env=d.server_process_env(os.environ),
                       capture_output=True, text=True, timeout=10)
    assert "Server-Client discovery" in r.stdout + r.stderr
