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

``use_system_arrow_pool()``: pyarrow (the metrics table's parquet parts and reads) allocates from
the C library's heap instead of its default mimalloc pool, unless the user chose a pool
(``ARROW_DEFAULT_MEMORY_POOL``).  mimalloc takes memory in 2 MB segments it keeps: reading the
text column ``status`` of a 3,000-row metrics.parquet raised the resident memory by 2.0 MB
(0.07 MB from the system pool), and the end of a run's summary read +5.3 MB at 3,000 rows
against +1.0 MB at 200 (+1.7 and +1.05 from the system pool), which ``malloc_trim`` then returns.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import time

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


_LAST_RELEASE = 0.0


def release() -> None:
    """Return the freed memory the allocators keep to the system (module docstring)."""
    global _LAST_RELEASE
    _LAST_RELEASE = time.monotonic()
    trim = _malloc_trim()
    if trim:
        trim(0)
    pa = sys.modules.get("pyarrow")
    if pa is not None:
        try:
            pa.default_memory_pool().release_unused()
        except Exception:   # noqa: BLE001  (an old pyarrow or another pool: nothing to give back)
            pass


def release_every(seconds: float) -> None:
    """``release()`` if the last one ran at least ``seconds`` ago: for the loops of a long run (its
    steps, the end phases' passes over every frame).  glibc reuses the free chunks of its heap,
    whose pages ``malloc_trim`` gave back, a piece at a time, so a pass over many frames touched
    them again one by one and the resident memory crept up with the frames although what the
    pass holds does not (measured in-process, 6 x 10 hair: the measures' pass over 12,000 frames
    +3.3 MB against +0.3 MB over 200, its traced Python heap flat)."""
    if time.monotonic() - _LAST_RELEASE >= seconds:
        release()


def use_system_arrow_pool() -> None:
    """Make pyarrow allocate from the C library's heap (module docstring); a no-op when the
    user set ``ARROW_DEFAULT_MEMORY_POOL`` or pyarrow cannot switch."""
    if os.environ.get("ARROW_DEFAULT_MEMORY_POOL"):
        return
    import pyarrow as pa

    try:
        pa.set_memory_pool(pa.system_memory_pool())
    except Exception:   # noqa: BLE001  (an old pyarrow: keep its default pool)
        pass
