"""The guide animation of a run from ``cfg.guides``: the source (hairexp/guides/animation.py for
``rigid``, ``scaled``, ``keyframed`` and ``file``; here the ``simulated`` coarse guide simulation
and the ``usd`` stage's guide prim), then the artist's edits (hairexp/guides/authoring.py)."""

from __future__ import annotations

import copy
import logging

import numpy as np

from hairexp.app.config import GuidesConfig
from hairexp.model.builders import check_counts
from hairexp.errors import ExtentError, InputError, SimulationError, choice_name, regular_file
from hairexp.guides.animation import EDITS_MEMBER, GuideAnimation, carried_guides, file_guides, rest_guides
from hairexp.guides.authoring import apply_edits, keyframed_positions
from hairexp.guides.store import FrameStore
from hairexp.model.dynamic_body import authoring_motion
from hairexp.model.scene import Scene
from hairexp.model.rigid import motion_poses
from hairexp.model.strands import Strands
from hairexp.physics.schedule import step_schedule
from hairexp.physics.settle import settle_seconds, settle_state, settle_step, settled_scene
from hairexp.physics.simulator import Simulator


def source_guides(cfg, scene, frames: int, fps: float) -> GuideAnimation:
    """Guide animation for frames 0..frames from ``cfg.guides`` (see module doc; ``keyframed``:
    ``authoring.keyframed_positions``), before the edits."""
    g = cfg.guides
    source = choice_name(g.source)
    motion = authoring_motion(scene.motion)   # a dynamic body: its initial pose held still
    if source == "file":
        anim = read_guide_file(g, scene.motion, frames, fps)
        unused_shape_keys(g, anim, "guides.file")
        return anim   # every frame's extent checked by GuideAnimation
    if source == "usd":  # the guide prim of the stage scene.usd
        from hairexp.io.usd_read import read_guides   # pxr is imported only for USD scenes

        anim = read_guides(cfg, scene, frames, fps)
        unused_shape_keys(g, anim, "the stage's guide prim")
        return anim
    body = rest_guides(cfg.scene, g.count, g.n_vertices, g.layout_radius)
    offsets = np.arange(g.count + 1) * g.n_vertices
    if source == "simulated":
        return simulate_guides(cfg, scene, body, offsets, frames, fps)
    if source == "keyframed":
        pos, offsets = keyframed_positions(g, motion, frames, fps)
        return GuideAnimation(pos, offsets, fps, where="guides.keyframes", motion=scene.motion)
    pos = carried_guides(g, body, offsets, motion, frames, fps, scaled=source == "scaled")
    return GuideAnimation(pos, offsets, fps, motion=scene.motion)


def read_guide_file(g, motion, frames: int, fps: float) -> GuideAnimation:
    """The guide animation of ``guides.file`` (``check_guide_file``, then
    ``animation.file_guides``); its errors are named ``guides.file=<path>...``."""
    check_guide_file(g.file)
    try:
        return file_guides(str(g.file), motion, frames, fps)
    except InputError as exc:   # the file's own errors name the path: say which key it is
        where = exc.where or ""
        if where.startswith(str(g.file)) and not where.startswith("guides.file="):
            raise InputError(str(exc)[len(where) + 2:], f"guides.file={where}") from exc
        raise


def unused_shape_keys(g, anim: GuideAnimation, source: str) -> None:
    """A warning when ``guides.count`` or ``guides.n_vertices``, set to other than the schema's
    default, differ from the guides a file or stage holds: they shape built guides only, and were
    ignored without a word (probe of issue 12, round 12)."""
    counts = np.diff(anim.offsets)
    held = {"count": len(counts), "n_vertices": int(counts[0]) if len(set(counts.tolist())) == 1 else None}
    for key, n in held.items():
        # a value left at the schema's default was not chosen: no warning for every stage or file
        if n is not None and int(getattr(g, key)) != n and int(getattr(g, key)) != getattr(GuidesConfig, key):
            logging.getLogger("hairexp").warning(
                "guides.%s=%s is not used: the guides come from %s, which holds %s (guides.count and "
                "guides.n_vertices shape the guides hairexp builds)", key, getattr(g, key), source,
                f"{n} guides" if key == "count" else f"guides of {n} vertices")


#: dtype kinds of a guide npz's arrays (numpy's ``dtype.kind``): real numbers, integer offsets
GUIDE_FILE_KINDS = {"guide_positions": ("f", "floating-point numbers (float64, m)"),
                    "guide_offsets": ("iuf", "integers"), "fps": ("iuf", "a real number (frames per second)")}


def check_guide_file(path) -> None:
    """The dtypes of a guide npz's arrays, read from their headers (no data is loaded): complex
    positions would lose their imaginary part without an error, strings or booleans would be read
    as numbers, and integer positions are not metres (millimetres or a grid's indices).  A file that cannot be read this way is left to ``file_guides``, which names it."""
    import zipfile

    regular_file(path, f"guides.file={path}", "guide npz")   # a FIFO would block the zip reader
    try:
        with zipfile.ZipFile(path) as z:
            stems = (n[:-4] if n.endswith(".npy") else n for n in z.namelist())
            others = sorted(n for n in stems if n not in GUIDE_FILE_KINDS and n != EDITS_MEMBER)
            headers = {}
            for name in GUIDE_FILE_KINDS:
                if f"{name}.npy" not in z.namelist():
                    continue
                with z.open(f"{name}.npy") as f:
                    version = np.lib.format.read_magic(f)
                    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                        np.lib.format.read_array_header_2_0
                    headers[name] = read(f)[2]
    except Exception:  # noqa: BLE001  (not a zip, a bad header: file_guides says what the file is)
        return
    for name, dtype in headers.items():
        kinds, what = GUIDE_FILE_KINDS[name]
        if dtype.kind not in kinds:
            raise InputError(f"{name} has dtype {dtype}, expected {what}", f"guides.file={path}")
    if others:   # ignored without a word (own probe, 2026-12-05): a misspelt optional array would be
        logging.getLogger("hairexp").warning(
            "guides.file=%s: %s not read (a guide file holds guide_positions, guide_offsets and fps)",
            path, ", ".join(others) + (" is" if len(others) == 1 else " are"))
    pos = headers.get("guide_positions")
    if pos is not None and pos.kind == "f" and pos.itemsize < 4:   # accepted without a word (probe of issue 12, round 18)
        eps = float(np.finfo(pos).eps)
        logging.getLogger("hairexp").warning(
            "guides.file=%s: guide_positions are %s, about %d significant digits (a step of %.2g mm at 1 m): "
            "the guides are read as they are; save them as float64 (or float32) for exact positions",
            path, pos, int(np.finfo(pos).precision), eps * 1e3)


def check_simulated_guides(cfg) -> None:
    """The keys of simulated guides checked before their simulation (InputError)."""
    if cfg.guides.n_vertices < 3:
        raise InputError("simulated guides need >= 3 vertices (two are held by the body)", "guides.n_vertices")
    check_counts(1, int(cfg.guides.n_vertices), float(cfg.scene.length), key="guides.n_vertices")   # as long as the hair


def simulate_guides(cfg, scene, body: np.ndarray, offsets: np.ndarray, frames: int, fps: float) -> GuideAnimation:
    """Free simulation of the guide strands (eq. 5, same solver settings) at the scene's rate.
    With ``guides.collide`` the guides collide with the scene's colliders (the collision stage
    of ``collision.*``, without hair-hair), so that a coarse guide is dragged over an object as
    the hair is; otherwise they pass through it.  With ``scene.settle`` > 0 the guides first
    settle under gravity for that time, the body (and colliders) held at their t = 0 poses, and
    the animation starts from the settled guides at rest (frame 0).  The other guide sources
    (rigid, scaled, keyframed, file, usd) are not settled: they are used as given."""
    check_simulated_guides(cfg)
    motion = authoring_motion(scene.motion)
    world = motion.transform(body, 0.0)
    strands = Strands.from_polylines(world, np.diff(offsets), scene.material.linear_density, where="guides")
    collide = bool(getattr(cfg.guides, "collide", False)) and bool(scene.colliders)
    gscene = Scene(scene.name + "_guides", strands, scene.material, motion, scene.gravity, body,
                   list(scene.colliders) if collide else [])
    ccfg = None
    if collide:
        ccfg = copy.deepcopy(cfg.collision)
        ccfg.hair_hair = False
    n_sub, dt = step_schedule(fps, cfg.solver.dt, frames)
    seconds = settle_seconds(cfg.scene)
    if seconds > 0:   # scene.settle: the guides settle as the detail hair does (hairexp/physics/settle.py)
        gscene = settled_scene(gscene, settle_state(gscene, cfg.solver, ccfg, seconds, settle_step(cfg.scene),
                                                    what="guides"))
    sim = Simulator(gscene, cfg.solver, collision_cfg=ccfg)
    state = sim.initial_state()
    out = FrameStore(state.x.shape)   # frame by frame to a temporary file: memory flat in the frames
    out.append(state.x)
    for f in range(frames):
        try:
            for _ in range(n_sub):
                state, _ = sim.step(state, dt)
        except SimulationError as exc:   # said to be the guides', not the hair's (no hair step has run)
            raise SimulationError(f"the guide simulation (guides.source=simulated), frame {f + 1} of {frames}: "
                                  f"{exc}") from exc
        out.append(state.x)
    try:
        return GuideAnimation(out, offsets, fps, motion=scene.motion)
    except ExtentError:   # guides placed far off by the config's values (build_guides names those keys)
        raise
    except InputError as exc:   # a guide the simulation folded or stretched out of shape: the simulation's failure
        # (it was called bad input, exit 2, without a word that the guides were simulated; probe of issue 12, round 10)
        raise SimulationError(f"the guide simulation (guides.source=simulated) produced guides that cannot be tracked: "
                              f"{exc}; the guides are simulated with the hair's solver.* settings (try a smaller "
                              "solver.dt, more solver.max_iterations, or another guides.source)") from exc


def edits_summary(edits) -> str:
    """``guides.edits`` in one line: each edit's kind, guides and key times."""
    def one(e) -> str:
        kind = choice_name(e.kind)
        return f"{kind} of guide {e.guide} keyed at {[float(t) for t in e.times]} s"
    return f"{len(edits)} edit{'s' if len(edits) != 1 else ''}: " + "; ".join(one(e) for e in edits)


def build_guides(cfg, scene, frames: int, fps: float, source_of=None) -> GuideAnimation:
    """The guide animation a run tracks and saves as guides.npz: the source's
    (``source_guides``) with the authored edits ``guides.edits`` applied in order
    (``authoring.apply_edits``; paper 4: the artist edits a coarse best-guess guide simulation by
    keyframing; ``source=keyframed`` keys the guides directly).  ``source_of``: a stand-in for
    ``source_guides`` with its arguments (``hairexp.app.assemble``: an experiment's variants share
    one guide simulation)."""
    try:
        anim = (source_of or source_guides)(cfg, scene, frames, fps)
    except ExtentError as exc:
        if exc.where != "guides":
            raise
        # procedural guides: the keys that placed them, not only "guides" (probe of issue 12)
        raise InputError(f"{str(exc).split(': ', 1)[1]}; these guides are built from scene.length, scene.root_center, "
                         "scene.root_radius x guides.layout_radius and the body's motion (scene.motion): check those "
                         "values", "guides") from exc
    if cfg.guides.edits and anim.edits_applied:
        usd = choice_name(cfg.guides.source) == "usd"
        source = f"scene.usd={cfg.scene.usd} (its guides)" if usd else f"guides.file={cfg.guides.file}"
        logging.getLogger("hairexp").warning(
            "%s was saved by a run that had applied its guides.edits (%s); this run's %d guides.edits are applied to "
            "it again: give guides.edits=[] to track %s", source, anim.edits_applied,
            len(cfg.guides.edits), "the stage's guides as they are" if usd else "the file as it is")
    if cfg.guides.edits:
        done = edits_summary(cfg.guides.edits)
        pos = apply_edits(anim.frames, anim.offsets, anim.fps, authoring_motion(scene.motion), cfg.guides.edits)
        before = anim.edits_applied
        anim = GuideAnimation(pos, anim.offsets, anim.fps, where="guides.edits", motion=scene.motion)
        anim.edits_applied = f"{before}; then {done}" if before else done
    anim.interpolation = choice_name(cfg.guides.interpolation)
    if choice_name(cfg.controller.name) != "free":
        warn_far_guides(scene, anim, frames)
    return anim


#: a guide root farther than this fraction of the hair's length from where the body carries it is said
ROOT_DRIFT = 0.01
#: ... and farther than this fraction is an error (the stress matrix's teleported guides jump 0.33 of it)
MAX_ROOT_DRIFT = 0.5


def warn_far_guides(scene, anim, frames: int | None = None) -> None:
    """An InputError when a guide's root at frame 0 is farther from every hair root than the hair
    is long: the guides are likely in another space or unit than the hair (a guide file or stage
    made for another scene; it was a warning, and the run ended "completed" at 515 % stretch;
    a warning when they look authored tip to root).  Else, with a keyframed body, a warning when
    a guide's root leaves the body (farther than ROOT_DRIFT x the hair's length from where the
    body carries its frame-0 root, at any frame of the run: 0..``frames``, not a longer file's later
    frames, which it never reads; round 28), an InputError beyond MAX_ROOT_DRIFT x it."""
    s = scene.strands
    hair_roots = scene.initial_positions()[np.asarray(s.offsets[:-1])]
    length = float(np.sum(s.rest_lengths)) / max(1, len(s.offsets) - 1)
    guide_roots = np.asarray(anim.frames[0])[np.asarray(anim.offsets[:-1])]
    d = np.linalg.norm(guide_roots[:, None, :] - hair_roots[None, :, :], axis=-1).min(axis=1)
    far = np.flatnonzero(d > length)
    tips = scene.initial_positions()[np.asarray(s.offsets[1:]) - 1]
    d_tip = np.linalg.norm(guide_roots[:, None, :] - tips[None, :, :], axis=-1).min(axis=1)
    if far.size and np.all(d_tip[far] < 0.5 * d[far]):   # the guides' roots at the hair's tips: reversed curves
        g = int(far[0])
        logging.getLogger("hairexp").warning(
            "guides: guide %d's root is %.3g m from the nearest hair root but %.3g m from a hair tip at frame 0 (%d of "
            "%d guides): the hair curves look authored tip to root; a curve's first vertex is its root (on the body)",
            g, d[g], d_tip[g], far.size, len(d))
        return
    if far.size:   # an error since round 12 of issue 12's probe: the run "completed" with the hair at 515 % stretch
        g = int(far[0])
        raise InputError(f"guide {g}'s root is {d[g]:.3g} m from the nearest hair root at frame 0, farther than the "
                         f"hair is long ({length:.3g} m; {far.size} of {len(d)} guides): the tracking would tear the "
                         "hair off its roots; check that the guides are in the hair's space and units", "guides")
    if scene.body is not None:   # a dynamic body's poses are known only as the run goes
        return
    # the guides' roots ride the body: where the body carries their frame-0 roots, at every frame
    # (guides left from another animation of the body pull the hair off its roots; probe of issue 12)
    motion, fps = scene.motion, float(anim.fps)
    R0, T0 = motion.pose(0.0)
    local = (guide_roots - T0) @ R0
    tol = ROOT_DRIFT * length
    warned = False
    n = len(anim.frames) if frames is None else min(len(anim.frames), int(frames) + 1)
    roots = np.asarray(anim.offsets[:-1])
    for f, R, T, P in _frames_with_poses(anim, motion, 1, n):
        drift = np.linalg.norm(P[roots] - (local @ R.T + T), axis=1)
        if drift.max() > MAX_ROOT_DRIFT * length:   # guides made on another body motion (probe, round 12)
            g = int(np.argmax(drift))
            raise InputError(f"guide {g}'s root is {drift[g]:.3g} m from where the body carries it at frame {f} "
                             f"(t = {f / fps:.4g} s), more than {MAX_ROOT_DRIFT:g} of the hair's length: the guides do "
                             "not ride this body, and the tracking would tear the hair off its roots; make the guides "
                             "with this body motion", "guides")
        if drift.max() > tol and not warned:   # said once; the later frames are still checked for the error
            warned = True
            g = int(np.argmax(drift))
            logging.getLogger("hairexp").warning(
                "guides: guide %d's root is %.3g m from where the body carries it at frame %d (t = %.4g s; more than "
                "%g of the hair's length): the guides do not ride the body, and the tracking will pull the hair near "
                "its roots after them; check that the guides were made with this body motion", g, drift[g], f, f / fps,
                ROOT_DRIFT)


#: frames read and posed together by ``_frames_with_poses``
POSE_BLOCK = 256


def _frames_with_poses(anim, motion, start: int, stop: int):
    """(f, R, T, frame f's positions) for frames start..stop - 1 of ``anim``, the body's poses at
    f / fps computed a block of frames at a time (``motion_poses``)."""
    fps = float(anim.fps)
    for a in range(start, stop, POSE_BLOCK):
        fs = np.arange(a, min(a + POSE_BLOCK, stop))
        R, T = motion_poses(motion, fs / fps)
        P = np.asarray(anim.frames[int(fs[0]):int(fs[-1]) + 1])
        for i, f in enumerate(fs):
            yield int(f), R[i], T[i], P[i]
