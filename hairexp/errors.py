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


class ExtentError(InputError):
    """A point of an input lies farther from the origin than MAX_COORDINATE (``check_extent``):
    its own type, so a caller can add what placed the points without reading the message."""


class ScratchError(HairexpError, OSError):
    """A temporary file of the run (outside the run folder: the guide frame store in the system's
    temporary folder) could not be written, or read back (``reading``): its own type, so the
    command line does not call it a run folder that cannot be written."""

    def __init__(self, *args, reading: bool = False):
        super().__init__(*args)
        self.reading = reading


class SimulationError(HairexpError, RuntimeError):
    """The solver could not produce a finite state, even after the configured recovery."""


def finite_number(value, key: str, allowed: str = "") -> float:
    """``value`` as a finite float, or an InputError naming ``key`` and, when given, the
    ``allowed`` range (``">= 0"``, ``"in [0, 1)"``): ``must be a finite number >= 0, got nan``."""
    import math

    what = f"a finite number {allowed}".rstrip() if allowed else "a finite number"
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"must be {what}, got {value!r}", key) from exc
    if not math.isfinite(v):
        raise InputError(f"must be {what}, got {v}", key)
    return v


#: m: a point of an input (a USD stage's curves, a guide file) farther than this from the origin
#: is refused as a unit error (hairexp reads metres; a far point also breaks the solver's linear
#: algebra, at 1e30 m a singular system instead of a named error)
MAX_COORDINATE = 1e4


#: m/s: a keyframed body or collider moving faster than this between keyframes, or a dynamic block
#: launched faster, is refused as a jump or a unit error (3 x the speed of sound; the stress
#: matrix's fastest collider moves at 10 m/s)
MAX_SPEED = 1e3
#: s, the shortest step a simulation takes (``Simulator.step``): below it the inertia M/dt^2 of the
#: step's objective overflows; solver.dt, scene.settle_dt and the step a frame is split into are
#: checked against it with the config (a traceback after the settle phase; independent probe, round 27)
MIN_STEP_DT = 1e-9


def points_range(points):
    """(min, max) per axis of points (n, 3), or (inf, -inf) for none (non-finite values propagate as
    numpy's min and max do).  Reduced as 3 contiguous rows: numpy's axis-0 reduction of an (n, 3)
    array took 0.64 ms at Celia's 7,826 vertices, this 14 us (the recording's bounds and the USD
    extents take the hair's range every frame)."""
    import numpy as np

    p = np.asarray(points)
    if not len(p):
        return np.full(3, np.inf), np.full(3, -np.inf)
    c = np.ascontiguousarray(p.reshape(-1, 3).T)
    return c.min(axis=1), c.max(axis=1)


def check_extent(points, where: str, counts=None, frame: int | None = None) -> None:
    """InputError naming ``where`` (and the curve and vertex, with ``counts``: vertices per curve;
    ``frame`` when given) when a point of ``points`` (N, 3) lies farther than MAX_COORDINATE from
    the origin.  Non-finite points are left to the callers' finiteness checks."""
    import numpy as np

    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        far = np.flatnonzero(np.abs(P).max(axis=1, initial=0.0) > MAX_COORDINATE)
    if not len(far):
        return
    i = int(far[0])
    at = f"vertex {i}"
    if counts is not None:
        ends = np.cumsum(np.asarray(counts, dtype=np.int64))
        c = int(np.searchsorted(ends, i, side="right"))
        at = f"curve {c} vertex {i - (int(ends[c - 1]) if c else 0)}"
    if frame is not None:
        at = f"frame {frame}, {at}"
    raise ExtentError(f"{at} is at {P[i].tolist()}, more than {MAX_COORDINATE:g} m from the origin: hairexp reads "
                     "metres (check the units of the input)", where)


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT or SIGTERM); ``signum`` is the signal's number.
    A KeyboardInterrupt, so code that lets Ctrl-C through lets this through too."""

    def __init__(self, signum: int):
        import signal

        self.signum = int(signum)
        name = signal.Signals(self.signum).name
        why = {"SIGXCPU": " (the process's CPU-time limit, ulimit -t, was reached)"}.get(name, "")
        super().__init__(f"interrupted by {name}{why}")


#: what a library's write error says (USD's ``Tf.ErrorException``, rerun's RuntimeError: their
#: exceptions carry no errno), and the errno each one is (``errno_in_text``)
_WRITE_ERRORS = (("No space left", "ENOSPC"), ("File too large", "EFBIG"), ("Disk quota", "EDQUOT"),
                 ("Read-only file system", "EROFS"), ("Permission denied", "EACCES"),
                 ("Insufficient permissions", "EACCES"), ("Operation not permitted", "EPERM"),
                 ("No such file or directory", "ENOENT"))


def errno_in_text(text: str) -> int | None:
    """The errno a library's write error names in its text (``_WRITE_ERRORS``), or None."""
    import errno

    return next((getattr(errno, name) for words, name in _WRITE_ERRORS if words in text), None)


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


def number(value, key: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           hi_open: bool = False) -> float:
    """``value`` as a finite float within [lo, hi] (``lo_open``/``hi_open``: the bound excluded).
    Every error names ``key`` and the whole allowed range (``must be a finite number > 0, got nan``)."""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    allowed = " and ".join(parts)
    v = finite_number(value, key, allowed)
    if (lo is not None and (v < lo or (lo_open and v == lo))) or (hi is not None and (v > hi or (hi_open and v == hi))):
        raise InputError(f"must be {allowed}, got {v:g}", key)
    return v


def enum_value(x):
    """A string Enum member's value (OmegaConf gives the schema's Enum fields as members); anything
    else as it is."""
    return getattr(x, "value", x)


def choice_name(x) -> str:
    """A config choice as its name: ``enum_value`` as a string (``solver.kernels`` given as the
    string "numba" or as an Enum member reads alike)."""
    return str(enum_value(x))


def choice(value, key: str, choices) -> str:
    """``value`` (a string, or a string Enum such as the config's) when it is one of ``choices``,
    else an InputError naming ``key`` and the choices.  For the Python API, where a dataclass
    config takes any value: ``SolverConfig(on_failure="ignore")`` ran as ``substep`` would not
    and ``derivatives="bogus"`` as the closed forms (probe of issue 16)."""
    raw = enum_value(value)
    if not isinstance(raw, str) or raw not in choices:
        raise InputError(f"must be one of {'|'.join(choices)}, got {type(raw).__name__} {raw!r:.60}", key)
    return raw


def flag(value, key: str) -> bool:
    """``value`` when it is a bool (numpy's too), else an InputError naming ``key``: in the Python
    API ``CollisionConfig(objects="no")`` was true, and switched the colliders on (probe of issue 16)."""
    import numpy as np

    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"must be true or false, got {type(value).__name__} {value!r:.60}", key)
    return bool(value)


def check_switches(cfg, section: str, choices: dict, flags=()) -> None:
    """``choice`` for each of ``choices`` (key -> its choices) and ``flag`` for each of ``flags``
    that the settings object ``cfg`` has, named ``<section>.<key>`` (attributes it lacks are
    left to their defaults)."""
    for key, options in choices.items():
        if hasattr(cfg, key):
            choice(getattr(cfg, key), f"{section}.{key}", options)
    for key in flags:
        if hasattr(cfg, key):
            value = getattr(cfg, key)
            flag(enum_value(value), f"{section}.{key}")


def integer(value, key: str, lo: int) -> int:
    """``value`` as an int >= lo (a bool is not one; a numpy integer is), or an InputError naming ``key``."""
    import numbers

    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputError(f"must be an integer >= {lo}, got {value!r}", key)
    if value < lo:
        raise InputError(f"must be >= {lo}, got {value}", key)
    return int(value)


def real(value, key: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
         hi_open: bool = False) -> float:
    """``number`` for the Python API: ``value`` must already be a real number (an int, a float, a
    numpy scalar), not a string, None or a bool, which ``float()`` would take or turn into 1.0."""
    return number(real_type(value, key), key, lo, hi, lo_open, hi_open)


def real_type(value, key: str):
    """``value`` itself when it is a real number (an int, a float, a numpy scalar; NaN and inf
    too), else an InputError naming ``key``: a string, None or a bool (``real``'s first check, for
    callers that check the range with messages of their own)."""
    import numbers

    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"must be a real number, got {type(value).__name__} {value!r}", key)
    return value


def real_array(value, key: str):
    """``value`` as a float64 numpy array, or an InputError naming ``key`` when it is not made of
    real numbers (strings, None, complex or ragged lists: numpy's own messages name neither the
    input nor its place)."""
    import numpy as np

    if isinstance(value, (str, bytes)) or value is None:
        raise InputError(f"must be an array of real numbers, got {type(value).__name__} {value!r:.60}", key)
    try:
        raw = value if isinstance(value, np.ndarray) else np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"must be an array of real numbers: {exc}", key) from None
    if raw.dtype.kind not in "biuf":
        raise InputError(f"must be an array of real numbers, got {raw.dtype} values", key)
    return np.asarray(raw, dtype=np.float64)


def whole_array(value, key: str):
    """``value`` as an int64 numpy array of whole numbers (floats allowed when whole), or an
    InputError naming ``key`` (a count of 10.7 was truncated to 10 without a word)."""
    import numpy as np

    raw = real_array(value, key)
    if not (np.isfinite(raw).all() and np.array_equal(raw, np.round(raw))):
        bad = raw.ravel()[~(np.isfinite(raw.ravel()) & (raw.ravel() == np.round(raw.ravel())))][:4].tolist()
        raise InputError(f"must be whole numbers, got {bad}", key)
    return raw.astype(np.int64)
