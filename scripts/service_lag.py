"""How long a service's reply waits for a fresh client's response reader (the budget of
``dvt_model.contract.REPLY_WAIT_S``).

Two network namespaces joined by a veth pair, as ``tests/test_multihost.py`` makes them: a
discovery server and a ``std_srvs/Trigger`` server in A, a client in B that calls the service
``--calls`` times, each time from a fresh participant (a new rclpy context), as soon as the
service is ready. The server waits up to 10 s for each client's response reader (a reply-wait
profile, :func:`dvt_model.rosutil.use_reply_wait`), so what ``rmw_fastrtps`` would have dropped
after its default 100 ms shows as a long wait instead. Prints JSON: per call the wait for
readiness, the request's transit and the reply's wait; the maximum and how many exceeded 50 and
100 ms. ``--busy`` keeps both cores busy meanwhile. Needs root (namespaces); about 1 s a call.

Usage::

    sudo .venv/bin/python scripts/service_lag.py [--calls 40] [--busy]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NS_A, NS_B, VETH_A, VETH_B = "dvtlagA", "dvtlagB", "dvtlagva", "dvtlagvb"
ADDR_A, ADDR_B = "10.213.9.1", "10.213.9.2"
SERVICE = "/dvt_lag/run"

SERVER = r'''
import sys, time
import rclpy
from std_srvs.srv import Trigger
from dvt_model import rosutil
rosutil.init(["lag_server"], reply_wait=[sys.argv[1]])  # the reply waits up to 10 s (below)
node = rclpy.create_node("lag_server")
def on_call(req, resp):
    resp.success, resp.message = True, repr(time.monotonic())
    return resp
node.create_service(Trigger, sys.argv[1], on_call)
print("UP", flush=True)
rclpy.spin(node)
'''

CLIENT = r'''
import json, sys, time
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger
calls, rows = int(sys.argv[2]), []
for i in range(calls):
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node(f"lag_client{i}", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    cli = node.create_client(Trigger, sys.argv[1])
    t0 = time.monotonic()
    while not cli.service_is_ready() and time.monotonic() - t0 < 30:
        ex.spin_once(timeout_sec=0.01)
    t1 = time.monotonic()
    fut = cli.call_async(Trigger.Request())
    while not fut.done() and time.monotonic() - t1 < 15:
        ex.spin_once(timeout_sec=0.01)
    t2 = time.monotonic()
    tc = float(fut.result().message) if fut.done() else None
    rows.append({"ready_s": t1 - t0, "request_s": None if tc is None else tc - t1,
                 "reply_s": None if tc is None else t2 - tc})
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)
print("ROWS " + json.dumps(rows), flush=True)
'''


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


def _teardown() -> None:
    for ns in (NS_A, NS_B):
        pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True,
                              text=True).stdout.split()
        for pid in pids:
            subprocess.run(["kill", "-9", pid], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=40)
    ap.add_argument("--busy", action="store_true", help="keep both cores busy meanwhile")
    args = ap.parse_args()
    if os.geteuid() != 0:
        print("service_lag: needs root (network namespaces)", file=sys.stderr)
        return 2
    _teardown()
    _ip("netns", "add", NS_A)
    _ip("netns", "add", NS_B)
    _ip("link", "add", VETH_A, "type", "veth", "peer", "name", VETH_B)
    for ns, dev, addr in ((NS_A, VETH_A, ADDR_A), (NS_B, VETH_B, ADDR_B)):
        _ip("link", "set", dev, "netns", ns)
        _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
        _ip("-n", ns, "link", "set", dev, "up")
        _ip("-n", ns, "link", "set", "lo", "up")
    work = Path(tempfile.mkdtemp(prefix="dvt-service-lag-"))
    (work / "server.py").write_text(SERVER)
    (work / "client.py").write_text(CLIENT)
    from dvt_model import rosutil

    env = dict(os.environ, ROS_DOMAIN_ID="77", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               FASTDDS_BUILTIN_TRANSPORTS="UDPv4", ROS_DISCOVERY_SERVER=f"{ADDR_A}:11811")
    env.pop(rosutil.PROFILES_ENV, None)
    server_env = dict(env)
    rosutil.use_reply_wait([SERVICE], wait_s=10.0, env=server_env)
    busy: list[subprocess.Popen[bytes]] = []
    procs: list[subprocess.Popen[bytes]] = []
    try:
        bindir = Path(sys.executable).parent
        procs.append(subprocess.Popen(
            ["ip", "netns", "exec", NS_A, str(bindir / "dvt-discovery"), "serve", "--listen",
             ADDR_A], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
        time.sleep(1.0)
        procs.append(subprocess.Popen(
            ["ip", "netns", "exec", NS_A, sys.executable, str(work / "server.py"), SERVICE],
            env=server_env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
        if args.busy:
            busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                    for _ in range(2)]
        out = subprocess.run(
            ["ip", "netns", "exec", NS_B, sys.executable, str(work / "client.py"), SERVICE,
             str(args.calls)], env=env, capture_output=True, text=True,
            timeout=60 + 20 * args.calls).stdout
    finally:
        for p in busy + procs:
            p.kill()
        _teardown()
    line = next((ln for ln in out.splitlines() if ln.startswith("ROWS ")), None)
    if line is None:
        print(f"service_lag: the client printed no result:\n{out}", file=sys.stderr)
        return 1
    rows = json.loads(line[5:])
    replies = sorted(r["reply_s"] for r in rows if r["reply_s"] is not None)
    print(json.dumps({
        "calls": len(rows), "busy": args.busy, "no_reply": len(rows) - len(replies),
        "reply_max_s": replies[-1] if replies else None,
        "reply_over_50ms": sum(x > 0.05 for x in replies),
        "reply_over_100ms": sum(x > 0.1 for x in replies), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
