"""Scene builders: turn a ``SceneConfig`` into a ``Scene``.

* ``wisp``: strands with roots spread uniformly over a disk on the rigid body, straight at
  rest along ``direction`` (optionally tilted at random by up to ``spread``).
* ``ponytail``: the Celia-scale ponytail (301 strands x 26 vertices by default): roots on a
  tight disk, strands fanning out as a cone whose rim strands tilt outward by ``spread``.
  A cone never makes two strands cross or touch at rest (the gap between neighbours grows
  along the strands), so hair-hair collisions start from a contact-free rest state.
* ``usd``: a user's USD stage ``scene.usd`` (hairexp/io/usd_read.py, README "USD scenes"); the
  dispatch over all builders is ``hairexp.app.builders.build_scene``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hairexp.errors import MAX_COORDINATE, InputError, choice_name
from hairexp.model.colliders import SHAPES
from hairexp.model.dynamic_body import build_dynamic_body
from hairexp.model.rigid import MAX_KEY_DEGREES, RigidMotion
from hairexp.model.scene import MATERIAL_MAX, MAX_GRAVITY, MIN_LINEAR_DENSITY, Material, Scene
from hairexp.model.strands import MAX_STRAND_LENGTH, Strands


def vec3(v, key: str) -> np.ndarray:
    a = np.asarray(list(v), dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InputError(f"expected 3 finite numbers, got {list(v)}", key)
    return a


def gravity(v, key: str = "scene.gravity") -> np.ndarray:
    """``scene.gravity`` (m/s^2) checked: 3 finite numbers of magnitude <= MAX_GRAVITY."""
    g = vec3(v, key)
    big = float(np.abs(g).max())
    if big > MAX_GRAVITY or float(np.linalg.norm(g / big if big else g)) * big > MAX_GRAVITY:
        raise InputError(f"is {g.tolist()}, larger than {MAX_GRAVITY:g} m/s^2 (about 100 g); gravity is in m/s^2 "
                         "(Earth's: [0, -9.81, 0])", key)
    return g


def _unit(v, key) -> np.ndarray:
    a = vec3(v, key)
    n = np.linalg.norm(a)
    if n == 0:
        raise InputError("direction must be non-zero", key)
    return a / n


def disk_points(n: int, radius: float) -> np.ndarray:
    """n points spread evenly over a disk (sunflower / Vogel spiral), (n, 2)."""
    k = np.arange(n) + 0.5
    r = radius * np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], 1)


def line_points(n: int, radius: float) -> np.ndarray:
    """n points evenly on the segment [-radius, radius] of the first layout axis (at the centres
    of n equal intervals), (n, 2)."""
    u = ((np.arange(n) + 0.5) / n * 2.0 - 1.0) * radius
    return np.stack([u, np.zeros(n)], 1)


#: m, the longest hair and the widest root disk a procedural builder makes (hair is metres long at most)
MAX_HAIR_SIZE = MAX_STRAND_LENGTH
#: m, the shortest rest edge a built strand may have (scene.length / (n_vertices - 1)): 30 cm in
#: 4,000 vertices (75 um edges) already failed its first step, 100,000 ran for minutes without one
MIN_REST_EDGE = 1e-4


def check_counts(n_strands: int, n_vertices: int, length: float | None = None, key: str = "scene.n_vertices") -> None:
    """``scene.n_strands`` >= 1 and ``scene.n_vertices`` >= 3 (and, with the strands' ``length``,
    edges of at least MIN_REST_EDGE), or an InputError naming the key (also called before the
    resource guard and by an experiment's check of every variant's config, so a bad count fails
    before anything runs: -2 x -3 strands would pass the guard's size)."""
    if n_strands < 1:
        raise InputError(f"must be >= 1, got {n_strands}", "scene.n_strands")
    if n_vertices < 3:
        raise InputError(f"must be >= 3 (two root vertices and one free), got {n_vertices}", key)
    if length is not None and np.isfinite(length) and 0 < length < 2 * MIN_REST_EDGE:   # no vertex count fits (round 16)
        raise InputError(f"is {length:g} m: a strand of 3 vertices (the fewest) needs at least {2e3 * MIN_REST_EDGE:g} mm "
                         f"for edges of {1e3 * MIN_REST_EDGE:g} mm (hairexp reads metres)", "scene.length")
    if length is not None and np.isfinite(length) and length > 0 and length / (n_vertices - 1) < MIN_REST_EDGE:
        raise InputError(f"{n_vertices} vertices on {length:g} m make edges of {1e3 * length / (n_vertices - 1):.3g} mm, "
                         f"shorter than {1e3 * MIN_REST_EDGE:g} mm: the stretch springs are then too stiff for any step "
                         f"to converge; use at most {int(length / MIN_REST_EDGE) + 1} vertices", key)


#: the smallest distance between two roots of ``straight_strands`` without a spread: 1 micrometre
#: (a hair is about 70 micrometres thick)
MIN_ROOT_GAP = 1e-6


def straight_strands(n_strands: int, n_vertices: int, length: float, root_radius: float, center: np.ndarray,
                     direction: np.ndarray, spread: float, seed: int, fan: bool = False,
                     layout: str = "disk") -> np.ndarray:
    """(n_strands * n_vertices, 3) straight strands rooted on a disk normal to ``direction``
    (``layout="line"``: on a diameter of it, along the axis on which guide 0 of a guide pair
    sits, hairexp/guides/animation.py ``rest_guides``: a flat strip of hair).

    ``fan``: strand i tilts outward in proportion to its root's distance from the centre (a
    cone, rim tilt ``spread``); otherwise each strand tilts by a random angle up to ``spread``."""
    check_counts(n_strands, n_vertices, length)
    # at most MAX_HAIR_SIZE: 1e300 made a guide simulation that diverged at its first step (probe, round 14)
    if not (0 < length <= MAX_HAIR_SIZE):
        raise InputError(f"must be a finite number > 0 and <= {MAX_HAIR_SIZE:g} (m), got {length}", "scene.length")
    if not (0 <= root_radius <= MAX_HAIR_SIZE):
        raise InputError(f"must be a finite number >= 0 and <= {MAX_HAIR_SIZE:g} (m), got {root_radius}",
                         "scene.root_radius")
    if fan and spread > 0 and root_radius == 0:
        raise InputError("must be > 0 for a ponytail with scene.spread > 0 (the rim strands tilt by spread)",
                         "scene.root_radius")
    if n_strands > 1 and root_radius == 0 and spread == 0:   # accepted silently (probe of issue 12, round 12)
        raise InputError(f"must be > 0 for {n_strands} strands without scene.spread: every strand would lie on the "
                         "same line", "scene.root_radius")
    max_spread = np.pi / 2 if fan else np.pi   # a cone's rim tilts by tan(spread)
    if not (0 <= spread < max_spread if fan else 0 <= spread <= max_spread):
        raise InputError(f"must be in [0, {max_spread:.4g}{')' if fan else ']'} rad, got {spread}", "scene.spread")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"must be an integer >= 0, got {seed!r}", "scene.seed")
    a = np.array([1.0, 0, 0]) if abs(direction[0]) < 0.9 else np.array([0, 0, 1.0])
    u = np.cross(direction, a)
    u /= np.linalg.norm(u)
    w = np.cross(direction, u)
    if layout not in ("disk", "line"):
        raise InputError(f"unknown root layout {layout!r} (disk|line)", "scene.root_layout")
    d2 = disk_points(n_strands, root_radius) if layout == "disk" else line_points(n_strands, root_radius)
    if n_strands > 1 and spread == 0:   # 1e-300 m was taken where 0 is refused (independent probe, round 26)
        gap = float(cKDTree(d2).query(d2, k=2)[0][:, 1].min())
        if gap < MIN_ROOT_GAP:
            raise InputError(f"is {root_radius:g} m: the {n_strands} roots would be {gap:.3g} m apart, less than "
                             f"{MIN_ROOT_GAP:g} m (a strand lying on another without scene.spread); give a radius "
                             "in metres, such as 0.02", "scene.root_radius")
    roots = center + d2[:, :1] * u + d2[:, 1:] * w
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, length, n_vertices)
    pts = []
    for i in range(n_strands):
        d = direction
        if fan and spread > 0:
            d = direction + np.tan(spread) * (roots[i] - center) / root_radius
            d = d / np.linalg.norm(d)
        elif spread > 0:
            axis = rng.normal(size=3)
            axis -= axis.dot(direction) * direction
            axis /= np.linalg.norm(axis)
            d = Rotation.from_rotvec(axis * spread * rng.uniform()).apply(direction)
        pts.append(roots[i] + s[:, None] * d)
    return np.concatenate(pts)


def build_motion(cfg, where: str = "scene.motion") -> RigidMotion:
    """The keyframed motion of a ``MotionConfig`` (``where``: its key): one translation and one
    rotation (3 numbers each) per time."""
    times = list(cfg.times)
    for key in ("translations", "rotations_deg"):
        keys = list(getattr(cfg, key))
        if len(keys) != len(times):
            raise InputError(f"has {len(keys)} keyframes but {where}.times has {len(times)}: one per time",
                             f"{where}.{key}")
        for i, k in enumerate(keys):
            v = vec3(k, f"{where}.{key}[{i}]")
            if key == "rotations_deg" and np.abs(v).max() > MAX_KEY_DEGREES:   # 1e9 was taken modulo 360 (probe, round 12)
                raise InputError(f"must be within +-{MAX_KEY_DEGREES:g} degrees (100 turns), got {v.tolist()}",
                                 f"{where}.{key}[{i}]")
    rot = np.deg2rad(np.asarray(cfg.rotations_deg, dtype=np.float64).reshape(-1, 3))
    return RigidMotion(np.asarray(cfg.times, dtype=np.float64), np.asarray(cfg.translations, dtype=np.float64),
                       rot, choice_name(cfg.interpolation), where=where, turns=True)


#: N, the softest stretch stiffness (EA) a config's hair may have (the API's Material takes less, for tests)
MIN_STRETCH_STIFFNESS = 1e-3


def build_material(h) -> Material:
    """The hair material of ``scene.hair``, validated."""
    for key in ("linear_density", "stretch_stiffness", "bending_stiffness"):
        if not (getattr(h, key) > 0 and np.isfinite(getattr(h, key))):
            raise InputError(f"must be a finite number > 0, got {getattr(h, key)}", f"scene.hair.{key}")
        if key == "stretch_stiffness" and getattr(h, key) < MIN_STRETCH_STIFFNESS:   # 1e-30: 212 % stretch (round 16)
            raise InputError(f"is {getattr(h, key):g} N, below {MIN_STRETCH_STIFFNESS:g}: hair that does not hold its "
                             "length (human hair: EA about 1-100 N)", f"scene.hair.{key}")
        if key == "linear_density" and getattr(h, key) < MIN_LINEAR_DENSITY:   # 1e-300 "converged" in 0 iterations
            raise InputError(f"is {getattr(h, key):g} kg/m, below {MIN_LINEAR_DENSITY:g}: massless hair (human hair is "
                             "about 1e-5 to 1e-4 kg/m; a step's inertia against its stiffness is then beyond double "
                             "precision)", f"scene.hair.{key}")
        if getattr(h, key) > MATERIAL_MAX:   # hair: EA ~ 1-100 N, EI ~ 1e-9-1e-5 N m^2, 1e-5-1e-3 kg/m
            raise InputError(f"is {getattr(h, key):g}, beyond {MATERIAL_MAX:g}: the step's Newton system (stiffness "
                             "against mass / dt^2) is then beyond double precision", f"scene.hair.{key}")
    for key in ("edge_damping", "air_drag"):
        if not (getattr(h, key) >= 0 and np.isfinite(getattr(h, key))):
            raise InputError(f"must be a finite number >= 0, got {getattr(h, key)}", f"scene.hair.{key}")
        if getattr(h, key) > MATERIAL_MAX:   # air_drag=1e300 diverged at the first step (probe of issue 12, round 14)
            raise InputError(f"is {getattr(h, key):g}, beyond {MATERIAL_MAX:g}: the step's Newton system (damping "
                             "against mass / dt) is then beyond double precision", f"scene.hair.{key}")
    return Material(h.linear_density, h.stretch_stiffness, h.bending_stiffness, h.edge_damping, h.air_drag)


def build_procedural_scene(cfg) -> Scene:
    """The ``wisp`` and ``ponytail`` builders (see the module doc), before ``with_dynamic_body``."""
    builder = choice_name(cfg.builder)
    direction = _unit(cfg.direction, "scene.direction")
    center = vec3(cfg.root_center, "scene.root_center")
    if np.abs(center).max() > MAX_COORDINATE:   # it ended as a diverged guide simulation, exit 3 (probe, round 12)
        raise InputError(f"{center.tolist()} is more than {MAX_COORDINATE:g} m from the origin: hairexp reads metres "
                         "(check the units)", "scene.root_center")
    if builder in ("wisp", "ponytail"):
        body_pts = straight_strands(cfg.n_strands, cfg.n_vertices, cfg.length, cfg.root_radius, center,
                                    direction, cfg.spread, cfg.seed, fan=builder == "ponytail",
                                    layout=choice_name(cfg.root_layout))
    else:  # pragma: no cover - the schema's Enum rejects other names
        raise InputError(f"unknown builder {builder!r}", "scene.builder")
    material = build_material(cfg.hair)
    motion = build_motion(cfg.motion)
    world = motion.transform(body_pts, 0.0)
    counts = np.full(cfg.n_strands, cfg.n_vertices)
    strands = Strands.from_polylines(world, counts, material.linear_density, where=f"scene {cfg.name}")
    colliders = [build_collider(c, i) for i, c in enumerate(getattr(cfg, "colliders", []) or [])]
    return Scene(cfg.name, strands, material, motion, gravity(cfg.gravity), body_pts, colliders)


def with_dynamic_body(cfg, scene: Scene) -> Scene:
    """``scene.body.dynamic``: the body becomes a dynamic block on a rail starting at the pose of
    ``scene.motion`` (hairexp/model/dynamic_body.py); otherwise the scene is returned as built."""
    body = getattr(cfg, "body", None)
    if body is None or not body.dynamic:
        return scene
    return replace(scene, motion=build_dynamic_body(body, scene.motion, scene.strands, scene.gravity))


def check_spin(shape: str, spin, key: str) -> None:
    """InputError for a spin on a collider other than a cylinder (``key``: the collider's)."""
    if shape != "cylinder" and spin != 0:
        raise InputError(f"is {spin} but only a cylinder spins (shape {shape})", f"{key}.spin")
    if abs(float(spin)) > MAX_SPIN:   # 1e9 rad/s taken without a word (probe of issue 12, round 15)
        raise InputError(f"must be within +-{MAX_SPIN:g} rad/s (about 1,600 turns a second), got {spin}", f"{key}.spin")


#: rad/s, the fastest collider spin
MAX_SPIN = 1e4


def build_collider(c, i: int):
    shape = choice_name(c.shape)
    key = f"scene.colliders[{i}]"
    if c.name is None or not str(c.name).strip():   # it became ``collider0`` without a word (probe of issue 12, round 17)
        raise InputError(f"must be a non-empty name, got {c.name!r} (a collider is found by its name: "
                         "measure.collider, the metrics' contacts_<name>)", f"{key}.name")
    common = dict(name=str(c.name), motion=build_motion(c.motion, f"{key}.motion"),
                  thickness=c.thickness, friction=c.friction, where=key)
    for k in ("radius", "half_length", "half_height"):
        if not (getattr(c, k) > 0 and np.isfinite(getattr(c, k))):
            raise InputError(f"must be a finite number > 0 (m), got {getattr(c, k)}", f"{key}.{k}")
    check_spin(shape, c.spin, key)
    if shape == "sphere":
        return SHAPES[shape](radius=c.radius, **common)
    if shape == "capsule":
        return SHAPES[shape](radius=c.radius, half_length=c.half_length, **common)
    if shape == "box":
        he = vec3(c.half_extents, f"{key}.half_extents")
        if not np.all(he > 0):
            raise InputError(f"must be > 0, got {he.tolist()}", f"{key}.half_extents")
        return SHAPES[shape](half_extents=tuple(he), **common)
    if shape == "cylinder":
        return SHAPES[shape](radius=c.radius, half_height=c.half_height, spin=c.spin, **common)
    return SHAPES[shape](**common)
