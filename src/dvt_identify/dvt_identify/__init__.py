"""dvt_identify: see the package README section in the repository README."""

import os as _os

# Small matrices (2x2 ... 6x6) everywhere: BLAS threads only add latency on a 2-core machine
# (an expm took 1.5-4 ms instead of 0.03 ms with OpenBLAS threading next to a busy plant).
# Set before numpy is first imported by this package; a user's explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
