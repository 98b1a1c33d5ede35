"""A service reply waits :data:`~dvt_model.contract.REPLY_WAIT_S` for a late client's reader.

``rmw_fastrtps`` drops a service's reply when the client's response reader is not matched
within the reply writer's ``max_blocking_time`` (100 ms by default); through a discovery server a
fresh client's reader can be matched 60-70 ms after its request arrives
(``scripts/service_lag.py``), and a red fresh-clone run lost the identifier's reply this way.
The identifier's services get a profile that waits longer (:func:`dvt_model.rosutil.init`).

The topic-level test makes the reader late for good: the client asks for a transient-local
reply, which the server's volatile reply writer cannot offer, so the reader never matches while
the request does. The server then waits exactly its reply budget before it drops the reply, and
that wait is what the test measures, with the profile and (the control) without it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from conftest import wait_for
from dvt_driver.run import discovery
from dvt_model import rosutil
from dvt_model.contract import REPLY_WAIT_S, SRV_IDENTIFY_RUN, reply_wait_profile
from dvt_model.errors import ContractError

NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def _wait_of(xml: str) -> dict[str, float]:
    root = ET.fromstring(xml)
    out = {}
    for w in root.iter(f"{NS}data_writer"):
        mbt = w.find(f"{NS}qos/{NS}reliability/{NS}max_blocking_time")
        assert mbt is not None, xml
        out[w.attrib["profile_name"]] = (int(mbt.findtext(f"{NS}sec") or "x")
                                         + int(mbt.findtext(f"{NS}nanosec") or "x") * 1e-9)
    return out


def test_profile_names_each_reply_topic_with_its_wait() -> None:
    xml = reply_wait_profile([SRV_IDENTIFY_RUN, "/a/b"], wait_s=0.25)
    assert _wait_of(xml) == {"rr/dvt/identify/runReply": pytest.approx(0.25),
                             "rr/a/bReply": pytest.approx(0.25)}
    assert _wait_of(reply_wait_profile([SRV_IDENTIFY_RUN])) == {
        "rr/dvt/identify/runReply": pytest.approx(REPLY_WAIT_S)}


@pytest.mark.parametrize(("services", "wait", "needle"), [
    ([], 1.0, "no service"), (["dvt/run"], 1.0, "'dvt/run'"), (["/a b"], 1.0, "'/a b'"),
    (["/a"], 0.0, "0.0"), (["/a"], float("nan"), "nan"), (["/a"], 1e5, "100000.0")])
def test_profile_rejects_bad_input_naming_it(services: list[str], wait: float,
                                             needle: str) -> None:
    with pytest.raises(ContractError, match=re.escape(needle)):
        reply_wait_profile(services, wait)


def test_discovery_profile_carries_the_reply_wait() -> None:
    xml = discovery.client_profile_xml([discovery.Endpoint("10.0.0.1")])
    assert _wait_of(xml) == {"rr/dvt/identify/runReply": pytest.approx(REPLY_WAIT_S)}


def test_use_reply_wait_writes_the_profile_and_keeps_a_users_file(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    path = rosutil.use_reply_wait([SRV_IDENTIFY_RUN], 1.5, env=env)
    assert path is not None and env[rosutil.PROFILES_ENV] == path
    assert _wait_of(Path(path).read_text()) == {"rr/dvt/identify/runReply": 1.5}
    assert rosutil.use_reply_wait([SRV_IDENTIFY_RUN], 1.5, env={}) == path  # same content
    own = {rosutil.PROFILES_ENV: str(tmp_path / "mine.xml")}
    assert rosutil.use_reply_wait([SRV_IDENTIFY_RUN], env=own) is None
    assert own == {rosutil.PROFILES_ENV: str(tmp_path / "mine.xml")}
    note = rosutil.users_profile_note([SRV_IDENTIFY_RUN], str(tmp_path / "mine.xml"))
    for part in (str(tmp_path / "mine.xml"), SRV_IDENTIFY_RUN, f"{REPLY_WAIT_S:g} s",
                 "100 ms", "dvt-discovery xml"):
        assert part in note, (part, note)


def test_a_process_with_the_users_file_says_its_replies_keep_100_ms(tmp_path: Path) -> None:
    """``rosutil.init(reply_wait=...)`` under the user's own profiles file warns, naming the
    file and the service (the user's file decides, silently before)."""
    mine = tmp_path / "mine.xml"
    mine.write_text(reply_wait_profile(["/other"], 0.5))
    env = {**os.environ, rosutil.PROFILES_ENV: str(mine)}
    code = ("import rclpy; from dvt_model import rosutil; "
            f"rosutil.init(['x'], reply_wait=[{SRV_IDENTIFY_RUN!r}]); rclpy.shutdown()")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert str(mine) in out.stderr and SRV_IDENTIFY_RUN in out.stderr, out.stderr
    assert "WARN" in out.stderr, out.stderr


SERVER = r'''
import sys, time, warnings
import rclpy
from std_srvs.srv import Trigger
from dvt_model import rosutil

def shown(message, category, filename, lineno, file=None, line=None):
    print(f"DROPPED {time.monotonic()!r} {message}", flush=True)

warnings.showwarning = shown
rosutil.init(["server"], reply_wait=[sys.argv[1]] if sys.argv[2] == "profile" else [])
node = rclpy.create_node("reply_wait_server")
def on_call(req, resp):
    print(f"CALL {time.monotonic()!r}", flush=True)
    resp.success = True
    return resp
node.create_service(Trigger, sys.argv[1], on_call)
print("UP", flush=True)
rosutil.spin(node)
'''

CLIENT = r'''
import sys, time
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger
rclpy.init()
node = rclpy.create_node("reply_wait_client")
# a transient-local reader: the server's volatile reply writer never matches it
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
cli = node.create_client(Trigger, sys.argv[1], qos_profile=qos)
# such a client is never "ready": wait for the service with a plain one; the transient-local
# request reaches the server once its reader has matched the writer
plain = node.create_client(Trigger, sys.argv[1])
deadline = time.monotonic() + 20
while not plain.service_is_ready() and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
fut = cli.call_async(Trigger.Request())
print("SENT", flush=True)
deadline = time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
print("REPLY" if fut.done() else "NO REPLY", flush=True)
'''


def _server_wait(tmp_path: Path, env: dict[str, str], mode: str) -> float:
    """Seconds the server held the reply before dropping it (its log's CALL to DROPPED)."""
    service = f"/dvt_test/reply_wait_{mode}"
    (tmp_path / "server.py").write_text(SERVER)
    (tmp_path / "client.py").write_text(CLIENT)
    env = {k: v for k, v in env.items() if k != rosutil.PROFILES_ENV}
    logs = {n: tmp_path / f"{n}-{mode}.log" for n in ("server", "client")}
    procs: list[subprocess.Popen[bytes]] = []
    try:
        with logs["server"].open("wb") as fh:
            procs.append(subprocess.Popen(
                [sys.executable, str(tmp_path / "server.py"), service, mode], env=env,
                stdout=fh, stderr=subprocess.STDOUT, start_new_session=True))
        wait_for(lambda: "UP" in logs["server"].read_text() or procs[0].poll() is not None,
                 30, "the server to be up")
        with logs["client"].open("wb") as fh:
            procs.append(subprocess.Popen(
                [sys.executable, str(tmp_path / "client.py"), service,
                 str(REPLY_WAIT_S + 3.0)], env=env,
                stdout=fh, stderr=subprocess.STDOUT, start_new_session=True))
        wait_for(lambda: "DROPPED" in logs["server"].read_text(), REPLY_WAIT_S + 30,
                 f"the server to drop the reply ({mode})")
        text = logs["server"].read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, 9)
            p.wait(timeout=10)
    t_call = float(re.search(r"CALL (\S+)", text).group(1))  # type: ignore[union-attr]
    t_drop = float(re.search(r"DROPPED (\S+)", text).group(1))  # type: ignore[union-attr]
    assert "client will not receive response" in text, text
    return t_drop - t_call


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_reply_waits_the_budget_for_a_late_reader(ros_env: dict[str, str],
                                                  tmp_path: Path) -> None:
    held = _server_wait(tmp_path, ros_env, "profile")
    assert 0.9 * REPLY_WAIT_S <= held <= REPLY_WAIT_S + 1.0, held
    default = _server_wait(tmp_path, ros_env, "default")  # the control: rmw's own 100 ms
    assert default < 0.5, default


LOSING_SERVER = r'''
import sys
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger
rclpy.init()
node = rclpy.create_node("losing_server")
calls = [0]
def on_call(req, resp):
    calls[0] += 1
    if calls[0] <= 2:  # the first two replies are lost (raised before they are sent)
        raise LookupError(f"call {calls[0]} lost")
    resp.success, resp.message = True, f"call {calls[0]}"
    return resp
node.create_service(Trigger, sys.argv[1], on_call)
exe = SingleThreadedExecutor()
exe.add_node(node)
print("UP", flush=True)
while True:
    try:
        exe.spin_once(timeout_sec=0.1)
    except LookupError as exc:
        print(f"LOST {exc}", flush=True)
'''


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_an_idempotent_call_is_sent_again_after_a_lost_reply(
        procs: Any, rclpy_context: Any, tmp_path: Path) -> None:
    """:func:`dvt_model.rosutil.call_idempotent` against a real server that loses its first two
    replies: sent once (the control), the call gets nothing; sent again every second, it gets
    the third."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    service = "/dvt_test/losing"
    (tmp_path / "server.py").write_text(LOSING_SERVER)
    server = procs.start("python3", str(tmp_path / "server.py"), service)
    wait_for(lambda: "UP" in procs.log(server) or server.poll() is not None, 30, "server up")
    node = rclpy.create_node("losing_client", context=rclpy_context)
    exe = SingleThreadedExecutor(context=rclpy_context)
    exe.add_node(node)
    try:
        cli = node.create_client(Trigger, service)
        wait_for(lambda: exe.spin_once(timeout_sec=0.05) or cli.service_is_ready(), 30,
                 "the service")
        assert rosutil.call_idempotent(exe, cli, Trigger.Request(), 2.0, resend_s=5.0) is None
        wait_for(lambda: "call 1 lost" in procs.log(server), 10, "the first loss")
        reply = rosutil.call_idempotent(exe, cli, Trigger.Request(), 20.0, resend_s=1.0)
        assert reply is not None and reply.message == "call 3", reply
        assert "call 2 lost" in procs.log(server)
        assert not cli._pending_requests, "a request left pending"
    finally:
        exe.remove_node(node)
        node.destroy_node()


def test_call_idempotent_rejects_bad_budgets_naming_them() -> None:
    with pytest.raises(ValueError, match="resend_after=0"):
        rosutil.call_idempotent(None, None, None, 1.0, resend_s=0)
    with pytest.raises(ValueError, match="timeout=-1"):
        rosutil.call_idempotent(None, None, None, -1, resend_s=1.0)
