"""Elastic and external energies of mass-spring hair (paper 3.4, "mass-spring chains that
resist stretching and bending, but not twisting" [RCT91]).  All in SI units, float64.
"""

from __future__ import annotations

import numpy as np
import torch

from hairexp.physics.terms import DTYPE, Term

#: Below this |kb| the bending direction is treated as undefined (straight within round-off).
KB_EPS = 1e-14


def _t(a) -> torch.Tensor:
    return torch.tensor(np.asarray(a), dtype=DTYPE)


#: [[1, -1], [-1, 1]] (x) ones(3, 3): the layout of a two-vertex element Hessian [[K, -K], [-K, K]].
_PAIR_SIGN = torch.kron(torch.tensor([[1.0, -1.0], [-1.0, 1.0]], dtype=DTYPE), torch.ones(3, 3, dtype=DTYPE))


def pair_hessian(K: torch.Tensor) -> torch.Tensor:
    """(n, 3, 3) block K of an edge element -> (n, 6, 6) Hessian [[K, -K], [-K, K]]."""
    return K.repeat(1, 2, 2) * _PAIR_SIGN


def stretch_energy(xs, k_l0, l0):
    """(n,) E = 1/2 (k / l0) (l - l0)^2 of each edge."""
    l = torch.linalg.vector_norm(xs[:, 1] - xs[:, 0], dim=-1)
    return 0.5 * k_l0 * (l - l0) ** 2


def stretch_kernel(xs, k_l0, l0, tension, need_hessian: bool):
    """Closed-form gradient (n, 6) and PSD Hessian (n, 6, 6) of Stretch (a pure function, so
    that torch.compile sees every input).

    dE/dx1 = (k/l0)(l - l0) u.  Hessian w.r.t. the edge vector:
    (k/l0) u u^T + max(T, 0)/l (I - u u^T), T the tension: T = (k/l0)(l - l0) gives the exact
    Hessian of a stretched spring and clamps the negative transverse stiffness of a compressed
    one at 0 (the exact PSD projection); ``tension`` overrides T (primal-dual Hessian)."""
    e = xs[:, 1] - xs[:, 0]
    l = torch.linalg.vector_norm(e, dim=-1)
    u = e / l.unsqueeze(-1)
    T_now = k_l0 * (l - l0)
    f = T_now.unsqueeze(-1) * u
    g = torch.cat([-f, f], dim=1)
    if not need_hessian:
        return g, None
    T = T_now if tension is None else tension
    c = T.clamp_min(0.0) / l
    # k/l0 uu^T + c (I - uu^T) = c I + (k/l0 - c) uu^T: eigenvalues c (twice) and k/l0, so PSD
    # for every c >= 0, including a tension iterate above (k/l0) l.
    uu = u.unsqueeze(-1) * u.unsqueeze(-2)
    K = torch.diag_embed(c.unsqueeze(-1).expand(-1, 3)) + (k_l0 - c).view(-1, 1, 1) * uu
    return g, pair_hessian(K)


class Stretch(Term):
    """Springs on edges: E = 1/2 (k / l0) (l - l0)^2, k the stretch stiffness EA (N).

    Primal-dual Hessian (compliant constraints, Tournier et al. 2015 "Stable constrained
    dynamics"): with ``tension`` set, the geometric stiffness T/l (I - u u^T) of each edge uses
    that tension iterate instead of (k/l0)(l - l0) from the current stretch.  The gradient, and
    so the converged state, is unchanged; only Newton's model is.  For stiff springs the
    stretch at an off-manifold iterate is a poor tension estimate, and the penalty form needs
    about twice the Newton iterations (experiments/bench_free.py).  Newton updates the tension
    by its linearisation (``linearized_tension``) and warm-starts it from the previous step.
    """

    name = "stretch"

    def __init__(self, edges: np.ndarray, rest_lengths: np.ndarray, k: float | np.ndarray):
        self.stencil = np.asarray(edges)
        self.l0 = _t(rest_lengths)
        self.k = _t(np.broadcast_to(k, rest_lengths.shape))
        self.k_l0 = self.k / self.l0
        self.tension: torch.Tensor | None = None  # (E,) N, the dual iterate; None: from the stretch

    energy_fn = staticmethod(stretch_energy)

    def energy_args(self):
        return self.k_l0, self.l0

    def tension_of(self, xs) -> torch.Tensor:
        """(E,) spring tension (k/l0)(l - l0) in N at element positions xs."""
        return self.k_l0 * (torch.linalg.vector_norm(xs[:, 1] - xs[:, 0], dim=-1) - self.l0)

    def linearized_tension(self, xs, dxs) -> torch.Tensor:
        """Tension after the step dxs, linearised: (k/l0)(l - l0 + u . (dx1 - dx0))."""
        e = xs[:, 1] - xs[:, 0]
        l = torch.linalg.vector_norm(e, dim=-1)
        return self.k_l0 * (l - self.l0 + ((dxs[:, 1] - dxs[:, 0]) * e).sum(-1) / l)

    kernel = staticmethod(stretch_kernel)

    def kernel_args(self):
        return self.k_l0, self.l0, self.tension


def curvature_binormal(e0: torch.Tensor, e1: torch.Tensor) -> torch.Tensor:
    """kb = 2 e0 x e1 / (|e0||e1| + e0.e1)  (Bergou et al. 2008).  |kb| = 2 tan(theta/2).

    Smooth at straight configurations, unlike atan2 forms: at three collinear nodes
    theta = atan2(|e0 x e1|, e0 . e1) has a zero autograd Hessian (tests/test_energies.py)."""
    l0 = torch.linalg.vector_norm(e0, dim=-1, keepdim=True)
    l1 = torch.linalg.vector_norm(e1, dim=-1, keepdim=True)
    return 2.0 * torch.linalg.cross(e0, e1) / (l0 * l1 + (e0 * e1).sum(-1, keepdim=True))


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([
        torch.stack([z, -v[..., 2], v[..., 1]], -1),
        torch.stack([v[..., 2], z, -v[..., 0]], -1),
        torch.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def kb_jacobian(xs):
    """kb (n, 3) and its Jacobian (n, 3, 9) w.r.t. (x0, x1, x2), in closed form:
    d kb / d e0 = (-2[e1]x - kb (l1 e0_hat + e1)^T) / chi,
    d kb / d e1 = ( 2[e0]x - kb (l0 e1_hat + e0)^T) / chi,  chi = l0 l1 + e0.e1."""
    e0, e1 = xs[:, 1] - xs[:, 0], xs[:, 2] - xs[:, 1]
    l0 = torch.linalg.vector_norm(e0, dim=-1, keepdim=True)
    l1 = torch.linalg.vector_norm(e1, dim=-1, keepdim=True)
    chi = (l0 * l1 + (e0 * e1).sum(-1, keepdim=True)).unsqueeze(-1)
    kb = 2.0 * torch.linalg.cross(e0, e1) / chi[..., 0]
    J0 = (-2.0 * _skew(e1) - kb.unsqueeze(-1) * (l1 * e0 / l0 + e1).unsqueeze(-2)) / chi
    J1 = (2.0 * _skew(e0) - kb.unsqueeze(-1) * (l0 * e1 / l1 + e0).unsqueeze(-2)) / chi
    return kb, torch.cat([-J0, J0 - J1, J1], dim=2)


def bending_energy(xs, w, s_rest):
    """(n,) E = w (|kb| - s)^2 = w (|kb|^2 - 2 s |kb| + s^2); |kb| is taken only where a rest
    curvature multiplies it (guarded at 0, where the energy has a kink), so a straight rest
    shape gives the exactly quadratic, smooth w |kb|^2."""
    kb = curvature_binormal(xs[:, 1] - xs[:, 0], xs[:, 2] - xs[:, 1])
    sq = (kb * kb).sum(-1)
    nrm = torch.sqrt(torch.where(s_rest > 0, sq, torch.ones_like(sq)).clamp_min(1e-300))
    mid = torch.where(s_rest > 0, 2.0 * s_rest * nrm, torch.zeros_like(sq))
    return w * (sq - mid + s_rest ** 2)


def bending_kernel(xs, w, s_rest, curved: bool, need_hessian: bool):
    """Closed-form gradient (n, 9) and Gauss-Newton PSD Hessian (n, 9, 9) of Bending.

    E = w (|kb| - s)^2.  grad = 2w J^T kb (1 - s/|kb|).  Hessian: 2w J^T [k k^T + c (I - k k^T)] J
    with c = max(0, 1 - s/|kb|), which is the exact Hessian at straight strands with s = 0 (the
    residual kb vanishes there).  With q = J^T k_hat it is 2w [c J^T J + (1 - c) q q^T]; at the
    kink (|kb| = 0 with rest curvature) k_hat is undefined and c = 0: no bending stiffness there.
    The scalars are folded into J and q before the products (cheaper than scaling 9x9s)."""
    kb, J = kb_jacobian(xs)
    nrm = torch.linalg.vector_norm(kb, dim=-1)
    has_s = s_rest > 0
    ratio = torch.where(has_s & (nrm > KB_EPS), s_rest / nrm.clamp_min(KB_EPS), torch.zeros_like(nrm))
    ratio = torch.where(has_s & (nrm <= KB_EPS), torch.ones_like(nrm), ratio)  # kink: no pull
    r = kb * (1.0 - ratio).unsqueeze(-1)
    g = 2.0 * w.unsqueeze(-1) * torch.einsum("nci,nc->ni", J, r)
    if not need_hessian:
        return g, None
    c = (1.0 - ratio).clamp_min(0.0)
    Js = J * torch.sqrt(2.0 * w * c).view(-1, 1, 1)
    if curved:
        khat = kb / nrm.clamp_min(KB_EPS).unsqueeze(-1)
        khat = torch.where((nrm > KB_EPS).unsqueeze(-1), khat, torch.zeros_like(khat))
        q = (khat.unsqueeze(-1) * J).sum(1, keepdim=True) * torch.sqrt(2.0 * w * (1.0 - c)).view(-1, 1, 1)
        Js = torch.cat([Js, q], dim=1)  # (n, 4, 9): H = Js^T Js in one product
    H = Js.transpose(1, 2) @ Js
    return g, H


def clamp_elements(bends: np.ndarray) -> np.ndarray:
    """(B,) True for the first element of each chain of the stencil: the element whose vertex i-1
    is no element's centre.  On every ``Strands`` that is the element centred on the last
    kinematic root vertex (``N_ROOT_VERTICES`` = 2: the root edge is carried by the body), i.e.
    the element of the clamp (tests/test_analytic.py checks it for every builder's layout)."""
    bends = np.asarray(bends)
    return ~np.isin(bends[:, 0], bends[:, 1])


def voronoi_lengths(bends: np.ndarray, rest_positions: np.ndarray, clamped: np.ndarray) -> np.ndarray:
    """(B,) rest length of hair each bending element stands for: the Voronoi length
    (|e_a| + |e_b|) / 2 of its centre vertex, and |e_b| / 2 at a clamp (``clamped``), whose
    first edge is the rigid root edge inside the body."""
    x = np.asarray(rest_positions, dtype=np.float64)[np.asarray(bends)]
    la = np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
    lb = np.linalg.norm(x[:, 2] - x[:, 1], axis=1)
    return 0.5 * (np.where(clamped, 0.0, la) + lb)


class Bending(Term):
    """Rotation-invariant bending on vertex triples with rest curvature (discrete elastic rods,
    Bergou et al. 2008, without twist):

        E_i = B / (2 l_i) (|kb_i| - |kb_rest_i|)^2,   B the bending stiffness EI (N m^2),

    l_i the Voronoi length of the element's centre vertex (``voronoi_lengths``).  Derivation:
    |kb| = 2 tan(theta/2) ~ theta, the turning angle between the edges, which samples the
    tangent at the two edge midpoints, so theta ~ kappa l_i and the element stands for
    1/2 B kappa^2 l_i = B theta^2 / (2 l_i) of E = 1/2 int B kappa^2 ds.  At an interior vertex
    l_i = (|e_a| + |e_b|) / 2, i.e. the weight B / (|e_a| + |e_b|).

    The clamp (the first element of a chain, ``clamp_elements``: centred on the last kinematic
    root vertex, the clamp point s = 0): the rigid root edge e_a is not a chord of the free hair
    but the body's tangent at s = 0 exactly (Euler-Bernoulli's clamp, zero slope at the root), so
    theta there ~ kappa(0) |e_b| / 2 and the element stands for the free half-edge [0, |e_b|/2]
    only: l_i = |e_b| / 2, weight B / |e_b|, independent of the root edge's length.  For uniform
    edges this is the symmetric ghost point of finite differences (w_{-1} = w_1) with the
    trapezoidal rule's half cell at the clamp: second order.  The plain Voronoi length there,
    (|e_a| + |e_b|) / 2, counts half of the rigid root edge as bendable hair and halves the
    clamp's stiffness: a first-order error (issue 13: a horizontal 20-vertex cantilever sagged
    1.114 x Euler-Bernoulli; now 1.0027, error ~ (h / L)^2 against the elastica;
    hairexp/evaluation/fidelity_static.py, tests/test_analytic.py).

    It depends on the configuration only through |kb| = 2 tan(theta/2), so it is invariant
    under every rotation.  With a straight rest shape (|kb_rest| = 0) it is exactly
    B/(2 l_i) |kb|^2, smooth with a non-zero Hessian at straight strands.  With rest
    curvature it keeps the rest bending *angle* (a model without twist has no material
    frame to keep the bending plane), and it has a kink at the straight configuration.

    ``clamped``: (B,) which elements sit on a clamp; None: the first element of each chain.
    """

    name = "bending"

    def __init__(self, bends: np.ndarray, rest_positions: np.ndarray, B: float | np.ndarray,
                 clamped: np.ndarray | None = None):
        self.stencil = np.asarray(bends)
        xr = _t(rest_positions)[torch.tensor(self.stencil)]
        e0r, e1r = xr[:, 1] - xr[:, 0], xr[:, 2] - xr[:, 1]
        kb_rest = curvature_binormal(e0r, e1r)
        s = torch.linalg.vector_norm(kb_rest, dim=-1)
        self.s_rest = torch.where(s < 1e-12, torch.zeros_like(s), s)  # exactly straight -> exactly quadratic
        self.curved = bool((self.s_rest > 0).any())  # static: no data-dependent branch in the kernel
        self.clamped = clamp_elements(self.stencil) if clamped is None else np.asarray(clamped, dtype=bool)
        self.lengths = _t(voronoi_lengths(self.stencil, rest_positions, self.clamped))
        self.w = _t(np.broadcast_to(B, (len(self.stencil),))) / (2.0 * self.lengths)

    energy_fn = staticmethod(bending_energy)

    def energy_args(self):
        return self.w, self.s_rest

    kernel = staticmethod(bending_kernel)

    def kernel_args(self):
        return self.w, self.s_rest, self.curved

    def kb_jacobian(self, xs):
        return kb_jacobian(xs)


class Gravity(Term):
    """E = -sum_i m_i g . x_i  (linear; zero Hessian)."""

    name = "gravity"

    def __init__(self, masses: np.ndarray, g: np.ndarray, vertices: np.ndarray | None = None):
        vertices = np.arange(len(masses)) if vertices is None else np.asarray(vertices)
        self.stencil = vertices.reshape(-1, 1)
        self.mg = _t(masses)[torch.tensor(vertices)].unsqueeze(-1) * _t(g).view(1, 3)
        self._mg_np = None

    def energy(self, xs):
        return -(self.mg * xs[:, 0]).sum(-1)

    def total_numpy(self, x: np.ndarray) -> float:
        """``total`` of full positions x (V, 3) in numpy (the metrics' potential energy: torch's
        gather costs milliseconds at Celia's size)."""
        if self._mg_np is None:
            self._mg_np = self.mg.numpy()
        return float(-(self._mg_np * x[self.stencil[:, 0]]).sum())

    def closed_form(self, xs, need_hessian):
        g = -self.mg
        return g, (torch.zeros(len(g), 3, 3, dtype=DTYPE) if need_hessian else None)


class EdgeDamping(Term):
    """Variational stretch damping over one step (a quadratic dissipation potential):

    D = c / (2 dt l0) * ((dx_b - dx_a) . u_n)^2,  dx = x - x_n,  u_n the edge direction at
    the start of the step.  Its gradient is the damping force c/l0 (relative velocity along
    the edge), c in N s.  Reset each step with ``set_reference``.

    Other integrators (hairexp/physics/integrators.py) pass ``set_reference(y_ref, h)`` with
    their velocity v = (x - y_ref)/h (BDF2: y_ref = 4/3 x_n - 1/3 x_{n-1}, h = 2 dt/3): D is then
    h R(v), R = c/(2 l0) (v_rel . u)^2 the Rayleigh dissipation, whose gradient in x is dR/dv at
    the scheme's velocity; u is the edge direction of y_ref."""

    name = "edge_damping"

    def __init__(self, edges: np.ndarray, rest_lengths: np.ndarray, c: float):
        self.stencil = np.asarray(edges)
        self.l0 = _t(rest_lengths)
        self.c = float(c)

    def set_reference(self, x_n: torch.Tensor, dt: float) -> None:
        xe = x_n[self.stencil_t]
        e = xe[:, 1] - xe[:, 0]
        self.u = e / torch.linalg.vector_norm(e, dim=-1, keepdim=True)
        self.xref = xe
        self.s = self.c / (dt * self.l0)

    def energy(self, xs):
        d = xs - self.xref
        rel = ((d[:, 1] - d[:, 0]) * self.u).sum(-1)
        return 0.5 * self.s * rel ** 2

    def closed_form(self, xs, need_hessian):
        d = xs - self.xref
        rel = ((d[:, 1] - d[:, 0]) * self.u).sum(-1)
        f = (self.s * rel).unsqueeze(-1) * self.u
        g = torch.cat([-f, f], 1)
        if not need_hessian:
            return g, None
        K = self.s.view(-1, 1, 1) * (self.u.unsqueeze(-1) * self.u.unsqueeze(-2))
        return g, pair_hessian(K)


class PointWell(Term):
    """Isotropic quadratic well of each vertex around an anchor: E = sum_i 1/2 w_i |x_i - y_i|^2.
    Subclasses set the weights ``w`` (n,) and anchors ``y`` (n, 3)."""

    def energy(self, xs):
        return 0.5 * self.w * ((xs[:, 0] - self.y) ** 2).sum(-1)

    def closed_form(self, xs, need_hessian):
        g = self.w.unsqueeze(-1) * (xs[:, 0] - self.y)
        if not need_hessian:
            return g, None
        return g, self.w.view(-1, 1, 1) * torch.eye(3, dtype=DTYPE).expand(len(g), 3, 3)


class AirDrag(PointWell):
    """Drag against still air over one step: D = gamma m / (2 dt) |x - x_n|^2 (gamma in 1/s):
    a well of weight gamma m / dt around the start-of-step positions x_n.  With another
    integrator, ``set_reference(y_ref, h)``: h R((x - y_ref)/h), R = gamma m/2 |v|^2 at the
    scheme's velocity (see ``EdgeDamping``)."""

    name = "air_drag"

    def __init__(self, masses: np.ndarray, gamma: float, vertices: np.ndarray):
        self.stencil = np.asarray(vertices).reshape(-1, 1)
        self.m = _t(masses)[torch.tensor(vertices)]
        self.gamma = float(gamma)

    def set_reference(self, x_n: torch.Tensor, dt: float) -> None:
        self.y = x_n[self.stencil_t][:, 0]
        self.w = self.gamma * self.m / dt


class Attraction(PointWell):
    """Attraction of each free vertex to a moving target (the nHair "start curve attract" /
    Vellum "pin to target" baseline): E = sum_i 1/2 k m_i |x_i - y_i(t)|^2, k in 1/s^2: a well of
    weight k m_i around the target.  ``set_target`` sets y at the end-of-step time before each solve."""

    name = "attraction"

    def __init__(self, masses: np.ndarray, k: float, vertices: np.ndarray):
        self.stencil = np.asarray(vertices).reshape(-1, 1)
        self.w = float(k) * _t(masses)[torch.tensor(np.asarray(vertices))]
        self.y = _t(np.zeros((len(self.stencil), 3)))

    def set_target(self, y) -> None:
        self.y = torch.as_tensor(np.asarray(y), dtype=DTYPE).reshape(-1, 3)

    def forces(self, x) -> np.ndarray:
        """(n, 3) spring forces -k m_i (x_i - y_i) at full positions x (V, 3)."""
        xs = torch.as_tensor(np.asarray(x), dtype=DTYPE)[self.stencil_t]
        return (-self.w.unsqueeze(-1) * (xs[:, 0] - self.y)).numpy()
