"""Ctrl-C (SIGINT) or SIGTERM while ``python -m hairexp`` starts: one line and exit 130 / 143.

Importing torch, scipy and numba takes seconds; a signal then would land in whichever import is
running and end the process with Python's traceback (SIGINT) or no word at all (SIGTERM).  Nothing
has been run or written yet, so ``install`` (called first thing by the app layer's package, only
when the process runs ``hairexp/__main__.py``) makes both signals print one line and exit
128 + signal at once, until the command line installs its own handlers around the run
(hairexp/app/signals.py ``InterruptSignals``, which end a run as ``interrupted``).
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import hairexp
from hairexp.app.signals import SIGNALS

#: the exit code of the command once its work has ended (``ended``); None while it starts
_ENDED_CODE: int | None = None
#: whether the command's work has begun (``begun``): its own handlers were installed around it
_BEGUN = False
#: what the command's work is, and where its outcome is told, for a signal after it (``begun``, ``ended``)
_WORK = _RUN = "the run"
_TOLD = _RUN_TOLD = "its run folder's summary.json says how the run ended"


def begun(work: str = _RUN, told: str = _RUN_TOLD) -> None:
    """The command's work begins (its handlers go in place around it): a signal after they are
    removed and before ``ended`` is not one "while starting".  After a run ended as interrupted
    a third quick signal in that window said "interrupted while starting; nothing was run or
    written" below the run's own line (probe of issue 12, round 13).  ``work``: what the work is
    ("the export"); ``told``: what a signal after it says of its outcome."""
    global _BEGUN, _WORK, _TOLD
    _BEGUN, _WORK, _TOLD = True, work, told


def ended(code: int, told: str | None = None) -> None:
    """The command's work has ended with ``code``: a signal from now on (the handlers are these
    again once the run's are removed) ends the process with 128 + signal, saying that the run
    had ended before it.  It said "interrupted while starting; nothing was run or written" after
    a completed run had written everything (probe of issue 12).  ``told``: the outcome to say, if
    ``begun``'s is not it."""
    global _ENDED_CODE, _TOLD
    _ENDED_CODE = int(code or 0)
    _TOLD = told or _TOLD


def _handler(signum, frame) -> None:
    name = signal.Signals(signum).name
    code = 128 + int(signum)
    mp = sys.modules.get("multiprocessing")   # no import inside a signal handler (it may land in one)
    if mp is not None and mp.parent_process() is not None:
        # a sweep's worker process (joblib's loky), idle, between jobs or around a job's run: left
        # to the main process, which stops the running jobs (hairexp/app/cli.py stop_sweep_jobs)
        # and says how the sweep ended.  An idle worker that exited here on a Ctrl-C (which reaches
        # every process of the group) made loky find its pool broken and kill the other workers,
        # a job among them that was writing its interrupted ending: its summary and outcome were
        # never written, metrics.parquet.tmp was left (probe of issue 12)
        return
    try:
        if _ENDED_CODE is None and not _BEGUN:
            sys.stderr.write(f"hairexp: interrupted by {name} while starting; nothing was run or written\n")
        elif _ENDED_CODE is None:
            sys.stderr.write(f"hairexp: {name} while the command was ending: {_TOLD}\n")
        else:
            sys.stderr.write(f"hairexp: {name} while exiting, after {_WORK} had ended (exit code {_ENDED_CODE} "
                             f"before it): {_TOLD}\n")
        sys.stderr.flush()
    finally:
        os._exit(code)   # no traceback from the import it landed in, no atexit work to do


def is_command_line() -> bool:
    """Whether this process runs ``python -m hairexp`` (its ``__main__.py``)."""
    main = sys.argv[0] if sys.argv else ""
    return os.path.basename(main) == "__main__.py" and os.path.basename(os.path.dirname(main)) == "hairexp"


def install(force: bool = False) -> bool:
    """The quiet startup handlers for SIGINT and SIGTERM, in the main thread of ``python -m hairexp``
    (``force``: whatever the process); whether they were installed.  Handlers someone else set
    (not the defaults) are left alone."""
    if not (force or is_command_line()) or threading.current_thread() is not threading.main_thread():
        return False
    installed = False
    for s in SIGNALS:
        h = signal.getsignal(s)
        if h in (signal.default_int_handler, signal.SIG_DFL) or h is hairexp._early_signal:
            signal.signal(s, _handler)
            installed = True
    return installed


def exit_now(code: int) -> None:
    """End the process with ``code`` once its own work is done: the ``atexit`` handlers run
    (logging's flush and close, the recording's), the standard streams flushed; then ``os._exit``,
    without the interpreter's teardown of every module and object (``python -m hairexp`` and the
    export's command; a signal during the export's 0.5 s of teardown killed it without a word:
    the handlers are gone by then; independent probe of issue 12, round 27).  That teardown did nothing a
    run needs and was the process's peak memory: measured on goaling_smoke (6 x 10 hair, 200
    frames), the peak resident memory was 555.2 MB when the run ended and 560.6 MB after the
    teardown (``ru_maxrss``), 5.3 MB for nothing (reports/bench_memory.md).  While another
    non-daemon thread runs (a sweep's launcher: its executor is shut down by the interpreter's
    own exit, before the threads are joined), the interpreter's exit is kept."""
    import atexit

    code = int(code or 0)
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        sys.exit(code)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        if stream is None:   # started with the stream closed (`>&-`): Python has none (round 21: a traceback)
            continue
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed or broken pipe: nothing more can be said
            pass
    os._exit(code)
