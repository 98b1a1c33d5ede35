"""``python -m dvt_identify.bench_identify``: the same as ``dvt-bench identify``."""

import sys

from dvt_identify.bench_identify import main

sys.exit(main())
