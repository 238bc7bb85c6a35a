"""What the time step asks of a controller (hairexp/control/ implements them).

The step (``Simulator.step``, hairexp/physics/simulator.py) calls these hooks without knowing
which controller it has:

* ``energy_terms(scene)``: energies the controller adds to the objective (eq. 5), once, when
  the Simulator is built (the attraction baseline's springs);
* ``bind(sim)``: once, after the objective is built (the tracking KKT solver needs its band);
* ``initial_control()``: the controller's part of the first ``State`` (``State.control``);
* ``begin(t, motion)``: at the start of every attempt, with the end-of-step time t and the
  body's poses over the step (targets, attraction anchors);
* ``solve(sim, state, dt, t_next, motion)``: the end-of-step positions (V, 3), the next
  ``State.control`` and a ``SolveInfo``;
* ``observe(sim, state, motion)`` and ``control_effort(sim, state)``: what a state says about
  the controller (metrics, recording), after the step.

``simulates``: False for a controller that prescribes the positions (skinning): the step then
builds no objective step, runs no collision stage and refuses a dynamic body.

This base class is the free controller: no terms, no constraints, Newton on eq. 5.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hairexp.physics.newton import newton_solve


#: the rtol of a stage before a multi-stage scheme's last is at most this (``scaled_iterations``): on
#: goaling 0.1 kept the step's end within 5.6e-6 m free, 1.5e-5 m tracked of the tight solves'; a
#: stage stopped after one iteration diverged (reports/trbdf2_cost.md, "A looser first stage")
STAGE_RTOL_CAP = 0.1


def scaled_iterations(opts, sim):
    """``opts`` (a solver's options with ``max_iterations`` and ``rtol``) for this solve: with the
    simulator's iteration budget applied (``sim.iteration_scale`` times the iterations during a
    step's last attempt, ``solver.last_attempt_iterations``) and, in a stage before a multi-stage
    scheme's last (``sim.stage_tolerance``: ``solver.stage_rtol_factor``), rtol that many times
    its own, at most ``STAGE_RTOL_CAP`` (never below its own); ``opts`` itself otherwise."""
    scale = int(getattr(sim, "iteration_scale", 1))
    if scale > 1:
        opts = replace(opts, max_iterations=scale * opts.max_iterations)
    factor = getattr(sim, "stage_tolerance", None)
    if factor is not None:
        loose = min(factor * opts.rtol, STAGE_RTOL_CAP)
        if loose > opts.rtol:
            opts = replace(opts, rtol=loose)
    return opts


class Controller:
    name = "free"
    simulates = True

    def energy_terms(self, scene) -> list:
        return []

    def bind(self, sim) -> None:
        pass

    def initial_control(self):
        return None

    def begin(self, t: float, motion) -> None:
        pass

    def solve(self, sim, state, dt: float, t_next: float, motion):
        """Newton on the objective begun for this step (paper eq. 5, no constraints)."""
        xf, info = newton_solve(sim.objective, sim.objective.initial_guess(), scaled_iterations(sim.newton, sim))
        return sim.objective.positions(xf).numpy(), None, info

    def check_control(self, control, where: str) -> None:
        """InputError naming ``where`` when ``control`` (a State's) is not iterates this
        controller can start from; the free controller reads none."""

    def observe(self, sim, state, motion) -> dict:
        """Per-state quantities for the metrics and the recording (scalars become columns)."""
        return {}

    def restore(self, sim, x: np.ndarray, control, pinned: np.ndarray | None = None) -> np.ndarray | None:
        """Positions x (V, 3) moved back onto the controller's constraints of the stage just
        solved (``control``: its iterates), after the collision stage moved vertices off them, or
        None where nothing needs to move (no constraints, or they hold).  ``pinned``: (V,) bool or
        None, vertices a collider or the strain limiter placed, which the move should leave where
        they are (``Simulator._restore`` passes them; a controller may ignore them)."""
        return None

    def restore_unmet(self, sim, x: np.ndarray, control):
        """The iterates ``control`` after ``restore``'s rounds ran out at x: the constraints x
        leaves unmet (non-penetration and the strain limit won) marked so, for the metrics.  The
        default leaves them as they are."""
        return control

    def control_effort(self, sim, state) -> float | None:
        """|F_c| / |m g| of the control force at ``state``, or None where it has none."""
        return None

    def cluster_of_vertex(self) -> np.ndarray | None:
        """(V,) cluster index of each vertex (-1: none), or None for a controller without clusters."""
        return None

    def cluster_weights(self) -> np.ndarray | None:
        """(V, K) each vertex's share in each cluster when a vertex can belong to several, or None
        (then ``cluster_of_vertex`` says it all)."""
        return None
