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
_WORK = "the run"
_TOLD = "its run folder's summary.json says how the run ended"


def begun(work: str = "the run", told: str = "its run folder's summary.json says how the run ended") -> None:
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
