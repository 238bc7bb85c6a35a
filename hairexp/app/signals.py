"""SIGINT and SIGTERM end a run as ``interrupted``.

Inside ``InterruptSignals()`` both signals raise ``hairexp.errors.Interrupted`` (a
KeyboardInterrupt carrying the signal number) in the main thread, so the run can write its
ending (partial metrics, ``summary.json`` saying ``interrupted``) and the command line exits
128 + signal (130, 143).  A signal the process inherited as ignored (SIGINT of a command a script
starts with ``&``) stays ignored throughout, as during start-up.  While the ending is written (``deferred()``) a further signal is only
remembered (``pending``).  Outside the main thread nothing is installed.

``InterruptSignals(on_signal=f)`` calls ``f(signum)`` once before raising (a second signal
meanwhile raises at once): the main process of a ``-m`` sweep forwards SIGTERM to its worker
processes there and waits a bounded time for their jobs to write their ``interrupted`` ending
(``hairexp.app.cli.stop_sweep_jobs``), before the launcher tears the workers down.
"""

from __future__ import annotations

import os
import signal
import threading
from contextlib import contextmanager
from pathlib import Path

from hairexp.errors import Interrupted

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class InterruptSignals:
    def __init__(self, on_signal=None):
        self.old: dict = {}
        self.defer = False
        self.pending: int | None = None
        self.on_signal = on_signal   # called once with the first signal's number, before raising
        self._signalled = False

    def _handler(self, signum, frame):
        if self.defer:
            self.pending = signum
            return
        if self.on_signal is not None and not self._signalled:
            self._signalled = True   # a second signal during on_signal raises at once
            self.on_signal(signum)
        raise Interrupted(signum)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in SIGNALS:
                if signal.getsignal(s) == signal.SIG_IGN:   # inherited as ignored (a script's `cmd &`): kept so,
                    continue                                 # as at start-up (POSIX; it was honoured only later)
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


def child_pids(pid: int | None = None) -> list[int]:
    """The live child processes of ``pid`` (this process), from /proc (Linux; [] elsewhere)."""
    pid = os.getpid() if pid is None else pid
    out = []
    try:
        entries = list(Path("/proc").iterdir())
    except OSError:
        return []
    for d in entries:
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()   # after "pid (comm) "
        if len(fields) > 1 and int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(d.name))
    return sorted(out)


def forward(signum: int, pids: list[int]) -> list[int]:
    """Send ``signum`` to ``pids``; the ones it reached."""
    sent = []
    for p in pids:
        try:
            os.kill(p, signum)
            sent.append(p)
        except OSError:
            pass
    return sent
