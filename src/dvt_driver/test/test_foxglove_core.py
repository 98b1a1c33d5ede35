"""The Foxglove bridge's pure core: settings, conversion, decimation, band, states, alarms,
the shipped layout; and the offline bag -> MCAP conversion (no ROS graph)."""

from __future__ import annotations

import itertools
import json
import math
import struct
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from dvt_driver.run import foxglove_core as fc
from dvt_driver.run import foxglove_layout as fl
from dvt_model.contract import (
    CURRENTS,
    DIAGNOSTICS,
    IDENTIFY_RESULT,
    JOINT_STATES,
    MODEL_RESIDUAL,
)

ROOT = Path(__file__).resolve().parents[3]
LAYOUT = ROOT / "docs" / "foxglove" / "dvt-layout.json"


def _stamp(ns: int) -> SimpleNamespace:
    return SimpleNamespace(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _js(ns: int, names: list[str], velocity: Sequence[float] = (),
        effort: Sequence[float] = (), position: Sequence[float] = ()) -> SimpleNamespace:
    return SimpleNamespace(header=SimpleNamespace(stamp=_stamp(ns), frame_id=""), name=names, position=list(position),
              velocity=list(velocity), effort=list(effort))


def _diag(ns: int, *status: tuple[str, int, str, dict[str, str]], as_bytes: bool = True) -> SimpleNamespace:
    return SimpleNamespace(header=SimpleNamespace(stamp=_stamp(ns), frame_id=""), status=[
        SimpleNamespace(level=bytes([lvl]) if as_bytes else lvl, name=name, message=msg, hardware_id="dvt",
           values=[SimpleNamespace(key=k, value=v) for k, v in values.items()])
        for name, lvl, msg, values in status])


# ------------------------------------------------------------------------------ settings
def test_settings_defaults_and_errors_name_the_parameter() -> None:
    s = fc.parse_settings({})
    assert (s.host, s.port, s.rate_hz) == ("127.0.0.1", 8765, 100.0)
    assert fc.parse_settings({"rate_hz": 50}).rate_hz == 50.0  # an integer is fine
    for values, needle in (({"rate_hz": 0.0}, "rate_hz: 0.0"), ({"port": 70000}, "port"),
                           ({"host": " "}, "host"), ({"band_sigmas": math.nan}, "band_sigmas"),
                           ({"rate": 5}, "unknown parameter(s) ['rate']"),
                           ({"mcap": 3}, "mcap"), ({"port": True}, "port")):
        with pytest.raises(fc.BridgeSettingsError, match=needle.replace("(", r"\(")
                           .replace(")", r"\)").replace("[", r"\[").replace("]", r"\]")):
            fc.parse_settings(values)


# ------------------------------------------------------------------------------ channels
def test_channels_unique_with_object_schemas_and_converters() -> None:
    topics = [c.topic for c in fc.CHANNELS]
    assert len(topics) == len(set(topics)) == len(fc.CHANNEL_TOPICS)
    for c in fc.CHANNELS:
        assert c.schema["type"] == "object"
        json.dumps(c.schema)
        if c.source is not None:
            assert c.source == c.topic  # forwarded under the ROS name: paths work on bags
            assert c.schema_name in fc.CONVERTERS
    assert {c.topic for c in fc.CHANNELS if c.decimated} == {
        JOINT_STATES, CURRENTS, "/dvt/model/joint_states", MODEL_RESIDUAL}
    with pytest.raises(KeyError, match="/nope"):
        fc.channel("/nope")


def test_joint_state_json_keeps_fields_and_nulls_non_finite() -> None:
    msg = _js(1_500_000_123, ["sun_shaft", "carrier3"], velocity=[1.25, math.nan],
              position=[0.5, -0.25])
    d = fc.joint_state_json(msg)
    assert d == {"header": {"stamp": {"sec": 1, "nsec": 500_000_123}, "frame_id": ""},
                 "name": ["sun_shaft", "carrier3"], "position": [0.5, -0.25],
                 "velocity": [1.25, None], "effort": []}
    json.dumps(d, allow_nan=False)


def test_diagnostics_level_as_number_from_bytes_or_int() -> None:
    for as_bytes in (True, False):
        d = fc.diagnostic_array_json(_diag(5, ("dvt_driver", 2, "boom", {"gear": "1"}),
                                           as_bytes=as_bytes))
        assert d["status"][0]["level"] == 2
        assert d["status"][0]["values"] == [{"key": "gear", "value": "1"}]


def test_identify_json() -> None:
    assert fc.identify_json('{"final_fit_percent": {"a": 97.5}}') == {
        "final_fit_percent": {"a": 97.5}}
    assert "not JSON" in fc.identify_json("nope")["error"]
    assert "not a JSON object" in fc.identify_json("[1]")["error"]
    assert fc.identify_json('{"x": NaN}') == {"x": None}


def test_peek_stamp_little_and_big_endian_and_errors() -> None:
    le = b"\x00\x01\x00\x00" + struct.pack("<iI", 12, 345) + b"rest"
    be = b"\x00\x00\x00\x00" + struct.pack(">iI", 12, 345)
    assert fc.peek_stamp_ns(le) == fc.peek_stamp_ns(be) == 12_000_000_345
    with pytest.raises(ValueError, match="too short"):
        fc.peek_stamp_ns(b"\x00\x01\x00\x00")
    with pytest.raises(ValueError, match="encapsulation"):
        fc.peek_stamp_ns(b"\x00\x07\x00\x00" + bytes(8))


def test_peek_stamp_matches_a_serialized_joint_state() -> None:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    JointState = ts.types["sensor_msgs/msg/JointState"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    import numpy as np

    msg = JointState(header=Header(stamp=Time(sec=1_795_000_000, nanosec=999_999_999),
                                   frame_id="x"), name=["a"], position=np.zeros(0),
                     velocity=np.array([1.0]), effort=np.zeros(0))
    raw = bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
    assert fc.peek_stamp_ns(raw) == 1_795_000_000_999_999_999
    assert fc.joint_state_json(msg)["velocity"] == [1.0]  # rosbags messages convert too


# ---------------------------------------------------------------------------- decimation
def test_decimator_forwards_rate_hz_and_the_same_stamps_on_every_topic() -> None:
    dec = fc.Decimator(100.0)
    stamps = [1_000_000_000_000 + i * 1_000_000 for i in range(1000)]  # 1 s at 1 kHz
    a = [t for t in stamps if dec.due("a", t)]
    b = [t for t in stamps if dec.due("b", t)]
    assert len(a) == 100 and a == b
    assert all(y - x == 10_000_000 for x, y in itertools.pairwise(a))
    assert dec.due("a", stamps[0])  # the clock went back: forwarded anew
    with pytest.raises(ValueError, match="rate_hz"):
        fc.Decimator(0.0)


# --------------------------------------------------------------------------------- band
def test_residual_band_mean_sigma_window() -> None:
    band = fc.ResidualBand(window_s=1.0, sigmas=2.0)
    out: dict[str, Any] = {}
    for i, v in enumerate([1.0, -1.0, 1.0, -1.0]):
        out = band.add(i * 100_000_000, ["a", "b"], [v, None])
    assert out["mean"][0] == pytest.approx(0.0) and out["sigma"][0] == pytest.approx(1.0)
    assert out["lower"][0] == pytest.approx(-2.0) and out["upper"][0] == pytest.approx(2.0)
    assert out["mean"][1] is None and out["samples"] == 4
    out = band.add(2_000_000_000, ["a", "b"], [5.0, 1.0])  # the others left the window
    assert out["samples"] == 1 and out["mean"] == [5.0, 1.0] and out["sigma"] == [0.0, 0.0]
    assert out["header"]["stamp"] == {"sec": 2, "nsec": 0}


# ------------------------------------------------------------------------------- states
def test_state_tracker_gear_from_driver_diagnostics_and_bands_from_currents() -> None:
    st = fc.StateTracker(engaged_current=0.5, period_s=1.0)
    first = st.update_currents(0, ["drive_motor", "brake1", "brake2", "brake3"],
                               [1.0, 0.9, 0.1, None])
    assert first is not None and first["bands_engaged"] == [1, 0, 0]
    assert first["engaged_count"] == 1 and first["gear"] == -1
    assert st.update_currents(1_000_000, ["brake1"], [0.9]) is None  # unchanged, not due
    assert st.update_currents(1_000_000_000, ["brake1"], [0.9]) is not None  # period
    assert st.update_diagnostics(1_100_000_000, {"status": [{"name": "dvt_model",
                                                             "level": 0}]}) is None
    diag = fc.diagnostic_array_json(_diag(1_200_000_000, ("dvt_driver", 0, "active", {
        "gear": "2", "shifting": "True", "mode": "CURRENT", "lifecycle_state": "active",
        "controller_status": "0x05"})))
    msg = st.update_diagnostics(1_200_000_000, diag)
    assert msg is not None
    assert (msg["gear"], msg["shifting"], msg["mode"], msg["controller_status"]) == \
        (2, True, "CURRENT", 5)


def test_alarms_on_change_and_recovery() -> None:
    al = fc.AlarmTracker()

    def diag(level: int, message: str) -> dict[str, Any]:
        return fc.diagnostic_array_json(_diag(7, ("dvt_driver", level, message, {})))

    assert al.update(diag(0, "ok")) == []
    [warn] = al.update(diag(1, "sample rate low"))
    assert (warn["level"], warn["name"], warn["message"]) == (fc.LOG_WARNING, "dvt_driver",
                                                              "sample rate low")
    assert al.update(diag(1, "sample rate low")) == []
    [err] = al.update(diag(2, "link lost"))
    assert err["level"] == fc.LOG_ERROR
    [info] = al.update(diag(0, "ok"))
    assert info["level"] == fc.LOG_INFO and "recovered" in info["message"]


# ------------------------------------------------------------------------------- bridge
def test_bridge_routes_messages_to_channels() -> None:
    br = fc.Bridge(fc.parse_settings({"rate_hz": 10.0}))
    assert br.wants(MODEL_RESIDUAL, 0) and not br.wants(MODEL_RESIDUAL, 50_000_000)
    assert br.wants(DIAGNOSTICS, 0) and br.wants(DIAGNOSTICS, 1)  # never decimated
    assert not br.wants("/other", 0)
    out = br.handle(MODEL_RESIDUAL, _js(0, ["sun_shaft", "carrier3"], [0.1, 0.2]), 99)
    assert [t for t, _, _ in out] == [MODEL_RESIDUAL, fc.RESIDUAL_BAND]
    assert all(t == 0 for _, _, t in out)  # log time = sample stamp
    out = br.handle(IDENTIFY_RESULT, SimpleNamespace(data='{"pushed": {"node": "dvt_model"}}'), 42)
    assert out[1] == (fc.IDENTIFY, {"pushed": {"node": "dvt_model"}}, 42)
    assert set(br.last) == fc.LATCHED_CHANNELS  # kept for clients that subscribe later
    assert br.last[fc.IDENTIFY] == out[1]
    out = br.handle(DIAGNOSTICS, _diag(3, ("dvt_driver", 2, "FAULT", {"gear": "1"})), 0)
    assert {t for t, _, _ in out} == {DIAGNOSTICS, fc.STATE, fc.ALARMS}
    with pytest.raises(KeyError, match="/nope"):
        br.handle("/nope", None, 0)


# ------------------------------------------------------------------------------- layout
def test_shipped_layout_is_generated_and_names_only_advertised_channels() -> None:
    text = LAYOUT.read_text()
    assert text == fl.layout_json(), "regenerate: python -c 'from dvt_driver.run." \
        "foxglove_layout import layout_json; print(layout_json(), end=\"\")' > " + str(LAYOUT)
    layout = json.loads(text)
    topics = fl.layout_topics(layout)
    assert topics <= fc.CHANNEL_TOPICS, topics - fc.CHANNEL_TOPICS
    assert {JOINT_STATES, "/dvt/model/joint_states", MODEL_RESIDUAL, fc.RESIDUAL_BAND,
            CURRENTS, fc.STATE, DIAGNOSTICS} <= topics
    kinds = {pid.split("!")[0] for pid in layout["configById"]}
    assert {"Plot", "StateTransitions", "DiagnosticSummary", "RosOut"} <= kinds


def test_layout_topics_rejects_broken_layouts() -> None:
    with pytest.raises(ValueError, match="configById"):
        fl.layout_topics({})
    with pytest.raises(ValueError, match="without a config"):
        fl.layout_topics({"configById": {}, "layout": "Plot!x"})
    with pytest.raises(ValueError, match="not a topic"):
        fl.layout_topics({"configById": {"Plot!x": {"paths": [{"value": "nope"}]}},
                          "layout": "Plot!x"})


# ------------------------------------------------------------------------------ offline
def test_convert_bag_writes_every_channel_of_the_bag(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from dvt_driver.run.foxglove import convert_bag

    bag = ROOT / "bags" / "thesis-none"  # recorded with the model node
    if not (bag / "metadata.yaml").exists():
        pytest.fail(f"{bag}: committed bag missing (a broken checkout)")
    out = tmp_path / "x.mcap"
    counts = convert_bag(bag, out, fc.parse_settings({"rate_hz": 20.0}))  # bag: 62.5 Hz
    assert counts[JOINT_STATES] > 10 and abs(counts[CURRENTS] - counts[JOINT_STATES]) <= 2
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = {c.topic for c in summary.channels.values()}
        assert topics <= fc.CHANNEL_TOPICS
        assert {JOINT_STATES, CURRENTS, MODEL_RESIDUAL, fc.RESIDUAL_BAND, fc.STATE,
                DIAGNOSTICS} <= topics
        stamps = [json.loads(m.data)["header"]["stamp"]
                  for _, ch, m in reader.iter_messages(topics=[JOINT_STATES])]
    ns = [s["sec"] * 1_000_000_000 + s["nsec"] for s in stamps]
    rate = (len(ns) - 1) / ((ns[-1] - ns[0]) * 1e-9)
    assert 18.0 <= rate <= 20.5
    with pytest.raises(fc.BridgeSettingsError, match="exists"):
        convert_bag(bag, out, fc.parse_settings({}))
    with pytest.raises(fc.BridgeSettingsError, match="not a bag"):
        convert_bag(tmp_path, tmp_path / "y.mcap", fc.parse_settings({}))
