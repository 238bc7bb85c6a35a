"""Error types.  Every error names the input and the place it came from, so that the
command line can print one clear line and exit non-zero."""


class HairexpError(Exception):
    """Base class of the errors hairexp raises on purpose."""


class InputError(HairexpError, ValueError):
    """Bad input: NaN/inf, wrong shapes, zero-length edges, empty clusters, unreadable files.

    ``where`` names the file, prim, strand index or config key at fault.
    """

    def __init__(self, message: str, where: str | None = None):
        self.where = where
        super().__init__(f"{where}: {message}" if where else message)


class SimulationError(HairexpError, RuntimeError):
    """The solver could not produce a finite state, even after the configured recovery."""


def finite_number(value, key: str) -> float:
    """``value`` as a finite float, or an InputError naming ``key``."""
    import math

    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"must be a number, got {value!r}", key) from exc
    if not math.isfinite(v):
        raise InputError(f"must be finite, got {v}", key)
    return v


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT or SIGTERM); ``signum`` is the signal's number.
    A KeyboardInterrupt, so code that lets Ctrl-C through lets this through too."""

    def __init__(self, signum: int):
        import signal

        self.signum = int(signum)
        super().__init__(f"interrupted by {signal.Signals(self.signum).name}")


def regular_file(path, where: str, what: str = "file"):
    """``path`` (a Path) when it is a readable regular file, else an InputError naming ``where``:
    no such file, a directory, a FIFO or device (reading one would block or never end), or a
    file this process may not read."""
    import os
    import stat
    from pathlib import Path

    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputError("no such file", where) from None
    except OSError as exc:
        raise InputError(f"cannot be read: {exc.strerror or exc}", where) from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"is a directory, not a {what}", where)
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"is not a regular file (a FIFO, socket or device), not a {what}", where)
    if not os.access(path, os.R_OK):
        raise InputError("cannot be read: permission denied", where)
    return path
