"""A controller is a plug-in: a module with ``build(cfg, scene, guides)`` and one registry entry.
Here a toy controller (a spring pulling every free vertex toward its rest position carried by
the body, added as an energy term) is registered from this test module and stepped by the unchanged Simulator."""

from __future__ import annotations

import numpy as np

from hairexp.app.assemble import assemble_scene
from hairexp.app.config import compose_config
from hairexp.control import REGISTRY, build_controller
from hairexp.physics.controller import Controller
from hairexp.physics.energies import Attraction
from hairexp.physics.simulator import Simulator


class RestSprings(Controller):
    name = "rest_springs"

    def __init__(self, scene, k: float):
        s = scene.strands
        self.free = np.flatnonzero(~s.kinematic)
        self.body_rest = scene.root_body[self.free]
        self.term = Attraction(s.masses, k, self.free)
        self.begun = []

    def energy_terms(self, scene) -> list:
        return [self.term]

    def begin(self, t, motion) -> None:
        self.begun.append(t)
        self.term.set_target(motion.transform(self.body_rest, t))

    def control_effort(self, sim, state) -> float:
        return float(np.linalg.norm(self.term.forces(state.x))) / sim.scene.free_weight_norm()


def build(cfg, scene, guides):
    return RestSprings(scene, 4000.0)


def test_a_registered_controller_is_built_and_stepped_without_touching_the_step(monkeypatch):
    monkeypatch.setitem(REGISTRY, "rest_springs", __name__)
    cfg, scene, guides = assemble_scene(compose_config(["experiment=goaling_smoke", "variants=[]", "frames=4"]))
    ctl = build_controller("rest_springs", cfg, scene, guides)
    free = Simulator(scene, cfg.solver, None, cfg.collision)
    held = Simulator(scene, cfg.solver, ctl, cfg.collision)
    a, b = free.initial_state(), held.initial_state()
    for _ in range(6):
        a, ia = free.step(a, 0.04)
        b, ib = held.step(b, 0.04)
        assert ia.converged and ib.converged
    rest = scene.motion.transform(scene.root_body, a.time)   # the rest shape carried by the body
    # the springs hold the hair nearer its carried rest shape than the free hair under the body's motion
    da = np.abs((a.x - rest)[ctl.free]).max()
    db = np.abs((b.x - rest)[ctl.free]).max()
    assert db < 0.5 * da, (da, db)
    # begun once per solve: per stage of the default integrator (trbdf2: 2 a step), at the stage's end
    stages = len(held.integrator.stages(b, 0.04)) if hasattr(held.integrator, "stages") else 1
    assert len(ctl.begun) == 6 * stages and np.isclose(ctl.begun[-1], 0.24)
    assert held.control_effort(b) > 0 and free.control_effort(a) is None


def test_an_unknown_controller_is_a_named_error():
    import pytest

    from hairexp.errors import InputError

    with pytest.raises(InputError, match="controller.name"):
        build_controller("nope", None, None, None)
