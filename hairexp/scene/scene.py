"""Scene (static: never changes during a run) and State (changes every step)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hairexp.scene.rigid import RigidMotion
from hairexp.scene.strands import Strands


@dataclass
class Material:
    linear_density: float        # kg/m
    stretch_stiffness: float     # EA, N
    bending_stiffness: float     # EI, N m^2
    edge_damping: float = 0.0    # N s
    air_drag: float = 0.0        # 1/s


@dataclass
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

    def initial_positions(self) -> np.ndarray:
        """(V, 3) world positions at t = 0 the run starts from and the tracking registers on."""
        return self.strands.rest if self.initial is None else self.initial

    def free_weight_norm(self) -> float:
        """|m g| of the free vertices (their stacked weights): the scale of every control-effort
        measure (constraint, attraction or implied skinning forces over weight); 1 without gravity."""
        free = ~self.strands.kinematic
        return float(np.linalg.norm(self.strands.masses[free, None] * self.gravity[None])) or 1.0

    def root_positions(self, t: float) -> np.ndarray:
        """(V, 3) with the kinematic rows set to the root positions at time t (others: rest)."""
        x = self.strands.rest.copy()
        k = self.strands.kinematic
        x[k] = self.motion.transform(self.root_body[k], t)
        return x

    def root_velocities(self, t: float) -> np.ndarray:
        v = np.zeros_like(self.strands.rest)
        k = self.strands.kinematic
        v[k] = self.motion.point_velocity(self.root_body[k], t)
        return v


@dataclass
class State:
    time: float
    x: np.ndarray   # (V, 3) positions, m
    v: np.ndarray   # (V, 3) velocities, m/s
    duals: dict = field(default_factory=dict)  # solver iterates carried to the next step (tensions, ...)

    def copy(self) -> "State":
        return State(self.time, self.x.copy(), self.v.copy(), {k: v.copy() for k, v in self.duals.items()})
