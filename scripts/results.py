"""Figures with provenance: run a named command and write ``docs/results/<name>.json``.

Every figure the README or the docs state comes from one of these commands; the file records
the command, the commit (``-dirty`` when the work tree had uncommitted changes), the date, the
machine's core count and the wall time, beside the figures the command printed. Usage::

    scripts/results.sh NAME [NAME ...]     # or: .venv/bin/python scripts/results.py NAME

Names: ``emps`` (examples/emps/run.sh), ``demo`` (scripts/demo.sh: its summary.json),
``identify`` (``dvt-bench identify --json``),
``hours`` (``dvt-bench identify --hours 1 --json``), ``loop`` (``dvt-bench loop
--with-identifier --json``), ``model`` (``dvt-bench model --json``), ``false_effects`` (the
randomised clean plants of tests/test_false_effects.py), ``all``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BIN = ROOT / ".venv" / "bin"
OUT = ROOT / "docs" / "results"


def _commit() -> str:
    sha = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, text=True,
                         capture_output=True, check=False).stdout.strip() or "unknown"
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                           text=True, capture_output=True, check=False).stdout.strip()
    return sha + ("-dirty" if dirty else "")


def _json_command(cmd: list[str]) -> dict[str, Any]:
    """Run ``cmd`` (prints one JSON document on stdout) and return the document."""
    r = subprocess.run(cmd, cwd=ROOT, text=True, capture_output=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"results: {' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    try:
        return dict(json.loads(r.stdout))
    except ValueError as exc:
        raise SystemExit(f"results: {' '.join(cmd)} did not print JSON: {exc}") from exc


def emps() -> tuple[list[str], dict[str, Any]]:
    with tempfile.TemporaryDirectory() as d:
        cmd = ["bash", "examples/emps/run.sh", d]
        r = subprocess.run(cmd, cwd=ROOT, text=True, capture_output=True, check=False)
        if r.returncode != 0:
            raise SystemExit(f"results: emps failed:\n{r.stderr[-2000:]}")
        bench = json.loads((Path(d) / "benchmark.json").read_text())
        rep = json.loads((Path(d) / "report.json").read_text())
    figures = {"summary": r.stdout.strip().splitlines(), "benchmark": bench,
               "accepted": bench["accepted"], "linear_reference": rep.get("linear_reference"),
               "final_parameters": rep["final"]["parameters"],
               "records_agree": rep.get("records_agree")}
    return [*cmd[:2], "OUTDIR"], figures


def demo() -> tuple[list[str], dict[str, Any]]:
    with tempfile.TemporaryDirectory() as d:
        cmd = ["bash", "scripts/demo.sh", d]
        r = subprocess.run(cmd, cwd=ROOT, text=True, capture_output=True, check=False)
        if r.returncode != 0:
            raise SystemExit(f"results: demo failed:\n{r.stderr[-2000:]}")
        summary = json.loads((Path(d) / "summary.json").read_text())
    return [*cmd[:2], "OUTDIR"], summary


def _bench(*args: str) -> Callable[[], tuple[list[str], dict[str, Any]]]:
    def run() -> tuple[list[str], dict[str, Any]]:
        cmd = [str(BIN / "dvt-bench"), *args]
        return ["dvt-bench", *args], _json_command(cmd)
    return run


def false_effects() -> tuple[list[str], dict[str, Any]]:
    sys.path.insert(0, str(ROOT / "tests"))
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from false_effects_run import one_seed  # type: ignore[import-not-found]
    from scipy import stats

    with tempfile.TemporaryDirectory() as d, ProcessPoolExecutor(
            max_workers=2, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(one_seed, range(40), [d] * 40))
    n = len(rows)
    k = sum(1 for r in rows if r["accepted"])
    bound = 1.0 if k >= n else float(stats.beta.ppf(0.95, k + 1, n - k))
    return (["python", "scripts/results.py", "false_effects"],
            {"clean_plants": n, "false_acceptances": k, "upper_bound_95": bound,
             "rows": [{kk: v for kk, v in r.items() if kk != "factors"} for r in rows]})


NAMES: dict[str, Callable[[], tuple[list[str], dict[str, Any]]]] = {
    "emps": emps,
    "demo": demo,
    "identify": _bench("identify", "--json"),
    "hours": _bench("identify", "--hours", "1", "--json"),
    "loop": _bench("loop", "--with-identifier", "--json"),
    "model": _bench("model", "--json"),
    "false_effects": false_effects,
}


def main(argv: list[str]) -> int:
    names = list(NAMES) if argv == ["all"] else argv
    bad = [n for n in names if n not in NAMES]
    if not names or bad:
        print(f"usage: results.py NAME... (NAME one of {', '.join(NAMES)} or all); "
              f"unknown: {bad}", file=sys.stderr)
        return 2
    OUT.mkdir(parents=True, exist_ok=True)
    for name in names:
        t0 = time.monotonic()
        cmd, figures = NAMES[name]()
        doc = {"name": name, "command": " ".join(cmd), "commit": _commit(),
               "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
               "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                           "load_average": list(os.getloadavg())},
               "seconds": round(time.monotonic() - t0, 1), "figures": figures}
        path = OUT / f"{name}.json"
        path.write_text(json.dumps(doc, indent=2, default=float) + "\n")
        print(f"results: {path.relative_to(ROOT)} ({doc['seconds']} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
