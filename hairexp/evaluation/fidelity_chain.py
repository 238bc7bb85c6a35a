"""Integrator fidelity on a hanging chain (issue 13): how much of a free swing a time integrator
keeps per period, and how far its period is off.

The chain: one strand of ``n_vertices`` (30 cm, 20 vertices by default), soft bending, no
damping, hanging straight down from a root (two kinematic vertices) in its exact static
equilibrium (each edge stretched by the weight below it).  The root moves sideways by
``swing`` (m) along a smooth step (a clamped cubic, zero velocity at both ends) over
``swing_time`` seconds and then stays put; from then on the chain swings freely.

Measured: the chain's first pendulum mode amplitude q(t), the mass-weighted projection of the
free vertices' sideways displacement (relative to the root) on the first mode shape of the
linearised model (so the higher modes the root motion also excites do not disturb the fit),
fitted with q = A exp(-sigma t) cos(omega_d t + phi) + c over ``periods`` periods after the
release.  Returned: amplitude kept per period exp(-sigma T), damping ratio
sigma / sqrt(sigma^2 + omega_d^2), period T = 2 pi / omega_d.

References: ``period_linear``, the first mode of the linearised model (generalized eigenproblem
K phi = omega^2 M phi, K the exact Hessian of stretch + bending + gravity at the equilibrium:
the discrete pendulum chain with its stretch and bending); ``period_continuum``, the heavy
hanging chain (Bernoulli/Euler: omega_1 = (j_01 / 2) sqrt(g / L), j_01 = 2.4048, the first zero
of J_0).  ``linear_prediction`` gives each integrator's amplification on the 1-DOF oscillator
x'' = -omega^2 x at omega dt (the linear analysis of hairexp/physics/integrators.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
import torch

from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Material, Scene
from hairexp.model.strands import Strands
from hairexp.physics.energies import Bending, Stretch
from hairexp.physics.integrators import LMM2_ALPHA, LMM2_BETA, TRBDF2_GAMMA, GeneralizedAlpha, bdf2_coefficients
from hairexp.physics.simulator import Simulator

#: first zero of the Bessel function J_0
J01 = 2.404825557695773
GRAVITY = 9.81


@dataclass
class ChainSolver:
    """The solver settings of the measurement (the fields ``Simulator`` reads; tight tolerances)."""

    integrator: str = "implicit_euler"
    rtol: float = 1e-7
    atol: float = 1e-12
    max_iterations: int = 50
    max_backtracks: int = 30
    derivatives: str = "closed_form"
    stretch_hessian: str = "primal_dual"
    compile: str = "off"
    on_failure: str = "substep"
    max_substep_levels: int = 4


@dataclass
class ChainFidelity:
    integrator: str
    dt: float
    amplitude_per_period: float    # exp(-sigma T): fraction of the amplitude kept per period
    damping_ratio: float
    period: float                  # s, measured
    period_linear: float           # s, first mode of the linearised discrete chain
    period_continuum: float        # s, heavy hanging chain 4 pi / (j01 sqrt(g/L))
    omega_dt: float                # omega_linear * dt
    steps: int
    iterations: int                # Newton iterations over the measured run

    @property
    def period_error(self) -> float:
        """Relative period error against the linearised chain."""
        return self.period / self.period_linear - 1.0


def chain_scene(length: float = 0.3, n_vertices: int = 20, linear_density: float = 2e-4,
                stretch_stiffness: float = 20.0, bending_stiffness: float = 1e-9,
                swing: float = 0.01, swing_time: float = 0.4) -> Scene:
    """The hanging chain in its static equilibrium, its root swung sideways (+x) by ``swing``."""
    l0 = length / (n_vertices - 1)
    rest = np.zeros((n_vertices, 3))
    rest[:, 1] = -l0 * np.arange(n_vertices)
    strands = Strands.from_polylines(rest, np.array([n_vertices]), linear_density, where="chain")
    # equilibrium: edge e carries the weight of every vertex below it
    below = np.cumsum(strands.masses[::-1])[::-1]           # mass at and below each vertex
    tension = GRAVITY * below[1:]                            # edge e = (e, e+1)
    lengths = l0 * (1.0 + tension / stretch_stiffness)
    x0 = np.zeros_like(rest)
    x0[1:, 1] = -np.cumsum(lengths)
    motion = RigidMotion(np.array([0.0, swing_time]), np.array([[0.0, 0.0, 0.0], [swing, 0.0, 0.0]]),
                         np.zeros((2, 3)), "cubic", where="chain swing")
    mat = Material(linear_density, stretch_stiffness, bending_stiffness)
    return Scene("hanging_chain", strands, mat, motion, np.array([0.0, -GRAVITY, 0.0]), x0.copy(), initial=x0)


def linearised(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, M_diag, free vertices): the exact Hessian of stretch + bending at the chain's
    equilibrium over the free DOFs (gravity is linear: no Hessian) and the lumped masses."""
    s, m = scene.strands, scene.material
    x0 = torch.tensor(scene.initial_positions(), dtype=torch.float64)   # a copy: the scene's arrays are read-only
    free = np.flatnonzero(~s.kinematic)
    terms = [Stretch(s.edges, s.rest_lengths, m.stretch_stiffness), Bending(s.bends, s.rest, m.bending_stiffness)]

    def energy(xf):
        x = x0.clone()
        x[free] = xf.reshape(-1, 3)
        return sum(t.total(x) for t in terms)

    K = torch.autograd.functional.hessian(energy, x0[free].reshape(-1)).numpy()
    return K, np.repeat(s.masses[free], 3), free


def first_mode(scene: Scene) -> tuple[float, np.ndarray]:
    """(omega, mass-normalised sideways (x) shape over the free vertices) of the linearised chain."""
    K, Md, _ = linearised(scene)
    w2, vecs = scipy.linalg.eigh(K, np.diag(Md))
    # the two lowest modes are the degenerate sideways (x, z) pendulum modes: take the x one
    for k in range(len(w2)):
        phi = vecs[:, k].reshape(-1, 3)
        if np.abs(phi[:, 0]).sum() > 10 * np.abs(phi[:, 1:]).sum():
            return float(np.sqrt(w2[k])), phi[:, 0]
    raise RuntimeError("no sideways mode found")


def _fit(t: np.ndarray, q: np.ndarray, omega0: float):
    """(A, sigma, omega_d, phi, c) of q = A exp(-sigma t) cos(omega_d t + phi) + c."""
    c0 = float(np.mean(q))
    qc = q - c0
    # initial phase and amplitude from a linear least-squares fit at omega0 without decay
    B = np.stack([np.cos(omega0 * t), np.sin(omega0 * t)], 1)
    (a, b), *_ = np.linalg.lstsq(B, qc, rcond=None)
    A0, phi0 = math.hypot(a, b), math.atan2(-b, a)

    def f(tt, A, sig, om, ph, c):
        return A * np.exp(-sig * tt) * np.cos(om * tt + ph) + c

    p, _ = scipy.optimize.curve_fit(f, t, q, p0=[A0, 0.1, omega0, phi0, c0], maxfev=20000)
    if p[0] < 0:
        p[0], p[3] = -p[0], p[3] + math.pi
    return p


def linear_prediction(integrator: str, omega_dt: float) -> tuple[float, float]:
    """(amplitude kept per period, relative period error) of ``integrator`` on x'' = -omega^2 x
    at omega dt: from the eigenvalues of the one-step map of the scheme's state."""
    W = float(omega_dt)
    if integrator == "implicit_euler":          # x1 = c (x0 + v0), v1 = x1 - x0 (dt = 1)
        c = 1.0 / (1.0 + W * W)
        A = np.array([[c, c], [c - 1.0, c]])
    elif integrator == "bdf2":                   # state (x_n, x_{n-1}, v_n, v_{n-1}), dt = 1
        b = 2.0 / 3.0
        c = 1.0 / (1.0 + b * b * W * W)
        r1 = c * np.array([4 / 3, -1 / 3, b * 4 / 3, -b / 3])
        rv = (r1 - np.array([4 / 3, -1 / 3, 0.0, 0.0])) / b
        A = np.array([r1, [1.0, 0, 0, 0], rv, [0, 0, 1.0, 0]])
    elif integrator == "generalized_alpha":      # state (x, v, a), dt = 1
        g = GeneralizedAlpha()
        am, af, gm, be = g.alpha_m, g.alpha_f, g.gamma, g.beta
        L = np.array([[W * W * (1 - af), 0, 1 - am], [1, 0, -be], [0, 1, -gm]])
        R = np.array([[-W * W * af, 0, -am], [1, 1, 0.5 - be], [0, 1, 1 - gm]])
        A = np.linalg.solve(L, R)
    elif integrator == "trbdf2":                 # state (x, v), dt = 1: TR stage, then BDF2 stage
        g = TRBDF2_GAMMA
        a0, a1, b = bdf2_coefficients((1 - g) / g)
        beta = b * (1 - g)

        def step(x0, v0):
            tau = 0.5 * g
            xg = (x0 + g * v0 - tau * tau * W * W * x0) / (1 + tau * tau * W * W)
            vg = (xg - x0 - tau * v0) / tau
            xref = a0 * xg - a1 * x0
            x1 = (xref + beta * (a0 * vg - a1 * v0)) / (1 + beta * beta * W * W)
            return x1, (x1 - xref) / beta

        A = np.array([step(1.0, 0.0), step(0.0, 1.0)]).T
    elif integrator == "lmm2":                   # state (x_{n+1}, x_n, v_{n+1}, v_n), dt = 1, a = -W^2 x
        (a0, a1, _), (b0, b1, b2) = LMM2_ALPHA, LMM2_BETA

        def step(x1, x0, v1, v0):
            xref = -a1 * x1 - a0 * x0 + b1 * v1 + b0 * v0
            vref = -a1 * v1 - a0 * v0 - W * W * (b1 * x1 + b0 * x0)
            x2 = (xref + b2 * vref) / (1 + b2 * b2 * W * W)
            return x2, x1, (x2 - xref) / b2, v1

        A = np.array([step(*e) for e in np.eye(4)]).T
    else:
        raise ValueError(f"no linear prediction for {integrator!r}")
    ev = np.linalg.eigvals(A)
    lam = ev[np.argmax(np.abs(ev.imag))]
    steps = 2 * math.pi / abs(np.angle(lam))     # steps per period
    return float(abs(lam) ** steps), float(steps * W / (2 * math.pi) - 1.0)


def measure_chain(integrator: str = "implicit_euler", dt: float = 0.04, periods: float = 3.0,
                  **scene_kw) -> ChainFidelity:
    """Simulate the swung chain with ``integrator`` at step ``dt`` and fit its first mode."""
    scene = chain_scene(**scene_kw)
    omega, phi = first_mode(scene)
    free = np.flatnonzero(~scene.strands.kinematic)
    mfree = scene.strands.masses[free]
    sim = Simulator(scene, ChainSolver(integrator=integrator))
    state = sim.initial_state()
    release = float(scene.motion.times[-1])
    T_lin = 2 * math.pi / omega
    n = int(math.ceil((release + periods * T_lin) / dt))
    ts, qs, iters = [], [], 0
    for _ in range(n):
        state, info = sim.step(state, dt)
        iters += info.iterations
        if state.time >= release - 1e-12:
            root = state.x[0, 0]
            ts.append(state.time - release)
            qs.append(float(np.sum(mfree * phi * (state.x[free, 0] - root))))
    A, sig, om, ph, c = _fit(np.array(ts), np.array(qs), omega)
    T = 2 * math.pi / om
    L = float(np.sum(scene.strands.rest_lengths))
    return ChainFidelity(integrator, dt, float(math.exp(-sig * T)), float(sig / math.hypot(sig, om)), float(T),
                         float(T_lin), float(4 * math.pi / (J01 * math.sqrt(GRAVITY / L))), float(omega * dt), n, iters)


__all__ = ["ChainFidelity", "chain_scene", "first_mode", "linear_prediction", "linearised", "measure_chain"]
