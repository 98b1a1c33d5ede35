"""Unit tests of ``dvt-bag`` (info, recover), also after a real SIGKILL of the writer."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from dvt_driver.recording import bagtool
from dvt_model import recording
from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATES, SPEED_NAMES
from dvt_model.recording import BagRecorder, bag_summary, joint_state_cdr

JS = "sensor_msgs/msg/JointState"
TOPICS = {JOINT_STATES: JS, CURRENTS: JS}
T0 = 1_700_000_000_000_000_000


def _sample(rec: BagRecorder, i: int) -> None:
    st = T0 + i * 1_000_000
    rec.write(JOINT_STATES,
              joint_state_cdr(st, SPEED_NAMES, velocity=[float(i), -float(i)]), st)
    rec.write(CURRENTS,
              joint_state_cdr(st, CURRENT_NAMES, effort=[i, 1.0, 2.0, 3.0]), st)


def _record(path: Path, n: int, **kw: object) -> BagRecorder:
    rec = BagRecorder(path, TOPICS, fsync=False, **kw)  # type: ignore[arg-type]
    for i in range(n):
        _sample(rec, i)
    return rec


_KILLED_WRITER = textwrap.dedent("""
    import os, signal, sys
    from dvt_model.contract import SPEED_NAMES
    from dvt_model.recording import BagRecorder, joint_state_cdr
    clock = [0.0]
    rec = BagRecorder(sys.argv[1], {"/dvt/joint_states": "sensor_msgs/msg/JointState"},
                      flush_period=0.5, clock=lambda: clock[0])
    for i in range(1000):
        st = 1_700_000_000_000_000_000 + i * 1_000_000
        clock[0] = i * 1e-3  # 1 kHz
        rec.write("/dvt/joint_states",
                  joint_state_cdr(st, SPEED_NAMES, velocity=[i, 0.0]), st)
        if rec.poll() or rec.message_count % 500 == 1:
            pass
    print(rec.message_count, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_sigkilled_writer_loses_at_most_one_flush_period(tmp_path: Path) -> None:
    """A real SIGKILL: everything older than one flush period (0.5 s = 500 samples) survives."""
    path = tmp_path / "killed"
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert int(proc.stdout.strip()) == 1000
    assert not (path / "metadata.yaml").exists()
    assert bagtool.main(["recover", str(path)]) == 0
    series = recording.read_topic_series(path, JOINT_STATES)
    n = series.stamps_ns.shape[0]
    assert 1000 - 501 <= n < 1000
    np.testing.assert_array_equal(series.velocity[:, 0], np.arange(n))


def test_bagtool_info_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with _record(tmp_path / "bag", 11):
        pass
    assert bagtool.main(["info", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert "/dvt/joint_states" in out and "11 msgs" in out and "1000.00 Hz" in out
    summary = bag_summary(tmp_path / "bag")
    assert summary.message_count == 22
    assert summary.duration == pytest.approx(0.010)

    assert bagtool.main(["recover", str(tmp_path / "bag")]) == 0
    assert "already readable" in capsys.readouterr().out

    assert bagtool.main(["recover", str(tmp_path / "nope")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dvt-bag: error:") and "nope" in err[0]

    (tmp_path / "bag" / "metadata.yaml").unlink()
    assert bagtool.main(["info", str(tmp_path / "bag")]) == 1
    assert "dvt-bag recover" in capsys.readouterr().err
    assert bagtool.main(["recover", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert "recovered 22 messages" in out
