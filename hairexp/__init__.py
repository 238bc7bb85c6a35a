"""hairexp: the HairControl tracking solver (Milliez, Sumner, Gross, Thomaszewski) as an
experiment framework.  See README.md for the command line, the Python API and the
layout; the method is the paper's (Milliez et al., "HairControl", sections 3.1-3.4)."""

__version__ = "0.1.0"

import os as _os
import signal as _signal
import sys as _sys


def _early_signal(signum, frame) -> None:
    """A signal while ``python -m hairexp`` (or ``-m hairexp.io.export_scene``) imports its
    libraries, before the app layer's start-up handlers (hairexp/app/startup.py) are in place:
    one line and 128 + signal (Ctrl-C 30 ms after the launch printed a KeyboardInterrupt
    traceback from ``import hydra``; independent probe of issue 12, round 24)."""
    try:
        _sys.stderr.write(f"hairexp: interrupted by {_signal.Signals(signum).name} while starting; nothing was run "
                          "or written\n")
        _sys.stderr.flush()
    finally:
        _os._exit(128 + int(signum))


#: the signals that end a command cleanly, from the first import on (here) to the run's ending
#: (hairexp/app/signals.py ``SIGNALS``, which says why each is there)
HANDLED_SIGNALS = (_signal.SIGINT, _signal.SIGTERM, _signal.SIGHUP, _signal.SIGQUIT, _signal.SIGUSR1, _signal.SIGUSR2,
                   _signal.SIGXCPU)
# "-m": this package is being imported while Python locates the module ``python -m`` runs
# (sys.argv[0] is "-m" until then); a library user's process keeps its own handlers
if _sys.argv[:1] == ["-m"]:
    for _s in HANDLED_SIGNALS:
        if _signal.getsignal(_s) in (_signal.default_int_handler, _signal.SIG_DFL):
            _signal.signal(_s, _early_signal)


def _fill_closed_std_fds() -> None:
    """A standard descriptor (0, 1, 2) the command was started without (``>&- 2>&-``) is opened on
    /dev/null, inheritable: else the next file opened took its number, close-on-exec, and a sweep's
    worker processes started without their standard streams and died; the sweep ran nothing and
    exited 1, saying a worker was killed (independent probe of issue 12, round 27).  Python's own
    ``sys.stdout`` stays None (hairexp/app/streams.py guards it)."""
    for fd in (0, 1, 2):
        try:
            _os.fstat(fd)
        except OSError:
            new = _os.open(_os.devnull, _os.O_RDWR)
            if new != fd:
                _os.dup2(new, fd)   # inheritable
                _os.close(new)
            else:
                _os.set_inheritable(fd, True)


if _sys.argv[:1] == ["-m"]:
    _fill_closed_std_fds()

# numpy/scipy's OpenBLAS threads and torch's OpenMP threads fight over the cores: with both
# at 2 threads on the 2-core machines a step took 54 ms instead of 22 ms (experiments/
# bench_free.py).  BLAS here only sees small vectors, so it gets one thread; torch keeps its
# own.  ``limit_blas_threads`` enforces it even when numpy was imported first.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# torch's OpenMP threads busy-wait between parallel regions by default.  With another busy
# process on the two cores (a second sweep worker, a test run) a tracked step went from 0.15 s
# to 7-60 s; passive waiting kept it at 0.14-0.9 s.  Read when torch loads, so set here first.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# rerun's SDK allocates from its own mimalloc heap, which keeps a freed page resident for
# ``purge_delay`` (10 ms): the pages of the recording's encoded chunks piled up under the next
# ones (with the recording on, a 3,000-frame run's peak was 5.0 / 2.1 MB above a 200-frame run's,
# 6 x 10 / 40 x 20 hair, against 3.4 / 1.1 MB with 0: reports/bench_memory.md).  0: back at once.
# Read when rerun's library loads, so set here first.
_os.environ.setdefault("MIMALLOC_PURGE_DELAY", "0")
# rerun's SDK logs its file writer's failures (a full disk, ``ulimit -f``) as coloured Rust log
# lines on stderr, beside hairexp's own line that names the same failure (a flush raises:
# outputs/rerun_sink.py flush_recording; a file without its footer is not given its final name).
# Off unless the user sets RUST_LOG (RUST_LOG=warn shows them).  Read when rerun's library loads.
_os.environ.setdefault("RUST_LOG", "off")


#: glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_tuned = False


def tune_runtime() -> None:
    """Once per process: one BLAS thread (see above), and keep freed large blocks in the heap.

    Each Newton iteration allocates and frees tens of MB of element arrays; by default glibc
    returns blocks above its mmap threshold to the OS at once, so every iteration paid page
    faults on fresh memory: the Celia-scale step took 69 ms instead of 46 ms
    (experiments/bench_free.py).  No effect where the C library is not glibc."""
    global _tuned
    if _tuned:
        return
    _tuned = True
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, 256 << 20)
        libc.mallopt(_M_TRIM_THRESHOLD, 512 << 20)
        libc.mallopt(_M_TOP_PAD, 64 << 20)
    except (OSError, AttributeError):
        pass
