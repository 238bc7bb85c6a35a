"""hairexp: the HairControl tracking solver (Milliez, Sumner, Gross, Thomaszewski) as an
experiment framework.  See README.md for the command line and ../paper for the method."""

__version__ = "0.1.0"

import os as _os

# numpy/scipy's OpenBLAS threads and torch's OpenMP threads fight over the cores: with both
# at 2 threads on the 2-core machines a step took 54 ms instead of 22 ms (experiments/
# bench_free.py).  BLAS here only sees small vectors, so it gets one thread; torch keeps its
# own.  ``limit_blas_threads`` enforces it even when numpy was imported first.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def limit_blas_threads() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
