"""Info records returned by the solvers.  Pure data: sinks turn them into metrics."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum


class Status(str, Enum):
    """How a solve (and a step) ended; the metrics table's ``status`` column holds the value."""

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    LINE_SEARCH_FAILED = "line_search_failed"
    DIVERGED = "diverged"
    SINGULAR = "singular"   # the step's linear system could not be solved (a singular KKT matrix)

    def __str__(self) -> str:
        return self.value


CONVERGED, MAX_ITERATIONS, LINE_SEARCH_FAILED, DIVERGED = (Status.CONVERGED, Status.MAX_ITERATIONS,
                                                           Status.LINE_SEARCH_FAILED, Status.DIVERGED)
SINGULAR = Status.SINGULAR


@dataclass
class SolveInfo:
    """One nonlinear solve (Newton or SQP) over one time step of size ``dt``."""

    status: Status = CONVERGED
    iterations: int = 0
    backtracks: int = 0
    grad_norm: float = 0.0          # final |grad H| (free) or |grad L| (SQP)
    force_scale: float = 0.0        # what the gradient is compared against
    constraint_norm: float = 0.0    # SQP only: max |C|
    secant_updates: int = 0         # SQP only: iterations whose Hessian model got the secant correction
    seconds: dict = field(default_factory=lambda: {"derivatives": 0.0, "assembly": 0.0, "solve": 0.0})
    tensions: dict = field(default_factory=dict)   # final stretch dual iterates (warm start of the next step)
    collision: object = None        # CollisionInfo of the collision stage that followed, if it ran
    restart: bool = False           # an implicit Euler step at a driver's velocity jump (solver.restart_at_jumps)

    @property
    def converged(self) -> bool:
        return self.status == CONVERGED


@dataclass
class StepInfo:
    """One time step as the integrator took it: possibly several substeps after a failure."""

    time: float                      # end-of-step time (s)
    dt: float
    status: Status
    iterations: int                  # summed over the substeps that make up the accepted step
    backtracks: int
    substeps: int                    # 1 unless recovery split the step
    grad_norm: float
    force_scale: float
    constraint_norm: float = 0.0
    recovered: bool = False          # a failed attempt was replaced by substeps or by a last attempt with more iterations
    object_contacts: int = 0         # collision stage: vertices corrected against colliders
    hair_contacts: int = 0           # collision stage: edge pairs given impulses
    penetration_max: float = 0.0     # m, after the collision stage
    collider_contacts: dict = field(default_factory=dict)   # collider name -> vertices corrected
    seconds: dict = field(default_factory=dict)   # derivatives, assembly, solve, collision, other, total
    iterations_attempted: int = 0    # all iterations done, including attempts that recovery replaced
    restarts: int = 0                # (sub)steps taken as implicit Euler at a driver's velocity jump
    restored: int = 0                # rounds that moved the hair back onto the controller's constraints after the collision stage
    contact_planes: int = 0          # contact planes of the second solve (collision.resolve), summed over substeps
    resolve_fallbacks: int = 0       # (sub)steps whose second solve failed: the collision stage's result stood

    @property
    def converged(self) -> bool:
        return self.status == CONVERGED
