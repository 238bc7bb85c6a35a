"""Export a config's scene as a USD stage in the input layout (README "USD scenes").

    python -m hairexp.io.export_scene scene.usda experiment=goaling controller=tracking guides.count=3

The overrides compose as for ``python -m hairexp`` (conf/); the stage holds the body motion,
the detail hair at rest, the guide animation of frames 0..frames at fps (``guides.*``) and the
colliders.  ``python -m hairexp experiment=from_usd scene.usd=scene.usda`` runs it.
Exit codes: 0 written (or ``--help``), 2 bad input or arguments (``hairexp: error: ...``).
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import replace
from pathlib import Path

from hairexp.app.assemble import assemble_scene
from hairexp.app.config import compose_config
from hairexp.errors import InputError
from hairexp.io.usd_write import write_scene_usd
from hairexp.model.dynamic_body import authoring_motion

log = logging.getLogger(__name__)


def export_scene(cfg, path) -> tuple:
    """Build ``cfg``'s scene and guides (``assemble_scene``, the run's assembly path, without the
    settle phase: the stage holds the elastic rest shape) and write them to ``path``; (scene, guides).
    An unwritable ``path`` is an InputError naming it, before anything is built."""
    check_writable(path)
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
        raise InputError(f"cannot write the USD stage: {' '.join(str(exc).split())}", str(path)) from exc
    return scene, guides


def check_writable(path) -> None:
    """``path`` can be written: its directory exists and is writable, and it is not a directory."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise InputError("is a directory: give the path of a .usda/.usdc/.usd file", str(path))
    if not parent.is_dir():
        raise InputError(f"cannot write the USD stage: no such directory {parent}", str(path))
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise InputError("cannot write the USD stage: permission denied", str(path))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    usage = "usage: python -m hairexp.io.export_scene OUT.usda|OUT.usdc|OUT.usd [key=value ...]"
    if args and args[0] in ("-h", "--help"):
        print(usage + "\n\n" + __doc__.strip())
        return 0
    if not args or "=" in args[0] or args[0].startswith("-"):
        why = ("the path of the stage to write is required" if not args or "=" in args[0]
               else f"unknown option {args[0]}")
        print(f"{usage}\nhairexp: error: {why}", file=sys.stderr)
        return 2
    try:
        cfg = compose_config(args[1:])
    except Exception as exc:  # unknown key, wrong type (Hydra's message, or the schema check's): bad input
        print(f"hairexp: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    try:
        scene, guides = export_scene(cfg, args[0])
    except (InputError, ValueError) as exc:
        print(f"hairexp: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args[0]}: {scene.strands.n_strands} strands, {guides.n_guides} guides, {guides.n_frames - 1} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
