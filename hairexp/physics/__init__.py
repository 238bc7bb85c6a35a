"""The hair's physics and the time step: energies and their derivatives (``terms``,
``energies``), the implicit Euler objective (eq. 5, ``objective``), Newton (``newton``), the
collision stage (``collisions``, ``edge_ccd``), the settle phase (``settle``), the step
schedule (``schedule``), the Controller interface the step calls (``controller``), the typed
per-step ``State`` (``state``), info records (``info``) and the step itself (``simulator``)."""

from hairexp.physics.controller import Controller
from hairexp.physics.info import SolveInfo, Status, StepInfo
from hairexp.physics.simulator import Simulator
from hairexp.physics.state import State

__all__ = ["Controller", "Simulator", "SolveInfo", "State", "Status", "StepInfo"]
