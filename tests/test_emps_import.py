"""The EMPS records as the benchmark's archive ships them import like the NPZ copies.

``../shared/data/emps`` holds the two records as NPZ, taken bit for bit from the archive's
``DATA_EMPS.mat`` and ``DATA_EMPS_PULSES.mat``, whose variables were ``N x 1`` (the folder's
README). A MATLAB file of that layout, written here from the NPZ, goes through ``dvt-import``
with the example's own mapping (``examples/emps/mapping.yaml``, what ``run.sh`` uses) and must
give the same bag as the NPZ: every stamp, position, velocity and force equal. A missing data
folder fails (``DVT_SKIP_EMPS=1`` leaves it out on request, never silently).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat

from dvt_identify.data import read_jointstate_topics
from dvt_identify.importer import main

ROOT = Path(__file__).resolve().parents[1]
EMPS = ROOT.parent / "shared" / "data" / "emps"
MAPPING = ROOT / "examples" / "emps" / "mapping.yaml"
TOPICS = ["/emps/joint_states", "/emps/drive"]

pytestmark = pytest.mark.skipif(os.environ.get("DVT_SKIP_EMPS") == "1",
                                reason="DVT_SKIP_EMPS=1: the EMPS data left out on request")


@pytest.mark.parametrize("record", ["estimation", "validation"])
def test_the_archive_layout_imports_like_the_npz(tmp_path: Path, record: str) -> None:
    src = EMPS / f"emps_{record}.npz"
    if not src.is_file():
        pytest.fail(f"EMPS data not found at {src}: the tests read ../shared/data/emps beside "
                    "the repository (set DVT_SKIP_EMPS=1 to leave it out)")
    with np.load(src) as d:
        cols = {k: np.asarray(d[k]) for k in d.files}
    mat = tmp_path / f"{record}.mat"
    savemat(mat, {k: v[:, None] if v.ndim == 1 else v for k, v in cols.items()})
    bags = {}
    for kind, path in (("npz", src), ("mat", mat)):
        out = tmp_path / kind
        assert main([str(path), "--mapping", str(MAPPING), "--out", str(out)]) == 0
        bags[kind] = read_jointstate_topics(out, TOPICS)
    for topic in TOPICS:
        a, b = bags["npz"][topic], bags["mat"][topic]
        assert np.array_equal(a.stamps_ns, b.stamps_ns) and a.names == b.names == ("carriage",)
        assert a.stamps_ns.size == cols["t"].size
        for field in ("position", "velocity", "effort"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None), (topic, field)
            if x is not None:
                assert np.array_equal(x, y), (topic, field)
    drive = bags["mat"]["/emps/drive"].effort
    assert drive is not None
    assert np.array_equal(drive[:, 0], cols["vir"] * cols["gtau"])
