"""Every node takes ``--ros-args --params-file docs/params/<node>.yaml``: started with its
example file, each node reports every value of the file through the standard parameter
services (``-p`` after the file overrides it)."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from conftest import ROOT, Procs, wait_for
from dvt_model.contract import DRIVER_NODE, IDENTIFY_NODE, MODEL_NODE, RECORDER_NODE

pytestmark = pytest.mark.timeout(150)

PARAMS = ROOT / "docs" / "params"
FOXGLOVE_NODE = "dvt_foxglove"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _value(pv: Any) -> Any:
    """A ``rcl_interfaces/ParameterValue`` as a Python value."""
    from rcl_interfaces.msg import ParameterType as T

    return {T.PARAMETER_BOOL: lambda: pv.bool_value,
            T.PARAMETER_INTEGER: lambda: pv.integer_value,
            T.PARAMETER_DOUBLE: lambda: pv.double_value,
            T.PARAMETER_STRING: lambda: pv.string_value,
            T.PARAMETER_STRING_ARRAY: lambda: list(pv.string_array_value),
            T.PARAMETER_DOUBLE_ARRAY: lambda: list(pv.double_array_value),
            T.PARAMETER_INTEGER_ARRAY: lambda: list(pv.integer_array_value),
            T.PARAMETER_NOT_SET: lambda: None}[pv.type]()


CASES = [
    ("dvt_driver_node", DRIVER_NODE, "dvt_driver.yaml", {}),
    ("dvt_model_node", MODEL_NODE, "dvt_model.yaml", {}),
    ("dvt_identify_node", IDENTIFY_NODE, "dvt_identify.yaml", {}),
    ("dvt-recorder", RECORDER_NODE, "dvt_recorder.yaml", {"output": "<tmp>/run"}),
    ("dvt-foxglove", FOXGLOVE_NODE, "dvt_foxglove.yaml", {"port": "<port>"}),
]


def test_every_node_has_an_example_params_file() -> None:
    names = {p.name for p in PARAMS.glob("*.yaml")}
    assert names == {c[2] for c in CASES}
    for _, node, fname, _ in CASES:
        data = yaml.safe_load((PARAMS / fname).read_text())
        assert list(data) == [node], f"{fname}: top-level key must be the node name {node}"
        assert data[node]["ros__parameters"], fname


START_S = 60.0
"""Longest start-up of a node until its parameter services answer [s] (a few seconds on a quiet
machine; a node importing scipy/numba on two loaded cores takes tens of seconds)."""
ASK_EVERY_S = 10.0
"""A request unanswered this long is sent again [s] (requests are idempotent): a request or
reply lost while the two nodes' service routes are still being matched is not waited for
until the deadline."""


@pytest.mark.ros
@pytest.mark.parametrize(("exe", "node", "fname", "overrides"), CASES,
                         ids=[c[1] for c in CASES])
def test_node_takes_its_params_file(exe: str, node: str, fname: str,
                                    overrides: dict[str, str], procs: Procs,
                                    rclpy_context: Any, tmp_path: Path) -> None:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter_client import AsyncParameterClient

    path = PARAMS / fname
    expected: dict[str, Any] = dict(yaml.safe_load(path.read_text())[node]["ros__parameters"])
    extra: list[str] = []
    for name, value in overrides.items():
        v: Any = value.replace("<tmp>", str(tmp_path))
        if v == "<port>":
            v = _free_port()
        extra += ["-p", f"{name}:={v}"]
        expected[name] = v
    proc = procs.start(exe, "--ros-args", "--params-file", str(path), *extra)

    client_node = rclpy.create_node("params_check", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(client_node)
    try:
        client = AsyncParameterClient(client_node, node)

        deadline = time.monotonic() + START_S

        def ready() -> bool:
            assert proc.poll() is None, procs.log(proc)
            ex.spin_once(timeout_sec=0.05)
            return client.services_are_ready()

        wait_for(ready, START_S, f"{node}'s parameter services")
        future = client.get_parameters(list(expected))
        asked = time.monotonic()
        while not future.done():
            assert proc.poll() is None, procs.log(proc)
            assert time.monotonic() < deadline, (
                f"{node} did not answer get_parameters within {START_S:g} s of its start")
            if time.monotonic() - asked > ASK_EVERY_S:
                future = client.get_parameters(list(expected))
                asked = time.monotonic()
            ex.spin_once(timeout_sec=0.05)
        got = {n: _value(v) for n, v in zip(expected, future.result().values, strict=True)}
        for name, want in expected.items():
            have = got[name]
            if isinstance(want, float) or isinstance(have, float):
                assert have == pytest.approx(want), (fname, name, have, want)
            else:
                assert have == want, (fname, name, have, want)
    finally:
        ex.shutdown(timeout_sec=1.0)
        client_node.destroy_node()
    assert procs.stop(proc) in (0, -2, 130), procs.log(proc)
