"""SIGINT and SIGTERM end a run as ``interrupted``.

Inside ``InterruptSignals()`` both signals raise ``hairexp.errors.Interrupted`` (a
KeyboardInterrupt carrying the signal number) in the main thread, so the run can write its
ending (partial metrics, ``summary.json`` saying ``interrupted``) and the command line exits
128 + signal (130, 143).  While the ending is written (``deferred()``) a further signal is only
remembered (``pending``).  Outside the main thread nothing is installed.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager

from hairexp.errors import Interrupted

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class InterruptSignals:
    def __init__(self):
        self.old: dict = {}
        self.defer = False
        self.pending: int | None = None

    def _handler(self, signum, frame):
        if self.defer:
            self.pending = signum
            return
        raise Interrupted(signum)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in SIGNALS:
                self.old[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc):
        for s, h in self.old.items():
            signal.signal(s, h)
        self.old.clear()
        return False

    @contextmanager
    def deferred(self):
        """Signals are remembered, not raised, inside this block."""
        old, self.defer = self.defer, True
        try:
            yield self
        finally:
            self.defer = old


def exit_code(signum: int) -> int:
    return 128 + int(signum)
