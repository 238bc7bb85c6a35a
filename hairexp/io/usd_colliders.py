"""Colliders as USD gprims under ``/Root/Colliders`` (README "USD scenes").

* sphere: Sphere ``radius``;
* box: Cube of ``size`` 2 whose transform scales by ``half_extents`` (in general half extents
  = size / 2 x the scale);
* cylinder: Cylinder, ``axis`` (written Y; read X, Y or Z), ``radius``, ``height`` = 2 x
  half_height, ``hairexp:spin`` (rad/s, about the axis);
* capsule: Capsule, ``axis`` (as the cylinder's), ``radius``, ``height`` = 2 x half_length (the
  cylindrical part);
* plane: Plane, ``axis`` (as the cylinder's): the half space below the plane through the prim's
  origin, normal to its axis (written Y: below the prim's y = 0).

Each has the custom attributes ``hairexp:thickness`` (m) and ``hairexp:friction`` (defaults
0.002 and 0.3, as in the config), and a rigid transform, time-sampled when the collider moves
(interpolated linearly in between); only a Cube's transform may scale, and not over time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom
from scipy.spatial.transform import Rotation

from hairexp.errors import InputError
from hairexp.io.usd_layout import (COLLIDER_DEFAULTS, COLLIDERS, FRICTION, NAME, NUMBER_TYPES, PLANE_SIZE, SPIN, THICKNESS,
                                   TOKEN_TYPES, check_type, read_motion, set_transform, stage_units)
from hairexp.model.colliders import Box, Capsule, Cylinder, Plane, Sphere

SUPPORTED = ("Sphere", "Cube", "Cylinder", "Capsule", "Plane")


def _one_value(prim, name: str, where: str, default=None):
    """The attribute's one value: its default, or its time samples when they all agree (else
    ``default``, else the schema's fallback).  Time samples alone read as the schema's fallback
    (a sphere of radius 1 m instead of the stage's 0.05; probe of issue 12), and a collider keeps
    its size and spin: samples that differ are an error.  An attribute declared with another type
    than a number (``string radius = "0.05"``, ``bool``, ``double[]``) is an error too."""
    attr = prim.GetAttribute(name)
    check_type(attr, NUMBER_TYPES, where)
    samples = attr.GetTimeSamples() if attr else []
    if samples:
        values = [attr.Get(t) for t in samples]
        if any(v != values[0] for v in values):
            raise InputError(f"{name} is animated ({values[0]!r} at time code {samples[0]:g} -> "
                             f"{next(v for v in values if v != values[0])!r}); a collider keeps its {name} "
                             "(author one value)", where)
        return values[0]
    value = attr.Get() if attr and attr.HasAuthoredValue() else default
    if value is None:
        value = attr.Get() if attr else None  # the schema's fallback
    return value


def _number(prim, name: str, where: str, positive: bool = False, default=None) -> float:
    value = _one_value(prim, name, where, default)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}", where) from None
    if not math.isfinite(value) or value < 0 or (positive and value == 0):
        raise InputError(f"{name} must be a finite number {'> 0' if positive else '>= 0'}, got {value}", where)
    return value


def _length(prim, name: str, where: str, positive: bool = False, default=None) -> float:
    """``_number`` for a length, in metres: the stage's value (authored, or the schema's fallback)
    times the stage's metres per unit (``stage_units``); hairexp's own ``default`` is in metres."""
    value = _number(prim, name, where, positive, default)
    attr = prim.GetAttribute(name)
    if default is not None and not (attr and (attr.HasAuthoredValue() or attr.GetNumTimeSamples())):
        return value
    return value * stage_units(prim.GetStage())


def _spin(prim, where: str) -> float:
    value = _one_value(prim, SPIN, where, COLLIDER_DEFAULTS[SPIN])
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{SPIN} must be a finite number (rad/s), got {value!r}", where)
    return float(value)


#: The fixed rotation of the prim's space that takes hairexp's collider axis (its own Y) onto the
#: prim's ``axis``: X by -90 degrees about Z, Z by +90 degrees about X (column vectors).
AXIS_TURNS = {"X": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
              "Y": np.eye(3),
              "Z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}


def _axis(prim, where: str) -> str:
    """The prim's ``axis``: X, Y or Z (USD's fallback for Capsule, Cylinder and Plane is Z)."""
    check_type(prim.GetAttribute("axis"), TOKEN_TYPES, where)
    axis = prim.GetAttribute("axis").Get()
    if axis not in AXIS_TURNS:
        raise InputError(f"axis is {axis!r}; a {prim.GetTypeName()} lies along X, Y or Z", where)
    return str(axis)


def _along_axis(motion, axis: str):
    """The collider's motion with its own Y turned onto the prim's ``axis`` (``_axis``): each
    keyframe's rotation R becomes R Q (``AXIS_TURNS``).  Between keyframes the motion is linear
    (slerp), and slerp(R_a Q, R_b Q) = slerp(R_a, R_b) Q, so the turned motion is the prim's at
    every time."""
    if axis == "Y":
        return motion
    Q = AXIS_TURNS[axis]
    rots = [(Rotation.from_rotvec(r) * Rotation.from_matrix(Q)).as_rotvec() for r in motion.rotvecs]
    return replace(motion, rotvecs=np.asarray(rots))


def _uniform(scale, axes: tuple, prim, where: str, why: str) -> float:
    """The prim's scale along ``axes`` (its transform's, constant in time: ``read_motion``), which
    must agree (to 1e-6: USD stores float scales), as one number: the factor of the sizes across
    them (a Sphere's radius; a Capsule's or Cylinder's radius across its axis)."""
    vals = np.asarray(scale, dtype=np.float64)[list(axes)]
    if np.abs(vals - vals.mean()).max() > 1e-6 * vals.max():
        raise InputError(f"its transform scales by {np.asarray(scale).tolist()}: a {prim.GetTypeName()} collider may be "
                         f"scaled only alike along {', '.join('XYZ'[i] for i in axes)} ({why}); put the sizes in its "
                         "attributes", where)
    return float(vals.mean())


#: Prim types that group colliders (their children are read as colliders or groups in turn).
GROUPS = ("Xform", "Scope", "")


def read_colliders(stage, path: str, tcps: float, file: str) -> list:
    """The colliders under ``path``: none when the prim does not exist at the default path
    ``/Root/Colliders`` (a stage without colliders); a ``scene.usd_colliders`` set to another path
    must name a prim (a misspelt path would silently run the scene without its colliders)."""
    root = stage.GetPrimAtPath(path) if path.startswith("/") else None
    if not root:
        if path == COLLIDERS:
            return []
        raise InputError(f"no prim at {path} (the colliders; scene.usd_colliders names its path: an absolute prim "
                         f"path, or {COLLIDERS} for a stage without colliders)", file)
    if root.GetTypeName() in SUPPORTED:   # one collider named instead of their parent: it ran with none
        raise InputError(f"is a {root.GetTypeName()}: scene.usd_colliders names the parent of the colliders (a Scope "
                         f"or Xform), each collider a child prim of it ({path}/<name>)", f"{file}:{path}")
    if not root.IsActive():   # its colliders are not on the stage: the scene ran without them, without a word
        logging.getLogger("hairexp").warning("%s: the colliders' prim %s is inactive: no collider used", file, path)
        return []
    out, seen = [], {}
    prims, off, empty = [], [], []
    # instance proxies too: a collider referenced as an instanceable asset is the stage's as any other
    everything = Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)
    it = iter(Usd.PrimRange(root, everything))
    next(it)   # the root itself
    for prim in it:   # children, and the children of groups (Xform, Scope, typeless) below them
        if not prim.IsActive():
            off.append(str(prim.GetPath()))
            it.PruneChildren()
        elif prim.IsAbstract() or not prim.IsDefined():   # a class or an over: no prim of the scene
            it.PruneChildren()
        elif prim.GetTypeName() in GROUPS:
            if not prim.GetFilteredChildren(everything):   # a typeless "def ball { double radius }" read as nothing: said
                empty.append(str(prim.GetPath()))
            continue
        else:
            prims.append(prim)
            it.PruneChildren()   # a collider's own children are not colliders
    if off:   # USD's way to switch a prim off; it was dropped without a word (probe of issue 12, round 12)
        logging.getLogger("hairexp").warning("%s: inactive collider prim(s) not used: %s", file, ", ".join(off))
    if empty:
        logging.getLogger("hairexp").warning("%s: prim(s) under the colliders that are no collider type and hold none "
                                             "(%s), not used: %s", file, ", ".join(SUPPORTED), ", ".join(empty))
    for prim in prims:
        where = f"{file}:{prim.GetPath()}"
        kind = prim.GetTypeName()
        if kind not in SUPPORTED:
            raise InputError(f"unsupported collider type {kind}; use {', '.join(SUPPORTED)} (grouped in Xform or "
                             "Scope prims at any depth)", where)
        motion, scale = read_motion(prim, tcps, where, allow_scale=True)
        name = _name(prim, where, root)
        if name in seen:   # two groups' prims of one name: ``measure.collider`` could not tell them apart
            raise InputError(f"a second collider named {name!r} (the first is {seen[name]}): give one a custom string "
                             f"{NAME}", where)
        seen[name] = prim.GetPath()
        common = dict(name=name, motion=motion, where=where,
                      thickness=_length(prim, THICKNESS, where, default=COLLIDER_DEFAULTS[THICKNESS]),
                      friction=_number(prim, FRICTION, where, default=COLLIDER_DEFAULTS[FRICTION]))
        if kind != "Cylinder" and prim.GetAttribute(SPIN).HasAuthoredValue():
            raise InputError(f"{SPIN} applies to Cylinder colliders only", where)
        if kind == "Sphere":
            s = _uniform(scale, (0, 1, 2), prim, where, "a Sphere stays a sphere")
            out.append(Sphere(radius=s * _length(prim, "radius", where, positive=True), **common))
        elif kind == "Cube":
            half = 0.5 * _length(prim, "size", where, positive=True) * scale
            out.append(Box(half_extents=tuple(float(h) for h in half), **common))
        elif kind in ("Cylinder", "Capsule"):
            axis = _axis(prim, where)
            common["motion"] = _along_axis(motion, axis)
            a = "XYZ".index(axis)
            s_r = _uniform(scale, tuple(i for i in range(3) if i != a), prim, where,
                           f"its cross-section stays round (the axis is {'XYZ'[a]})")
            radius = s_r * _length(prim, "radius", where, positive=True)
            half = 0.5 * float(scale[a]) * _length(prim, "height", where, positive=True)
            if kind == "Cylinder":
                out.append(Cylinder(radius=radius, half_height=half, spin=_spin(prim, where), **common))
            else:
                out.append(Capsule(radius=radius, half_length=half, **common))
        else:
            common["motion"] = _along_axis(motion, _axis(prim, where))
            out.append(Plane(**common))
    return out


def _name(prim, where: str, root=None) -> str:
    """A collider's name: its ``hairexp:name`` (written where the name is not a USD identifier),
    else the prim's name; in an instance of an asset (an instance proxy), whose prims every
    instance shares, its path below the colliders' prim ``root`` with "_" for "/" (two
    instances of a ball asset: ``ball0_geo``, ``ball1_geo``)."""
    a = prim.GetAttribute(NAME)
    if not a.HasAuthoredValue():
        if prim.IsInstanceProxy() and root is not None:
            return str(prim.GetPath().MakeRelativePath(root.GetPath())).replace("/", "_")
        return prim.GetName()
    v = a.Get()
    if not isinstance(v, str) or not v.strip():
        raise InputError(f"{NAME} must be a non-empty string (the collider's name), got {v!r}", where)
    return v


def _custom(prim, name: str, value: float) -> None:
    prim.CreateAttribute(name, Sdf.ValueTypeNames.Double, custom=True).Set(float(value))


def write_colliders(stage, colliders: list, pose_samples) -> list:
    """Define one prim per collider under ``/Root/Colliders``; ``pose_samples(motion)`` gives
    the (time code or None for the default, matrix) pairs of its transform.  Returns the
    (prim path, collider) pairs written."""
    if not colliders:
        return []
    UsdGeom.Scope.Define(stage, COLLIDERS)
    used, written = set(), []
    for c in colliders:
        name = Tf.MakeValidIdentifier(c.name)
        while name in used:
            name += "_"
        used.add(name)
        path = f"{COLLIDERS}/{name}"
        if isinstance(c, Sphere):
            g = UsdGeom.Sphere.Define(stage, path)
            g.CreateRadiusAttr(float(c.radius))
        elif isinstance(c, Box):
            g = UsdGeom.Cube.Define(stage, path)
            g.CreateSizeAttr(2.0)
        elif isinstance(c, Cylinder):
            g = UsdGeom.Cylinder.Define(stage, path)
            g.CreateAxisAttr(UsdGeom.Tokens.y), g.CreateRadiusAttr(float(c.radius))
            g.CreateHeightAttr(2.0 * c.half_height)
            _custom(g.GetPrim(), SPIN, c.spin)
        elif isinstance(c, Capsule):
            g = UsdGeom.Capsule.Define(stage, path)
            g.CreateAxisAttr(UsdGeom.Tokens.y), g.CreateRadiusAttr(float(c.radius))
            g.CreateHeightAttr(2.0 * c.half_length)
        elif isinstance(c, Plane):
            g = UsdGeom.Plane.Define(stage, path)
            g.CreateAxisAttr(UsdGeom.Tokens.y), g.CreateWidthAttr(PLANE_SIZE), g.CreateLengthAttr(PLANE_SIZE)
        else:
            raise TypeError(f"cannot write collider {c.name!r} of type {type(c).__name__} to USD")
        set_transform(g, pose_samples(c.motion))
        if isinstance(c, Box):
            g.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(tuple(float(h) for h in c.half_extents))
        _custom(g.GetPrim(), THICKNESS, c.thickness)
        _custom(g.GetPrim(), FRICTION, c.friction)
        if name != c.name:   # a prim name is an identifier; the collider keeps its own (round 23: renamed silently)
            g.GetPrim().CreateAttribute(NAME, Sdf.ValueTypeNames.String, custom=True).Set(str(c.name))
        g.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(g, Usd.TimeCode.Default()))
        written.append((path, c))
    return written
