"""The ``skinned`` baseline controller: no simulation; the detail hair rides on the guides
(positions x_g(t), hairexp/control/skinning.py), velocities by finite difference, no collisions.
Its control effort is the force the hair's own physics would need to move that way."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hairexp.control.skinning import GuideSkinning
from hairexp.errors import InputError
from hairexp.physics.controller import Controller
from hairexp.physics.info import CONVERGED, SolveInfo
from hairexp.physics.state import State


@dataclass(frozen=True)
class SkinnedStep:
    """``State.control`` of a skinned state: the step that prescribed it (start x, v and dt, and
    the integrator's history there, for its step plan)."""

    x: np.ndarray
    v: np.ndarray
    dt: float
    history: object = None


class SkinnedController(Controller):
    name = "skinned"
    simulates = False

    def __init__(self, scene, guides):
        if scene.body is not None:
            raise InputError("the skinned controller needs a keyframed body (scene.body.dynamic=false)",
                             "controller.name")
        self.skin = GuideSkinning(scene, guides)

    def solve(self, sim, state, dt, t_next, motion):
        t0 = time.perf_counter()
        x_new = self.skin.positions(t_next, motion)
        info = SolveInfo(CONVERGED, 0, seconds={"derivatives": 0.0, "assembly": 0.0,
                                                 "solve": time.perf_counter() - t0})
        return x_new, SkinnedStep(state.x, state.v, dt, state.history), info

    def control_effort(self, sim, state) -> float | None:
        """|F_c| / |m g|: F_c = -(gradient of eq. 5 at the skinned positions) = the force that,
        added to gravity and the hair's elastic forces, makes the implicit Euler step land on
        x_g (the control force a physical hair would need to follow the skinning; with another
        ``solver.integrator``, that integrator's step from the previous state)."""
        prev = state.control
        if prev is None:
            return None
        obj = sim.objective
        scheme = getattr(sim.integrator, "final_stage", sim.integrator)   # TR-BDF2: its BDF2 stage
        plan = scheme.plan(sim, State(state.time - prev.dt, prev.x, prev.v, history=prev.history), prev.dt)
        obj.begin_step(prev.x, prev.v, sim.scene.root_positions(state.time), prev.dt, None, plan)
        ev = obj.evaluate(sim.free_dofs(state.x), need_hessian=False)
        return float(np.linalg.norm(ev.grad)) / sim.scene.free_weight_norm()


def build(cfg, scene, guides) -> SkinnedController:
    return SkinnedController(scene, guides)
