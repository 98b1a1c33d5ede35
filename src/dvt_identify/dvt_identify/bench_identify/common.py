"""What the three benchmarks of ``dvt-bench identify`` share: the committed recordings, timing,
the machine's state and the output helpers (pure: no ROS)."""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dvt_identify.errors import BenchError
from dvt_model import BLAS_THREAD_VARIABLES
from dvt_model.errors import BagError
from dvt_model.recording import is_bag, read_run, read_run_info, read_truth, write_run

Array = NDArray[np.float64]
Log = Callable[[str], None]
"""Where progress lines go."""

DEFAULT_ESTIMATION = "ident-none-1"
"""The committed recording used for estimation by default (in the repository's ``bags/``)."""
DEFAULT_VALIDATION = "ident-none-2"
"""The committed recording used for validation by default."""

BLAS_ENV = BLAS_THREAD_VARIABLES
"""The BLAS thread-count variables (one list: :data:`dvt_model.BLAS_THREAD_VARIABLES`)."""


def blas_env() -> dict[str, str | None]:
    """The BLAS/OpenMP thread-count variables of this process's environment."""
    return {key: os.environ.get(key) for key in BLAS_ENV}


def quiet(_msg: str) -> None:
    """A :data:`Log` that prints nothing."""
    return None


def stderr_log(msg: str) -> None:
    """A :data:`Log` that prints on stderr."""
    print(f"[dvt-bench identify] {msg}", file=sys.stderr, flush=True)


def load_average() -> list[float]:
    """The 1-, 5- and 15-minute load averages (``[]`` where unknown)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover - not on Linux
        return []


# ---------------------------------------------------------------------------------------------
# Recordings


def default_bag(name: str, option: str) -> Path:
    """The committed recording ``bags/<name>``: looked up in the working directory and its
    parents, then beside this package's source tree.

    Raises:
        BenchError: not found (naming ``option``, which gives the bag explicitly).
    """
    here = Path(__file__).resolve()
    for root in (Path.cwd(), *Path.cwd().parents, *here.parents):
        cand = root / "bags" / name
        if is_bag(cand):
            return cand
    raise BenchError(f"{option}: no default recording bags/{name} found from {Path.cwd()} "
                     "(give the bag directories explicitly)")


def prefix_copy(src: Path, dst: Path, seconds: float | None) -> dict[str, Any]:
    """``src`` itself, or its first ``seconds`` [s] written to ``dst`` (the two sample topics
    only, :func:`dvt_model.recording.write_run`).

    Returns:
        ``{"path", "source", "samples", "seconds", "rate_hz", "write_seconds"}``.

    Raises:
        BenchError: ``seconds`` leaves fewer than 2 samples.
    """
    run = read_run(src)
    n_all = int(run.t.size)
    rate = (n_all - 1) / float(run.t[-1] - run.t[0]) if n_all > 1 else math.nan
    if seconds is None:
        return {"path": str(src), "source": str(src), "samples": n_all,
                "seconds": float(run.t[-1] - run.t[0]) if n_all else 0.0, "rate_hz": rate,
                "write_seconds": 0.0}
    n = int(np.searchsorted(run.t - run.t[0], seconds, side="right"))
    if n < 2:
        raise BenchError(f"--seconds: {seconds} s leaves {n} sample(s) of {src}")
    t0 = time.perf_counter()
    write_run(dst, run.stamps_ns[:n], run.speeds[:n], run.currents[:n], truth=read_truth(src))
    return {"path": str(dst), "source": str(src), "samples": n,
            "seconds": float(run.t[n - 1] - run.t[0]), "rate_hz": rate,
            "write_seconds": time.perf_counter() - t0}


def recording_info(path: Path) -> dict[str, Any]:
    """What ``run.yaml`` beside a committed recording says about how it was made (experiment,
    parameter set, hidden preset), or ``{}``."""
    try:
        data = read_run_info(path) or {}
    except BagError:
        return {}
    exp = data.get("experiment")
    return {k: v for k, v in (("experiment", exp.get("name") if isinstance(exp, dict) else exp),
                              ("params", data.get("params")), ("hidden", data.get("hidden")))
            if v is not None}


def timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """``fn()``, its wall time [s] and this process's CPU time [s]."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def fit_percent(fig: Any) -> dict[str, float]:
    """Output name -> fit [%] of a :class:`dvt_identify.metrics` figures object."""
    return {n: float(v) for n, v in zip(fig.output_names, fig.fit_percent, strict=True)}


def finite(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by ``None`` (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def num(v: Any, fmt: str = ".4g") -> str:
    """``v`` formatted with ``fmt`` when a float, ``-`` when ``None``."""
    return "-" if v is None else format(v, fmt) if isinstance(v, float) else str(v)
