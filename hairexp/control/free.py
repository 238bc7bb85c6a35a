"""The ``free`` controller: the hair's own physics, Newton on eq. 5 with no constraints
(the step's default, hairexp/physics/controller.py)."""

from __future__ import annotations

from hairexp.physics.controller import Controller


class FreeController(Controller):
    name = "free"


def build(cfg, scene, guides) -> FreeController:
    return FreeController()
