"""Scene: everything about a run that never changes during it (the per-step state is
``hairexp.physics.state.State``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hairexp.errors import InputError, real
from hairexp.model.dynamic_body import DynamicBody
from hairexp.model.rigid import RigidMotion
from hairexp.model.strands import Strands


#: the largest material constant accepted (SI units): beyond, the step's Newton system (stiffness
#: against mass / dt^2) is beyond double precision
MATERIAL_MAX = 1e9
#: kg/m, the lightest hair accepted: 1e-300 (massless) "converged" in 0 iterations (probe of issue 12, round 14)
MIN_LINEAR_DENSITY = 1e-9
#: m/s^2, the largest gravity (about 100 g): -1e300 overflowed the first step into a numpy warning
#: and "try solver.on_failure=substep" (probe of issue 12)
MAX_GRAVITY = 1e3


@dataclass(frozen=True)
class Material:
    linear_density: float        # kg/m
    stretch_stiffness: float     # EA, N
    bending_stiffness: float     # EI, N m^2
    edge_damping: float = 0.0    # N s
    air_drag: float = 0.0        # 1/s

    def __post_init__(self):
        """Finite values in range, named (the Python API took NaN or negative values that the
        command line refuses and failed later as a diverged step; probe of issue 12, round 10)."""
        for key, lo, strict in (("linear_density", 0.0, True), ("stretch_stiffness", 0.0, True),
                                ("bending_stiffness", 0.0, False), ("edge_damping", 0.0, False),
                                ("air_drag", 0.0, False)):
            # at most MATERIAL_MAX, as for scene.hair.*: 1e300 diverged at the first step (probe of issue 12, round 14)
            real(getattr(self, key), f"Material.{key}", lo=MIN_LINEAR_DENSITY if key == "linear_density" else lo,
                 hi=MATERIAL_MAX, lo_open=strict and key != "linear_density")


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
    #: (V,) m, the hair's widths per vertex as a USD stage authored them (its curves' ``widths``),
    #: written back to the result's curves; display only (contact thickness is the config's
    #: collision.hair_thickness and the colliders' thickness); None: the default display width
    widths: np.ndarray | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"must be a non-empty string, got {self.name!r}", "Scene.name")
        if not isinstance(self.motion, (RigidMotion, DynamicBody)):
            raise InputError(f"must be a RigidMotion (hairexp.model.rigid; RigidMotion.static() for a body at rest) "
                             f"or a DynamicBody, got {type(self.motion).__name__}", "Scene.motion")
        if not isinstance(self.colliders, (list, tuple)):
            raise InputError(f"must be a list of collider objects (hairexp.model.colliders), got "
                             f"{type(self.colliders).__name__}", "Scene.colliders")
        if not isinstance(self.strands, Strands):
            raise InputError(f"must be a Strands (hairexp.model.strands), got {type(self.strands).__name__}",
                             "Scene.strands")
        if not isinstance(self.material, Material):
            raise InputError(f"must be a Material, got {type(self.material).__name__}", "Scene.material")
        V = self.strands.n_vertices
        for key, shape in (("gravity", (3,)), ("root_body", (V, 3)), ("initial", (V, 3))):
            a = getattr(self, key)
            if a is None and key == "initial":
                continue
            try:
                arr = np.asarray(a, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise InputError(f"must be real numbers of shape {shape}: {exc}", f"Scene.{key}") from exc
            if arr.shape != shape:
                raise InputError(f"must have shape {shape} (the strands have {V} vertices), got {arr.shape}",
                                 f"Scene.{key}")
            if not np.isfinite(arr).all():
                bad = np.argwhere(~np.isfinite(arr))[0].tolist()
                raise InputError(f"must be finite, got {arr[tuple(bad)]} at index {bad}", f"Scene.{key}")
            if key == "gravity" and float(np.linalg.norm(arr)) > MAX_GRAVITY:   # as scene.gravity (round 14)
                raise InputError(f"is {arr.tolist()}, larger than {MAX_GRAVITY:g} m/s^2 (about 100 g)", "Scene.gravity")
            # a read-only float64 copy: the Simulator built its gravity and root terms from these, and a
            # caller's later edit (scene.gravity[1] = -20) changed the scene under them without a word
            # (probe of issue 16; ``dataclasses.replace`` makes a scene with other values)
            arr = np.array(arr, dtype=np.float64)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        if self.widths is not None:
            w = np.array(self.widths, dtype=np.float64) if not isinstance(self.widths, (str, bytes)) else None
            if w is None or w.shape != (V,):
                raise InputError(f"must be None or an array of {V} widths (m, one per vertex), got "
                                 f"{np.shape(self.widths) if w is not None else repr(self.widths)}", "Scene.widths")
            bad = np.flatnonzero(~(np.isfinite(w) & (w >= 0)))
            if len(bad):
                raise InputError(f"must be finite and >= 0 (m), got {w[bad[0]]} at vertex {int(bad[0])}", "Scene.widths")
            w.setflags(write=False)
            object.__setattr__(self, "widths", w)   # frozen: the checked float64 copy, read-only
        for c in self.colliders:
            if not hasattr(c, "name") or isinstance(c, str):
                raise InputError(f"must be collider objects (hairexp.model.colliders), got {c!r}", "Scene.colliders")
        names = [getattr(c, "name", None) for c in self.colliders]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:   # metrics columns, the recording, the USD prims and measure.collider are by name
            where = [f"{getattr(c, 'name', None)!r} from {getattr(c, 'where', '') or 'scene.colliders'}"
                     for c in self.colliders if getattr(c, "name", None) in twice]
            raise InputError(f"collider names must be unique; {', '.join(map(repr, twice))} is used more than once "
                             f"({'; '.join(where)})", "scene.colliders")

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
