"""Settle phase (``scene.settle``, seconds; 0 = off): start a run from hair at rest under gravity.

The builders make the hair in its elastic rest shape (straight strands), which is not in
equilibrium under gravity: left alone it sags before anything moves.  With ``scene.settle`` > 0 the
hair is simulated free (no controller) from time -settle to 0, with the run's solver settings
and steps of ``scene.settle_dt`` (default 0.04 s, whatever the run's dt: runs at different dt
start from the same state), always with implicit Euler whatever ``solver.integrator`` (its damping
reaches the equilibrium fastest, and runs with different integrators start from the same state), the body and the colliders held at their t = 0 poses (keyframed motions hold
their first pose with zero velocity before their first key, hairexp/model/rigid.py; a dynamic
body is replaced by its initial pose held still).  The run then starts from the settled
positions at rest (zero velocity): ``Scene.root_body`` (body frame) and ``Scene.initial`` (world)
hold them, and the tracking is registered on them (paper 3.1-3.2: correspondence and offsets in
the configuration the run starts from).  The elastic rest shape (rest lengths and bending angles,
``Strands.rest``) is unchanged.  Simulated guides (``guides.source: simulated``) settle the same
way for the same time (hairexp/app/guides.py); the other guide sources are not settled.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np

from hairexp.errors import MIN_STEP_DT, InputError, finite_number
from hairexp.model.dynamic_body import authoring_motion
from hairexp.physics.simulator import Simulator

log = logging.getLogger(__name__)


def settle_seconds(scene_cfg) -> float:
    """``scene.settle`` validated: a finite number >= 0 (s)."""
    v = finite_number(getattr(scene_cfg, "settle", 0.0), "scene.settle")
    if not v >= 0:
        raise InputError(f"must be >= 0 (seconds), got {v}", "scene.settle")
    return v


def settle_step(scene_cfg) -> float:
    """``scene.settle_dt`` validated: the settle phase's step (s), finite and > 0.  It is fixed,
    not the run's dt, so that runs at different dt start from the same settled state (and large
    implicit Euler steps damp the sag's oscillation quickly)."""
    v = finite_number(getattr(scene_cfg, "settle_dt", 0.04), "scene.settle_dt")
    # 1e300 overflowed the first settle step (probe of issue 12, round 14); 1e-10: a traceback (round 27)
    if not MIN_STEP_DT <= v <= 1.0:
        raise InputError(f"must be at least {MIN_STEP_DT:g} and at most 1 (seconds), got {v}", "scene.settle_dt")
    return v


def settle_state(scene, solver_cfg, collision_cfg, seconds: float, dt: float, what: str = "hair") -> np.ndarray:
    """(V, 3) world positions of ``scene``'s hair after ``seconds`` of free simulation from its
    rest shape, the body and colliders held at their t = 0 poses (see module doc)."""
    held = replace(scene, motion=authoring_motion(scene.motion), initial=None)
    # always implicit Euler (hairexp/physics/integrators.py): the settle phase exists to reach the
    # equilibrium, which its damping reaches fastest, and every integrator then starts from the same state
    sim = Simulator(held, solver_cfg, collision_cfg=collision_cfg, integrator="implicit_euler")
    n = max(1, int(math.ceil(seconds / dt - 1e-9)))
    t0 = time.perf_counter()
    state = sim.initial_state()
    state.time = -n * dt
    tips = scene.strands.offsets[1:] - 1
    move = 0.0
    for _ in range(n):
        prev = state.x[tips].copy()
        state, _ = sim.step(state, dt)
        move = float(np.max(np.linalg.norm(state.x[tips] - prev, axis=1)))
    log.info("settle %s (%s): %d steps of %.4g s in %.1f s; tips moved at most %.3g mm in the last step",
             what, scene.name, n, dt, time.perf_counter() - t0, 1e3 * move)
    return state.x


def settled_scene(scene, x: np.ndarray):
    """``scene`` starting from world positions x (V, 3) at t = 0: ``initial`` = x, the free rows
    of ``root_body`` from x (the kinematic rows, the roots, are kept exactly)."""
    motion = authoring_motion(scene.motion)
    root_body = scene.root_body.copy()
    free = ~scene.strands.kinematic
    root_body[free] = motion.to_body(x, 0.0)[free]
    return replace(scene, root_body=root_body, initial=np.asarray(x, dtype=np.float64).copy())


def settle_scene(scene, cfg):
    """The scene of a run: ``scene`` itself when ``cfg.scene.settle`` is 0, else settled (steps of
    ``scene.settle_dt``, whatever the run's dt)."""
    seconds, step = settle_seconds(cfg.scene), settle_step(cfg.scene)   # both validated, even when off
    if seconds == 0:
        return scene
    return settled_scene(scene, settle_state(scene, cfg.solver, cfg.collision, seconds, step))
