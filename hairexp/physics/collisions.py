"""The collision stage of a step (paper 3.4, after Bridson et al. 2002): after the solve,
detect contacts over the step and filter the end-of-step positions and velocities.

Hair against objects: each free vertex's path over the step is taken into the collider's body
frame at both ends (x_n at t_n, x_{n+1} at t_{n+1}), where the collider is static.  Conservative
advancement on the signed distance (1-Lipschitz) finds the first time the path comes within
the thickness, so a fast vertex cannot tunnel through a thin collider.  From the contact point
the rest of the move keeps only its tangential part, reduced by Coulomb friction relative to
the surface (spin included); the end position is projected outside; the normal relative
velocity is made non-negative (inelastic) and the tangential one is reduced by friction.

Hair against hair: pairs whose edges meet during the step (exact continuous edge-edge test on
the linear motion, ``edge_ccd``) get inelastic impulses; edges within the hair thickness at the
end of the step get repulsion impulses.  Impulses act at the closest points with barycentric weights,
so they are equal and opposite (linear momentum is conserved).  Adjacent edges of a strand are
excluded.  Passes repeat up to ``max_passes``; a later pass tests only the edge pairs with an edge
whose vertices the pass before moved or slowed (the others would get no impulse again).

The hair-hair broad phase (``HairHair.neighbours``) works in a frame that co-moves with the
hair (the best-fit rigid motion of each step removed, so distances are unchanged and a
swinging groom is nearly still), keeps a Verlet neighbour list there while the motion is calm,
and falls back to swept boxes on violent steps; boxes are paired on a uniform grid
(hairexp/physics/broad_phase.py, compiled; without numba ``scipy.spatial.cKDTree`` queries).
``filter_reachable`` then drops pairs whose start distance exceeds h plus the most
their vertices' displacements can close it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from hairexp.model.colliders import Box, Capsule, Cylinder, Plane, Sphere
from hairexp.physics.broad_phase import (centred_cross, contact_impulses, edge_edge_ccd_pairs, frame_positions,
                                         grid_pairs, pair_distances, reachable, rotation_matrix, rotation_vector,
                                         swept_boxes)
from hairexp.physics.contact_geometry import EdgeGaps
from hairexp.physics.edge_ccd import BISECTIONS, _closest_segment_params, edge_edge_ccd
from hairexp.physics.kernels import HAVE_NUMBA, njit, read_only

#: Conservative-advancement iterations and tolerance (fraction of the thickness or 1e-6 m).
CA_ITERATIONS, CA_TOL = 40, 1e-6
#: Quantiles of the bounding-sphere radius that split the broad phase's boxes into classes.
CLASS_QUANTILES = (0.5, 0.9, 1.0)
#: Most rounds of strain limiting (each followed by the object and edge responses to its moves)
#: after a step with contacts; the rounds stop as soon as a round moves nothing.  A strand pressed
#: 45 degrees over a rising box rim (tests/test_collisions.py) needs 183 rounds since the edges are
#: kept out of the colliders as well (its edges 6 mm into the box before, at 100 rounds then)
LIMIT_ROUNDS = 300
#: The first rounds hold the vertices in contact (their neighbours come to them); later rounds move
#: them too (two vertices held farther apart than their chain allows, e.g. on either side of a rim).
PIN_ROUNDS = 16
#: A round whose limiter and object response move no vertex by more than this (m) ends the rounds.
LIMIT_TOL = 1e-10
#: Fraction of the overlap (h - d) removed per step by the repulsion impulse (Bridson 2002, 7.2).
REPULSION = 0.25


@dataclass
class CollisionInfo:
    object_contacts: int = 0
    hair_contacts: int = 0
    penetration_max: float = 0.0      # m, deepest end-of-step penetration into a collider's thickness after the stage
    passes: int = 0
    broad_phases: dict = field(default_factory=dict)   # hair-hair broad phase: {"reused"|"rebuilt"|"swept": passes}
    strain_limited: int = 0           # edges over the strain limit after the contacts, shortened
    limit_rounds: int = 0             # rounds of strain limiting and object response (limit_strain)
    edge_contacts: int = 0            # edges pushed out of a collider's shell (edge_response; also in object_contacts)
    restored: int = 0                 # rounds of the controller's constraints restored after the stage (Simulator._restore)
    resolved: int = 0                 # contact planes of the step's second solve (collision.resolve, Simulator._resolve_contacts)
    resolve_failed: int = 0           # 1: that second solve did not converge and the stage's result stood
    candidates: int = 0               # most hair-hair edge pairs that reached the narrow phase in a pass
    seconds: float = 0.0
    per_collider: dict = field(default_factory=dict)


def object_stage(colliders, x0, x1, t0, t1, dt, movable, dist_out: list | None = None, discrete: bool = False,
                 push: np.ndarray | None = None, solved: np.ndarray | None = None):
    """Returns corrected (x1, v1, contacts, contacts per collider).  ``dist_out``: a list that
    gets, when there was no contact (x1 is the input's), each collider's signed distance minus
    thickness of the movable vertices at x1 and t1 (``Collider.distance``), which the path test
    computed; left empty otherwise.  ``discrete``: the end points alone are tested and projected
    onto the shells (no path, no positional friction; the velocities' inelastic contact and
    Coulomb friction as always): after a solve that saw the contacts (``collision.resolve``), whose
    end points left a collider's surface along it, where a straight path x0 -> x1 would cut
    through the collider and be stopped inside it.  ``push``, ``solved``: see ``contact_velocities``."""
    dist: list = []
    if discrete:
        x1, contacts, per = object_positions(colliders, x1, x1, t1, t1, 0.0, movable, friction=False, dist_out=dist)
    else:
        x1, contacts, per = object_positions(colliders, x0, x1, t0, t1, dt, movable, dist_out=dist)
    known = dist if contacts == 0 else None
    if dist_out is not None and known is not None:
        dist_out.extend(known)
    return (x1, contact_velocities(colliders, x1, (x1 - x0) / dt, t1, movable, dist=known, push=push, solved=solved),
            contacts, per)


def object_positions(colliders, x0, x1, t0, t1, dt, movable, friction: bool = True, dist_out: list | None = None):
    """Positions of the object response: paths x0 (at t0) -> x1 (at t1) are stopped where
    they first come within a collider's thickness, keep their tangential rest (friction,
    surface spin over ``dt``), and end outside.  ``friction=False``: the tangential rest is
    kept whole (the strain limiter's moves are a projection, not motion over the step: Coulomb
    friction on them, scaled by their normal part, stalled the limiter on a curved surface).
    Returns (x1, contacts, per collider).  ``dist_out``: a list that gets each collider's d1 (the
    end points' signed distance minus thickness, at the x1 that collider saw: all of them x1's
    when there was no contact)."""
    x1 = x1.copy()
    contacts = 0
    idx = np.flatnonzero(movable)
    per = {}
    for col in colliders:
        X0, X1, d0, d1, L = path_test(col, x0, x1, idx, t0, t1)
        th = col.thickness
        if dist_out is not None:
            dist_out.append(d1)
        D = X1 - X0
        cand = (d1 < 0) | (d0 - L < 0)
        if not cand.any():
            per[col.name] = 0
            continue
        ci = np.flatnonzero(cand)
        s = np.zeros(ci.size)
        hit = np.zeros(ci.size, dtype=bool)
        active = np.ones(ci.size, dtype=bool)
        tol = max(CA_TOL, 1e-3 * th)
        for _ in range(CA_ITERATIONS):
            a = np.flatnonzero(active)
            if a.size == 0:
                break
            X = X0[ci[a]] + s[a, None] * D[ci[a]]
            d = col.sdf_body(X) - th
            close = d <= tol
            hit[a[close]] = True
            active[a[close]] = False
            step = np.where(L[ci[a]] > 0, d / np.maximum(L[ci[a]], 1e-300), np.inf)
            s[a] = s[a] + np.where(close, 0.0, step)
            beyond = ~close & (s[a] > 1.0)
            active[a[beyond]] = False
        hit |= active       # still approaching after the iteration cap (grazing paths): stop there, conservatively
        hit |= d1[ci] < 0  # ends within the thickness (e.g. the collider moved onto it)
        s = np.clip(s, 0.0, 1.0)
        h = ci[hit]
        if h.size == 0:
            per[col.name] = 0
            continue
        sh = s[hit]
        Xc = X0[h] + sh[:, None] * D[h]
        n = col.normal_body(Xc)
        Xc = Xc + np.maximum(th - col.sdf_body(Xc), 0.0)[:, None] * n      # contact point on the shell
        rest = X1[h] - Xc                                                  # remaining relative move
        spin = dt * (1.0 - sh)[:, None] * col.spin_velocity_body(Xc)       # surface motion over the rest
        rel = rest - spin
        rn = np.sum(rel * n, axis=1)
        into = np.minimum(rn, 0.0)
        rel_t = rel - rn[:, None] * n
        rel_n = np.maximum(rn, 0.0)[:, None] * n
        tn = np.linalg.norm(rel_t, axis=1)
        mu = col.friction if friction else 0.0
        scale = np.where(tn > 0, np.maximum(0.0, 1.0 - mu * (-into) / np.maximum(tn, 1e-300)), 1.0)
        Xe = Xc + spin + rel_t * scale[:, None] + rel_n
        for _ in range(3):  # project outside the shell (curved surfaces)
            de = col.sdf_body(Xe) - th
            Xe = Xe + np.maximum(-de, 0.0)[:, None] * col.normal_body(Xe)
        R, T = col.motion.pose(t1)
        x1[idx[h]] = Xe @ R.T + T
        contacts += h.size
        per[col.name] = int(h.size)
    return x1, contacts, per


def _shape_code(col) -> tuple[int, np.ndarray]:
    """(code, parameters) of a collider whose signed distance ``_path_test`` has compiled: its
    class exactly one of the shapes (a subclass may define another ``sdf_body``); code -1: none."""
    kind = type(col)
    if kind is Sphere:
        return 0, np.array([col.radius], dtype=np.float64)
    if kind is Capsule:
        return 1, np.array([col.radius, col.half_length], dtype=np.float64)
    if kind is Box:
        return 2, np.asarray(col.half_extents, dtype=np.float64).reshape(3)
    if kind is Cylinder:
        return 3, np.array([col.radius, col.half_height], dtype=np.float64)
    if kind is Plane:
        return 4, np.zeros(1)
    return -1, np.zeros(1)


def path_test(col, x0, x1, idx, t0, t1):
    """(X0, X1, d0, d1, L) of the paths x0[idx] (at t0) -> x1[idx] (at t1) against ``col``: the
    end points in its body frame, their signed distances minus its thickness and the paths'
    lengths there; ``Collider.to_body`` and ``sdf_body`` (hairexp/model/colliders.py), in one
    compiled pass for the five shapes (``_path_test``; Celia's object stage spent 3.2 ms a call in
    the array form on 7,525 vertices and two colliders, 2026-12-06)."""
    code, prm = _shape_code(col)
    if code < 0 or not HAVE_NUMBA:
        X0 = col.to_body(x0[idx], t0)
        X1 = col.to_body(x1[idx], t1)
        d0 = col.sdf_body(X0) - col.thickness
        d1 = col.sdf_body(X1) - col.thickness
        return X0, X1, d0, d1, np.linalg.norm(X1 - X0, axis=1)
    R0, T0 = col.motion.pose(t0)
    R1, T1 = col.motion.pose(t1)
    n = idx.size
    X0, X1 = np.empty((n, 3)), np.empty((n, 3))
    d0, d1, L = np.empty(n), np.empty(n), np.empty(n)
    _path_test(np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(x1, dtype=np.float64),
               idx.astype(np.int64, copy=False), R0, T0, R1, T1, code, prm, float(col.thickness), X0, X1, d0, d1, L)
    return X0, X1, d0, d1, L


@njit(cache=True, error_model="numpy")
def _sdf(code, p, a, b, c):
    """Signed distance of the body-frame point (a, b, c) to shape ``code`` (``_shape_code``), as
    the shapes' ``sdf_body``."""
    if code == 0:      # sphere
        return math.sqrt(a * a + b * b + c * c) - p[0]
    if code == 1:      # capsule along y
        qb = b - min(max(b, -p[1]), p[1])
        return math.sqrt(a * a + qb * qb + c * c) - p[0]
    if code == 2:      # box
        qa, qb, qc = abs(a) - p[0], abs(b) - p[1], abs(c) - p[2]
        ma, mb, mc = max(qa, 0.0), max(qb, 0.0), max(qc, 0.0)
        return math.sqrt(ma * ma + mb * mb + mc * mc) + min(max(qa, max(qb, qc)), 0.0)
    if code == 3:      # cylinder along y
        da = math.sqrt(a * a + c * c) - p[0]
        db = abs(b) - p[1]
        ma, mb = max(da, 0.0), max(db, 0.0)
        return min(max(da, db), 0.0) + math.sqrt(ma * ma + mb * mb)
    return b           # plane y = 0


@njit(cache=True, error_model="numpy")
def _path_test(x0, x1, idx, R0, T0, R1, T1, code, p, th, X0, X1, d0, d1, L):
    for k in range(idx.shape[0]):
        i = idx[k]
        for j in range(3):
            X0[k, j] = (x0[i, 0] - T0[0]) * R0[0, j] + (x0[i, 1] - T0[1]) * R0[1, j] + (x0[i, 2] - T0[2]) * R0[2, j]
            X1[k, j] = (x1[i, 0] - T1[0]) * R1[0, j] + (x1[i, 1] - T1[1]) * R1[1, j] + (x1[i, 2] - T1[2]) * R1[2, j]
        d0[k] = _sdf(code, p, X0[k, 0], X0[k, 1], X0[k, 2]) - th
        d1[k] = _sdf(code, p, X1[k, 0], X1[k, 1], X1[k, 2]) - th
        e0, e1, e2 = X1[k, 0] - X0[k, 0], X1[k, 1] - X0[k, 1], X1[k, 2] - X0[k, 2]
        L[k] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


def edge_boxes(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): the axis-aligned boxes of the edges a[i] - b[i], grown by ``radius`` / 2 on every side."""
    return np.minimum(a, b) - 0.5 * radius, np.maximum(a, b) + 0.5 * radius


def bounding_spheres(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centres, radii) of the spheres around the boxes ``lo``-``hi``."""
    return 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1)


def _of_active(pairs, active):
    """The pairs with at least one edge in ``active`` (None: all)."""
    return pairs if active is None else pairs[active[pairs[:, 0]] | active[pairs[:, 1]]]


class HairHair:
    def __init__(self, strands, thickness: float, skin: float = 0.003):
        self.E = strands.edges
        self.h = float(thickness)
        self.inv_m = strands.inverse_masses
        self.skin = float(skin)
        self._list = None      # (pairs, distances, Y_ref): the neighbour list, built at list-frame positions Y_ref
        self._frame, self._frame_x = None, None   # list frame (A, b) at the start of the next step, and x there

    def frames(self, x0, x1):
        """Positions along the step (s = 0, 1/2, 1 of the linear paths) in the list frame.

        The list frame co-moves with the hair: each step, the best-fit (Kabsch) rigid motion
        of x0 -> x1 (rotation R about the centroid c(s), which moves linearly) is removed,
        Y(s) = F(R(s)^T (x(s) - c(s)) + c0), with R(s) slerped from I to R and F the frame at
        the start of the step.  A rigid map per instant keeps every distance between
        simultaneous points, and the bulk swing of a groom (its largest motion) is gone.  When
        x0 is not where the last step ended (first step, a retried step) the frame restarts."""
        if self._frame_x is None or self._frame_x.shape != x0.shape or not np.array_equal(self._frame_x, x0):
            self._frame, self._frame_x, self._list = (np.eye(3), np.zeros(3)), x0.copy(), None
        kab = self._kabsch(x0, x1)
        maps = [self._map_at(kab, s_) for s_ in (0.0, 0.5, 1.0)]
        if HAVE_NUMBA:
            Ys = np.empty((3,) + x0.shape)
            frame_positions(np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(x1, dtype=np.float64),
                            np.array([0.0, 0.5, 1.0]), np.stack([m[0] for m in maps]), np.stack([m[1] for m in maps]), Ys)
            return tuple(Ys)
        return tuple(((1 - s_) * x0 + s_ * x1) @ As.T + bs for s_, (As, bs) in zip((0.0, 0.5, 1.0), maps))

    @staticmethod
    def _kabsch(x0, x1):
        """(c0, c1, rotation vector of R): the best-fit rigid motion x1 - c1 ~ R (x0 - c0)."""
        if HAVE_NUMBA:
            c0, c1, H = centred_cross(np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(x1, dtype=np.float64))
        else:
            c0, c1 = x0.mean(0), x1.mean(0)
            H = (x0 - c0).T @ (x1 - c1)
        U, _, Vt = np.linalg.svd(H)
        R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        return c0, c1, rotation_vector(R)

    def _map_at(self, kab, s: float):
        """(A, b): the list frame at instant s of the step, Y = A x + b."""
        A, b = self._frame
        c0, c1, rv = kab
        Rs = rotation_matrix(s * rv)
        cs = (1 - s) * c0 + s * c1
        return A @ Rs.T, b + A @ (c0 - Rs.T @ cs)

    def frame_at(self, x0, x1, s: float = 1.0):
        """(A, b): the list frame at instant s of the step x0 -> x1 (``frames`` first)."""
        return self._map_at(self._kabsch(x0, x1), s)

    def end_step(self, x0, x1) -> None:
        """Keep the list frame at the end of the step (x0 -> x1 as the collision stage left
        it) for the next one."""
        self._frame, self._frame_x = self.frame_at(x0, x1, 1.0), x1.copy()

    def neighbours(self, Ys, active=None):
        """Edge pairs that can come within the thickness h during the step, from positions
        ``Ys`` along the step (start, middle, end) in the list frame (``frames``).  Returns
        (pairs, how the broad phase ran: "reused", "rebuilt" or "swept").

        Calm motion: a Verlet neighbour list (as in molecular dynamics).  Built at Y_ref (the
        end of a step), it holds every edge pair closer than h + skin.  In the list frame,
        while every vertex stays within skin / 2 of Y_ref, a pair not in the list stays
        farther apart than h + skin - 2 (skin / 2) = h: it cannot touch.  Of the listed pairs,
        those whose distance at Y_ref minus how far their vertices have moved since is below h
        are returned.  A settled or swinging groom reuses the list for many steps.

        Violent motion (a vertex moves more than skin / 2 within the step): swept boxes of the
        edges over the step, grown by h / 2; pairs whose boxes overlap.

        ``active`` (E,) bool: only pairs with at least one active edge (the collision stage's
        later passes: the edges whose vertices its last pass moved).

        The step's path is checked at three instants; between them the list frame turns
        smoothly (slerp), which the check does not bound exactly."""
        E = self.E
        if self._list is not None:
            pairs, dist, ref = self._list
            moved = np.max([np.einsum("ij,ij->i", Y - ref, Y - ref) for Y in Ys], axis=0)
            if float(moved.max()) < (0.5 * self.skin) ** 2:
                m = np.sqrt(np.maximum(moved[E[:, 0]], moved[E[:, 1]]))
                return _of_active(pairs[dist - m[pairs[:, 0]] - m[pairs[:, 1]] < self.h], active), "reused"
        ref = Ys[-1]
        moved = np.max([np.linalg.norm(Y - ref, axis=1) for Y in Ys], axis=0)
        if float(moved.max()) < 0.5 * self.skin:
            pairs, dist = self.near_pairs(ref, self.h + self.skin)
            self._list = (pairs, dist, ref.copy())
            m = np.maximum(moved[E[:, 0]], moved[E[:, 1]])
            return _of_active(pairs[dist - m[pairs[:, 0]] - m[pairs[:, 1]] < self.h], active), "rebuilt"
        self._list = None
        return self.swept_pairs(Ys, active), "swept"

    def near_pairs(self, X, radius: float):
        """Non-adjacent edge pairs whose segments in positions X are closer than ``radius``,
        and their distances."""
        E = self.E
        a, b = X[E[:, 0]], X[E[:, 1]]
        pairs = self._pairs(*edge_boxes(a, b, radius))
        if HAVE_NUMBA:
            d = pair_distances(np.ascontiguousarray(X, dtype=np.float64), E, pairs)
        else:
            i, j = pairs[:, 0], pairs[:, 1]
            s, t = _closest_segment_params(a[i], b[i], a[j], b[j])
            d = np.linalg.norm(a[i] + s[:, None] * (b[i] - a[i]) - a[j] - t[:, None] * (b[j] - a[j]), axis=1)
        keep = d < radius
        return pairs[keep], d[keep]

    def swept_pairs(self, Xs, active=None):
        """Non-adjacent edge pairs whose boxes around the edges' positions ``Xs`` (grown by
        h / 2) overlap."""
        E = self.E
        if HAVE_NUMBA:
            return self._pairs(*swept_boxes(np.ascontiguousarray(np.stack(Xs), dtype=np.float64), E, 0.5 * self.h), active)
        P = np.stack([X[E[:, k]] for X in Xs for k in (0, 1)], 1)
        return self._pairs(P.min(1) - 0.5 * self.h, P.max(1) + 0.5 * self.h, active)

    def _pairs(self, lo, hi, active=None):
        """Pairs of edges whose boxes ``lo``, ``hi`` overlap and that share no vertex: the
        compiled grid (hairexp/physics/broad_phase.py), or without numba the cKDTree queries
        (``_box_pairs``)."""
        if HAVE_NUMBA:
            return grid_pairs(lo, hi, self.E, active)
        pairs = self._box_pairs(lo, hi)
        return _of_active(pairs[self._not_adjacent(pairs)], active)

    def _not_adjacent(self, pairs):
        """Mask: the two edges share no vertex (adjacent edges of a strand are excluded)."""
        ei, ej = self.E[pairs[:, 0]], self.E[pairs[:, 1]]
        return ~((ei[:, 0] == ej[:, 0]) | (ei[:, 0] == ej[:, 1]) | (ei[:, 1] == ej[:, 0]) | (ei[:, 1] == ej[:, 1]))

    @staticmethod
    def _box_pairs(lo, hi):
        """Pairs (i, j) of axis-aligned boxes that overlap, each once.  The boxes' bounding
        spheres go into cKDTrees by radius class (quantiles of the radius, so a few large boxes
        do not widen every query): ``query_pairs`` within a class, ``sparse_distance_matrix``
        between classes; then the exact box test."""
        if len(lo) < 2:
            return np.zeros((0, 2), dtype=np.int64)
        c, r = bounding_spheres(lo, hi)
        bounds = np.unique(np.quantile(r, CLASS_QUANTILES))
        cls = np.minimum(np.searchsorted(bounds, r), len(bounds) - 1)
        idx = np.arange(len(c))
        groups = [(idx[cls == k], float(r[cls == k].max())) for k in range(len(bounds)) if np.any(cls == k)]
        trees = [cKDTree(c[g]) for g, _ in groups]
        found = []
        for k, (gk, rk) in enumerate(groups):
            for m in range(k, len(groups)):
                gm, rm = groups[m]
                if m == k:
                    pr = trees[k].query_pairs(2.0 * rk, output_type="ndarray").reshape(-1, 2)
                    found.append(np.stack([gk[pr[:, 0]], gk[pr[:, 1]]], 1))
                else:
                    sd = trees[k].sparse_distance_matrix(trees[m], rk + rm, output_type="ndarray")
                    found.append(np.stack([gk[sd["i"]], gm[sd["j"]]], 1))
        pairs = np.concatenate(found).astype(np.int64)
        i, j = pairs[:, 0], pairs[:, 1]
        ok = np.ones(len(pairs), dtype=bool)
        for d in range(3):
            ok &= (lo[i, d] <= hi[j, d]) & (lo[j, d] <= hi[i, d])
        return pairs[ok]

    def filter_reachable(self, x0, x1, pairs):
        """Pairs that can come within the thickness during the step.  A point of each edge
        moves by a convex combination of its vertices' displacements, so the distance between
        the segments changes by at most D = max |d_i - d_j| (i on edge a, j on edge b) over the
        step; pairs whose distance at the start exceeds h + D are dropped (exact, conservative)."""
        if len(pairs) == 0:
            return pairs
        E = self.E
        if HAVE_NUMBA:
            return pairs[reachable(np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(x1, dtype=np.float64),
                                   E, np.ascontiguousarray(pairs, dtype=np.int64), self.h)]
        i, j = pairs[:, 0], pairs[:, 1]
        a0, a1, b0, b1 = x0[E[i, 0]], x0[E[i, 1]], x0[E[j, 0]], x0[E[j, 1]]
        s, t = _closest_segment_params(a0, a1, b0, b1)
        d0 = np.linalg.norm(a0 + s[:, None] * (a1 - a0) - b0 - t[:, None] * (b1 - b0), axis=1)
        d = x1 - x0
        D = np.zeros(len(pairs))
        for va in (E[i, 0], E[i, 1]):
            for vb in (E[j, 0], E[j, 1]):
                D = np.maximum(D, np.linalg.norm(d[va] - d[vb], axis=1))
        return pairs[d0 - D < self.h]

    def impulses(self, x1, v1, pairs, dt, x0=None):
        """One pass: continuous edge-edge detection over the step (exact, ``edge_ccd``) gives
        inelastic impulses along the side the edges started on; pairs that end within the hair
        thickness get repulsion impulses.  Returns (v1 updated, number of pairs given impulses)."""
        if len(pairs) == 0:
            return v1, 0
        E = self.E
        if HAVE_NUMBA:   # the same steps compiled (hairexp/physics/broad_phase.py)
            P = len(pairs)
            pairs = np.ascontiguousarray(pairs, dtype=np.int64)
            x1c = np.ascontiguousarray(x1, dtype=np.float64)
            x0c = x1c if x0 is None else np.ascontiguousarray(x0, dtype=np.float64)
            hit, wa_c, wb_c = np.zeros(P, dtype=bool), np.zeros(P), np.zeros(P)
            if x0 is not None:
                edge_edge_ccd_pairs(x0c, x1c - x0c, E, pairs, 0.1 * self.h, BISECTIONS, hit, np.empty(P), wa_c, wb_c)
            v1 = np.ascontiguousarray(v1, dtype=np.float64)
            given = contact_impulses(x1c, v1, x0c, E, pairs, hit, wa_c, wb_c,
                                     np.ascontiguousarray(self.inv_m, dtype=np.float64), self.h, dt, REPULSION)
            return v1, int(given)
        i, j = pairs[:, 0], pairs[:, 1]
        verts = np.stack([E[i, 0], E[i, 1], E[j, 0], E[j, 1]], 1)
        hit = np.zeros(len(pairs), dtype=bool)
        n = np.zeros((len(pairs), 3))
        wa = np.zeros(len(pairs))
        wb = np.zeros(len(pairs))
        target = np.zeros(len(pairs))
        if x0 is not None:
            d = x1 - x0
            hit, _, wa_c, wb_c = edge_edge_ccd(x0[E[i, 0]], x0[E[i, 1]], x0[E[j, 0]], x0[E[j, 1]],
                                               d[E[i, 0]], d[E[i, 1]], d[E[j, 0]], d[E[j, 1]], 0.1 * self.h)
            if hit.any():
                pa = x0[E[i, 0]] + wa_c[:, None] * (x0[E[i, 1]] - x0[E[i, 0]])
                pb = x0[E[j, 0]] + wb_c[:, None] * (x0[E[j, 1]] - x0[E[j, 0]])
                nc = pa - pb                                                 # the side a started on
                cr = np.cross(x0[E[i, 1]] - x0[E[i, 0]], x0[E[j, 1]] - x0[E[j, 0]])
                tiny = np.linalg.norm(nc, axis=1) < 1e-12
                cr = cr * np.where(np.sum(cr * (x1[E[i, 0]] - x1[E[j, 0]]), 1) < 0, 1.0, -1.0)[:, None]
                nc = np.where(tiny[:, None], cr, nc)
                n[hit] = nc[hit]
                wa[hit], wb[hit] = wa_c[hit], wb_c[hit]
                target[hit] = REPULSION * self.h / dt
        # proximity at the end of the step
        a, b = _closest_segment_params(x1[E[i, 0]], x1[E[i, 1]], x1[E[j, 0]], x1[E[j, 1]])
        p = x1[E[i, 0]] + a[:, None] * (x1[E[i, 1]] - x1[E[i, 0]])
        q = x1[E[j, 0]] + b[:, None] * (x1[E[j, 1]] - x1[E[j, 0]])
        dist = np.linalg.norm(p - q, axis=1)
        close = (dist < self.h) & ~hit
        n[close] = (p - q)[close]
        wa[close], wb[close] = a[close], b[close]
        target[close] = REPULSION * (self.h - dist[close]) / dt
        act = hit | close
        if not act.any():
            return v1, 0
        idx = np.flatnonzero(act)
        nn = n[idx] / np.maximum(np.linalg.norm(n[idx], axis=1, keepdims=True), 1e-300)
        w = np.stack([1 - wa[idx], wa[idx], -(1 - wb[idx]), -wb[idx]], 1)   # barycentric weights
        vv = verts[idx]
        vn = np.sum(np.einsum("pk,pkc->pc", w, v1[vv]) * nn, 1)
        dvn = np.maximum(target[idx] - vn, 0.0)                             # stop approach, then separate gently
        denom = np.sum(w ** 2 * self.inv_m[vv], 1)
        ok = denom > 0
        I = np.where(ok, dvn / np.where(ok, denom, 1.0), 0.0)               # impulse magnitude (kg m/s)
        # Jacobi relaxation: a vertex in many contacts would get the sum of all their impulses
        # (velocities blew up to metres per step in a dense ponytail); each pair's impulse is
        # divided by the largest contact count among its vertices, which keeps every impulse
        # equal and opposite (momentum is conserved); further passes finish the job.
        count = np.bincount(vv[I > 0].ravel(), minlength=len(v1))
        I = I / np.maximum(count[vv].max(axis=1), 1)
        # a contact next to a root vertex (infinite mass) with a small weight on the free vertex
        # would need dvn / w from that vertex (91 m/s seen): no vertex changes by more than dvn
        vmax = np.max(np.abs(w) * self.inv_m[vv], axis=1) * I
        I = np.where(vmax > dvn, I * dvn / np.maximum(vmax, 1e-300), I)
        dv = (w * self.inv_m[vv] * I[:, None])[..., None] * nn[:, None, :]
        np.add.at(v1, vv.ravel(), dv.reshape(-1, 3))
        return v1, int((I > 0).sum())


def contact_velocities(colliders, x1, v1, t1, movable, dist: list | None = None, push: np.ndarray | None = None,
                       solved: np.ndarray | None = None):
    """Inelastic contact: vertices on a collider's shell get no approaching normal velocity
    relative to the surface, and Coulomb friction on the tangential one: its velocity change at
    most the friction coefficient times the normal one (the approaching velocity removed here, plus
    ``push`` (colliders, V) m/s, the normal velocity each collider's contact forces in the solve gave
    each vertex: ``collision.resolve``'s planes, which leave no approaching velocity for the stage
    to remove).  A vertex a collider's planes press (push > 0) is in contact with it even a little
    off its shell (a plane is the surface's tangent at the stage's point, NEAR), and keeps no
    normal velocity relative to it either way: force only at zero gap velocity (the push-out of a
    vertex that started inside is not a bounce).  ``solved`` (colliders, V) bool: vertices whose
    friction with that collider acted in the solve already (``ContactPlanes.set_friction``): no
    friction here.
    ``dist``: each collider's ``distance`` of the movable vertices at (x1, t1), when known
    (``object_stage``)."""
    near = np.flatnonzero(movable)
    for i, col in enumerate(colliders):
        shell = col.on_shell(x1[near], t1) if dist is None else dist[i] < col.shell_tolerance()
        pressed = push[i] if push is not None else np.zeros(len(x1))   # m/s; none: no solve's contact forces
        shell |= pressed[near] > 0.0
        c = near[shell]
        if c.size:
            n = col.normal(x1[c], t1)
            vs = col.surface_velocity(x1[c], t1)
            vr = v1[c] - vs
            vn = np.sum(vr * n, axis=1)
            jn = np.maximum(-vn, 0.0) + pressed[c]
            vt = vr - vn[:, None] * n
            tn = np.linalg.norm(vt, axis=1)
            f = np.where((jn > 0) & (tn > 0), np.maximum(0.0, 1.0 - col.friction * jn / np.maximum(tn, 1e-300)), 1.0)
            if solved is not None:
                f = np.where(solved[i][c], 1.0, f)
            # a vertex the solve's contact forces press (push > 0) ends on the surface: no normal velocity
            # relative to it either way (force > 0 only at zero gap velocity; the push-out of a vertex
            # that started inside is not a bounce)
            vn_out = np.where(pressed[c] > 0.0, 0.0, np.maximum(vn, 0.0))
            v1[c] = vs + vt * f[:, None] + vn_out[:, None] * n
    return v1


class StrainLimit:
    """Strain limiting after the collision response (Provot 1995, as used by Bridson et al.
    2002): a collision stops a vertex at a surface while its neighbours finish their move, which
    can stretch or crush an edge several times over at dt = 0.04 s.  Edge lengths are clamped to
    [1 - limit, 1 + limit] x rest, moving their free end points in proportion to their inverse
    masses (a root vertex does not move), in Gauss-Seidel sweeps along the strands (all strands'
    k-th edges at once), from the root to the tip and back."""

    def __init__(self, strands, limit: float, sweeps: int = 3):
        E = strands.edges
        self.E, self.L, self.Lmin = E, strands.rest_lengths * (1.0 + limit), strands.rest_lengths * (1.0 - limit)
        self.w = strands.inverse_masses
        self.strand = strands.strand_of_vertex[E[:, 0]]
        local = E[:, 0] - strands.offsets[self.strand]
        self.order = [np.flatnonzero(local == k) for k in range(int(local.max()) + 1)] if len(E) else []
        self.sweeps = sweeps
        # each strand's edges root to tip (CSR: strand s owns edge_of[edge_ptr[s]:edge_ptr[s + 1]]), for the kernel
        self.edge_of = np.lexsort((local, self.strand)).astype(np.int64) if len(E) else np.zeros(0, np.int64)
        self.edge_ptr = np.concatenate([[0], np.cumsum(np.bincount(self.strand, minlength=strands.n_strands))]).astype(np.int64)
        self.compiled = HAVE_NUMBA   # ``limit_sweeps``; False: the numpy sweeps (the reference the tests compare)

    def _outside(self, x: np.ndarray) -> np.ndarray:
        """(E,) bool: the edges of x outside the limit."""
        E = self.E
        n = np.linalg.norm(x[E[:, 1]] - x[E[:, 0]], axis=1)
        return (n > self.L * (1 + 1e-9)) | (n < self.Lmin * (1 - 1e-9))

    def outside(self, x: np.ndarray) -> bool:
        """Whether an edge of x is outside the limit (``apply`` would move something)."""
        return bool(self._outside(x).any())

    def apply(self, x: np.ndarray, pinned: np.ndarray | None = None) -> int:
        """Clamps the edge lengths of x in place; returns how many edges were outside.
        ``pinned`` vertices (in contact with a collider) do not move: their neighbours come
        to them, instead of the limiter pulling them into the collider.  The sweeps visit only the
        strands with an edge outside (the others' edges would not move)."""
        E, w = self.E, self.w if pinned is None else np.where(pinned, 0.0, self.w)
        outside = self._outside(x)
        over = int(np.sum(outside))
        if over == 0:
            return 0
        active = np.zeros(len(self.edge_ptr) - 1, dtype=bool)
        active[self.strand[outside]] = True
        if self.compiled:
            limit_sweeps(x, np.ascontiguousarray(w, dtype=np.float64), self.w, self.E, self.L, self.Lmin,
                         self.edge_ptr, self.edge_of, active, self.sweeps)
            return over
        order = [g for g in (g[active[self.strand[g]]] for g in self.order) if g.size]
        for _ in range(self.sweeps):
            for group in order + order[::-1]:
                a, b = E[group, 0], E[group, 1]
                d = x[b] - x[a]
                n = np.linalg.norm(d, axis=1)
                excess = np.maximum(n - self.L[group], 0.0) + np.minimum(n - self.Lmin[group], 0.0)
                wa, wb = w[a], w[b]
                both = (wa + wb == 0) & (self.w[a] + self.w[b] > 0)   # two pinned ends: both move
                wa, wb = np.where(both, self.w[a], wa), np.where(both, self.w[b], wb)
                ws = wa + wb
                k = (excess != 0) & (ws > 0) & (n > 0)
                if not k.any():
                    continue
                corr = (excess[k] / (n[k] * ws[k]))[:, None] * d[k]
                x[a[k]] += wa[k, None] * corr
                x[b[k]] -= wb[k, None] * corr
        return over


@njit(cache=True)
def limit_sweeps(x, w, w_all, E, L, Lmin, edge_ptr, edge_of, active, sweeps):
    """``StrainLimit.apply``'s sweeps, compiled: each active strand's edges root to tip and back,
    ``sweeps`` times, one strand after another.  The numpy sweeps visit all strands' k-th edges
    at once; strands share no vertex, so the order within a strand is the same and the results
    are bit for bit the same (tests/test_collisions.py).  ``w``: inverse masses with the pinned
    vertices at 0; ``w_all``: without the pins (two pinned ends both move)."""
    for s in range(len(active)):
        if not active[s]:
            continue
        a0, a1 = edge_ptr[s], edge_ptr[s + 1]
        for _ in range(sweeps):
            for back in range(2):
                for jj in range(a1 - a0):
                    e = edge_of[a1 - 1 - jj] if back else edge_of[a0 + jj]
                    a, b = E[e, 0], E[e, 1]
                    dx, dy, dz = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
                    n = math.sqrt(dx * dx + dy * dy + dz * dz)
                    excess = max(n - L[e], 0.0) + min(n - Lmin[e], 0.0)
                    wa, wb = w[a], w[b]
                    if wa + wb == 0 and w_all[a] + w_all[b] > 0:
                        wa, wb = w_all[a], w_all[b]
                    ws = wa + wb
                    if excess != 0 and ws > 0 and n > 0:
                        c = excess / (n * ws)
                        cx, cy, cz = c * dx, c * dy, c * dz
                        x[a, 0] += wa * cx
                        x[a, 1] += wa * cy
                        x[a, 2] += wa * cz
                        x[b, 0] -= wb * cx
                        x[b, 1] -= wb * cy
                        x[b, 2] -= wb * cz


#: rounds of ``edge_response`` (edges pushed out, then the vertices' response to the pushes)
EDGE_ROUNDS = 8


#: directions across an edge that ``_way_out`` tries
EDGE_DIRECTIONS = 16


def _way_out(col, gaps, P: np.ndarray, e: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(n, 3) world unit directions across the unit edge directions e, from the world points P
    inside ``col``: of EDGE_DIRECTIONS directions in the plane across each edge, the one along
    which phi is largest at ``depth`` from P (the shortest way out, to that resolution)."""
    ref = np.where(np.abs(e[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(e, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(e, u)
    ang = 2.0 * np.pi * np.arange(EDGE_DIRECTIONS) / EDGE_DIRECTIONS
    M = np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :]   # (n, k, 3)
    Q = P[:, None, :] + np.maximum(depth, 1e-9)[:, None, None] * M
    phi = col.sdf_body(gaps.body(Q.reshape(-1, 3))).reshape(len(P), EDGE_DIRECTIONS)
    return M[np.arange(len(P)), np.argmax(phi, axis=1)]


def edge_response(colliders, E: np.ndarray, w: np.ndarray, x1, t1, movable, dist: list | None = None,
                  only: np.ndarray | None = None):
    """Edges against the colliders at t1: an edge whose end points are both outside a collider's
    thickness shell but whose segment dips into it (a ball or a rim between two vertices, a box
    corner: the object response tests vertices only) is pushed out along the normal at its
    closest point (``contact_geometry.EdgeGaps``: min over the segment of phi - thickness,
    closed forms or a safeguarded Newton search per shape).  The closest point a + s (b - a)
    moves out by its depth: the end points move by (1 - s) w_a lam n and s w_b lam n, lam =
    depth / ((1 - s)^2 w_a + s^2 w_b) (inverse masses w; a root does not move), the
    position-based projection of the edge's constraint (Mueller et al. 2007).  Each round is
    followed by the object response to the moves at t1 (no friction, as the strain limiter's), so
    that a push cannot move a vertex into a collider; the rounds (at most EDGE_ROUNDS) end when no
    edge is deeper than the collider's shell tolerance.  Edges with an end point inside (a root
    under the scalp) are left to the vertex response.  ``dist``: each collider's distance
    (``Collider.distance``) of the movable vertices at x1, when known (the object pass's path
    test), for the first round.  ``only``: (V,) bool, the vertices whose edges to test in the
    first round (the others' edges are known to be clear: the strain limiter's rounds pass the
    vertices they moved); later rounds test the edges of the vertices the pushes moved.  Returns
    (x1, edges pushed, summed over the rounds)."""
    # read-only whatever E's flags (the scene's edges as built, or a deep copy's): one build of _edge_candidates
    a_all, b_all = read_only(E[:, 0]), read_only(E[:, 1])
    w = np.where(movable, w, 0.0)
    mov = movable[a_all] | movable[b_all]
    pushed_total = 0
    fixed = np.flatnonzero(~movable)
    test = mov if only is None else mov & (only[a_all] | only[b_all])
    for r in range(EDGE_ROUNDS):
        if not test.any():
            break
        before = x1.copy()
        pushed = 0
        if HAVE_NUMBA:
            half = reach = None   # the candidates' pass computes the edges' lengths itself
        else:
            half = 0.5 * np.linalg.norm(x1[b_all] - x1[a_all], axis=1)
            reach = float(half.max(initial=0.0))
        for i, col in enumerate(colliders):
            R, T = col.motion.pose(t1)
            gaps = EdgeGaps(col, R, T)
            tol = col.shell_tolerance()
            if r == 0 and dist is not None:   # the path test's distances of the movable vertices
                g = np.empty(len(x1))
                g[movable] = dist[i]
                g[fixed] = gaps.vertex_gaps(x1[fixed])
            else:
                g = gaps.vertex_gaps(x1)
            # phi is 1-Lipschitz: along an edge of length 2 half it is >= (ga + gb) / 2 - half, so only
            # an edge with that bound below -tol can dip deeper than the shell's tolerance
            if HAVE_NUMBA:
                cand = np.empty(len(a_all), dtype=np.int64)
                cand = cand[:_edge_candidates(x1, a_all, b_all, g, test, tol, cand)]
            else:
                if g.min(initial=np.inf) - reach >= tol:   # no edge reaches the shell
                    continue
                ga, gb = g[a_all], g[b_all]
                cand = np.flatnonzero(test & (ga > -tol) & (gb > -tol) & (0.5 * (ga + gb) - half < -tol))
            if cand.size == 0:
                continue
            a, b = a_all[cand], b_all[cand]
            d, sc, n = gaps.edge_gaps(x1[a], x1[b], normals=True)
            deep = d < -tol
            if not deep.any():
                continue
            a, b, d, sc, n = a[deep], b[deep], d[deep], sc[deep], n[deep]
            # the push goes across the edge: at an interior minimum of phi along a smooth segment the
            # normal is across it anyway; inside a box (phi's kinks) the nearest face's normal can lie
            # along the edge, which would slide the edge along itself without lifting it out
            e = x1[b] - x1[a]
            e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
            n = n - np.sum(n * e, axis=1, keepdims=True) * e
            flat = np.linalg.norm(n, axis=1) < 0.5
            if flat.any():   # no normal across the edge (its closest point on a shape's centre or axis,
                # a face's normal along it): of EDGE_DIRECTIONS directions across the edge, the one in
                # which the shape ends soonest (the largest phi at the depth's distance)
                n[flat] = _way_out(col, gaps, x1[a[flat]] + sc[flat, None] * (x1[b[flat]] - x1[a[flat]]), e[flat],
                                   -d[flat])
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
            denom = (1.0 - sc) ** 2 * w[a] + sc ** 2 * w[b]
            ok = denom > 0
            lam = np.where(ok, (-d + 0.5 * tol) / np.where(ok, denom, 1.0), 0.0)
            np.add.at(x1, a, ((1.0 - sc) * w[a] * lam)[:, None] * n)
            np.add.at(x1, b, (sc * w[b] * lam)[:, None] * n)
            pushed += int(ok.sum())
        if pushed == 0:
            break
        pushed_total += pushed
        moved = movable & np.any(x1 != before, axis=1)
        x1, _, _ = object_positions(colliders, before, x1, t1, t1, 0.0, moved, friction=False)
        moved |= movable & np.any(x1 != before, axis=1)
        test = mov & (moved[a_all] | moved[b_all])
    return x1, pushed_total


@njit(cache=True, error_model="numpy")
def _edge_candidates(x, a, b, g, test, tol, out):
    """``edge_response``'s candidates in one compiled pass: the edges e with test[e], both end
    points' gaps g above -tol and the Lipschitz bound (g_a + g_b) / 2 - |x_b - x_a| / 2 below -tol,
    written to out in ascending order; returns their count (the numpy expression's, bit for bit:
    the same sums in the same order)."""
    n = 0
    for e in range(a.shape[0]):
        if not test[e]:
            continue
        ga, gb = g[a[e]], g[b[e]]
        if not (ga > -tol and gb > -tol):
            continue
        d0, d1, d2 = x[b[e], 0] - x[a[e], 0], x[b[e], 1] - x[a[e], 1], x[b[e], 2] - x[a[e], 2]
        if 0.5 * (ga + gb) - 0.5 * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < -tol:
            out[n] = e
            n += 1
    return n


def limit_strain(limiter: StrainLimit, colliders, x1, t1, movable, edges: bool = False):
    """Strain limiting after the object response, in rounds: the limiter's sweeps, then the
    object response to its moves at t1 (continuous, so that a move cannot cross a thin collider;
    without friction; colliders do not move within the rounds).  The rounds end when a round
    moves nothing: every edge within the limit and every vertex outside the colliders, with the
    object response the last move.  The first ``PIN_ROUNDS`` hold the vertices in contact (a
    vertex stopped at a surface keeps its place, its neighbours come to it); later rounds let
    the limiter move them as well, along the surface.

    The response used to end the rounds as soon as it stopped nothing (edges could still be
    over the limit when the sweeps had not finished) and applied Coulomb friction to the
    limiter's moves: a strand pressed over a rim (one vertex on the top face, the next stopped
    on the side after sliding down it) stayed stretched, 58 % on Celia's goblet at 10 %.
    Returns (x1, edges outside the limit summed over the rounds, rounds)."""
    limited, rounds = 0, 0
    changed = movable.copy()   # vertices the last round moved: the response checks them and the limiter's moves
    for rounds in range(1, LIMIT_ROUNDS + 1):
        pinned = None
        if rounds <= PIN_ROUNDS:
            pinned = np.zeros(len(x1), dtype=bool)
            for col in colliders:
                pinned |= col.on_shell(x1, t1)
        before = x1.copy()
        n = limiter.apply(x1, pinned)
        limited += n
        check = movable & (changed | np.any(x1 != before, axis=1))
        x1, _, _ = object_positions(colliders, before, x1, t1, t1, 0.0, check, friction=False)
        if edges:   # the edges of the vertices this round moved (the others' were clear after the last); all at first
            x1, _ = edge_response(colliders, limiter.E, limiter.w, x1, t1, movable,
                                  only=movable if rounds == 1 else np.any(x1 != before, axis=1))
        changed = np.any(np.abs(x1 - before) > LIMIT_TOL, axis=1)
        if n == 0 and not changed.any():
            break
    return x1, limited, rounds


def collision_stage(cfg, scene, hh: HairHair | None, x0, x1, t0, t1, dt, limiter: StrainLimit | None = None,
                    dist_out: list | None = None, discrete: bool = False, push: np.ndarray | None = None,
                    solved: np.ndarray | None = None):
    """Filter (x1, v1) for contacts.  Returns (x1, v1, CollisionInfo).  With ``limiter``, a
    step with object contacts ends with strain limiting (``StrainLimit``).  ``dist_out``: a list
    that gets each collider's ``distance`` of the movable vertices at the returned x1 and t1 when
    the stage knows them without another evaluation (its last pass had no object contact and
    nothing moved after it; the object contacts' path test computed them), else stays empty.  ``hh``: the edge
    contacts (``HairHair``) or None.  The volume model (``collision.hair_hair_model=volume``,
    hairexp/physics/hair_volume.py) is not a pass of this stage: it filters the scheme's end
    velocities and moves no position, so the Simulator applies it (``Simulator._stage``) and
    these passes see the solve's path.  ``discrete``: the object passes test the end points only
    (``object_stage``).  ``push``: the normal velocity (colliders, V) m/s the solve's contact forces
    gave the vertices, which bounds their Coulomb friction as well; ``solved``: the vertices whose
    friction acted in the solve (``contact_velocities``)."""
    tic = time.perf_counter()
    info = CollisionInfo()
    movable = ~scene.strands.kinematic
    v1 = (x1 - x0) / dt
    dist = None            # each collider's distance at the current x1, when the object pass computed it
    active = None          # edges whose vertices the last pass moved (None: the first pass, every edge)
    for p in range(max(1, cfg.max_passes)):
        n_obj = n_hh = 0
        dist = None
        if hh is not None:
            x_pass, v_pass = x1, v1.copy()
            Ys = hh.frames(x0, x1)
            pairs, how = hh.neighbours(Ys, active)
            info.broad_phases[how] = info.broad_phases.get(how, 0) + 1
            near = hh.filter_reachable(x0, x1, pairs)
            info.candidates = max(info.candidates, len(near))
            v1, n_hh = hh.impulses(x1, v1, near, dt, x0)
            hit = movable & np.any(v1 != v_pass, axis=1)      # the vertices an impulse reached
            x1 = np.where(hit[:, None], x0 + dt * v1, x1)
        if scene.colliders:
            found: list = []
            x1, v1, n_obj, per = object_stage(scene.colliders, x0, x1, t0, t1, dt, movable, dist_out=found,
                                              discrete=discrete, push=push, solved=solved)
            dist = found or None    # (filled only when the pass had no contact)
            for k, c in per.items():
                info.per_collider[k] = info.per_collider.get(k, 0) + c
        info.object_contacts += n_obj
        info.hair_contacts += n_hh
        info.passes = p + 1
        if n_obj + n_hh == 0:
            break
        if hh is not None:
            # the next pass tests only pairs with an edge whose vertices this pass moved or slowed: the
            # others' paths x0 -> x1 and velocities are unchanged, and this pass gave them no impulse
            # (else their vertices would have changed), so they would get none again
            moved = np.any(x1 != x_pass, axis=1) | np.any(v1 != v_pass, axis=1)
            active = moved[hh.E[:, 0]] | moved[hh.E[:, 1]]
    edges = bool(getattr(cfg, "edge_response", True)) and bool(scene.colliders)
    moved_after = False    # whether the edge response or the limiter moved x1 after the passes
    if edges:
        x1, info.edge_contacts = edge_response(scene.colliders, scene.strands.edges, scene.strands.inverse_masses,
                                               x1, t1, movable, dist)
        info.object_contacts += info.edge_contacts
        moved_after = info.edge_contacts > 0
    if limiter is not None and info.object_contacts > 0:
        x1, info.strain_limited, info.limit_rounds = limit_strain(limiter, scene.colliders, x1, t1, movable, edges)
        moved_after = True
    if moved_after:   # the velocities of the final positions, once
        v1 = contact_velocities(scene.colliders, x1, (x1 - x0) / dt, t1, movable, push=push, solved=solved)
        dist = None
    if hh is not None:
        hh.end_step(x0, x1)
    if scene.colliders:
        if dist is None:
            dist = [c.distance(x1[movable], t1) for c in scene.colliders]
        pen = [np.maximum(-d, 0.0).max(initial=0.0) for d in dist]
        info.penetration_max = float(max(pen))
        if dist_out is not None:
            dist_out.extend(dist)
    info.seconds = time.perf_counter() - tic
    return x1, v1, info
