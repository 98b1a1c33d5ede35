"""Driver side and identifier side on two "machines": two network namespaces and a veth pair.

Namespace A (10.213.7.1, the robot): ``dvt-launch sim --start-discovery-server
10.213.7.1:11811`` (discovery server, plant, driver, model node) and a probe that waits for the
identifier's result. Namespace B (10.213.7.2, the workstation): ``dvt_identify_node`` and a probe
that must see samples, pushes a parameter to the model node and starts an identification; the
identifier pushes its model to the model node and publishes its result. Every participant runs
with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and UDP only (no shared memory), so whatever
crosses goes through the discovery server and over the veth pair; a control probe in B without
the discovery server must see nothing.

Skipped with the reason where namespaces cannot be made (not root, no ``ip``, no netns support).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import ROOT, script, wait_for
from dvt_driver.run import discovery

ADDR_A, ADDR_B = "10.213.7.1", "10.213.7.2"
PORT = 11811
TAG = f"dvt{os.getpid() % 100000}"
NS_A, NS_B = f"{TAG}a", f"{TAG}b"
VETH_A, VETH_B = f"{TAG}va", f"{TAG}vb"

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(120)]


def _ip_exe() -> str | None:
    found = shutil.which("ip")
    for cand in (found, "/usr/sbin/ip", "/sbin/ip", "/usr/bin/ip"):
        if cand and os.path.exists(cand):
            return cand
    return None


IP = _ip_exe() or "ip"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run([IP, *args], capture_output=True, text=True, timeout=10,
                          check=check)


def _why_not() -> str | None:
    if not sys.platform.startswith("linux"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    if _ip_exe() is None:
        return "the 'ip' command (iproute2) is not installed (scripts/bootstrap.sh installs it)"
    return None


def _teardown_ns() -> None:
    for ns in (NS_A, NS_B):
        pids = _ip("netns", "pids", ns, check=False).stdout.split()
        for pid in pids:  # only processes this test started live in its namespaces
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
        _ip("netns", "del", ns, check=False)
    _ip("link", "del", VETH_A, check=False)


@pytest.fixture
def two_hosts() -> Iterator[None]:
    reason = _why_not()
    if reason:
        pytest.skip(reason)
    _teardown_ns()
    try:
        r = _ip("netns", "add", NS_A, check=False)
        if r.returncode != 0:
            pytest.skip(f"'ip netns add' failed: {r.stderr.strip()}")
        try:
            _ip("netns", "add", NS_B)
            _ip("link", "add", VETH_A, "type", "veth", "peer", "name", VETH_B)
            _ip("link", "set", VETH_A, "netns", NS_A)
            _ip("link", "set", VETH_B, "netns", NS_B)
            for ns, dev, addr in ((NS_A, VETH_A, ADDR_A), (NS_B, VETH_B, ADDR_B)):
                _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
                _ip("-n", ns, "link", "set", dev, "up")
                _ip("-n", ns, "link", "set", "lo", "up")
        except subprocess.CalledProcessError as exc:
            pytest.skip(f"cannot set up the namespaces: {' '.join(exc.cmd)}: "
                        f"{(exc.stderr or '').strip()}")
        yield
    finally:
        _teardown_ns()


class NsProcs:
    """Processes started inside a namespace; all stopped at the end (SIGINT, then SIGKILL)."""

    def __init__(self, logdir: Path) -> None:
        self.logdir = logdir
        self.procs: list[tuple[subprocess.Popen[bytes], Path]] = []

    def start(self, ns: str, name: str, argv: list[str], env: dict[str, str]
              ) -> subprocess.Popen[bytes]:
        log = self.logdir / f"{name}.log"
        with log.open("wb") as fh:
            proc = subprocess.Popen([IP, "netns", "exec", ns, *argv], env=env, stdout=fh,
                                    stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append((proc, log))
        return proc

    def log(self, name: str) -> str:
        path = self.logdir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop_all(self) -> None:
        for proc, _ in reversed(self.procs):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGINT)
        deadline = time.monotonic() + 15
        for proc, _ in reversed(self.procs):
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)


PROBE_B = r'''
import json, sys, time
import rclpy
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from dvt_model import rosutil
from dvt_model.contract import answer_of

rclpy.init()
node = rclpy.create_node("probe_b")
count = {"n": 0}
node.create_subscription(JointState, "/dvt/joint_states",
                         lambda m: count.__setitem__("n", count["n"] + 1), rosutil.SENSOR_QOS)

def spin_until(pred, timeout, what):
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            print(f"TIMEOUT {what}", flush=True)
            sys.exit(1)
        rclpy.spin_once(node, timeout_sec=0.05)

spin_until(lambda: count["n"] >= 50, 30, "samples")
print(f"SAMPLES {count['n']}", flush=True)
client = AsyncParameterClient(node, "dvt_model")
spin_until(lambda: client.services_are_ready(), 20, "model parameter services")
# a set of one value and a read are idempotent: sent again while a reply is lost (the
# real-time model node's 100 ms reply wait, a fresh client across a discovery server)
spin = lambda s: rclpy.spin_once(node, timeout_sec=s)
res, _ = answer_of(lambda: client.set_parameters([Parameter("reanchor_period", value=2.5)]),
                   10, 2.0, wait=spin)
print(f"PUSHED {res.results[0].successful}", flush=True)
res, _ = answer_of(lambda: client.get_parameters(["reanchor_period"]), 10, 2.0, wait=spin)
print(f"GOT reanchor_period {res.values[0].double_value}", flush=True)
cli = node.create_client(Trigger, "/dvt/identify/run")
spin_until(lambda: cli.service_is_ready(), 20, "identify service")
fut = cli.call_async(Trigger.Request())
spin_until(fut.done, 10, "identify run")
print(f"IDENTIFY {fut.result().success} {fut.result().message}", flush=True)
'''

PROBE_A = r'''
import sys, time
import rclpy
from std_msgs.msg import String
from dvt_model import rosutil

rclpy.init()
node = rclpy.create_node("probe_a")
got = []
node.create_subscription(String, "/dvt/identify/result", got.append, rosutil.LATCHED_QOS)
deadline = time.monotonic() + float(sys.argv[1])
while not got and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print("RESULT " + (got[0].data if got else "none"), flush=True)
'''

CONTROL = r'''
import sys, time
import rclpy
from sensor_msgs.msg import JointState
from dvt_model import rosutil

rclpy.init()
node = rclpy.create_node("probe_control")
got = []
node.create_subscription(JointState, "/dvt/joint_states", got.append, rosutil.SENSOR_QOS)
deadline = time.monotonic() + float(sys.argv[1])
while time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print(f"CONTROL {len(got)}", flush=True)
'''


def test_driver_and_identifier_on_two_hosts(two_hosts: None, ros_env: dict[str, str],
                                            tmp_path: Path) -> None:
    base = dict(ros_env)
    base.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                 "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"})  # no shared memory across "hosts"
    client_env = discovery.apply_env(
        base, discovery.server_env([discovery.Endpoint(ADDR_A, PORT)]))
    py = sys.executable
    probes = {}
    for name, text in (("probe_b", PROBE_B), ("probe_a", PROBE_A), ("control", CONTROL)):
        probes[name] = tmp_path / f"{name}.py"
        probes[name].write_text(text)
    procs = NsProcs(tmp_path)
    try:
        # A: the robot
        launch = procs.start(NS_A, "launch", [
            script("dvt-launch"), "sim", "--rate", "250", "--log-dir", str(tmp_path / "a"),
            "--start-discovery-server", f"{ADDR_A}:{PORT}"], base)
        wait_for(lambda: "model node publishing" in procs.log("launch")
                 or launch.poll() is not None, 45, "the robot side (dvt-launch) to be up")
        assert launch.poll() is None, procs.log("launch")
        result_probe = procs.start(NS_A, "probe_a", [py, str(probes["probe_a"]), "50"],
                                   client_env)
        # B: the workstation, and a control without the discovery server
        control = procs.start(NS_B, "control", [py, str(probes["control"]), "4"], base)
        procs.start(NS_B, "identify", [
            script("dvt_identify_node"), "--ros-args",
            "-p", f"estimation_bags:=[{ROOT / 'bags' / 'ident-none-1'}]",
            "-p", f"validation_bags:=[{ROOT / 'bags' / 'ident-none-2'}]",
            "-p", "augment:=false", "-p", f"output_dir:={tmp_path / 'identify'}"], client_env)
        probe = procs.start(NS_B, "probe_b", [py, str(probes["probe_b"])], client_env)

        wait_for(lambda: "SAMPLES" in procs.log("probe_b") or probe.poll() is not None, 30,
                 "samples from A in B")
        assert "SAMPLES" in procs.log("probe_b"), procs.log("probe_b")
        wait_for(lambda: control.poll() is not None, 15, "the control probe")
        assert "CONTROL 0" in procs.log("control"), (
            "samples crossed without the discovery server: " + procs.log("control"))
        wait_for(lambda: probe.poll() is not None, 40, "the push and the identify request")
        out = procs.log("probe_b")
        assert "PUSHED True" in out and "GOT reanchor_period 2.5" in out, out
        assert "IDENTIFY True" in out, out + procs.log("identify")
        wait_for(lambda: result_probe.poll() is not None, 55, "the identifier's result in A")
        line = next((ln for ln in procs.log("probe_a").splitlines()
                     if ln.startswith("RESULT ")), "RESULT none")
        assert line != "RESULT none", procs.log("probe_a") + procs.log("identify")
        result = json.loads(line[len("RESULT "):])
        assert "error" not in result, result
        assert result["pushed"]["node"] == "dvt_model", result
        assert launch.poll() is None, procs.log("launch")
    finally:
        procs.stop_all()


SAMPLES_PROBE = r'''
import sys, time
import rclpy
from sensor_msgs.msg import JointState
from dvt_model import rosutil

rclpy.init()
node = rclpy.create_node("probe_samples")
got = []
node.create_subscription(JointState, "/dvt/joint_states", got.append, rosutil.SENSOR_QOS)
deadline = time.monotonic() + float(sys.argv[1])
while len(got) < 50 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print(f"SAMPLES {len(got)}", flush=True)
'''


def test_static_peers_across_hosts(two_hosts: None, ros_env: dict[str, str],
                                   tmp_path: Path) -> None:
    """``dvt-launch --static-peers``: unicast discovery of the listed machine only."""
    base = dict(ros_env)
    base.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                 "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"})
    probe_file = tmp_path / "probe.py"
    probe_file.write_text(SAMPLES_PROBE)
    procs = NsProcs(tmp_path)
    try:
        launch = procs.start(NS_A, "launch", [
            script("dvt-launch"), "sim", "--no-model", "--rate", "250",
            "--log-dir", str(tmp_path / "a"), "--static-peers", ADDR_B], base)
        wait_for(lambda: "samples flowing" in procs.log("launch") or launch.poll() is not None,
                 45, "the robot side (dvt-launch) to be up")
        assert launch.poll() is None, procs.log("launch")
        probe = procs.start(NS_B, "probe", [sys.executable, str(probe_file), "20"],
                            discovery.apply_env(base, discovery.static_peers_env([ADDR_A])))
        wait_for(lambda: probe.poll() is not None, 30, "the probe in B")
        assert "SAMPLES 50" in procs.log("probe"), procs.log("probe") + procs.log("launch")
    finally:
        procs.stop_all()
