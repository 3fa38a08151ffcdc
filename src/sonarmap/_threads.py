"""One BLAS thread for the per-ping work of the command line.

The per-ping pipeline's matrix products are small (a 96 x 96 deconvolution operator, a 16 x 16
block grid interpolated to the lattice): a multi-threaded BLAS gains nothing on them, but its
worker threads spin and wait for cores.  When another process (or sonarmap's own reader thread)
keeps the cores busy, a ping then waits milliseconds for a BLAS thread: measured on the real
Oculus pings with one competing process on 2 cores, 69 ms per ping with OpenBLAS's default
threads against 33 ms with one.  The CLI therefore runs BLAS single-threaded, unless the user
chose a thread count through the usual environment variables.  Library users who process pings
live can do the same with ``threadpoolctl.threadpool_limits(1, user_api="blas")``.
"""

from __future__ import annotations

import os
from typing import Any

__all__ = ["limit_blas_threads", "THREAD_ENV_VARS"]

#: Environment variables through which a user sets the BLAS / OpenMP thread count themselves.
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")

_LIMITER: list[Any] = []


def limit_blas_threads() -> bool:
    """Limit BLAS to one thread for the rest of the process (once); returns whether it did.

    Does nothing when one of :data:`THREAD_ENV_VARS` is set (the user's choice stands).
    """
    if _LIMITER:
        return True
    if any(os.environ.get(v) for v in THREAD_ENV_VARS):
        return False
    from threadpoolctl import threadpool_limits

    import numpy  # noqa: F401 - load the BLAS library so that the limit applies to it

    _LIMITER.append(threadpool_limits(limits=1, user_api="blas"))
    return True
