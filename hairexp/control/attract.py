"""The ``attract`` baseline controller: the free simulation plus a spring
1/2 k m_i |x_i - x_g,i(t)|^2 pulling each free vertex to its guide-skinned position
(hairexp/control/skinning.py), its anchor set at the end-of-step time before each solve."""

from __future__ import annotations

import math

import numpy as np

from hairexp.control.skinning import GuideSkinning
from hairexp.errors import InputError
from hairexp.physics.controller import Controller
from hairexp.physics.energies import Attraction


class AttractController(Controller):
    name = "attract"

    def __init__(self, scene, guides, stiffness: float):
        self.skinning = GuideSkinning(scene, guides)
        self.guides = guides
        s = scene.strands
        self.attraction = Attraction(s.masses, stiffness, np.flatnonzero(~s.kinematic))

    def energy_terms(self, scene) -> list:
        return [self.attraction]

    def begin(self, t: float, motion) -> None:
        self.guides.check_time(t, "Simulator.step: state.time")
        self.attraction.set_target(self.skinning.free_positions(t, motion))

    def control_effort(self, sim, state) -> float:
        """|F_c| / |m g|: the springs' forces at ``state`` (toward the anchors of the last solve)."""
        return float(np.linalg.norm(self.attraction.forces(state.x))) / sim.scene.free_weight_norm()


def build(cfg, scene, guides) -> AttractController:
    k = float(cfg.controller.attract_stiffness)
    if not (k > 0 and math.isfinite(k)):
        raise InputError(f"must be > 0, got {k}", "controller.attract_stiffness")
    return AttractController(scene, guides, k)
