"""Write scenes and run results as USD stages (layout: ``usd_layout``, README "USD scenes").

* ``write_scene_usd(path, scene, guides, fps, frames)``: a scene in the input layout that
  ``experiment=from_usd`` reads (a template for users, and the round trip);
* ``write_result_usd(path, scene, positions, guide_positions, guide_offsets, fps)``: a run's
  ``result.usdc`` (binary crate, the default) or ``result.usda`` (``output.usd_format``): the
  input layout sampled at every frame plus ``/Root/Result/Hair``.

Body and collider transforms: a ``linear`` motion is written at its keyframes (it re-imports
exactly); a ``cubic`` one, and every motion in a result stage, once per frame (it re-imports
linear between frames); a still one as an untimed value.  Points are float32 (USD's
``point3f``), transforms and sizes float64.  Files are written to a temporary name in the same
folder, then renamed: a failed write leaves nothing under the final name.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom, Vt

from hairexp.io.usd_colliders import write_colliders
from hairexp.memory import release
from hairexp.io.usd_layout import (BODY, GUIDE_WIDTH, GUIDES, HAIR, HAIR_WIDTH, RESULT, RESULT_HAIR, ROOT,
                                   matrix_from_pose, set_transform)

log = logging.getLogger(__name__)
FORMATS = (".usda", ".usdc", ".usd")


#: a streamed stage (``write_result_usd``) is saved whenever this many bytes of samples (points,
#: extents and transforms, all prims together) were added
SAVE_BYTES = 1 << 20
MATRIX_BYTES = 128
#: what an unsaved time sample costs in memory beyond its data (the layer's sample map entry and
#: the value's holder), counted with each sample so that small samples are saved as often as their
#: memory asks
SAMPLE_BYTES = 256


class Saves:
    """Saves a file-backed stage every SAVE_BYTES of samples added (``add``), so that its samples
    leave memory (a saved crate layer reads them back from the file on demand)."""

    def __init__(self, stage):
        self.stage, self.added = stage, 0

    def add(self, nbytes: int) -> None:
        self.added += nbytes
        if self.added >= SAVE_BYTES:
            if not self.stage.GetRootLayer().Save():
                raise OSError(f"cannot write {self.stage.GetRootLayer().realPath}")
            self.added = 0
            release()   # each save's packing tables grow with the samples saved: free them, or the heap grows


def new_stage(fps: float, frames: int, doc: str, path=None) -> Usd.Stage:
    """A stage in memory, or (``path``) one backed by a new file that ``Save`` writes."""
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


def define_curves(stage, path: str, counts, width: float) -> UsdGeom.BasisCurves:
    c = UsdGeom.BasisCurves.Define(stage, path)
    c.CreateTypeAttr(UsdGeom.Tokens.linear)
    c.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    c.CreateCurveVertexCountsAttr(Vt.IntArray([int(n) for n in counts]))
    c.CreateWidthsAttr(Vt.FloatArray([width]))
    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    c.CreatePointsAttr()
    c.CreateExtentAttr()
    return c


def set_points(curves: UsdGeom.BasisCurves, points: np.ndarray, tc=Usd.TimeCode.Default()) -> None:
    p = np.ascontiguousarray(points, dtype=np.float32)
    curves.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), tc)
    r = 0.5 * curves.GetWidthsAttr().Get()[0]
    extent = np.stack([p.min(axis=0) - r, p.max(axis=0) + r]).astype(np.float32)
    curves.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(extent), tc)


def write_body(stage, scene, samples) -> None:
    """``/Root/Body`` with its transform samples and ``/Root/Body/Hair`` at rest (body space)."""
    set_transform(UsdGeom.Xform.Define(stage, BODY), samples)
    set_points(define_curves(stage, HAIR, scene.strands.counts, HAIR_WIDTH), scene.root_body)


def write_animation(stage, path: str, frames, offsets: np.ndarray, width: float, saves: Saves | None = None,
                    what: str = "points") -> None:
    """BasisCurves with one time sample per frame (time code f = frame f); ``frames``: a
    sequence of (V, 3) arrays.  ``saves``: the stage is file-backed and saved every
    ``SAVE_BYTES`` of samples (``Saves``), so a long run's result is written with the memory of
    one block of frames; a non-finite frame is refused (AssertionError naming ``what``)."""
    curves = define_curves(stage, path, np.diff(offsets), width)
    for f, P in enumerate(frames):
        if not np.isfinite(P).all():
            raise AssertionError(f"refusing to write non-finite {what} (frame {f}) to {stage.GetRootLayer().realPath}")
        set_points(curves, P, Usd.TimeCode(f))
        if saves is not None:
            saves.add(12 * len(P) + 24 + 2 * SAMPLE_BYTES)   # points and extent


def save(stage, path) -> None:
    path = Path(path)
    if path.suffix not in FORMATS:
        raise ValueError(f"{path}: a USD file name ends with one of {', '.join(FORMATS)}")
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)  # same suffix: same file format
    try:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"cannot write {tmp}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


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
    write_colliders(stage, scene.colliders, samples)
    save(stage, path)


def write_result_usd(path, scene, positions, guide_positions, guide_offsets, fps: float) -> None:
    """A run's result.usdc (or .usda: the format follows the suffix): positions (frames+1, V, 3)
    and guide_positions (frames+1, Vg, 3) in world space (arrays, or sequences of frames such
    as ``NpyFrames``), body and colliders sampled at every frame.

    The stage is written as a crate file under a temporary name, saved every ``SAVE_BYTES``
    of samples, transforms included (memory stays flat in the number of frames), then renamed; an ASCII result is
    exported from it at the end."""
    path = Path(path)
    if path.suffix not in FORMATS:
        raise ValueError(f"{path}: a USD file name ends with one of {', '.join(FORMATS)}")
    frames = len(positions) - 1
    crate = path.with_name(path.stem + ".tmp.usdc")
    stage = None
    try:
        stage = new_stage(fps, frames, "hairexp result: the input layout plus /Root/Result/Hair (README 'USD scenes')",
                          path=crate)
        saves = Saves(stage)
        samples = lambda motion: pose_samples(motion, fps, frames, keyframes=False, saves=saves)  # noqa: E731
        write_body(stage, scene, samples(scene.motion))
        if np.ndim(guide_positions) == 3 and len(guide_positions) and len(guide_positions[0]) > 0:
            write_animation(stage, GUIDES, guide_positions, guide_offsets, GUIDE_WIDTH, saves, "guide_positions")
        write_colliders(stage, scene.colliders, samples)
        UsdGeom.Scope.Define(stage, RESULT)
        write_animation(stage, RESULT_HAIR, positions, scene.strands.offsets, HAIR_WIDTH, saves, "positions")
        if path.suffix == ".usda":
            save(stage, path)
        else:
            if not stage.GetRootLayer().Save():
                raise OSError(f"cannot write {crate}")
            stage = None
            os.replace(crate, path)
    finally:
        stage = None   # releases the layer (a traceback keeps this frame alive) before its file goes
        crate.unlink(missing_ok=True)
