"""dvt_model: see the package README section in the repository README.

Importing any dvt package holds BLAS to one thread in this process (:func:`one_blas_thread`;
``dvt_driver`` and ``dvt_identify`` import this package first).
"""

import os as _os
import sys as _sys

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that set the BLAS libraries' thread count (read when numpy loads)."""


def one_blas_thread() -> int:
    """Hold the BLAS libraries of this process to the thread count of ``OPENBLAS_NUM_THREADS``,
    1 unless the user set it; returns that count.

    Why: (1) small matrices (2x2 ... 6x6) everywhere, so BLAS threads only add latency on a
    2-core machine (an expm took 1.5-4 ms instead of 0.03 ms with OpenBLAS threading next to a
    busy plant), and the identifier spreads its work over processes (``dvt_identify.parallel``);
    (2) the same numbers in every process: a product summed by two threads differs from one
    thread's in the last bits, and an identification can end in another local optimum from
    there (``docs/identification.md``, Tests: the ``gravity_arm`` plant took a false term with
    one thread and not with two). The variables alone act only if numpy has not loaded yet (a
    caller, a test runner or ``sensor_msgs`` may have imported it first); then the running
    libraries are limited with ``threadpoolctl``.
    """
    for var in BLAS_THREAD_VARIABLES:
        _os.environ.setdefault(var, "1")
    raw = _os.environ["OPENBLAS_NUM_THREADS"]
    threads = int(raw) if raw.isdigit() and int(raw) > 0 else 1
    if "numpy" in _sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=threads, user_api="blas")
    return threads


one_blas_thread()
