"""Write scenes and run results as USD stages (layout: ``usd_layout``, README "USD scenes").

* ``write_scene_usd(path, scene, guides, fps, frames)``: a scene in the input layout that
  ``experiment=from_usd`` reads (a template for users, and the round trip);
* ``write_result_usd(path, scene, positions, guide_positions, guide_offsets, fps, clips)``: a
  run's ``result.usdc`` (binary crate, the default) or ``result.usda`` (``output.usd_format``):
  the input layout sampled at every frame plus ``/Root/Result/Hair``; a long run's samples in
  value clips (``result.clips/``, ``write_clipped``).

Body and collider transforms: a ``linear`` motion is written at its keyframes (it re-imports
exactly); a ``cubic`` one, and every motion in a result stage, once per frame (it re-imports
linear between frames); a still one as an untimed value.  Points are float32 (USD's
``point3f``), transforms and sizes float64.  Files are written to a temporary name in the same
folder, then renamed: a failed write leaves nothing under the final name.

Value clips (``output.usd_clips``; README "USD scenes"): every time-sampled attribute of a
result (hair and guide points and extents, the moving transforms) is written in chunks of
CLIP_FRAMES frames into ``<stem>.clips/<k>.usdc``, one crate layer a chunk, each written once and
released, so the writer holds one chunk whatever the run's length (a single file-backed layer is
packed whole at every save: its tables grow with the frames).  The root layer ``<stem>.usdc``
holds the prims, the topology, the widths, the untimed values and one clip set on ``/Root``
(``clipPrimPath`` /Root: the clips mirror the root's prim paths, so one list of assets serves every
animated prim below it) with a manifest ``<stem>.clips/manifest.usdc`` declaring the clipped
attributes.  Clip k holds frames k x CLIP_FRAMES .. (k + 1) x CLIP_FRAMES (the next chunk's first
frame too, so that times between two frames interpolate across a clip boundary as in one layer);
it is active from k x CLIP_FRAMES on, and clip time = stage time.  Clips are crate files whatever
the root's format (a ``.usda`` root stays readable: the bulk of the samples is binary).  Asset paths
are relative (``./result.clips/0.usdc``): the run folder can be moved.  The clips are written into
``<stem>.clips.tmp/``, renamed to ``<stem>.clips/``, then the root layer is written and renamed; a
failure removes both.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
from pathlib import Path

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from hairexp.errors import choice_name, errno_in_text, points_range
from hairexp.io.usd_colliders import write_colliders
from hairexp.memory import release
from hairexp.io.usd_layout import (BODY, EDITS_APPLIED, GUIDE_WIDTH, GUIDES, HAIR, HAIR_WIDTH, RESULT, RESULT_HAIR, ROOT,
                                   matrix_from_pose, set_transform)

log = logging.getLogger(__name__)
FORMATS = (".usda", ".usdc", ".usd")
#: frames in one value clip (``write_clipped``); ``output.usd_clips=auto`` writes a run of at most
#: this many frames as a single layer
CLIP_FRAMES = 250
CLIP_POLICIES = ("auto", "always", "never")


#: a streamed stage (``write_result_usd``) is saved whenever this many bytes of samples (points,
#: extents and transforms, all prims together) were added
SAVE_BYTES = 1 << 20
MATRIX_BYTES = 128
#: what an unsaved time sample costs in memory beyond its data (the layer's sample map entry and
#: the value's holder), counted with each sample so that small samples are saved as often as their
#: memory asks
SAMPLE_BYTES = 256


def usd_write_error(exc: Exception, file) -> OSError:
    """USD's error (``pxr.Tf.ErrorException``: one line per failed write, thousands when the disk
    fills during a save) as one OSError naming ``file``: its errno when the text says which
    (disk full, file-size limit, ...), else EIO with USD's first message (probe of issue 12: a full
    disk during the result's export ended with a traceback and pages of USD lines, exit 1)."""
    text = str(exc)
    code = errno_in_text(text)
    if code is not None:
        return OSError(code, os.strerror(code), str(file))
    first = next((line.strip() for line in text.splitlines() if line.strip()), type(exc).__name__)
    if " : " in first:   # "Error in '<C++ function>' at line N in file F : 'what'": the what
        first = first.rsplit(" : ", 1)[1]
        if len(first) > 1 and first[0] == first[-1] == "'":
            first = first[1:-1]
    return OSError(errno.EIO, f"USD could not write it: {first[:300]}", str(file))


@contextlib.contextmanager
def writing(file):
    """USD calls that write ``file``: their errors raised as one OSError (``usd_write_error``)."""
    try:
        yield
    except Tf.ErrorException as exc:
        raise usd_write_error(exc, file) from None


def _saved(file, call) -> None:
    """``call()``, a USD call that writes ``file`` and returns whether it did: its errors, and a
    False, raised as one OSError naming ``file`` (``writing``)."""
    with writing(file):
        ok = call()
    if not ok:
        raise OSError(errno.EIO, "USD could not write it", str(file))


class Saves:
    """Saves a file-backed stage (or Sdf layer) every SAVE_BYTES of samples added (``add``), so
    that its samples leave memory (a saved crate layer reads them back from the file on demand)."""

    def __init__(self, stage):
        self.layer = stage.GetRootLayer() if isinstance(stage, Usd.Stage) else stage
        self.added = 0

    def add(self, nbytes: int) -> None:
        self.added += nbytes
        if self.added >= SAVE_BYTES:
            _saved(self.layer.realPath, self.layer.Save)
            self.added = 0
            release()   # each save's packing tables grow with the samples saved: free them, or the heap grows


def new_stage(fps: float, frames: int, doc: str, path=None) -> Usd.Stage:
    """A stage in memory, or (``path``) one backed by a new file that ``Save`` writes."""
    with writing(path):
        stage = Usd.Stage.CreateInMemory() if path is None else Usd.Stage.CreateNew(str(path))
    if stage is None:
        raise OSError(f"cannot create the USD stage {path}")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(int(frames))
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, ROOT).GetPrim())
    stage.GetRootLayer().documentation = doc
    return stage


def _code(tc: float) -> float:
    """A time code, snapped to the frame it is within 1e-9 of (0.2 s x 25 fps -> 5, not 5.000000000000001)."""
    return float(round(tc)) if abs(tc - round(tc)) < 1e-9 else tc


def pose_samples(motion, fps: float, frames: int, keyframes: bool, saves: Saves | None = None):
    """(time code, or None for the untimed value, USD matrix) of a RigidMotion; the per-frame
    samples are made as they are read (a generator), each one counted in ``saves``."""
    if len(motion.times) == 1:
        return [(None, matrix_from_pose(*motion.pose(float(motion.times[0]))))]
    if keyframes and motion.interpolation == "linear":
        return [(_code(float(t) * fps), matrix_from_pose(*motion.pose(float(t)))) for t in motion.times]
    return _frame_poses(motion, fps, frames, saves)


def _frame_poses(motion, fps: float, frames: int, saves: Saves | None):
    for f in range(frames + 1):
        yield float(f), matrix_from_pose(*motion.pose(f / fps))
        if saves is not None:   # the sample yielded has been set
            saves.add(MATRIX_BYTES + SAMPLE_BYTES)


def hair_widths(scene):
    """The detail hair's display widths: the (V,) widths a USD stage authored (``Scene.widths``),
    else HAIR_WIDTH for all."""
    return HAIR_WIDTH if getattr(scene, "widths", None) is None else scene.widths


def _half_width(width) -> float:
    """Half the largest of ``width`` (a number or per-vertex widths): the extent's margin."""
    return 0.5 * float(np.max(width))


def define_curves(stage, path: str, counts, width) -> UsdGeom.BasisCurves:
    """A linear BasisCurves prim; ``width``: one width for all (constant interpolation; so are
    per-vertex widths that are all equal) or one per vertex."""
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateTypeAttr(UsdGeom.Tokens.linear)
    c.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    c.CreateCurveVertexCountsAttr(Vt.IntArray([int(n) for n in counts]))
    if np.ndim(width) == 1 and len(width) and np.all(np.float32(width) == np.float32(width[0])):
        width = float(width[0])
    if np.ndim(width) == 0:
        c.CreateWidthsAttr(Vt.FloatArray([float(width)]))
        c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    else:
        c.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(width, dtype=np.float32)))
        c.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    c.CreatePointsAttr()
    c.CreateExtentAttr()
    return c


def _extent(p: np.ndarray, r: float) -> np.ndarray:
    """USD's extent of points p (n, 3) with half width r (``points_range``: every frame's hair)."""
    lo, hi = points_range(p)
    return np.stack([lo - r, hi + r]).astype(np.float32)


def finite_frame(P, f: int, what: str, file) -> np.ndarray:
    """Frame ``f`` of ``what`` as USD stores it (point3f: float32, contiguous); a non-finite one
    is refused (AssertionError naming ``what``, the frame and ``file``)."""
    p = np.ascontiguousarray(P, dtype=np.float32)
    if not np.isfinite(p).all():
        raise AssertionError(f"refusing to write non-finite {what} (frame {f}) to {file}")
    return p


def set_points(curves: UsdGeom.BasisCurves, points: np.ndarray, tc=Usd.TimeCode.Default()) -> None:
    p = np.ascontiguousarray(points, dtype=np.float32)
    curves.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), tc)
    r = _half_width(curves.GetWidthsAttr().Get())
    curves.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(_extent(p, r)), tc)


def write_body(stage, scene, samples) -> None:
    """``/Root/Body`` with its transform samples and ``/Root/Body/Hair`` at rest (body space)."""
    set_transform(UsdGeom.Xform.Define(stage, BODY), samples)
    set_points(define_curves(stage, HAIR, scene.strands.counts, hair_widths(scene)), scene.root_body)


def write_animation(stage, path: str, frames, offsets: np.ndarray, width: float, saves: Saves | None = None,
                    what: str = "points") -> None:
    """BasisCurves with one time sample per frame (time code f = frame f); ``frames``: a
    sequence of (V, 3) arrays.  ``saves``: the stage is file-backed and saved every
    ``SAVE_BYTES`` of samples (``Saves``), so a long run's result is written with the memory of
    one block of frames; a non-finite frame is refused (AssertionError naming ``what``)."""
    curves = define_curves(stage, path, np.diff(offsets), width)
    for f, P in enumerate(frames):
        set_points(curves, finite_frame(P, f, what, stage.GetRootLayer().realPath), Usd.TimeCode(f))
        if saves is not None:
            saves.add(12 * len(P) + 24 + 2 * SAMPLE_BYTES)   # points and extent


def _discard(tmp: Path) -> None:
    """Remove a temporary file if it is there; an error doing so (its folder is not one: the
    write's own error says why) is not raised over the write's (``[Errno 20] Not a directory``
    of the unlink hid USD's)."""
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass


def save(stage, path) -> None:
    path = Path(path)
    if path.suffix not in FORMATS:
        raise ValueError(f"{path}: a USD file name ends with one of {', '.join(FORMATS)}")
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)  # same suffix: same file format
    try:
        _saved(path, lambda: stage.GetRootLayer().Export(str(tmp)))
        os.replace(tmp, path)
    finally:
        _discard(tmp)


def write_scene_usd(path, scene, guides, fps: float, frames: int) -> None:
    """``scene`` and ``guides`` (sampled at frames 0..frames) in the input layout."""
    if scene.motion.interpolation == "cubic" and len(scene.motion.times) > 1:
        log.warning("%s: the cubic body motion is written once per frame; it re-imports as linear between frames",
                    path)
    stage = new_stage(fps, frames, "hairexp scene (input layout, README 'USD scenes')")
    samples = lambda motion: pose_samples(motion, fps, frames, keyframes=True)  # noqa: E731
    write_body(stage, scene, samples(scene.motion))
    shapes = np.stack([guides.shape_at(f / fps) for f in range(frames + 1)])
    write_animation(stage, GUIDES, shapes, guides.offsets, GUIDE_WIDTH)
    mark_edits(stage, getattr(guides, "edits_applied", ""))
    write_colliders(stage, scene.colliders, samples)
    save(stage, path)


def clipped(policy: str, frames: int) -> bool:
    """Whether a result of ``frames`` frames is written with value clips (``output.usd_clips``)."""
    if policy not in CLIP_POLICIES:
        raise ValueError(f"usd_clips is {policy!r}; use one of {', '.join(CLIP_POLICIES)}")
    return policy == "always" or (policy == "auto" and frames > CLIP_FRAMES)


def clips_dir(path) -> Path:
    """The folder of the value clips of the result stage ``path``: ``result.usdc`` -> ``result.clips``."""
    path = Path(path)
    return path.with_name(path.stem + ".clips")


def write_result_usd(path, scene, positions, guide_positions, guide_offsets, fps: float,
                     clips: str = "auto", edits_applied: str = "") -> None:
    """A run's result.usdc (or .usda: the format follows the suffix): positions (frames+1, V, 3)
    and guide_positions (frames+1, Vg, 3) in world space (arrays, or sequences of frames such
    as ``NpyFrames``), body and colliders sampled at every frame.

    ``clips`` (``output.usd_clips``): ``never``: one layer; ``always``: value clips
    (``write_clipped``); ``auto``: clips when there are more than CLIP_FRAMES frames.  A
    ``<stem>.clips`` folder left beside ``path`` by an earlier write is removed.  ``edits_applied``:
    the ``guides.edits`` the guides carry (``GuideAnimation.edits_applied``), said on the guides
    prim (customData ``EDITS_APPLIED``) for a run that reads the stage back.

    One layer: the stage is written as a crate file under a temporary name, saved every
    ``SAVE_BYTES`` of samples, transforms included, then renamed; an ASCII result is exported
    from it at the end.  Its memory still grows with the frames (each save packs the whole
    layer's tables)."""
    path = Path(path)
    if path.suffix not in FORMATS:
        raise ValueError(f"{path}: a USD file name ends with one of {', '.join(FORMATS)}")
    frames = len(positions) - 1
    if clipped(choice_name(clips), frames):
        write_clipped(path, scene, positions, guide_positions, guide_offsets, fps, edits_applied)
        return
    crate = path.with_name(path.stem + ".tmp.usdc")
    stage = None
    try:
        stage = new_stage(fps, frames, "hairexp result: the input layout plus /Root/Result/Hair (README 'USD scenes')",
                          path=crate)
        saves = Saves(stage)
        samples = lambda motion: pose_samples(motion, fps, frames, keyframes=False, saves=saves)  # noqa: E731
        write_body(stage, scene, samples(scene.motion))
        if _has_guides(guide_positions):
            write_animation(stage, GUIDES, guide_positions, guide_offsets, GUIDE_WIDTH, saves, "guide_positions")
            mark_edits(stage, edits_applied)
        write_colliders(stage, scene.colliders, samples)
        UsdGeom.Scope.Define(stage, RESULT)
        write_animation(stage, RESULT_HAIR, positions, scene.strands.offsets, hair_widths(scene), saves, "positions")
        if path.suffix == ".usda":
            save(stage, path)
        else:
            _saved(path, stage.GetRootLayer().Save)
            stage = None
            os.replace(crate, path)
        shutil.rmtree(clips_dir(path), ignore_errors=True)   # an earlier write's clips: not this stage's
    finally:
        stage = None   # releases the layer (a traceback keeps this frame alive) before its file goes
        _discard(crate)


def mark_edits(stage, edits_applied: str) -> None:
    """The guides prim's customData ``EDITS_APPLIED``: the edits its guides carry (none: not set)."""
    if edits_applied:
        stage.GetPrimAtPath(GUIDES).SetCustomDataByKey(EDITS_APPLIED, str(edits_applied))


def _has_guides(guide_positions) -> bool:
    return np.ndim(guide_positions) == 3 and len(guide_positions) > 0 and len(guide_positions[0]) > 0


class _Channel:
    """One time-sampled attribute of a clipped result: its prim path, name, value type and the
    per-frame value (``value(f)``, with the bytes it costs) made on demand."""

    def __init__(self, prim: str, name: str, type_name, value, nbytes: int):
        self.prim, self.name, self.type_name, self.value, self.nbytes = prim, name, type_name, value, nbytes


def _curve_channels(path: str, frames, width: float, what: str, file) -> list:
    """Points and extent of a BasisCurves prim; each frame is read once for both (a non-finite
    frame is refused: AssertionError naming ``what``)."""
    cache = {}

    def frame(f):
        if f not in cache:
            cache.clear()
            p = finite_frame(frames[f], f, what, file)
            cache[f] = (Vt.Vec3fArray.FromNumpy(p), Vt.Vec3fArray.FromNumpy(_extent(p, _half_width(width))))
        return cache[f]

    n = len(frames[0])
    return [_Channel(path, "points", Sdf.ValueTypeNames.Point3fArray, lambda f: frame(f)[0], 12 * n + SAMPLE_BYTES),
            _Channel(path, "extent", Sdf.ValueTypeNames.Float3Array, lambda f: frame(f)[1], 24 + SAMPLE_BYTES)]


def _pose_channel(prim: str, motion, fps: float) -> _Channel:
    return _Channel(prim, "xformOp:transform", Sdf.ValueTypeNames.Matrix4d,
                    lambda f: matrix_from_pose(*motion.pose(f / fps)), MATRIX_BYTES + SAMPLE_BYTES)


def _write_clip(file: Path, channels: list, first: int, last: int, fps: float) -> Sdf.Layer:
    """Clip layer ``file``: the channels' samples at frames first..last (over specs), saved every
    SAVE_BYTES and at the end; returns the layer (the caller drops it)."""
    with writing(file):
        layer = Sdf.Layer.CreateNew(str(file))
    if layer is None:
        raise OSError(f"cannot create {file}")
    layer.timeCodesPerSecond = layer.framesPerSecond = float(fps)   # as the root's: no time scaling
    paths = []
    for c in channels:
        spec = Sdf.CreatePrimInLayer(layer, c.prim)
        attr = spec.attributes.get(c.name) or Sdf.AttributeSpec(spec, c.name, c.type_name)
        paths.append(attr.path)
    saves = Saves(layer)
    for f in range(first, last + 1):
        for c, p in zip(channels, paths):
            layer.SetTimeSample(p, float(f), c.value(f))
            saves.add(c.nbytes)
    _saved(file, layer.Save)
    return layer


def write_clipped(path, scene, positions, guide_positions, guide_offsets, fps: float, edits_applied: str = "") -> None:
    """``write_result_usd`` with value clips (module docstring): ``<stem>.clips/<k>.usdc`` with
    frames k x CLIP_FRAMES .. (k + 1) x CLIP_FRAMES of every time-sampled attribute, a manifest,
    and the root layer ``path`` with the rest and the clip set on /Root.  Memory: one chunk."""
    path = Path(path)
    frames = len(positions) - 1
    final, tmp = clips_dir(path), path.with_name(path.stem + ".clips.tmp")
    stage = None
    renamed = False
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        # the root layer in memory (small: no per-frame samples); a moving transform's op is
        # declared without values, the clips hold them
        stage = new_stage(fps, frames, "hairexp result: the input layout plus /Root/Result/Hair, the per-frame "
                          f"samples in value clips ./{final.name}/ (README 'USD scenes')")
        moving = lambda motion: len(motion.times) > 1  # noqa: E731
        samples = lambda motion: [] if moving(motion) else pose_samples(motion, fps, frames, keyframes=False)  # noqa: E731
        channels = []
        write_body(stage, scene, samples(scene.motion))
        if moving(scene.motion):
            channels.append(_pose_channel(BODY, scene.motion, fps))
        if _has_guides(guide_positions):
            define_curves(stage, GUIDES, np.diff(guide_offsets), GUIDE_WIDTH)
            mark_edits(stage, edits_applied)
            channels += _curve_channels(GUIDES, guide_positions, GUIDE_WIDTH, "guide_positions", path)
        for prim, c in write_colliders(stage, scene.colliders, samples):
            if moving(c.motion):
                channels.append(_pose_channel(prim, c.motion, fps))
        UsdGeom.Scope.Define(stage, RESULT)
        define_curves(stage, RESULT_HAIR, np.diff(scene.strands.offsets), hair_widths(scene))
        channels += _curve_channels(RESULT_HAIR, positions, hair_widths(scene), "positions", path)

        starts = list(range(0, frames, CLIP_FRAMES)) or [0]
        assets = []
        for k, first in enumerate(starts):
            layer = _write_clip(tmp / f"{k}.usdc", channels, first, min(first + CLIP_FRAMES, frames), fps)
            if k == 0:   # every clip has the same attributes: the manifest is the first one's
                manifest = Usd.ClipsAPI.GenerateClipManifestFromLayers([layer], ROOT)
                _saved(tmp / "manifest.usdc", lambda: manifest.Export(str(tmp / "manifest.usdc")))
                manifest = None
            layer = None
            release()   # the chunk's samples and packing tables
            assets.append(f"./{final.name}/{k}.usdc")

        api = Usd.ClipsAPI(stage.GetPrimAtPath(ROOT))
        api.SetClipPrimPath(ROOT)
        api.SetClipAssetPaths(Sdf.AssetPathArray(assets))
        api.SetClipManifestAssetPath(Sdf.AssetPath(f"./{final.name}/manifest.usdc"))
        api.SetClipActive(Vt.Vec2dArray([(float(s), float(k)) for k, s in enumerate(starts)]))
        api.SetClipTimes(Vt.Vec2dArray([(float(t), float(t)) for t in sorted({*starts, frames})]))
        shutil.rmtree(final, ignore_errors=True)   # an earlier write's clips
        os.replace(tmp, final)
        renamed = True
        save(stage, path)
    except BaseException:
        if renamed:
            shutil.rmtree(final, ignore_errors=True)
        raise
    finally:
        stage = None
        shutil.rmtree(tmp, ignore_errors=True)
