"""The prim layout of hairexp's USD stages and the conversions between USD's matrices and
hairexp's rigid poses (README "USD scenes").

Input layout, read by ``experiment=from_usd`` and written by ``write_scene_usd``: metres
(metersPerUnit 1; a stage in other units is read in metres: ``stage_units``), Y up (a Z-up stage
is turned to Y up: ``world_transform``), time code f is frame f, timeCodesPerSecond is the frame
rate::

    /Root                 Xform
    /Root/Body            Xform: the rigid body the hair roots on, its transform time-sampled
    /Root/Body/Hair       BasisCurves: the detail hair at rest, in the body's space
    /Root/Guides          BasisCurves: the guides in world space, one time sample per frame
    /Root/Colliders/<n>   Sphere, Cube, Cylinder, Capsule or Plane (axis Y), optionally
                          time-sampled, with hairexp:thickness, hairexp:friction, hairexp:spin

A run's ``result.usdc`` (or ``.usda``) has the same prims (so it re-imports) plus
``/Root/Result/Hair``: the simulated hair in world space, one time sample per frame.  A long
run's time samples are in value clips (``result.clips/``, a clip set on ``/Root``; see
``usd_write``): read the stage through ``Usd.Stage.Open``, which composes them.

USD composes row vectors: ``p_world = p_local * M`` with the translation in the last row;
hairexp's poses are column-vector ``x = R X + T``.
"""

from __future__ import annotations

import math
import re

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom
from scipy.spatial.transform import Rotation

from hairexp.errors import InputError
from hairexp.model.rigid import RigidMotion

ROOT = "/Root"
BODY = "/Root/Body"
HAIR = "/Root/Body/Hair"
GUIDES = "/Root/Guides"
COLLIDERS = "/Root/Colliders"
RESULT = "/Root/Result"
RESULT_HAIR = "/Root/Result/Hair"

THICKNESS, FRICTION, SPIN = "hairexp:thickness", "hairexp:friction", "hairexp:spin"
#: a collider's own name where it is not a USD identifier (the prim's name is made one: 'ball-1' is
#: the prim ball_1); read back as the collider's name, so that measure.collider and the metrics'
#: contacts_<name> still match after a re-import
NAME = "hairexp:name"
#: customData key on the guides prim of a run's result: which ``guides.edits`` the guides there
#: carry (``GuideAnimation.edits_applied``; a stage read back with the same edits applies them again)
EDITS_APPLIED = "hairexp:edits_applied"
#: Collider attributes read when a prim does not author them (the config's defaults).
COLLIDER_DEFAULTS = {THICKNESS: 0.002, FRICTION: 0.3, SPIN: 0.0}

HAIR_WIDTH = 0.001    # m, display width of detail hair
GUIDE_WIDTH = 0.003   # m, display width of guides
PLANE_SIZE = 2.0      # m, display width and length of a Plane collider (it is infinite)

#: Largest |R^T R - I| entry (and |scale - 1|) accepted as a rigid transform.
RIGID_TOL = 1e-6


def tf_message(exc: Exception) -> str:
    """The first quoted reason in a Tf error (``Error in '...' at line N in file F : 'reason'``, one
    per error), else the text.  A reason may hold quotes and end with a newline: a syntax error's
    ``'<file>:67:6: Expected } at '{' in </Root/Colliders>\n'`` was skipped for the next error's
    ``Failed to open layer`` (probe of issue 12, round 18)."""
    found = re.findall(r" : '(.*?)'\s*(?=\n\s*Error in |\Z)", str(exc), flags=re.S)
    return " ".join(found[0].split()) if found else " ".join(str(exc).split())


def _kind(label: str, *names: str) -> tuple[str, frozenset]:
    """(what to say, the value types) of the attributes a reader accepts: the types of the
    ``Sdf.ValueTypeNames`` ``names`` whatever their role (point3f[], vector3f[], normal3f[] and
    float3[] hold the same values)."""
    return label, frozenset(getattr(Sdf.ValueTypeNames, n).type for n in names)


#: The declared types an attribute read by hairexp may have (``check_type``).
POINTS_TYPES = _kind("point3f[] (an array of 3-vectors: point3f[], float3[], double3[], half3[], vector3f[], ...)",
                     "Float3Array", "Double3Array", "Half3Array")
COUNTS_TYPES = _kind("int[] (an array of integers)", "IntArray", "UIntArray", "Int64Array", "UInt64Array")
NUMBER_TYPES = _kind("a number (double, float, half or int)",
                     "Double", "Float", "Half", "Int", "UInt", "Int64", "UInt64")
TOKEN_TYPES = _kind("token", "Token", "String")
_OP_ORDER_TYPES = _kind("token[] (the names of the transform ops, in order)", "TokenArray")
_OP_VEC3 = _kind("double3 (or float3 or half3)", "Double3", "Float3", "Half3")
_OP_SCALAR = _kind("double (or float or half)", "Double", "Float", "Half")
#: xformOp:<type> -> the value types USD computes a transform from (UsdGeomXformOp)
_OP_TYPES = {"transform": _kind("matrix4d", "Matrix4d"),
             "orient": _kind("quatd (or quatf or quath)", "Quatd", "Quatf", "Quath"),
             **{op: _OP_VEC3 for op in ("translate", "scale", "rotateXYZ", "rotateXZY", "rotateYXZ", "rotateYZX",
                                        "rotateZXY", "rotateZYX")},
             **{op + axis: _OP_SCALAR for op in ("rotate", "translate", "scale") for axis in "XYZ"}}


def check_type(attr, kind: tuple[str, frozenset], where: str, owner: str = "") -> None:
    """InputError naming the attribute (prefixed by ``owner``, e.g. ``/Root.``, when it is not on
    the prim ``where`` names) when its declared type is not one of ``kind``'s: a string where
    points are read, an int where an int[] is (a ValueError or TypeError deep in numpy, a Tf
    error out of USD: a traceback instead of this error).  The types are those the layers author
    (a schema's attribute reports the schema's type whatever a layer declares, and its value is
    the layer's).  An attribute that does not exist is left to the caller."""
    if not attr:
        return
    label, types = kind
    declared = [spec.typeName for spec in attr.GetPropertyStack(Usd.TimeCode.Default())] + [attr.GetTypeName()]
    bad = next((t for t in declared if t.type not in types), None)
    if bad is not None:
        raise InputError(f"{owner}{attr.GetName()} has type {str(bad) or 'unknown'}, expected {label}", where)


def check_quaternions(attr, where: str, owner: str = "") -> None:
    """InputError when a value of the orient op ``attr`` (its default and every time sample) is not
    a finite quaternion of non-zero length: USD turned a zero quaternion into no rotation without a
    word (probe of issue 12, round 11).  Lengths other than 1 are normalised, as USD does."""
    times = [Usd.TimeCode.Default()] + [Usd.TimeCode(t) for t in attr.GetTimeSamples()]
    for tc in times:
        q = attr.Get(tc)
        if q is None:
            continue
        v = np.array([q.GetReal(), *q.GetImaginary()], dtype=np.float64)
        if not np.isfinite(v).all() or np.linalg.norm(v) < 1e-12:
            raise InputError(f"{owner}{attr.GetName()} at {time_label(tc)} is {v.tolist()}, not a rotation "
                             "(a quaternion must be finite and of non-zero length)", where)


def check_transform_types(prim, where: str) -> None:
    """InputError when a transform op of ``prim`` or of an ancestor it inherits from has a value
    type USD cannot compute a transform from (``string xformOp:transform``: a Tf error out of
    ComputeLocalToWorldTransform), ``xformOpOrder`` is not a token[] (USD ignores it: the prim
    did not move) or names an op the prim does not have (USD skips it with a warning)."""
    p = prim
    while p and p.IsValid() and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable):
            owner = "" if p == prim else f"{p.GetPath()}."   # the property's path: on another prim
            order = p.GetAttribute("xformOpOrder")
            if order and order.HasAuthoredValue():
                check_type(order, _OP_ORDER_TYPES, where, owner)
                names = [str(n) for n in order.Get()]
                for name in names:
                    if name == "!resetXformStack!":
                        continue
                    attr_name = name.removeprefix("!invert!")
                    parts = attr_name.split(":")
                    if len(parts) < 2 or parts[0] != "xformOp" or parts[1] not in _OP_TYPES:
                        raise InputError(f"{owner}xformOpOrder names {name}, which is not a transform op "
                                         "(xformOp:<translate, scale, rotateXYZ, ..., orient or transform>[:<suffix>])",
                                         where)
                    attr = p.GetAttribute(attr_name)
                    if not attr:
                        raise InputError(f"{owner}xformOpOrder names {name}, but the prim has no attribute "
                                         f"{attr_name} (USD would skip the op)", where)
                    check_type(attr, _OP_TYPES[parts[1]], where, owner)
                    if parts[1] == "orient":
                        check_quaternions(attr, where, owner)
                if "!resetXformStack!" in names:   # the ancestors' transforms do not apply
                    return
        p = p.GetParent()


def stage_units(stage) -> float:
    """Metres per unit of the stage's lengths: its ``metersPerUnit`` where authored (0.01 for a
    stage in centimetres, as Maya writes them), else 1 (USD's fallback is 0.01, but a stage that
    does not say is read in metres, hairexp's own unit).  ``open_stage`` has checked it is a
    finite number > 0."""
    return float(UsdGeom.GetStageMetersPerUnit(stage)) if UsdGeom.StageHasAuthoredMetersPerUnit(stage) else 1.0


#: A Z-up stage's world turned to hairexp's Y up: the rotation by -90 degrees about X, (x, y, z) ->
#: (x, z, -y), as a USD (row-vector) matrix: its up axis becomes +Y, its +Y becomes -Z
Z_UP_TO_Y_UP = Gf.Matrix4d(1, 0, 0, 0, 0, 0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1)


def world_transform(xformable, tc, where: str) -> Gf.Matrix4d:
    """``ComputeLocalToWorldTransform(tc)``, with a Tf error (a value USD cannot compute a
    transform from: see ``check_transform_types``) an InputError naming ``where`` and the time;
    to hairexp's world (metres, Y up):

    * on a stage in other units (``stage_units`` s) the translation times s: the transform from
      the prim's space in metres to the world's in metres (rotation and any scale are unit-free;
      the points of a prim are read times s, ``usd_read.read_curves``);
    * on a Z-up stage (``upAxis`` Z, as Blender writes them) then turned by ``Z_UP_TO_Y_UP``: the
      world is turned, each prim's own space is not (a Capsule along its own Y stays one)."""
    try:
        M = xformable.ComputeLocalToWorldTransform(tc)
    except Tf.ErrorException as exc:
        raise InputError(f"cannot compute the transform at {time_label(tc)}: {tf_message(exc)}", where) from None
    stage = xformable.GetPrim().GetStage()
    s = stage_units(stage)
    if s != 1.0:
        M = Gf.Matrix4d(M)
        M.SetRow(3, Gf.Vec4d(M[3][0] * s, M[3][1] * s, M[3][2] * s, M[3][3]))
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        M = M * Z_UP_TO_Y_UP
    return M


def time_label(tc) -> str:
    if isinstance(tc, Usd.TimeCode):
        return "the default time" if tc.IsDefault() else f"time code {tc.GetValue():g}"
    return f"time code {float(tc):g}"


def matrix_from_pose(R: np.ndarray, T: np.ndarray) -> Gf.Matrix4d:
    """USD (row-vector) matrix of ``x = R X + T``."""
    m = np.eye(4)
    m[:3, :3] = np.asarray(R).T
    m[3, :3] = T
    return Gf.Matrix4d(m.tolist())


def pose_from_matrix(M, where: str, tc, allow_scale: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, T, scale) with ``x = R diag(scale) X + T`` from a USD matrix.

    Rejects non-finite and projective matrices, shear and mirroring; a scale other than 1 only
    with ``allow_scale`` (a Cube's half extents).  The error names ``where`` and the time."""
    m = np.array(M, dtype=np.float64).reshape(4, 4)
    at = time_label(tc)
    if not np.isfinite(m).all():
        raise InputError(f"transform at {at} is not finite", where)
    if np.abs(m[:3, 3]).max() > RIGID_TOL or abs(m[3, 3] - 1.0) > RIGID_TOL:
        raise InputError(f"transform at {at} is projective (last column {m[:, 3].tolist()})", where)
    A = m[:3, :3].T                      # column-vector linear part: R diag(scale)
    scale = np.linalg.norm(A, axis=0)
    if (scale < 1e-12).any():
        raise InputError(f"transform at {at} is degenerate (scale {scale.tolist()})", where)
    R = A / scale
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev > RIGID_TOL:
        raise InputError(f"transform at {at} is not rigid: it shears (|R^T R - I| = {dev:.1e})", where)
    if np.linalg.det(R) < 0:   # the message said "shears or mirrors (|R^T R - I| = 0)" (probe, round 13)
        raise InputError(f"transform at {at} is not rigid: it mirrors (a negative scale, determinant "
                         f"{np.linalg.det(A):.3g}); hair and colliders cannot be mirrored", where)
    if not allow_scale and np.abs(scale - 1.0).max() > RIGID_TOL:
        raise InputError(f"transform at {at} is not rigid: it scales by {scale.tolist()} "
                         "(bodies and colliders move rigidly; put sizes in the shape's attributes)", where)
    return R, m[3, :3].copy(), scale


def set_transform(xformable, samples):
    """Add an ``xformOp:transform`` holding (time code or None for the untimed value, matrix)
    samples; returns the op."""
    op = xformable.AddTransformOp()
    for tc, M in samples:
        if tc is None:
            op.Set(M)
        else:
            op.Set(M, tc)
    return op


def transform_times(prim) -> list[float]:
    """Time samples of the prim's transform and of its ancestors' (sorted)."""
    times = set()
    p = prim
    while p and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable):
            times.update(UsdGeom.Xformable(p).GetTimeSamples())
        p = p.GetParent()
    return sorted(times)


#: ``read_motion``: a transform is read at every frame (time code) between its first and last
#: sample, and a segment between two reads is halved while the pose USD computes at its middle
#: differs from the linear interpolation there (translation, slerp of the rotation) by more than
#: POSE_TOL_M in position or POSE_TOL_RAD in rotation, at most POSE_SPLITS times (2^6 reads a frame)
POSE_TOL_M, POSE_TOL_RAD, POSE_SPLITS = 1e-5, 1e-5, 6
#: ``read_motion``: at most this many frames of a transform read one by one (beyond: its samples only)
MAX_POSE_FRAMES = 200_000


def _pose_at(xf, tc: float, where: str, allow_scale: bool):
    return pose_from_matrix(world_transform(xf, Usd.TimeCode(tc), where), where, tc, allow_scale)


def _mid_error(a, b, m) -> tuple[float, float]:
    """(m, rad): how far the pose m (R, T) at the middle of the segment between poses a and b is
    from their linear interpolation there (the translations' mean, the rotations' slerp)."""
    Ra, Rb, Rm = (Rotation.from_matrix(p[0]) for p in (a, b, m))
    half = Ra * Rotation.from_rotvec(0.5 * (Ra.inv() * Rb).as_rotvec())
    return (float(np.linalg.norm(m[1] - 0.5 * (a[1] + b[1]))), float((half.inv() * Rm).magnitude()))


def read_motion(prim, tcps: float, where: str, allow_scale: bool = False) -> tuple[RigidMotion, np.ndarray]:
    """The prim's world transform as a linear ``RigidMotion`` and its scale (which must not
    change over time).

    USD computes a transform from its ops' values, interpolated between their time samples (an
    angle of ``rotateY``, a parent's rotation about a pivot): between two samples a prim can turn
    a whole turn, or swing along an arc.  So the transform is read at every time code from its
    first to its last sample (its own and its ancestors'; one per frame), and between two reads
    the motion is linear only where the pose USD computes at their middle is the linear one's
    (``POSE_TOL_M``, ``POSE_TOL_RAD``), else read there too (not a keyed matrix op, below: read at
    its samples, as before).  Keys at only the samples read a turn
    of 360 degrees keyed at two frames as no motion, of 270 degrees as -90, and a parent's turn as a
    straight line (independent probe, 2026-12-07).  The motion's velocity jumps (where a time
    integrator restarts, ``RigidMotion.velocity_jumps``) are at the samples that are keyframes: at
    least one frame from the samples beside them; samples at every frame are a motion's samples."""
    check_transform_types(prim, where)
    xf = UsdGeom.Xformable(prim)
    authored = np.asarray(transform_times(prim), dtype=np.float64)
    if not authored.size:   # no time sample: the untimed value, still
        tc = Usd.TimeCode.Default()
        R, T, scale = pose_from_matrix(world_transform(xf, tc, where), where, tc, allow_scale)
        return RigidMotion(np.zeros(1), T[None], Rotation.from_matrix(R).as_rotvec()[None], "linear",
                           where=where), scale
    # a matrix op keyed at several times: USD interpolates its sixteen numbers one by one, which neither
    # turns nor keeps the size (hairexp's own result files key the body so): read at its samples only,
    # rigid between them
    dense = not _keyed_matrix(prim)
    lo, hi = float(authored[0]), float(authored[-1])
    frames = np.arange(math.ceil(lo), math.floor(hi) + 1.0) if dense and hi - lo <= MAX_POSE_FRAMES else np.zeros(0)
    codes = np.union1d(authored, frames).tolist()
    rots, trans, scale0, secs = [], [], None, []

    def add(tc, pose):
        nonlocal scale0
        R, T, scale = pose
        if scale0 is None:
            scale0 = scale
        elif allow_scale and np.abs(scale - scale0).max() > 1e-9 * scale0.max():
            # (a rigid prim's scale is 1 within RIGID_TOL at every time, checked above: its round-off may
            # differ between samples; the body was refused as "a collider" for 1.0000001; round 23)
            raise InputError(f"the scale changes at {time_label(tc)} ({scale0.tolist()} -> {scale.tolist()}); "
                             "a collider's scale is part of its size, which cannot change", where)
        rots.append(R)
        trans.append(T)
        secs.append(tc / tcps)

    prev = _pose_at(xf, codes[0], where, allow_scale)
    add(codes[0], prev)
    for a, b in zip(codes[:-1], codes[1:]):
        end = _pose_at(xf, b, where, allow_scale)
        # the segment [a, b] halved where its middle is not the linear motion's: depth first, in order
        stack = [(a, prev, b, end, 0)]
        while stack:
            ta, pa, tb, pb, depth = stack.pop()
            if dense and depth < POSE_SPLITS:
                tm = 0.5 * (ta + tb)
                pm = _pose_at(xf, tm, where, allow_scale)
                dx, dr = _mid_error(pa, pb, pm)
                if dx > POSE_TOL_M or dr > POSE_TOL_RAD:
                    stack.append((tm, pm, tb, pb, depth + 1))
                    stack.append((ta, pa, tm, pm, depth + 1))
                    continue
            add(tb, pb)
        prev = end
    rv = Rotation.from_matrix(np.asarray(rots)).as_rotvec()   # between keys the shortest turn: the reads are close
    return RigidMotion(np.asarray(secs), np.asarray(trans), rv, "linear", where=where,
                       jump_times=_keyframes(authored) / tcps), scale0


def _keyed_matrix(prim) -> bool:
    """Whether the prim's transform or an ancestor's has a matrix op (``xformOp:transform``) with
    more than one time sample."""
    p = prim
    while p and not p.IsPseudoRoot():
        if p.IsA(UsdGeom.Xformable):
            for op in UsdGeom.Xformable(p).GetOrderedXformOps():
                if op.GetOpType() == UsdGeom.XformOp.TypeTransform and op.GetNumTimeSamples() > 1:
                    return True
        p = p.GetParent()
    return False


def _keyframes(codes: np.ndarray) -> np.ndarray:
    """The time codes among a transform's samples ``codes`` that are keyframes: the first and the
    last (the stillness outside them), and those more than one frame (time code) from each sample
    beside them."""
    gap = np.diff(codes)
    sparse = np.concatenate([[True], gap > 1.0 + 1e-9]) & np.concatenate([gap > 1.0 + 1e-9, [True]])
    sparse[0] = sparse[-1] = True
    return codes[sparse]
