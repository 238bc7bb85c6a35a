"""A run folder belongs to one run.

``claim(folder, overwrite)`` refuses a folder that already holds anything but Hydra's own
entries (``.hydra/`` and the job's ``*.log``, which Hydra writes before the run starts), and
then takes the folder by creating ``summary.json`` exclusively, so two launches into the same
folder cannot both start.  With ``overwrite`` the files a previous run wrote there (the run
folder's files, ``stream/``, and variant sub-folders made only of those) are removed first;
anything else in the folder is never deleted and is refused.

A running ``summary.json`` records the process (``owner``: pid and host); a run killed with
SIGKILL never writes its ending, and the refusal of its folder says so (``running_state``:
"a run killed while running (pid N)").
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import socket
import tempfile
from pathlib import Path

from hairexp.errors import InputError
from hairexp.outputs.files import write_json

SUMMARY = "summary.json"
STREAM = "stream"
#: disk space a run holds from its start for its ending's summary.json (``reserve``): on a disk that
#: fills during the run, the ending frees it and writes its summary there (a summary is ~10 kB)
RESERVE = ".ending.reserve"
RESERVE_BYTES = 128 << 10
#: what a run writes into its folder (README "Run folder")
RUN_FILES = frozenset({SUMMARY, "metrics.parquet", "result.npz", "result.usda", "result.usdc", "guides.npz",
                       "recording.rrd", "recording.partial.rrd", "comparison.rrd", "comparison.partial.rrd",
                       RESERVE})
RUN_DIRS = frozenset({STREAM, "result.clips", "result.clips.tmp"})   # the USD result's value clips (io/usd_write.py)


#: the lock a launch holds on a fixed run or sweep folder from before Hydra starts until the process
#: ends (``hold``): a second launch into the folder meanwhile is refused before Hydra rewrites the
#: first one's ``.hydra/`` record
LOCK = ".lock"
_HELD: list[int] = []
#: the folders ``hold`` made, and every folder it locked (``unhold_unused``)
_MADE: list[Path] = []
_LOCKED: list[Path] = []


def held_elsewhere(folder: Path) -> bool:
    """Whether another process holds the launch lock (``hold``) of ``folder``; the lock is not
    taken (a lock that can be taken is released at once)."""
    import fcntl

    lock = Path(folder) / LOCK
    if lock.is_symlink() or not lock.is_file():
        return False
    try:
        fd = os.open(lock, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def hydra_link_refusal(folder: Path) -> str | None:
    """Why Hydra may not write its record into ``folder`` when its ``.hydra`` is a symbolic link
    or holds one: Hydra writes through them, so a file (or a folder) outside the run folder was
    overwritten or filled (probe of issue 12, round 12).  None when there is no such link."""
    h = Path(folder) / ".hydra"
    if h.is_symlink():
        return f"{h} is a symbolic link (to {os.readlink(h)}): Hydra would write its record through it"
    if h.is_dir():
        try:
            links = sorted(q.name for q in h.iterdir() if q.is_symlink())
        except OSError:
            return None
        if links:
            return (f"{h} holds symbolic links ({', '.join(links[:4])}): Hydra would write its record through "
                    "them")
    return None


#: the files of Hydra's record of a run (``.hydra/``, or the folder ``hydra.output_subdir`` names)
HYDRA_RECORD = frozenset({"config.yaml", "hydra.yaml", "overrides.yaml"})


#: a sweep job's outcome, in Hydra's record of the job (written by hairexp/app/cli.py ``job``)
OUTCOME = Path(".hydra") / "outcome.json"


def _own_outcome(folder: Path) -> bool:
    """Whether ``folder``'s OUTCOME is this process's (a sweep job's "running" outcome, written
    before the job claims its folder), not a previous job's."""
    try:
        d = json.loads((Path(folder) / OUTCOME).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and d.get("status") == "running" and d.get("pid") == os.getpid()


def _hydras(p: Path) -> bool:
    """Hydra's own entries (``.hydra/``, the job's ``*.log``) and the launch's ``.lock``.  Hydra's
    record under another name (``hydra.output_subdir=rec``): a folder of only its files (the run
    refused its own record as another run's; independent probe of issue 12, round 23)."""
    if p.name in (".hydra", LOCK) or (p.is_file() and not p.is_symlink() and p.suffix == ".log"):
        return True
    if p.is_dir() and not p.is_symlink():
        try:
            names = {q.name for q in p.iterdir()}
        except OSError:
            return False
        return bool(names) and names <= HYDRA_RECORD and all((p / n).is_file() for n in names)
    return False


def hold(folder: Path) -> bool:
    """Take the launch lock of ``folder`` (creating it and its ``.lock``): an exclusive ``flock``
    kept until this process ends (the kernel drops it then, also after SIGKILL).  False when
    another process holds it (a launch into the same folder that has not ended).  Where the
    filesystem cannot lock, True (the run's ``claim`` still refuses a folder in use).  Two
    launches into one new folder used to pass the empty-folder check together: the refused one
    had already rewritten the running one's ``.hydra/config.yaml`` (probe of issue 12, round 10)."""
    import fcntl

    folder = Path(folder)
    if not folder.exists():
        _MADE.append(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:   # a link planted as .lock is not followed (it made a file outside the folder; probe of issue 12)
        fd = os.open(folder / LOCK, os.O_CREAT | os.O_RDWR | getattr(os, "O_NOFOLLOW", 0), 0o644)
    except OSError as exc:
        if os.path.islink(folder / LOCK):
            raise InputError(f"{LOCK} is a symbolic link; a run folder's {LOCK} is the launch's own file", str(folder)) from exc
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return False
    except OSError:   # no locks on this filesystem
        os.close(fd)
        return True
    _HELD.append(fd)
    _LOCKED.append(folder)
    return True


def unhold_unused() -> bool:
    """Remove the ``.lock`` of the folders ``hold`` locked that hold nothing else, and the folders
    it made for them: the launch ended before anything was written (Hydra could not compose the
    config; a folder holding only ``.lock`` was left; probe of issue 12, round 19).  Returns whether
    every such folder held nothing else (nothing of the launch is left)."""
    clean = True
    for folder in [f for f in _MADE] + [Path(f) for f in _LOCKED if Path(f) not in _MADE]:
        try:
            names = {p.name for p in folder.iterdir()}
            # Hydra's multirun.yaml, written as a sweep began, of a sweep whose jobs could not be composed
            # (the user's hydra.sweeper.params): it blocked the next launch into the folder (round 26)
            if LOCK in names and names <= {LOCK, "multirun.yaml"}:
                (folder / "multirun.yaml").unlink(missing_ok=True)
                (folder / LOCK).unlink()
                if folder in _MADE:
                    folder.rmdir()
            else:
                clean = False
        except FileNotFoundError:
            pass
        except OSError:
            clean = False
    return clean


def _is_tmp(p: Path) -> bool:
    return ".tmp" in p.name


def inside_run_refusal(folder, choose: str = "folder") -> str | None:
    """Why ``folder`` cannot be a run folder because it lies inside another run's (a parent holding
    a run's ``summary.json``: a run folder belongs to one run; the command line's and the API's
    check), naming what to ``choose`` instead, or None."""
    for parent in Path(os.path.abspath(folder)).parents:
        if (parent / SUMMARY).is_file():
            return (f"lies inside {parent}, another run's folder (its {SUMMARY}); a run folder belongs to one run: "
                    f"choose a {choose} outside it")
    return None


def _variant_names(folder: Path) -> set[str]:
    """The variants an experiment's ``summary.json`` in ``folder`` names: those it ran and those its
    config lists (an interrupted experiment's next variant has a folder before its entry); none for
    a single run's, or where there is none or it cannot be read."""
    try:
        with open(folder / SUMMARY, encoding="utf-8") as f:
            summary = json.load(f)
    except (OSError, ValueError):
        return set()
    if not isinstance(summary, dict):
        return set()
    names = set()
    ran = summary.get("variants")
    if isinstance(ran, dict):
        names |= {str(k) for k in ran}
    config = summary.get("config")
    listed = config.get("variants") if isinstance(config, dict) else None
    if isinstance(listed, list):
        names |= {str(v["name"]) for v in listed if isinstance(v, dict) and "name" in v}
    return names


def _removable(folder: Path, top: bool) -> tuple[list[Path], list[Path]]:
    """(entries a previous run wrote, entries that are not a run's) of ``folder``.  A sub-folder
    is the previous run's only when it is one of the variants its experiment's summary names: a
    copy of another run's folder kept inside was removed with it (independent probe,
    2026-12-07)."""
    ours, foreign = [], []
    variants = _variant_names(folder) if top else set()
    for p in sorted(folder.iterdir()):
        if top and _hydras(p):
            continue
        if p.is_symlink():   # a run writes no links: one is never followed nor removed (probe of issue 12, round 10)
            foreign.append(p)
        elif _is_tmp(p) and not p.is_dir():
            ours.append(p)
        elif p.name in RUN_FILES and not p.is_dir():
            # a file that only has a run file's name is not a run's (a user's notes saved as
            # summary.json were deleted by overwrite=true; probe of issue 12, round 12)
            (ours if _run_file(p) else foreign).append(p)
        elif p.name in RUN_DIRS and p.is_dir():
            strays = _strays(p)   # a user's file inside a run's folder is never deleted (probe of issue 12, round 11)
            (foreign.extend(strays) if strays else ours.append(p))
        elif p.is_dir() and p.name in variants and (p / SUMMARY).is_file():   # a variant's run folder
            sub_ours, sub_foreign = _removable(p, top=False)
            (foreign.extend(sub_foreign) if sub_foreign else ours.append(p))
        else:
            foreign.append(p)
    return ours, foreign


#: how each kind of run file begins (``_run_file``)
_MAGIC = {".parquet": (b"PAR1",), ".npz": (b"PK\x03\x04", b"PK\x05\x06"), ".rrd": (b"RRF",),
          ".usda": (b"#usda",), ".usdc": (b"PXR-USDC",)}


def _run_file(p: Path) -> bool:
    """Whether the file ``p`` (named as a run file) holds what a run writes under that name: a
    ``summary.json`` a JSON object with a ``status`` (or empty: a run stopped as it began), the
    other files their format's first bytes (an empty partial recording: a run stopped as it began);
    the disk reserve anything."""
    if p.name == RESERVE:
        return True
    try:
        if p.name == SUMMARY:
            text = p.read_text(errors="replace")
            if not text:
                return True
            try:
                return isinstance(d := json.loads(text), dict) and "status" in d
            except ValueError:
                return False
        with open(p, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    if not head:
        return p.name.endswith(".partial.rrd")
    return any(head.startswith(m) for m in _MAGIC.get(p.suffix, ()))


def _strays(d: Path) -> list[Path]:
    """The entries of a run's own folder ``d`` (``stream/``, ``result.clips/``) that a run does not
    write there: ``stream/``: ``<array>.npy`` and ``metrics/part-NNNNN.parquet``; the clips: ``*.usdc``
    (and temporary files, ``*.tmp*``); symbolic links never."""
    out = []
    for q in d.rglob("*"):
        rel = q.relative_to(d)
        if q.is_symlink():
            out.append(q)
        elif q.is_dir():
            if not (d.name == STREAM and rel.as_posix() == "metrics"):
                out.append(q)
        elif _is_tmp(q):
            continue
        elif d.name == STREAM:
            ok = (len(rel.parts) == 1 and q.suffix == ".npy") or (
                len(rel.parts) == 2 and rel.parts[0] == "metrics" and q.suffix == ".parquet")
            if not ok:
                out.append(q)
        elif len(rel.parts) != 1 or q.suffix != ".usdc":
            out.append(q)
    return sorted(out)


def reserve(folder: Path) -> bool:
    """Hold RESERVE_BYTES of the disk in ``folder`` (a file of zeros, its blocks allocated), so
    that a run whose disk fills still has room for its ending's summary.json (it stayed "running",
    and a later run was told the run had been killed; probe of issue 12).  False if the disk has
    not even that much free (nothing is left behind)."""
    path = Path(folder) / RESERVE
    try:
        with open(path, "wb") as f:
            f.write(bytes(RESERVE_BYTES))
            f.flush()
            os.fsync(f.fileno())
        return True
    except OSError:
        path.unlink(missing_ok=True)
        return False


def free_reserve(folder: Path, quiet: bool = True) -> None:
    """Give the space ``reserve`` held back to the disk (just before the summary is written);
    ``quiet=False``: an OSError if it cannot be removed (a folder made immutable mid-run), for the
    failed ending to say (it was left without a word; independent probe of issue 12, round 26)."""
    path = Path(folder) / RESERVE
    try:
        path.unlink(missing_ok=True)
    except OSError:
        try:   # an immutable folder's files can still be emptied: the space is given back, 0 bytes left
            os.truncate(path, 0)   # (128 kB stayed; independent probe of issue 12, round 31)
        except OSError:
            pass
        if not quiet:
            raise


def owner() -> dict:
    """The process that runs: ``pid`` and ``host``, written into a running ``summary.json``."""
    return {"pid": os.getpid(), "host": socket.gethostname()}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # another user's process
        return True
    return True


def running_run(folder: Path) -> tuple[str, dict] | None:
    """(kind, summary) of a ``summary.json`` of ``folder`` that says ``running`` (a run that never
    wrote its ending), None when it says anything else or cannot be read.  kind: ``"killed"``
    (its process no longer exists on this host: SIGKILL, a power cut), ``"live"`` (it does; a pid
    reused since by another process reads as live), ``"elsewhere"`` (another host's), ``"unknown"``
    (no process id recorded)."""
    try:
        s = json.loads((Path(folder) / SUMMARY).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(s, dict) or s.get("status") != "running":
        return None
    pid, host = s.get("pid"), s.get("host")
    if not isinstance(pid, int):
        return "unknown", s
    if host != socket.gethostname():
        return "elsewhere", s
    return ("live" if _alive(pid) else "killed"), s


def running_state(folder: Path, found: tuple[str, dict] | None = None) -> str | None:
    """What the ``summary.json`` of ``folder`` says of a run that never wrote its ending
    (``running_run``): ``"a run killed while running (pid N)"``, ``"a run still running (pid N)"``,
    ``"a run still running or killed (pid N on HOST)"``; None when it is not such a run.
    ``found``: ``running_run(folder)`` when the caller has read it already."""
    found = running_run(folder) if found is None else found
    if found is None:
        return None
    kind, s = found
    return {"unknown": "a run that never wrote its ending (status running, no process id recorded)",
            "killed": f"a run killed while running (pid {s.get('pid')})",
            "live": f"a run still running (pid {s.get('pid')})",
            "elsewhere": f"a run still running or killed (pid {s.get('pid')} on {s.get('host')})"}[kind]


def live_refusal(folder: Path) -> str | None:
    """Why ``overwrite=true`` cannot replace the run in ``folder`` (one still running, here or on
    another host), or None: it deleted a live run's files under it, which then failed, and the
    folder mixed the two runs' files (probe of issue 12)."""
    found = running_run(folder)
    if found is None or found[0] not in ("live", "elsewhere"):
        return None
    return f"holds {running_state(folder, found)}: overwrite=true replaces a finished run only; wait for it to end or stop it first"


def overwrite_refusal(folder: Path) -> str | None:
    """Why ``overwrite=true`` cannot replace what ``folder`` holds (a live run, or files no run
    wrote, which it never deletes), or None.  The command line asks before Hydra writes its
    ``.hydra/`` files: asked only in ``claim``, a refused overwrite had already replaced the
    previous run's config record with its own (probe of issue 12)."""
    folder = Path(folder)
    if not used_entries(folder):
        return None
    live = live_refusal(folder)
    if live is not None:
        return live
    if (folder / "multirun.yaml").is_file():   # its jobs' files were named as foreign ones (round 27)
        return ("it is a -m sweep's folder (multirun.yaml and its job folders): overwrite=true replaces a run's "
                "folder, not a sweep's; choose another folder, or remove the sweep's")
    _, foreign = _removable(folder, top=True)
    if foreign:
        return ("overwrite=true removes only what a run wrote; the folder also holds "
                + ", ".join(_foreign_label(p, folder) for p in foreign[:6]))
    return None


def _foreign_label(p: Path, folder: Path) -> str:
    """``p`` (an entry no run wrote) as the refusal names it: one with a run file's name says why
    it is not that run file (a garbage summary.json was named as if it were any other file; probe
    of issue 12, round 13)."""
    name = str(p.relative_to(folder))
    if p.is_symlink():
        return f"{name} (a symbolic link)"
    if p.name not in RUN_FILES and p.name not in RUN_DIRS:
        return name
    if p.is_dir() and p.name in RUN_FILES:
        return f"{name} (a folder, where a run writes a file)"
    if p.name in RUN_DIRS:
        return f"{name} (a file, where a run writes a folder)" if not p.is_dir() else name
    if not os.access(p, os.R_OK):
        return f"{name} (unreadable)"
    what = ("not a run's summary: not a JSON object with a status" if p.name == SUMMARY
            else f"not a {p.suffix[1:]} file: it does not begin as one")
    return f"{name} ({what})"


def used_entries(folder: Path) -> list[Path]:
    """What ``folder`` holds of another run: all but Hydra's own entries and a refused run's
    summary (``refused_summary``), which the next run replaces."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return [p for p in sorted(folder.iterdir()) if not _hydras(p) and not refused_summary(p)]


#: the key of a summary.json written for a run that ended before it claimed its folder: why (refused
#: by its settings, or interrupted); no step ran and nothing else was written
REFUSED = "refused"


def refused_summary(p: Path) -> bool:
    """``p`` is the ``summary.json`` of a run that ended before it claimed its folder (refused by
    its settings: failed; or interrupted), which the next run into the folder replaces."""
    if p.name != SUMMARY or p.is_symlink() or not p.is_file() or p.stat().st_size > (1 << 20):
        return False
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and d.get("status") in ("failed", "interrupted") and bool(d.get(REFUSED))


def used_refusal(folder: Path, used: list[Path] | None = None) -> str | None:
    """Why a run may not be written into ``folder`` without ``overwrite`` (it holds another run's
    files), or None (absent or empty but for Hydra's own)."""
    folder = Path(folder)
    used = used_entries(folder) if used is None else used
    if not used:
        return None
    shown = [p for p in used if not p.name.startswith(".")] or used   # not the run's own hidden reserve file
    names = ", ".join(p.name for p in shown[:6]) + (", ..." if len(shown) > 6 else "")
    found = running_run(folder)
    held = f"; it holds {running_state(folder, found)}" if found else ""
    if found is not None and found[0] in ("live", "elsewhere"):
        # it advised overwrite=true, which then refused the live run (independent probe of issue 12, round 30)
        return (f"the run folder is not empty ({names}){held}; a run folder belongs to one run: choose another "
                "folder (hydra.run.dir), or wait for that run to end (overwrite=true replaces a finished run only)")
    return (f"the run folder is not empty ({names}){held}; a run folder belongs to one run: choose another folder "
            "(hydra.run.dir) or set overwrite=true to replace the run in it")


#: bytes of each job log (``*.log`` in a run folder) written before this process's job began:
#: a previous run's lines, which ``claim(overwrite=True)`` removes (``note_job_logs``)
_PREVIOUS_LOG_BYTES: dict[Path, int] = {}


def note_job_logs(folder: Path) -> None:
    """Record the size of ``folder``'s job logs as the job starts (the command line calls it
    first thing): what they hold then is a previous run's.  ``overwrite=true`` replaced the
    previous run's files but left its lines in ``__main__.log``, so the new run's log showed
    warnings the new run never raised (probe of issue 12)."""
    folder = Path(folder)
    if folder.is_dir():
        for p in folder.glob("*.log"):
            if p.is_file():
                _PREVIOUS_LOG_BYTES[p.resolve()] = p.stat().st_size


def _drop_previous_log_lines(folder: Path) -> None:
    """Remove the previous run's lines from the front of ``folder``'s job logs, in place (the
    job's log handler appends: its next line goes after what is kept)."""
    for p in Path(folder).glob("*.log"):
        n = _PREVIOUS_LOG_BYTES.pop(p.resolve(), 0)
        if n and p.is_file():
            with open(p, "r+b") as f:
                f.seek(n)
                ours = f.read()
                f.seek(0)
                f.write(ours)
                f.truncate()


def claim(folder: Path, overwrite: bool = False) -> None:
    """Make ``folder`` this run's: create it, refuse it (InputError) when it holds another
    run's files unless ``overwrite``, and create ``summary.json`` exclusively."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError("is not a folder", str(folder))
    linked = hydra_link_refusal(folder)
    if linked is not None:
        raise InputError(linked, str(folder))
    used = used_entries(folder)
    if used:
        if not overwrite:
            raise InputError(used_refusal(folder, used), str(folder))
        refused = overwrite_refusal(folder)
        if refused is not None:
            raise InputError(refused, str(folder))
        ours, _ = _removable(folder, top=True)
        stuck = _unremovable(folder, ours)
        if stuck is not None:   # nothing removed: the previous run is left whole (it was half removed; round 26)
            raise OSError(errno.EPERM, f"overwrite=true cannot remove the previous run: {stuck[0]} is {stuck[1]}; "
                          "nothing of that run was removed (the folder holds it as it was)")
        # the previous run's summary first: if a removal fails below, no summary is left saying
        # "completed" beside results that are gone (probe of issue 12, round 10)
        for p in sorted(ours, key=lambda q: q.name != SUMMARY):
            try:
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
            except OSError as exc:
                _removal_failed(folder, p, exc)
        _drop_previous_log_lines(folder)
        if not _own_outcome(folder):   # a sweep job's outcome in Hydra's record: the previous job's
            try:                        # "interrupted" stood beside this run's completed summary (round 31)
                (folder / OUTCOME).unlink(missing_ok=True)
            except OSError as exc:
                _removal_failed(folder, folder / OUTCOME, exc)
    folder.mkdir(parents=True, exist_ok=True)
    if refused_summary(folder / SUMMARY):   # a refused run's: replaced by this run's, and so are its log
        (folder / SUMMARY).unlink()          # lines (its "failed (exit 2)" line stood above this run's; round 19)
        _drop_previous_log_lines(folder)
    try:
        os.close(os.open(folder / SUMMARY, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
    except FileExistsError:
        raise InputError("another run has just started in this folder", str(folder)) from None


#: Linux's inode flags (linux/fs.h): FS_IOC_GETFLAGS, and the immutable and append-only flags
#: (``chattr +i``, ``chattr +a``), under which not even root can remove a file or an entry of a folder
_FS_IOC_GETFLAGS, _FS_IMMUTABLE_FL, _FS_APPEND_FL = 0x80086601, 0x10, 0x20


def pinned(path: Path) -> str | None:
    """Why ``path`` (a file or folder, not followed if a link) is immutable or append-only, or None
    (also where the file system has no such flags)."""
    import fcntl
    import struct

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except OSError:   # a link, a socket, unreadable: its removal decides
        return None
    try:
        flags = struct.unpack("i", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, b"\0" * 8)[:4])[0]
    except OSError:
        return None
    finally:
        os.close(fd)
    if flags & _FS_IMMUTABLE_FL:
        return "immutable (chattr +i)"
    if flags & _FS_APPEND_FL:
        return "append-only (chattr +a)"
    return None


def _unremovable(folder: Path, ours: list[Path]) -> tuple[Path, str] | None:
    """(the first path of ``ours`` (entries of ``folder``, folders with all they hold) that cannot
    be removed, why), or None: checked before ``overwrite=true`` removes anything.  An immutable
    file stopped the removal halfway, and the new run's failed summary stood beside the previous
    run's results (independent probe of issue 12, round 26).  Checked: the flags of the folders
    and files and the folders' write access; a removal can still fail for another reason
    (``_removal_failed``)."""
    todo = [folder, *ours]
    while todo:
        p = todo.pop()
        why = pinned(p)
        if why is None and p.is_dir() and not p.is_symlink():
            try:
                entries = [] if p == folder else list(p.iterdir())
            except OSError as exc:
                return p, f"not readable ({exc.strerror or exc})"
            if (entries or p == folder) and not os.access(p, os.W_OK):
                why = "not writable"
            todo.extend(entries)
        if why is not None:
            return p, why
    return None


def _removal_failed(folder: Path, p: Path, exc: OSError) -> None:
    """``overwrite=true`` could not remove ``p`` of the previous run (an immutable file, a read-only
    disk): the folder held half of that run and no summary (independent probe of issue 12, round 25).
    A failed summary (``refused``: no step ran) says what was left; OSError naming the file."""
    where = exc.filename if isinstance(exc.filename, str) and os.path.isabs(exc.filename) else str(p)
    try:
        left = ", ".join(sorted(q.name for q in folder.iterdir() if not _hydras(q))) or "nothing"
    except OSError:
        left = "?"
    msg = (f"overwrite=true could not remove the previous run's {where}: {exc.strerror or exc}; the folder holds "
           f"what was left of that run ({left})")
    try:
        write_json(folder / SUMMARY, {"status": "failed", "error": msg, **owner(),
                                      REFUSED: "the previous run could not be removed: no step ran"})
    except OSError:
        pass
    raise OSError(exc.errno, msg, where) from exc


def remove_tmp(folder: Path) -> None:
    """Remove temporary files (``*.tmp*``) left in ``folder`` and its sub-folders."""
    folder = Path(folder)
    if folder.is_dir():
        for p in folder.rglob("*.tmp*"):
            if p.is_file():
                p.unlink(missing_ok=True)


#: free disk a run folder's filesystem must have before Hydra starts: Hydra's .hydra/ files, the
#: running summary and the room held for the ending (hairexp/outputs/folder.py RESERVE_BYTES)
MIN_FREE_BYTES = 256 << 10


#: names a run folder keeps for Hydra's record and the launch lock (hairexp/outputs/folder.py)
RESERVED_NAMES = (".hydra", ".lock")


def reserved_part(path: str) -> str | None:
    """Why ``path`` cannot be a run, sweep or job folder when one of its parts is a name a run
    folder keeps for itself (``.hydra``, ``.lock``), or None: a run in ``<dir>/.hydra`` was taken
    for Hydra's record of ``<dir>``, which a later run then found empty and wrote into (probe of
    issue 12, round 12)."""
    bad = next((part for part in Path(path).parts if part in RESERVED_NAMES), None)
    if bad is None:
        return None
    return f"its part {bad} is a name a run folder keeps for {'Hydra' if bad == '.hydra' else 'the launch lock'}"


def unusable_folder(path: str) -> str | None:
    """Why ``path`` cannot be (or be made) a writable folder, or None.  Nothing is left behind:
    writability is tried with a temporary folder, removed at once."""
    p = Path(os.path.abspath(path))
    reserved = reserved_part(path)
    if reserved is not None:
        return reserved
    probe = p
    try:
        while True:   # the deepest part of the path that exists
            try:
                os.stat(probe)
                break
            except FileNotFoundError:
                if os.path.islink(probe):   # mkdir then failed with FileExistsError's traceback (probe of issue 12)
                    return f"{probe} is a symbolic link to {os.readlink(probe)}, which does not exist"
                if probe.parent == probe:
                    return f"{probe} does not exist"
                probe = probe.parent
            except NotADirectoryError:   # a file on the way: its parent exists
                probe = probe.parent
            except PermissionError:
                return f"{probe} cannot be reached: permission denied"
        if not probe.is_dir():
            return f"{probe} is a file" if probe == p else f"{probe} is a file, not a folder to create it in"
        # append-only (chattr +a): the probe folder could not be removed, and TemporaryDirectory's clean-up
        # recursed into a RecursionError traceback of 6,615 lines (independent probe of issue 12, round 29)
        why = pinned(probe)
        if why is not None and (probe == p or why.startswith("immutable")):
            return f"{probe} is {why}: a run replaces and removes its files in its folder" if probe == p else \
                f"{probe} is {why}: no folder can be made in it"
        if why is None:   # (an append-only parent takes new folders: not tried, its probe could not be removed)
            os.rmdir(tempfile.mkdtemp(dir=probe, prefix=".hairexp-probe-"))
        st = os.statvfs(probe)
        free = st.f_bavail * st.f_frsize
        if free < MIN_FREE_BYTES:   # Hydra's own .hydra/ writes would fail with a traceback, exit 1 (probe of issue 12)
            return f"its disk has {free / 1024:.0f} kB free, less than the {MIN_FREE_BYTES >> 10} kB a run needs to start"
    except OSError as exc:
        why = exc.strerror or errno.errorcode.get(exc.errno or 0, type(exc).__name__)
        return f"cannot create a folder in {probe}: {why}" if probe != p else f"cannot write in {p}: {why}"
    return None
