"""Hair-object contact inside the time-step objective: an IPC log barrier on the gaps of hair
edges to the colliders, with lagged smoothed Coulomb friction (``collision.contact=barrier``).

Incremental Potential Contact (Li et al. 2020, "Incremental Potential Contact", eq. 6) adds to
the objective that Newton and the SQP minimise (eq. 5, hairexp/physics/objective.py)

    B(x) = kappa sum_e w_e b(d_e(x)),   b(d) = -(d - d_hat)^2 ln(d / d_hat)  for 0 < d < d_hat,
                                        b(d) = 0 for d >= d_hat,

d_e the gap of edge e to a collider shape at its *end-of-step* pose (the distance of the whole
segment minus the collider's thickness, hairexp/physics/contact_geometry.py; the vertices are
the segments' end points, so they are covered).  w_e is the edge's rest length: B is then a
quadrature of a barrier density along the hair, independent of the resolution (codimensional
IPC, Li et al. 2021, weights the rods' barrier by their discretisation in the same way), and an
edge whose closest point is a shared vertex counts half a length on each side.

    b'(d)  = -2 (d - d_hat) ln(d / d_hat) - (d - d_hat)^2 / d,
    b''(d) = -2 ln(d / d_hat) - 4 (d - d_hat) / d + (d - d_hat)^2 / d^2   (> 0 on (0, d_hat)).

Gradient: kappa w b'(d) grad d, grad d = ((1 - s*) n, s* n) (contact_geometry).  Hessian
(``HESSIAN``, ``ObjectContact.contact_hessians``): per contact the full kappa w (b''(d) grad d
grad d^T + b'(d) hess d), hess d in closed form (contact_geometry.sdf_normal_hessian,
edge_distance_hessian: the shape's curvature at the closest point and the closest point's motion
along the edge).  b' < 0, so on a curved surface the second part softens the tangential
directions by lambda / rho (lambda the contact force, rho the radius of curvature); the
Gauss-Newton Hessian that drops it (and IPC's eigenvalue-clamped per-contact Hessian, which
for a vertex contact is the same) overestimates that stiffness, and where lambda / rho is
comparable to the inertia m / h^2 Newton and the SQP converged only linearly (|dx| halving per
iteration on splitting's ball).  The default keeps the negative part up to MASS_FRACTION of the
inertia diagonal, so the assembled Hessian stays positive definite.  An edge couples two
consecutive vertices of a strand: its 6 x 6 block lies inside the strand's band (half-bandwidth
5 <= 8).

Activation distance d_hat = ``collision.barrier_dhat`` x max(collider thickness, hair thickness)
per collider; stiffness kappa = ``collision.barrier_stiffness`` x rho / dt^2 (rho the mean linear
density): the barrier's curvature b''(d_hat / 2) ~ 3.6 then exceeds the inertia term rho / dt^2
of the same length of hair, so a contact stops the hair within d_hat in one step.  The value is
+inf where any gap is <= 0: a line search can never accept a point inside a collider, and the
step bound ``max_step`` (conservative advancement) keeps the iterates out of the sets between
line-search samples too (no tunnelling).

Friction (IPC sec. 5, lagged): per active contact the normal force lambda = kappa w |b'(d)|, the
closest parameter s, the tangent basis T (3 x 2) and the collider surface's displacement over the
step dc (rigid motion and spin) are frozen at the lag point; the tangential relative displacement
u = T^T ((1 - s) (x_a - x_a^n) + s (x_b - x_b^n) - dc) gets the potential

    D = mu lambda f0(|u|),  f0(y) = -y^3 / (3 eps^2) + y^2 / eps + eps / 3  (y < eps),  y  (else),

eps = eps_v dt (``collision.friction_epsilon`` = eps_v, m/s: slower is static friction).
f1 = f0' = -y^2/eps^2 + 2 y / eps (y < eps), 1 (else); grad_u D = mu lambda f1(y) u / y; the
Hessian mu lambda [(f1' y - f1) / y^3 u u^T + f1 / y I] is PSD on both branches (y < eps:
eigenvalues 2/eps (1 - y/eps) and 2/eps - y/eps^2; y >= eps: (I - u u^T / y^2) / y).  The lag is
refreshed at every Newton/SQP iteration (the solver re-evaluates H after it), so the converged
step satisfies the friction law with the normal forces of its own end state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hairexp.physics.assembly import add_pair_blocks
from hairexp.physics.collisions import path_test
from hairexp.physics.contact_geometry import EdgeGaps, advance, edge_distance_hessian, sdf_normal_hessian, shape_normal
from hairexp.physics.newton import NewtonOptions, newton_solve

#: Contacts closer than this fraction of d_hat count as "in contact" in the step's info.
CONTACT_REPORT = 1.0
#: Shapes with flat faces or straight rulings: edge contacts as end-point pairs (``_hybrid``).
FLAT_SHAPES = ("Box", "Cylinder")
#: An edge's interior closest point counts only when closer than both end points by this
#: fraction of d_hat (``_hybrid``).
INTERIOR_MARGIN = 1e-3
#: A collider that sweeps over hair within a step is advanced in sub-intervals of at most this
#: fraction of its thinnest size (``thin_size``), each followed by a few Newton iterations
#: (``begin_contact_step``).
SWEEP_FRACTION = 0.5
MAX_SUB_INTERVALS = 64
#: Newton iterations of each intermediate sub-interval solve.
SUB_INTERVAL_ITERATIONS = 8
#: The barrier Hessian: "gauss_newton" (kappa w b'' grad d grad d^T only), "projected" (IPC's
#: per-contact full Hessian, eigenvalues clamped at 0) or "mass_bounded" (the full Hessian, its
#: negative curvature part kept up to MASS_FRACTION of the inertia, ``contact_hessians``).
HESSIAN = "mass_bounded"
MASS_FRACTION = 0.9


def thin_size(col) -> float:
    """The collider's thinnest half size (m): what a sweep must not jump over in one piece."""
    name = type(col).__name__
    if name in ("Sphere", "Capsule"):
        return float(col.radius)
    if name == "Cylinder":
        return float(min(col.radius, col.half_height))
    if name == "Box":
        return float(min(col.half_extents))
    return np.inf


def sweep_substeps(colliders, x: np.ndarray, free: np.ndarray, t0: float, dt: float, fraction: float,
                   cap: int) -> int:
    """How many equal substeps a step from positions x at t0 over dt is split into so that no
    collider passes the hair it can reach by more than ``fraction`` of its thinnest half size
    (``thin_size``, plus its thickness) per substep (``collision.max_travel``,
    ``collision.max_travel_substeps``; at most ``cap``).  A collider faster than that jumps over
    hair within one step: a 10 m/s ball of radius 5 cm moves 0.4 m per 0.04 s step, and one step
    can only push the strands it meets 0.4 m ahead of it (the barrier's feasible path) or let
    them through it (the post-solve stage).  Split, the hair meets it a piece at a time and each
    substep's inertia carries the impulse, as a smaller ``solver.dt`` would.

    A CFL-like condition on the collider's own motion: in its frame a free vertex moves from
    Phi_0^-1 x to Phi_1^-1 x, a segment of length L (the hair held still: the hair's own motion
    into a collider is what the contact's CCD handles; counting it split goaling's tracked
    steps against its still wheel, 11 of 56, for no change of its contacts).  The signed
    distance is 1-Lipschitz, so a vertex whose distances d0, d1 at the segment's ends satisfy
    (d0 + d1 - L)/2 > thickness cannot come within its thickness on the way and is left out.  A
    shape without a finite thinnest size (a plane: a half space cannot be jumped over) never
    splits a step.  1: no split."""
    if fraction <= 0 or not colliders:
        return 1
    idx = np.flatnonzero(free) if free.dtype == bool else np.asarray(free)
    n = 1
    for c in colliders:
        thin = thin_size(c)
        if not np.isfinite(thin) or thin <= 0:
            continue
        (R0, T0), (R1, T1) = c.motion.pose(t0), c.motion.pose(t0 + dt)
        if np.array_equal(R0, R1) and np.array_equal(T0, T1):
            continue          # still over the step: every segment has length 0
        _, _, d0, d1, L = path_test(c, x, x, idx, t0, t0 + dt)     # d: minus the thickness
        reach = 0.5 * (d0 + d1 - L) <= 0.0
        if not reach.any():
            continue
        sweep = float(L[reach].max())
        n = max(n, int(np.ceil(sweep / (fraction * (thin + c.thickness)) - 1e-9)))
    return int(min(max(n, 1), cap))


def barrier(d: np.ndarray, dh) -> np.ndarray:
    """IPC barrier b(d) (Li et al. 2020 eq. 6); 0 for d >= d_hat, inf for d <= 0."""
    d = np.asarray(d, dtype=np.float64)
    out = np.zeros_like(d)
    on = (d < dh) & (d > 0)
    dhb = np.broadcast_to(dh, d.shape)
    out[on] = -(d[on] - dhb[on]) ** 2 * np.log(d[on] / dhb[on])
    out[d <= 0] = np.inf
    return out


def barrier_d1(d, dh):
    """b'(d) on (0, d_hat), 0 beyond."""
    r = np.where((d < dh) & (d > 0), -2 * (d - dh) * np.log(np.maximum(d, 1e-300) / dh) - (d - dh) ** 2 / np.maximum(d, 1e-300), 0.0)
    return r


def barrier_d2(d, dh):
    """b''(d) on (0, d_hat), 0 beyond."""
    dd = np.maximum(d, 1e-300)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):   # the lanes np.where drops (d <= 0)
        return np.where((d < dh) & (d > 0), -2 * np.log(dd / dh) - 4 * (d - dh) / dd + (d - dh) ** 2 / dd ** 2, 0.0)


def barrier_torch(d: torch.Tensor, dh) -> torch.Tensor:
    """The same b(d) in torch (the autograd reference of the tests)."""
    dh = torch.as_tensor(dh, dtype=d.dtype)
    inside = (d < dh) & (d > 0)
    ds = torch.where(inside, d, dh)
    return torch.where(inside, -(ds - dh) ** 2 * torch.log(ds / dh), torch.zeros_like(d))


def f0_friction(y, eps):
    """IPC's smoothed friction magnitude f0 (Li et al. 2020 eq. 16)."""
    return np.where(y < eps, -y ** 3 / (3 * eps ** 2) + y ** 2 / eps + eps / 3, y)


def f1_over_y(y, eps):
    """f1(y) / y (finite at y = 0: 2 / eps)."""
    return np.where(y < eps, -y / eps ** 2 + 2 / eps, 1.0 / np.maximum(y, 1e-300))


def tangent_bases(n: np.ndarray) -> np.ndarray:
    """(m, 3, 2) orthonormal tangent bases T of the unit normals n (m, 3) (the friction's)."""
    a = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=2)


def surface_displacement(col, P: np.ndarray, R1: np.ndarray, T1: np.ndarray, t0: float, dt: float) -> np.ndarray:
    """(m, 3) the displacement from t0 to t1 = t0 + dt of the collider's surface points at the world
    points P (m, 3) at t1 (pose (R1, T1)): its rigid motion and spin (the friction's dc)."""
    Xb = (P - T1) @ R1
    R0, T0 = col.motion.pose(t0)
    return (P - (Xb @ R0.T + T0)) + dt * (col.spin_velocity_body(Xb) @ R1.T)


def smoothed_friction(T: np.ndarray, mulam: np.ndarray, rel: np.ndarray, Jw: np.ndarray | None, eps: float,
                      need_hessian: bool, derivatives: bool = True):
    """IPC's lagged friction (module doc) on m contact points: energy sum mu lam f0(|u|),
    u = T^T rel (T (m, 3, 2) tangent bases, rel (m, 3) the points' displacement relative to the
    surface, mulam (m,) mu lambda), and with ``derivatives`` its gradient (m, 6) and with
    ``need_hessian`` its PSD Hessian (m, 6, 6) for the two vertices of each point, weighted Jw (m, 2)
    (None where not asked)."""
    u = np.einsum("nij,ni->nj", T, rel)                                  # (m, 2)
    y = np.linalg.norm(u, axis=1)
    e = float(np.dot(mulam, f0_friction(y, eps)))
    if not derivatives:
        return e, None, None
    gu = (mulam * f1_over_y(y, eps))[:, None] * u                       # dD/du (m, 2)
    g3 = np.einsum("nij,nj->ni", T, gu)                                 # dD/d(contact point) (m, 3)
    g = (Jw[:, :, None] * g3[:, None, :]).reshape(-1, 6)
    if not need_hessian:
        return e, g, None
    small = y < eps
    uh = u / np.maximum(y, 1e-300)[:, None]
    coef_uu = np.where(small, -y / eps ** 2, -1.0 / np.maximum(y, 1e-300))   # (f1' y - f1)/y^3 |u|^2
    M = f1_over_y(y, eps)[:, None, None] * np.eye(2) + coef_uu[:, None, None] * uh[:, :, None] * uh[:, None, :]
    M *= mulam[:, None, None]
    H3 = np.einsum("nij,njk,nlk->nil", T, M, T)                         # (m, 3, 3)
    H = (Jw[:, :, None, None, None] * Jw[:, None, :, None, None]) * H3[:, None, None]   # (m, 2, 2, 3, 3)
    return e, g, H.transpose(0, 1, 3, 2, 4).reshape(-1, 6, 6)


@dataclass
class ContactStats:
    """The barrier's view of one step, for ``StepInfo`` (pure data)."""

    contacts: int = 0            # edges within d_hat of a collider at the end of the step
    per_collider: dict = None
    gap_min: float = np.inf      # m, smallest edge gap (edge distance minus thickness) at the end
    penetration_max: float = 0.0  # m, deepest vertex or edge point inside a thickness shell
    start_moved: int = 0         # free vertices the feasible start carried with a collider
    start_feasible: bool = True
    friction_contacts: int = 0
    sub_intervals: int = 1       # pieces the colliders' motion over the step was advanced in
    curvature_scale_min: float = 1.0   # smallest gamma of ObjectContact.contact_hessians (1: exact)


class ObjectContact:
    """Barrier + friction for all hair edges against all colliders (one object per Simulator).

    ``edges`` (E, 2) vertex indices, ``weights`` (E,) m (rest lengths), ``kinematic`` (V,),
    ``free_slot`` (V,) as in hairexp/model/strands.py; ``colliders``: hairexp/model/colliders.py."""

    def __init__(self, colliders, edges, weights, kinematic, free_slot, strand_of_vertex, linear_density: float,
                 hair_thickness: float, dhat_scale: float, stiffness_scale: float, friction_eps_v: float,
                 friction: bool = True):
        self.colliders = list(colliders)
        E = np.asarray(edges)
        free = ~np.asarray(kinematic)
        keep = free[E[:, 0]] | free[E[:, 1]]            # an edge of two roots is prescribed: nothing to do
        self.E, self.w = E[keep], np.asarray(weights, dtype=np.float64)[keep]
        self.free_slot = np.asarray(free_slot)
        self.kinematic = np.asarray(kinematic)
        self.strand_of_vertex = np.asarray(strand_of_vertex)
        self.rho = float(linear_density)
        self.dhat = np.array([dhat_scale * max(c.thickness, hair_thickness) for c in self.colliders])
        #: per collider, the radius of a ball about its body origin holding its thickness shell (inf: unbounded)
        self._reach = [float(c.bounding_radius()) + float(c.thickness) for c in self.colliders]
        self.stiffness_scale = float(stiffness_scale)
        self.eps_v = float(friction_eps_v)
        self.use_friction = bool(friction) and any(c.friction > 0 for c in self.colliders)
        self.kappa = 0.0
        self.vertex_mass = None   # (V,) inertia diagonal m / h^2 of the step (begin_contact_step)
        self.gaps: list[EdgeGaps] = []
        self._lag = None
        self.stats = ContactStats()

    # -- per step -------------------------------------------------------------------------
    def begin(self, x_n: np.ndarray, t0: float, t1: float, dt: float) -> None:
        """Collider poses at the end of the step, kappa for this dt; friction lag cleared."""
        self.dt, self.t0, self.t1 = float(dt), float(t0), float(t1)
        self.x_n = np.asarray(x_n, dtype=np.float64)
        self.kappa = self.stiffness_scale * self.rho / self.dt ** 2
        self.set_time(t1)
        self._lag = None
        self.stats = ContactStats(per_collider={c.name: 0 for c in self.colliders})

    def set_time(self, t: float) -> None:
        """Collider poses at time t (t1 but for the sub-intervals of ``begin_contact_step``)."""
        self.t_pose = float(t)
        self.gaps = [EdgeGaps(c, *c.motion.pose(t)) for c in self.colliders]

    def poses(self) -> list:
        return [(g.R, g.T) for g in self.gaps]

    def sub_intervals(self, x_n: np.ndarray) -> int:
        """How many sub-intervals the colliders' motion over the step is cut into: a collider
        that sweeps over hair (``_swept``) by more than SWEEP_FRACTION of its thinnest size
        (``thin_size``) is advanced in pieces of that length (see ``begin_contact_step``)."""
        m = 1
        for k, c in enumerate(self.colliders):
            R0, T0 = c.motion.pose(self.t0)
            idx = self._swept(x_n, k, R0, T0)
            bad = self._near(x_n, k, 0.0)
            if idx.size == 0 and (bad.size == 0 or np.all(self.gaps[k].edge_gaps(x_n[self.E[bad, 0]], x_n[self.E[bad, 1]]) > 0)):
                continue
            X0, X1 = (x_n - T0) @ R0, self.gaps[k].body(x_n)
            sweep = float(np.linalg.norm(X1 - X0, axis=1).max(initial=0.0))
            m = max(m, int(np.ceil(sweep / (SWEEP_FRACTION * thin_size(c)))))
        return min(m, MAX_SUB_INTERVALS)

    def _near(self, x: np.ndarray, k: int, margin: float) -> np.ndarray:
        """Edge indices whose gap to collider k can be below margin (cheap vertex bound).

        A bounded shape lies in the ball of its ``bounding_radius`` about its body origin, so a
        point's gap is at least its distance to that ball's centre minus the radius and the
        thickness (the signed distance is 1-Lipschitz and at least the ball's own): edges that
        bound excludes are dropped before the shape's distance is evaluated, for the few others
        only.  The same edges as the shape's distance at every vertex gives (tests/test_barrier.py),
        at a fraction of the cost: most edges of a groom are far from most colliders, and this runs
        at every evaluation of the objective (about 300 times a step on celia_smoke)."""
        gp, E = self.gaps[k], self.E
        reach = self._reach[k]
        if np.isfinite(reach):
            gs = np.linalg.norm(x - gp.T, axis=1) - reach
            cand = np.flatnonzero(gp.edge_lower_bound(x[E[:, 0]], x[E[:, 1]], gs[E[:, 0]], gs[E[:, 1]]) < margin)
            if cand.size == 0:
                return cand
            Ec = E[cand]
            xa, xb = x[Ec[:, 0]], x[Ec[:, 1]]
            return cand[gp.edge_lower_bound(xa, xb, gp.vertex_gaps(xa), gp.vertex_gaps(xb)) < margin]
        g = gp.vertex_gaps(x)
        lb = gp.edge_lower_bound(x[E[:, 0]], x[E[:, 1]], g[E[:, 0]], g[E[:, 1]])
        return np.flatnonzero(lb < margin)

    def active(self, x: np.ndarray, normals: bool = False):
        """Per collider: (edge indices, gaps, weight factors[, s, normals]) of the contacts within
        d_hat.  A contact is an edge's closest point; against a plane (whose minimum over a
        segment is at an end point, so min(d_a, d_b) has a kink where an edge lies parallel to
        it) each edge is instead two end-point contacts of half its weight: smooth, and feasible
        exactly when the segment is.

        Side result ``self.segments_were_clear``: every edge within d_hat (a superset of those that
        can touch a shell) had a segment gap > 0, i.e. ``segments_clear(x)`` without a second
        closest-point search (``energy``)."""
        out = []
        self.segments_were_clear = True
        for k, gp in enumerate(self.gaps):
            idx = self._near(x, k, self.dhat[k])
            E = self.E[idx]
            if type(self.colliders[k]).__name__ == "Plane":
                da, db = gp.vertex_gaps(x[E[:, 0]]), gp.vertex_gaps(x[E[:, 1]])
                if np.any(np.minimum(da, db) <= 0):
                    self.segments_were_clear = False
                idx2 = np.concatenate([idx, idx])
                d = np.concatenate([da, db])
                s = np.concatenate([np.zeros(idx.size), np.ones(idx.size)])
                n = np.broadcast_to(gp.R[:, 1], (2 * idx.size, 3))
                on = d < self.dhat[k]
                wf = np.full(on.sum(), 0.5)
                out.append((idx2[on], d[on], wf, s[on], n[on]) if normals else (idx2[on], d[on], wf))
                continue
            if type(self.colliders[k]).__name__ in FLAT_SHAPES:
                out.append(self._hybrid(gp, x, idx, k, normals))
                continue
            if normals:
                d, s, n = gp.edge_gaps(x[E[:, 0]], x[E[:, 1]], normals=True)
                self.segments_were_clear &= not np.any(d <= 0)
                on = d < self.dhat[k]
                out.append((idx[on], d[on], np.ones(on.sum()), s[on], n[on]))
            else:
                d = gp.edge_gaps(x[E[:, 0]], x[E[:, 1]])
                self.segments_were_clear &= not np.any(d <= 0)
                on = d < self.dhat[k]
                out.append((idx[on], d[on], np.ones(on.sum())))
        return out

    def _hybrid(self, gp, x, idx, k, normals):
        """Contacts of edges against a shape with flat faces (box, cylinder): an edge lying on a
        face has its minimum gap at both end points at once, where min(d_a, d_b) has a kink that
        stalls Newton (measured: a wisp pressed onto a box face did not converge in 50 SQP
        iterations).  Its contacts are the two end points (half its weight each: smooth) plus,
        only where the segment's closest point is interior and closer than both end points (an
        edge across a box edge or corner), that interior point with the edge's weight."""
        E = self.E[idx]
        d, s, n = gp.edge_gaps(x[E[:, 0]], x[E[:, 1]], normals=True)
        self.segments_were_clear &= not np.any(d <= 0)
        da, db = gp.vertex_gaps(x[E[:, 0]]), gp.vertex_gaps(x[E[:, 1]])
        inner = (s > 0) & (s < 1) & (d < np.minimum(da, db) - INTERIOR_MARGIN * self.dhat[k])
        col = self.colliders[k]
        parts = []
        for dv, sv, vert in ((da, 0.0, E[:, 0]), (db, 1.0, E[:, 1])):
            on = dv < self.dhat[k]
            nv = shape_normal(col, gp.body(x[vert[on]])) @ gp.R.T if normals else None
            parts.append((idx[on], dv[on], np.full(on.sum(), 0.5), np.full(on.sum(), sv), nv))
        on = inner & (d < self.dhat[k])
        parts.append((idx[on], d[on], np.ones(on.sum()), s[on], n[on] if normals else None))
        cat = [np.concatenate([p[i] for p in parts]) for i in range(4)]
        if normals:
            return (*cat[:3], cat[3], np.concatenate([p[4] for p in parts]))
        return tuple(cat[:3])

    def segments_clear(self, x: np.ndarray) -> bool:
        """Every whole edge (not only its contacts) outside every thickness shell."""
        for k, gp in enumerate(self.gaps):
            idx = self._near(x, k, 0.0)
            if idx.size and np.any(gp.edge_gaps(x[self.E[idx, 0]], x[self.E[idx, 1]]) <= 0):
                return False
        return True

    def feasible(self, x: np.ndarray) -> bool:
        return self.segments_clear(x) and all(np.all(d > 0) for _, d, _ in self.active(x))

    # -- objective pieces (x: full positions (V, 3)) ----------------------------------------
    def energy(self, x: np.ndarray) -> float:
        """B(x) + D(x); inf if an edge touches or enters a thickness shell."""
        e = 0.0
        acts = self.active(x)
        if not self.segments_were_clear:
            return np.inf
        for k, (idx, d, wf) in enumerate(acts):
            if np.any(d <= 0):
                return np.inf
            e += self.kappa * float(np.dot(self.w[idx] * wf, barrier(d, self.dhat[k])))
        if self._lag is not None:
            e += self._friction(x, need_hessian=False)[0]
        return e

    def derivatives(self, x: np.ndarray, need_hessian: bool = True):
        """Per-contact gradient (n, 6), Hessian (n, 6, 6) or None, and edge indices (n,).  The
        Hessian is the one ``HESSIAN`` names (see ``contact_hessians``)."""
        idx_all, g_all, H_all = [], [], []
        for k, (idx, d, wf, s, n) in enumerate(self.active(x, normals=True)):
            if idx.size == 0:
                continue
            J = np.concatenate([(1 - s)[:, None] * n, s[:, None] * n], axis=1)   # grad d, (n, 6)
            c1 = self.kappa * self.w[idx] * wf * barrier_d1(d, self.dhat[k])
            idx_all.append(idx)
            g_all.append(c1[:, None] * J)
            if need_hessian:
                c2 = self.kappa * self.w[idx] * wf * barrier_d2(d, self.dhat[k])
                H = c2[:, None, None] * J[:, :, None] * J[:, None, :]
                if HESSIAN != "gauss_newton":
                    H = H + c1[:, None, None] * self.distance_hessian(x, k, idx, s)
                H_all.append(H)
        if need_hessian and H_all and HESSIAN != "gauss_newton":
            H_all = self.contact_hessians(np.concatenate(idx_all), np.concatenate(H_all))
        if self._lag is not None:
            idx, g, H = self._friction(x, need_hessian, derivatives=True)
            if idx.size:
                idx_all.append(idx)
                g_all.append(g)
                if need_hessian:
                    H_all.append(H)
        if not idx_all:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 6)), (np.zeros((0, 6, 6)) if need_hessian else None)
        return (np.concatenate(idx_all), np.concatenate(g_all), np.concatenate(H_all) if need_hessian else None)

    def distance_hessian(self, x: np.ndarray, k: int, idx: np.ndarray, s: np.ndarray) -> np.ndarray:
        """hess d (n, 6, 6), world frame, of the contacts (edges ``idx``, closest parameters s)
        against collider k (contact_geometry.edge_distance_hessian; an end-point contact, s = 0
        or 1, is a vertex's: s fixed)."""
        gp = self.gaps[k]
        E = self.E[idx]
        A, B = gp.body(x[E[:, 0]]), gp.body(x[E[:, 1]])
        D = B - A
        nb, Hb = sdf_normal_hessian(self.colliders[k], A + s[:, None] * D)
        Hd = edge_distance_hessian(Hb, nb, D, s, (s > 0) & (s < 1))
        R6 = np.kron(np.eye(2), gp.R)
        return R6 @ Hd @ R6.T

    def contact_hessians(self, idx: np.ndarray, H: np.ndarray) -> list:
        """The per-contact Hessians kappa w (b'' grad d grad d^T + b' hess d) made safe for the
        solver: each split by its eigenvalues into a PSD part H+ and an NSD part H- (b' < 0 and hess
        d is PSD on a convex shape's curved side: H- is the tangential softening of a curved
        contact, e.g. -lambda / rho (I - n n^T) for a vertex on a sphere).

        ``HESSIAN = "projected"``: H+ only (IPC's projection, Li et al. 2020 sec. 5; for a vertex
        contact this is the Gauss-Newton term, as the curvature is all tangential and negative).
        ``HESSIAN = "mass_bounded"``: H+ + gamma_c H-, gamma_c in [0, 1] the largest scale with
        sum_c gamma_c H-_c >= -MASS_FRACTION M (M the inertia diagonal mass / h^2 of the step,
        ``vertex_mass``): with |H-_c| <= mu_c on its vertices, L_v = sum of mu_c over the contacts
        on vertex v and gamma_c = min(1, MASS_FRACTION min_v m_v / L_v).  The total Hessian M + (PSD
        elastic terms) + sum H+ + sum gamma H- stays >= (1 - MASS_FRACTION) M > 0, so the Newton/SQP
        step is a descent direction, and where the bound does not bite (gamma = 1) it is the exact
        Hessian: the iteration converges quadratically instead of linearly at the rate
        (lambda / rho) / (m / h^2) that dropping the term costs (measured: |dx| halved per iteration
        on splitting's ball, where lambda / rho ~ m / h^2)."""
        lam, V = np.linalg.eigh(0.5 * (H + H.transpose(0, 2, 1)))
        Hp = np.einsum("nij,nj,nkj->nik", V, np.maximum(lam, 0.0), V)
        if HESSIAN == "projected" or self.vertex_mass is None:
            return [Hp]
        Hm = np.einsum("nij,nj,nkj->nik", V, np.minimum(lam, 0.0), V)
        mu = np.maximum(-lam[:, 0], 0.0)
        E = self.E[idx]
        # the vertices an NSD part acts on (a zero block: an end-point contact of the other vertex)
        on = np.stack([np.abs(Hm[:, :3, :3]).max(axis=(1, 2)) > 0, np.abs(Hm[:, 3:, 3:]).max(axis=(1, 2)) > 0], axis=1)
        on &= ~self.kinematic[E]
        L = np.zeros(len(self.kinematic))
        np.add.at(L, E[on], np.broadcast_to(mu[:, None], on.shape)[on])
        with np.errstate(over="ignore", divide="ignore"):
            cap = np.where(on, MASS_FRACTION * self.vertex_mass[E] / np.maximum(L[E], 1e-300), np.inf).min(axis=1)
        gamma = np.clip(cap, 0.0, 1.0)
        self.stats.curvature_scale_min = min(self.stats.curvature_scale_min, float(gamma.min(initial=1.0)))
        return [Hp + gamma[:, None, None] * Hm]

    def add_to(self, x: np.ndarray, grad: np.ndarray, ab: np.ndarray | None) -> float:
        """Add the contact gradient to ``grad`` (N,) and its Hessian to the lower band ``ab``
        (bw + 1, N) of the free DOFs; returns the norm of the contact force."""
        idx, g, H = self.derivatives(x, ab is not None)
        if idx.size == 0:
            return 0.0
        contrib = add_pair_blocks(grad, ab, self.free_slot[self.E[idx]], g, H)
        return float(np.linalg.norm(contrib))

    # -- line-search filter -----------------------------------------------------------------
    def max_step(self, x: np.ndarray, p: np.ndarray) -> float:
        """Largest alpha <= 1 such that x + a p (p: (V, 3), 0 on the roots) keeps every edge gap
        above CCD_ETA times its value at x for all a in [0, alpha] (contact_geometry.advance)."""
        return float(self.max_step_per_edge(x, p).min(initial=1.0))

    def max_step_per_edge(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        E = self.E
        alpha = np.ones(len(E))
        speed = np.maximum(np.linalg.norm(p[E[:, 0]], axis=1), np.linalg.norm(p[E[:, 1]], axis=1))
        for k, gp in enumerate(self.gaps):
            idx = self._near(x, k, float(speed.max(initial=0.0)) + self.dhat[k])
            if idx.size == 0:
                continue
            a = advance(gp, x[E[idx, 0]], x[E[idx, 1]], p[E[idx, 0]], p[E[idx, 1]])
            alpha[idx] = np.minimum(alpha[idx], a)
        return alpha

    # -- a feasible start ---------------------------------------------------------------------
    def feasible_start(self, x_n: np.ndarray, x_guess: np.ndarray, poses0=None) -> np.ndarray:
        """A start of the solve inside the feasible set at the end-of-step poses, as near the
        guess (x_n + dt v_n) as conservative advancement from x_n allows.

        1. Carry with the colliders: x_n is feasible against the colliders at t_n (the previous
           step ended there), and a rigid motion keeps every distance, so a point moved with a
           collider's relative motion Phi_{n+1} Phi_n^-1 is as far from it at t_{n+1} as it was at
           t_n.  Each free vertex of an edge that is infeasible at t_{n+1} (a collider swept onto
           it: a 10 m/s ball moves 0.4 m per 0.04 s step) is carried; an edge between a carried
           and an uncarried vertex that is then infeasible carries its other end too, until no
           edge is infeasible (the carried part of a strand keeps its shape: it is pushed ahead).
        2. Each strand moves from there toward the guess by its own conservative-advancement
           step (strands do not interact through object contact).
        If an edge of two root vertices is infeasible nothing helps: the start stays infeasible,
        the solve reports divergence and the step is retried as substeps."""
        x0 = np.array(x_n, dtype=np.float64)
        x0[self.kinematic] = x_guess[self.kinematic]
        moved = np.zeros(len(x0), dtype=bool)
        free = ~self.kinematic
        E = self.E
        for _ in range(3):   # several colliders: carrying by one may push into another
            bad_any = False
            for k, (c, gp) in enumerate(zip(self.colliders, self.gaps)):
                R0, T0 = c.motion.pose(self.t0) if poses0 is None else poses0[k]
                R1, T1 = gp.R, gp.T
                carried = moved.copy()
                swept = self._swept(x_n, k, R0, T0)
                for _it in range(len(x0)):
                    idx = self._near(x0, k, 0.0)
                    d = gp.edge_gaps(x0[E[idx, 0]], x0[E[idx, 1]])
                    bad = np.union1d(idx[d <= 0], swept)
                    swept = np.zeros(0, dtype=np.int64)
                    if bad.size == 0:
                        break
                    verts = np.unique(E[bad].ravel())
                    verts = verts[free[verts] & ~carried[verts]]
                    if verts.size == 0:
                        bad_any = True
                        break
                    X = (x_n[verts] - T0) @ R0                  # body frame at t_n
                    x0[verts] = X @ R1.T + T1                   # the same body point at t_{n+1}
                    carried[verts] = True
                moved |= carried
            if not bad_any:
                break
        self.stats.start_moved = int((moved & free).sum())
        p = x_guess - x0
        p[self.kinematic] = 0.0
        a_edge = self.max_step_per_edge(x0, p)
        S = int(self.strand_of_vertex.max()) + 1
        a_strand = np.ones(S)
        np.minimum.at(a_strand, self.strand_of_vertex[E[:, 0]], a_edge)
        x_start = x0 + a_strand[self.strand_of_vertex][:, None] * p
        self.stats.start_feasible = self.feasible(x_start)
        return x_start

    def _swept(self, x_n: np.ndarray, k: int, R0, T0) -> np.ndarray:
        """Edges of x_n that collider k sweeps over during the step although they may be outside
        it at both ends (a 10 m/s ball passes a strand within one step): in the collider's frame
        the hair's points move from Phi_n^-1 x_n to Phi_{n+1}^-1 x_n (linearly, as the collision
        stage takes them); conservative advancement with floor 0 finds the paths that reach the shell."""
        gp = self.gaps[k]
        X0, X1 = (x_n - T0) @ R0, gp.body(x_n)
        E = self.E
        move = np.linalg.norm(X1 - X0, axis=1)
        body = EdgeGaps(self.colliders[k], np.eye(3), np.zeros(3))
        g0 = body.vertex_gaps(X0)
        lb = body.edge_lower_bound(X0[E[:, 0]], X0[E[:, 1]], g0[E[:, 0]], g0[E[:, 1]])
        idx = np.flatnonzero(lb - np.maximum(move[E[:, 0]], move[E[:, 1]]) < 0)
        if idx.size == 0:
            return idx
        P = X1 - X0
        a = advance(body, X0[E[idx, 0]], X0[E[idx, 1]], P[E[idx, 0]], P[E[idx, 1]], eta=0.0)
        return idx[a < 1.0]

    # -- friction ---------------------------------------------------------------------------
    def update_lag(self, x: np.ndarray) -> None:
        """Freeze the friction data at x: normal forces, closest parameters, tangent bases and
        the colliders' surface displacement over the step at the contact points."""
        if not self.use_friction:
            return
        parts = []
        for k, (idx, d, wf, s, n) in enumerate(self.active(x, normals=True)):
            c = self.colliders[k]
            if idx.size == 0 or c.friction <= 0:
                continue
            lam = self.kappa * self.w[idx] * wf * np.abs(barrier_d1(d, self.dhat[k]))
            E = self.E[idx]
            P = (1 - s)[:, None] * x[E[:, 0]] + s[:, None] * x[E[:, 1]]
            gp = self.gaps[k]
            dc = surface_displacement(c, P, gp.R, gp.T, self.t0, self.dt)
            parts.append((idx, s, tangent_bases(n), lam * c.friction, dc))
        if not parts:
            self._lag = None
            return
        cat = lambda i: np.concatenate([p[i] for p in parts])   # noqa: E731
        self._lag = (cat(0), cat(1), cat(2), cat(3), cat(4))
        self.stats.friction_contacts = len(self._lag[0])

    def _friction(self, x: np.ndarray, need_hessian: bool, derivatives: bool = False):
        idx, s, T, mulam, dc = self._lag
        E = self.E[idx]
        eps = self.eps_v * self.dt
        rel = ((1 - s)[:, None] * (x[E[:, 0]] - self.x_n[E[:, 0]]) + s[:, None] * (x[E[:, 1]] - self.x_n[E[:, 1]]) - dc)
        e, g, H = smoothed_friction(T, mulam, rel, np.stack([1 - s, s], axis=1), eps, need_hessian, derivatives)
        if not derivatives:
            return (e,)
        return idx, g, H

    # -- after the step ---------------------------------------------------------------------
    def end_stats(self, x: np.ndarray) -> ContactStats:
        """Contacts, smallest gap and deepest penetration (vertices and whole edges) at x."""
        st = self.stats
        pen, gmin, total = 0.0, np.inf, 0
        for k, gp in enumerate(self.gaps):
            idx = self._near(x, k, self.dhat[k] * CONTACT_REPORT)
            E = self.E[idx]
            d = gp.edge_gaps(x[E[:, 0]], x[E[:, 1]]) if idx.size else np.zeros(0)
            n = int(np.sum(d < self.dhat[k] * CONTACT_REPORT))
            st.per_collider[self.colliders[k].name] = n
            total += n
            if d.size:
                gmin = min(gmin, float(d.min()))
                pen = max(pen, float(np.maximum(-d, 0.0).max()))
        st.contacts, st.gap_min, st.penetration_max = total, gmin, pen
        return st


def make_object_contact(scene, collision_cfg) -> ObjectContact | None:
    """The barrier for ``collision.contact=barrier`` when the scene has colliders and
    ``collision.objects`` is on; None otherwise (the post-solve stage handles object contact, or
    nothing does).  Hair-hair contact stays in the post-solve stage either way."""
    cc = collision_cfg
    mode = str(getattr(getattr(cc, "contact", "stage"), "value", getattr(cc, "contact", "stage"))) if cc is not None else "stage"
    if cc is None or mode != "barrier" or not cc.objects or not scene.colliders:
        return None
    s = scene.strands
    rho = float(np.sum(s.masses) / max(float(np.sum(s.rest_lengths)), 1e-300))
    return ObjectContact(scene.colliders, s.edges, s.rest_lengths, s.kinematic, s.free_slot, s.strand_of_vertex, rho,
                         float(cc.hair_thickness), float(cc.barrier_dhat), float(cc.barrier_stiffness),
                         float(cc.friction_epsilon), bool(cc.friction))


def begin_contact_step(contact: ObjectContact, objective, x_n: np.ndarray, t0: float, t1: float, dt: float,
                       newton_opts=None) -> None:
    """Poses at t1, kappa, and the objective's feasible start (``objective.x_start``) for a step
    begun with ``objective.begin_step``.

    A collider that sweeps over hair during the step (a 10 m/s ball moves 0.4 m per 0.04 s step,
    8 times its radius) is advanced in m sub-intervals (``sub_intervals``): at each intermediate
    pose t0 + k dt / m the start is made feasible (``feasible_start``: elements it reached are
    carried by the pose's small relative motion) and a few Newton iterations on the step's
    objective at that pose (``SUB_INTERVAL_ITERATIONS``) let the hair slide around it; the last
    pose is the step's own.  Carrying the hair by the whole step's motion instead (m = 1) was
    tried: the 10 m/s ball then carried the struck strands 0.4 m ahead of itself every step, they
    stayed trapped in front of it with 11,000 % strain, and Newton stalled (reports/contact.md)."""
    contact.begin(x_n, t0, t1, dt)
    if getattr(objective, "mass_diag", None) is not None:
        contact.vertex_mass = objective.vertex_inertia()
    m = contact.sub_intervals(x_n)
    contact.stats.sub_intervals = m
    x = np.asarray(x_n, dtype=np.float64)
    poses_prev = [c.motion.pose(t0) for c in contact.colliders]
    fv = objective.free_vertices
    for k in range(1, m):
        contact.set_time(t0 + k * dt / m)
        x = x.copy()
        x[contact.kinematic] = objective.x_full[contact.kinematic]
        x = contact.feasible_start(x, x, poses_prev)
        opts = NewtonOptions(max_iterations=SUB_INTERVAL_ITERATIONS)
        if newton_opts is not None:
            opts = NewtonOptions(newton_opts.rtol, newton_opts.atol, SUB_INTERVAL_ITERATIONS, newton_opts.max_backtracks)
        xf, _ = newton_solve(objective, x[fv].reshape(-1), opts)
        x = objective.full_positions(xf)
        poses_prev = contact.poses()
    contact.set_time(t1)
    guess = objective.full_positions(objective.x_pred)
    start = contact.feasible_start(x, guess, poses_prev)
    objective.x_start = start[fv].reshape(-1)


def contact_collision_info(contact: ObjectContact, x: np.ndarray, info_cls):
    """The step's barrier figures as the collision stage's info record (``info_cls``:
    collisions.CollisionInfo), so metrics and summaries read them where they read the stage's."""
    st = contact.end_stats(x)
    ci = info_cls()
    ci.object_contacts = st.contacts
    ci.penetration_max = st.penetration_max
    ci.per_collider = dict(st.per_collider)
    return ci
