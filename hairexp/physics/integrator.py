"""The time step, phase by phase:

1. kinematics: root positions of the rigid body at t + dt (a dynamic body, ``scene.body``, first
   moves under gravity, its rail and the hair's force of the previous step; its state travels in
   ``State.duals['body']`` so that a retried step restarts from it, hairexp/scene/dynamic_body.py);
2. solve: minimise the implicit Euler objective (eq. 5) - Newton for the free controller;
3. velocities: v_{n+1} = (x_{n+1} - x_n) / dt; a dynamic body takes the force the hair exerts on
   its roots at x_{n+1} (for the next step);
4. recovery: a step that diverged or did not converge is retried as two half steps
   (``solver.on_failure=substep``, recursively), kept and flagged (``warn``), or stops the
   run (``raise``).  A non-finite state is never returned.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from hairexp import tune_runtime
from hairexp.errors import SimulationError
from hairexp.physics.energies import AirDrag, Attraction, Bending, EdgeDamping, Gravity, Stretch
from hairexp.physics.info import CONVERGED, DIVERGED, SolveInfo, StepInfo
from hairexp.physics.newton import NewtonOptions, newton_solve
from hairexp.physics.objective import ImplicitEulerObjective
from hairexp.tracking.sqp import sqp_solve
from hairexp.scene.dynamic_body import DynamicBody
from hairexp.scene.scene import Scene, State

TIME_KEYS = ("derivatives", "assembly", "solve", "collision", "other")
#: ``solver.compile=auto`` compiles the derivative kernels from this many vertices on.
COMPILE_MIN_VERTICES = 4000

log = logging.getLogger(__name__)


def _value(x):
    return getattr(x, "value", x)


class _NoColliders:
    """The scene seen by the collision stage when object collisions are switched off."""

    def __init__(self, scene):
        self.strands, self.colliders, self.motion = scene.strands, [], scene.motion


class Simulator:
    def __init__(self, scene: Scene, solver_cfg, tracking_cfg=None, guides=None, collision_cfg=None,
                 attraction: tuple | None = None):
        """``tracking_cfg`` and ``guides`` given: the tracked controller (SQP with constraints);
        otherwise the free controller (Newton, no constraints are built).  ``attraction``:
        (guides, k) adds the attraction baseline (controller ``attract``): a spring
        1/2 k m_i |x_i - x_g,i(t)|^2 pulls each free vertex to its guide-skinned position
        (hairexp/tracking/skinning.py), its target set before each solve."""
        tune_runtime()
        self.scene = scene
        self.cfg = solver_cfg
        s, m = scene.strands, scene.material
        terms = [Stretch(s.edges, s.rest_lengths, m.stretch_stiffness),
                 Bending(s.bends, s.rest, m.bending_stiffness)]
        free_vertices = np.flatnonzero(~s.kinematic)
        if m.edge_damping > 0:
            terms.append(EdgeDamping(s.edges, s.rest_lengths, m.edge_damping))
        if m.air_drag > 0:
            terms.append(AirDrag(s.masses, m.air_drag, free_vertices))
        self.attraction = self.skinning = None
        if attraction is not None:
            from hairexp.tracking.skinning import GuideSkinning

            a_guides, k = attraction
            self.skinning = GuideSkinning(scene, a_guides)
            self.attraction = Attraction(s.masses, k, free_vertices)
            terms.append(self.attraction)
        external = [Gravity(s.masses, scene.gravity, free_vertices)] if np.any(scene.gravity != 0) else []
        self.terms, self.external = terms, external
        self.objective = ImplicitEulerObjective(terms, s.masses, s.kinematic, s.free_index,
                                                str(_value(solver_cfg.derivatives)), external,
                                                primal_dual=str(_value(solver_cfg.stretch_hessian)) == "primal_dual")
        self.newton = NewtonOptions(solver_cfg.rtol, solver_cfg.atol, solver_cfg.max_iterations, solver_cfg.max_backtracks)
        self.on_failure = str(_value(solver_cfg.on_failure))
        # collision stage: built only when the scene has something to collide (else no code runs)
        self.collision_cfg = collision_cfg
        cc = collision_cfg
        self.collide_objects = bool(cc is not None and cc.objects and scene.colliders)
        self.hair_hair = self.limiter = None
        if (self.collide_objects or (cc is not None and cc.hair_hair)) and cc.strain_limit > 0:
            from hairexp.physics.collisions import StrainLimit

            self.limiter = StrainLimit(s, cc.strain_limit)
        if cc is not None and cc.hair_hair:
            from hairexp.physics.collisions import HairHair

            self.hair_hair = HairHair(s, cc.hair_thickness, cc.skin)
        self.tracker = None
        if tracking_cfg is not None:
            from hairexp.tracking.controller import TrackingController

            self.tracker = TrackingController(scene, guides, tracking_cfg, self.objective.assembler.bandwidth)
        self.body = scene.motion if isinstance(scene.motion, DynamicBody) else None
        #: internal terms (their forces on the roots are the hair's force on a dynamic body)
        self._internal = [t for t in terms if t.name in ("stretch", "bending", "edge_damping")]
        mode = str(_value(getattr(solver_cfg, "compile", "off")))
        if mode == "on" or (mode == "auto" and s.n_vertices >= COMPILE_MIN_VERTICES):
            self._compile()

    def _compile(self) -> None:
        if str(_value(self.cfg.derivatives)) != "closed_form":
            return
        for t in self.terms:
            t.compile()  # compiles lazily at the first call; falls back to eager if that fails

    def free_dofs(self, x: np.ndarray) -> np.ndarray:
        return x[self.objective.free_vertices].reshape(-1)

    def initial_state(self) -> State:
        """Hair at rest in the body frame, moving rigidly with the body at t = 0."""
        sc = self.scene
        x = sc.motion.transform(sc.root_body, 0.0)
        v = sc.motion.point_velocity(sc.root_body, 0.0)
        duals = self.tracker.initial_duals() if self.tracker else {}
        if self.body is not None:
            # the hair's force at t = 0: its elastic forces on the roots (0 for hair at rest); the
            # edge damping is 0 since everything moves rigidly with the body
            b = self.body.initial(self.root_force(x, damping=False))
            self.body.set_window(0.0, b, 0.0, b)
            duals["body"] = b
        return State(0.0, x, v, duals)

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

    def control_effort(self, state: State) -> float | None:
        """|F_c| / |m g| over the free vertices: the attraction's spring forces at ``state`` (the
        target of the last solve); None for the free and tracked controllers (the tracked one
        reports ``constraint_force_rel``)."""
        if self.attraction is None:
            return None
        return float(np.linalg.norm(self.attraction.forces(state.x))) / self.scene.free_weight_norm()

    # -- one attempt ----------------------------------------------------------------------
    def _solve(self, state: State, dt: float) -> tuple[State, SolveInfo]:
        t_next = state.time + dt
        obj = self.objective
        body = None
        if self.body is not None:  # the block moves first, with the hair force of the previous step
            body = self.body.advance(state.duals["body"], dt)
            self.body.set_window(state.time, state.duals["body"], t_next, body)
        if self.attraction is not None:
            self.attraction.set_target(self.skinning.free_positions(t_next))
        obj.begin_step(state.x, state.v, self.scene.root_positions(t_next), dt, state.duals)
        if self.tracker is None:
            xf, info = newton_solve(obj, obj.initial_guess(), self.newton)
            duals = info.duals
        else:
            tr = self.tracker
            tr.begin(t_next)
            d = state.duals
            xf, tk, lam, info = sqp_solve(obj, tr, obj.initial_guess(), d["t"], d["lambda"], tr.opts)
            duals = {**info.duals, "t": tk, "lambda": lam}
        x_new = obj.positions(xf).numpy()
        v_new = (x_new - state.x) / dt
        if body is not None:
            duals = {**duals, "body": self.body.with_hair_force(body, self.root_force(x_new))}
        if not (np.isfinite(x_new).all() and np.isfinite(v_new).all()
                and (body is None or np.isfinite(duals["body"]).all())):
            info.status = DIVERGED
        elif self.collide_objects or self.hair_hair is not None:
            from hairexp.physics.collisions import collision_stage

            sc = self.scene if self.collide_objects else _NoColliders(self.scene)
            x_new, v_new, cinfo = collision_stage(self.collision_cfg, sc, self.hair_hair, state.x, x_new,
                                                  state.time, t_next, dt, self.limiter)
            info.seconds["collision"] = info.seconds.get("collision", 0.0) + cinfo.seconds
            info.collision = cinfo
            if not (np.isfinite(x_new).all() and np.isfinite(v_new).all()):  # never return a non-finite state
                info.status = DIVERGED
        return State(t_next, x_new, v_new, duals), info

    def _advance(self, state: State, dt: float, level: int) -> tuple[State, list[SolveInfo]]:
        new, info = self._solve(state, dt)
        self._attempted += info.iterations
        if info.converged:
            return new, [info]
        if self.on_failure == "substep" and level < self.cfg.max_substep_levels:
            mid, a = self._advance(state, 0.5 * dt, level + 1)
            end, b = self._advance(mid, 0.5 * dt, level + 1)
            return end, a + b
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
    def step(self, state: State, dt: float) -> tuple[State, StepInfo]:
        t0 = time.perf_counter()
        self._attempted = 0
        new, infos = self._advance(state, dt, 0)
        total = time.perf_counter() - t0
        last = infos[-1]
        worst = next((i for i in infos if not i.converged), last)
        sec = {k: sum(i.seconds.get(k, 0.0) for i in infos) for k in TIME_KEYS}
        sec["other"] = max(total - sum(sec[k] for k in TIME_KEYS if k != "other"), 0.0)
        sec["total"] = total
        info = StepInfo(time=new.time, dt=dt, status=worst.status, iterations=sum(i.iterations for i in infos),
                        backtracks=sum(i.backtracks for i in infos), substeps=len(infos),
                        grad_norm=last.grad_norm, force_scale=last.force_scale, constraint_norm=last.constraint_norm,
                        recovered=len(infos) > 1 and all(i.converged for i in infos), seconds=sec,
                        iterations_attempted=self._attempted)
        cis = [i.collision for i in infos if i.collision is not None]
        if cis:
            info.object_contacts = sum(c.object_contacts for c in cis)
            info.hair_contacts = sum(c.hair_contacts for c in cis)
            info.penetration_max = max(c.penetration_max for c in cis)
            for c in cis:
                for k, n in c.per_collider.items():
                    info.collider_contacts[k] = info.collider_contacts.get(k, 0) + n
        if len(infos) > 1 and info.recovered:
            info.status = CONVERGED
        return new, info
