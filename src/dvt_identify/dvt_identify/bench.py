"""``dvt-bench``: benchmarks that print what they measured (not tests).

    dvt-bench model    --rate 1000 --seconds 10 --json   (model node fed at 1 kHz)
    dvt-bench link     --rate 1000 --seconds 30 --json   (plant -> driver -> recorder)
    dvt-bench loop     --json                            (change detection on the live chain)
    dvt-bench identify [--monte-carlo N] --json          (identifier speed / statistics)

Each target is a module with ``main(argv) -> int``, imported by name when asked for: ``link``
and ``loop`` are the driver package's benchmarks (they need the plant), which this package does
not depend on; without ``dvt_driver`` installed those targets alone are unavailable.
"""

from __future__ import annotations

import importlib
import sys

_TARGETS = {
    "model": "dvt_model.bench",
    "link": "dvt_driver.run.bench",
    "loop": "dvt_driver.run.bench_loop",
    "identify": "dvt_identify.bench_identify",
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] not in _TARGETS:
        print(__doc__, file=sys.stderr)
        print(f"dvt-bench: expected one of {sorted(_TARGETS)}", file=sys.stderr)
        return 2
    name = _TARGETS[args[0]]
    try:
        module = importlib.import_module(name)
    except ModuleNotFoundError as exc:
        print(f"dvt-bench: error: {args[0]}: {name} is not installed ({exc})", file=sys.stderr)
        return 2
    return int(module.main(args[1:]))


if __name__ == "__main__":
    sys.exit(main())
