"""Kinematic colliders with analytic signed distances (paper 3.4: impulse-based collision
handling after each step, following Bridson et al. 2002).

Each collider is a shape in its body frame, carried by a ``RigidMotion``, with a thickness
(the distance hair keeps from the surface, m) and a Coulomb friction coefficient.  A cylinder
can spin about its own axis (a wheel).  Queries are vectorised over points:
``sdf_body(X)`` (signed distance, negative inside, before the thickness), ``normal_body(X)``
(unit outward gradient).  World queries at time t map through the pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hairexp.errors import InputError, real_type
from hairexp.model.rigid import RigidMotion

EPS = 1e-12


def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), EPS)


#: m, a collider's contact shell at most this thick (hair's contact is millimetres)
MAX_THICKNESS = 1.0
#: a Coulomb friction coefficient at most this (rubber on rubber is about 1-2)
MAX_FRICTION = 100.0


@dataclass
class Collider:
    name: str
    motion: RigidMotion
    thickness: float = 0.0
    friction: float = 0.0
    where: str = ""           # the input it came from (a config key): errors name ``where.thickness`` etc.

    def _key(self, field: str) -> str:
        return f"{self.where}.{field}" if self.where else f"colliders.{self.name}.{field}"

    def __post_init__(self):
        if not isinstance(self.motion, RigidMotion):   # None failed at the first step, in the barrier (a probe)
            raise InputError(f"must be a RigidMotion (the collider's keyframed pose), got {type(self.motion).__name__}",
                             self._key("motion"))
        for key in ("thickness", "friction"):          # "1" or None: a raw TypeError of the comparison below
            real_type(getattr(self, key), self._key(key))
        # at most MAX_THICKNESS m and MAX_FRICTION: 1e300 diverged, "try a smaller solver.dt" (probe of issue 12, round 14)
        if not (0 <= self.thickness <= MAX_THICKNESS):
            raise InputError(f"thickness must be a finite number >= 0 and <= {MAX_THICKNESS:g} (m), got {self.thickness}",
                             self._key("thickness"))
        if not (0 <= self.friction <= MAX_FRICTION):
            raise InputError(f"friction must be a finite number >= 0 and <= {MAX_FRICTION:g}, got {self.friction}",
                             self._key("friction"))

    def _sizes(self, *keys: str) -> None:
        """The lengths ``keys``, each a finite number > 0 (m): the Python classes took a NaN or
        negative radius, and hair passed through a sphere of radius NaN without a contact (an
        outside probe, 2026-12-07; the config's colliders were checked in ``build_collider`` only)."""
        for key in keys:
            v = float(real_type(getattr(self, key), self._key(key)))
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"must be a finite number > 0 (m), got {v}", self._key(key))

    # shape interface (body frame) ------------------------------------------------------
    def sdf_body(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def normal_body(self, X: np.ndarray) -> np.ndarray:
        """Unit outward normal by central differences of the SDF (exact enough for analytic
        shapes; subclasses override with closed forms where they are simple)."""
        h = 1e-7
        g = np.stack([self.sdf_body(X + h * e) - self.sdf_body(X - h * e) for e in np.eye(3)], -1)
        return _unit(g)

    def spin_velocity_body(self, X: np.ndarray) -> np.ndarray:
        return np.zeros_like(X)

    # world queries -----------------------------------------------------------------------
    def to_body(self, x: np.ndarray, t: float) -> np.ndarray:
        return self.motion.to_body(x, t)

    def distance(self, x: np.ndarray, t: float) -> np.ndarray:
        """Signed distance minus thickness: < 0 means too close or inside."""
        return self.sdf_body(self.to_body(x, t)) - self.thickness

    def shell_tolerance(self) -> float:
        """m: a ``distance`` below this is on the shell (``on_shell``)."""
        return 1e-3 * max(self.thickness, 1e-3) + 1e-9

    def on_shell(self, x: np.ndarray, t: float) -> np.ndarray:
        """(n,) bool: points on (or within) the thickness shell, i.e. in contact."""
        return self.distance(x, t) < self.shell_tolerance()

    def normal(self, x: np.ndarray, t: float) -> np.ndarray:
        R, _ = self.motion.pose(t)
        return self.normal_body(self.to_body(x, t)) @ R.T

    def surface_velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        """Velocity of the collider's material at world points x (rigid motion plus spin)."""
        R, T = self.motion.pose(t)
        w, Tdot = self.motion.velocity(t)
        X = self.to_body(x, t)
        return np.cross(w, x - T) + Tdot + self.spin_velocity_body(X) @ R.T

    def bounding_radius(self) -> float:
        raise NotImplementedError


@dataclass
class Sphere(Collider):
    radius: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        self._sizes("radius")

    def sdf_body(self, X):
        return np.linalg.norm(X, axis=-1) - self.radius

    def normal_body(self, X):
        return _unit(X)

    def bounding_radius(self):
        return self.radius


@dataclass
class Capsule(Collider):
    """Segment along the body y axis from -half_length to +half_length, with a radius."""
    radius: float = 0.05
    half_length: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        self._sizes("radius", "half_length")

    def sdf_body(self, X):
        Q = X.copy()
        Q[..., 1] -= np.clip(X[..., 1], -self.half_length, self.half_length)
        return np.linalg.norm(Q, axis=-1) - self.radius

    def normal_body(self, X):
        Q = X.copy()
        Q[..., 1] -= np.clip(X[..., 1], -self.half_length, self.half_length)
        return _unit(Q)

    def bounding_radius(self):
        return self.radius + self.half_length


@dataclass
class Box(Collider):
    half_extents: tuple = (0.1, 0.1, 0.1)

    def __post_init__(self):
        super().__post_init__()
        try:
            he = np.asarray(self.half_extents, dtype=np.float64)
        except (TypeError, ValueError):
            he = np.zeros(0)
        if he.shape != (3,) or not (np.isfinite(he).all() and (he > 0).all()):
            raise InputError(f"must be 3 finite numbers > 0 (m), got {self.half_extents!r:.60}", self._key("half_extents"))

    def sdf_body(self, X):
        q = np.abs(X) - np.asarray(self.half_extents)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)

    def bounding_radius(self):
        return float(np.linalg.norm(self.half_extents))


@dataclass
class Cylinder(Collider):
    """Axis along the body y axis, |y| <= half_height; ``spin`` (rad/s) turns the surface about
    the axis (a wheel: surface velocity spin * (y_axis x r))."""
    radius: float = 0.1
    half_height: float = 0.05
    spin: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        self._sizes("radius", "half_height")
        if not np.isfinite(real_type(self.spin, self._key("spin"))):
            raise InputError(f"spin must be a finite number (rad/s), got {self.spin}", self._key("spin"))

    def sdf_body(self, X):
        r = np.linalg.norm(X[..., [0, 2]], axis=-1)
        d = np.stack([r - self.radius, np.abs(X[..., 1]) - self.half_height], -1)
        return np.minimum(np.maximum(d[..., 0], d[..., 1]), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)

    def spin_velocity_body(self, X):
        return self.spin * np.cross(np.array([0.0, 1.0, 0.0]), X * np.array([1.0, 0.0, 1.0]))

    def bounding_radius(self):
        return float(np.hypot(self.radius, self.half_height))


@dataclass
class Plane(Collider):
    """The half space below the body-frame plane y = 0 (normal +y)."""

    def sdf_body(self, X):
        return X[..., 1]

    def normal_body(self, X):
        n = np.zeros_like(X)
        n[..., 1] = 1.0
        return n

    def bounding_radius(self):
        return np.inf


SHAPES = {"sphere": Sphere, "capsule": Capsule, "box": Box, "cylinder": Cylinder, "plane": Plane}
