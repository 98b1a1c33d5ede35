"""Figures with provenance: run a named command and write ``docs/results/<name>.json``.

Every figure the README or the docs state comes from one of these commands; the file records
the command, the commit (``-dirty`` when the work tree had uncommitted changes), the date, the
machine's core count and the wall time, beside the figures the command printed. Usage::

    scripts/results.sh NAME [NAME ...]     # or: .venv/bin/python scripts/results.py NAME

Names: ``emps`` (examples/emps/run.sh), ``emps_nested`` (the refit after the choice, judged on
the EMPS estimation record alone, examples/emps/nested.py), ``demo`` (scripts/demo.sh: its
summary.json), ``identify`` (``dvt-bench identify --json``),
``hours`` (``dvt-bench identify --hours 1 --json``), ``loop`` (``dvt-bench loop
--with-identifier --json``), ``model`` (``dvt-bench model --json``), ``false_effects`` (the
randomised clean plants of tests/test_false_effects.py), ``detector`` (the change detector's
false alarms on 8 clean simulated plants, ``scripts/detector_residual.py``),
``detector_starts`` (its first minutes after 150 starts, the same script), ``detector_first``
(its first minute, before the colour, after 400 starts, the same script),
``detector_carried`` (the first minute with a colour carried from an earlier run, 560 starts,
the same script), ``detector_carried_starts`` (its first 6 minutes, 120 starts), ``secant`` (the
compliant play's secant share on ``ident-backlash``, ``scripts/secant_sweep.py``), ``draws``
(hidden effects on fresh draws of the friction presets, ``scripts/effect_draws.py``),
``draws_other`` (the same on the plant's other presets), ``dry_step``
(the fit step's bias on a model with dry friction, ``scripts/dry_step_bias.py``), ``belt``
and ``belt_friction`` (random belt drives read by a sign-blind pulse counter, without and with a
Coulomb friction on the motor, ``scripts/belt_draws.py``), ``belt_window`` (the same drives,
every initial state from its record's first 10 samples), ``belt_lag`` / ``belt_lag_undeclared``
/ ``belt_lag_clean`` (the counter read through a 30-ms filter with and without the
``sensor_lag`` candidate, and the clean drives with it), ``belt_calibration`` (three of the
drives recorded and identified 30 times each: the reported std against the estimates' spread;
``belt_calibration_signed``: the same with the speed read with its sign),
``all``.

``scripts/results.sh table`` runs nothing: it writes the README's results table (between
``<!-- results:begin -->`` and ``<!-- results:end -->``) from the JSON files as they are
(``tests/test_readme_results.py`` checks that the README holds exactly that table).
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
    # what this script writes itself (the result files, the README's table) is not a change
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                            ":!docs/results", ":!README.md"], cwd=ROOT,
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
               "records_agree": rep.get("records_agree"),
               "test_spread": rep.get("test_spread")}
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


DETECTOR_ARGS = ["--seeds", *(str(s) for s in range(3100, 3108)), "--seconds", "1500", "--json"]
"""``detector``: 8 clean plants of 25 min (the figures of docs/loop.md, "Limits")."""
DETECTOR_STARTS_ARGS = ["--seeds", *(str(s) for s in range(4000, 4030)), "--seconds", "1800",
                        "--restart-s", "360", "--node-only", "--json"]
"""``detector_starts``: 30 clean plants of 30 min, a new detector every 6 min (150 starts: the
first minutes after a start, docs/loop.md "Limits")."""
DETECTOR_FIRST_ARGS = ["--seeds", *(str(s) for s in range(5100, 5120)), "--seconds", "1200",
                       "--restart-s", "60", "--node-only", "--json"]
"""``detector_first``: 20 clean plants of 20 min, a new detector every minute (400 starts, each
tested until its first colour: the first minute after a start, docs/loop.md "Limits")."""
DETECTOR_CARRIED_ARGS = ["--seeds", *(str(s) for s in range(5200, 5240)), "--seconds", "1200",
                         "--restart-s", "60", "--carry-s", "360", "--node-only", "--json"]
"""``detector_carried``: 40 other clean plants of 20 min; the first 6 min of each learn a colour
that every start on the rest carries in, a new detector every minute (560 starts: the first
minute with a carried colour, docs/loop.md "Limits")."""
DETECTOR_CARRIED_STARTS_ARGS = [
    "--seeds", *(str(s) for s in range(4100, 4130)), "--seconds", "1800", "--restart-s", "360",
    "--carry-s", "360", "--node-only", "--json"]
"""``detector_carried_starts``: 30 other clean plants of 30 min; the first 6 min of each learn a
colour that every start on the rest carries in, a new detector every 6 min (120 starts: the
first minute and minutes 1-5 with a carried colour, then the run's own)."""


def _script(*args: str) -> Callable[[], tuple[list[str], dict[str, Any]]]:
    """A named command that runs ``python ARGS`` in the project's venv (prints one JSON
    document)."""
    def run() -> tuple[list[str], dict[str, Any]]:
        cmd = ["python", *args]
        return cmd, _json_command([str(BIN / "python"), *args])
    return run


NAMES: dict[str, Callable[[], tuple[list[str], dict[str, Any]]]] = {
    "emps": emps,
    "emps_nested": _script("examples/emps/nested.py", "--json"),
    "demo": demo,
    "identify": _bench("identify", "--json"),
    "hours": _bench("identify", "--hours", "1", "--json"),
    "loop": _bench("loop", "--with-identifier", "--json"),
    "model": _bench("model", "--json"),
    "false_effects": false_effects,
    "compare": _bench("identify", "--compare", "ident-none-1=ident-none-val", "--json"),
    "detector": _script("scripts/detector_residual.py", *DETECTOR_ARGS),
    "detector_starts": _script("scripts/detector_residual.py", *DETECTOR_STARTS_ARGS),
    "detector_first": _script("scripts/detector_residual.py", *DETECTOR_FIRST_ARGS),
    "detector_carried": _script("scripts/detector_residual.py", *DETECTOR_CARRIED_ARGS),
    "detector_carried_starts": _script("scripts/detector_residual.py",
                                       *DETECTOR_CARRIED_STARTS_ARGS),
    "secant": _script("scripts/secant_sweep.py", "--json"),
    "draws": _script("scripts/effect_draws.py", "--json"),
    "draws_other": _script("scripts/effect_draws.py", "--presets", "other", "--json"),
    "dry_step": _script("scripts/dry_step_bias.py", "--json"),
    "first_refits": _script("scripts/first_refits.py", "--json"),
    "first_refits_1k": _script("scripts/first_refits.py", "--rate", "1000", "--json"),
    "belt": _script("scripts/belt_draws.py", "--json"),
    "belt_friction": _script("scripts/belt_draws.py", "--friction", "0.12", "--json"),
    "belt_window": _script("scripts/belt_draws.py", "--init-window", "10", "--json"),
    "belt_lag": _script("scripts/belt_draws.py", "--sensor-lag", "0.03", "--lag-candidate",
                        "--json"),
    "belt_lag_undeclared": _script("scripts/belt_draws.py", "--sensor-lag", "0.03", "--json"),
    "belt_lag_clean": _script("scripts/belt_draws.py", "--lag-candidate", "--json"),
    "belt_calibration": _script("scripts/belt_draws.py", "--seeds", "1", "4", "5",
                                "--realizations", "30", "--json"),
    "belt_calibration_signed": _script("scripts/belt_draws.py", "--seeds", "1", "4", "5",
                                       "--realizations", "30", "--signed", "--json"),
}


BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"


def _get(doc: Any, *path: str) -> Any:
    for k in path:
        if not isinstance(doc, dict) or k not in doc:
            return None
        doc = doc[k]
    return doc


def _n(v: Any, fmt: str = ".3g") -> str:
    return "?" if not isinstance(v, (int, float)) or isinstance(v, bool) else format(v, fmt)


def _pair(d: Any, fmt: str = ".2f") -> str:
    return " / ".join(_n(x, fmt) for x in d.values()) if isinstance(d, dict) else "?"


def _row_emps(f: dict[str, Any]) -> tuple[str, str]:
    rows = {r.get("label", ""): r for r in _get(f, "benchmark", "rows") or []}
    ours: dict[str, Any] = next((r for k, r in rows.items()
                                 if k.startswith("dvt-identify, chosen")), {})
    lin: dict[str, Any] = next((r for k, r in rows.items() if "linear reference" in k), {})
    parts = _get(f, "benchmark", "part_fits") or {}
    whole: dict[str, Any] = next((r for r in parts.get("rows", [])
                                  if str(r.get("part", "")).startswith("whole record")), {})
    lin_whole = ""
    if "linear_test_rms_mm" in whole:
        lw = whole["linear_test_rms_mm"]
        wins = lw <= whole.get("test_rms_mm", 0.0)
        lin_whole = (f" (our linear reference fitted on all of it {_n(lw)} mm"
                     + (": the simple model wins there)" if wins else ")"))
    spread = ("" if not parts else
              f"; the same structure fitted by the benchmark's criterion on parts of the "
              f"estimation record {_n(parts.get('test_min_mm'))}-"
              f"{_n(parts.get('test_max_mm'))} mm, on all of it "
              f"{_n(whole.get('test_rms_mm'))} mm{lin_whole}")
    ts = f.get("test_spread") or {}

    def halves(key: str) -> str:
        return " / ".join(_n(1000 * p["rmse"]["position"]) for p in ts.get(key, [])
                          if "rmse" in p)
    tool_halves = ("" if not ts.get("reference_parts") else
                   f"; refitted on each half (the tool's spread): {halves('parts')} mm, the "
                   f"linear reference {halves('reference_parts')} mm")
    return ("EMPS (real drive), test record, effects chosen on the estimation record only, "
            "the chosen model refitted on all of it",
            f"position RMSE {_n(ours.get('test_rms_mm'))} mm; our linear reference "
            f"{_n(lin.get('test_rms_mm'))} mm; published: LTI 5.53, NARX 5.17, best 2.64 mm"
            f"{spread}{tool_halves}")


def _row_identify(f: dict[str, Any]) -> tuple[str, str]:
    return ("`dvt-bench identify`: 38 s at 1 kHz, baseline / augment loop",
            f"{_n(f.get('baseline_seconds'), '.2f')} s / {_n(f.get('loop_seconds'), '.2f')} s "
            f"(targets {_n(_get(f, 'targets', 'baseline_seconds'))} / "
            f"{_n(_get(f, 'targets', 'loop_seconds'))} s); validation fit "
            f"{_pair(_get(f, 'fit', 'loop_validation_fit_percent'))} %")


def _row_hours(f: dict[str, Any]) -> tuple[str, str]:
    return ("an hour at 1 kHz (`dvt-bench identify --hours 1`)",
            f"{_n(f.get('loop_seconds'), '.0f')} s, peak {_n(f.get('peak_rss_mb'), '.0f')} MB "
            f"(targets {_n(_get(f, 'targets', 'loop_seconds'))} s, "
            f"{_n(_get(f, 'targets', 'peak_rss_mb'), '.0f')} MB)")


def _row_loop(f: dict[str, Any]) -> tuple[str, str]:
    return ("the live loop, friction step (`dvt-bench loop --with-identifier`)",
            f"{_n(f.get('rate_hz'), '.0f')} Hz, outcome {f.get('outcome', '?')}, "
            f"{_n(f.get('false_alarms'))} false alarms, {_n(f.get('model_dropped'))} samples "
            f"dropped, pushed {_n(f.get('push_after_change_s'))} s and restored "
            f"{_n(f.get('restored_s'))} s after the change, model node p99 "
            f"{_n(_get(f, 'model_latency_ms', 'p99'))} ms")


def _row_model(f: dict[str, Any]) -> tuple[str, str]:
    lat = _get(f, "latency_ms") or _get(f, "model_latency_ms") or {}
    return ("the model node alone (`dvt-bench model`)",
            f"latency p50 {_n(_get(lat, 'p50'))} ms, p99 {_n(_get(lat, 'p99'))} ms")


def _row_false(f: dict[str, Any]) -> tuple[str, str]:
    return ("randomised clean plants (inertias, dampings and bands drawn; 1 kHz and 62.5 Hz; "
            "three noise levels)",
            f"{_n(f.get('false_acceptances'))} of {_n(f.get('clean_plants'))} accept an "
            f"effect (95 % upper bound {_n(100 * f['upper_bound_95'], '.1f')} %)"
            if isinstance(f.get("upper_bound_95"), (int, float)) else "?")


def _row_compare(f: dict[str, Any]) -> tuple[str, str]:
    run = (_get(f, "runs") or [{}])[0]
    peer = run.get("peer") or {}
    if "not_run" in peer:
        return ("the peer (multiple shooting, CasADi + IPOPT), same data, same run",
                f"not run: {peer['not_run']}")
    return ("the peer (multiple shooting, CasADi + IPOPT) on `ident-none-1` -> `-val`, "
            "same run: ours / peer",
            f"validation fit {_pair(run.get('validation_fit_percent_free_run'))} % / "
            f"{_pair(peer.get('validation_fit_percent_free_run'))} %; M off "
            f"{_n(run.get('M_error_percent'), '.2f')} / {_n(peer.get('M_error_percent'), '.2f')} "
            f"%, D off {_n(run.get('D_error_percent'), '.2f')} / "
            f"{_n(peer.get('D_error_percent'), '.2f')} %; {_n(run.get('seconds'), '.1f')} s / "
            f"{_n(peer.get('fit_seconds'), '.0f')} s")


def _alarm_rate(r: dict[str, Any]) -> str:
    """A false-alarm row of ``scripts/detector_residual.py``: count, hours and bounds."""
    b = r.get("per_hour_95") or [None, None]
    return (f"{_n(r.get('alarms'))} in {_n(r.get('hours'), '.2f')} h (one-sided 95 % "
            f"{_n(b[0], '.2f')} to {_n(b[1], '.2f')}/h)")


def _row_detector(f: dict[str, Any]) -> tuple[str, str]:
    rows = {r.get("detector", ""): r for r in f.get("false_alarms") or []}
    colour: dict[str, Any] = next((r for k, r in rows.items() if k.endswith("with the colour")),
                                  {})
    arma: dict[str, Any] = next((r for k, r in rows.items() if k == "colour_s 0, learn_s 20"), {})
    return ("the change detector's false alarms on the clean simulated plant (node path, "
            f"{len(f.get('seeds') or [])} runs of {_n(f.get('seconds_each'), '.0f')} s)",
            f"with the colour {_alarm_rate(colour)}; each window's ARMA(1,1) "
            f"{_alarm_rate(arma)}; design "
            f"{_n(colour.get('design_per_hour'), '.2f')}/h")


def _row_detector_starts(f: dict[str, Any]) -> tuple[str, str]:
    rows = f.get("false_alarms") or []
    grow = next((r for r in rows if str(r.get("detector", "")).endswith("shorter history")), {})
    return ("the change detector's minutes 1-5 after a start (the colour on 60-240 s of "
            f"history), clean simulated plant ({_n(grow.get('starts'))} starts)",
            f"{_alarm_rate(grow)}; design 0.25/h")


def _row_detector_first(f: dict[str, Any]) -> tuple[str, str]:
    rows = f.get("false_alarms") or []
    first = next((r for r in rows if str(r.get("detector", "")).endswith("before the colour")),
                 {})
    return ("the change detector's first minute after a start (before the colour), clean "
            f"simulated plant ({_n(first.get('starts'))} starts)",
            f"{_alarm_rate(first)}; design 0.25/h")


def _row_detector_carried(f: dict[str, Any]) -> tuple[str, str]:
    rows = f.get("false_alarms") or []
    first = next((r for r in rows if "the first minute with the carried colour"
                  in str(r.get("detector", ""))), {})
    return ("the change detector's first minute after a start with the colour of an earlier "
            "run (`detector.colour_file`), clean simulated plant "
            f"({_n(first.get('starts'))} starts)", f"{_alarm_rate(first)}; design 0.25/h")


def _row_demo(f: dict[str, Any]) -> tuple[str, str]:
    ident = _get(f, "closed_loop", "identification") or {}
    acc = ident.get("accepted") if isinstance(ident, dict) else None
    ep = _get(f, "episode", "figures") or {}
    return ("the demo (`scripts/demo.sh`): closed loop, then the loop on its own",
            f"accepted {', '.join(acc) if isinstance(acc, list) and acc else '?'}; live residual "
            f"RMS {_pair(_get(f, 'closed_loop', 'live_residual_rms_before'), '.2f')} -> "
            f"{_pair(_get(f, 'closed_loop', 'live_residual_rms_after'), '.2f')} rad/s; "
            f"episode {ep.get('outcome', '?')}, restored {_n(ep.get('restored_s'))} s after "
            "the change")


def _row_belt(f: dict[str, Any]) -> tuple[str, str]:
    s = f.get("summary") or {}
    n = s.get("drives")
    lo, med = (s.get("test_fit_percent_min_median") or [None, None])[:2]
    return ("random belt drives read by a sign-blind pulse counter (300 + 200 samples at 50 Hz "
            "per record, every prior 1; `--select-on cv`, the last 200 samples as test)",
            f"named as drawn (the map, nothing else) {_n(s.get('named_as_drawn'))} of {_n(n)}; "
            f"test fit above 95 % {_n(s.get('test_fit_above_95'))} of {_n(n)} (min "
            f"{_n(lo, '.1f')} %, median {_n(med, '.1f')} %); better than the linear reference "
            f"{_n(s.get('better_than_reference'))} of {_n(n)}")


def _row_draws(f: dict[str, Any]) -> tuple[str, str]:
    rows = [r for r in f.get("rows") or [] if isinstance(r, dict)]
    presets = list(dict.fromkeys(str(r.get("preset")) for r in rows))
    named = [r for r in rows if r.get("named_as_drawn") is True]
    missed = [f"{r.get('preset')} {r.get('draw')}: "
              f"{', '.join(map(str, r.get('accepted') or [])) or 'nothing'}"
              for r in rows if r.get("named_as_drawn") is not True]
    rules = []
    if "stribeck" in presets:
        strib = [r for r in rows if r.get("preset") == "stribeck"]
        humps = sum(all(f"stribeck_friction@{m}" in (r.get("accepted") or [])
                        for m in _get(r, "plant", "stribeck") or {}) for r in strib)
        rules.append("the Stribeck curve by a dry friction on each member it acts on; its "
                     f"hump on every such member in {humps} of {len(strib)}")
    if "position_friction" in presets:
        rules.append("the friction that depends on position, which no candidate has, by "
                     "effects on its member only")
    return (f"hidden effects on fresh draws of the plant's presets ({', '.join(presets)}; "
            f"{len(rows) // max(len(presets), 1)} draws each), identified as `dvt-identify` "
            "does: the accepted effects name what the plant hides, where it acts, and nothing "
            "else" + (f" ({'; '.join(rules)})" if rules else ""),
            f"{len(named)} of {len(rows)}" + (f"; not: {'; '.join(missed)}" if missed else ""))


ROWS: dict[str, Callable[[dict[str, Any]], tuple[str, str]]] = {
    "emps": _row_emps, "identify": _row_identify, "hours": _row_hours, "loop": _row_loop,
    "model": _row_model, "false_effects": _row_false, "compare": _row_compare,
    "demo": _row_demo, "detector": _row_detector, "detector_starts": _row_detector_starts,
    "detector_first": _row_detector_first,
    "detector_carried": _row_detector_carried,
    "belt": _row_belt, "draws": _row_draws, "draws_other": _row_draws}


def table() -> str:
    """The README's results table from ``docs/results/*.json`` (missing: "not run yet")."""
    lines = ["| what | measured | command, commit, date |", "|---|---|---|"]
    for name, row in ROWS.items():
        path = OUT / f"{name}.json"
        if not path.exists():
            lines.append(f"| {name} | not run yet | `scripts/results.sh {name}` |")
            continue
        doc = json.loads(path.read_text())
        what, figure = row(doc.get("figures") or {})
        lines.append(f"| {what} | {figure} | [`{name}`](docs/results/{name}.json): "
                     f"{doc.get('commit', '?')}, {str(doc.get('date', '?'))[:10]} |")
    return "\n".join(lines)


def write_table(readme: Path = ROOT / "README.md") -> None:
    """Replace the README's table between :data:`BEGIN` and :data:`END` by :func:`table`."""
    text = readme.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"results: {readme} has no {BEGIN} ... {END} block")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    readme.write_text(f"{head}{BEGIN}\n{table()}\n{END}{tail}")


def main(argv: list[str]) -> int:
    if argv == ["table"]:
        write_table()
        return 0
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
    write_table()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
