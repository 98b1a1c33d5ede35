"""``dvt-bench``: benchmarks that print what they measured (not tests).

    dvt-bench model    --rate 1000 --seconds 10 --json   (model node fed at 1 kHz)
    dvt-bench link     --rate 1000 --seconds 30 --json   (plant -> driver -> recorder)
    dvt-bench loop     --json                            (change detection on the live chain)
    dvt-bench identify [--monte-carlo N] --json          (identifier speed / statistics)

Each target is a module of one of the three packages with ``main(argv) -> int``
(:mod:`dvt_model.bench`, :mod:`dvt_driver.run.bench`, :mod:`dvt_driver.system.bench_loop` with
:mod:`dvt_driver.system.bench_detect`, :mod:`dvt_identify.bench_identify`); the dispatch lives
in the integration layer (:mod:`dvt_driver.system`) because it reaches into both the driver and
the identifier. A target is imported only when asked for (each brings its own dependencies, ROS
for some).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

__all__ = ["TARGETS", "main"]

TARGETS = ("identify", "link", "loop", "model")
"""The benchmarks ``dvt-bench`` runs."""


def _entry(target: str) -> Callable[[list[str]], int]:
    """The ``main`` of ``target`` (imported now)."""
    if target == "model":
        from dvt_model.bench import main as model_main

        return model_main
    if target == "link":
        from dvt_driver.run.bench import main as link_main

        return link_main
    if target == "loop":
        from dvt_driver.system.bench_loop import main as loop_main

        return loop_main
    from dvt_identify.bench_identify import main as identify_main

    return identify_main


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``dvt-bench``; returns the exit status (2: no or an unknown target)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in TARGETS:
        print(__doc__, file=sys.stderr)
        print(f"dvt-bench: expected one of {list(TARGETS)}", file=sys.stderr)
        return 2
    return int(_entry(args[0])(args[1:]))


if __name__ == "__main__":
    sys.exit(main())
