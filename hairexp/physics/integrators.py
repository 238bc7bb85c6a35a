"""Time integrators of the step (``solver.integrator``, default ``trbdf2``), each written as a
minimisation (a multi-stage scheme: one per stage).

Every scheme here advances (x_n, v_n, history) to x_{n+1} by minimising

    G(x) = 1/(2 h^2) |x - x_pred|^2_M + E(y(x)) / (1 - alpha_f),   y(x) = (1 - alpha_f) x + alpha_f x_n,

(E: stretch, bending, gravity, the controller's springs; dissipation potentials see below), and
then sets v_{n+1} = (x_{n+1} - x_ref) / h_v.  A scheme is the tuple (x_pred, h, x_ref, h_v,
alpha_f) it computes from the state: its ``StepPlan``.  dG/dx = M (x - x_pred)/h^2 + grad E(y) = 0
is the scheme's discrete equation of motion; the Hessian is M/h^2 + (1 - alpha_f) hess E(y), PSD
wherever hess E is, so Newton and the SQP (paper 3.4) work unchanged: only the inertia term and
the point where E is evaluated change.  The tracking constraints and the variance penalty act on
the end-of-step positions x in every scheme.

``implicit_euler`` (paper eq. 5, Martin et al. 2011): x_pred = x_n + dt v_n, h = h_v = dt,
x_ref = x_n, alpha_f = 0.  First order; damps every motion (at dt = 0.04 s the hanging chain's
first mode keeps 42 % of its amplitude per period).

``bdf2`` (second-order backward differentiation, used for cloth by Choi and Ko 2002, "Stable but
responsive cloth").  Applied to the first-order system x' = v, M v' = F(x):

    x_{n+1} - a0 x_n + a1 x_{n-1} = beta v_{n+1},    v_{n+1} - a0 v_n + a1 v_{n-1} = beta M^-1 F(x_{n+1}).

Eliminating v_{n+1}: x_{n+1} = x~ + beta^2 M^-1 F(x_{n+1}) with the predictor
x~ = a0 x_n - a1 x_{n-1} + beta (a0 v_n - a1 v_{n-1}), the stationarity condition of
1/(2 beta^2) |x - x~|^2_M + E(x): h = h_v = beta, x_ref = a0 x_n - a1 x_{n-1}.  Constant step:
a0 = 4/3, a1 = 1/3, beta = 2 dt/3.  Variable step (substep recovery halves dt): with
w = dt_n / dt_{n-1}, the quadratic through (t_{n-1}, x_{n-1}), (t_n, x_n), (t_{n+1}, x_{n+1})
differentiated at t_{n+1} gives a0 = (1 + w)^2 / (1 + 2w), a1 = w^2 / (1 + 2w),
beta = dt_n (1 + w) / (1 + 2w) (w = 1: the constant-step values; exact for quadratics,
tests/test_integrator.py).  Zero-stable for w < 1 + sqrt(2); the halving recovery only makes
w = 2^-k (shorter) and w = 2 (back up).  The first step of a run has no history: it is one
implicit Euler step (the standard start; its local error O(dt^2) keeps BDF2 second order).

``trbdf2`` (the default; Bank et al. 1985): a trapezoidal stage to t_n + gamma dt, then the
variable-step BDF2 stage above through (t_n, x_n), (t_n + gamma dt, x_g) to t_{n+1}, gamma = 2 -
sqrt 2.  Second order and L-stable; each stage is a minimisation of G solved by the Simulator as a
step of its own.  See ``TRBDF2`` (what it carries between steps: the end acceleration, constraint
forces included; its restart after a collision stage that moved vertices) and ``Trapezoidal``.

``generalized_alpha`` (Chung and Hulbert 1993, with high-frequency dissipation rho_inf):
Newmark's x_{n+1} = x_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a_{n+1}),
v_{n+1} = v_n + dt ((1 - gamma) a_n + gamma a_{n+1}) with the balance at intermediate points
M ((1 - alpha_m) a_{n+1} + alpha_m a_n) = F(y),  y = (1 - alpha_f) x_{n+1} + alpha_f x_n.
a_{n+1} = (x - x*)/(beta dt^2), x* = x_n + dt v_n + dt^2 (1/2 - beta) a_n, so the balance is the
stationarity of G with h^2 = beta dt^2 / (1 - alpha_m) and
x_pred = x* - alpha_m beta dt^2 a_n / (1 - alpha_m); v_{n+1} = (x - x_ref)/h_v with
h_v = beta dt / gamma, x_ref = x* - h_v (v_n + dt (1 - gamma) a_n).  Parameters:
alpha_m = (2 rho - 1)/(rho + 1), alpha_f = rho/(rho + 1), gamma = 1/2 - alpha_m + alpha_f,
beta = (1 - alpha_m + alpha_f)^2 / 4: second order, unconditionally stable for linear systems,
spectral radius rho at infinite frequency (stiff stretch modes decay by rho per step), minimal
low-frequency dissipation.  ``ALPHA_RHO_INF`` = 0.8: at omega dt = 0.28 (the chain at dt 0.04 s)
the linear analysis gives 99.99 % amplitude per period and +0.69 % period.  It is a one-step
scheme in (x, v, a): a changed dt (substeps) needs no special formula; ``a`` is the history.
The first step starts from a_0 = M^-1 F(x_0, v_0) (the equation of motion at t = 0).
EXPERIMENTAL: on the chain at small amplitude it matches the linear analysis (99.99 %, +0.71 %,
hairexp/evaluation/fidelity_chain.py), but it is not stable on stiff nonlinear motion: with the
stiff stretch springs (omega dt ~ 800 at dt 0.04 s) rotating fast, the energy at the interpolated
point (an edge interpolated between two rotated ends is shorter) and the ringing acceleration
history (stiff modes decay only by rho_inf per step) pump energy in: a chain whose root is swung
0.3 m in 0.25 s gains energy without bound at dt 0.04 and 0.01 s (it agrees with BDF2 at 1 ms),
and goaling needs substeps and fails to converge.  Also tried and dropped (same test): the
alpha_f = 0 member (Wood-Bossak-Zienkiewicz; rho_inf 0.8 blows up, 0.5 is stable there but its
period error is +1.37 % at omega dt 0.28) and generalized-alpha with interpolated forces instead
of positions (blows up at rho_inf 0.6 and 0.8).  BDF2 (rho_inf = 0: L-stable) is the robust one.

Also tried and dropped (2026-12-07, the one-solve scheme the step-cost target of issue 13 asks
for): the theta-method x_{n+1} = x_n + dt ((1 - theta) v_n + theta v_{n+1}),
v_{n+1} = v_n + dt ((1 - theta) a_n + theta a_{n+1}), a minimisation of G with h = h_v = theta dt,
x_pred = x_n + dt v_n + theta (1 - theta) dt^2 a_n, x_ref = x_n + (1 - theta) dt v_n and a_n the
previous step's end acceleration (TR-BDF2's trapezoidal stage is theta = 1/2).  theta = 0.55 meets
both chain targets with one solve (91.6 % amplitude per period, +0.69 % period at dt 0.04 s,
2.38 Newton iterations a step against TR-BDF2's 4.48 and implicit Euler's 2.13; goaling free 3.91
against 5.23 and 3.27), but its stiff modes decay only by (1 - theta)/theta = 0.82 a step, and
goaling tracked goes unstable once the guides stop: from 1.8 s the kinetic energy grows from
1e-3 to 5e-3 J, the edge strain from 1e-4 to 3.7e-3, 26.5 SQP iterations a step (max 422, seven
steps substepped; TR-BDF2 8.21 / 38).  Taking a_n without the constraint forces (the physical
forces at x_{n+1}): 23.1 / 348; with ``tracking.exact_compression``: 57 / 843.  The 90 % target
needs theta <= 0.56 (linear analysis: 90.0 %; 0.58 86.9 %, 0.6 84.0 %), and goaling tracked is
stable only from about 0.58 on: theta 0.56 13.6 / 284, 0.58 5.50 / 40, 0.6 6.02 / 54, 0.7 5.18 / 39.

Dissipation (``EdgeDamping``, ``AirDrag``, hairexp/physics/energies.py) are Rayleigh potentials
R(v) whose force is -dR/dv at the scheme's velocity: each is the potential h_v R((y - y_ref)/h_v)
of the evaluation point y, whose gradient is dR/dv at v = (y - y_ref)/h_v.  With
y_ref = alpha_f x_n + (1 - alpha_f) x_ref - alpha_f h_v v_n that velocity is
(1 - alpha_f) v_{n+1} + alpha_f v_n: the end-of-step velocity of implicit Euler and BDF2
(alpha_f = 0: y_ref = x_ref) and the intermediate velocity of generalized-alpha.
``set_reference(y_ref, h_v)`` sets it each step (the edge direction of the damping is that of y_ref).

The kinematic roots follow the same velocity and history formulas from their prescribed
positions (for BDF2 the second-order backward difference; for generalized-alpha the Newmark
recursion, whose start-up error in the roots' a decays by rho_inf per step, a_0 = 0 there).

Collision stage (after the solve, hairexp/physics/collisions.py): it filters positions and
velocities of the vertices in contact; those vertices take the stage's values.  For BDF2 the
history of those vertices is shifted by the same corrections (x_n += dx, v_n += dv): the
recursion v_{n+1} = a0 v_n - a1 v_{n-1} + ... would otherwise re-inject the removed motion (an
inelastic impulse dv with unchanged history comes out as 1.5 dv after a few steps, a bounce);
shifted, the correction is kept exactly and the differences (the acceleration memory) are kept.
Generalized-alpha keeps a_{n+1} of the solve (x, v, a are independent state there).  The stage
itself works, as under implicit Euler, on the path x_n -> x_{n+1} and its velocity
(x_{n+1} - x_n)/dt: a touched vertex takes that filtered velocity (first order at contacts);
an untouched one keeps the scheme's (touched: moved by > 1e-12 m or its velocity changed by
> 1e-9 m/s, ``TOUCH_TOL_*`` in hairexp/physics/simulator.py).

Velocity filters (``after_velocity_filter``; the hair volume, hairexp/physics/hair_volume.py,
after Petrovic et al. 2005, who filter the grid-smoothed velocities and let the next implicit
solve carry the change into positions): after the last stage of a step the filter changes the
scheme's end velocity v_{n+1} by dv and moves no position.  It is an impulse at t_{n+1} (an
operator split), and each scheme carries it into the next step as it would the start of a motion
that had had the filtered velocity all along:

- implicit Euler: x_pred = x_{n+1} + dt (v_{n+1} + dv), nothing else is carried;
- BDF2: v_n += dv (as after a collision: the recursion keeps the acceleration memory and does
  not re-inject -dv) and x_n -= dt_n dv (the positions' backward difference then also sees
  v_{n+1} + dv: x_ref = a0 x_{n+1} - a1 x_n gains a1 dt_n dv, and x_pred = x_ref + beta (a0 v_{n+1} -
  a1 v_n) gains exactly dt dv in total, as under implicit Euler.  With x_n kept, a free vertex
  would move beta dv = 2/3 dt dv the next step and lag dt dv / 2 behind in the end);
- TR-BDF2: the next trapezoidal stage starts from v_0 = v_{n+1} + dv (x_pred gains gamma dt dv)
  and keeps a_0 = the BDF2 stage's end acceleration.  a_0 is M^-1 F at x_{n+1} (elastic,
  gravity, tracking constraint forces), which the filter does not change since it moves no
  position; the filter is not a force of the model, and adding dv / dt to a_0 would apply it a
  second time through tau^2 a_0.  Only the dissipation in a_0 (edge damping, air drag) was
  evaluated at the unfiltered velocity: the stage's explicit half keeps that, its implicit half
  sees the filtered motion.  No restart either: the restart is for positions a collision moved
  (stretch forces far from the smooth motion); a velocity-only change leaves the state's
  positions and forces smooth.  Measured (2026-12-02, a wisp of 40 x 12 jerked up 12 cm, 25 steps
  with the volume): without the restart the max strain is the run's without hair-hair (2.0e-4)
  at 13.4 Newton iterations a step; restarting after every filtered step gave 7.9 iterations and
  4.6e-5, but 10 x less kinetic energy after 1 s (8.8e-7 against 8.7e-6 J), implicit Euler's
  damping on every step;
- generalized-alpha keeps its a_{n+1} (as after a collision).

Driver discontinuities (``solver.restart_at_jumps``, on by default): a step in which the kinematic
roots' prescribed velocity jumps (a linearly keyed ``scene.motion`` at an inner key, or at its
first or last key where the motion starts or stops; ``RigidMotion.velocity_jumps``: a key in
[t_n, t_n + dt) after t = 0 whose segments on both sides span at least 2 steps, so that keys as
dense as the steps, a USD stage's per-frame time samples, are stepped through as before) is one
implicit Euler step (``Restart``), and the scheme restarts after it (the
next step is its first step: BDF2 and lmm2 start with implicit Euler, TR-BDF2 with an implicit
Euler first stage, generalized-alpha from the equation of motion).  A velocity jump is an impulse
the second-order schemes cannot resolve: it excites the stiff stretch modes, which TR-BDF2's
trapezoidal stage (|r| = 1 on them) carries into the BDF2 stage, whose extrapolation then ends
with nearly every edge compressed (Celia's benchmark jerk, 1.2 m/s from rest at 0.08 s: 7301 of
7525 edges, median strain -1.5e-4; implicit Euler +5e-5), a near-buckling state where the
PSD-clamped Hessian over-estimates the true curvature 3.3 x along the SQP's step and the solve
converges linearly (50 iterations, then substeps; experiments/sqp_curvature.py).  Restarting a
scheme at a discontinuity of its input is the standard remedy (as after a collision stage that
moved vertices); the order is lost there in any case (``tests/test_integrator_order.py``).
Dynamic bodies (simulated, not keyed) are not checked.

The settle phase (hairexp/physics/settle.py) always uses implicit Euler: it exists to reach
the equilibrium under gravity, which implicit Euler's damping reaches fastest, and runs with
different integrators then start from the same state.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hairexp.errors import InputError, choice_name

#: rho_inf of ``generalized_alpha`` (high-frequency spectral radius).
ALPHA_RHO_INF = 0.8


@dataclass(frozen=True)
class History:
    """What a multistep or augmented scheme carries from step to step (``State.history``):
    x, v: (V, 3) the previous step's start positions and velocities and dt its step (BDF2);
    a: (V, 3) accelerations at the state (generalized-alpha)."""

    x: np.ndarray | None = None
    v: np.ndarray | None = None
    dt: float | None = None
    a: np.ndarray | None = None
    restart: bool = False   # TR-BDF2: the last step's collision stage moved vertices (see TRBDF2)
    a_prev: np.ndarray | None = None   # lmm2: the acceleration at the previous step's start
    calm: int = 0                      # lmm2: steps since its last restart

    def copy(self) -> "History":
        c = lambda z: None if z is None else z.copy()   # noqa: E731
        return replace(self, x=c(self.x), v=c(self.v), a=c(self.a), a_prev=c(self.a_prev))


@dataclass
class StepPlan:
    """One step of a scheme: G(x) = |x - x_pred|^2_M / (2 h^2) + E(y)/(1 - alpha_f),
    v_{n+1} = (x - x_ref)/h_v, dissipation reference (y_ref, h_v) (see module doc).
    All arrays (V, 3)."""

    x_pred: np.ndarray
    h: float
    x_ref: np.ndarray
    h_v: float
    alpha_f: float = 0.0
    y_ref: np.ndarray | None = None   # None: x_ref
    x_star: np.ndarray | None = None  # generalized-alpha: Newmark's x*
    note: str = ""                    # "start": a first step without history


class ImplicitEuler:
    """Paper eq. (5)."""

    name = "implicit_euler"
    #: how a dynamic body's position advances under this scheme (``DynamicBody.advance``): 1 is
    #: symplectic Euler, the displacement this scheme gives hair under a constant acceleration
    body_theta = 1.0
    #: the lightest dynamic body (block plus roots, over the free hair it carries) whose staggered
    #: coupling (hairexp/model/dynamic_body.py) is stable under this scheme, measured on the
    #: stylization wisp in free fall with a coupling force one hair weight wrong: implicit Euler
    #: decays at 1.5 x; bdf2 grows at 3 x and decays slowly at 5 x; trbdf2 oscillates without
    #: decaying at 2 x and decays at 3 x (stylization's block is 23 x)
    min_body_ratio = 1.0

    def plan(self, sim, state, dt: float) -> StepPlan:
        return StepPlan(state.x + dt * state.v, dt, state.x, dt)

    def velocity(self, x_new, state, plan: StepPlan) -> np.ndarray:
        return (x_new - plan.x_ref) / plan.h_v

    def history(self, state, x_new, v_new, plan: StepPlan, dt: float):
        return None

    def after_collision(self, state, history, dx, dv, touched):
        return history

    def after_velocity_filter(self, state, history, dv):
        """A velocity filter (the hair volume) changed the end velocities by dv (V, 3) and moved
        no position (module doc, "Velocity filters"): nothing is carried here."""
        return history


class Restart(ImplicitEuler):
    """One implicit Euler step at a driver discontinuity (module doc, "Driver discontinuities"):
    whatever the scheme, what it carries to the next step is the restart mark, so the next step is
    the scheme's first step (``History.restart``; a History without x, v or a)."""

    name = "restart"

    def history(self, state, x_new, v_new, plan, dt):
        return History(restart=True)

    def after_collision(self, state, history, dx, dv, touched):
        return History(restart=True)

    def after_velocity_filter(self, state, history, dv):
        return History(restart=True)


def bdf2_coefficients(w: float) -> tuple[float, float, float]:
    """(a0, a1, beta/dt) of variable-step BDF2 for the step ratio w = dt_n / dt_{n-1}."""
    return (1 + w) ** 2 / (1 + 2 * w), w * w / (1 + 2 * w), (1 + w) / (1 + 2 * w)


class BDF2(ImplicitEuler):
    name = "bdf2"
    min_body_ratio = 5.0

    def plan(self, sim, state, dt: float) -> StepPlan:
        h = state.history
        if h is None or h.x is None:   # the first step: implicit Euler
            p = super().plan(sim, state, dt)
            p.note = "start"
            return p
        a0, a1, b = bdf2_coefficients(dt / h.dt)
        beta = b * dt
        x_ref = a0 * state.x - a1 * h.x
        return StepPlan(x_ref + beta * (a0 * state.v - a1 * h.v), beta, x_ref, beta)

    def history(self, state, x_new, v_new, plan, dt):
        return History(x=state.x, v=state.v, dt=dt)

    def after_collision(self, state, history, dx, dv, touched):
        if history is None or not touched.any():
            return history
        return replace(history, x=history.x + dx, v=history.v + dv)

    def after_velocity_filter(self, state, history, dv):
        """v_n += dv, x_n -= dt_n dv (module doc, "Velocity filters")."""
        if history is None or history.x is None:
            return history
        return replace(history, x=history.x - history.dt * dv, v=history.v + dv)


class GeneralizedAlpha(ImplicitEuler):
    name = "generalized_alpha"

    def __init__(self, rho_inf: float = ALPHA_RHO_INF):
        r = float(rho_inf)
        self.rho_inf = r
        self._set((2 * r - 1) / (r + 1), r / (r + 1))

    def _set(self, alpha_m: float, alpha_f: float) -> None:
        self.alpha_m, self.alpha_f = alpha_m, alpha_f
        self.gamma = 0.5 - self.alpha_m + self.alpha_f
        self.beta = 0.25 * (1 - self.alpha_m + self.alpha_f) ** 2

    def plan(self, sim, state, dt: float) -> StepPlan:
        h = state.history
        a = sim.accelerations(state) if h is None or h.a is None else h.a
        b, g, am, af = self.beta, self.gamma, self.alpha_m, self.alpha_f
        x_star = state.x + dt * state.v + dt * dt * (0.5 - b) * a
        x_pred = x_star - (am * b * dt * dt / (1 - am)) * a
        h_v = b * dt / g
        x_ref = x_star - h_v * (state.v + dt * (1 - g) * a)
        y_ref = af * state.x + (1 - af) * x_ref - af * h_v * state.v
        return StepPlan(x_pred, float(np.sqrt(b / (1 - am))) * dt, x_ref, h_v, af, y_ref, x_star,
                        "start" if h is None or h.a is None else "")

    def history(self, state, x_new, v_new, plan, dt):
        return History(a=(x_new - plan.x_star) / (self.beta * dt * dt))


#: gamma of TR-BDF2 (Bank et al. 1985): 2 - sqrt(2) makes both stages' Jacobians equal and the
#: scheme L-stable.
TRBDF2_GAMMA = 2.0 - np.sqrt(2.0)


class Trapezoidal(ImplicitEuler):
    """The first stage of TR-BDF2: the trapezoidal rule over a stage of length dt,
    x_1 - x_0 = dt/2 (v_0 + v_1),  M (v_1 - v_0) = dt/2 (F_0 + F(x_1, v_1)).
    Eliminating v_1 with tau = dt/2: x_1 = x_0 + dt v_0 + tau^2 a_0 + tau^2 M^-1 F(x_1), the
    stationarity condition of G with x_pred = x_0 + dt v_0 + tau^2 a_0, h = tau;
    v_1 = (x_1 - x_0)/tau - v_0, i.e. x_ref = x_0 + tau v_0, h_v = tau.

    a_0 = M^-1 F_0 is the total acceleration at the stage's start: the one the previous step's
    BDF2 stage ended with (``History.a``, constraint forces of a tracked run included), else
    (the first step of a run) M^-1 F(x_0, v_0) from ``Simulator.accelerations``.  Taking the
    constraint forces from the previous step matters: without them the stage treats the hair's
    tracking constraints as if they had exerted no force at x_0, and the SQP ran out of
    iterations on goaling tracked from the stop on (65-100 iterations a step).  Its history is the stage's start (x_0, v_0, dt): the BDF2
    stage that follows reads it."""

    name = "trapezoidal"
    body_theta = 0.5   # exact for a constant acceleration, as this stage is

    def plan(self, sim, state, dt: float) -> StepPlan:
        tau = 0.5 * dt
        h = state.history
        a0 = h.a if h is not None and h.a is not None else sim.accelerations(state)
        return StepPlan(state.x + dt * state.v + tau * tau * a0, tau, state.x + tau * state.v, tau)

    def history(self, state, x_new, v_new, plan, dt):
        return History(x=state.x, v=state.v, dt=dt)

    after_collision = BDF2.after_collision


class _StageEuler(ImplicitEuler):
    """Implicit Euler as TR-BDF2's restart stage: its history is the stage's start, as the
    trapezoidal stage's (the BDF2 stage reads it)."""

    history = Trapezoidal.history
    after_collision = BDF2.after_collision


class _StageBDF2(BDF2):
    """TR-BDF2's second stage: BDF2 through the stage's start and the first stage's end.  Its
    history is the step's end acceleration a = (x - x_pred)/h^2 (the scheme's own: the discrete
    equation of motion M (x - x_pred)/h^2 = F(x) + constraint forces), the next trapezoidal
    stage's a_0; after a collision stage that moved vertices it is only the restart mark."""

    body_theta = 0.5   # exact for a constant acceleration (the plain BDF2 keeps symplectic Euler)

    def history(self, state, x_new, v_new, plan, dt):
        return History(a=(x_new - plan.x_pred) / plan.h ** 2)

    def after_collision(self, state, history, dx, dv, touched):
        return History(restart=True) if touched.any() else history

    def after_velocity_filter(self, state, history, dv):
        """The end acceleration stays the next trapezoidal stage's a_0, and no restart (module
        doc, "Velocity filters")."""
        return history


class TRBDF2:
    """TR-BDF2 (Bank et al. 1985; Hosea and Shampine 1996): a trapezoidal stage to
    t_n + gamma dt, then the variable-step BDF2 step through (t_n, x_n), (t_n + gamma dt, x_g)
    to t_{n+1} (step ratio w = (1 - gamma)/gamma; with gamma = 2 - sqrt(2) its coefficients are
    a0 = 1/(gamma (2 - gamma)), a1 = (1 - gamma)^2/(gamma (2 - gamma)), beta = (1 - gamma) dt/(2 - gamma),
    the textbook TR-BDF2).  Second order, L-stable (stiff stretch modes decay: |r| -> 0), and
    at omega dt = 0.28 (the chain at dt 0.04 s) the linear analysis gives 99.95 % amplitude per
    period and +0.3 % period error, against BDF2's 97 % and +2.5 %.  Two solves per step, each
    a stage of the step handled as a step of its own by the Simulator (controller, collision
    stage, dynamic body).  What it carries to the next step (``History``): the end
    acceleration (the next trapezoidal stage's a_0), or the restart mark.

    Restart: after a step whose collision stage moved vertices, the first stage is implicit
    Euler instead of the trapezoidal rule.  The trapezoidal stage takes half of its force
    explicitly, and a state the collision stage (or the strain limiter) displaced carries
    stretch forces far from the smooth motion, which the trapezoidal rule (|r| = 1 on stiff
    modes) does not damp: measured on goaling free with cubic keys at dt 0.04 s, the hair hit the
    wheel and the strain grew to 150 within two steps.  Restarting a scheme at a discontinuity
    is the standard remedy; it makes that one step first order, as the collision stage is
    anyway.  The BDF2 stage then uses the same formula (variable step, ratio (1 - gamma)/gamma).

    Cost (issue 13 asks <= 1.3 x implicit Euler's step): each stage's solve costs about what
    implicit Euler's one does (goaling at dt 0.04 s: 3.50 and 3.34 Newton iterations against
    3.30 a step; tracked 4.48 and 3.91 SQP iterations against 3.20), so a step costs about 2.05 x
    free and 2.5 x tracked.  Measured and not worth it (reports/trbdf2_cost.md): first iterates
    from the history (x_pred + tau^2 a_0, x_pred + beta^2 a_g, x_0 + h v_0, extrapolated
    positions: -0.23 to +0.89 iterations a step), warm starts from the converged stage (-0.05 free,
    -0.14 tracked), and the first stage's Hessian in the BDF2 stage (same M/h^2): as its first
    direction 3.34 -> 7.05 iterations, as every direction (chord) most steps do not converge.
    Even a first iterate 100 x closer than x_pred leaves 2.2 (free) and 2.7 (tracked) iterations
    a stage: the stiff stretch springs, not the predictor, set the count.  A looser first stage
    (2026-12-06, section 6 of the report: its rtol 0.3, the BDF2 stage's 1e-5) saves about one
    evaluation a step (evaluations ratio 1.85 -> 1.61 free, 2.01 -> 1.78 tracked; end positions
    within 2.4e-5 m of the converged run's), still far from 1.3; stopping it after one iteration
    (a linearly implicit trapezoidal stage) diverges: 34.6 (free) and 48.6 (tracked) iterations in
    the BDF2 stage, 0.29-0.51 m off, since the trapezoidal rule (|r| = 1) does not damp the stiff
    modes its unconverged solve leaves."""

    name = "trbdf2"
    gamma = TRBDF2_GAMMA
    min_body_ratio = 3.0

    def __init__(self):
        self.tr, self.bdf2, self.ie = Trapezoidal(), _StageBDF2(), _StageEuler()

    @property
    def final_stage(self):
        """The scheme of a step's last stage (what a state's velocity comes from)."""
        return self.bdf2

    def stages(self, state, dt: float):
        """[(stage scheme, stage length)] of the step from ``state``."""
        restart = state.history is not None and state.history.restart
        first = self.ie if restart else self.tr
        return [(first, self.gamma * dt), (self.bdf2, (1.0 - self.gamma) * dt)]


#: lmm2's coefficients (alpha_0, alpha_1, alpha_2), (beta_0, beta_1, beta_2) (see ``LMM2``)
LMM2_ALPHA = (-0.175, -0.825, 1.0)
LMM2_BETA = (0.125, 0.5125, 0.5375)
#: lmm2's BDF2 steps after a restart (see ``LMM2``)
LMM2_CALM_STEPS = 3


class LMM2(BDF2):
    """EXPERIMENTAL: a two-step, second-order, A-stable linear multistep method with one solve
    a step, applied to x' = v, M v' = F(x) as BDF2 is:

        sum_j alpha_j x_{n+j} = dt sum_j beta_j v_{n+j},   sum_j alpha_j v_{n+j} = dt sum_j beta_j a_{n+j}

    (j = 0, 1, 2; alpha_2 = 1).  Eliminating v_{n+2} (as for BDF2): x_{n+2} = x~ + h^2 M^-1 F(x_{n+2})
    with h = h_v = beta_2 dt, x_ref = -alpha_1 x_{n+1} - alpha_0 x_n + dt (beta_1 v_{n+1} + beta_0 v_n),
    x~ = x_ref + h (-alpha_1 v_{n+1} - alpha_0 v_n + dt (beta_1 a_{n+1} + beta_0 a_n)): the
    stationarity of G, so Newton and the SQP work unchanged.  The accelerations a are the scheme's
    own (x - x~)/h^2 at the end of each step (constraint forces included, as TR-BDF2's a_0).
    Unlike BDF2 (beta_0 = beta_1 = 0, the only order-2 member with no old forces) the old forces
    buy phase accuracy: the coefficients ``LMM2_ALPHA``/``LMM2_BETA`` (rho(z) = (z - 1)(z + 0.175),
    beta from the order-2 conditions with beta_0 = 0.125) are A-stable, and the linear analysis
    at omega dt = 0.28 (the chain at dt 0.04 s) gives 99.85 % amplitude per period and +0.91 %
    period, with stiff modes decaying by |r_inf| = 0.48 a step (BDF2: 97 %, +2.5 %, 0; the
    trapezoidal rule 100 %, +0.7 %, 1).  Within this family, period error and stiff damping trade
    against each other (Dahlquist's second barrier: +0.8 % needs |r_inf| 0.65, +1.2 % 0.37).
    Constant step only: a changed dt (substep recovery), a collision stage that moved vertices
    or a velocity filter restart it with one implicit Euler step (first order there), followed by
    ``LMM2_CALM_STEPS`` (3) constant-step BDF2 steps (L-stable) before the two-step method
    resumes: without them, the stiff modes a contact and the strain limiter excite rang on at
    0.48 a step after the contact ended, and splitting's 3-guide run took 12.8 SQP iterations a
    step (max 99, one step unconverged, the clumps [20, 16, 8] instead of [16, 16, 16]); with
    them 3.9 (BDF2: 3.9).  Members with stronger stiff damping did not need them only at a
    period error the chain target refuses (|r_inf| 0.25: 4.6 iterations, +1.4 % period).

    Measured (2026-12-03, README "Time integrators"): one solve a step makes it cheap (goaling
    3.7 / 4.1 Newton / SQP iterations a step against TR-BDF2's 5.9 / 7.6; the Celia benchmark
    7.2 SQP iterations a step against 23.9), but its error constant is larger than TR-BDF2's:
    goaling free at dt 0.04 s is 5.95 % of the hair length RMS from the reference (TR-BDF2 2.57 %,
    BDF2 8.7 %).  No A-stable linear multistep method does better than the trapezoidal rule's
    error constant (Dahlquist's second barrier), so a one-solve scheme of this kind cannot reach
    TR-BDF2's accuracy at dt 0.04 s."""

    name = "lmm2"
    min_body_ratio = 5.0

    #: steps of BDF2 (L-stable) after a restart before the two-step method resumes
    calm_steps = LMM2_CALM_STEPS

    def plan(self, sim, state, dt: float) -> StepPlan:
        h = state.history
        if h is None or h.x is None or h.a is None or h.dt is None or abs(h.dt - dt) > 1e-12 * dt:
            p = ImplicitEuler.plan(self, sim, state, dt)   # the first step, a changed dt or a restart
            p.note, p.a_start, p.calm = "start", None, 0
            return p
        if h.calm < self.calm_steps or h.a_prev is None:   # BDF2 (constant step) while calming down
            p = BDF2.plan(self, sim, state, dt)
        else:
            (a0, a1, _), (b0, b1, b2) = LMM2_ALPHA, LMM2_BETA
            x_ref = -a1 * state.x - a0 * h.x + dt * (b1 * state.v + b0 * h.v)
            v_ref = -a1 * state.v - a0 * h.v + dt * (b1 * h.a + b0 * h.a_prev)
            hh = b2 * dt
            p = StepPlan(x_ref + hh * v_ref, hh, x_ref, hh)
        p.a_start, p.calm = h.a, h.calm + 1
        return p

    def history(self, state, x_new, v_new, plan, dt):
        """The step's start (x, v, dt), its end acceleration (the scheme's own, constraint forces
        included), the start's acceleration and the steps since the last restart."""
        return History(x=state.x, v=state.v, dt=dt, a=(x_new - plan.x_pred) / plan.h ** 2, a_prev=plan.a_start,
                       calm=plan.calm)

    def after_collision(self, state, history, dx, dv, touched):
        return History(restart=True) if touched.any() else history

    def after_velocity_filter(self, state, history, dv):
        return History(restart=True)


#: ``solver.integrator``'s default: the only scheme here that meets both of issue 13's targets on
#: the hanging chain at dt 0.04 s (reports/fidelity.md) and is robust on every scene and stress
#: case (reports/stress_trbdf2.md, reports/integrator_verdicts.md); README "Time integrators".
DEFAULT_INTEGRATOR = "trbdf2"

#: solver.integrator -> scheme
INTEGRATORS = {"implicit_euler": ImplicitEuler, "bdf2": BDF2, "trbdf2": TRBDF2,
               "generalized_alpha": GeneralizedAlpha, "lmm2": LMM2}


def make_integrator(name: str):
    """The scheme named by ``solver.integrator`` (InputError naming the key if unknown)."""
    name = choice_name(name)
    if name not in INTEGRATORS:
        raise InputError(f"unknown integrator {name!r} (one of {', '.join(INTEGRATORS)})", "solver.integrator")
    return INTEGRATORS[name]()
