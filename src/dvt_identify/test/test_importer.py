"""dvt-import: columns + mapping to a JointState bag, and its errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dvt_identify.data import read_jointstate_topics
from dvt_identify.errors import ImportDataError
from dvt_identify.importer import (
    ImportMapping,
    SignalMap,
    build_topics,
    derivative,
    describe_columns,
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


def test_csv_with_trailing_commas(tmp_path: Path) -> None:
    """Lines ending in a comma (an empty last cell) and an empty trailing header are ignored."""
    p = tmp_path / "log.csv"
    p.write_text("t,q,\n0.0,1.0,\n0.001,2.0,\n0.002,3.0,\n\n")
    cols = load_columns(p)
    assert sorted(cols) == ["q", "t"]
    assert cols["q"].tolist() == [1.0, 2.0, 3.0]


def test_csv_errors_name_line_and_column(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("t,q\n0.0,1.0\n0.001,x\n")
    with pytest.raises(ImportDataError, match=r"line 3, column 'q' \(column 2\): not a number"):
        load_columns(p)
    p.write_text("t,,q\n0,1,2\n")
    with pytest.raises(ImportDataError, match="column 2 has an empty name"):
        load_columns(p)
    p.write_text("t,q\n0,1,5\n")
    with pytest.raises(ImportDataError, match="line 2: 3 cells, header has 2"):
        load_columns(p)


def test_dt_without_time_column(tmp_path: Path) -> None:
    p = tmp_path / "notime.npz"
    np.savez(p, q=0.5 * T**2)
    mp = ImportMapping(None, (SignalMap("/x/js", "slide", "velocity", "d(q)"),), dt=1e-3)
    bag = import_columns(p, tmp_path / "bag", mp)
    js = read_jointstate_topics(bag, ["/x/js"])["/x/js"]
    assert js.stamps_ns[0] == 0 and js.stamps_ns[-1] == 999_000_000
    assert js.velocity is not None
    assert js.velocity[1:-1, 0] == pytest.approx(T[1:-1], abs=1e-9)


def test_second_derivative_and_range(tmp_path: Path) -> None:
    mp = ImportMapping("t", (SignalMap("/x/js", "slide", "effort", "d2(q)"),
                             SignalMap("/x/js", "slide", "position", "q")),
                       sample_range=(100, 900))
    topics = build_topics({"t": T, "q": 0.5 * T**2}, mp, "mem")
    js = topics["/x/js"]
    assert js.stamps_ns.size == 800 and js.stamps_ns[0] == 0  # the range starts the clock
    assert js.effort is not None and js.position is not None
    # the second derivative of t^2/2 is 1 everywhere inside the range (no end effects there)
    assert js.effort[:, 0] == pytest.approx(np.ones(800), abs=1e-6)
    assert js.position[0, 0] == pytest.approx(0.5 * T[100] ** 2)


def test_cli_dt_range_and_order(tmp_path: Path) -> None:
    p = tmp_path / "log.csv"
    p.write_text("q,\n" + "".join(f"{0.5 * (k * 1e-3) ** 2},\n" for k in range(500)))
    rc = main([str(p), "--out", str(tmp_path / "bag"), "--dt", "0.001", "--range", "10:410",
               "--signal", "/x/js", "slide", "velocity", "d(q)"])
    assert rc == 0
    js = read_jointstate_topics(tmp_path / "bag", ["/x/js"])["/x/js"]
    assert js.stamps_ns.size == 400
    rc = main([str(p), "--out", str(tmp_path / "bag2"), "--dt", "0.001",
               "--signal", "/x/js", "slide", "velocity", "d7(q)"])
    assert rc == 2


def test_mapping_time_and_dt_exclusive(tmp_path: Path) -> None:
    from dvt_identify.importer import parse_mapping

    sig = [{"topic": "/x", "joint": "j", "field": "position", "expr": "q"}]
    with pytest.raises(ImportDataError, match="exactly one of 'time'"):
        parse_mapping({"time": "t", "dt": 0.001, "signals": sig}, "m.yaml")
    with pytest.raises(ImportDataError, match="exactly one of 'time'"):
        parse_mapping({"signals": sig}, "m.yaml")
    with pytest.raises(ImportDataError, match="dt: expected a finite period > 0"):
        parse_mapping({"dt": -1, "signals": sig}, "m.yaml")
    with pytest.raises(ImportDataError, match="range: expected 0 <= start < stop"):
        parse_mapping({"time": "t", "range": "5:2", "signals": sig}, "m.yaml")


def _mat(tmp_path: Path) -> Path:
    """A MATLAB v5 file as MATLAB writes a logger's record: column vectors, a scalar gain, a
    two-channel matrix, a struct, and variables that are not columns (text, cells, complex,
    empty)."""
    from scipy.io import savemat

    p = tmp_path / "rec.mat"
    savemat(p, {"t": T[:, None], "qm": (0.5 * T ** 2)[:, None], "gtau": 35.0,
                "y": np.column_stack([np.sin(T), np.cos(T)]),
                "meta": {"kv": 2.5, "ref": {"qg": T[None, :]}},
                "note": "bench 3", "cells": np.array([T[:2], "x"], dtype=object),
                "z": T + 1j, "empty": np.zeros((0, 0))})
    return p


def _mat73(tmp_path: Path) -> Path:
    """The same record as :func:`_mat` in MATLAB's v7.3 layout: HDF5 behind a 512-byte MATLAB
    header, each array stored with its dimensions reversed and its ``MATLAB_class``, structs as
    groups, text as UTF-16 codes, MATLAB's ``#refs#`` store."""
    import h5py

    p = tmp_path / "rec73.mat"
    with h5py.File(p, "w", userblock_size=512) as f:
        def put(group: h5py.Group, name: str, value: object, cls: str = "double") -> None:
            group.create_dataset(name, data=np.asarray(value).T).attrs["MATLAB_class"] = (
                np.bytes_(cls))

        def struct(group: h5py.Group, name: str) -> h5py.Group:
            g = group.create_group(name)
            g.attrs["MATLAB_class"] = np.bytes_("struct")
            return g

        put(f, "t", T[:, None])
        put(f, "qm", (0.5 * T ** 2)[:, None])
        put(f, "gtau", [[35.0]])
        put(f, "y", np.column_stack([np.sin(T), np.cos(T)]))
        meta = struct(f, "meta")
        put(meta, "kv", [[2.5]])
        put(struct(meta, "ref"), "qg", T[None, :])
        put(f, "note", np.frombuffer("bench 3".encode("utf-16-le"), np.uint16)[None, :], "char")
        f.create_group("#refs#").create_dataset("a", data=np.zeros(2))
    with p.open("r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, HDF5 schema 1.00 .".ljust(124)
                 + b"\x00\x02IM")
    return p


@pytest.mark.parametrize("write", [_mat, _mat73], ids=["v5", "v7.3"])
def test_mat_variables_are_columns(tmp_path: Path, write: Any) -> None:
    """MATLAB vectors of either orientation are columns, 1 x 1 a scalar, a matrix one column per
    channel (``y.1``, ``y.2``), a struct's fields ``meta.kv``; text, cells and complex are not;
    the v7.3 (HDF5) layout gives the same columns as v5."""
    cols = load_columns(write(tmp_path))
    assert sorted(cols) == ["gtau", "meta.kv", "meta.ref.qg", "qm", "t", "y.1", "y.2"]
    assert cols["t"].shape == (T.size,) and cols["meta.ref.qg"] == pytest.approx(T)
    assert cols["gtau"].shape == () and float(cols["gtau"]) == 35.0
    assert cols["y.2"] == pytest.approx(np.cos(T)) and cols["y.1"] == pytest.approx(np.sin(T))


def test_npz_arrays_of_matlab_shapes_are_columns(tmp_path: Path) -> None:
    """An NPZ ``N x 1`` array is a column; channels x samples run along the longer side."""
    np.savez(tmp_path / "rows.npz", t=T, y=np.vstack([T, 2 * T]), q=T[:, None])
    npz = load_columns(tmp_path / "rows.npz")
    assert npz["y.2"] == pytest.approx(2 * T) and npz["q"].shape == (T.size,)


def test_mat_to_bag_through_the_cli(tmp_path: Path) -> None:
    """``dvt-import rec.mat`` with a struct field as a factor writes the bag as from NPZ."""
    out = tmp_path / "bag"
    assert main([str(_mat(tmp_path)), "--time", "t", "--out", str(out),
                 "--signal", "/x/js", "s", "position", "qm",
                 "--signal", "/x/drive", "s", "effort", "y.1 * gtau / meta.kv"]) == 0
    back = read_jointstate_topics(out, ["/x/js", "/x/drive"])
    assert back["/x/drive"].effort is not None and back["/x/js"].position is not None
    assert back["/x/drive"].effort[:, 0] == pytest.approx(np.sin(T) * 35.0 / 2.5)
    assert back["/x/js"].position[:, 0] == pytest.approx(0.5 * T ** 2)


def test_mat_errors_name_the_file(tmp_path: Path) -> None:
    """A v7.3 header with no readable HDF5 behind it, and a file that is no MATLAB file, name the
    file; a missing column lists the columns the file has."""
    v73 = tmp_path / "big.mat"
    v73.write_bytes(b"MATLAB 7.3 MAT-file".ljust(124) + b"\x00\x02IM" + bytes(600))
    with pytest.raises(ImportDataError, match=r"big\.mat: cannot read MATLAB v7\.3 \(HDF5\) file"):
        load_columns(v73)
    broken = tmp_path / "broken.mat"
    broken.write_bytes(b"not a mat file" * 20)
    with pytest.raises(ImportDataError, match=r"broken\.mat: cannot read MATLAB file"):
        load_columns(broken)
    with pytest.raises(ImportDataError, match=r"column 'note' not found \(columns: gtau, "
                                              r"meta\.kv, meta\.ref\.qg, qm, t, y\.1, y\.2\)"):
        import_columns(_mat(tmp_path), tmp_path / "bag", _mapping(("/x", "j", "effort", "note")))


def test_list_shows_the_columns_and_writes_nothing(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """``--list`` prints each column (a scalar's value; a column's length and range, a time
    column's step) and needs no ``--out``; without either, the command says what is missing."""
    lines = describe_columns({"t": T, "gtau": np.float64(35.0), "q": np.r_[np.nan, T[1:]]})
    assert lines[0].split() == ["gtau", "scalar", "35"]
    assert "1000 samples, 0.001 .. 0.999, 1 non-finite" in lines[1] and "time" not in lines[1]
    assert "1000 samples, 0 .. 0.999, increasing: mean step 0.001" in lines[2]
    assert main([str(_mat(tmp_path)), "--list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("rec.mat: 7 columns")
    assert [ln.split()[0] for ln in out[1:]] == ["gtau", "meta.kv", "meta.ref.qg", "qm", "t",
                                                 "y.1", "y.2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.mat"]
    with pytest.raises(SystemExit) as exit_:
        main([str(_mat(tmp_path)), "--time", "t"])
    assert exit_.value.code == 2 and "--list" in capsys.readouterr().err
    assert main([str(tmp_path / "none.mat"), "--list"]) == 2
    assert "none.mat: file not found" in capsys.readouterr().err
