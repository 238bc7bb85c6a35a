"""Give freed heap memory back to the system between the phases of a run.

A run's end phases (metrics.parquet, the measures, result.npz, result.usdc, the summary) each
allocate and free blocks whose number grows with the run's length; the allocators keep freed
blocks for reuse, so without this the resident memory of each phase stacks on the blocks the
previous phases freed, and the run's peak grew with its length although what it holds does not
(reports/bench_memory.md: with a release between phases the 3,000-frame run's peak came closer to
the 200-frame run's by about 2 MB, 6 x 10 hair).

``release()``: glibc's ``malloc_trim(0)`` (returns free pages anywhere in the heap, not only at
its top; a no-op where the C library is not glibc) and, when pyarrow is loaded, its memory
pool's ``release_unused()`` (pyarrow's default pool is mimalloc, which keeps freed segments).
Costs about a millisecond; called a handful of times per run, never per step.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_TRIM = None


def _malloc_trim():
    global _TRIM
    if _TRIM is None:
        _TRIM = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                _TRIM = libc.malloc_trim   # glibc only (musl has none: AttributeError)
                _TRIM.argtypes, _TRIM.restype = [ctypes.c_size_t], ctypes.c_int
            except (OSError, AttributeError):
                _TRIM = False
    return _TRIM


def release() -> None:
    """Return the freed memory the allocators keep to the system (module docstring)."""
    trim = _malloc_trim()
    if trim:
        trim(0)
    pa = sys.modules.get("pyarrow")
    if pa is not None:
        try:
            pa.default_memory_pool().release_unused()
        except Exception:   # noqa: BLE001  (an old pyarrow or another pool: nothing to give back)
            pass
