"""A dynamic rigid block carrying the hair roots, resting on a rail that ends (paper 4,
"Stylization", Fig. 7: "a wisp of hair is attached to a rigid block resting on a rail"; the
tracked hair "pulls itself off the rail by building up the necessary momentum").

The block only translates (its rotation stays the initial one of ``scene.motion``).  Forces:

* gravity on the block and on the root vertices it carries (the first two vertices of every
  strand are kinematic and ride on the block; their mass is added to the block's);
* the rail: a unilateral support of the block's reference point (the body origin, i.e. the pose
  translation) at world height ``rail_height`` while its x <= ``rail_end``, with Coulomb friction
  ``rail_friction`` in the rail's plane (x and z).  The block can lift off; past the rail's end
  (or once below the rail) nothing holds it.  Contact is an inelastic impulse: a block landing on
  the rail stops its downward motion there;
* the force the hair exerts on the block through its roots.

Coupling (staggered, momentum-consistent).  Each step the block moves first, with the hair's
force of the *previous* step, and its end-of-step pose prescribes the hair roots; the hair is then
solved (Newton or SQP) with the roots on the block.  The force the hair exerts on the block over
that step is the sum, over the root vertices, of the internal forces (stretch, bending, edge
damping) at the end-of-step state:  F_hair_on_block = -sum_{i root} dE_int/dx_i(x_{n+1}).  The
internal energies are translation invariant, so this is exactly minus the internal force on the
free hair, which implicit Euler balances as

    (P_hair(n+1) - P_hair(n)) / dt = M_hair g + F_drag + F_tracking - F_hair_on_block

(at convergence).  With no tracking forces this is the "momentum change minus gravity and drag"
of the free hair; with tracking, the constraint forces A^T lambda (the tracker's control, paper
3.4) stay on the hair and do not push the block directly: the block feels the hair only through
its roots.  Block and hair exchange equal and opposite impulses, one step apart, so the total
momentum of block + hair changes by gravity, rail (and drag, collision, tracking) impulses plus
the telescoping lag term dt (F_0 - F_N) (the first and the last hair force), which does not grow
with the number of steps (``tests/test_dynamic_body.py``).

Stability.  The lag makes the scheme partitioned-explicit: when the hair is stiffly attached
(its stretch springs, which carry the whole strand axially within one step), a perturbation of
the coupling force is multiplied by about m_hair / (m_block + m_roots) per step (the "added mass"
ratio of partitioned fluid-structure coupling).  So the block must be heavier than the free hair
it carries; ``build_dynamic_body`` refuses a lighter one.  Measured on the stylization wisp in free
fall (tests/test_dynamic_body.py): with its 50 g block (23 x the hair) a disturbance of one hair
weight shrinks about 25x per step; at 1.6 x it shrinks by 0.4-0.63 per step; at 0.9 x it grows.

The block's state (position, velocity, hair force, last rail force) lives in ``State.body``
(hairexp/physics/state.py; slices ``POSITION``, ``VELOCITY``, ``HAIR_FORCE``, ``RAIL_FORCE``), never
in this object, which is frozen scene data: a step that fails and is retried as substeps starts
again from the same State.  The poses of the step being solved are a ``BodyWindow``
(``DynamicBody.window``, built from the State at every attempt and passed explicitly to whatever
needs the pose): ``pose``, ``velocity``, ``transform``, ``point_velocity`` and ``to_body`` work like
``RigidMotion``'s for times within that step (linear in time between the step's start and end
poses).  As a motion, the ``DynamicBody`` itself answers for t = 0 only (its initial pose, the
window [0, 0]); asked for another time it raises.  ``reference`` is the block held at its initial
pose: the frame guides are authored in (hairexp/guides/animation.py), whose world positions are
then carried by the live block.
"""

from __future__ import annotations


import numpy as np
from scipy.spatial.transform import Rotation

from hairexp.errors import InputError, finite_number
from hairexp.model.rigid import RigidMotion

#: Layout of ``State.body`` (one float64 vector).
POSITION, VELOCITY, HAIR_FORCE, RAIL_FORCE = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
STATE_SIZE = 12
#: The rail supports the block while it is no more than this (m) below the rail height.
CONTACT_TOLERANCE = 1e-9


class DynamicBody:
    """The block: static parameters, the step being solved (window), and the update rule."""

    interpolation = "linear"   # between the start and end poses of a step

    def __init__(self, rotation: np.ndarray, position: np.ndarray, velocity: np.ndarray, mass: float,
                 carried_mass: float, gravity: np.ndarray, rail_height: float, rail_end: float, friction: float):
        self.R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        self.p0 = np.asarray(position, dtype=np.float64).reshape(3)
        self.u0 = np.asarray(velocity, dtype=np.float64).reshape(3)
        self.mass = float(mass)                    # the block, kg
        self.carried_mass = float(carried_mass)    # the root vertices it carries, kg
        self.total_mass = self.mass + self.carried_mass
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.rail_height, self.rail_end, self.friction = float(rail_height), float(rail_end), float(friction)
        rv = Rotation.from_matrix(self.R).as_rotvec()
        self.reference = RigidMotion(np.zeros(1), self.p0[None], rv[None])   # the block held at its initial pose
        self.times = np.zeros(1)          # like a RigidMotion with one key: its initial pose
        self.translations = self.p0[None].copy()
        self.rotvecs = rv[None]
        b = self.initial(np.zeros(3))
        self._start = self.at(0.0, b)   # the motion interface at t = 0 (see the module doc)

    # -- state ---------------------------------------------------------------------------
    def initial(self, hair_force: np.ndarray) -> np.ndarray:
        b = np.zeros(STATE_SIZE)
        b[POSITION], b[VELOCITY], b[HAIR_FORCE] = self.p0, self.u0, hair_force
        return b

    def supported(self, p: np.ndarray) -> bool:
        """Whether the rail is under the block at position p (it is over the rail, not below it)."""
        return bool(p[0] <= self.rail_end and p[1] >= self.rail_height - CONTACT_TOLERANCE)

    def advance(self, b: np.ndarray, dt: float, theta: float = 1.0) -> np.ndarray:
        """The block at the end of a step of dt from ``b``, under gravity, the hair force
        ``b[HAIR_FORCE]`` of the previous step and the rail's impulse (unilateral, inelastic,
        Coulomb friction in the rail plane).  The new hair force is left to the caller
        (``with_hair_force``), once the hair is solved.

        Position update p + dt (theta u_new + (1 - theta) u): ``theta`` = 1 is symplectic Euler,
        p + dt u + dt^2 a, the displacement implicit Euler gives the hair under the same constant
        acceleration; theta = 1/2 is p + dt u + dt^2 a / 2, exact for a constant acceleration as the
        second-order schemes (trbdf2's stages) are.  The block must move as the hair's scheme would
        move it: with symplectic Euler under trbdf2 hair the roots fell twice as far as the hair in
        the first stage of a free fall, and a spurious hair force of 3 % of the hair's weight pulled
        the block for good (tests/test_dynamic_body.py).  Steps that touch the rail use theta = 1
        (the block lands exactly on it)."""
        p, u, fh = b[POSITION], b[VELOCITY], b[HAIR_FORCE]
        M = self.total_mass
        u_new = u + dt * (self.gravity + fh / M)
        rail = np.zeros(3)
        if self.supported(p) and p[1] + dt * u_new[1] < self.rail_height:
            theta = 1.0
            uy = (self.rail_height - p[1]) / dt            # land exactly on the rail (or stay on it)
            Jn = M * (uy - u_new[1])                        # >= 0: the rail only pushes
            ut = u_new[[0, 2]]
            st = float(np.linalg.norm(ut))
            Jmax = self.friction * Jn
            if M * st <= Jmax:                              # sticks
                Jt = -M * ut
            else:                                           # slides: kinetic friction against the motion
                Jt = -Jmax * ut / st
            u_new = np.array([u_new[0] + Jt[0] / M, uy, u_new[2] + Jt[1] / M])
            rail = np.array([Jt[0], Jn, Jt[1]]) / dt
        out = b.copy()
        out[VELOCITY] = u_new
        out[POSITION] = p + dt * (theta * u_new + (1.0 - theta) * u)
        out[RAIL_FORCE] = rail
        return out

    @staticmethod
    def with_hair_force(b: np.ndarray, force: np.ndarray) -> np.ndarray:
        out = b.copy()
        out[HAIR_FORCE] = force
        return out

    # -- the step being solved --------------------------------------------------------------
    def window(self, t0: float, b0: np.ndarray, t1: float, b1: np.ndarray) -> "BodyWindow":
        """The block's poses over the step from t0 (state b0) to t1 (state b1)."""
        return BodyWindow(self.R, t0, b0, t1, b1)

    def at(self, t: float, b: np.ndarray) -> "BodyWindow":
        """The block at the single time t of state b (the window [t, t])."""
        return BodyWindow(self.R, t, b, t, b)

    # as a motion: the initial pose only (t = 0)
    def pose(self, t: float):
        return self._start.pose(t)

    def velocity(self, t: float):
        return self._start.velocity(t)

    def transform(self, X_body: np.ndarray, t: float) -> np.ndarray:
        return self._start.transform(X_body, t)

    def point_velocity(self, X_body: np.ndarray, t: float) -> np.ndarray:
        return self._start.point_velocity(X_body, t)

    def to_body(self, x_world: np.ndarray, t: float) -> np.ndarray:
        return self._start.to_body(x_world, t)


class BodyWindow:
    """The block's poses within one step [t0, t1], linear in time between its start and end
    positions (the rotation is the block's fixed one).  Immutable; one per attempt."""

    interpolation = "linear"

    def __init__(self, R: np.ndarray, t0: float, b0: np.ndarray, t1: float, b1: np.ndarray):
        self.R = R
        self._w = (float(t0), np.array(b0[POSITION]), float(t1), np.array(b1[POSITION]), np.array(b1[VELOCITY]))

    def _fraction(self, t: float) -> float:
        t0, _, t1, _, _ = self._w
        tol = 1e-9 * max(1.0, abs(t1))
        if not (t0 - tol <= t <= t1 + tol):
            raise RuntimeError(f"the dynamic body's pose is known within the step being solved "
                               f"[{t0:.9g}, {t1:.9g}] s only, asked for t={t:.9g} s")
        return 0.0 if t1 == t0 else min(max((t - t0) / (t1 - t0), 0.0), 1.0)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        a = self._fraction(float(t))
        _, p0, _, p1, _ = self._w
        return self.R.copy(), (1.0 - a) * p0 + a * p1

    def velocity(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Angular velocity (always 0) and the block's velocity over the step (its end velocity:
        symplectic Euler moves it by dt u_{n+1})."""
        self._fraction(float(t))
        return np.zeros(3), self._w[4].copy()

    def transform(self, X_body: np.ndarray, t: float) -> np.ndarray:
        R, T = self.pose(t)
        return X_body @ R.T + T

    def point_velocity(self, X_body: np.ndarray, t: float) -> np.ndarray:
        _, Tdot = self.velocity(t)
        return np.broadcast_to(Tdot, np.shape(X_body)).copy()

    def to_body(self, x_world: np.ndarray, t: float) -> np.ndarray:
        R, T = self.pose(t)
        return (x_world - T) @ R


def authoring_motion(motion):
    """The motion guides are authored against: a dynamic body's initial pose held still (its
    ``reference``), a keyframed motion itself."""
    return getattr(motion, "reference", motion)


def build_dynamic_body(body_cfg, motion: RigidMotion, strands, gravity: np.ndarray) -> DynamicBody:
    """The block of ``scene.body`` (validated), starting at the pose of ``scene.motion`` at t=0."""
    mass = finite_number(body_cfg.mass, "scene.body.mass")
    if not mass > 0:
        raise InputError(f"must be > 0 (kg), got {mass}", "scene.body.mass")
    rail_height = finite_number(body_cfg.rail_height, "scene.body.rail_height")
    rail_end = finite_number(body_cfg.rail_end, "scene.body.rail_end")
    mu = finite_number(body_cfg.rail_friction, "scene.body.rail_friction")
    if not mu >= 0:
        raise InputError(f"must be >= 0, got {mu}", "scene.body.rail_friction")
    vel = np.asarray(list(body_cfg.velocity), dtype=np.float64)
    if vel.shape != (3,) or not np.isfinite(vel).all():
        raise InputError(f"expected 3 finite numbers (m/s), got {list(body_cfg.velocity)}", "scene.body.velocity")
    if len(motion.times) > 1:
        if motion.where.startswith("scene.motion"):
            raise InputError("a dynamic body takes only its initial pose from scene.motion: give one keyframe "
                             f"(got {len(motion.times)})", f"{motion.where}.times")
        # a USD stage's body prim (it named scene.motion.times, a key the user never set; probe of issue 12)
        raise InputError(f"is animated ({len(motion.times)} time samples), but scene.body.dynamic=true moves the "
                         "body by the hair's forces from its initial pose: remove the body's time samples, or "
                         "leave scene.body.dynamic=false", motion.where)
    m = strands.masses
    carried = float(m[strands.kinematic].sum())
    hair = float(m[~strands.kinematic].sum())
    if not mass + carried > hair:
        raise InputError(f"the block ({mass:.4g} kg, plus {carried:.4g} kg of roots) must be heavier than the free "
                         f"hair it carries ({hair:.4g} kg): the staggered hair-block coupling amplifies a disturbance "
                         "by about m_hair / m_block per step", "scene.body.mass")
    R, T = motion.pose(0.0)
    if T[0] <= rail_end and T[1] < rail_height - 1e-6:
        # under its own rail, the block fell from the first step without a word (probe of issue 12)
        raise InputError(f"is {rail_height:g} m, but the block starts at y = {T[1]:g} m (its initial pose), "
                         f"{rail_height - T[1]:g} m below its rail: set scene.body.rail_height to the block's start "
                         "height (or lift the block)", "scene.body.rail_height")
    return DynamicBody(R, T, vel, mass, carried, gravity, rail_height, rail_end, mu)
