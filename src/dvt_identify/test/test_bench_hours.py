"""``dvt-bench identify --hours``: the identification's memory grows little with the
recording's length (runs read one at a time and kept at the fit rate, the fit and the drift
check folded segment by segment, the linear reference on at most 24 000 samples, the model's
span for the candidate scores kept by its parts).

Two recordings of the same plant in runs of one minute, 2 and 8 minutes long, each identified
(baseline, drift check and augment loop) in a process of its own: the 8-minute one's peak
resident memory exceeds the 2-minute one's by less than :data:`MARGIN_MB` (measured: 282 ->
357 MB). What still grows is what an identification holds whole: the runs at the fit rate, the
fitted residual and simulated outputs, the model's span for the candidate scores (together
about 12 MB per minute of 1 kHz data). With the fit's Jacobian held whole instead (up to
48 MB of it, :data:`dvt_identify.streamls.DENSE_BYTES` before), the same two recordings gave
305 -> 670 MB.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dvt_identify.bench_identify import hours

pytestmark = pytest.mark.slow

MARGIN_MB = 100.0
"""Largest growth of the peak resident memory from 2 to 8 minutes of 1 kHz data [MB]."""


def _identify(info: dict[str, object]) -> dict[str, object]:
    cmd = [sys.executable, "-m", "dvt_identify.bench_identify.hours", "identify",
           json.dumps({"est": info["estimation"], "val": [info["validation"]]})]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=True)
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def test_peak_memory_does_not_grow_with_the_recording(tmp_path: Path) -> None:
    short = hours.generate(tmp_path / "short", 2 / 60, run_minutes=1.0)
    long = hours.generate(tmp_path / "long", 8 / 60, run_minutes=1.0)
    a, b = _identify(short), _identify(long)
    assert b["fit_samples"] > 3.5 * float(a["fit_samples"])  # four times the data
    grown = float(b["peak_rss_mb"]) - float(a["peak_rss_mb"])
    print(f"peak RSS {a['peak_rss_mb']:.0f} MB (2 min) -> {b['peak_rss_mb']:.0f} MB (8 min): "
          f"{grown:+.0f} MB")
    assert grown < MARGIN_MB, (a["peak_rss_mb"], b["peak_rss_mb"])
