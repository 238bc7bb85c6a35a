"""Distances of hair vertices and edges to the analytic collider shapes, and conservative
advancement (CCD) against them: the geometry of the contact barrier (hairexp/physics/barrier.py).

Every collider shape (hairexp/model/colliders.py) is convex (sphere, capsule, box, cylinder) or a
half space (plane), so its signed distance phi is a convex, 1-Lipschitz function of the point.
The gap of an edge ``[a, b]`` is

    d_e(a, b) = min_{s in [0, 1]} phi(a + s (b - a)) - thickness,

the distance of the *whole segment*, not only of its end points: an edge cannot run through a
ball whose centre passes between two vertices (codimensional IPC, Li et al. 2021, measures the
distances of rods' edges for the same reason).  phi along the segment is convex in s, so s* is
unique up to flat parts; closed forms give it for the sphere (closest point of the segment to
the centre), the capsule (closest points of two segments) and the plane (the lower end point);
the box and the cylinder a safeguarded Newton search on the slope of phi along the segment
(``_safeguarded_newton``: closed-form normals and Hessians, bisection across region boundaries).
By the envelope theorem the gradient of d_e
is ((1 - s*) n, s* n), n the unit outward normal at the closest point (Danskin).

Conservative advancement (Mirtich 1996; IPC's additive CCD, Li et al. 2020 sec. 4, uses the same
idea): along a straight move x + alpha p every point of an edge moves at most
alpha max(|p_a|, |p_b|), so d_e(alpha) >= d_e(alpha_k) - (alpha - alpha_k) max(|p_a|, |p_b|).
Stepping alpha_{k+1} = alpha_k + (d_e(alpha_k) - eta d_e(0)) / max(|p_a|, |p_b|) keeps every
intermediate gap above eta d_e(0) > 0 (``CCD_ETA``), so no edge crosses or tunnels through a
shape, however thin, between samples.
"""

from __future__ import annotations

import numpy as np

from hairexp.physics.edge_ccd import _closest_segment_params

#: Golden-section iterations of the closest point on a segment for shapes without a closed form.
GOLDEN_ITERATIONS = 48
_INVPHI = (np.sqrt(5.0) - 1.0) / 2.0
#: Conservative advancement keeps every gap above this fraction of its start value (IPC's ACCD
#: uses a fraction 0.1 of the distance as its target separation, Li et al. 2020 sec. 4).
CCD_ETA = 0.1
#: Conservative-advancement iterations per line search; an element that has not reached
#: alpha = 1 by then stops the step where it is (conservative).
CCD_ITERATIONS = 60
#: Iterations of the safeguarded Newton search of the box's and the cylinder's closest points.
NEWTON_ITERATIONS = 40


def segment_closest(col, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of body-frame segments A B (n, 3) to collider ``col``'s shape: (s (n,), phi
    (n,)) with phi the signed distance (before the thickness) at A + s (B - A)."""
    name = type(col).__name__
    if len(A) == 0:
        return np.zeros(0), np.zeros(0)
    D = B - A
    if name == "Sphere":
        s = np.clip(-np.einsum("ij,ij->i", A, D) / np.maximum(np.einsum("ij,ij->i", D, D), 1e-300), 0.0, 1.0)
    elif name == "Capsule":
        n = len(A)
        p2 = np.tile([0.0, -col.half_length, 0.0], (n, 1))
        q2 = np.tile([0.0, col.half_length, 0.0], (n, 1))
        s, _ = _closest_segment_params(A, B, p2, q2)
    elif name == "Plane":
        s = (B[:, 1] < A[:, 1]).astype(np.float64)
    elif name in ("Box", "Cylinder"):
        s = _safeguarded_newton(col, A, D)
    else:
        s = _golden(col, A, D)
    if name not in ("Sphere", "Capsule", "Plane"):
        # the end points themselves (a minimum at an end is common: a vertex touching a face)
        fs = col.sdf_body(A + s[:, None] * D)
        f0, fb = col.sdf_body(A), col.sdf_body(B)
        s = np.where(f0 < fs, 0.0, s)
        fs = np.minimum(fs, f0)
        s = np.where(fb < fs, 1.0, s)
    return s, col.sdf_body(A + s[:, None] * D)


def _golden(col, A: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Golden-section search of min_s phi(A + s D) on [0, 1] (shapes without closed-form normals)."""
    lo, hi = np.zeros(len(A)), np.ones(len(A))
    m1, m2 = hi - _INVPHI, lo + _INVPHI
    f1 = col.sdf_body(A + m1[:, None] * D)
    f2 = col.sdf_body(A + m2[:, None] * D)
    for _ in range(GOLDEN_ITERATIONS):
        left = f1 < f2          # the minimum lies in [lo, m2]
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
        m2n = np.where(left, m1, lo + _INVPHI * (hi - lo))
        m1n = np.where(left, hi - _INVPHI * (hi - lo), m2)
        f2n = np.where(left, f1, np.nan)
        f1n = np.where(left, np.nan, f2)
        m1, m2 = m1n, m2n
        need1, need2 = np.isnan(f1n), np.isnan(f2n)
        if need1.any():
            f1n[need1] = col.sdf_body(A[need1] + m1[need1, None] * D[need1])
        if need2.any():
            f2n[need2] = col.sdf_body(A[need2] + m2[need2, None] * D[need2])
        f1, f2 = f1n, f2n
    return 0.5 * (lo + hi)


def _safeguarded_newton(col, A: np.ndarray, D: np.ndarray) -> np.ndarray:
    """min_s phi(A + s D) on [0, 1] for the box and the cylinder: phi is convex along the segment,
    so its slope F_s = D . n is nondecreasing in s and its sign brackets s*.  Each iteration
    shrinks the bracket by that sign and takes the Newton step s - F_s / F_ss (closed-form normal
    and Hessian, ``sdf_normal_hessian``) where it stays inside the bracket, else the bracket's
    midpoint: quadratic convergence on a smooth piece, bisection across the shapes' region
    boundaries (face to edge, side to rim).  It replaced a 48-iteration golden-section search, the
    largest cost of a contact iteration on goaling's wheel (10.8 of 17.2 s of its SQP solves)."""
    m = len(A)
    lo, hi = np.zeros(m), np.ones(m)
    n0 = sdf_normal_hessian(col, A)[0]
    n1 = sdf_normal_hessian(col, A + D)[0]
    g0 = np.einsum("mi,mi->m", D, n0)
    g1 = np.einsum("mi,mi->m", D, n1)
    s = np.where(g0 >= 0, 0.0, np.where(g1 <= 0, 1.0, 0.5))
    act = np.flatnonzero((g0 < 0) & (g1 > 0))
    for _ in range(NEWTON_ITERATIONS):
        if act.size == 0:
            break
        Da = D[act]
        n, H = sdf_normal_hessian(col, A[act] + s[act, None] * Da)
        g = np.einsum("mi,mi->m", Da, n)
        h = np.einsum("mi,mij,mj->m", Da, H, Da)
        lo[act] = np.where(g < 0, s[act], lo[act])
        hi[act] = np.where(g > 0, s[act], hi[act])
        sn = s[act] - g / np.where(h > 0, h, 1.0)
        inside = (h > 0) & (sn > lo[act]) & (sn < hi[act])
        sn = np.where(inside, sn, 0.5 * (lo[act] + hi[act]))
        step = np.abs(sn - s[act])
        s[act] = sn
        act = act[(step > 1e-15) & (g != 0) & (hi[act] > lo[act])]
    return s


class EdgeGaps:
    """Gaps of hair edges to one collider at a fixed pose (R, T): world x = R X + T."""

    def __init__(self, col, R: np.ndarray, T: np.ndarray):
        self.col, self.R, self.T = col, R, T

    def body(self, x: np.ndarray) -> np.ndarray:
        return (x - self.T) @ self.R

    def vertex_gaps(self, x: np.ndarray) -> np.ndarray:
        """(V,) phi(x) - thickness of world points x (V, 3)."""
        return self.col.sdf_body(self.body(x)) - self.col.thickness

    def edge_gaps(self, xa: np.ndarray, xb: np.ndarray, normals: bool = False):
        """Gaps of world segments xa xb (n, 3): d (n,), and with ``normals`` also s (n,) and the
        world unit normals (n, 3) at the closest points."""
        A, B = self.body(xa), self.body(xb)
        s, phi = segment_closest(self.col, A, B)
        d = phi - self.col.thickness
        if not normals:
            return d
        if len(A) == 0:
            return d, s, np.zeros((0, 3))
        P = A + s[:, None] * (B - A)
        n = shape_normal(self.col, P) @ self.R.T
        return d, s, n

    def edge_lower_bound(self, xa: np.ndarray, xb: np.ndarray, ga: np.ndarray, gb: np.ndarray) -> np.ndarray:
        """A lower bound of the edge gaps from the end points' gaps ga, gb: every point of the
        segment is within |b - a| / 2 of an end point and phi is 1-Lipschitz."""
        return np.minimum(ga, gb) - 0.5 * np.linalg.norm(xb - xa, axis=1)


def advance(gaps: EdgeGaps, xa, xb, pa, pb, alpha_hi: float = 1.0, eta: float = CCD_ETA) -> np.ndarray:
    """Per edge, the largest alpha in [0, alpha_hi] reached by conservative advancement along
    xa + alpha pa, xb + alpha pb with every gap on the way above ``eta`` times its start value.
    Edges already at gap <= 0 get alpha 0.  With eta = 0 an alpha < alpha_hi means the path
    reaches the shell (to the advancement's convergence).

    The bound of each advancement step is the separating plane of two convex sets (the shape's
    thickness shell is convex; Boyd & Vandenberghe 2004, 8.2): at alpha_k, with y* the closest
    point of the segment, n* the shape's normal there and d_k the gap, the plane n*.y = n*.y* - d_k
    supports the shell and the whole segment lies on its far side, so for alpha > alpha_k

        d(alpha) >= min over the end points e of  g_e + (alpha - alpha_k) n*.p_e,
        g_e = n*.(x_e - y*) + d_k >= d_k

    (a linear function over a segment is smallest at an end point).  Unlike the Lipschitz bound
    d_k - (alpha - alpha_k) max |p_e|, it lets hair slide along a surface (n*.p ~ 0) in one step
    even at a tiny gap; both are rigorous for convex shapes."""
    d0 = gaps.edge_gaps(xa, xb)
    speed = np.maximum(np.linalg.norm(pa, axis=1), np.linalg.norm(pb, axis=1))
    out = np.full(len(xa), alpha_hi)
    cand = (d0 - alpha_hi * speed < eta * d0) & (speed > 0)   # the others cannot come closer than eta d0
    out[d0 <= 0] = 0.0
    cand &= d0 > 0
    idx = np.flatnonzero(cand)
    floor = eta * d0[idx]
    a = np.zeros(idx.size)
    active = np.ones(idx.size, dtype=bool)
    for _ in range(CCD_ITERATIONS):
        j = np.flatnonzero(active)
        if j.size == 0:
            break
        i = idx[j]
        A = xa[i] + a[j, None] * pa[i]
        B = xb[i] + a[j, None] * pb[i]
        d, s, n = gaps.edge_gaps(A, B, normals=True)
        y = A + s[:, None] * (B - A)
        steps = []
        for X, P in ((A, pa[i]), (B, pb[i])):
            g = np.einsum("ij,ij->i", n, X - y) + d
            v = np.einsum("ij,ij->i", n, P)
            steps.append(np.where(v < 0, (g - floor[j]) / np.maximum(-v, 1e-300), np.inf))
        step = np.minimum(*steps)
        step = np.where(d > floor[j], step, 0.0)
        a_new = np.minimum(a[j] + np.maximum(step, 0.0), alpha_hi)
        done = a_new >= alpha_hi
        stalled = ~done & (a_new - a[j] <= 1e-3 * (a[j] + 1e-12))   # converged onto the floor: stop here
        a[j] = np.where(stalled, a[j], a_new)
        active[j[done | stalled]] = False
    out[idx] = a
    return out


def shape_normal(col, X: np.ndarray) -> np.ndarray:
    """Unit outward normals (body frame) at body points X: closed form for the analytic shapes
    (``sdf_normal_hessian``), the collider's own (central differences) for any other."""
    try:
        return sdf_normal_hessian(col, X)[0]
    except ValueError:
        return col.normal_body(X)


def sdf_normal_hessian(col, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form unit normal grad phi (n, 3) and Hessian hess phi (n, 3, 3) of the shape's
    signed distance at body-frame points X (n, 3) outside it (the barrier's curvature term).

    Each shape's phi outside it is the distance |X - c(X)| to its closest surface point c (minus a
    radius): hess phi = (I - n n^T) (I - grad c) / rho, rho = |X - c|.  Sphere: c the centre
    (radius subtracted), hess = (I - n n^T) / rho.  Capsule: c on the axis segment; beside it
    grad c = e_y e_y^T, so hess = (I - n n^T - e_y e_y^T) / rho; beyond its ends a sphere's.
    Box: c clamps X to the box; grad c = I - P, P the coordinates outside the slab, so
    hess = (P - n n^T) / rho (0 on a face, a cylinder's along an edge, a sphere's at a corner).
    Cylinder (axis y): beside the side c has the same height and grad c = e_y e_y^T + (R / r) t t^T,
    t the circumferential unit: hess = t t^T / r; above a cap c is the cap point: hess = 0; beyond
    the rim c = R u + h e_y (u radial): hess = ((I - n n^T) - (R / r) t t^T) / rho.  Plane: 0.
    Inside a shape (never evaluated at a feasible iterate) the face or side formulas are used."""
    name = type(col).__name__
    X = np.asarray(X, dtype=np.float64)
    m = len(X)
    I3 = np.eye(3)
    n = np.zeros((m, 3))
    H = np.zeros((m, 3, 3))
    if m == 0:
        return n, H
    if name == "Plane":
        n[:, 1] = 1.0
        return n, H
    if name in ("Sphere", "Capsule"):
        Q = X.copy()
        if name == "Capsule":
            Q[:, 1] -= np.clip(X[:, 1], -col.half_length, col.half_length)
        rho = np.maximum(np.linalg.norm(Q, axis=1), 1e-300)
        n = Q / rho[:, None]
        P = np.broadcast_to(I3, (m, 3, 3)).copy()
        if name == "Capsule":
            beside = np.abs(X[:, 1]) < col.half_length
            P[beside, 1, 1] = 0.0
        H = (P - n[:, :, None] * n[:, None, :]) / rho[:, None, None]
        return n, H
    if name == "Box":
        h = np.asarray(col.half_extents, dtype=np.float64)
        q = np.abs(X) - h
        sg = np.where(X < 0, -1.0, 1.0)
        out = q > 0
        outside = out.any(axis=1)
        v = sg * np.maximum(q, 0.0)
        rho = np.maximum(np.linalg.norm(v, axis=1), 1e-300)
        n[outside] = v[outside] / rho[outside, None]
        k = np.argmax(q, axis=1)
        ins = ~outside
        n[ins, k[ins]] = sg[ins, k[ins]]
        Pm = out[:, :, None] * I3[None]
        Ho = (Pm - n[:, :, None] * n[:, None, :]) / rho[:, None, None]
        H[outside] = Ho[outside]
        return n, H
    if name == "Cylinder":
        R, hh = float(col.radius), float(col.half_height)
        r = np.maximum(np.hypot(X[:, 0], X[:, 2]), 1e-300)
        u = np.stack([X[:, 0] / r, np.zeros(m), X[:, 2] / r], axis=1)
        t = np.stack([-u[:, 2], np.zeros(m), u[:, 0]], axis=1)       # e_y x u
        sy = np.where(X[:, 1] < 0, -1.0, 1.0)
        ey = np.zeros((m, 3))
        ey[:, 1] = sy
        d0, d1 = r - R, np.abs(X[:, 1]) - hh
        tt = t[:, :, None] * t[:, None, :]
        rim = (d0 > 0) & (d1 > 0)
        side = ~rim & (d0 >= d1)
        cap = ~rim & ~side
        n[side], n[cap] = u[side], ey[cap]
        H[side] = tt[side] / r[side, None, None]
        if rim.any():
            rho = np.hypot(d0[rim], d1[rim])
            nr = (d0[rim, None] * u[rim] + d1[rim, None] * ey[rim]) / rho[:, None]
            n[rim] = nr
            H[rim] = ((I3 - nr[:, :, None] * nr[:, None, :]) - (R / r[rim])[:, None, None] * tt[rim]) / rho[:, None, None]
        return n, H
    raise ValueError(f"no closed-form curvature for {name}")


def edge_distance_hessian(Hphi: np.ndarray, n: np.ndarray, D: np.ndarray, s: np.ndarray,
                          interior: np.ndarray) -> np.ndarray:
    """hess d (m, 6, 6) of the edge gap d(a, b) = min_s phi(a + s (b - a)) - thickness w.r.t.
    (a, b), from phi's normal n and Hessian Hphi at the closest point and D = b - a (all in one
    frame).  With F(x, s) = phi(a + s D) and J = [(1 - s) I, s I] (3 x 6):
    F_xx = J^T Hphi J, F_xs = J^T Hphi D + (-n, n), F_ss = D^T Hphi D; an interior minimiser s*
    moves with x (F_s = 0 implicitly), so hess d = F_xx - F_xs F_xs^T / F_ss (implicit function
    theorem); at an end point (``interior`` False) s is fixed and hess d = F_xx.  Where F_ss
    vanishes (an edge along a flat face) the interior minimiser is not unique and the end-point
    form is kept."""
    m = len(s)
    w = np.stack([1.0 - s, s], axis=1)                                      # (m, 2)
    Fxx = (w[:, :, None, None, None] * w[:, None, :, None, None]) * Hphi[:, None, None]   # (m, 2, 2, 3, 3)
    Fxx = Fxx.transpose(0, 1, 3, 2, 4).reshape(m, 6, 6)
    HD = np.einsum("mij,mj->mi", Hphi, D)
    Fss = np.einsum("mi,mi->m", D, HD)
    Fxs = np.concatenate([w[:, :1] * HD - n, w[:, 1:] * HD + n], axis=1)    # (m, 6)
    tr = np.einsum("mii->m", Hphi)
    ok = interior & (Fss > 1e-9 * np.einsum("mi,mi->m", D, D) * tr)
    out = Fxx.copy()
    if ok.any():
        out[ok] -= Fxs[ok, :, None] * Fxs[ok, None, :] / Fss[ok, None, None]
    return out
