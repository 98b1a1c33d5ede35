"""The progress line: drawn in place on a terminal, nothing when the stream is not one; used by
``recover`` (``dvt-bag recover``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dvt_model.contract import CURRENT_NAMES, CURRENTS, JOINT_STATES, SPEED_NAMES
from dvt_model.progress import CLEAR, ProgressLine, fraction
from dvt_model.recording import BagRecorder, joint_state_cdr, recover

JS = "sensor_msgs/msg/JointState"
T0 = 1_700_000_000_000_000_000


class FakeStream:
    """A stream that says whether it is a terminal and keeps what is written."""

    def __init__(self, tty: bool) -> None:
        self.tty = tty
        self.text = ""
        self.flushes = 0

    def write(self, text: str) -> int:
        self.text += text
        return len(text)

    def flush(self) -> None:
        self.flushes += 1

    def isatty(self) -> bool:
        return self.tty


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_silent_when_not_a_terminal() -> None:
    s = FakeStream(tty=False)
    line = ProgressLine(s, "[x] ", elapsed=True)
    assert not line.active
    line.update("round 1", force=True)
    line("round 2")
    line.note("accepted")
    line.close()
    assert s.text == "" and s.flushes == 0


def test_one_line_rewritten_in_place_on_a_terminal() -> None:
    s, clock = FakeStream(tty=True), Clock()
    line = ProgressLine(s, "[x] ", clock=clock, width=40)
    assert line.active
    line.update("round 1: scoring 3/20")
    assert s.text == CLEAR + "[x] round 1: scoring 3/20"
    assert "\n" not in s.text
    clock.now += 0.01
    line.update("round 1: scoring 4/20")  # within min_interval: not redrawn
    assert s.text.count(CLEAR) == 1
    clock.now += 0.2
    line.update("round 1: scoring 5/20")
    assert s.text.endswith(CLEAR + "[x] round 1: scoring 5/20")
    line.update("refit 1/2", force=True)
    assert s.text.endswith(CLEAR + "[x] refit 1/2")
    line.close()
    assert s.text.endswith(CLEAR) and "\n" not in s.text


def test_notes_stay_and_the_status_is_redrawn_under_them() -> None:
    s, clock = FakeStream(tty=True), Clock()
    line = ProgressLine(s, clock=clock, width=80)
    line.update("scoring")
    line.note("round 1: ACCEPTED coulomb")
    assert s.text == CLEAR + "scoring" + CLEAR + "round 1: ACCEPTED coulomb\n" + CLEAR + "scoring"
    line.close()


def test_long_text_cut_to_the_terminal_width_and_elapsed_time() -> None:
    s, clock = FakeStream(tty=True), Clock()
    with ProgressLine(s, "p: ", elapsed=True, clock=clock, width=50) as line:
        clock.now += 12.34
        line.update("a very long message\nwith a newline " + "x" * 100)
        shown = s.text.removeprefix(CLEAR)
        assert shown.startswith("p:  12.3 s  a very long message with")
        assert len(shown) == 49 and shown.endswith("…")
    assert s.text.endswith(CLEAR)  # closed by the context manager


def test_fraction() -> None:
    assert fraction(3, 20) == "3/20 (15 %)"
    assert fraction(0, 0) == "0/0"


def _killed_bag(path: Path, n: int) -> Path:
    """A recording cut off like after a SIGKILL (no summary, no metadata.yaml)."""
    rec = BagRecorder(path, {JOINT_STATES: JS, CURRENTS: JS}, fsync=False, flush_period=0.0)
    for i in range(n):
        st = T0 + i * 1_000_000
        rec.write(JOINT_STATES, joint_state_cdr(st, SPEED_NAMES, velocity=[i, -i]), st)
        rec.write(CURRENTS, joint_state_cdr(st, CURRENT_NAMES, effort=[i, 0, 0, 0]), st)
    rec.flush()
    data = (path / f"{path.name}.mcap").read_bytes()
    rec.close()
    cut = path.parent / f"{path.name}-killed"
    cut.mkdir()
    (cut / "run.mcap").write_bytes(data)
    return cut


@pytest.mark.parametrize("tty", [True, False])
def test_recover_shows_progress_only_on_a_terminal(tmp_path: Path, tty: bool) -> None:
    bag = _killed_bag(tmp_path / "run", 2500)  # 5000 messages: two updates
    s = FakeStream(tty)
    result = recover(bag, progress=ProgressLine(s, "dvt-bag recover: ", min_interval=0.0))
    assert result.total == 5000
    if tty:
        assert "dvt-bag recover: run.mcap: read " in s.text and "4000 messages" in s.text
        assert s.text.endswith(CLEAR)  # cleared before returning
        assert "\n" not in s.text
    else:
        assert s.text == ""


def test_recover_is_quiet_by_default_when_stderr_is_no_terminal(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _killed_bag(tmp_path / "run", 1200)
    assert recover(bag).total == 2400
    assert capsys.readouterr().err == ""


def test_as_a_context_manager_it_guards_stderr(monkeypatch: pytest.MonkeyPatch) -> None:
    """Other writes to stderr (a warning) clear the status line first and it is redrawn under
    them; stderr is restored on exit."""
    import sys

    s = FakeStream(tty=True)
    monkeypatch.setattr(sys, "stderr", s)
    with ProgressLine.stderr("p: ", elapsed=False) as line:
        assert sys.stderr is not s
        line.update("reading")
        print("warning: a gap", file=sys.stderr)
        assert s.text == CLEAR + "p: reading" + CLEAR + "warning: a gap" + "\n" + CLEAR + "p: reading"
    assert sys.stderr is s and s.text.endswith(CLEAR)


def test_not_a_terminal_leaves_stderr_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    s = FakeStream(tty=False)
    monkeypatch.setattr(sys, "stderr", s)
    with ProgressLine.stderr("p: ") as line:
        assert sys.stderr is s
        line.update("reading")
        print("warning: a gap", file=sys.stderr)
    assert s.text == "warning: a gap\n"
