"""The per-step state of a run: what changes from step to step (the Scene never does)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass
class State:
    """One instant of a run.  A step maps a State to the next one and never modifies it, so a
    failed step is retried from the same State (``Simulator.step(state, dt)`` again).

    ``tensions``: the primal-dual stretch Hessian's dual iterates by term name
    (hairexp/physics/energies.py ``Stretch``), the Newton/SQP warm start of the next step.
    ``control``: the controller's own iterates (tracking: ``TrackingIterates`` with the
    sliding parameters t and the multipliers lambda of paper 3.4; skinned: the step it
    prescribed), None for the free controller.
    ``body``: a dynamic body's state vector (hairexp/model/dynamic_body.py layout: position,
    velocity, the hair's force on it, the rail's force), None for a keyframed body.
    ``history``: what the integrator carries (hairexp/physics/integrators.py ``History``: BDF2's
    previous x, v and dt, generalized-alpha's accelerations), None for implicit Euler and at the
    start of a run."""

    time: float
    x: np.ndarray   # (V, 3) positions, m
    v: np.ndarray   # (V, 3) velocities, m/s
    tensions: dict = field(default_factory=dict)
    control: object = None
    body: np.ndarray | None = None
    history: object = None

    def copy(self) -> "State":
        return replace(self, x=self.x.copy(), v=self.v.copy(), tensions={k: v.copy() for k, v in self.tensions.items()},
                       body=None if self.body is None else self.body.copy(),
                       history=None if self.history is None else self.history.copy())
