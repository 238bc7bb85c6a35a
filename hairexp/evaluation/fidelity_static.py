"""Static fidelity of the strand model against beam theory (issue 13): two measurements that a
report script can tabulate over vertex counts, and that tests/test_analytic.py checks.

* ``cantilever(n)``: a horizontal strand clamped at its root sags under its own weight; its tip
  deflection against Euler-Bernoulli ``w L^4 / (8 EI)`` (w = rho g, the weight per length) and
  against the inextensible elastica (the same beam without the small-slope linearisation).
* ``hanging(n)``: a strand hanging straight down stretches under the weight below each edge;
  the strain of every free edge against ``T / EA``, T = g x (mass of the free vertices below it).

The clamp is the strand's kinematic root (``N_ROOT_VERTICES`` vertices carried by the body): its
last vertex is the clamp point s = 0, and the kinematic root edge, which lies inside the clamp
(s < 0), holds the tangent there.  The *free length* L is the arc length from the clamp vertex to
the tip.  Strands here have uniform edges h = L / (n - N_ROOT_VERTICES), the root edge included,
so n vertices put n - N_ROOT_VERTICES free edges on the same free length L whatever n is.

The equilibrium is the minimum of stretch + bending + gravity, found by Newton on the dense
Hessian of the free DOFs (the simulator's terms, built as ``Simulator`` builds them), to a
residual force of 1e-9 x the strand's weight (the round-off floor of the stiff springs' forces,
eps |x| EA / l0, is ~1e-10 of it at 20-40 vertices).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.integrate import solve_bvp

from hairexp.model.strands import N_ROOT_VERTICES, Strands
from hairexp.physics.energies import Bending, Gravity, Stretch
from hairexp.physics.terms import autograd_grad_hess

G = 9.81                  # m/s^2
#: the measured cantilever (issue 13): EI 3e-4 N m^2, free length 0.3 m, default hair density
#: and stretch stiffness: sag w L^4 / (8 EI) = 2.2 % of L
EI = 3e-4                 # N m^2
FREE_LENGTH = 0.3         # m
LINEAR_DENSITY = 2e-4     # kg/m
EA = 20.0                 # N


def clamped_strand(n_vertices: int, free_length: float, direction, linear_density: float) -> Strands:
    """One straight strand of ``n_vertices`` along ``direction`` with uniform edges
    h = free_length / (n_vertices - N_ROOT_VERTICES), its clamp vertex (the last kinematic one) at
    the origin, the kinematic root edge(s) behind it (inside the clamp)."""
    n_free_edges = n_vertices - N_ROOT_VERTICES
    if n_free_edges < 1:
        raise ValueError(f"a clamped strand needs more than {N_ROOT_VERTICES} vertices, got {n_vertices}")
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    s = free_length * (np.arange(n_vertices) - (N_ROOT_VERTICES - 1)) / n_free_edges
    return Strands.from_polylines(s[:, None] * d, np.array([n_vertices]), linear_density, where="fidelity_static")


#: ``clamp`` choices: the simulator's bending (the clamp element weighs its free half-edge), or
#: the plain Voronoi length there (the discretisation before issue 13, for comparison)
CLAMPS = ("free_half", "voronoi")


def static_terms(strands: Strands, stretch_stiffness: float, bending_stiffness: float, gravity,
                 clamp: str = "free_half") -> list:
    """The elastic and gravity terms of the static energy, as ``Simulator`` builds them
    (``clamp="voronoi"``: the bending of before issue 13 instead, see ``CLAMPS``)."""
    if clamp not in CLAMPS:
        raise ValueError(f"clamp must be one of {CLAMPS}, got {clamp!r}")
    free = np.flatnonzero(~strands.kinematic)
    clamped = None if clamp == "free_half" else np.zeros(len(strands.bends), dtype=bool)
    return [Stretch(strands.edges, strands.rest_lengths, stretch_stiffness),
            Bending(strands.bends, strands.rest, bending_stiffness, clamped=clamped),
            Gravity(strands.masses, np.asarray(gravity, dtype=np.float64), free)]


def _energy(terms, x: np.ndarray) -> float:
    xt = torch.from_numpy(x)
    return float(sum(float(t.total(xt)) for t in terms))


def _grad_hess(terms, x: np.ndarray, free_slot: np.ndarray, n_dof: int, exact: bool):
    """Dense gradient (N,) and Hessian (N, N) of the summed terms over the free DOFs: the
    exact (autograd) element Hessians with ``exact``, else the closed-form PSD ones."""
    g = np.zeros(n_dof + 1)         # the last row and column collect the kinematic entries
    H = np.zeros((n_dof + 1, n_dof + 1))
    xt = torch.from_numpy(x)
    for t in terms:
        st = np.asarray(t.stencil)
        xs = xt[t.stencil_t]
        if exact:
            ge, He = autograd_grad_hess(t.energy, xs)
        else:
            ge, He = t.grad_hess(xs, need_hessian=True)
        dof = (3 * free_slot[st][:, :, None] + np.arange(3)).reshape(len(st), -1)
        dof[np.repeat(free_slot[st] < 0, 3, axis=1)] = n_dof
        np.add.at(g, dof, ge.numpy())
        np.add.at(H, (dof[:, :, None], dof[:, None, :]), He.numpy())
    return g[:n_dof], H[:n_dof, :n_dof]


@dataclass(frozen=True)
class Equilibrium:
    x: np.ndarray           # (V, 3) m
    iterations: int
    residual: float         # max |force| on a free vertex over the strand's weight


def static_equilibrium(strands: Strands, terms, tol: float = 1e-9, max_iterations: int = 60) -> Equilibrium:
    """Minimise the summed ``terms`` over the free vertices from the rest shape (kinematic
    vertices held at rest), to max |force| <= tol x weight: Newton with Armijo backtracking on
    the exact Hessian where it is positive definite (quadratic convergence near the minimum),
    else on the closed-form PSD one (whose clamped compression stiffness converges linearly)."""
    x = np.array(strands.rest, dtype=np.float64)
    free = ~strands.kinematic
    n_dof = 3 * int(free.sum())
    weight = max(float(strands.masses[free].sum()) * G, 1e-300)
    E = _energy(terms, x)
    res = np.inf
    for it in range(max_iterations + 1):
        g, H = _grad_hess(terms, x, strands.free_slot, n_dof, exact=True)
        res = float(np.abs(g).max()) / weight
        if res <= tol:
            return Equilibrium(x, it, res)
        try:
            np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            _, H = _grad_hess(terms, x, strands.free_slot, n_dof, exact=False)
        dx = np.linalg.solve(H, -g)
        step = np.zeros_like(x)
        step[free] = dx.reshape(-1, 3)
        alpha, slope = 1.0, float(g @ dx)
        while True:
            x_try = x + alpha * step
            E_try = _energy(terms, x_try)
            if E_try <= E + 1e-4 * alpha * slope or alpha < 1e-8:
                break
            if alpha == 1.0:  # near the minimum the energy change is round-off: take a step that lowers the force
                g_try, _ = _grad_hess(terms, x_try, strands.free_slot, n_dof, exact=False)
                if np.abs(g_try).max() < 0.5 * np.abs(g).max():
                    break
            alpha *= 0.5
        x, E = x_try, E_try
    return Equilibrium(x, max_iterations, res)


def euler_bernoulli_tip(w: float, EI: float, L: float) -> float:
    """Tip deflection w L^4 / (8 EI) of a clamped cantilever under the uniform load w (N/m)."""
    return w * L ** 4 / (8.0 * EI)


def elastica_tip(w: float, EI: float, L: float) -> float:
    """Tip deflection of the inextensible elastica under its own weight w per (rest) length,
    clamped horizontally: EI theta'' = -w (L - s) cos(theta), theta(0) = 0, theta'(L) = 0,
    deflection = int_0^L sin(theta) ds (solve_bvp to 1e-10)."""
    s = np.linspace(0.0, L, 201)

    def rhs(s, y):  # y = (theta, theta', deflection)
        return np.vstack([y[1], -w * (L - s) * np.cos(y[0]) / EI, np.sin(y[0])])

    def bc(a, b):
        return np.array([a[0], b[1], a[2]])

    lin = w / (6.0 * EI) * (L ** 3 - (L - s) ** 3)  # the small-slope solution as the start
    y0 = np.vstack([lin, w * (L - s) ** 2 / (2.0 * EI), np.zeros_like(s)])
    sol = solve_bvp(rhs, bc, s, y0, tol=1e-10, max_nodes=100000)
    if not sol.success:  # pragma: no cover - smooth, mildly nonlinear problem
        raise RuntimeError(f"elastica solve failed: {sol.message}")
    return float(sol.sol(L)[2])


@dataclass(frozen=True)
class Cantilever:
    n_vertices: int
    free_length: float       # m
    tip_deflection: float    # m, the simulated strand's tip drop below the clamp
    euler_bernoulli: float   # m, w L^4 / (8 EI)
    elastica: float          # m, the nonlinear (finite-slope) beam
    iterations: int
    residual: float

    @property
    def ratio(self) -> float:
        """Simulated over Euler-Bernoulli tip deflection."""
        return self.tip_deflection / self.euler_bernoulli

    @property
    def ratio_elastica(self) -> float:
        return self.tip_deflection / self.elastica


def cantilever(n_vertices: int, EI: float = EI, free_length: float = FREE_LENGTH,
               linear_density: float = LINEAR_DENSITY, EA: float = EA, g: float = G,
               direction=(1.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), clamp: str = "free_half") -> Cantilever:
    """Static sag of a clamped strand along ``direction`` under gravity -g ``up`` (see the
    module doc for the clamp and the free length; ``clamp``: see ``CLAMPS``)."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    s = clamped_strand(n_vertices, free_length, direction, linear_density)
    eq = static_equilibrium(s, static_terms(s, EA, EI, -g * up, clamp))
    tip, clamp = eq.x[-1], eq.x[N_ROOT_VERTICES - 1]
    w = linear_density * g
    return Cantilever(n_vertices, free_length, float((clamp - tip) @ up), euler_bernoulli_tip(w, EI, free_length),
                      elastica_tip(w, EI, free_length), eq.iterations, eq.residual)


@dataclass(frozen=True)
class Hanging:
    n_vertices: int
    free_length: float        # m
    strain: np.ndarray        # (free edges,) (l - l0) / l0 of each free edge, root to tip
    strain_analytic: np.ndarray  # (free edges,) g (mass of the free vertices below) / EA
    elongation: float         # m, of the free length
    elongation_continuum: float  # m, rho g L^2 / (2 EA) of a continuous elastic string

    @property
    def max_strain_error(self) -> float:
        """max |strain - analytic| over the free edges, relative to the largest analytic strain."""
        return float(np.abs(self.strain - self.strain_analytic).max() / self.strain_analytic.max())


def hanging(n_vertices: int, EI: float = EI, free_length: float = FREE_LENGTH,
            linear_density: float = LINEAR_DENSITY, EA: float = EA, g: float = G) -> Hanging:
    """A strand clamped at its top hanging straight down under gravity: each free edge carries
    the weight of the free vertices below it, T = g sum m, so its strain is T / EA exactly (the
    lumped masses put the tension of edge j at rho g (L - s_mid_j), the continuous string's at
    the edge's midpoint, so the total elongation is rho g L^2 / (2 EA) exactly too)."""
    s = clamped_strand(n_vertices, free_length, (0.0, -1.0, 0.0), linear_density)
    eq = static_equilibrium(s, static_terms(s, EA, EI, (0.0, -g, 0.0)))
    e = s.edges[N_ROOT_VERTICES - 1:]   # the free edges, root to tip
    l = np.linalg.norm(eq.x[e[:, 1]] - eq.x[e[:, 0]], axis=1)
    l0 = s.rest_lengths[N_ROOT_VERTICES - 1:]
    below = np.cumsum(s.masses[::-1])[::-1]          # mass of vertex i and every vertex after it
    T = g * below[e[:, 1]]
    return Hanging(n_vertices, free_length, (l - l0) / l0, T / EA, float((l - l0).sum()),
                   linear_density * g * free_length ** 2 / (2.0 * EA))


def observed_order(n_vertices, errors) -> list[float]:
    """Convergence order between successive vertex counts: log(e_a / e_b) / log(h_a / h_b),
    h = L / (n - N_ROOT_VERTICES) the edge length."""
    h = [1.0 / (n - N_ROOT_VERTICES) for n in n_vertices]
    return [float(np.log(abs(errors[i] / errors[i + 1])) / np.log(h[i] / h[i + 1]))
            for i in range(len(h) - 1)]


def table(vertex_counts=(10, 20, 40), clamp: str = "free_half", **kw) -> list[dict]:
    """One row per vertex count: the cantilever's sag ratios and the hanging strand's errors."""
    rows = []
    for n in vertex_counts:
        c, h = cantilever(n, clamp=clamp, **kw), hanging(n, **kw)
        rows.append(dict(n_vertices=n, tip_deflection=c.tip_deflection, euler_bernoulli=c.euler_bernoulli,
                         elastica=c.elastica, sag_ratio=c.ratio, sag_ratio_elastica=c.ratio_elastica,
                         hanging_strain_error=h.max_strain_error,
                         hanging_elongation_ratio=h.elongation / h.elongation_continuum))
    return rows
