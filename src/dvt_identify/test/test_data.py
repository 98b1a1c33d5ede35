"""Bag round trip, alignment by stamp, data checks and pre-processing."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from dvt_identify.bagload import check_excitation, load_segment
from dvt_identify.data import (
    Checks,
    DataWarning,
    JointStateSeries,
    SignalSpec,
    decimate,
    lowpass,
    make_segment,
    read_jointstate_topics,
    write_jointstate_bag,
)
from dvt_identify.errors import DataError

IN = [SignalSpec("current", "/a/currents", "effort", "motor")]
OUT = [SignalSpec("speed", "/a/joint_states", "velocity", "shaft")]


def _series(n: int = 400, dt_ns: int = 1_000_000, t0: int = 5 * 10**9
            ) -> dict[str, JointStateSeries]:
    stamps = t0 + dt_ns * np.arange(n, dtype=np.int64)
    t = (stamps - t0) * 1e-9
    cur = np.sin(2 * np.pi * 3 * t)
    vel = np.cos(2 * np.pi * 3 * t)
    return {
        "/a/joint_states": JointStateSeries(stamps, ("shaft", "other"),
                                            velocity=np.column_stack([vel, 2 * vel])),
        "/a/currents": JointStateSeries(stamps, ("motor", "brake"),
                                        effort=np.column_stack([cur, 0 * cur])),
        "/a/unknown": JointStateSeries(stamps[:10], ("z",), position=np.zeros((10, 1))),
    }


def _bag(tmp_path: Path, topics: dict[str, JointStateSeries], name: str = "bag") -> Path:
    return write_jointstate_bag(tmp_path / name, topics)


def test_roundtrip_and_segment(tmp_path: Path) -> None:
    topics = _series()
    bag = _bag(tmp_path, topics)
    back = read_jointstate_topics(bag, ["/a/joint_states", "/a/currents"])
    assert back["/a/joint_states"].names == ("shaft", "other")
    assert back["/a/joint_states"].velocity == pytest.approx(topics["/a/joint_states"].velocity)
    assert back["/a/currents"].position is None
    assert np.array_equal(back["/a/currents"].stamps_ns, topics["/a/currents"].stamps_ns)
    seg = load_segment(bag, IN, OUT)  # the unknown topic is ignored
    assert seg.u.shape == (400, 1) and seg.y.shape == (400, 1)
    assert seg.dt == pytest.approx(1e-3)
    assert seg.t[0] == 0.0
    assert seg.y[:, 0] == pytest.approx(topics["/a/joint_states"].velocity[:, 0])  # type: ignore


def test_alignment_drops_unmatched_samples_and_fills_short_gaps(tmp_path: Path) -> None:
    topics = _series()
    js = topics["/a/joint_states"]
    keep = np.ones(400, bool)
    keep[[100, 101]] = False  # two samples lost on one topic only
    assert js.velocity is not None
    topics["/a/joint_states"] = JointStateSeries(js.stamps_ns[keep], js.names,
                                                 velocity=js.velocity[keep])
    seg = load_segment(_bag(tmp_path, topics), IN, OUT)
    assert seg.n == 400
    assert "2 missing samples filled" in seg.notes[0]


@pytest.mark.parametrize("problem,match", [
    ("nan", r"/a/joint_states: no piece of at least 395 samples between the splits of the "
            r"recording: topic /a/joint_states: velocity\[shaft\] non-finite in 1 sample "
            r"\(first at t = 0.007000 s \(stamp 5007000000 ns, message 7\)\)"),
    ("order", r"no piece of at least 395 samples between the splits of the recording: topic "
              r"/a/currents: a stamp that does not increase \(first at message 50 \(repeats: "
              r"5049000000 ns after 5049000000 ns"),
    ("gap", r"/a/joint_states: no piece of at least 250 samples between the 1 gap\(s\) of more "
            r"than 3 missing samples: 0.05 s \(49 missing samples\) after t = 0.199000 s"),
    ("saturated", r"effort\[motor\] \(current\) is saturated"),
    ("short", r"too little data: 400 aligned samples"),
    ("constant", r"no excitation: every input is constant"),
    ("topic", r"topic /a/currents missing \(topics present: \['/a/joint_states'"),
    ("joint", r"joint 'motor' not in name list"),
])
def test_data_checks_name_bag_topic_and_problem(tmp_path: Path, problem: str,
                                                match: str) -> None:
    topics = _series()
    js, cu = topics["/a/joint_states"], topics["/a/currents"]
    assert js.velocity is not None and cu.effort is not None
    checks = Checks()
    inputs = IN
    if problem == "nan":  # salvaged (see test_data_segments) unless nothing long enough is left
        v = js.velocity.copy()
        v[7, 0] = np.nan
        topics["/a/joint_states"] = JointStateSeries(js.stamps_ns, js.names, velocity=v)
        checks = Checks(min_samples=395)  # pieces of 7 and 392 samples
    elif problem == "order":
        st = cu.stamps_ns.copy()
        st[51] = st[49]
        topics["/a/currents"] = JointStateSeries(st, cu.names, effort=cu.effort)
        checks = Checks(min_samples=395)  # pieces of 50 and 350 samples
    elif problem == "gap":
        keep = np.ones(400, bool)
        keep[200:249] = False
        topics["/a/joint_states"] = JointStateSeries(js.stamps_ns[keep], js.names,
                                                     velocity=js.velocity[keep])
        checks = Checks(min_samples=250)  # both pieces (200 and 151 samples) too short
    elif problem == "saturated":
        inputs = [SignalSpec("current", "/a/currents", "effort", "motor",
                             saturation=(-0.9, 0.9))]
    elif problem == "short":
        checks = Checks(min_samples=1000)
    elif problem == "constant":
        topics["/a/currents"] = JointStateSeries(cu.stamps_ns, cu.names,
                                                 effort=np.ones_like(cu.effort))
    elif problem == "topic":
        del topics["/a/currents"]
    elif problem == "joint":
        topics["/a/currents"] = JointStateSeries(cu.stamps_ns, ("m2", "brake"),
                                                 effort=cu.effort)
    bag = _bag(tmp_path, topics)
    with pytest.raises(DataError, match=match) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        load_segment(bag, inputs, OUT, checks)
    assert str(bag) in str(info.value)


def test_unreadable_bag_and_existing_output(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="bag not found"):
        load_segment(tmp_path / "nope", IN, OUT)
    (tmp_path / "junk").mkdir()
    with pytest.raises(DataError, match="junk: not a readable bag: metadata.yaml is missing"):
        load_segment(tmp_path / "junk", IN, OUT)
    (tmp_path / "junk" / "metadata.yaml").write_text("not: [a bag")
    with pytest.raises(DataError, match="junk: cannot open bag"):
        load_segment(tmp_path / "junk", IN, OUT)
    bag = _bag(tmp_path, _series())
    with pytest.raises(DataError, match="already exists"):
        write_jointstate_bag(bag, _series())


def test_excitation_check_over_estimation_set() -> None:
    t = np.arange(300) * 0.01
    u = np.column_stack([np.sin(t), np.zeros(300)])
    seg = make_segment("b1", t, u, np.cos(t), ["motor", "brake"], ["w"])
    with pytest.raises(DataError, match="input brake has no excitation"):
        check_excitation([seg], Checks(), {"brake": "/dvt/currents effort[brake1]"})


def test_lowpass_and_decimate() -> None:
    t = np.arange(2000) * 1e-3
    x = np.sin(2 * np.pi * 2 * t) + 0.5 * np.sin(2 * np.pi * 200 * t)
    seg = make_segment("b", t, x, x, ["u"], ["y"])
    lp = lowpass(seg, 20.0, 4, True)
    assert np.std(lp.y[200:-200, 0] - np.sin(2 * np.pi * 2 * t[200:-200])) < 0.01
    dec = decimate(seg, 5)
    assert dec.dt == pytest.approx(5e-3) and dec.n == 400
    assert "decimated by 5" in dec.notes[-1]
    with pytest.raises(DataError, match="cutoff"):
        lowpass(seg, 600.0)
