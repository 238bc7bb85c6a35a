"""Export a config's scene as a USD stage in the input layout (README "USD scenes").

    python -m hairexp.io.export_scene scene.usda experiment=goaling controller=tracking guides.count=3
    python -m hairexp.io.export_scene --force scene.usda ...   (replace an existing file)

The overrides compose as for ``python -m hairexp`` (conf/); the stage holds the body motion,
the detail hair at rest, the guide animation of frames 0..frames at fps (``guides.*``) and the
colliders.  ``python -m hairexp experiment=from_usd scene.usd=scene.usda`` runs it.
An existing file is never replaced without ``--force`` (``-f``).
Exit codes: 0 written (or ``--help``), 2 bad input or arguments, or an existing file without
``--force`` (``hairexp: error: ...``), 4 a path that cannot be written (its folder missing, a file,
or not writable), as for a run folder of ``python -m hairexp``.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path

from hairexp.app import startup
from hairexp.app.assemble import assemble_scene
from hairexp.app.config import compose_config
from hairexp.app.signals import InterruptSignals, exit_code
from hairexp.errors import InputError, Interrupted, ScratchError
from hairexp.io.usd_write import FORMATS, write_scene_usd
from hairexp.outputs.folder import pinned
from hairexp.model.dynamic_body import authoring_motion

log = logging.getLogger(__name__)


#: frames at most in an exported stage (``guard.allow_large=true`` lifts it): 100,000 frames of
#: Celia's 3 guides of 26 vertices are about 100 MB of crate
MAX_EXPORT_FRAMES = 100_000


class DestinationError(InputError):
    """The stage's path cannot be written (exit 4 on the command line)."""


def export_scene(cfg, path, overwrite: bool = False) -> tuple:
    """Build ``cfg``'s scene and guides (``assemble_scene``, the run's assembly path, without the
    settle phase: the stage holds the elastic rest shape) and write them to ``path``; (scene, guides,
    frames written: 0..frames).
    An unwritable ``path`` (a DestinationError), or an existing file without ``overwrite``, is an
    InputError naming it, before anything is built."""
    check_writable(path, overwrite)
    if cfg.get("variants"):   # an experiment's base config, said as assemble says it (probe of issue 12, round 14)
        log.warning("the config has %d variant(s) (%s); the stage holds its base scene, without any variant's "
                    "overrides (variants=[] silences this)", len(cfg.variants), ", ".join(str(v.name) for v in cfg.variants))
    if float(cfg.scene.settle or 0) > 0:   # dropped without a word (probe of issue 12, round 14)
        log.warning("scene.settle=%g not used: the stage holds the hair at its elastic rest shape, unsettled; give "
                    "scene.settle to the run that reads the stage (experiment=from_usd scene.usd=%s scene.settle=%g)",
                    float(cfg.scene.settle), path, float(cfg.scene.settle))
    frames = cfg.get("frames")
    if isinstance(frames, int) and frames > MAX_EXPORT_FRAMES and not bool(cfg.guard.allow_large):
        # 2e7 frames ran for minutes and grew without a word, where the run itself is refused (probe, round 15)
        raise InputError(f"is {frames}: a stage of more than {MAX_EXPORT_FRAMES:,} frames (every frame's guides are "
                         "built and written) is refused; export fewer frames, or set guard.allow_large=true", "frames")
    cfg, scene, guides = assemble_scene(cfg, settle=False)
    ref = authoring_motion(scene.motion)
    if ref is not scene.motion:  # a dynamic block (scene.body): its motion is not known before a run
        log.warning("%s: the dynamic body is written at its initial pose; import the stage with "
                    "scene.body.dynamic=true (and its scene.body.*) to make it dynamic again", path)
        scene = replace(scene, motion=ref)
        guides.attach(ref)
    try:
        write_scene_usd(path, scene, guides, cfg.fps, cfg.frames)
    except (OSError, RuntimeError) as exc:   # pxr's Tf errors are RuntimeErrors
        raise DestinationError(f"cannot write the USD stage: {' '.join(str(exc).split())}", str(path)) from exc
    return scene, guides, int(cfg.frames)


def check_writable(path, overwrite: bool = False) -> None:
    """``path`` can be written: its folder exists and is writable, and it is not a folder; an
    existing file is refused unless ``overwrite`` (the command line's ``--force``)."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise DestinationError("is a directory: give the path of a .usda/.usdc/.usd file", str(path))
    if not parent.is_dir():
        above = parent
        while not above.exists() and above != above.parent:   # the nearest part that exists
            above = above.parent
        why = (f"{above} is a file, not a folder" if above.exists() and not above.is_dir()
               else f"no such directory {parent}")
        raise DestinationError(f"cannot write the USD stage: {why}", str(path))
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise DestinationError("cannot write the USD stage: permission denied", str(path))
    pinned_why = pinned(parent)
    if pinned_why is not None:   # its temporary stage could not be renamed nor removed: left behind (round 29)
        raise DestinationError(f"cannot write the USD stage: {parent} is {pinned_why} (the stage is written to a "
                               "temporary file there, then renamed)", str(path))
    if p.suffix not in FORMATS:   # checked after the whole scene was built (probe, round 15)
        raise InputError(f"a USD file name ends with one of {', '.join(FORMATS)}", str(path))
    if (p.exists() or p.is_symlink()) and not overwrite:
        raise InputError("the file exists; give --force to replace it, or another path", str(path))


def main(argv: list[str] | None = None, command: bool = False) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    usage = "usage: python -m hairexp.io.export_scene [--force] OUT.usda|OUT.usdc|OUT.usd [key=value ...]"
    if any(a in ("-h", "--help") for a in args):
        print(usage + "\n\n" + __doc__.strip())
        return 0
    force = any(a in ("-f", "--force") for a in args)
    args = [a for a in args if a not in ("-f", "--force")]
    flag = next((a for a in args if a.startswith("-") and "=" not in a), None)
    paths = [a for a in args if "=" not in a and not a.startswith("-")]
    if flag is None and len(paths) == 1 and args and "=" in args[0]:   # the path after the overrides: taken
        args = paths + [a for a in args if a != paths[0]]   # (it said the path was missing; probe, round 28)
    if not args or "=" in args[0] or flag is not None:
        why = ("the path of the stage to write is required" if flag is None
               else f"unknown option {flag} (the options are --force and --help)")
        print(f"hairexp: error: {why} ({usage})", file=sys.stderr)   # one line (probe of issue 12, round 16)
        return 2
    launch = [a for a in args[1:] if a.lstrip("+~").startswith(("hydra.", "overwrite="))]
    if launch:   # accepted and ignored without a word (probe of issue 12, round 14)
        log.warning("%s not used: the exporter writes one stage at the path given (--force replaces an existing "
                    "file); hydra.* and overwrite are a run's", ", ".join(launch))
        args = [args[0]] + [a for a in args[1:] if a not in launch]
    try:
        cfg = compose_config(args[1:])
    except Exception as exc:  # unknown key, wrong type (Hydra's message, or the schema check's): bad input
        print(f"hairexp: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    # a signal once the export has ended, after its handlers below are removed, says what was written
    # (it said the early handler's "while starting; nothing was run or written" after a stage had
    # replaced the old file; independent probe of issue 12, round 26)
    # (``command``: this process is the command; a caller's process keeps its own handlers)
    start = time.time()
    if command and startup.install(force=True):
        startup.begun("the export", f"{args[0]} was written whole if the export said 'wrote {args[0]}'")
    code = _export(cfg, args[0], force, start)
    if command:
        startup.ended(code, f"{args[0]} was written whole" if code == 0 or _written_since(args[0], start)
                      else f"nothing was written to {args[0]}")
    return code


def _written_since(path: str, start: float) -> bool:
    """Whether the stage at ``path`` was written by this export (begun at ``start``): a signal just
    after the write (its file is renamed into place whole, or not at all)."""
    p = Path(path)
    return p.is_file() and p.stat().st_mtime >= start - 1


def _export(cfg, path: str, force: bool, start: float) -> int:
    """The export of ``main`` and its exit code; its lines on the standard streams."""
    try:
        # a signal ends the export with one line, its temporary file removed (Ctrl-C printed a
        # KeyboardInterrupt traceback, SIGTERM left a 1.6 MB *.tmp.usda; independent probe of issue 12, round 21)
        with InterruptSignals():
            scene, guides, frames = export_scene(cfg, path, overwrite=force)
            # a full or closed stdout: the entry point's guarded streams (hairexp/app/streams.py) say it, exit 4
            print(f"wrote {path}: {scene.strands.n_strands} strands, {guides.n_guides} guides, {frames} frames "
                  f"(0..{frames})")
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
        print(f"hairexp: interrupted by {signal.Signals(signum).name} "
              + (f"after {path} was written" if _written_since(path, start)
                 else f"while exporting; nothing was written to {path}"),
              file=sys.stderr)
        return exit_code(signum)
    except (InputError, ValueError) as exc:
        print(f"hairexp: error: {exc}", file=sys.stderr)
        return 4 if isinstance(exc, DestinationError) else 2
    except OSError as exc:   # the guide frame store (TMPDIR) on a full disk or past ulimit -f: a traceback, exit 1 (round 20)
        if isinstance(exc, ScratchError):
            print(f"hairexp: cannot {'read a temporary file back' if exc.reading else 'write a temporary file'}: {exc} "
                  "(a full disk, or a file-size limit: ulimit -f; TMPDIR chooses the folder); nothing was written to "
                  f"{path}", file=sys.stderr)
        else:
            print(f"hairexp: error: {path}: {exc}", file=sys.stderr)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main())
