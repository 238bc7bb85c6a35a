"""Guide animations: G guide polylines with one shape per frame, rooted on the rigid body.

``GuideAnimation.shape_at(t)`` interpolates between frames when the time step is smaller than
the frame interval (``guides.interpolation``: ``catmull_rom``, the default, C1 in time; or
``linear``), and holds the first/last frame outside the animation.
Sources (``guides.source``): ``rigid`` (rest guides carried by the body), ``scaled`` (rest
guides scaled about their roots by keyframed factors, then carried by the body: the paper's
Fig. 2 shrinking guide), ``file`` (an npz with ``guide_positions`` (F, Vg, 3),
``guide_offsets`` (G + 1,) and ``fps``, such as a run's guides.npz), ``simulated`` (the rest
guides simulated as free strands with the scene's body motion, material and gravity: the
paper's "initial simulation on a coarse set of guide hairs using best-guess parameters"; with
``guides.collide`` they collide with the scene's colliders), ``usd`` (the guide prim of the
stage ``scene.usd``, hairexp/io/usd_read.py).  The sources that need the simulator or a USD
stage (``simulated``, ``usd``) and the dispatch over all of them are in hairexp/app/guides.py.

Guides are authored in the body frame.  On a dynamic body (``scene.body.dynamic``, paper 4
Stylization) the animation's world positions are those of the block held at its initial pose
(``DynamicBody.reference``: the pose is not known before the simulation), and ``shape_at`` carries
the body-frame guide with the live block: world = block pose at t x body-frame guide.  A
``simulated`` guide source on a dynamic body simulates the guides on the block held still.
"""

from __future__ import annotations

import math
import numbers
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from hairexp.errors import InputError, check_extent, real_array, regular_file
from hairexp.guides.store import BLOCK_BYTES, FrameStore
from hairexp.model.dynamic_body import authoring_motion
from hairexp.model.rigid import motion_poses
from hairexp.model.strands import check_folds, suspect_frames, validate_polylines


#: frames per second a guide animation and a run (hairexp/physics/schedule.py) may have: a guide
#: file at 1e-9 froze the guides, fps=1e-3 failed after the guide simulation (probes of issue 12)
MIN_FPS, MAX_FPS = 0.1, 1e5


def check_fps(fps: float) -> None:
    """An InputError naming ``fps`` when the run's frame rate is outside MIN_FPS .. MAX_FPS or not finite."""
    if not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        raise InputError(f"must be a finite number from {MIN_FPS:g} to {MAX_FPS:g} (frames per second), got {fps}",
                         "fps")

#: frames of an in-memory animation checked together (``suspect_frames``)
CHECK_BLOCK = 512

#: how ``shape_at`` interpolates between frames (``guides.interpolation``)
INTERPOLATIONS = ("catmull_rom", "linear")


class GuideAnimation:
    """``positions``: (F, Vg, 3) m, an array or a ``FrameStore`` (hairexp/guides/store.py: the
    frames kept in a temporary file, read a block at a time; the run's sources build one, so a
    long run's guides take the memory of one block); ``offsets`` (G + 1,); ``fps``.

    ``frames`` is what was given (read frame by frame: ``frames[f]``, iteration);
    ``positions`` is every frame as one array (loaded from a store on each access: for small
    animations and tests)."""

    #: between frames: "catmull_rom" (uniform Catmull-Rom in time: the cubic Hermite segment
    #: through frames f and f + 1 with the tangents (P_{f+1} - P_{f-1}) / 2 and (P_{f+2} - P_f) / 2,
    #: the first and last frames' missing neighbours reflected, P_{-1} = 2 P_0 - P_1; it passes
    #: through every frame and its velocity is continuous) or "linear" (the chord: the velocity jumps
    #: at every frame).  A tracked step that ends between frames (the trapezoidal stage of
    #: ``trbdf2``, substeps) takes its targets from it; with the chord, the trapezoidal stage's velocity
    #: 2 (x_g - x_n) / tau - v_n doubled each jump of the targets' velocity and the hair rang between
    #: the stages (README "Tracking performance")
    interpolation: str = "catmull_rom"
    #: a one-line account of the ``guides.edits`` already applied to these positions ("" for none):
    #: saved in guides.npz (``EDITS_MEMBER``) so that a run tracking that file again with the
    #: experiment's edits is warned that they are applied twice (probe of issue 12, round 34)
    edits_applied: str = ""

    def __init__(self, positions, offsets, fps: float, where: str = "guides", motion=None):
        self.where, self.fps = where, fps
        if isinstance(positions, FrameStore):
            if positions.dtype != np.float64:
                raise InputError(f"guide positions must be float64, got {positions.dtype}", where)
            self.frames = positions
        else:
            self.frames = real_array(positions, f"{where} positions")
        raw = real_array(offsets, f"{where} offsets") if not isinstance(offsets, np.ndarray) else offsets
        if raw.ndim != 1:   # "must be integers ..., got int64 (1, 4)" named the type for a shape (independent probe)
            raise InputError(f"guide offsets must be a 1-D array (G + 1,) of integers, got shape {raw.shape}: "
                             f"{raw.ravel()[:8].tolist()}", self.where)
        if raw.dtype.kind not in "iuf" or (raw.dtype.kind == "f" and not (
                np.isfinite(raw).all() and np.array_equal(raw, np.round(raw)))):
            raise InputError(f"guide offsets must be integers (G + 1,), got {raw.dtype} {raw.shape}: "
                             f"{raw.ravel()[:8].tolist()}", self.where)
        self.offsets = raw.astype(np.int64)
        shape = self.frames.shape
        if len(shape) != 3 or shape[-1] != 3 or shape[0] < 1:
            raise InputError(f"guide positions must have shape (frames, vertices, 3), got {tuple(shape)}",
                             self.where)
        counts = np.diff(self.offsets)
        if counts.size == 0 or self.offsets[0] != 0:
            raise InputError("guide offsets must start at 0 and name at least one guide", self.where)
        if isinstance(self.fps, bool) or not isinstance(self.fps, numbers.Real) or not (
                np.isfinite(self.fps) and MIN_FPS <= self.fps <= MAX_FPS):
            # 1e-9 (a frame every 30 years) froze the guides at their first frame without a word
            raise InputError(f"fps must be a number from {MIN_FPS:g} to {MAX_FPS:g} (frames per second), "
                             f"got {self.fps!r}", self.where)
        self.fps = float(self.fps)
        self._check_frame(0, self.frames[0], counts)
        n = len(self.frames)
        block = self.frames.per_block if isinstance(self.frames, FrameStore) else CHECK_BLOCK
        for a in range(1, n, block):   # the other frames a block at a time; those that may fail one by one
            P = np.asarray(self.frames[a:min(a + block, n)])
            for i in np.flatnonzero(suspect_frames(P, counts)):
                self._check_frame(a + int(i), P[i], counts)
        self._rest = np.array(self.frames[0])
        self._body_cache: dict[int, np.ndarray] = {}
        self.attach(motion)

    def _check_frame(self, f: int, P, counts) -> None:
        """InputError naming frame f of the guides for non-finite points, wrong shapes or counts,
        zero-length edges, points past MAX_COORDINATE or folds."""
        P, _ = validate_polylines(P, counts, f"{self.where} frame {f}", min_vertices=2, folds=False)
        check_extent(P, self.where, counts, frame=f)   # a point 1e30 away: a unit error, not a fold
        check_folds(P, counts, f"{self.where} frame {f}")

    @property
    def positions(self) -> np.ndarray:
        return self.frames if isinstance(self.frames, np.ndarray) else np.asarray(self.frames)

    def attach(self, motion) -> None:
        """Interpolate between frames in the body frame of ``motion`` and map back with its
        exact pose, so that the guide roots follow the body between frames as the detail
        hair roots do (a linear blend of world positions would cut corners when it turns).
        A dynamic body: the positions are in its ``reference`` pose (authoring), ``shape_at``
        maps them with the live block.  A frame's body-frame shape is computed when it is
        first needed (four frames are kept: a Catmull-Rom segment's)."""
        ref = None if motion is None else authoring_motion(motion)
        if ref is not None and not (callable(getattr(ref, "to_body", None)) and callable(getattr(ref, "pose", None))):
            # motion="x" was taken, and failed at the first shape_at (probe of issue 16)
            raise InputError(f"the body motion must be a rigid motion (hairexp.model RigidMotion, a scene's motion, or "
                             f"a dynamic body) or None, got {type(motion).__name__} {motion!r:.40}", self.where)
        self.motion = motion
        self._ref = ref
        self._body_cache = {}

    def _body(self, f: int) -> np.ndarray:
        """Frame f in the body frame of the attached motion."""
        B = self._body_cache.get(f)
        if B is None:
            B = self._ref.to_body(self.frames[f], f / self.fps)
            if len(self._body_cache) >= 4:
                self._body_cache.pop(next(iter(self._body_cache)))
            self._body_cache[f] = B
        return B

    @property
    def n_guides(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def rest(self) -> np.ndarray:
        return self._rest

    def guides(self, P: np.ndarray) -> list[np.ndarray]:
        return [P[a:b] for a, b in zip(self.offsets[:-1], self.offsets[1:])]

    def check_time(self, t: float, where: str) -> None:
        """InputError naming ``where`` when a controller that follows the guides is asked for a
        time outside the animation, by more than half a frame: ``shape_at`` holds the first and
        last frames there, and a step there tracked still guides and said converged (one frame:
        still guides, taken at any time)
        (``Simulator.step`` with a state at t = 1e6 or -1; probe of issue 16; ``Run.steps``
        refuses such a run before its first step)."""
        if self.n_frames == 1:   # one frame: still guides, a pose for all times
            return
        last = (self.n_frames - 1) / self.fps
        if not (-0.5 / self.fps <= t <= last + 0.5 / self.fps):
            raise InputError(f"the step reaches t = {t:g} s, outside the guide animation (0 .. {last:g} s, frames "
                             f"0..{self.n_frames - 1} at {self.fps:g} fps): the controller follows the guides; step a state "
                             "within it", where)

    def shape_at(self, t: float, motion=None) -> np.ndarray:
        """(Vg, 3) guide vertices at time t (between frames as ``interpolation`` says; before the
        first frame and after the last, that frame held, as a DCC holds an animation outside its
        range: a run checks that its guides reach its last frame, ``Run``); ``motion``:
        the body's poses at t when they are not those the animation was attached to (a dynamic
        body's step window, hairexp/model/dynamic_body.py)."""
        try:
            tf = math.nan if isinstance(t, (str, bytes)) else float(t)
        except (TypeError, ValueError):
            tf = math.nan
        if not math.isfinite(tf):
            raise InputError(f"shape_at's time must be a finite number of seconds, got {t!r}", self.where)
        u = float(np.clip(tf * self.fps, 0.0, self.n_frames - 1))
        f = min(int(np.floor(u)), self.n_frames - 2) if self.n_frames > 1 else 0
        src = (lambda k: self.frames[k]) if self.motion is None else self._body
        a = u - f
        if self.n_frames == 1:
            B = src(0)
        elif a == 0.0:
            B = np.array(src(f))
        elif self.interpolation == "linear" or self.n_frames == 2:
            B = (1 - a) * src(f) + a * src(f + 1)
        else:
            B = catmull_rom(src, f, a, self.n_frames)
        return B if self.motion is None else (motion or self.motion).transform(B, t)

    def save(self, f) -> None:
        """guides.npz (``guide_positions``, ``guide_offsets``, ``fps``, compressed as
        ``np.savez_compressed``) to the path or binary file ``f``, written a block of frames at
        a time."""
        if not (isinstance(f, (str, os.PathLike)) or callable(getattr(f, "write", None))):
            # save(None) said "'NoneType' object has no attribute 'write'" (probe of issue 16)
            raise InputError(f"save needs a path or a binary file open for writing, got {type(f).__name__} {f!r:.40}",
                             self.where)
        with zipfile.ZipFile(f, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
            with zf.open("guide_positions.npy", "w", force_zip64=True) as dst:
                np.lib.format.write_array_header_1_0(dst, {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float64)),
                                                           "fortran_order": False, "shape": tuple(self.frames.shape)})
                step = max(1, BLOCK_BYTES // max(1, 24 * self.frames.shape[1]))
                for start in range(0, self.n_frames, step):
                    dst.write(np.ascontiguousarray(self.frames[start:start + step]))
            extra = ((EDITS_MEMBER, np.asarray(self.edits_applied)),) if self.edits_applied else ()
            for name, a in (("guide_offsets", self.offsets), ("fps", np.asarray(self.fps))) + extra:
                with zf.open(f"{name}.npy", "w", force_zip64=True) as dst:
                    np.lib.format.write_array(dst, np.asanyarray(a), allow_pickle=False)


def catmull_rom(src, f: int, a: float, n: int) -> np.ndarray:
    """The uniform Catmull-Rom segment between frames f and f + 1 at 0 < a < 1 (cubic Hermite,
    tangents from the neighbouring frames; a missing neighbour at either end reflected:
    P_{-1} = 2 P_0 - P_1, P_n = 2 P_{n-1} - P_{n-2}).  ``src(k)``: frame k; n frames, n >= 3."""
    P1, P2 = src(f), src(f + 1)
    P0 = src(f - 1) if f > 0 else 2.0 * P1 - P2
    P3 = src(f + 2) if f + 2 < n else 2.0 * P2 - P1
    a2 = a * a
    a3 = a2 * a
    return ((2.0 * a3 - 3.0 * a2 + 1.0) * P1 + (-2.0 * a3 + 3.0 * a2) * P2
            + 0.5 * (a3 - 2.0 * a2 + a) * (P2 - P0) + 0.5 * (a3 - a2) * (P3 - P1))


def rest_guides(scene_cfg, count: int, n_vertices: int, layout_radius: float) -> np.ndarray:
    """(count * n_vertices, 3) straight rest guides in the body frame, rooted on a circle of
    ``layout_radius`` x the root radius (the disk centre for a single guide)."""
    if count < 1:
        raise InputError(f"must be >= 1, got {count}", "guides.count")
    if n_vertices < 2:
        raise InputError(f"must be >= 2, got {n_vertices}", "guides.n_vertices")
    d = np.asarray(scene_cfg.direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    center = np.asarray(scene_cfg.root_center, dtype=np.float64)
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 0, 1.0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    if count == 1:
        roots = center[None]
    else:
        phi = 2 * np.pi * np.arange(count) / count
        r = layout_radius * scene_cfg.root_radius
        if not r > 0:   # every guide on one line: its clusters coincide (probe of issue 12, round 14)
            raise InputError(f"is {layout_radius} with scene.root_radius={scene_cfg.root_radius}: the {count} guides would "
                             "all be rooted at the disk's centre, on one line; give both > 0 (or guides.count=1)",
                             "guides.layout_radius")
        roots = center + r * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)
    s = np.linspace(0.0, scene_cfg.length, n_vertices)
    return np.concatenate([r0 + s[:, None] * d for r0 in roots])


#: the optional member of a guide npz saying which guides.edits made it (a string; ``edits_applied``)
EDITS_MEMBER = "edits_applied"

#: how the files np.load reads begin: an npz is a zip archive, a .npy has its own magic
ZIP_MAGIC, NPY_MAGIC = b"PK\x03\x04", b"\x93NUMPY"
#: a zip archive with no member begins with its end-of-central-directory record
ZIP_EMPTY = b"PK\x05\x06"


def npz_kind(path: Path, where: str) -> None:
    """An InputError naming ``where`` unless ``path`` begins as an npz (a zip archive) or a .npy
    does: an empty file, or one of another kind (text, a pickle), which np.load would report as
    "pickled (object) data" and advise loading unsafely."""
    with open(path, "rb") as f:
        head = f.read(8)
    if not head:
        raise InputError("is empty (0 bytes), not a guide npz", where)
    if head.startswith(ZIP_EMPTY):
        raise InputError("is an empty zip archive: it holds no arrays (a guide npz holds guide_positions, "
                         "guide_offsets and fps)", where)
    if not (head.startswith(ZIP_MAGIC) or head.startswith(NPY_MAGIC)):
        raise InputError(f"is not an npz file (a zip archive of .npy arrays, as np.savez writes): it begins "
                         f"with {head!r}", where)


def unreadable_npz(path: Path, exc: BaseException) -> str:
    """What is wrong with an npz that np.load could not read: a zip archive that ends early (a
    copy or download cut short: its central directory, at the end, is missing), or whose members
    are damaged (CRC, deflate or header errors), named as such with the reader's own words."""
    size = path.stat().st_size if path.exists() else 0
    said = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, zipfile.BadZipFile) and "not a zip file" in str(exc):
        return (f"is truncated or corrupt: it begins as an npz (a zip archive) but its end, the archive's "
                f"directory, is missing ({size} bytes; a copy or download cut short?); the reader said {said}")
    if isinstance(exc, (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError)):
        return f"is corrupt or truncated: an array in it cannot be read ({size} bytes); the reader said {said}"
    return f"cannot read guide animation: {said}"


def file_guides(path, motion, frames: int | None = None, fps: float | None = None) -> GuideAnimation:
    """The ``file`` source: an npz with ``guide_positions``, ``guide_offsets`` and ``fps``.  With
    ``frames``/``fps`` (the run's), a file that ends before the run does is an error: the guides
    would be held still at its last frame."""
    path = Path(path)
    where = f"guides.file={path}"
    regular_file(path, where, "guide npz")
    npz_kind(path, where)
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise InputError(f"is a single {type(data).__name__} (.npy), not an npz with guide_positions, "
                             "guide_offsets and fps", where)
        with data:
            missing = [k for k in ("guide_positions", "guide_offsets", "fps") if k not in data.files]
            if missing:
                raise InputError(f"has no array {', '.join(repr(k) for k in missing)} (a guide npz holds guide_positions, "
                                 f"guide_offsets and fps; this one has {', '.join(data.files) or 'none'})", where)
            pos, off, gfps = data["guide_positions"], data["guide_offsets"], data["fps"]
            if np.size(gfps) != 1:
                raise InputError(f"fps must be one number, got an array of shape {np.shape(gfps)}", where)
            gfps = float(np.asarray(gfps).reshape(-1)[0])
            note = np.asarray(data[EDITS_MEMBER]) if EDITS_MEMBER in data.files else np.asarray("")
            edited = str(note.reshape(-1)[0]) if note.dtype.kind == "U" and note.size == 1 else ""
    except InputError:
        raise
    except Exception as exc:   # a truncated, corrupt or empty file: zipfile, pickle, EOF and shape errors
        raise InputError(unreadable_npz(path, exc), where) from exc
    if np.ndim(pos) == 3 and len(pos) and np.asarray(pos).dtype.kind in "iuf":   # kept out of memory for the run
        pos = FrameStore.of(np.asarray(pos, dtype=np.float64))
    anim = GuideAnimation(pos, off, gfps, where=str(path), motion=motion)
    anim.edits_applied = edited
    if frames is not None and fps is not None and frames / fps > (anim.n_frames - 1) / anim.fps + 1e-9:
        raise InputError(f"has frames 0..{anim.n_frames - 1} ({(anim.n_frames - 1) / anim.fps:g} s at {anim.fps:g} fps) "
                         f"but the run needs {frames} frames at {fps:g} fps ({frames / fps:g} s)", where)
    return anim


def carried_guides(g, body: np.ndarray, offsets: np.ndarray, motion, frames: int, fps: float,
                   scaled: bool) -> FrameStore:
    """(frames + 1, Vg, 3) world positions (a ``FrameStore``) of the body-frame guides ``body``
    carried by ``motion`` (``rigid``), scaled about their roots by ``g.scale_times``/``g.scale_factors``
    (``scaled``)."""
    store = FrameStore(body.shape)
    roots = np.repeat(body[offsets[:-1]], g.n_vertices, axis=0) if scaled else None
    for start in range(0, frames + 1, store.per_block):   # the poses a block at a time
        fs = np.arange(start, min(start + store.per_block, frames + 1))
        R, T = motion_poses(motion, fs / fps)
        for i, f in enumerate(fs):
            X = body
            if scaled:   # guides.scale_times/scale_factors: checked in hairexp/app/validate.py
                s = float(np.interp(f / fps, g.scale_times, g.scale_factors))
                X = roots + s * (body - roots)
            store.append(X @ R[i].T + T[i])   # motion.transform(X, f / fps)
    return store

