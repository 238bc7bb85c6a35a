"""SIGINT and SIGTERM (and the other signals that would end the process at once, ``SIGNALS``) end
a run as ``interrupted``.

Inside ``InterruptSignals()`` both signals raise ``hairexp.errors.Interrupted`` (a
KeyboardInterrupt carrying the signal number) in the main thread, so the run can write its
ending (partial metrics, ``summary.json`` saying ``interrupted``) and the command line exits
128 + signal (130, 143).  A signal the process inherited as ignored (SIGINT of a command a script
starts with ``&``) stays ignored throughout, as during start-up.  While the ending is written (``deferred()``) a further signal is only
remembered (``pending``).  Outside the main thread nothing is installed.

A signal that lands inside an object's ``__del__`` (where a raised exception is printed and
lost) is delivered again a moment later, until the finaliser has returned.  Once a run has
written its completed summary, a signal is only kept (``note_late``): the run stays completed,
and its caller takes the signal (``take_late``: an experiment stops before its next variant, the
command line exits 128 + signal saying the run's results are whole).

``InterruptSignals(on_signal=f)`` calls ``f(signum)`` once before raising (a second signal
meanwhile is noted and does not cut it short): the main process of a ``-m`` sweep forwards SIGTERM to its worker
processes there and waits a bounded time for their jobs to write their ``interrupted`` ending
(``hairexp.app.cli.stop_sweep_jobs``), before the launcher tears the workers down.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

from hairexp import HANDLED_SIGNALS
from hairexp.errors import Interrupted

#: the signals that end a run as ``interrupted`` (exit 128 + signal): SIGINT, SIGTERM, SIGHUP (the
#: terminal closed; it killed the process and left its summary "running": probe of issue 12,
#: round 10), and the others whose default kills the process at once, which did the same
#: (round 19): SIGQUIT (Ctrl-\\, exit 131; no core is dumped), SIGUSR1 / SIGUSR2 (138 / 140) and
#: SIGXCPU (the soft CPU-time limit, ``ulimit -S -t``, exit 152).  SIGKILL cannot be caught;
#: SIGXFSZ is ignored by Python (a write past ``ulimit -f`` fails with EFBIG, named).
SIGNALS = HANDLED_SIGNALS   # one list: the package's early handler (hairexp/__init__.py) takes the same
#: s, the delay before a signal that landed in a finaliser is delivered again
REDELIVER_SECONDS = 0.01


#: a file whose appearance stops a run as its signal would (a sweep's stop mark, which holds the
#: signal's name: hairexp/app/cli.py STOP_MARK), or None; ``watch_stop_file``, ``stop_requested``
_STOP_FILE: Path | None = None


def watch_stop_file(path) -> None:
    """Let ``stop_requested`` read ``path`` (None: nothing is watched).  A sweep job watches its
    sweep's stop mark: the SIGTERM the main process forwards to the workers was lost when it came
    while a job was starting (the job ran on for the whole STOP_WAIT_SECONDS and was killed, or
    ran to its end; independent probe of issue 12, round 35); the mark, written before the
    signal is forwarded, is read between steps."""
    global _STOP_FILE
    _STOP_FILE = None if path is None else Path(path)


def read_stop_mark(path) -> int | None:
    """The signal a stop mark at ``path`` names (SIGTERM when it names none of ``SIGNALS`` or
    cannot be read), or None when there is no mark."""
    try:
        name = Path(path).read_text().strip()
    except FileNotFoundError:
        return None
    except OSError:
        return int(signal.SIGTERM)
    named = {signal.Signals(s).name: int(s) for s in SIGNALS}
    return named.get(name, int(signal.SIGTERM))


def stop_requested() -> int | None:
    """The signal named in the watched stop file once it exists (``read_stop_mark``), else None.
    A file read a call: cheap enough for every step."""
    return None if _STOP_FILE is None else read_stop_mark(_STOP_FILE)


class InterruptSignals:
    def __init__(self, on_signal=None):
        self.old: dict = {}
        self.defer = False
        self.pending: int | None = None
        self.on_signal = on_signal   # called once with the first signal's number, before raising
        self._signalled = False
        self._stopping = False   # on_signal is running: a further signal waits with it
        self._told = False
        self.raised: int | None = None   # the signal this handler raised as Interrupted (``lost``)

    def _handler(self, signum, frame):
        if self.defer or (frame is not None and frame.f_code in _ENTERING):
            # entering a deferral counts as deferred: a signal kept pending through a long C call
            # (the hair-hair broad phase's kd-tree query) was handled as its MemoryError reached the
            # run's ``except``, in the entry of the ending's ``deferred()``: it escaped the ending,
            # which never ran, and summary.json was left "running" (independent probe of issue 12,
            # round 33)
            self.pending = signum
            return
        if _in_finaliser(frame):
            # raised inside a __del__ (numba's compiler objects, rerun's recording stream), the
            # interrupt is printed as "Exception ignored" and lost: the job ran on until a sweep's
            # teardown killed it, its summary left "running" (probe of issue 12).  Sent again a
            # moment later (from a timer thread: os.kill to itself here would recurse into this
            # handler at once), it is handled here again until the finaliser has returned.
            timer = threading.Timer(REDELIVER_SECONDS, os.kill, (os.getpid(), signum))
            timer.daemon = True
            timer.start()
            return
        if self._stopping:
            # a second Ctrl-C while on_signal waits for a sweep's jobs: raised, it ended the main
            # process at once and the workers died before writing their endings (probe of issue 12)
            if not self._told:
                self._told = True
                print("hairexp: still stopping: waiting for the jobs to write their endings (SIGKILL ends at once)",
                      file=sys.stderr)
            return
        if self.on_signal is not None and not self._signalled:
            self._signalled = self._stopping = True
            try:
                self.on_signal(signum)
            finally:
                self._stopping = False
        self.raised = signum
        raise Interrupted(signum)

    def lost(self) -> int | None:
        """The signal this handler raised if the code it landed in swallowed it, for a caller whose
        block returned normally: the Interrupted of a Ctrl-C to a sweep's main process that landed in
        joblib's waiting for its jobs was lost under load, and the sweep ran on to exit 0, its next
        job started (independent probe of issue 12, round 30)."""
        return self.raised

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

    def deferred(self) -> "_Deferred":
        """Signals are remembered, not raised, inside this block (and while it is entered)."""
        return _Deferred(self)

    def whole(self) -> "_Deferred":
        """The block runs to its end: a signal meanwhile is raised after it (unless signals are
        deferred around it)."""
        return _Deferred(self, whole=True)


class _Deferred:
    """The block of ``InterruptSignals.deferred()`` / ``whole()``.  A class, not a generator: the
    handler knows its entry's frames (``_ENTERING``), in which a signal is kept as in the block."""

    __slots__ = ("signals", "whole", "old")

    def __init__(self, signals: InterruptSignals, whole: bool = False):
        self.signals, self.whole, self.old = signals, whole, False

    def __enter__(self) -> InterruptSignals:
        self.old, self.signals.defer = self.signals.defer, True
        return self.signals

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.signals.defer = self.old
        if self.whole and exc_type is None and self.signals.pending is not None and not self.signals.defer:
            raise Interrupted(self.signals.pending)
        return False


#: the code of the calls that enter a deferral: a signal handled in one of them is kept pending
_ENTERING = frozenset({InterruptSignals.deferred.__code__, InterruptSignals.whole.__code__,
                       _Deferred.__init__.__code__, _Deferred.__enter__.__code__})


#: signals that arrived after a run had written its completed ending (``note_late``)
_LATE: list[int] = []


def note_late(signum: int) -> None:
    """A signal arrived after a run had written its completed summary: the run is whole and
    stays completed; the caller that started it (an experiment's next variant, the command
    line's exit code) takes it with ``take_late``."""
    _LATE.append(int(signum))


def take_late() -> int | None:
    """The first signal ``note_late`` kept (and forget them all), or None."""
    first = _LATE[0] if _LATE else None
    _LATE.clear()
    return first


#: functions in which a raised exception is printed as "Exception ignored" and lost: finalisers,
#: and llvmlite's ctypes callbacks of numba's compile cache (a SIGINT there while the tracked
#: step's kernels compiled left numba's library half-built: "no compiled object yet", exit 1 with a
#: traceback; probe of issue 12, round 15)
_LOSING_FRAMES = frozenset({"__del__", "_raw_object_cache_notify", "_raw_object_cache_getbuffer"})


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` runs inside an object's ``__del__`` or a ctypes callback
    (``_LOSING_FRAMES``), where a raised exception is lost."""
    while frame is not None:
        if frame.f_code.co_name in _LOSING_FRAMES:
            return True
        frame = frame.f_back
    return False


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


def _is_resource_tracker(pid: int) -> bool:
    """Whether ``pid`` runs a resource tracker (joblib's loky or multiprocessing's): a helper of the
    launcher, not a job's worker, that ignores SIGINT and SIGTERM only; any other signal
    forwarded to it (SIGQUIT) killed it, and its relaunched successor printed a traceback for each
    shared resource it no longer knew (own probe of issue 12, round 20)."""
    try:
        return b"resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def worker_pids(pid: int | None = None) -> list[int]:
    """``child_pids`` without the resource trackers: the processes a sweep's signal goes to."""
    return [p for p in child_pids(pid) if not _is_resource_tracker(p)]


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


def start_resource_tracker() -> None:
    """Start the launcher's resource tracker (joblib's loky) now, with the handled signals other
    than SIGINT and SIGTERM ignored while it is made, so that it inherits them ignored.  The
    tracker ignores only SIGINT and SIGTERM itself: a SIGHUP or SIGQUIT to the whole process group
    (the terminal closed) killed it, and its relaunched successor printed 9 KeyError tracebacks
    after the sweep's closing line (independent probe of issue 12, round 31).  The workers are
    started by the main process later, with its own handlers: not touched.  Nothing happens when
    joblib is not installed or the tracker runs already."""
    try:
        from joblib.externals.loky.backend import resource_tracker
    except ImportError:
        return
    quiet = [s for s in SIGNALS if s not in (signal.SIGINT, signal.SIGTERM)]
    old = {}
    try:
        for s in quiet:
            old[s] = signal.signal(s, signal.SIG_IGN)
        resource_tracker.ensure_running()
    except (OSError, ValueError):   # not the main thread, or the tracker could not start: loky tries again itself
        pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
