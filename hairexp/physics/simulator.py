"""The time step, phase by phase (``Simulator._stage``, top to bottom; a multi-stage integrator,
the default TR-BDF2, runs phases 1-4 once per stage, ``Simulator._attempt``):

1. kinematics: the body's poses over the step (``motion_of``): a keyframed body's motion, or a
   dynamic body (``scene.body``) that first moves under gravity, its rail and the hair's force of
   the previous step (hairexp/model/dynamic_body.py; its state travels in ``State.body``, its
   poses in an explicit ``BodyWindow``); the root positions at t + dt; the controller's
   ``begin`` (targets, anchors at t + dt);
2. solve: minimise the time-step objective of ``solver.integrator`` (TR-BDF2's stage, implicit
   Euler, eq. 5, BDF2 or generalized-alpha: hairexp/physics/integrators.py, the ``StepPlan``) plus the
   controller's terms, under its constraints: the controller's ``solve`` (Newton for the free
   controller, SQP for tracking, hairexp/physics/controller.py);
3. velocities: the integrator's, v_{n+1} = (x_{n+1} - x_n) / dt for implicit Euler, and its
   history (``State.history``); a dynamic body takes the force the hair exerts on its roots at
   x_{n+1} (for the next step);
4. collision stage: hair against the colliders and itself, after the solve (paper 3.4;
   hairexp/physics/collisions.py), only when the scene has something to collide; the vertices
   it moved or whose velocity it changed take its positions and velocities, and the
   integrator adjusts its history to them (``after_collision``).  The hair volume
   (``collision.hair_hair_model=volume``) is a velocity filter before the object contacts, after
   a step's last stage: it changes the end velocities only (``after_velocity_filter``).
   With ``collision.resolve`` (the default) the solve of 2. already carries planes for the hair
   resting on a collider (``_resting_planes``), and at the step's last stage the stage's contacts
   that those did not hold are solved again as planes (``_resolve_contacts``,
   hairexp/physics/contact_planes.py), the stage then run on the end points only;
5. recovery (``_advance``): a step that diverged or did not converge is retried as two half
   steps from the same State (``solver.on_failure=substep``, recursively), kept and flagged
   (``warn``), or stops the run (``fail``).  A non-finite state is never returned.

A step in which a collider sweeps over the hair it can reach by more than ``collision.max_travel``
of its thinnest half size is first split into equal substeps (``sweep_substeps`` in
hairexp/physics/barrier.py, at most ``collision.max_travel_substeps``), each run through 1-5.

The Simulator never names a controller: it is given one (``Controller``; None: the free step).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np
import torch

from hairexp import tune_runtime
from hairexp.errors import (MIN_STEP_DT, InputError, SimulationError, check_switches, choice_name, enum_value,
                            finite_number, flag, integer, number)
from hairexp.model.scene import Scene
from hairexp.model.strands import curve_vertex, first_short_edge
from hairexp.physics.barrier import begin_contact_step, contact_collision_info, make_object_contact, sweep_substeps
from hairexp.physics.collisions import (CollisionInfo, HairHair, StrainLimit, collision_stage, contact_velocities,
                                        edge_response, limit_strain, object_positions, path_test)
from hairexp.physics.contact_planes import NEAR, stage_planes
from hairexp.physics.controller import Controller
from hairexp.physics.hair_volume import HairVolume
from hairexp.physics.energies import AirDrag, Bending, EdgeDamping, Gravity, Stretch
from hairexp.physics.info import CONVERGED, DIVERGED, MAX_ITERATIONS, SolveInfo, StepInfo
from hairexp.physics.integrators import DEFAULT_INTEGRATOR, History, ImplicitEuler, Restart, make_integrator
from hairexp.physics.newton import NewtonOptions
from hairexp.physics.objective import ImplicitEulerObjective
from hairexp.physics.state import State
from hairexp.physics.strand_kernels import check_options

TIME_KEYS = ("derivatives", "assembly", "solve", "collision", "other")
#: ``solver.compile=auto`` compiles the derivative kernels from this many vertices on.
COMPILE_MIN_VERTICES = 4000
#: A vertex the collision stage moved by more than this (m) or whose velocity it changed by more
#: than this (m/s) is "touched" (round-off of the stage's x0 + dt v is far below both).
TOUCH_TOL_X, TOUCH_TOL_V = 1e-12, 1e-9
#: collision.resolve: solves of a stage with contact planes at most (the first, then one for each
#: growth of the active set; ``Simulator._resolve_contacts``)
RESOLVE_ROUNDS = 4
#: collision.resolve: a first solve with the resting hair's planes stands when the stage after it moved
#: no vertex by more than this fraction of the thinnest collider's thickness (``Simulator._stage_kept``)
KEPT_MOVE = 0.01
#: most rounds of the controller's constraints restored after the collision stage, each followed by
#: the colliders' response to the move (``Simulator._restore``)
RESTORE_ROUNDS = 8

log = logging.getLogger(__name__)


def _merge_stages(infos: list[SolveInfo]) -> SolveInfo:
    """The stages of one multi-stage step as one SolveInfo: counts and seconds summed, the
    status of the first failed stage (else converged), the last stage's residuals and warm
    start, the collision stages' contacts summed."""
    last = infos[-1]
    out = SolveInfo(status=next((i.status for i in infos if not i.converged), CONVERGED),
                    iterations=sum(i.iterations for i in infos), backtracks=sum(i.backtracks for i in infos),
                    grad_norm=last.grad_norm, force_scale=last.force_scale,
                    constraint_norm=max(i.constraint_norm for i in infos), tensions=last.tensions)
    out.seconds = {k: sum(i.seconds.get(k, 0.0) for i in infos) for k in set().union(*(i.seconds for i in infos))}
    out.collision = _sum_collisions([i.collision for i in infos if i.collision is not None])
    return out


def _distances(col, x: np.ndarray, idx: np.ndarray, t: float) -> np.ndarray:
    """``col.distance`` of the points x[idx] at time t, by the collision stage's compiled pass
    (``collisions.path_test``: Celia's 7,826 vertices 1.7 -> 0.2 ms a collider)."""
    return path_test(col, x, x, idx, t, t)[3]


def _after(earlier: SolveInfo, later: SolveInfo) -> SolveInfo:
    """Two solves of one stage, one after the other (the contact planes' second solve,
    ``Simulator._resolve_contacts``), as one: ``later`` with ``earlier``'s iterations, backtracks
    and seconds added, its residuals and warm start, and ``earlier``'s status where that did not
    converge (recovery then retries the step, as for one solve that failed)."""
    if not earlier.converged:
        later.status = earlier.status
    later.iterations += earlier.iterations
    later.backtracks += earlier.backtracks
    for k, v in earlier.seconds.items():
        later.seconds[k] = later.seconds.get(k, 0.0) + v
    return later


def _sum_collisions(cis: list):
    """Several collision stages' ``CollisionInfo`` as one (counts and seconds summed, the deepest
    penetration, contacts per collider summed), or None for none."""
    if not cis:
        return None
    c = replace(cis[-1], per_collider={}, broad_phases={})
    c.object_contacts = sum(ci.object_contacts for ci in cis)
    c.hair_contacts = sum(ci.hair_contacts for ci in cis)
    c.penetration_max = max(ci.penetration_max for ci in cis)
    c.strain_limited = sum(ci.strain_limited for ci in cis)
    c.limit_rounds = sum(ci.limit_rounds for ci in cis)
    c.restored = sum(ci.restored for ci in cis)
    c.resolved = sum(ci.resolved for ci in cis)
    c.resolve_failed = sum(ci.resolve_failed for ci in cis)
    c.passes = sum(ci.passes for ci in cis)
    c.seconds = sum(ci.seconds for ci in cis)
    for ci in cis:
        for k, n in ci.per_collider.items():
            c.per_collider[k] = c.per_collider.get(k, 0) + n
        for k, n in ci.broad_phases.items():
            c.broad_phases[k] = c.broad_phases.get(k, 0) + n
    return c


class _NoColliders:
    """The scene seen by the collision stage when object collisions are switched off."""

    def __init__(self, scene):
        self.strands, self.colliders, self.motion = scene.strands, [], scene.motion


#: the longest step ``Simulator.step`` takes (s): the command line's steps are at most a frame (fps >= 0.1)
MAX_STEP_DT = 10.0
#: solver.last_attempt_iterations at most (a step's last attempt with this many times the iterations)
MAX_LAST_ATTEMPT = 64
#: solver.max_substep_levels at most: 2^10 substeps of a failing step (beyond, a run whose steps
#: all fail retries each of them for hours before it reports)
MAX_SUBSTEP_LEVELS = 10
#: solver.max_iterations and tracking.max_iterations at most this (not MAX_ITERATIONS: that is a status): a solve that has not converged in
#: it will not (a step takes 2-25 here); 1e8 with an unreachable tolerance ran for hours without
#: a step (probe of issue 12, round 12)
MAX_ITERATION_BUDGET = 10_000


#: ``solver.atol`` / ``tracking.atol`` at most this (N): an absolute tolerance on the gradient that
#: hair's forces (mN) always meet accepts the first iterate of every step
MAX_ATOL = 1e-3
#: ``solver.max_backtracks`` at most this
MAX_BACKTRACKS = 100


def check_solver_config(s) -> None:
    """The solver settings (``solver.*``: hairexp/app/config.py SolverConfig, or any object with
    its attributes) a step can run with, or an InputError naming the key: checked by the config's
    validation and by ``Simulator`` itself, so that the Python API refuses what the command line
    does (``SolverConfig(rtol=nan)`` and ``max_iterations=0`` ran and failed later; probe of
    issue 12, round 10).  Attributes the object lacks are left out (their defaults apply)."""
    if isinstance(s, dict) or not hasattr(s, "rtol"):
        raise InputError(f"must be a solver config (hairexp.app.config.SolverConfig, or an object with its attributes: "
                         f"dt, rtol, atol, max_iterations, ...), got {type(s).__name__}", "solver")
    make_integrator(getattr(s, "integrator", DEFAULT_INTEGRATOR))   # InputError naming solver.integrator
    check_options(getattr(s, "kernels", "numba"), getattr(s, "threads", "auto"))   # solver.kernels, solver.threads
    if hasattr(s, "restart_at_jumps"):
        flag(enum_value(s.restart_at_jumps), "solver.restart_at_jumps")
    check_switches(s, "solver", SOLVER_CHOICES)   # the config's Enums; any value in a dataclass of the API
    # >= 1, or an absolute tolerance above hair's forces (mN), accepts the first iterate (probe of issue 12, round 14)
    rtol = number(s.rtol, "solver.rtol", lo=0, hi=1, hi_open=True)
    if hasattr(s, "stage_rtol_factor"):
        number(s.stage_rtol_factor, "solver.stage_rtol_factor", lo=1, hi=MAX_STAGE_RTOL_FACTOR)
    atol = number(getattr(s, "atol", 0.0), "solver.atol", lo=0, hi=MAX_ATOL)
    if rtol == 0 and atol == 0:
        raise InputError("solver.rtol and solver.atol are both 0: no step can converge; give one > 0", "solver.rtol")
    if hasattr(s, "dt"):   # worded as the step schedule words it (hairexp/physics/schedule.py)
        dt = finite_number(s.dt, "solver.dt", "> 0")
        if dt <= 0:
            raise InputError(f"must be a finite number > 0, got {dt:g}", "solver.dt")
        if dt < MIN_STEP_DT:
            raise InputError(f"must be at least {MIN_STEP_DT:g} s (the inertia M/dt^2 overflows below it), got {dt:g}",
                             "solver.dt")
    for key, lo in (("max_iterations", 1), ("max_backtracks", 0)):
        if hasattr(s, key):
            integer(getattr(s, key), f"solver.{key}", lo)
    if getattr(s, "max_backtracks", 0) > MAX_BACKTRACKS:   # 1e6 was taken (probe of issue 12, round 16)
        raise InputError(f"must be at most {MAX_BACKTRACKS} (each halves the step: 2^-{MAX_BACKTRACKS} is below double "
                         f"precision), got {s.max_backtracks}", "solver.max_backtracks")
    if getattr(s, "max_iterations", 1) > MAX_ITERATION_BUDGET:
        raise InputError(f"must be at most {MAX_ITERATION_BUDGET} (a Newton solve takes 2-25 iterations; one that has "
                         f"not converged in {MAX_ITERATION_BUDGET} will not), got {s.max_iterations}",
                         "solver.max_iterations")
    if integer(getattr(s, "last_attempt_iterations", 1), "solver.last_attempt_iterations", 1) > MAX_LAST_ATTEMPT:
        raise InputError(f"must be at most {MAX_LAST_ATTEMPT} (times the iterations of a solve), got "
                         f"{s.last_attempt_iterations}", "solver.last_attempt_iterations")
    if integer(getattr(s, "max_substep_levels", 0), "solver.max_substep_levels", 0) > MAX_SUBSTEP_LEVELS:
        raise InputError(f"must be <= {MAX_SUBSTEP_LEVELS} (a failing step is retried as up to 2^levels substeps, "
                         f"{2 ** MAX_SUBSTEP_LEVELS} at {MAX_SUBSTEP_LEVELS}), got {s.max_substep_levels}",
                         "solver.max_substep_levels")


#: the solver's choices (hairexp/app/config.py's Enums, which a test compares): checked by
#: ``check_solver_config`` for a config of the Python API, whose dataclass takes any value
SOLVER_CHOICES = {"derivatives": ("closed_form", "autograd"), "stretch_hessian": ("primal_dual", "penalty"),
                  "compile": ("auto", "on", "off"), "on_failure": ("substep", "warn", "fail")}
#: the collision settings' choices and switches (``check_collision_config``)
COLLISION_CHOICES = {"contact": ("barrier", "stage"), "hair_hair_model": ("edges", "volume")}
COLLISION_FLAGS = ("objects", "hair_hair", "friction", "edge_response", "resolve", "plane_friction")

#: solver.stage_rtol_factor at most this (rtol x the factor is capped at STAGE_RTOL_CAP anyway)
MAX_STAGE_RTOL_FACTOR = 1e6

#: collision.barrier_dhat's bound (d_hat as a multiple of the contact thickness)
MAX_BARRIER_DHAT = 10.0
#: ``collision.max_passes`` at most this (each pass checks every vertex against every collider)
MAX_COLLISION_PASSES = 1000
#: ``collision.skin`` at most this (m): the hair-hair neighbour list holds every edge pair closer
#: than hair_thickness + skin; beyond a metre it is every pair of a head of hair
MAX_SKIN = 1.0
#: collision.max_travel_substeps at most (substeps of one step for a fast collider)
MAX_TRAVEL_SUBSTEPS = 1024
#: (key, lo, hi, lo_open) of the collision settings' numbers (m, 1/s, m/s; see ``check_collision_config``)
_COLLISION_NUMBERS = (
    # m: 1e300 a traceback (round 14), 0.09 stretched a wisp 130 % apart (round 15); hair is 0.05-0.1 mm thick
    ("hair_thickness", 0, 0.01, True),
    ("skin", 0, MAX_SKIN, False),   # 1e300 overflowed the neighbour grid (probe, round 14)
    ("strain_limit", 0, 1, False),
    ("max_travel", 0, None, False),
    ("volume_cell", 0, 1.0, True),   # m: a cell of a metre holds a head of hair
    ("volume_friction", 0, 1e6, False),   # 1/s
    ("volume_pressure_speed", 0, 100.0, False),   # m/s; 1e300 overflowed
    # a fraction of the thickness: 1e6 made d_hat 2 km and every vertex a contact of every
    # collider (the first step did not end in minutes; probe of issue 12)
    ("barrier_dhat", 0, MAX_BARRIER_DHAT, True),
    ("barrier_stiffness", 0, 1e9, True),
    ("friction_epsilon", 0, 10.0, True),   # m/s
)


def check_collision_config(c) -> None:
    """The collision settings (``collision.*``: hairexp/app/config.py CollisionConfig, or any
    object with its attributes) the collision stage and the barrier can run with, or an
    InputError naming the key: checked by the config's validation and by ``Simulator`` itself
    (the Python API took ``hair_thickness=10`` and moved hair 14.6 m in three "converged" steps,
    and a dict failed with an AttributeError; independent probe of issue 12, round 35).
    Attributes the object lacks are left out (their defaults apply)."""
    if isinstance(c, (dict, str, bytes)) or not hasattr(c, "objects"):
        raise InputError(f"must be a collision config (hairexp.app.config.CollisionConfig, or an object with its "
                         f"attributes: objects, hair_hair, hair_thickness, ...) or None, got {type(c).__name__}",
                         "collision")
    for key, lo, hi, lo_open in _COLLISION_NUMBERS:
        if hasattr(c, key):
            number(getattr(c, key), f"collision.{key}", lo=lo, hi=hi, lo_open=lo_open,
                   hi_open=key == "strain_limit")
    if hasattr(c, "max_passes"):
        integer(c.max_passes, "collision.max_passes", 1)
        if c.max_passes > MAX_COLLISION_PASSES:   # hair resting on a surface counts in every pass: 1e9 never ended
            raise InputError(f"must be <= {MAX_COLLISION_PASSES}, got {c.max_passes}", "collision.max_passes")
    if hasattr(c, "max_travel_substeps"):
        integer(c.max_travel_substeps, "collision.max_travel_substeps", 1)
        if c.max_travel_substeps > MAX_TRAVEL_SUBSTEPS:   # each substep is a whole step's solve
            raise InputError(f"must be <= {MAX_TRAVEL_SUBSTEPS}, got {c.max_travel_substeps}",
                             "collision.max_travel_substeps")
    check_switches(c, "collision", COLLISION_CHOICES, COLLISION_FLAGS)


class Simulator:
    def __init__(self, scene: Scene, solver_cfg, controller: Controller | None = None, collision_cfg=None,
                 integrator: str | None = None):
        """``controller``: what drives the hair beyond its physics (hairexp/control/); None is the
        free step.  ``collision_cfg``: the collision stage's settings, None for no stage.
        ``integrator``: overrides ``solver.integrator`` (the settle phase uses implicit Euler)."""
        tune_runtime()
        if not isinstance(scene, Scene):
            raise InputError(f"must be a Scene (hairexp.model.scene), got {type(scene).__name__}", "Simulator scene")
        check_solver_config(solver_cfg)
        if collision_cfg is not None:
            check_collision_config(collision_cfg)
        if controller is not None and not isinstance(controller, Controller):
            raise InputError(f"must be a Controller (hairexp.physics.controller; e.g. the app's build_controller), got "
                             f"{type(controller).__name__}", "Simulator controller")
        self.scene = scene
        self.cfg = solver_cfg
        if integrator is None:
            integrator = getattr(solver_cfg, "integrator", DEFAULT_INTEGRATOR)
        self.integrator = make_integrator(integrator)
        #: a step where the keyed roots' velocity jumps is an implicit Euler step, and the scheme
        #: restarts after it (``solver.restart_at_jumps``; not for implicit Euler itself, nor with a
        #: dynamic body, whose motion is simulated)
        self.restart_at_jumps = (bool(enum_value(getattr(solver_cfg, "restart_at_jumps", True)))
                                 and type(self.integrator) is not ImplicitEuler and scene.body is None)
        self._restart = Restart()
        self.controller = controller = Controller() if controller is None else controller
        s, m = scene.strands, scene.material
        terms = [Stretch(s.edges, s.rest_lengths, m.stretch_stiffness),
                 Bending(s.bends, s.rest, m.bending_stiffness)]
        free_vertices = np.flatnonzero(~s.kinematic)
        if m.edge_damping > 0:
            terms.append(EdgeDamping(s.edges, s.rest_lengths, m.edge_damping))
        if m.air_drag > 0:
            terms.append(AirDrag(s.masses, m.air_drag, free_vertices))
        terms += controller.energy_terms(scene)
        external = [Gravity(s.masses, scene.gravity, free_vertices)] if np.any(scene.gravity != 0) else []
        self.terms, self.external = terms, external
        kernels, threads = check_options(getattr(solver_cfg, "kernels", "numba"), getattr(solver_cfg, "threads", "auto"))
        self.objective = ImplicitEulerObjective(terms, s.masses, s.kinematic, s.free_slot,
                                                choice_name(solver_cfg.derivatives), external,
                                                primal_dual=choice_name(solver_cfg.stretch_hessian) == "primal_dual",
                                                kernels=kernels, threads=threads)
        self.newton = NewtonOptions(solver_cfg.rtol, solver_cfg.atol, solver_cfg.max_iterations, solver_cfg.max_backtracks)
        #: a multi-stage scheme's stages before the last are solved to this many times each solver's
        #: rtol (``solver.stage_rtol_factor``; a config without the key: 1): the controllers' solves
        #: read it from ``stage_tolerance`` while a stage before the last runs (``_stage``,
        #: ``controller.scaled_iterations``)
        self.stage_rtol_factor = float(enum_value(getattr(solver_cfg, "stage_rtol_factor", 1.0)))
        self.stage_tolerance = None
        self.on_failure = choice_name(solver_cfg.on_failure)
        #: the solves' iteration budget, as a multiple of their max_iterations (the controllers
        #: read it); above 1 only during a step's last attempt (``solver.last_attempt_iterations``)
        self.iteration_scale = 1
        self._last_attempts, self._last_failed = 0, False
        self.body = scene.body
        if self.body is not None:
            hair = float(s.masses[~s.kinematic].sum())
            need = getattr(self.integrator, "min_body_ratio", 1.0)
            if need > 1.0 and self.body.total_mass < need * hair:   # 1 x: build_dynamic_body checks it
                raise InputError(
                    f"the block ({self.body.mass:.4g} kg, plus {self.body.carried_mass:.4g} kg of roots) must weigh at "
                    f"least {need:g} x the free hair it carries ({hair:.4g} kg) with solver.integrator="
                    f"{self.integrator.name}: lighter, the staggered block-hair coupling is unstable under this scheme "
                    f"(hairexp/physics/integrators.py min_body_ratio); use a heavier block or "
                    f"solver.integrator=implicit_euler (stable from 1 x)", "scene.body.mass")
        # collision stage: built only when the scene has something to collide (else no code runs)
        self.collision_cfg = collision_cfg
        cc = collision_cfg
        self.collide_objects = bool(cc is not None and cc.objects and scene.colliders)
        # collision.contact=barrier: object contact inside the objective (hairexp/physics/barrier.py);
        # the post-solve stage then only handles hair-hair contact
        self.contact = make_object_contact(scene, cc)
        if self.contact is not None:
            self.objective.contact = self.contact
            self.collide_objects = False
        # a step in which a collider sweeps over hair by more than max_travel of its thinnest size
        # is split into equal substeps (``sweep_substeps``), in either contact mode
        self.sweep_colliders = list(scene.colliders) if (self.contact is not None or self.collide_objects) else []
        #: collision.resolve: the stage's object contacts as planes of a second solve (``_resolve_contacts``)
        self.resolve = bool(self.collide_objects and enum_value(getattr(cc, "resolve", False)))
        self.resolve_failures = 0
        #: (colliders, V) N: the normal forces of the last step's planes at its end (its last stage),
        #: the friction's normal forces of the next solve's resting contacts (``_with_friction``)
        self._plane_forces = None
        #: collision.plane_friction: resting contact's Coulomb friction inside the solve (``_with_friction``)
        self.plane_friction = bool(self.resolve and enum_value(getattr(cc, "plane_friction", False)))
        self._resolve_spent = None   # the SolveInfo of a failed second solve (``_resolve_contacts``)
        self.max_travel = float(getattr(cc, "max_travel", 0.0)) if cc is not None else 0.0
        self.max_travel_substeps = int(getattr(cc, "max_travel_substeps", 1)) if cc is not None else 1
        self._free_mask = ~s.kinematic
        self.hair_hair = self.limiter = None
        if (self.collide_objects or (cc is not None and cc.hair_hair)) and cc.strain_limit > 0:
            self.limiter = StrainLimit(s, cc.strain_limit)
        if cc is not None and cc.hair_hair:
            if choice_name(getattr(cc, "hair_hair_model", "edges")) == "volume":
                self.hair_hair = HairVolume(s, cc.volume_cell, cc.volume_friction, cc.volume_pressure_speed)
            else:
                self.hair_hair = HairHair(s, cc.hair_thickness, cc.skin)
        controller.bind(self)
        #: internal terms (their forces on the roots are the hair's force on a dynamic body)
        self._internal = [t for t in terms if t.name in ("stretch", "bending", "edge_damping")]
        mode = choice_name(getattr(solver_cfg, "compile", "off"))
        if mode == "on" or (mode == "auto" and s.n_vertices >= COMPILE_MIN_VERTICES):
            self._compile()

    def _compile(self) -> None:
        if choice_name(self.cfg.derivatives) != "closed_form":
            return
        for t in self.objective.torch_terms:   # the terms without a compiled numba kernel
            t.compile()  # compiles lazily at the first call; falls back to eager if that fails

    def free_dofs(self, x: np.ndarray) -> np.ndarray:
        return x[self.objective.free_vertices].reshape(-1)

    def initial_state(self) -> State:
        """Hair at rest in the body frame, moving rigidly with the body at t = 0."""
        sc = self.scene
        x = sc.motion.transform(sc.root_body, 0.0)
        v = sc.motion.point_velocity(sc.root_body, 0.0)
        body = None
        if self.body is not None:
            # the hair's force at t = 0: its elastic forces on the roots (0 for hair at rest); the
            # edge damping is 0 since everything moves rigidly with the body
            body = self.body.initial(self.root_force(x, damping=False))
        return State(0.0, x, v, control=self.controller.initial_control(), body=body)

    def motion_of(self, state: State):
        """The body's poses at ``state.time``: the keyframed motion, or the dynamic block there."""
        return self.scene.motion if self.body is None else self.body.at(state.time, state.body)

    def root_force(self, x: np.ndarray, damping: bool = True) -> np.ndarray:
        """(3,) N: the force the hair exerts on the body through its kinematic root vertices at
        positions x (V, 3): minus the gradient of the internal energies (stretch, bending and,
        within a step, edge damping) summed over the root vertices."""
        s = self.scene.strands
        X = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))
        F = np.zeros_like(x, dtype=np.float64)
        with torch.no_grad():
            for t in self._internal:
                if t.name == "edge_damping" and not damping:
                    continue
                g, _ = t.grad_hess(X[t.stencil_t], False, self.objective.derivatives)
                st = np.asarray(t.stencil)
                np.add.at(F, st, -g.numpy().reshape(st.shape[0], st.shape[1], 3))
        return F[s.kinematic].sum(axis=0)

    def accelerations(self, state: State) -> np.ndarray:
        """(V, 3) m/s^2: M^-1 F(x, v) of the free vertices at ``state`` (elastic, gravity, the
        controller's springs as begun for the step, dissipation at v); 0 on the kinematic roots.
        Generalized-alpha's start (hairexp/physics/integrators.py)."""
        obj = self.objective
        X = torch.from_numpy(np.ascontiguousarray(state.x, dtype=np.float64))
        for t in self.terms:
            if hasattr(t, "set_reference"):
                t.set_reference(torch.from_numpy(state.x - state.v), 1.0)   # (x - ref)/1 = v
        G = np.zeros_like(state.x, dtype=np.float64)
        with torch.no_grad():
            for t in self.terms + self.external:
                g, _ = t.grad_hess(X[t.stencil_t], False, obj.derivatives)
                st = np.asarray(t.stencil)
                np.add.at(G, st, g.numpy().reshape(st.shape[0], st.shape[1], 3))
        a = np.zeros_like(G)
        fv = obj.free_vertices
        a[fv] = -G[fv] / obj.m_free[:, None]
        return a

    def control_effort(self, state: State) -> float | None:
        """The controller's control effort at ``state`` (|F_c| / |m g|), None where it has none."""
        return self.controller.control_effort(self, self.checked_state(state, "Simulator.control_effort"))

    def observe(self, state: State) -> dict:
        """The controller's per-state quantities (metrics, recording) at ``state`` (checked as a
        step checks it: a state of another scene gave a residual of the wrong hair)."""
        state = self.checked_state(state, "Simulator.observe")
        return self.controller.observe(self, state, self.motion_of(state))

    # -- one attempt ----------------------------------------------------------------------
    def _attempt(self, state: State, dt: float) -> tuple[State, SolveInfo]:
        """One step of the integrator; a multi-stage scheme (TR-BDF2) runs its stages as steps
        of their own (each with its controller solve and collision stage) and reports them as
        one solve.  A stage that did not converge is reported in that solve (recovery then
        retries the whole step) but the later stages still run, so the state ends at the step's
        time; a stage that diverged (a non-finite state) ends the attempt."""
        if self.restart_at_jumps and self.scene.motion.velocity_jumps(state.time, state.time + dt, since=0.0):
            # the roots' velocity jumps in this step: one implicit Euler step, then the scheme
            # restarts (hairexp/physics/integrators.py, "Driver discontinuities")
            state, info = self._stage(state, dt, self._restart, dt)
            info.restart = True
            return state, info
        stages = getattr(self.integrator, "stages", None)
        if stages is None:
            return self._stage(state, dt, self.integrator, dt)
        infos, plan = [], stages(state, dt)
        for k, (scheme, h) in enumerate(plan):
            state, info = self._stage(state, h, scheme, dt, last=k == len(plan) - 1)
            infos.append(info)
            if info.status == DIVERGED:    # a non-finite state: the attempt ends here
                break
        return state, _merge_stages(infos)

    def _stage(self, state: State, dt: float, integ, step_dt: float, last: bool = True) -> tuple[State, SolveInfo]:
        """One stage of length dt with the scheme ``integ`` (the whole step for a one-stage
        scheme), within a step of length ``step_dt``; ``last``: the step's last stage (a velocity
        filter, the hair volume, runs after it only)."""
        ctl = self.controller
        t_next = state.time + dt
        # 1. kinematics: the body's poses over the step (a dynamic block moves first, with the
        #    hair force of the previous step), the controller's targets at t_next
        body, motion = None, self.scene.motion
        if self.body is not None:
            if not ctl.simulates:
                raise SimulationError(f"the {ctl.name} controller cannot drive a dynamic body")
            body = self.body.advance(state.body, dt, getattr(integ, "body_theta", 1.0))
            motion = self.body.window(state.time, state.body, t_next, body)
        ctl.begin(t_next, motion)
        # 2. solve
        plan = integ.plan(self, state, dt)
        if ctl.simulates:
            self.objective.begin_step(state.x, state.v, self.scene.root_positions(t_next, motion), dt, state.tensions,
                                      plan)
            if self.contact is not None:   # collider poses at t_next, a feasible start
                begin_contact_step(self.contact, self.objective, state.x, state.time, t_next, dt, self.newton)
        # a stage before the step's last is the scheme's intermediate point (TR-BDF2's x_g): solved
        # to solver.stage_rtol_factor x rtol, the step's end to rtol (README "The first stage's tolerance")
        self.stage_tolerance = None if last or self.stage_rtol_factor == 1.0 else self.stage_rtol_factor
        # collision.resolve: the hair resting on a collider keeps its planes in the first solve of every
        # stage (``_resting_planes``); at the step's last stage a second solve only where they did not hold
        carried = self._resting_planes(state, t_next) if self.resolve and ctl.simulates else None
        if carried is not None:
            self.objective.contact = carried
        try:
            x_new, control, info = ctl.solve(self, state, dt, t_next, motion)
        finally:
            self.stage_tolerance = None
            if carried is not None:
                self.objective.contact = None
        # 3. velocities (the integrator's), its history, and the hair's force on a dynamic body
        v_new = integ.velocity(x_new, state, plan)
        history = integ.history(state, x_new, v_new, plan, dt)
        if body is not None:
            body = self.body.with_hair_force(body, self.root_force(x_new))
        if not (np.isfinite(x_new).all() and np.isfinite(v_new).all()
                and (body is None or np.isfinite(body).all())):
            info.status = DIVERGED
        # 4. collision stage (the barrier's contact figures first, when it ran)
        elif ctl.simulates and self.contact is not None and self.hair_hair is None:
            info.collision = contact_collision_info(self.contact, x_new, CollisionInfo)
        elif ctl.simulates and (self.collide_objects or self.hair_hair is not None):
            sc = self.scene if self.collide_objects else _NoColliders(self.scene)
            x_solve = x_new
            hh, volume = self.hair_hair, None
            if isinstance(hh, HairVolume):
                # the volume is a velocity filter (hairexp/physics/hair_volume.py): once per step,
                # after its last stage, over the whole step, on the scheme's end velocity at the
                # solve's positions; it moves no position, so the object contacts below see the
                # solve's path, as without it
                hh = None
                if last:
                    volume = self.hair_hair
            if volume is not None:
                tic = time.perf_counter()
                v_filtered, pressed = volume.apply(x_solve, v_new, step_dt)
                dv_volume = v_filtered - v_new
                t_volume = time.perf_counter() - tic
            dist: list = []       # the colliders' distances at x_new, when the stage computed them
            if self.collide_objects or hh is not None:
                push = solved = None
                if carried is not None:
                    forces = carried.vertex_forces(x_new, len(sc.colliders))
                    push = self._plane_push(forces, plan)
                    solved = carried.friction_vertices(len(sc.colliders), len(x_new))
                    if last:
                        self._plane_forces = forces
                elif last:
                    self._plane_forces = None
                x_new, v_stage, cinfo = collision_stage(self.collision_cfg, sc, hh, state.x, x_new,
                                                        state.time, t_next, dt, self.limiter, dist_out=dist, push=push,
                                                        solved=solved)
                if (last and carried is not None and cinfo.object_contacts > 0 and cinfo.edge_contacts == 0
                        and self._planes_hold(carried, x_solve, sc.colliders, t_next)
                        and self._stage_kept(x_new, x_solve, sc.colliders)):
                    # the resting hair's planes held it, no edge dipped into a collider between its
                    # vertices and the stage moved nothing more than the micrometres the penalty
                    # leaves: the first solve is the step's (no second solve)
                    cinfo.resolved = len(carried)
                elif self.resolve and last and cinfo.object_contacts > 0 and sc.colliders:
                    # the stage's contacts as planes of a second solve (hairexp/physics/contact_planes.py),
                    # then the stage again on its result; at the step's end only: a scheme's intermediate
                    # point is not a result and the next stage solves again (Celia tracked, SQP iterations
                    # a step 6.31 -> 6.05, contact steps 5.1 -> 2.8 x the others' time, 2026-12-07)
                    failures, self._resolve_spent = self.resolve_failures, None
                    again = self._resolve_contacts(state, dt, t_next, motion, x_new, x_solve, sc.colliders, carried)
                    cinfo.resolve_failed = int(self.resolve_failures > failures)
                    if self._resolve_spent is not None:   # a failed second solve: the stage's result stands
                        info.iterations += self._resolve_spent.iterations
                        info.backtracks += self._resolve_spent.backtracks
                    if again is not None:
                        x_solve, control, info2, planes = again
                        info = _after(info, info2)
                        v_new = integ.velocity(x_solve, state, plan)
                        history = integ.history(state, x_solve, v_new, plan, dt)
                        if body is not None:
                            body = self.body.with_hair_force(body, self.root_force(x_solve))
                        first = cinfo
                        dist = []
                        # the planes' normal forces bound the friction of the vertices they press
                        # (they leave no approaching velocity for the stage's inelastic contact):
                        # the velocity they gave, h^2 / h_v F / m in the scheme's v = (x - x_ref) / h_v
                        forces = planes.vertex_forces(x_solve, len(sc.colliders))
                        self._plane_forces = forces
                        x_new, v_stage, cinfo = collision_stage(self.collision_cfg, sc, hh, state.x, x_solve,
                                                                state.time, t_next, dt, self.limiter, dist_out=dist,
                                                                discrete=True, push=self._plane_push(forces, plan))
                        cinfo.seconds += first.seconds
                        cinfo.resolved = len(planes)
                        # the contact frames are those the first stage found (the re-solve leaves its
                        # contacts on the shell, where the second corrects micrometres)
                        cinfo.object_contacts = max(cinfo.object_contacts, first.object_contacts)
                        for k, c in first.per_collider.items():
                            cinfo.per_collider[k] = max(cinfo.per_collider.get(k, 0), c)
                if type(integ) is ImplicitEuler:
                    v_new = v_stage
                else:
                    # the stage filters the path velocity (x_solve - x_n)/dt; the vertices it touched
                    # take its velocity, the others keep the integrator's
                    dx = x_new - x_solve
                    touched = (np.any(np.abs(dx) > TOUCH_TOL_X, axis=1)
                               | np.any(np.abs(v_stage - (x_solve - state.x) / dt) > TOUCH_TOL_V, axis=1))
                    dx = np.where(touched[:, None], dx, 0.0)
                    dv = np.where(touched[:, None], v_stage - v_new, 0.0)
                    v_new = v_new + dv
                    history = integ.after_collision(state, history, dx, dv, touched)
                placed = np.any(x_new != x_solve, axis=1) if last else None
                if placed is not None and placed.any():
                    # the stage moved vertices: the controller's constraints back, at the step's end
                    # only (a scheme's intermediate point is not a result, and its next stage solves
                    # the constraints again): goaling tracked 0.59 -> 0.39 s of collision time at the
                    # same residual (README "The tracking solver")
                    tic = time.perf_counter()
                    x_new, cinfo.restored, control = self._restore(x_new, control, t_next, sc.colliders, placed)
                    cinfo.seconds += time.perf_counter() - tic
            else:
                cinfo = CollisionInfo()
            if volume is not None:
                # the filter's change on top of the contact response; a vertex on a collider's shell
                # is then filtered by the inelastic contact again (no approaching normal velocity,
                # Coulomb friction), so the filter never drives hair into a collider
                tic = time.perf_counter()
                v_end = v_new + dv_volume
                if sc.colliders:
                    v_end = contact_velocities(sc.colliders, x_new, v_end, t_next, ~self.scene.strands.kinematic,
                                               dist=dist or None)
                history = integ.after_velocity_filter(state, history, v_end - v_new)
                v_new = v_end
                cinfo.hair_contacts += pressed
                cinfo.seconds += t_volume + time.perf_counter() - tic
            info.seconds["collision"] = info.seconds.get("collision", 0.0) + cinfo.seconds
            if self.contact is not None:   # object contact was the barrier's: its figures
                bc = contact_collision_info(self.contact, x_new, CollisionInfo)
                cinfo.object_contacts, cinfo.per_collider = bc.object_contacts, bc.per_collider
                cinfo.penetration_max = max(cinfo.penetration_max, bc.penetration_max)
            info.collision = cinfo
            if not (np.isfinite(x_new).all() and np.isfinite(v_new).all()):  # never return a non-finite state
                info.status = DIVERGED
        return State(t_next, x_new, v_new, info.tensions, control, body, history), info

    def _resting_planes(self, state: State, t_next: float):
        """Planes for the first solve of every stage (``collision.resolve``): on the hair resting
        on a collider, the movable vertices within ``NEAR`` of its shell on either side at the
        stage's start positions and its end pose, sliding over its surface by less than that in the
        stage, and the edges they end (``stage_planes`` at the start positions).  Hair lying on a
        collider then needs no second solve each step (a strand dropped on a plane, 50 steps: bdf2
        666 -> 248 Newton iterations, trbdf2 1,150 -> 409 with the planes in its first stage too;
        the same end state).  Hair that slides faster over the surface (the spinning wheel of
        goaling) or is further off gets none: planes taken where it is now would hold it off the
        surface where it arrives (goaling tracked 8.14 / 42 -> 8.32 / 51 SQP iterations a step with
        planes on every vertex near a shell), and a vertex deeper inside (a collider that moved onto
        it) could get a plane of the far side of a thin one.  None when no vertex qualifies."""
        cols = self.scene.colliders
        if not cols:
            return None
        s = self.scene.strands
        movable = np.flatnonzero(~s.kinematic)
        dt = t_next - state.time
        resting = np.zeros(len(state.x), dtype=bool)
        for col in cols:
            near = col.shell_tolerance() + NEAR * col.thickness
            c = movable[np.abs(_distances(col, state.x, movable, t_next)) < near]
            if c.size:
                slide = np.linalg.norm(state.v[c] - col.surface_velocity(state.x[c], t_next), axis=1) * dt
                resting[c[slide < near]] = True
        if not resting.any():
            return None
        return self._with_friction(stage_planes(cols, state.x, t_next, s.edges, resting, s.free_slot,
                                                self.objective.vertex_inertia()), state, t_next)

    def _planes_hold(self, planes, x: np.ndarray, colliders, t: float) -> bool:
        """Whether the solve's positions x (V, 3) with ``planes`` need no further solve: no movable
        vertex without a plane inside a collider's shell, and no plane holding hair beyond the
        surface it was taken at (``ContactPlanes.stale``)."""
        movable = np.flatnonzero(~self.scene.strands.kinematic)
        inside = np.zeros(len(x), dtype=bool)
        for col in colliders:
            inside[movable] |= _distances(col, x, movable, t) < -col.shell_tolerance()
        inside[planes.vertices()] = False
        return not inside.any() and not planes.stale(colliders, x, t).any()

    @staticmethod
    def _stage_kept(x_stage: np.ndarray, x_solve: np.ndarray, colliders) -> bool:
        """Whether the collision stage moved no vertex of the solve's positions by more than
        ``KEPT_MOVE`` of the thinnest collider's thickness (the penalty's micrometres)."""
        tol = KEPT_MOVE * min(c.thickness for c in colliders) + 1e-9
        return bool(np.abs(x_stage - x_solve).max(initial=0.0) <= tol)

    def _plane_push(self, forces: np.ndarray, plan) -> np.ndarray:
        """(colliders, V) m/s: the normal velocity the planes' forces (colliders, V) N gave each
        vertex in the stage's scheme, h^2 / h_v F / m (v = (x - x_ref) / h_v), which bounds the
        stage's Coulomb friction (``contact_velocities``; the planes leave it no approaching velocity
        to remove)."""
        return forces * (plan.h ** 2 / plan.h_v) / self.scene.strands.masses

    def _with_friction(self, planes, state: State, t_next: float):
        """With ``collision.plane_friction``: ``planes`` (the resting hair's, ``_resting_planes``)
        with Coulomb friction in the solve on the vertex planes of the vertices the last step's
        planes pressed, its normal force capped by that force (``_plane_forces``;
        ``ContactPlanes.update_lag``); a new contact has none yet and gets its friction from the
        stage, bounded by the planes' push.  Measured (2026-12-07): a strand lying across a slope
        stays where mu > tan(slope) (20 degrees, mu 0.5 and 0.8: 2.8 and 2.4 mm in 1 s, the first
        step's slide; 35 degrees: mu 0.5 slides 51 mm, 0.8 holds, 5 mm), where without it it slid
        40 mm at mu 0.8; Celia tracked 5.89 -> 6.16 SQP iterations a step with one step recovered
        by substeps, goaling 8.21 -> 8.71 (the lag turns the SQP's secant correction and non-
        monotone search off in those solves).  Friction in the second solves too (lagged the same
        way) gave Celia 6.15 / 38, and with the normal force held fixed through a solve 6.34 / 65
        with two steps recovered."""
        F = self._plane_forces
        if planes is None or not self.plane_friction or F is None or F.shape[1] != len(state.x):
            return planes
        vp = planes.e[:, 0] == planes.e[:, 1]
        lam = np.where(vp, F[planes.collider, planes.e[:, 0]], 0.0)
        eps_v = float(getattr(self.collision_cfg, "friction_epsilon", 1e-3))
        planes.set_friction(self.scene.colliders, state.x, state.time, t_next, eps_v, lam)
        return planes

    def _resolve_contacts(self, state: State, dt: float, t_next: float, motion, x_stage: np.ndarray,
                          x_first: np.ndarray, colliders, keep=None):
        """The stage's contacts (positions ``x_stage``, corrected from the solve's ``x_first``) as
        penalty planes of a second solve of the same stage from x_first (``collision.resolve``,
        hairexp/physics/contact_planes.py); ``keep``: the resting hair's planes of the first solve
        (``_resting_planes``), taken again with them.  Where that solve leaves a vertex without a plane inside
        a collider, or a plane holds hair beyond the surface it was taken at (``ContactPlanes.stale``),
        every plane is taken again at its positions (the set only grows) and the stage solved again
        from there, up to RESOLVE_ROUNDS solves: a sequence of linearised contact constraints, as
        an SQP linearises its constraints at each iterate.  Returns (positions, controller iterates,
        SolveInfo of all the solves, planes), or None when there is no plane or a solve did not
        converge to finite positions (the stage's result stands, counted in ``resolve_failures``)."""
        obj = self.objective
        s = self.scene.strands
        movable = ~s.kinematic
        inertia = obj.vertex_inertia()
        # the vertices the stage moved, wherever they end: one whose straight path crossed a collider is
        # stopped where it met it, and may end far from its shell (goaling with bdf2: a tip held 2.8 cm
        # from the solve's end, 17 mm off the wheel, its edge compressed by 43 % with no second solve;
        # independent probe, 2026-12-07)
        # (how far: the stage's move, or the solve's path when longer, which reached the collider that moved it;
        # lmm2 on goaling_smoke: a tip moved 3.9 mm by the stage, ended 5.9 mm off the wheel with no plane, 13.5 %)
        shift = np.linalg.norm(x_stage - x_first, axis=1)
        moved = np.where(movable & (shift > 0.0), np.maximum(shift, np.linalg.norm(x_first - state.x, axis=1)), 0.0)
        planes = stage_planes(colliders, x_stage, t_next, s.edges, movable, s.free_slot, inertia, x_first, keep=keep,
                              moved=moved)
        if planes is None:
            return None
        start, total = x_first, None
        for _ in range(RESOLVE_ROUNDS):
            obj.contact, obj.x_start = planes, start[obj.free_vertices].reshape(-1)
            try:
                x2, control2, info2 = self.controller.solve(self, state, dt, t_next, motion)
            finally:
                obj.contact, obj.x_start = None, None
            total = info2 if total is None else _after(total, info2)
            if not info2.converged or not np.isfinite(x2).all():
                self.resolve_failures += 1
                self._resolve_spent = total   # its iterations were done: the step counts them
                return None
            # vertices the planes left inside a collider's shell (an active set to grow), or planes
            # that hold hair off the surface (taken where it has slid past): the planes taken again
            # at these positions, and the stage solved again from them
            if self._planes_hold(planes, x2, colliders, t_next):
                break
            again = stage_planes(colliders, x2, t_next, s.edges, movable, s.free_slot, inertia, keep=planes)
            if again is None:
                break
            planes, start = again, x2
        # the vertices without a plane were nowhere near a collider after the stage: their moves from
        # there to the solve's end are tested as paths (a thin collider the solve dragged them through)
        free_of = movable.copy()
        free_of[planes.e.ravel()] = False
        x2, _, _ = object_positions(colliders, x_stage, x2, t_next, t_next, 0.0, free_of, friction=False)
        return x2, control2, total, planes

    def _restore(self, x: np.ndarray, control, t1: float, colliders, placed: np.ndarray | None = None
                 ) -> tuple[np.ndarray, int, object]:
        """Post-stabilisation after the collision stage: the controller moves the positions back
        onto its constraints (``Controller.restore``: the tracking's smallest mass-weighted move,
        a fraction of a millimetre after a contact), then the colliders' vertex and edge responses
        to that move (at t1, without friction: a projection, as the strain limiter's) and, with
        ``collision.strain_limit``, the limiter's rounds, in rounds until the constraints hold (at
        most RESTORE_ROUNDS; non-penetration and the strain limit win where all cannot hold).
        The vertices the stage (``placed``) or an earlier round's responses moved are pinned in
        the next moves: the move goes through the others, so the responses do not undo it (the
        plain alternation lost about 5x of the residual a round: goaling 5.4e-9 L after 8 rounds
        against 4.7e-13 L now, in 8 rounds in all instead of 25).  Velocities are the stage's: the
        move is a projection, not motion.  Returns (positions, rounds that moved them, the
        controller's iterates: where the rounds ran out, with the constraints left unmet marked by
        ``Controller.restore_unmet``)."""
        movable = ~self.scene.strands.kinematic
        edges = bool(getattr(self.collision_cfg, "edge_response", True))
        rounds = 0
        pinned = np.zeros(len(x), dtype=bool) if placed is None else placed.copy()
        for rounds in range(RESTORE_ROUNDS):
            xr = self.controller.restore(self, x, control, pinned)
            if xr is None:
                return x, rounds, control
            xp = xr
            if colliders:
                moved = movable & np.any(xr != x, axis=1)
                xr, _, _ = object_positions(colliders, x, xr, t1, t1, 0.0, moved, friction=False)
                if edges:
                    xr, _ = edge_response(colliders, self.scene.strands.edges, self.scene.strands.inverse_masses, xr,
                                          t1, movable)
                if self.limiter is not None and self.limiter.outside(xr):
                    # the move's strain as well (the limiter's rounds end with the contacts' response)
                    xr, _, _ = limit_strain(self.limiter, colliders, xr, t1, movable, edges)
            pinned |= np.any(xr != xp, axis=1)   # placed by a collider or the limiter: the next move keeps them
            x = xr
        return x, rounds + 1, self.controller.restore_unmet(self, x, control)

    def _advance(self, state: State, dt: float, level: int) -> tuple[State, list[SolveInfo]]:
        new, info = self._attempt(state, dt)
        self._attempted += info.iterations
        if info.converged:
            return new, [info]
        if self.on_failure == "substep" and level < self.cfg.max_substep_levels:
            mid, a = self._advance(state, 0.5 * dt, level + 1)
            end, b = self._advance(mid, 0.5 * dt, level + 1)
            return end, a + b
        scale = int(getattr(self.cfg, "last_attempt_iterations", 1))
        if self.on_failure == "substep" and info.status == MAX_ITERATIONS and scale > 1 and not self._last_failed:
            # the deepest level ran out of iterations: once more with ``scale`` times the solves'
            # iterations (the controllers read ``iteration_scale``).  On Celia's tracked run the
            # SQP converges linearly on compressed strands (README "Tracking performance"), and one
            # step of 150 was kept unconverged at 4.7 x its gradient tolerance
            self.iteration_scale = scale
            try:
                again, info2 = self._attempt(state, dt)
            finally:
                self.iteration_scale = 1
            self._attempted += info2.iterations
            if info2.converged:
                self._last_attempts += 1
                return again, [info2]
            self._last_failed = True   # one failed last attempt a step: its cost stays bounded
        if info.status == DIVERGED:
            raise SimulationError(
                f"step from t={state.time:.6g} s with dt={dt:.3g} s diverged (non-finite state) "
                f"after {info.iterations} iterations; try a smaller solver.dt or solver.on_failure=substep")
        if self.on_failure == "fail":
            raise SimulationError(
                f"step from t={state.time:.6g} s with dt={dt:.3g} s did not converge ({info.status}, "
                f"|grad|={info.grad_norm:.3g} vs force scale {info.force_scale:.3g}, {info.iterations} iterations)")
        return new, [info]

    # -- public ---------------------------------------------------------------------------
    def checked_state(self, state: State, where: str) -> State:
        """``state`` as a step reads it, or an InputError (a TypeError for what is not a State)
        naming ``where`` and the state's field: a time that is not a finite number, positions or
        velocities of another shape or not floating-point numbers (integer positions, a cast that
        dropped everything below a metre, "diverged ... try a smaller solver.dt"; lists of floats and
        float32 arrays are taken as float64 copies), a non-finite vertex (named with its strand), a
        zero-length edge, an integrator history of another scene, or controller iterates this
        controller cannot use (``Controller.check_control``: a free run's state in a tracked
        simulator was an AttributeError deep in the SQP; probe of issue 16).  The state given is
        never modified."""
        if not isinstance(state, State):
            raise TypeError(f"{where}: state must be a hairexp State (Simulator.initial_state() or a step's), "
                            f"got {type(state).__name__}")
        if (isinstance(state.time, (bool, np.bool_)) or not isinstance(state.time, (int, float, np.integer, np.floating))
                or not np.isfinite(state.time)):
            raise InputError(f"the state's time must be a finite number (s), got {state.time!r}", f"{where}: state.time")
        shape = (self.scene.strands.n_vertices, 3)
        if np.shape(state.x) != shape or np.shape(state.v) != shape:   # an IndexError deep in the step (probe of issue 12)
            raise InputError(f"the state's positions and velocities must have the scene's shape {shape}, "
                             f"got {np.shape(state.x)} and {np.shape(state.v)}", f"{where}: state.x, state.v")
        offsets = self.scene.strands.offsets
        arrays = {}
        for field, what in (("x", "positions"), ("v", "velocities")):
            given = getattr(state, field)
            values = np.asarray(given)
            if values.dtype.kind != "f":
                # complex, object or strings: numba's and numpy's own errors; integers: a cast that dropped
                # everything below a metre, which then "diverged ... try a smaller solver.dt"
                raise InputError(f"the state's {what} must be floating-point numbers, got dtype {values.dtype}"
                                 + (" (positions cast to integers lose everything below a metre)" if values.dtype.kind in "biu"
                                    else ""), f"{where}: state.{field}")
            if not isinstance(given, np.ndarray) or values.dtype != np.float64:
                arrays[field] = values = np.array(values, dtype=np.float64)
            if not np.isfinite(values).all():
                bad = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
                strand, k = curve_vertex(offsets, bad)
                raise InputError(f"the state's {what} are not finite: vertex {bad} (strand {strand}, vertex {k} along it) "
                                 f"is {values[bad].tolist()}", f"{where}: state.{field}")
        x = arrays.get("x", np.asarray(state.x))
        e = first_short_edge(x, offsets)   # the stretch's direction is undefined there: the step "diverged"
        if e is not None:
            strand, k = curve_vertex(offsets, e)
            raise InputError(f"the state's positions put vertices {e} and {e + 1} (strand {strand}, vertices {k} and "
                             f"{k + 1} along it) {float(np.linalg.norm(x[e + 1] - x[e])):.3g} m apart: an edge of zero "
                             "length cannot be stepped", f"{where}: state.x")
        h = state.history
        if h is not None:
            if not isinstance(h, History):
                raise InputError(f"must be None or the integrator's History (a step's state carries it), got "
                                 f"{type(h).__name__}", f"{where}: state.history")
            for field in ("x", "v", "a", "a_prev"):
                a = getattr(h, field)
                if a is not None and np.shape(a) != shape:
                    raise InputError(f"{field} has the shape {np.shape(a)}, not the scene's {shape}: a state of another "
                                     "scene", f"{where}: state.history")
        self.controller.check_control(state.control, f"{where}: state.control")
        return replace(state, **arrays) if arrays else state

    def step(self, state: State, dt: float) -> tuple[State, StepInfo]:
        if not isinstance(state, State):
            raise TypeError(f"Simulator.step: state must be a hairexp State (Simulator.initial_state() or a step's), "
                            f"got {type(state).__name__}")
        if (isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer, np.floating))
                or not (np.isfinite(dt) and dt > 0)):   # -0.01 stepped time backwards and said converged (probe of issue 12)
            raise InputError(f"dt must be a finite number > 0 (s), got {dt!r}", "Simulator.step")
        if dt > MAX_STEP_DT:   # 1e9 "diverged ... try a smaller solver.dt" naming a substep's dt (probe, round 15)
            raise InputError(f"dt={dt!r} s is above {MAX_STEP_DT:g} s: hair moves in milliseconds; a step of a frame "
                             "(1/24 s) is the longest the integrators are meant for", "Simulator.step")
        if dt < MIN_STEP_DT:   # 1e-300: the inertia M/dt^2 overflowed and the step "diverged" (probe of issue 12)
            raise InputError(f"dt={dt!r} s is below {MIN_STEP_DT:g} s: the inertia term M/dt^2 then swamps every force "
                             "in double precision (or overflows)", "Simulator.step")
        state = self.checked_state(state, "Simulator.step")
        t0 = time.perf_counter()
        self._attempted = 0
        self._last_attempts, self._last_failed = 0, False
        n = sweep_substeps(self.sweep_colliders, state.x, self._free_mask, float(state.time), float(dt),
                           self.max_travel, self.max_travel_substeps) if self.sweep_colliders else 1
        if n == 1:
            new, infos = self._advance(state, dt, 0)
        else:   # a fast collider: n equal substeps, each with its own recovery
            new, infos = state, []
            for _ in range(n):
                new, part = self._advance(new, dt / n, 0)
                infos += part
        total = time.perf_counter() - t0
        last = infos[-1]
        worst = next((i for i in infos if not i.converged), last)
        sec = {k: sum(i.seconds.get(k, 0.0) for i in infos) for k in TIME_KEYS}
        sec["other"] = max(total - sum(sec[k] for k in TIME_KEYS if k != "other"), 0.0)
        sec["total"] = total
        info = StepInfo(time=new.time, dt=dt, status=worst.status, iterations=sum(i.iterations for i in infos),
                        backtracks=sum(i.backtracks for i in infos), substeps=len(infos),
                        grad_norm=last.grad_norm, force_scale=last.force_scale, constraint_norm=last.constraint_norm,
                        recovered=(len(infos) > n or self._last_attempts > 0) and all(i.converged for i in infos),
                        seconds=sec,
                        iterations_attempted=self._attempted, restarts=sum(bool(i.restart) for i in infos))
        c = _sum_collisions([i.collision for i in infos if i.collision is not None])
        if c is not None:
            info.object_contacts, info.hair_contacts = c.object_contacts, c.hair_contacts
            info.penetration_max = c.penetration_max
            info.restored = c.restored
            info.contact_planes, info.resolve_fallbacks = c.resolved, c.resolve_failed
            info.collider_contacts.update(c.per_collider)
        if info.recovered or (n > 1 and all(i.converged for i in infos)):
            info.status = CONVERGED
        return new, info
