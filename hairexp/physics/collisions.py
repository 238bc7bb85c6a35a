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
excluded.  The broad phase is a ``scipy.spatial.cKDTree`` over swept edge bounds.  Passes
repeat up to ``max_passes``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from hairexp.physics.edge_ccd import _closest_segment_params, edge_edge_ccd

#: Conservative-advancement iterations and tolerance (fraction of the thickness or 1e-6 m).
CA_ITERATIONS, CA_TOL = 40, 1e-6
#: Fraction of the overlap (h - d) removed per step by the repulsion impulse (Bridson 2002, 7.2).
REPULSION = 0.25


@dataclass
class CollisionInfo:
    object_contacts: int = 0
    hair_contacts: int = 0
    penetration_max: float = 0.0      # m, deepest end-of-step penetration into a collider's thickness after the stage
    passes: int = 0
    seconds: float = 0.0
    per_collider: dict = field(default_factory=dict)


def object_stage(colliders, x0, x1, t0, t1, dt, movable):
    """Returns corrected (x1, v1, contacts)."""
    x1 = x1.copy()
    contacts = 0
    idx = np.flatnonzero(movable)
    per = {}
    for col in colliders:
        X0 = col.to_body(x0[idx], t0)
        X1 = col.to_body(x1[idx], t1)
        th = col.thickness
        d0 = col.sdf_body(X0) - th
        d1 = col.sdf_body(X1) - th
        D = X1 - X0
        L = np.linalg.norm(D, axis=1)
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
        scale = np.where(tn > 0, np.maximum(0.0, 1.0 - col.friction * (-into) / np.maximum(tn, 1e-300)), 1.0)
        Xe = Xc + spin + rel_t * scale[:, None] + rel_n
        for _ in range(3):  # project outside the shell (curved surfaces)
            de = col.sdf_body(Xe) - th
            Xe = Xe + np.maximum(-de, 0.0)[:, None] * col.normal_body(Xe)
        R, T = col.motion.pose(t1)
        x1[idx[h]] = Xe @ R.T + T
        contacts += h.size
        per[col.name] = int(h.size)
    v1 = (x1 - x0) / dt
    # inelastic: no approaching normal relative velocity at the end of the step
    for col in colliders:
        near = np.flatnonzero(movable)
        d = col.distance(x1[near], t1)
        c = near[d < 1e-3 * max(col.thickness, 1e-3) + 1e-9]
        if c.size:
            n = col.normal(x1[c], t1)
            vs = col.surface_velocity(x1[c], t1)
            vr = v1[c] - vs
            vn = np.sum(vr * n, axis=1)
            neg = vn < 0
            vt = vr - vn[:, None] * n
            tn = np.linalg.norm(vt, axis=1)
            f = np.where(neg & (tn > 0), np.maximum(0.0, 1.0 - col.friction * (-vn) / np.maximum(tn, 1e-300)), 1.0)
            v1[c] = vs + vt * f[:, None] + np.maximum(vn, 0.0)[:, None] * n
    return x1, v1, contacts, per


class HairHair:
    def __init__(self, strands, thickness: float):
        self.E = strands.edges
        self.sov = strands.strand_of_vertex
        self.h = float(thickness)
        self.m = strands.masses
        self.inv_m = np.where(strands.kinematic, 0.0, 1.0 / strands.masses)

    def candidate_pairs(self, x0, x1, body=None):
        """Edge pairs whose swept bounding boxes, grown by the hair thickness, overlap.

        ``body``: (X0, X1) the same positions in the frame of the body the roots are attached
        to.  A common rigid motion does not change how hairs move relative to each other, and in
        that frame a jerk of the head does not inflate every swept box.  A cKDTree over the box
        centres gives the candidates; the box test then removes e.g. parallel neighbours."""
        E = self.E
        X0, X1 = body if body is not None else (x0, x1)
        pts = np.stack([X0[E[:, 0]], X0[E[:, 1]], X1[E[:, 0]], X1[E[:, 1]]], 1)     # (E, 4, 3)
        lo = pts.min(1) - 0.5 * self.h
        hi = pts.max(1) + 0.5 * self.h
        c = 0.5 * (lo + hi)
        r = 0.5 * np.linalg.norm(hi - lo, axis=1)
        tree = cKDTree(c)
        pairs = tree.query_pairs(2 * float(r.max()), output_type="ndarray")
        if len(pairs) == 0:
            return pairs
        i, j = pairs[:, 0], pairs[:, 1]
        keep = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
        ei, ej = E[i], E[j]
        adjacent = (ei[:, 0] == ej[:, 0]) | (ei[:, 0] == ej[:, 1]) | (ei[:, 1] == ej[:, 0]) | (ei[:, 1] == ej[:, 1])
        return pairs[keep & ~adjacent]

    def impulses(self, x1, v1, pairs, dt, x0=None):
        """One pass: continuous edge-edge detection over the step (exact, ``edge_ccd``) gives
        inelastic impulses along the side the edges started on; pairs that end within the hair
        thickness get repulsion impulses.  Returns (v1 updated, number of pairs given impulses)."""
        if len(pairs) == 0:
            return v1, 0
        E = self.E
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


def collision_stage(cfg, scene, hh: HairHair | None, x0, x1, t0, t1, dt):
    """Filter (x1, v1) for contacts.  Returns (x1, v1, CollisionInfo)."""
    tic = time.perf_counter()
    info = CollisionInfo()
    movable = ~scene.strands.kinematic
    v1 = (x1 - x0) / dt
    for p in range(max(1, cfg.max_passes)):
        n_obj = n_hh = 0
        if hh is not None:
            body = (scene.motion.to_body(x0, t0), scene.motion.to_body(x1, t1)) if hasattr(scene, "motion") else None
            pairs = hh.candidate_pairs(x0, x1, body)
            v1, n_hh = hh.impulses(x1, v1, pairs, dt, x0)
            x1 = np.where(movable[:, None], x0 + dt * v1, x1)
        if scene.colliders:
            x1, v1, n_obj, per = object_stage(scene.colliders, x0, x1, t0, t1, dt, movable)
            for k, c in per.items():
                info.per_collider[k] = info.per_collider.get(k, 0) + c
        info.object_contacts += n_obj
        info.hair_contacts += n_hh
        info.passes = p + 1
        if n_obj + n_hh == 0:
            break
    if scene.colliders:
        pen = [np.maximum(-c.distance(x1[movable], t1), 0.0).max(initial=0.0) for c in scene.colliders]
        info.penetration_max = float(max(pen))
    info.seconds = time.perf_counter() - tic
    return x1, v1, info
