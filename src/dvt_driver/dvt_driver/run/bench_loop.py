"""``dvt-bench loop``: the loop benchmark's entry point (:func:`dvt_driver.run.bench.loop_main`;
the benchmark itself is in :mod:`dvt_driver.run.bench`)."""

from __future__ import annotations

import sys

from dvt_driver.run.bench import loop_main as main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
