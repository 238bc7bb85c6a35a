"""A scene and its guide animation from a USD stage (``experiment=from_usd``; layout in
``usd_layout`` and README "USD scenes").

* ``build_usd_scene(scene_cfg)``: the body's motion, the detail hair at rest and the colliders
  from the stage ``scene.usd``; material and gravity from the config, as for every builder;
* ``read_guides(cfg, scene, frames, fps)``: the guide prim, one time sample per frame;
* ``stage_timing(cfg)``: ``frames: null`` / ``fps: null`` filled in from the stage.

Transforms are sampled at their authored time samples (time code / timeCodesPerSecond = s) and
interpolated linearly in between (``RigidMotion`` ``linear``: translation and slerp).  Every
error is an ``InputError`` whose ``where`` is ``scene.usd=<file>:<prim>``.
"""

from __future__ import annotations

import copy
import logging
import math
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from pxr import Sdf, Tf, Usd, UsdGeom

from hairexp.errors import InputError, check_extent, choice_name, regular_file
from hairexp.io.usd_colliders import read_colliders
from hairexp.io.usd_layout import (COUNTS_TYPES, EDITS_APPLIED, POINTS_TYPES, TOKEN_TYPES, check_transform_types, check_type,
                                   read_motion, stage_units, time_label, world_transform)
from hairexp.io.usd_layout import HAIR_WIDTH as DEFAULT_HAIR_WIDTH
from hairexp.io.usd_layout import tf_message as _message
from hairexp.guides.animation import MAX_FPS, MIN_FPS, GuideAnimation, check_fps
from hairexp.guides.store import FrameStore
from hairexp.model.builders import build_collider, build_material, build_motion, gravity
from hairexp.model.scene import Scene
from hairexp.model.strands import N_ROOT_VERTICES, Strands, check_folds, curve_vertex, validate_polylines

_open: dict = {}   # path -> stage of the last read (reloaded when the file changes)
_warned: set = set()   # the prims whose cubic type was warned about
log = logging.getLogger(__name__)


def open_stage(path: str) -> tuple[Usd.Stage, str]:
    """The stage at ``path`` (the value of ``scene.usd``) and the ``where`` prefix of its errors."""
    if not path:
        raise InputError("the path of a USD stage is required (scene.builder=usd or guides.source=usd)",
                         "scene.usd")
    where = f"scene.usd={path}"
    regular_file(path, where, "USD stage")
    with _usd_stderr() as said:   # USD's own warnings, said below as one line each (or by the error)
        try:
            stage = _open.get(path)
            if stage is None:
                stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
            stage.Reload()  # a stage kept from an earlier read: pick up edits of the file
        except Exception as exc:  # pxr.Tf.ErrorException: not a USD file, syntax error, ...
            _open.pop(path, None)
            raise InputError(f"cannot read the USD stage: {_message(exc)}{_format_hint(path)}", where) from exc
    if not stage:
        raise InputError("cannot read the USD stage", where)
    errors = stage.GetCompositionErrors()
    if errors:
        # a missing sublayer or reference: USD skips it with a warning on stderr and the run went on
        # without what it held (probe of issue 12)
        _open.pop(path, None)
        raise InputError(f"the stage does not compose: {' '.join(str(errors[0]).split())}"
                         + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""), where)
    for line in said:
        log.warning("%s: USD: %s", where, line)
    _open.clear()
    _open[path] = stage
    if UsdGeom.StageHasAuthoredMetersPerUnit(stage):
        mpu = UsdGeom.GetStageMetersPerUnit(stage)
        if not (isinstance(mpu, float) and math.isfinite(mpu) and mpu > 0):
            raise InputError(f"metersPerUnit is {mpu!r}; it must be a number > 0 (metres per unit of the stage's "
                             "lengths: 1 metres, 0.01 centimetres)", where)
    if UsdGeom.GetStageUpAxis(stage) not in (UsdGeom.Tokens.y, UsdGeom.Tokens.z):
        raise InputError(f"upAxis is {UsdGeom.GetStageUpAxis(stage)}; USD stages are Y or Z up "
                         "(a Z-up stage is turned to hairexp's Y up)", where)
    _other_layer_units(stage, where)
    return stage, where


def _format_hint(path: str) -> str:
    """Why a file may not read: a text stage named .usdc (USD reads a .usdc file as a crate: "crate
    bootstrap section corrupt") or a crate named .usda."""
    suffix = os.path.splitext(str(path))[1].lower()
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return ""
    if suffix == ".usdc" and head.startswith(b"#usda"):
        return "; the file is a text (usda) stage named .usdc, which USD reads as a binary crate: rename it .usda or .usd"
    if suffix == ".usda" and head.startswith(b"PXR-USDC"):
        return "; the file is a binary crate named .usda, which USD reads as text: rename it .usdc or .usd"
    return ""


def _other_layer_units(stage, where: str) -> None:
    """A warning for each sublayer or reference whose metersPerUnit or upAxis differs from the
    stage's (its root layer's, or USD's fallbacks): USD converts neither, so its values are read in
    the stage's unit and axes (a groom in centimetres referenced into a stage in metres read its
    20 cm strands as 20 m; independent probe, 2026-12-07)."""
    root = stage.GetRootLayer()
    mine = {"metersPerUnit": stage_units(stage), "upAxis": str(UsdGeom.GetStageUpAxis(stage))}
    for layer in stage.GetUsedLayers():
        if layer == root or layer.anonymous:
            continue
        info = layer.pseudoRoot
        for key, ours in mine.items():
            if not info.HasInfo(key):
                continue
            theirs = info.GetInfo(key)
            same = (math.isclose(float(theirs), ours, rel_tol=1e-9) if key == "metersPerUnit" and
                    isinstance(theirs, (int, float)) else str(theirs) == ours)
            if not same:
                log.warning("%s: %s sets %s = %s, the stage %s: USD does not convert a layer's values, so they "
                            "are read in the stage's %s (scale or turn the referencing prim, or author the layer "
                            "in the stage's)", where, layer.identifier, key, theirs, ours,
                            "unit" if key == "metersPerUnit" else "axes")


class _usd_stderr:
    """USD's C++ diagnostics (``Warning: in _ReportErrors at line ... -- Could not load sublayer
    ...``) written to the process's stderr while a stage opens, caught (file descriptor 2 points
    at a temporary file meanwhile) and kept as a list of one-line messages: printed before the
    error line that says the same, they made two lines of one error (probe of issue 12, round 14)."""

    def __enter__(self) -> list:
        self.lines: list[str] = []
        try:
            sys.stderr.flush()
            self._tmp = tempfile.TemporaryFile()
            self._saved = os.dup(2)
            os.dup2(self._tmp.fileno(), 2)
        except (OSError, ValueError, AttributeError):   # no descriptor 2 to redirect: USD's lines go where they go
            self._saved = None
        return self.lines

    def __exit__(self, *exc) -> bool:
        if self._saved is None:
            return False
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._tmp.seek(0)
        text = self._tmp.read().decode(errors="replace")
        self._tmp.close()
        for raw in text.split("Warning: ")[1:] if "Warning: " in text else text.splitlines():
            line = " ".join(raw.split())
            if " -- " in line:   # "in _ReportErrors at line 3326 of .../stage.cpp -- <what>"
                line = line.split(" -- ", 1)[1]
            if line:
                self.lines.append(line)
        return False


def get_prim(stage, path: str, where: str, what: str, key: str, schema=None, hint: str = "") -> Usd.Prim:
    """The prim at ``path`` (the value of config key ``key``), of type ``schema``; ``hint`` ends
    the message when there is none."""
    prim = stage.GetPrimAtPath(path) if path.startswith("/") else None
    if not prim:
        if path.startswith("/"):   # a prim under an inactive one is not on the stage: say which (probe, round 12)
            for anc in Sdf.Path(path).GetAncestorsRange():
                a = stage.GetPrimAtPath(anc)
                if a and not a.IsActive():
                    raise InputError(f"is inactive (active = false), so {path} ({what}) is not on the stage: activate "
                                     f"it, or name another prim with {key}", f"{where}:{anc}")
        raise InputError(f"no prim at {path} ({what}; {key} names its path){hint}", where)
    if not prim.IsActive():   # it was simulated as if active (probe of issue 12)
        raise InputError(f"is inactive (active = false) ({what}): activate it, or name another prim with {key}",
                         f"{where}:{path}")
    if prim.IsAbstract():   # a class (or inside one): read and simulated, where USD's traversal skips it (a probe)
        raise InputError(f"is abstract (a class, or inside one): not a prim of the scene ({what}); define it with "
                         f"'def', or name another prim with {key}", f"{where}:{path}")
    if schema is not None and not prim.IsA(schema):
        raise InputError(f"is a {prim.GetTypeName() or 'typeless prim'}, expected {schema.__name__} ({what})",
                         f"{where}:{path}")
    return prim


def check_curve_types(prim, where: str) -> None:
    """InputError naming the attribute when one that ``read_curves`` reads is declared with a
    type it cannot read (``string points``, ``int curveVertexCounts = 60``: a ValueError or
    TypeError out of numpy), or when a transform op of the prim or of an
    ancestor has a type USD cannot compute a transform from."""
    curves = UsdGeom.BasisCurves(prim)
    check_type(curves.GetPointsAttr(), POINTS_TYPES, where)
    check_type(curves.GetCurveVertexCountsAttr(), COUNTS_TYPES, where)
    check_type(curves.GetWrapAttr(), TOKEN_TYPES, where)
    check_type(curves.GetTypeAttr(), TOKEN_TYPES, where)
    check_transform_types(prim, where)


def _array(attr, tc, where: str, dtype, columns: int = 0) -> np.ndarray | None:
    """The attribute's value at ``tc`` as an array of ``dtype`` ((n, columns) with ``columns``),
    None when it has none; a value that is not such an array (past ``check_curve_types``: a
    value whose type differs from the declared one, from another layer) is an InputError."""
    name = attr.GetName()
    try:
        value = attr.Get(tc)
        if value is None:
            return None
        out = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, Tf.ErrorException) as exc:
        raise InputError(f"{name} at {time_label(tc)} cannot be read as numbers ({_message(exc)})", where) from None
    if out.size == 0:
        return out.reshape((0, columns) if columns else (0,))
    if out.ndim != (2 if columns else 1) or (columns and out.shape[1] != columns):
        raise InputError(f"{name} at {time_label(tc)} has the shape {list(out.shape)}, expected "
                         + (f"an array of {columns}-vectors" if columns else "an array of numbers"), where)
    return out


def read_curves(prim, tc, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(points (V, 3) float64 in the prim's space, counts (S,)) of a BasisCurves at ``tc``.  A
    ``cubic`` curve is read as its control polygon, with a warning (once per prim and file).
    The callers check the attributes' types first (``check_curve_types``)."""
    curves = UsdGeom.BasisCurves(prim)
    if curves.GetWrapAttr().Get() not in (None, UsdGeom.Tokens.nonperiodic):
        raise InputError(f"wrap is {curves.GetWrapAttr().Get()}; hair curves are open (nonperiodic)", where)
    kind = curves.GetTypeAttr().Get()
    if kind not in (None, UsdGeom.Tokens.linear) and where not in _warned:
        _warned.add(where)
        log.warning("%s: type is %s (basis %s): hairexp simulates the points as the vertices of a polyline, not as "
                    "the curve they control; author type = \"linear\" so that viewers draw what is simulated",
                    where, kind, curves.GetBasisAttr().Get())
    pts = _array(curves.GetPointsAttr(), tc, where, np.float64, columns=3)
    counts = _array(curves.GetCurveVertexCountsAttr(), tc, where, np.int64)
    if pts is None or len(pts) == 0:
        raise InputError(f"has no points at {time_label(tc)}", where)
    if counts is None or len(counts) == 0:
        raise InputError(f"has no curveVertexCounts at {time_label(tc)}", where)
    s = stage_units(prim.GetStage())
    return (pts * s if s != 1.0 else pts), counts


def rest_time(attr) -> Usd.TimeCode:
    """The points' default (untimed) value if authored, else time code 0."""
    return Usd.TimeCode.Default() if attr.Get(Usd.TimeCode.Default()) is not None else Usd.TimeCode(0)


def stage_rate(stage, where: str) -> float:
    """The stage's timeCodesPerSecond, finite and > 0 (time codes are converted to seconds by it)."""
    tcps = float(stage.GetTimeCodesPerSecond())
    if not (math.isfinite(tcps) and tcps > 0):
        raise InputError(f"timeCodesPerSecond is {tcps:g}; it must be > 0 (time codes per second)", where)
    return tcps


def apply(points: np.ndarray, M) -> np.ndarray:
    m = np.array(M, dtype=np.float64).reshape(4, 4)
    return points @ m[:3, :3] + m[3, :3]


def check_hair_rides_body(hair, body, where: str, body_path: str) -> None:
    """InputError if a transform between the hair and the stage root that the body does not
    share is animated (the hair's own or a parent's that is not the body or above it): the hair
    is read at rest and carried by the body's motion alone, so such an animation would be
    dropped without a word (probe of issue 12)."""
    shared = set()
    p = body
    while p and p.IsValid():
        shared.add(p.GetPath())
        p = p.GetParent()
    p = hair
    while p and p.IsValid() and p.GetPath() not in shared:
        xf = UsdGeom.Xformable(p)
        if xf and xf.TransformMightBeTimeVarying():
            if body is None:
                raise InputError(f"the transform of {p.GetPath()} is animated: the hair is read at rest and, with "
                                 "scene.usd_body=none, moves with scene.motion only; name the animated prim as the "
                                 "body (scene.usd_body), or remove the animation", where)
            raise InputError(f"the transform of {p.GetPath()} is animated: the hair is read at rest and moves with "
                             f"the body ({body_path}) only; animate the body's transform instead, or remove the "
                             "animation", where)
        p = p.GetParent()


def curve_prims(root, key: str, what: str, noun: str, where: str) -> list:
    """``root`` itself if it is a BasisCurves, else every active BasisCurves under it in the stage's
    order (inactive ones are said, not used, as ``noun`` curves; classes and overs are no prims of
    the scene); none is an InputError naming ``key`` (``scene.usd_hair`` or ``scene.usd_guides``)
    and ``what`` it names."""
    if root.IsA(UsdGeom.BasisCurves):
        return [root]
    prims, off, classes = [], [], []
    # an inactive prim's children are not on the stage; an instanceable prim's are, as instance proxies
    for p in Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        if p.IsA(UsdGeom.BasisCurves) and p.IsDefined():   # not an over
            (classes if p.IsAbstract() else prims if p.IsActive() else off).append(p)
    if off:
        log.warning("%s: inactive %s curves not used: %s", where, noun, ", ".join(str(p.GetPath()) for p in off))
    if classes:   # skipped without a word (a probe)
        log.warning("%s: abstract %s curves (classes, or inside one) not used: %s", where, noun,
                    ", ".join(str(p.GetPath()) for p in classes))
    if not prims:
        raise InputError(f"is a {root.GetTypeName() or 'typeless prim'} with no active BasisCurves under it; "
                         f"{key} names {what}: a BasisCurves, or a prim holding them", where)
    return prims


def hair_prims(stage, cfg, file: str) -> list:
    """The detail hair's BasisCurves prims (``curve_prims``): ``scene.usd_hair`` itself, or the
    curves under the parent it names (hair exported as several curve sets, one per description or
    clump)."""
    root = get_prim(stage, cfg.usd_hair, file, "the detail hair", "scene.usd_hair")
    guides = Sdf.Path(cfg.usd_guides) if str(cfg.usd_guides).startswith("/") else None
    if guides is not None and root.GetPath() == guides:
        # the guides themselves simulated as detail hair, with only "the hair's points are animated" said (a
        # probe); hair inside a guides parent is the guides reader's to refuse ("holds the detail hair")
        raise InputError(f"is the guides ({cfg.usd_guides}, scene.usd_guides): scene.usd_hair names the detail hair's "
                         "own BasisCurves or a prim holding only hair curves", f"{file}:{cfg.usd_hair}")
    if (not root.IsA(UsdGeom.BasisCurves) and guides is not None and guides.HasPrefix(root.GetPath())
            and stage.GetPrimAtPath(guides)):
        # the guides' frame 0 would have been read as hair
        raise InputError(f"holds the guides ({cfg.usd_guides}, scene.usd_guides): scene.usd_hair names the detail "
                         "hair's own BasisCurves or a prim holding only hair curves", f"{file}:{cfg.usd_hair}")
    return curve_prims(root, "scene.usd_hair", "the detail hair", "hair", f"{file}:{cfg.usd_hair}")


#: m: a hair curve authored wider than this is warned of (a unit error, most likely: hair is
#: 0.02-0.2 mm thick); its widths are still written back to the result as authored
WIDE_HAIR = 0.01


def read_widths(curves: UsdGeom.BasisCurves, tc, counts: np.ndarray, where: str) -> np.ndarray | None:
    """(V,) m, the curves' ``widths`` at ``tc`` per vertex (constant: one for all; uniform: one a
    curve; varying or vertex: one a vertex, as for linear curves), or None when none are authored
    or their count does not fit their interpolation (warned: the result's hair is then drawn at
    the default width).  A width that is not finite or is negative is an InputError naming the
    curve and vertex; widths of zero (tapered tips) are taken."""
    primvar = UsdGeom.PrimvarsAPI(curves.GetPrim()).GetPrimvar("widths")
    if primvar and primvar.HasAuthoredValue():   # primvars:widths (DCC exporters; UsdImaging reads it first)
        attr, interp = primvar.GetAttr(), primvar.GetInterpolation()
    else:
        attr, interp = curves.GetWidthsAttr(), curves.GetWidthsInterpolation()
    if not attr.HasAuthoredValue():
        return None
    w = _array(attr, tc, where, np.float64)
    if w is None or w.size == 0:
        return None
    V, S = int(counts.sum()), len(counts)
    expect = {UsdGeom.Tokens.constant: 1, UsdGeom.Tokens.uniform: S, UsdGeom.Tokens.varying: V,
              UsdGeom.Tokens.vertex: V}.get(interp)
    if expect is None or len(w) != expect:
        log.warning("%s: %s has %d values with %s interpolation (%s curves, %d vertices): not used; the result's "
                    "hair is drawn %g mm wide", where, attr.GetName(), len(w), interp, S, V, 1e3 * DEFAULT_HAIR_WIDTH)
        return None
    if interp == UsdGeom.Tokens.constant:
        per_vertex = np.full(V, w[0])
    elif interp == UsdGeom.Tokens.uniform:
        per_vertex = np.repeat(w, counts)
    else:   # varying, vertex: one a vertex (linear curves)
        per_vertex = w
    bad = np.flatnonzero(~(np.isfinite(per_vertex) & (per_vertex >= 0)))
    if len(bad):
        v = int(bad[0])
        c, k = curve_vertex(np.concatenate([[0], np.cumsum(counts)]), v)
        raise InputError(f"{attr.GetName()}: curve {c} vertex {k} has the width {float(per_vertex[v]):.6g}; widths are "
                         "finite and >= 0", where)
    s = stage_units(curves.GetPrim().GetStage())
    per_vertex = per_vertex * s
    if per_vertex.max() > WIDE_HAIR:
        log.warning("%s: widths up to %.4g m: wider than hair (%g m at most here; hairexp reads metres: check the "
                    "stage's metersPerUnit); written back as authored", where, per_vertex.max(), WIDE_HAIR)
    return per_vertex


def read_hair(hair, body, cfg, file: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(points in the body's space at rest, curveVertexCounts, widths per vertex or None) of one
    hair prim, checked."""
    where = f"{file}:{hair.GetPath()}"
    check_curve_types(hair, where)   # before the samples are counted and the rest time chosen
    tc = rest_time(UsdGeom.BasisCurves(hair).GetPointsAttr())
    samples = UsdGeom.BasisCurves(hair).GetPointsAttr().GetTimeSamples()
    if len(samples) > (0 if tc.IsDefault() else 1):   # ignored without a word (probe of issue 12)
        logging.getLogger("hairexp").warning(
            "%s: the hair's points are animated (%d time samples); the hair is read at rest (%s) and simulated: "
            "its animation is not used (animate the body, %s, or the guides instead)", where, len(samples),
            "the default value" if tc.IsDefault() else "time code 0", cfg.usd_body)
    pts, counts = read_curves(hair, tc, where)
    with units_hint(hair.GetStage()):
        validate_polylines(pts, counts, where, min_vertices=N_ROOT_VERTICES + 1, folds=False)  # before any transform
        check_extent(pts, where, counts)
        check_folds(pts, counts, where)   # after the extent: a point 1e30 away is a unit error, not a fold
    widths = read_widths(UsdGeom.BasisCurves(hair), tc, counts, where)
    check_hair_rides_body(hair, body, where, cfg.usd_body)
    # hair space -> body space at the rest time (identity for hair authored under the body); no body
    # prim (scene.usd_body=none): hair space -> world (``build_usd_scene`` takes it to scene.motion's body)
    t0 = Usd.TimeCode(0) if tc.IsDefault() else tc
    rel = world_transform(UsdGeom.Xformable(hair), t0, where)
    if widths is not None:   # widths are in the prim's space, as its points: scaled by its transform's (mean) scale
        widths = widths * abs(float(np.linalg.det(np.array(rel)[:3, :3]))) ** (1.0 / 3.0)
    if body is not None:
        rel = rel * world_transform(UsdGeom.Xformable(body), t0, f"{file}:{cfg.usd_body}").GetInverse()
    return (pts if np.allclose(np.array(rel), np.eye(4), rtol=0, atol=1e-12) else apply(pts, rel)), counts, widths


#: an error about a length or a distance (``units_hint`` adds the stage's unit to those only)
LENGTH_ERROR = re.compile(r"zero-length|from the origin| long\b| apart\b|\d m\b")


class units_hint:
    """An InputError raised inside (a length check: a zero-length edge, a point or translation
    too far from the origin) says the stage's unit when it is not the metre: a stage of
    metersPerUnit 1e-9 had 'a zero-length edge' of 1e-11 m."""

    def __init__(self, stage):
        self.s = stage_units(stage)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if exc is None or not isinstance(exc, InputError) or self.s == 1.0:
            return False
        text = str(exc)
        if exc.where and text.startswith(f"{exc.where}: "):
            text = text[len(exc.where) + 2:]
        if not LENGTH_ERROR.search(text):   # a count, a fold, a rotation: not about lengths (probe of issue 16)
            return False
        raise type(exc)(f"{text} (the stage's lengths are read in metres: its values x its metersPerUnit "
                        f"{self.s:g})", exc.where) from exc


def no_body(cfg) -> bool:
    """``scene.usd_body=none`` (or empty): the stage has no body prim; the hair is read in world
    space and moved by the config's ``scene.motion``."""
    return str(cfg.usd_body).strip().lower() in ("", "none", "null")


def build_usd_scene(cfg):
    """The Scene of ``scene.usd`` (builder ``usd``); see the module doc."""
    stage, file = open_stage(cfg.usd)
    tcps = stage_rate(stage, file)
    if no_body(cfg):   # a groom on no moving prim: the config's scene.motion carries it (still by default)
        body, motion = None, build_motion(cfg.motion)
    else:
        body = get_prim(stage, cfg.usd_body, file, "the rigid body", "scene.usd_body", UsdGeom.Xformable)
        with units_hint(stage):
            motion, _ = read_motion(body, tcps, f"{file}:{cfg.usd_body}")
    parts = [read_hair(h, body, cfg, file) for h in hair_prims(stage, cfg, file)]
    body_pts = np.concatenate([p for p, _, _ in parts]) if len(parts) > 1 else parts[0][0]
    if body is None:   # the stage's world at rest -> scene.motion's body space at t = 0
        body_pts = motion.to_body(body_pts, 0.0)
    counts = np.concatenate([c for _, c, _ in parts]) if len(parts) > 1 else parts[0][1]
    # the authored widths, written back to the result (a prim without any: the default display width)
    widths = None if all(w is None for _, _, w in parts) else np.concatenate(
        [np.full(len(p), DEFAULT_HAIR_WIDTH) if w is None else w for p, _, w in parts])
    where = f"{file}:{cfg.usd_hair}"
    material = build_material(cfg.hair)
    with units_hint(stage):
        strands = Strands.from_polylines(motion.transform(body_pts, 0.0), counts, material.linear_density, where=where)
    colliders = read_colliders(stage, cfg.usd_colliders, tcps, file)
    colliders += [build_collider(c, i) for i, c in enumerate(getattr(cfg, "colliders", []) or [])]
    return Scene(cfg.name, strands, material, motion, gravity(cfg.gravity), body_pts, colliders, widths=widths)


def _rescaled_hint(attr) -> str:
    """Why an attribute authored on whole frames can have fractional time samples: it comes from
    a sublayer or reference whose timeCodesPerSecond differs from the root layer's (USD rescales
    its samples; a root layer that sets none has USD's default 24)."""
    stage = attr.GetPrim().GetStage()
    root = stage.GetRootLayer()
    rates = {}
    for spec in attr.GetPropertyStack(Usd.TimeCode.Default()):
        layer = spec.layer
        if layer != root and layer.HasTimeCodesPerSecond():
            rates[layer.identifier] = layer.timeCodesPerSecond
    mine = root.timeCodesPerSecond if root.HasTimeCodesPerSecond() else None
    other = {k: v for k, v in rates.items() if v != (mine if mine is not None else 24.0)}
    if not other:
        return ""
    name, rate = next(iter(other.items()))
    said = f"{mine:g}" if mine is not None else "none set (USD's default 24)"
    return (f"; the samples come from {name} at {rate:g} time codes per second, which USD rescales to the root "
            f"layer's rate ({said}): set timeCodesPerSecond = {rate:g} on the root layer")


def guide_frames(attr, where: str) -> int:
    """Number of frames N of a guide attribute sampled at time codes 0, 1, ..., N-1."""
    samples = attr.GetTimeSamples()
    if not samples:
        raise InputError("points have no time samples: guides need one per frame at time codes 0, 1, 2, ...", where)
    for s in samples:
        if s != round(s) or s < 0:
            raise InputError(f"time sample at time code {s:g} is not a frame (frames are time codes 0, 1, 2, ...)"
                             + _rescaled_hint(attr), where)
    have = {int(s) for s in samples}
    missing = next((f for f in range(max(have) + 1) if f not in have), None)
    if missing is not None:
        at = ", ".join(f"{s:g}" for s in samples[:4]) + (", ..." if len(samples) > 4 else "")
        # a referenced layer of another rate, rescaled to every second code, read as a gap (round 26)
        raise InputError(f"no time sample at time code {missing} (frame {missing}): guides need one per frame (its "
                         f"samples are at time codes {at})" + _rescaled_hint(attr), where)
    return len(have)


def guide_prims(stage, cfg, file: str) -> list:
    """The guides' BasisCurves prims (``curve_prims``): ``scene.usd_guides`` itself, or the curves
    under the parent it names (guides exported one prim each)."""
    path = cfg.scene.usd_guides
    # a stage without guides (hair and body only) is also simulated with guides.source=rigid (the rest
    # guides carried by the body): said, since a free run also draws and saves guides (probe, round 18)
    root = get_prim(stage, path, file, "the guides", "scene.usd_guides",
                    hint="; a stage without guides runs with guides.source=rigid (the rest guides carried by the body)")
    prims = curve_prims(root, "scene.usd_guides", "the guides", "guide", f"{file}:{path}")
    hair = Sdf.Path(cfg.scene.usd_hair) if str(cfg.scene.usd_hair).startswith("/") else None
    if (not root.IsA(UsdGeom.BasisCurves) and hair is not None
            and any(p.GetPath().HasPrefix(hair) or hair.HasPrefix(p.GetPath()) for p in prims)):
        raise InputError(f"holds the detail hair ({cfg.scene.usd_hair}, scene.usd_hair): scene.usd_guides names the "
                         "guides' own BasisCurves or a prim holding only guide curves", f"{file}:{path}")
    return prims


def read_guides(cfg, scene, frames: int, fps: float):
    """Guide animation of ``scene.usd_guides`` (world space, one time sample per frame; several
    prims under a parent: their curves in the stage's order)."""
    stage, file = open_stage(cfg.scene.usd)
    path = cfg.scene.usd_guides
    prims = guide_prims(stage, cfg, file)
    tcps = stage_rate(stage, file)
    n = None
    for prim in prims:
        where = f"{file}:{prim.GetPath()}"
        check_curve_types(prim, where)   # before the time samples are checked
        n_p = guide_frames(UsdGeom.BasisCurves(prim).GetPointsAttr(), where)
        if frames / fps > (n_p - 1) / tcps + 1e-9:
            raise InputError(f"guides have time samples for frames 0..{n_p - 1} ({(n_p - 1) / tcps:g} s at {tcps:g} fps) "
                             f"but the run needs {frames} frames at {fps:g} fps ({frames / fps:g} s)", where)
        n = n_p if n is None else min(n, n_p)
    frames_pos = None   # a FrameStore: frame by frame to a temporary file
    first: list = []    # per prim: (counts, points) of time code 0
    for f in range(n):
        parts, all_counts = [], []
        for i, prim in enumerate(prims):
            where = f"{file}:{prim.GetPath()}"
            pts, counts = read_curves(prim, Usd.TimeCode(f), where)
            if f == 0:
                first.append((counts, len(pts)))
            elif not np.array_equal(counts, first[i][0]):
                raise InputError(f"curveVertexCounts change at time code {f}: the guide topology must stay the same "
                                 "in every frame", where)
            elif len(pts) != first[i][1]:
                raise InputError(f"time code {f} has {len(pts)} points, time code 0 has {first[i][1]}: the guide "
                                 "topology must stay the same in every frame", where)
            with units_hint(stage):
                validate_polylines(pts, counts, f"{where} frame {f}", min_vertices=2, folds=False)   # finite, to transform
            parts.append(apply(pts, world_transform(UsdGeom.Xformable(prim), Usd.TimeCode(f), where)))
            all_counts.append(counts)
        X = np.concatenate(parts) if len(parts) > 1 else parts[0]
        if frames_pos is None:
            frames_pos = FrameStore(X.shape)
            counts0 = np.concatenate(all_counts) if len(all_counts) > 1 else all_counts[0]
        frames_pos.append(X)
    offsets = np.concatenate([[0], np.cumsum(counts0)])
    where = f"{file}:{path}"
    with units_hint(stage):
        anim = GuideAnimation(frames_pos, offsets, tcps, where=where, motion=scene.motion)   # extent, folds: checked there
    named = stage.GetPrimAtPath(path)   # a run's result says which guides.edits its guides carry (usd_write.mark_edits)
    anim.edits_applied = str(named.GetCustomDataByKey(EDITS_APPLIED) or "") if named else ""
    return anim


def stage_timing(cfg):
    """A copy of ``cfg`` with ``frames: null`` (the stage's endTimeCode, converted to the run's
    rate) and ``fps: null`` (the stage's timeCodesPerSecond) filled in."""
    if choice_name(cfg.scene.builder) != "usd":
        key = "frames" if cfg.frames is None else "fps"
        raise InputError("null (take it from the USD stage) needs scene.builder=usd; give a number", key)
    stage, file = open_stage(cfg.scene.usd)
    tcps = stage_rate(stage, file)
    fps = tcps if cfg.fps is None else float(cfg.fps)
    if cfg.fps is not None:   # fps=0 was said as "endTimeCode 5 gives no frame after frame 0" (probe, round 32)
        check_fps(fps)
    if cfg.fps is None and not MIN_FPS <= tcps <= MAX_FPS:   # it was reported as ``fps``, a key the user never set
        raise InputError(f"timeCodesPerSecond is {tcps:g}; with fps null (the stage's rate) it is the run's frame rate, "
                         f"which must be from {MIN_FPS:g} to {MAX_FPS:g}: fix the stage's rate or set fps", file)
    frames = cfg.frames
    if frames is None:
        # the root layer's endTimeCode alone (HasAuthoredTimeCodeRange wants startTimeCode too: a stage
        # with only endTimeCode = 3 was told it had none; probe of issue 12)
        if not stage.GetRootLayer().HasEndTimeCode():
            raise InputError("the stage has no endTimeCode to take frames from: set frames=N", file)
        exact = stage.GetEndTimeCode() * fps / tcps
        if not math.isfinite(exact):   # inf, nan, 1e308 (x fps): OverflowError / ValueError tracebacks (a probe)
            raise InputError(f"endTimeCode {stage.GetEndTimeCode():g} is {exact:g} frames at {fps:g} fps, not a finite "
                             f"number: end the stage on a frame, or set frames=N", file)
        frames = int(math.floor(exact + 1e-9))
        if frames < 1:
            raise InputError(f"endTimeCode {stage.GetEndTimeCode():g} gives no frame after frame 0", file)
        if abs(exact - round(exact)) > 1e-6:   # 2.5 was cut to 2 frames without a word
            raise InputError(f"endTimeCode {stage.GetEndTimeCode():g} is {exact:g} frames at {fps:g} fps, not a whole "
                             f"number: end the stage on a frame, or set frames=N", file)
    if stage.HasAuthoredTimeCodeRange() and stage.GetStartTimeCode() != 0:   # said, not silently dropped (probe of issue 12)
        logging.getLogger("hairexp").warning(
            "%s: startTimeCode is %g, but a run starts at time code 0 (t = 0 s: the body, colliders and guides are read "
            "from time code 0) and runs to frame %d; shift the stage's animation to start at 0 to simulate from %g",
            file, stage.GetStartTimeCode(), frames, stage.GetStartTimeCode())
    out = copy.deepcopy(cfg)
    OmegaConf.set_readonly(out, False)
    out.frames, out.fps = frames, fps
    return out
