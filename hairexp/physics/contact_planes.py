"""The collision stage's contacts taken back into the solve (``collision.resolve``).

The post-solve stage (hairexp/physics/collisions.py) puts vertices that the solve drove into a
collider back on its surface, but the solve never saw the collider: the rest of the strand
finished its move, so the edges next to a contact stretch (up to the strain limiter's clamp,
10 % by default), and the next step's solve starts from that strain.  With ``collision.resolve``
the stage's contacts become one-sided linear constraints of the step, enforced by a stiff
penalty, and the step is solved again:

    g_i(x) = d_i + n_i . (y_i(x) - p_i) >= 0,      E_c(x) = sum_i k_i / 2 min(g_i(x), 0)^2,

on every movable vertex within ``NEAR`` of a collider's thickness shell after the stage (or
inside it in the solve's result the stage corrected), and on the interior closest point of every
edge within ``NEAR`` of it (an edge that dips into a collider between its vertices: the stage's
edge response), at the collider's end-of-step pose: y_i(x) is the vertex, or (1 - s_i) x_a +
s_i x_b for the edge's point at parameter s_i, p_i its position after the stage, n_i the
collider's outward normal there and d_i its distance to the shell.  The plane is the first-order
model of the shell at p_i, a supporting plane of the five convex shapes (a penalty on the signed
distance linearised about the stage's point, as the linearised contact constraints of an
active-set method, e.g. Otaduy et al. 2009, "Implicit contact handling for deformable objects").

The penalty (``ContactPlanes.psi``) is the one-sided quadratic psi(g) = k/2 min(g, 0)^2 (C^1; the
exterior quadratic penalty of constrained optimisation, Nocedal and Wright 2006, 17.1): its force
grows linearly with the depth g < 0 below the shell's surface, so the Newton model of a point in
contact is exact once the set of pressed planes is found, and hair the penalty holds ends F / k
inside the shell (k = ``STIFFNESS`` times the point's inertia m / h^2 of the step: about
1 / STIFFNESS of the step's displacement), where the stage counts a contact and applies its
inelastic contact and Coulomb friction to the velocities.  A C^2 form tried first (psi'' rising
linearly over a layer of a quarter thickness above the plane's zero) converged linearly: its force
grows with the depth squared in the layer, where lightly pressed hair rests, and Newton's iterates
on a square law halve the distance to the root each time (goaling tracked 4-6 SQP iterations a
solve at a constant set of pressed planes; with the quadratic 8.25 -> 7.86 SQP iterations a step,
27.0 -> 23.6 in its contact steps, reports/contact.md).  The Hessian k (w w^T) (x) (n n^T),
w = (1 - s, s), on the pressed planes is positive semi-definite: Newton's step and the SQP's stay
descent directions (taking it on the planes not pressed too stalled Newton on hair leaving a
collider, whose steps along n it cut by the stiffness).

The re-solved positions then go through the collision stage again, which places the small
penetrations the penalty leaves (micrometres) and applies the inelastic contact and
Coulomb friction to the velocities: the hair wraps around the collider in the solve instead of
being stretched by the stage; its friction is bounded by the normal velocity the planes' forces
gave (``vertex_forces``), as they leave it no approaching velocity to remove.  With
``collision.plane_friction`` the resting contacts' friction is in the solve instead
(``set_friction``: IPC's smoothed, lagged friction).  Interface: the objective's ``contact`` hooks
(hairexp/physics/objective.py, as the barrier's ObjectContact): ``energy``, ``add_to``,
``update_lag``, ``max_step``.
"""

from __future__ import annotations

import numpy as np

from hairexp.physics.assembly import add_pair_blocks
from hairexp.physics.barrier import smoothed_friction, surface_displacement, tangent_bases
from hairexp.physics.contact_geometry import EdgeGaps

#: penalty stiffness / the vertex's inertia m / h^2 of the step
STIFFNESS = 1e4
#: vertices within this many shell tolerances plus this fraction of the collider's thickness
#: of its shell after the stage get a plane (the placed ones are on it)
NEAR = 0.5


class ContactPlanes:
    """One-sided penalty planes on points of hair edges (see the module doc).

    ``edges`` (n, 2) vertex indices, ``s`` (n,) the points' parameters along them, ``normals``
    (n, 3) unit outward normals, ``points`` (n, 3) the planes' points, ``gaps`` (n,) g there (the
    points' distances to the shell), ``stiffness`` (n,) N/m, ``collider`` (n,) each plane's
    collider; ``free_slot`` (V,) the free index of each vertex, -1 for a kinematic one
    (hairexp/model/strands.py)."""

    def __init__(self, edges, s, normals, points, gaps, stiffness, free_slot, collider=0):
        self.e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        s = np.asarray(s, dtype=np.float64)
        self.w = np.stack([1.0 - s, s], axis=1)                                # (n, 2)
        self.n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        self.c = np.asarray(gaps, dtype=np.float64) - np.einsum("ij,ij->i", self.n, np.asarray(points, dtype=np.float64))
        self.k = np.asarray(stiffness, dtype=np.float64)
        self.slot = np.asarray(free_slot)[self.e]                              # (n, 2), -1: kinematic
        self.collider = np.broadcast_to(np.asarray(collider, dtype=np.int64), self.k.shape).copy()
        self._fric = None   # set_friction's (planes (m,), mu (m,), T (m, 3, 2), y_n (m, 3), dc (m, 3), eps);
        #                     its normal forces' cap ``_cap`` and lag ``_lam`` (m,) (``update_lag``)

    def __len__(self) -> int:
        return len(self.e)

    def vertices(self) -> np.ndarray:
        """The vertices with a plane of their own (s = 0 on a degenerate edge (v, v))."""
        return np.unique(self.e[self.e[:, 0] == self.e[:, 1], 0])

    def points(self, x: np.ndarray, sel=slice(None)) -> np.ndarray:
        """y_i(x) (m, 3) of the planes ``sel``: their points on the hair at full positions x (V, 3)."""
        e, w = self.e[sel], self.w[sel]
        return w[:, 0, None] * x[e[:, 0]] + w[:, 1, None] * x[e[:, 1]]

    def gap(self, x: np.ndarray) -> np.ndarray:
        """g_i(x) (n,) for full positions x (V, 3)."""
        return self.c + np.einsum("ij,ij->i", self.n, self.points(x))

    def stale(self, colliders, x: np.ndarray, t: float) -> np.ndarray:
        """(n,) bool: planes the positions x (V, 3) press on (g < 0) whose edge is farther than
        ``NEAR`` from its collider's shell at time t: a supporting plane that holds hair which
        has slid past the part of the surface it was taken at (off a curved surface, round a
        box's edge), where the surface itself would let it go."""
        out = np.zeros(len(self.e), dtype=bool)
        on = self.gap(x) < 0.0
        for i, col in enumerate(colliders):
            sel = np.flatnonzero(on & (self.collider == i))
            if sel.size == 0:
                continue
            gp = EdgeGaps(col, *col.motion.pose(t))
            d = gp.edge_gaps(x[self.e[sel, 0]], x[self.e[sel, 1]])
            out[sel] = d > col.shell_tolerance() + NEAR * col.thickness
        return out

    # -- the penalty psi(g): one-sided quadratic ---------------------------------------------
    def psi(self, g: np.ndarray, sel=slice(None)):
        """(psi, psi', psi'') of the planes ``sel`` at their gaps g: k/2 g^2, k g, k below the
        plane (g < 0), 0 on and beyond it (module doc)."""
        k = self.k[sel]
        u = np.minimum(g, 0.0)
        return 0.5 * k * u * u, k * u, np.where(g < 0.0, k, 0.0)

    def vertex_forces(self, x: np.ndarray, n_colliders: int) -> np.ndarray:
        """(n_colliders, V) the magnitudes (N) of each collider's planes' normal forces on each
        vertex of x (V, 3): an edge point's force shared by its ends by the weights w.  The collision
        stage's Coulomb friction is bounded by them (``contact_velocities``' ``push``)."""
        f = -self.psi(self.gap(x))[1]                    # >= 0
        V = len(x)
        out = np.zeros((n_colliders, V))
        for j in range(2):
            np.add.at(out, (self.collider, self.e[:, j]), self.w[:, j] * f)
        return out

    # -- friction of resting contact: smoothed Coulomb (IPC, Li et al. 2020, sec. 5) ------------
    def set_friction(self, colliders, x_n: np.ndarray, t0: float, t1: float, eps_v: float, lam: np.ndarray) -> None:
        """Coulomb friction on the planes with a normal force ``lam`` (n,) N > 0 (the previous
        step's, ``Simulator._with_friction``: the cap of the force lagged at each evaluation,
        ``update_lag``) on a collider with ``friction`` mu > 0: the tangential displacement of
        the plane's point over the stage
        relative to the collider's surface there, u = T^T (y(x) - y(x_n) - dc) (T the plane's
        tangent basis, dc the surface point's displacement from t0 to t1: rigid motion and spin),
        gets the potential mu lam f0(|u|) (``barrier.f0_friction``, eps = eps_v (t1 - t0): slower
        slip is static).  The stage's friction on the velocities cannot stop a slide the solve
        made: with it alone a strand lying across a 20 degree slope (mu 0.8) slid 40 mm in 1 s."""
        mu = np.array([float(colliders[c].friction) for c in self.collider]) if len(self.e) else np.zeros(0)
        sel = np.flatnonzero((mu > 0) & (np.asarray(lam) > 0))
        if sel.size == 0:
            return
        y = self.points(x_n, sel)
        dc = np.zeros_like(y)
        dt = float(t1 - t0)
        for i, col in enumerate(colliders):
            on = np.flatnonzero(self.collider[sel] == i)
            if on.size:
                dc[on] = surface_displacement(col, y[on], *col.motion.pose(t1), t0, dt)
        self._fric = (sel, mu[sel], tangent_bases(self.n[sel]), y, dc, max(float(eps_v) * dt, 1e-12))
        self._cap = np.asarray(lam, dtype=np.float64)[sel]
        self._lam = self._cap.copy()

    def friction_vertices(self, n_colliders: int, n_vertices: int) -> np.ndarray | None:
        """(colliders, V) bool: the vertices whose planes carry friction in the solve; None when
        none does."""
        if self._fric is None:
            return None
        out = np.zeros((n_colliders, n_vertices), dtype=bool)
        sel = self._fric[0]
        for j in range(2):
            out[self.collider[sel], self.e[sel, j]] |= self.w[sel, j] > 0
        return out

    def _friction(self, x: np.ndarray, need_hessian: bool):
        """(energy, gradient (m, 6), Hessian (m, 6, 6) or None) of the friction planes at x
        (``barrier.smoothed_friction``)."""
        sel, mu, T, y_n, dc, eps = self._fric
        return smoothed_friction(T, mu * self._lam, self.points(x, sel) - y_n - dc, self.w[sel], eps, need_hessian)

    # -- the objective's contact hooks ------------------------------------------------------
    @property
    def lagged(self) -> bool:
        """With friction its normal forces are lagged (``update_lag``): the solvers re-take the
        objective's value after each evaluation; without, nothing is lagged."""
        return self._fric is not None

    def update_lag(self, x: np.ndarray) -> None:
        """The friction's normal forces at x: each friction plane's penalty force k max(-g, 0),
        at most the previous step's (a first iterate deep in the collider does not lock the hair)."""
        if self._fric is not None:
            sel = self._fric[0]
            self._lam = np.minimum(self._cap, -self.psi(self.gap(x)[sel], sel)[1])

    def energy(self, x: np.ndarray) -> float:
        e = float(self.psi(self.gap(x))[0].sum())
        if self._fric is not None:
            e += self._friction(x, False)[0]
        return e

    def add_to(self, x: np.ndarray, grad: np.ndarray, ab: np.ndarray | None) -> float:
        """Add the gradient to ``grad`` (N,) and the Hessian to the lower band ``ab`` (bw + 1, N)
        of the free DOFs; returns the norm of the penalty force."""
        g = self.gap(x)
        on = g < 0.0
        if self._fric is not None:
            _, gf, Hf = self._friction(x, ab is not None)
            add_pair_blocks(grad, ab, self.slot[self._fric[0]], gf, Hf)
        if not on.any():
            return 0.0
        _, d1, d2 = self.psi(g[on], on)
        n, w = self.n[on], self.w[on]
        ge = (w[:, :, None] * (d1[:, None] * n)[:, None, :]).reshape(-1, 6)   # dE/dx of the two ends
        H = None
        if ab is not None:   # psi'' (w w^T) (x) (n n^T)
            H = np.einsum("m,mi,mj,mk,ml->mikjl", d2, w, w, n, n).reshape(-1, 6, 6)
        slot = self.slot[on]
        add_pair_blocks(grad, ab, slot, ge, H)
        free = np.repeat(slot >= 0, 3, axis=1)
        return float(np.sqrt(np.sum(ge[free] ** 2)))   # the planes' forces on the free ends, each counted alone

    def max_step(self, x: np.ndarray, p: np.ndarray) -> float:
        """The penalty is finite everywhere: no step bound."""
        return 1.0


def stage_planes(colliders, x: np.ndarray, t: float, edges: np.ndarray, movable: np.ndarray, free_slot: np.ndarray,
                 inertia: np.ndarray, x_first: np.ndarray | None = None,
                 keep: "ContactPlanes | None" = None, moved: np.ndarray | None = None) -> ContactPlanes | None:
    """Planes at positions x (V, 3) and time t (the collision stage's output), or None when there
    is none: one at every movable vertex within ``NEAR`` of a collider's shell there, or inside
    the shell at ``x_first`` (the solve's positions the stage corrected: the stage may leave a vertex
    whose path met the moving collider a few millimetres off its end-of-step shell), and one at the
    interior closest point of every edge within ``NEAR`` of the shell there (the edge response's).
    ``inertia`` (V,): each vertex's m / h^2 of the step (0 for the kinematic ones).  ``keep``:
    planes whose vertices and edges get one again, taken at x, wherever they are (the active set
    of a solve only grows: a plane dropped because the hair sat beyond ``NEAR`` let it fall back
    in the next solve).  ``moved`` (V,) m: 0 for a vertex the collision stage did not move, else a
    reach (the stage's move, or the solve's path when longer); a moved vertex gets a plane of each
    collider within that reach (plus ``NEAR``) of it, wherever it ends (a path the stage stopped
    where it met a collider can end far from the collider's shell at the step's end)."""
    E = np.asarray(edges)
    E = E[movable[E[:, 0]] | movable[E[:, 1]]]
    idx = np.flatnonzero(movable)
    out = {k: [] for k in "esnpdmc"}

    def add(e, s_, n, p, d, m):
        for k, v in zip("esnpdmc", (e, s_, n, p, d, m, np.full(len(e), ci))):
            out[k].append(v)

    for ci, col in enumerate(colliders):
        gp = EdgeGaps(col, *col.motion.pose(t))
        near = col.shell_tolerance() + NEAR * col.thickness
        gv = gp.vertex_gaps(x)
        sel = gv[idx] < near
        if x_first is not None:
            sel |= gp.vertex_gaps(x_first[idx]) < near
        if moved is not None:
            sel |= (moved[idx] > 0.0) & (gv[idx] < moved[idx] + near)
        forced = np.zeros(len(E), dtype=bool)
        if keep is not None:
            mine = keep.collider == ci
            vtx = mine & (keep.e[:, 0] == keep.e[:, 1])
            kept_v = np.zeros(len(x), dtype=bool)
            kept_v[keep.e[vtx, 0]] = True
            sel |= kept_v[idx]
            ke = keep.e[mine & ~vtx]   # the kept edge planes' edges, matched by a key a V + b
            forced = np.isin(E[:, 0] * len(x) + E[:, 1], ke[:, 0] * len(x) + ke[:, 1])
        v = idx[sel]
        if v.size:
            add(np.stack([v, v], axis=1), np.zeros(v.size), col.normal(x[v], t), x[v], gv[v], STIFFNESS * inertia[v])
        cand = np.flatnonzero((gp.edge_lower_bound(x[E[:, 0]], x[E[:, 1]], gv[E[:, 0]], gv[E[:, 1]]) < near) | forced)
        if cand.size == 0:
            continue
        d, s_, n = gp.edge_gaps(x[E[cand, 0]], x[E[cand, 1]], normals=True)
        use = ((d < near) | forced[cand]) & (s_ > 0.0) & (s_ < 1.0)
        if not use.any():
            continue
        e, s_ = E[cand[use]], s_[use]
        m = np.where(movable[e], inertia[e], np.inf).min(axis=1)
        add(e, s_, n[use], (1.0 - s_)[:, None] * x[e[:, 0]] + s_[:, None] * x[e[:, 1]], d[use], STIFFNESS * m)
    if not out["e"]:
        return None
    c = {k: np.concatenate(v) for k, v in out.items()}
    return ContactPlanes(c["e"], c["s"], c["n"], c["p"], c["d"], c["m"], free_slot, c["c"])
