"""Scene: everything about a run that never changes during it (the per-step state is
``hairexp.physics.state.State``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hairexp.errors import InputError
from hairexp.model.dynamic_body import DynamicBody
from hairexp.model.rigid import RigidMotion
from hairexp.model.strands import Strands


@dataclass(frozen=True)
class Material:
    linear_density: float        # kg/m
    stretch_stiffness: float     # EA, N
    bending_stiffness: float     # EI, N m^2
    edge_damping: float = 0.0    # N s
    air_drag: float = 0.0        # 1/s


@dataclass(frozen=True)
class Scene:
    """Everything about a run that does not change from step to step.

    ``root_body``: (V, 3) initial positions in the body frame of ``motion``: the kinematic root
    vertices, which the body carries rigidly, and the state the run starts from
    (``Simulator.initial_state``).
    ``initial``: (V, 3) world positions at t = 0 the run starts from and the tracking is registered
    on (correspondence, constraint offsets, variance rest values, skinning offsets), when they
    differ from the elastic rest shape ``strands.rest`` (``scene.settle`` > 0: the hair settled
    under gravity, hairexp/physics/settle.py); None: ``strands.rest``.  The elastic rest shape
    (rest lengths, rest bending angles) is always ``strands.rest``."""

    name: str
    strands: Strands
    material: Material
    motion: RigidMotion
    gravity: np.ndarray
    root_body: np.ndarray
    colliders: list = field(default_factory=list)
    initial: np.ndarray | None = None

    def __post_init__(self):
        names = [getattr(c, "name", None) for c in self.colliders]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:   # metrics columns, the recording, the USD prims and measure.collider are by name
            raise InputError(f"collider names must be unique; {', '.join(map(repr, twice))} is used more than once "
                             f"(colliders: {names})", "scene.colliders")

    def initial_positions(self) -> np.ndarray:
        """(V, 3) world positions at t = 0 the run starts from and the tracking registers on."""
        return self.strands.rest if self.initial is None else self.initial

    def free_weight_norm(self) -> float:
        """|m g| of the free vertices (their stacked weights): the scale of every control-effort
        measure (constraint, attraction or implied skinning forces over weight); 1 without gravity."""
        free = ~self.strands.kinematic
        return float(np.linalg.norm(self.strands.masses[free, None] * self.gravity[None])) or 1.0

    @property
    def body(self) -> DynamicBody | None:
        """The dynamic block (``scene.body.dynamic``), or None for a keyframed body."""
        return self.motion if isinstance(self.motion, DynamicBody) else None

    def root_positions(self, t: float, motion=None) -> np.ndarray:
        """(V, 3) with the kinematic rows set to the root positions at time t (others: rest);
        ``motion``: the body's poses at t when they are not ``self.motion``'s (a dynamic body's
        step window, ``DynamicBody.window``)."""
        x = self.strands.rest.copy()
        k = self.strands.kinematic
        x[k] = (motion or self.motion).transform(self.root_body[k], t)
        return x

    def root_velocities(self, t: float, motion=None) -> np.ndarray:
        v = np.zeros_like(self.strands.rest)
        k = self.strands.kinematic
        v[k] = (motion or self.motion).point_velocity(self.root_body[k], t)
        return v
