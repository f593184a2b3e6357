"""One BLAS thread per process, set by the project (not the user's shell).

The flight's linear algebra is small and dense (15 x 15 covariances, a few hundred measurement rows,
per-unit 3 x 3 blocks) and runs thousands of times a second: a second BLAS thread costs more in
hand-over than it saves, and OpenBLAS's default pool (one thread per core) competes with JSBSim and the
other processes for the cores. Issue 16 measured a 7x7 flight at 1.4x real time with the default pool
and 9.7x with OPENBLAS_NUM_THREADS=1 on 2 cores. threadpoolctl sets the pools of the BLAS libraries
loaded in this process (numpy's and scipy's OpenBLAS each have their own)."""

from __future__ import annotations

from threadpoolctl import threadpool_info, threadpool_limits


def single_blas_thread() -> None:
    """Limit every loaded BLAS library to one thread (idempotent; cheap when already done)."""
    if any(lib.get("user_api") == "blas" and lib.get("num_threads", 1) > 1 for lib in threadpool_info()):
        threadpool_limits(limits=1, user_api="blas")
