"""Newton's method on the implicit Euler objective (eq. 5): the free step.

Each iteration assembles the PSD Hessian in banded storage, solves with a banded Cholesky
(``ImplicitEulerObjective.solve``: per strand in numba with ``solver.kernels=numba``, else
``scipy.linalg.solveh_banded``; the Hessian is block diagonal over strands with half-bandwidth 8), and backtracks along the Newton direction until the Armijo condition
holds.  Convergence: |grad H| <= atol + rtol * (|f_inertia| + |f_internal| + |f_external|),
i.e. the residual force is small relative to the forces acting.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hairexp.physics.assembly import banded_solve  # noqa: F401  (re-exported: the LAPACK solve)
from hairexp.physics.info import CONVERGED, DIVERGED, LINE_SEARCH_FAILED, MAX_ITERATIONS, SolveInfo
from hairexp.physics.objective import ImplicitEulerObjective

#: Armijo sufficient-decrease constant (Nocedal & Wright, eq. 3.4).
ARMIJO_C1 = 1e-4
#: Step shrink factor of the backtracking line search.
BACKTRACK = 0.5


@dataclass
class NewtonOptions:
    rtol: float = 1e-5
    atol: float = 1e-10
    max_iterations: int = 30
    max_backtracks: int = 30


def line_search(value_fn, x: np.ndarray, p: np.ndarray, f0: float, slope: float, max_backtracks: int,
                noise: float = 0.0, alpha0: float = 1.0):
    """Backtracking Armijo search on ``value_fn`` from x along p (slope = grad . p < 0).

    ``noise``: the round-off of the values.  Near convergence the predicted decrease drops
    below it and a strict Armijo test would reject good Newton steps (seen as a stall at
    |grad|/F ~ 1e-7 with steps of 1e-9); a value within ``noise`` of the Armijo bound passes.
    ``alpha0``: the first trial step (the contact barrier's collision-free bound, <= 1).
    Returns (alpha, new value, backtracks, the accepted point x + alpha p) or (0, f0, n, x) if no
    decrease was found."""
    alpha = alpha0
    for k in range(max_backtracks + 1):
        x_new = x + alpha * p
        f = value_fn(x_new)
        if np.isfinite(f) and f <= f0 + ARMIJO_C1 * alpha * slope + noise:
            return alpha, f, k, x_new
        alpha *= BACKTRACK
    return 0.0, f0, max_backtracks, x


def _evaluate(obj, x: np.ndarray, want_step: bool = True):
    """(evaluation, Newton step or None): the objective's fused pass where it has one
    (``ImplicitEulerObjective.evaluate_step``) and the step is likely needed, else its evaluation
    (the step solved after, if needed).  Where the step is likely not needed (the iterate is
    predicted to converge) and the objective has the fused pass (``fuses``), the gradient alone
    (``banded`` None, the cheaper half of the pass: no band to zero, fill and factor); the caller
    takes the fused pass after it if the iterate did not converge (``newton_solve``)."""
    step = getattr(obj, "evaluate_step", None)
    if step is None:
        return obj.evaluate(x, need_hessian=True), None
    if not want_step:
        return obj.evaluate(x, need_hessian=not getattr(obj, "fuses", False)), None
    return step(x)


def likely_converged(norms: list, alpha: float, tol: float) -> bool:
    """Whether the next iterate's gradient norm is predicted below ``tol``: after a full step, by
    quadratic convergence from the last two norms, g_next = g_k (g_k / g_k-1)^2.  Only chooses
    between the fused pass and evaluate + solve (the same results); a wrong guess costs time only:
    a factorisation for nothing, or the unfused pass."""
    if alpha != 1.0 or len(norms) < 2 or not norms[-2] > 0.0:
        return False
    r = norms[-1] / norms[-2]
    return norms[-1] * r * r <= tol


def newton_solve(obj: ImplicitEulerObjective, x0: np.ndarray, opts: NewtonOptions) -> tuple[np.ndarray, SolveInfo]:
    info = SolveInfo()
    x = x0.copy()
    ev, p = _evaluate(obj, x)
    f = obj.value(x)   # after evaluate: the contact's friction lag is set there
    sec = info.seconds
    norms = []
    while True:
        for k in ("derivatives", "assembly"):
            sec[k] += ev.seconds[k]
        gnorm = float(np.linalg.norm(ev.grad))
        norms.append(gnorm)
        info.grad_norm, info.force_scale = gnorm, ev.force_scale
        if not (np.isfinite(gnorm) and np.isfinite(f)):
            info.status = DIVERGED
            return x, info
        if gnorm <= opts.atol + opts.rtol * ev.force_scale:
            info.status = CONVERGED
            info.tensions = obj.final_tensions(x)
            return x, info
        if info.iterations >= opts.max_iterations:
            info.status = MAX_ITERATIONS
            return x, info
        step_ev = ev   # the evaluation the step is solved from
        if p is None and ev.banded is None:
            # a gradient-only evaluation, and not converged: the fused pass at x (its gradient is
            # ev's bit for bit, and so is the step evaluate + solve would give), or, where it falls
            # back to ``evaluate`` (no step), the step solved from that evaluation's band below
            step_ev, p = obj.evaluate_step(x)
            for k in ("derivatives", "assembly"):
                sec[k] += step_ev.seconds[k]
        if p is None:
            t0 = time.perf_counter()
            p = obj.solve(step_ev.banded, -step_ev.grad)
            sec["solve"] += time.perf_counter() - t0
        slope = float(np.dot(ev.grad, p))
        if not np.isfinite(slope):
            info.status = DIVERGED
            return x, info
        alpha, f_new, bt, x_new = line_search(obj.value, x, p, f, slope, opts.max_backtracks, obj.value_noise,
                                              obj.max_step(x, p))
        info.backtracks += bt
        info.iterations += 1
        if alpha == 0.0:
            info.status = LINE_SEARCH_FAILED
            return x, info
        obj.update_tensions(x, alpha * p)
        x = x_new   # x + alpha * p, as the line search took it
        f = f_new
        # gradient and Hessian together: a separate gradient-only check would repeat most of
        # the derivative work on every iterate that is not yet converged
        ev, p = _evaluate(obj, x, not likely_converged(norms, alpha, opts.atol + opts.rtol * ev.force_scale))
        if obj.contact is not None and getattr(obj.contact, "lagged", True):
            f = obj.value(x)   # the contact's friction lag moved with the evaluation
