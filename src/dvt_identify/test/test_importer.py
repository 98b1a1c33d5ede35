"""dvt-import: columns + mapping to a JointState bag, and its errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvt_identify.data import read_jointstate_topics
from dvt_identify.errors import ImportDataError
from dvt_identify.importer import (
    ImportMapping,
    SignalMap,
    build_topics,
    derivative,
    evaluate,
    import_columns,
    load_columns,
    main,
)

T = np.arange(1000) * 1e-3


def _npz(tmp_path: Path, **over: object) -> Path:
    cols: dict[str, object] = {"t": T, "q": 0.5 * T ** 2, "v_cmd": np.sin(T), "k": np.float64(3.0)}
    cols.update(over)
    p = tmp_path / "rec.npz"
    np.savez(p, **cols)  # type: ignore[arg-type]
    return p


def _mapping(*sigs: tuple[str, str, str, str], cutoff: float | None = None) -> ImportMapping:
    return ImportMapping("t", tuple(SignalMap(*s) for s in sigs), cutoff_hz=cutoff)


def test_npz_to_bag_roundtrip(tmp_path: Path) -> None:
    mp = _mapping(("/x/joint_states", "slide", "position", "q"),
                  ("/x/joint_states", "slide", "velocity", "d(q)"),
                  ("/x/drive", "slide", "effort", "v_cmd * k"))
    bag = import_columns(_npz(tmp_path), tmp_path / "bag", mp)
    back = read_jointstate_topics(bag, ["/x/joint_states", "/x/drive"])
    js, dr = back["/x/joint_states"], back["/x/drive"]
    assert js.names == ("slide",) and dr.effort is not None and js.velocity is not None
    assert np.array_equal(js.stamps_ns, dr.stamps_ns)
    assert js.stamps_ns[1] - js.stamps_ns[0] == 1_000_000
    assert dr.effort[:, 0] == pytest.approx(3.0 * np.sin(T))
    assert js.velocity[1:-1, 0] == pytest.approx(T[1:-1], abs=1e-9)  # d(t^2/2) = t
    assert dr.position is None


def test_filtered_derivative_is_zero_phase() -> None:
    t = np.arange(4000) * 1e-3
    x = np.sin(2 * np.pi * 2 * t) + 1e-4 * np.random.default_rng(0).normal(size=t.size)
    d = derivative(x, t, 100.0, 4)
    want = 2 * np.pi * 2 * np.cos(2 * np.pi * 2 * t)
    assert np.max(np.abs(d - want)[200:-200]) < 0.05 * 4 * np.pi


def test_csv_and_expressions(tmp_path: Path) -> None:
    p = tmp_path / "rec.csv"
    p.write_text("t,a,b\n0,1,2\n0.1,2,4\n0.2,3,8\n")
    cols = load_columns(p)
    mp = _mapping(("/x", "j", "effort", "a"))
    assert evaluate("a * 2 / b", cols, cols["t"], mp, "src") == pytest.approx([1.0, 1.0, 0.75])


@pytest.mark.parametrize("over,sig,match", [
    ({}, ("/x", "j", "effort", "nope"), r"column 'nope' not found \(columns: k, q, t, v_cmd\)"),
    ({"q": np.where(T > 0.5, np.nan, T)}, ("/x", "j", "position", "q"),
     r"column 'q': value nan at row 501"),
    ({"t": np.r_[T[:10], T[9], T[11:]]}, ("/x", "j", "position", "q"),
     r"time column 't' not strictly increasing at row 10"),
    ({}, ("/x", "j", "speed", "q"), r"field 'speed' not one of position, velocity, effort"),
    ({}, ("/x", "j", "effort", "q +"), r"expression 'q \+'"),
    ({"q": T[:10]}, ("/x", "j", "position", "q"), r"column 'q': length 10, time column has 1000"),
])
def test_import_errors(tmp_path: Path, over: dict[str, object], sig: tuple[str, str, str, str],
                       match: str) -> None:
    with pytest.raises(ImportDataError, match=match):
        import_columns(_npz(tmp_path, **over), tmp_path / "bag", _mapping(sig))


def test_field_missing_for_some_joints(tmp_path: Path) -> None:
    cols = load_columns(_npz(tmp_path))
    mp = _mapping(("/x", "a", "position", "q"), ("/x", "b", "position", "q"),
                  ("/x", "a", "velocity", "d(q)"))
    with pytest.raises(ImportDataError, match="field velocity given for a but not for b"):
        build_topics(cols, mp, "src")


def test_cli_mapping_file_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = _npz(tmp_path)
    m = tmp_path / "map.yaml"
    m.write_text("time: t\nderivative: {cutoff_hz: 50}\nsignals:\n"
                 "  - {topic: /x/js, joint: s, field: velocity, expr: d(q)}\n")
    assert main([str(src), "--mapping", str(m), "--out", str(tmp_path / "b1"),
                 "--signal", "/x/drive", "s", "effort", "v_cmd"]) == 0
    assert (tmp_path / "b1" / "metadata.yaml").exists()
    # existing output, then --force
    assert main([str(src), "--mapping", str(m), "--out", str(tmp_path / "b1")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("dvt-import: error: ") and "already exists" in err[-1]
    assert main([str(src), "--mapping", str(m), "--out", str(tmp_path / "b1"), "--force"]) == 0
    assert main([str(tmp_path / "missing.npz"), "--time", "t", "--signal", "/x", "a", "effort",
                 "q", "--out", str(tmp_path / "b2")]) == 2
    assert "file not found" in capsys.readouterr().err
