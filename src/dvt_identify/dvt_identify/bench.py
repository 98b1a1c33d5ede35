"""``dvt-bench``: benchmarks that print what they measured (not tests).

    dvt-bench model    --rate 1000 --seconds 10 --json   (model node fed at 1 kHz)
    dvt-bench link     --rate 1000 --seconds 30 --json   (plant -> driver -> recorder)
    dvt-bench identify [--monte-carlo N] --json          (identifier speed / statistics)
"""

from __future__ import annotations

import importlib
import sys

_TARGETS = {
    "model": "dvt_model.bench",
    "link": "dvt_driver.bench",
    "identify": "dvt_identify.bench_identify",
}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] not in _TARGETS:
        print(__doc__, file=sys.stderr)
        print(f"dvt-bench: expected one of {sorted(_TARGETS)}", file=sys.stderr)
        return 2
    module = importlib.import_module(_TARGETS[args[0]])
    return int(module.main(args[1:]))


if __name__ == "__main__":
    sys.exit(main())
