"""An experiment's variants run side by side, one process each (``variants_mode``).

The variants of an experiment are independent runs, each in its own folder: on two idle cores the
free and the tracked Celia run together instead of one after the other.  Each variant runs in a
child process forked from the experiment's (``os.fork``: the imports, the compiled kernels and the
checked configs are there already; nothing is started anew).  The child runs the variant exactly
as the sequential experiment does (``run_checked`` into ``<out>/<name>/``), with one kernel thread
(the other core is the other variant's), and sends its summary, or its error, back through a pipe.

``variants_mode``:

- ``sequential``: one variant after the other, in the experiment's process (the only mode before
  2026-12-07);
- ``parallel``: at most as many variants at once as the process may use cores;
- ``auto`` (the default): parallel when the process may use at least two cores, the machine's
  cores were idle but for at most ``AUTO_BUSY_CORES`` over ``IDLE_WINDOW_S`` (``idle_cores``,
  /proc/stat; the load average where it cannot be read), the longest variant is estimated to
  take at least ``PARALLEL_MIN_SECONDS`` (the resource guard's estimate: a variant of a second or
  less gains nothing worth a process) and the variants that would run together fit in the share of the
  available memory a run may take without being called large; else sequential.

The experiment's contract is the sequential one: the summary lists the variants in the
experiment's order, a failing variant fails the experiment (the variants still running are
stopped with SIGTERM and end ``interrupted``), and SIGINT/SIGTERM end every variant
``interrupted`` (the signal is forwarded to the children, which write their endings; the
experiment waits for them, at most ``STOP_WAIT_SECONDS``, then kills what is left and marks its
summary ``failed``).  A child killed outright (SIGKILL, the kernel's out-of-memory killer) leaves
its summary ``running``; the experiment rewrites it as ``failed``, naming the signal.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import signal
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from hairexp.app.guard import LARGE_RUN_SHARE, available_memory
from hairexp.app.run import end_dead_run, run_checked
from hairexp.app.signals import SIGNALS, note_late, take_late
from hairexp.errors import HairexpError, Interrupted, SimulationError, choice_name
from hairexp.outputs.folder import running_run
from hairexp.outputs.progress import set_slot
from hairexp.physics.bandchol import cap_threads, pick_threads

log = logging.getLogger("hairexp")

#: s: ``auto`` runs the variants side by side only when the longest is estimated to take at least this
#: long (the guard's estimate: spreading 0.72 s a variant, goaling 0.91, splitting 1.07, stylization
#: 2.76, Celia 21.6; the smoke scenes 0.07-1.5).  Side by side, each variant settles and simulates
#: its guides itself (one after the other they share them: ``shared_settle``), which the short
#: scenes' steps do not repay (2026-12-07, whole commands, sequential -> parallel: spreading 8.82 ->
#: 9.42 s, goaling 4.98 -> 5.22, splitting 8.44 -> 8.10, stylization 8.45 -> 8.35; Celia about
#: 14 -> 12 s)
PARALLEL_MIN_SECONDS = 2.0
#: s: after a stop, the variants still running are waited for this long to write their endings
STOP_WAIT_SECONDS = 60.0
#: s: the wait loop's poll of the children (a signal interrupts it at once)
POLL_SECONDS = 0.5

#: why ``auto`` keeps this process's experiments sequential (``keep_sequential``), or None
_HELD: str | None = None


def keep_sequential(why: str | None) -> None:
    """``auto`` runs this process's experiments' variants one after the other (``why`` is said in
    the summary); None: it chooses again.  A sweep's job: the sweep's workers share the cores
    already, and the load average, a minute behind, said "idle" to both workers' first jobs."""
    global _HELD
    _HELD = why


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


#: s: how long ``idle_cores`` watches the machine's CPU time
IDLE_WINDOW_S = 0.15
#: ``auto``: the other processes may keep at most this many cores busy (as ``pick_threads``' test)
AUTO_BUSY_CORES = 0.75


def _cpu_times() -> tuple[float, float] | None:
    """(idle, total) jiffies of all CPUs from /proc/stat, or None where it cannot be read."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    try:
        v = [float(x) for x in fields[1:]]
    except ValueError:
        return None
    total = sum(v[:8])   # user nice system idle iowait irq softirq steal (guest time is in user)
    return v[3] + (v[4] if len(v) > 4 else 0.0), total


def idle_cores(window: float = IDLE_WINDOW_S) -> float | None:
    """How many of the machine's cores were idle over the next ``window`` seconds (this process
    sleeps meanwhile), or None where /proc/stat cannot be read.  Unlike the load average, a minute
    behind (after a heavy command it still said busy, and ``auto`` ran Celia's variants one after
    the other on an idle machine: reports/bench_experiment_parallel.md, round 3), it is now's."""
    a = _cpu_times()
    if a is None:
        return None
    time.sleep(window)
    b = _cpu_times()
    if b is None or b[1] <= a[1]:
        return None
    n = os.cpu_count() or 1
    return n * (b[0] - a[0]) / (b[1] - a[1])


def choose_width(mode: str, n_variants: int, seconds: list[float], memory: list[float]) -> tuple[int, str]:
    """(how many variants run at once, why): 1 is the sequential experiment.  ``seconds`` and
    ``memory``: the guard's estimates of each variant (may be empty when unknown)."""
    mode = choice_name(mode)
    if n_variants < 2 or mode == "sequential" or not hasattr(os, "fork"):
        return 1, "sequential" if mode == "sequential" else "one variant" if n_variants < 2 else "no fork here"
    cores = usable_cores()
    width = max(1, min(n_variants, cores))
    if width < 2:
        return 1, f"{cores} usable core"
    if mode == "parallel":
        return width, f"variants_mode=parallel, {width} at once"
    if _HELD is not None:
        return 1, _HELD
    if seconds and max(seconds) < PARALLEL_MIN_SECONDS:
        return 1, f"short variants (estimated {max(seconds):.2f} s at most)"
    idle = idle_cores()
    if idle is None:   # no /proc/stat: the load average
        if pick_threads("auto") < 2:
            return 1, "the load average leaves no core idle"
    elif idle < min(cores, os.cpu_count() or cores) - AUTO_BUSY_CORES:
        return 1, f"{idle:.1f} of {os.cpu_count()} cores idle"
    avail = available_memory()
    together = sum(sorted(memory, reverse=True)[:width]) if memory else 0.0
    if avail is not None and together > LARGE_RUN_SHARE * avail:
        return 1, f"{width} variants together would take {together / 1e9:.1f} GB of {avail / 1e9:.1f} GB available"
    return width, f"{width} at once on {cores} cores"


@dataclass
class _Child:
    name: str
    index: int
    pid: int
    fd: int
    slot: int = 0               # its progress bar's line
    data: bytearray = field(default_factory=bytearray)
    status: int | None = None   # waitpid's status once reaped
    message: tuple | None = None


def _child_main(vcfg, folder: Path, slot: int, name: str, wfd: int, mask) -> None:
    """The child: run the variant, send ("ok", summary, late) / ("interrupted", signum) /
    ("error", exception or its text, traceback text) through ``wfd``, and leave without running the
    parent's exit handlers."""
    code = 0
    try:
        try:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)   # the parent's, from before the fork
            cap_threads(1)   # the other core is the other variant's
            _torch_threads(1)
            set_slot(slot, name)
            s = run_checked(vcfg, folder)
            # the run is whole: a signal from here on is kept as a late one (as the run's own handler
            # does after its completed ending), not raised into the message's writing
            for sig in SIGNALS:
                if signal.getsignal(sig) != signal.SIG_IGN:
                    signal.signal(sig, lambda signum, frame: note_late(signum))
            data = pickle.dumps(("ok", s, take_late()))
        except KeyboardInterrupt as exc:
            data = pickle.dumps(("interrupted", int(getattr(exc, "signum", signal.SIGINT))))
        except BaseException as exc:  # noqa: BLE001  (sent to the experiment, which raises it)
            tb = "".join(traceback.format_exception(exc))
            try:
                data = pickle.dumps(("error", exc, tb))
                pickle.loads(data)
            except Exception:  # noqa: BLE001  (an exception that does not pickle: its text)
                data = pickle.dumps(("error", f"{type(exc).__name__}: {exc}", tb))
        view = memoryview(data)
        while view:
            n = os.write(wfd, view)
            view = view[n:]
    except BaseException:  # noqa: BLE001
        code = 1
    finally:
        try:
            for h in logging.getLogger().handlers + log.handlers:
                h.flush()
            sys.stdout.flush()
            sys.stderr.flush()
        except BaseException:  # noqa: BLE001
            pass
        os._exit(code)


def _torch_threads(n: int) -> None:
    torch = sys.modules.get("torch")
    if torch is not None:
        try:
            torch.set_num_threads(n)
        except RuntimeError:   # pragma: no cover
            pass


def _start(vcfg, folder: Path, index: int, slot: int, name: str, live: dict) -> _Child:
    """Fork the variant's process and put it in ``live`` before a signal can come: signals are
    blocked from before the fork (in the child, one would raise in the parent's frames) until the
    child is known here (a SIGTERM between the two left a variant running unseen by the stop)."""
    rfd, wfd = os.pipe()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    try:
        try:
            pid = os.fork()
        except OSError as exc:   # EAGAIN (a process limit: ulimit -u), ENOMEM
            os.close(rfd)
            os.close(wfd)
            raise SimulationError(f"variant {name}: could not start a process for it: {exc} (variants_mode="
                                  "sequential runs the variants one after the other in this process)") from exc
        if pid == 0:   # the child never returns from here
            os.close(rfd)
            _child_main(vcfg, folder, slot, name, wfd, old)
        os.close(wfd)
        child = live[pid] = _Child(name, index, pid, rfd, slot)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    return child


def _read(child: _Child) -> bool:
    """Read what the child sent; True at its end (the pipe closed)."""
    try:
        chunk = os.read(child.fd, 1 << 16)
    except BlockingIOError:   # pragma: no cover
        return False
    if chunk:
        child.data += chunk
        return False
    os.close(child.fd)
    _, child.status = os.waitpid(child.pid, 0)
    try:
        child.message = pickle.loads(bytes(child.data)) if child.data else None
    except Exception:  # noqa: BLE001
        child.message = None
    return True


def _wait_some(live: dict[int, _Child], timeout: float) -> list[_Child]:
    """The children that ended within ``timeout`` seconds (a signal raises here, as Interrupted)."""
    ended = []
    fds = {c.fd: c for c in live.values()}
    ready, _, _ = select.select(list(fds), [], [], timeout)
    for fd in ready:
        if _read(fds[fd]):
            ended.append(fds[fd])
    return ended


def _died(child: _Child) -> str:
    st = child.status
    if st is not None and os.WIFSIGNALED(st):
        sig = os.WTERMSIG(st)
        name = signal.Signals(sig).name if sig in signal.Signals.__members__.values() else str(sig)
        return f"its process was killed by {name}" + (" (the out-of-memory killer sends SIGKILL)" if sig == signal.SIGKILL else "")
    code = os.WEXITSTATUS(st) if st is not None and os.WIFEXITED(st) else None
    return f"its process ended (exit {code}) without a result"


def run_side_by_side(out: Path, names: list[str], vcfgs: list, width: int, signals, on_done, on_failed):
    """Run the variants ``width`` at a time.  ``on_done(index, summary)`` for each completed variant
    (in the order they end), ``on_failed(index, exc)`` for a failed, interrupted or killed one.
    The first failure stops the variants still running (SIGTERM; a signal after a variant had
    completed: that signal), whose endings are waited for, and the variants not yet started do not
    start.  Returns (index of the first failure, its exception), or (None, None).  A signal to this
    process (Interrupted) is forwarded to the running variants, whose endings are waited for, and
    raised."""
    pending = list(range(len(names)))
    live: dict[int, _Child] = {}
    slots = list(range(width))
    first: tuple[int, BaseException] | None = None
    try:
        while pending or live:
            while pending and len(live) < width and first is None:
                i = pending.pop(0)
                slot = slots.pop(0)
                _start(vcfgs[i], out / names[i], i, slot, names[i], live)
            if not live:
                break
            for c in _wait_some(live, POLL_SECONDS):
                slots.append(c.slot)
                exc = _reap(c, live, out, on_done, on_failed)
                if exc is None and c.message[2] is not None:   # a signal after it had completed: the others stop
                    exc = Interrupted(c.message[2])
                if exc is not None and first is None:
                    first = (c.index, exc)
                    _stop(live, exc.signum if isinstance(exc, Interrupted) else int(signal.SIGTERM))
    except BaseException as exc:   # a signal to the experiment (Interrupted), or a bug here
        sig = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGTERM)
        with signals.deferred():
            _stop(live, sig)
            _finish(live, out, on_done, on_failed)
        raise
    return first if first is not None else (None, None)


def _stop(live: dict[int, _Child], sig: int) -> None:
    for c in live.values():
        try:
            os.kill(c.pid, sig)
        except ProcessLookupError:
            pass


def _finish(live: dict[int, _Child], out: Path, on_done, on_failed) -> None:
    """Wait for the stopped children's endings (at most STOP_WAIT_SECONDS, then SIGKILL)."""
    end = time.monotonic() + STOP_WAIT_SECONDS
    while live:
        left = end - time.monotonic()
        if left <= 0:
            _stop(live, signal.SIGKILL)
            end = float("inf")
            left = POLL_SECONDS
        for c in _wait_some(live, min(left, POLL_SECONDS)):
            _reap(c, live, out, on_done, on_failed)


def _reap(c: _Child, live: dict[int, _Child], out: Path, on_done, on_failed) -> BaseException | None:
    """An ended child out of ``live``, told to ``on_done`` or ``on_failed``; its exception, or None."""
    del live[c.pid]
    exc = _outcome(c, out)
    if exc is None:
        on_done(c.index, c.message[1])
    else:
        on_failed(c.index, exc)
    return exc


def _outcome(c: _Child, out: Path) -> BaseException | None:
    """None for a completed child, else the exception it ended with."""
    m = c.message
    if isinstance(m, tuple) and m and m[0] == "ok":
        return None
    if isinstance(m, tuple) and m and m[0] == "interrupted":
        return Interrupted(int(m[1]))
    if isinstance(m, tuple) and m and m[0] == "error":
        exc, tb = m[1], m[2]
        if isinstance(exc, str):   # did not pickle: a bug, said with its traceback
            exc = RuntimeError(exc)
            exc.add_note(f"in variant {c.name}'s process:\n{tb}")
        elif not isinstance(exc, (HairexpError, OSError, MemoryError)):   # a bug: where it was, in the child
            exc.add_note(f"in variant {c.name}'s process:\n{tb}")
        return exc
    why = _died(c)
    found = running_run(out / c.name)   # its summary left "running": ended as a killed sweep job's is
    if found is not None and found[0] == "killed":
        end_dead_run(out / c.name, found[1], "failed", why)
    return SimulationError(f"variant {c.name}: {why}")
