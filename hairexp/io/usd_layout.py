"""The prim layout of hairexp's USD stages and the conversions between USD's matrices and
hairexp's rigid poses (README "USD scenes").

Input layout, read by ``experiment=from_usd`` and written by ``write_scene_usd``: metres
(metersPerUnit 1), Y up, time code f is frame f, timeCodesPerSecond is the frame rate::

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

import numpy as np
from pxr import Gf, Usd, UsdGeom
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
#: Collider attributes read when a prim does not author them (the config's defaults).
COLLIDER_DEFAULTS = {THICKNESS: 0.002, FRICTION: 0.3, SPIN: 0.0}

HAIR_WIDTH = 0.001    # m, display width of detail hair
GUIDE_WIDTH = 0.003   # m, display width of guides
PLANE_SIZE = 2.0      # m, display width and length of a Plane collider (it is infinite)

#: Largest |R^T R - I| entry (and |scale - 1|) accepted as a rigid transform.
RIGID_TOL = 1e-6


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
    if dev > RIGID_TOL or np.linalg.det(R) < 0:
        raise InputError(f"transform at {at} is not rigid: it shears or mirrors (|R^T R - I| = {dev:.1e})", where)
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


def read_motion(prim, tcps: float, where: str, allow_scale: bool = False) -> tuple[RigidMotion, np.ndarray]:
    """The prim's world transform as a linear ``RigidMotion`` (keyframes at its time samples)
    and its scale (which must not change over time)."""
    xf = UsdGeom.Xformable(prim)
    times = transform_times(prim) or [Usd.TimeCode.Default()]
    rots, trans, scale0 = [], [], None
    for tc in times:
        R, T, scale = pose_from_matrix(xf.ComputeLocalToWorldTransform(tc), where, tc, allow_scale)
        if scale0 is None:
            scale0 = scale
        elif np.abs(scale - scale0).max() > 1e-9 * scale0.max():
            raise InputError(f"the scale changes at {time_label(tc)} ({scale0.tolist()} -> {scale.tolist()}); "
                             "a collider keeps its size", where)
        rots.append(Rotation.from_matrix(R).as_rotvec())
        trans.append(T)
    secs = [0.0] if isinstance(times[0], Usd.TimeCode) else [t / tcps for t in times]
    return RigidMotion(np.asarray(secs), np.asarray(trans), np.asarray(rots), "linear", where=where), scale0
