"""The standard streams of a command: their write errors kept, not raised.

A full or closed stdout or stderr (``>/dev/full``, ``2>&-``, ``| head -c 0``) raised from whichever
print met it (a sweep's job lines, a bad value's error line, Hydra's ``--cfg``, ``--help``): a
traceback and exit 1 or 4 instead of the command's own code and ending (independent probes of
issue 12, rounds 21, 23 and 24).  ``guard_streams()`` wraps both; ``stdout_checked(code)`` at the
end turns a lost standard output into one line on stderr and exit 4 (README "Exit codes").
"""

from __future__ import annotations

import errno
import os
import sys


class Tolerant:
    """A standard stream whose write errors are kept (``error``) instead of raised; a closed
    stream (None in Python) writes nowhere."""

    def __init__(self, stream):
        self._stream = stream if stream is not None else open(os.devnull, "w")
        self.error: OSError | None = None

    def _keep(self, exc: Exception) -> None:
        if self.error is None:
            self.error = exc if isinstance(exc, OSError) else OSError(errno.EBADF, str(exc))

    def write(self, s):
        try:
            return self._stream.write(s)
        except (OSError, ValueError) as exc:
            self._keep(exc)
            return len(s)

    def flush(self):
        try:
            self._stream.flush()
        except (OSError, ValueError) as exc:
            self._keep(exc)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def guard_streams() -> None:
    """Wrap ``sys.stdout`` and ``sys.stderr`` (once), and point the logging handlers that write to
    the bare streams (Hydra's console handler, made before a sweep job runs) at the wrapped ones."""
    import logging

    bare = {}   # id of a bare stream -> its wrapper
    if not isinstance(sys.stdout, Tolerant):
        old = sys.stdout
        sys.stdout = bare[id(old)] = Tolerant(old)
    if not isinstance(sys.stderr, Tolerant):
        old = sys.stderr
        sys.stderr = bare[id(old)] = Tolerant(old)
    if not bare:
        return
    loggers = [logging.getLogger()] + [lg for lg in logging.root.manager.loggerDict.values()
                                       if isinstance(lg, logging.Logger)]
    for lg in loggers:
        for h in lg.handlers:
            if type(h) is logging.StreamHandler and id(getattr(h, "stream", None)) in bare:
                h.setStream(bare[id(h.stream)])


def stdout_checked(code: int, prog: str) -> int:
    """``code``, or 4 when it is 0 but the standard output could not be written (the work is
    done, what it printed is lost); the lost output is said on stderr whatever the code (a
    comparison that found differences, exit 1, lost its lines silently; round 25)."""
    out = sys.stdout
    if isinstance(out, Tolerant):
        out.flush()
        if out.error is not None:
            print(f"{prog}: error: cannot write the standard output: {out.error}", file=sys.stderr)
            return code or 4
    return code
