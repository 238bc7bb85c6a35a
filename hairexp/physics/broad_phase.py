"""Compiled pieces of the hair-hair contact stage (hairexp/physics/collisions.py, ``HairHair``):
which edge boxes overlap, which candidate pairs can come within the hair's thickness during a
step, their continuous edge-edge test and impulses, and the list frame's Kabsch fit.  Each is the
numpy / scipy code of ``HairHair`` written pair by pair (or vertex by vertex) with the same
formulas; that code stays the path without numba, and tests/test_collisions.py checks the two
against each other.

``grid_pairs``: a uniform grid (spatial hashing without a hash: each box is entered in every cell
its extent covers, the entries are sorted by cell, and the boxes that share a cell are tested
exactly).  A pair that shares several cells is reported only by the cell at the low corner of
the two boxes' common cell range (max of their first cells on each axis), so each overlapping
pair comes out once, with no set to merge.  The cell's side is the median of the boxes' largest
extents, doubled while the entries would exceed ``MAX_ENTRIES_PER_BOX`` per box (a few very large
swept boxes).  Edge pairs that share a vertex (adjacent edges of a strand) are skipped in the
same pass.  On the 117 box sets of the Celia benchmark's jerk with hair-hair (7,525 edges, 8,000 to
128,000 overlapping pairs) it takes 0.115 x the time of the ``scipy.spatial.cKDTree`` queries by
radius class it replaced (the same pairs; both timed in one process, 2026-12-06;
``HairHair._box_pairs`` keeps that path where numba is missing, and tests/test_collisions.py
compares the two).

``reachable``: the exact conservative test of ``HairHair.filter_reachable`` pair by pair;
``pair_distances``: the neighbour list's segment distances; ``edge_edge_ccd_pairs``:
``edge_ccd.edge_edge_ccd``; ``contact_impulses``: ``HairHair.impulses`` after its CCD;
``centred_cross``, ``frame_positions``, ``rotation_matrix``, ``rotation_vector``: the list frame
(``HairHair.frames``) without scipy ``Rotation`` calls.

Celia's benchmark with hair-hair (``experiments.bench_collisions``), this code against the numpy
path in one process, steps alternated: the collision stage 0.18 x the time, the step 0.29 x, the
same contacts and Newton iterations (README "Benchmarks", 2026-12-06).
"""

from __future__ import annotations

import math

import numpy as np

from hairexp.physics.kernels import njit

#: the grid's cell grows (doubles) while the boxes would take more entries than this per box
MAX_ENTRIES_PER_BOX = 27


@njit(cache=True)
def _grid_setup(lo, hi, max_per_box):
    """(cell side, origin, cells per axis) of the grid for boxes ``lo``, ``hi`` (n, 3): the side
    is the median of the boxes' largest extents, doubled while the entries exceed ``max_per_box``
    x n or the cell count overflows 2^60."""
    n = lo.shape[0]
    org = np.empty(3)
    top = np.empty(3)
    ext = np.empty(n)
    for d in range(3):
        org[d] = lo[0, d]
        top[d] = hi[0, d]
    for i in range(n):
        m = 0.0
        for d in range(3):
            org[d] = min(org[d], lo[i, d])
            top[d] = max(top[d], hi[i, d])
            m = max(m, hi[i, d] - lo[i, d])
        ext[i] = m
    span = max(top[0] - org[0], max(top[1] - org[1], top[2] - org[2]))
    c = max(np.median(ext), 1e-9 * span, 1e-300)
    while _entries(lo, hi, org, 1.0 / c) > max_per_box * n or (math.floor(span / c) + 1.0) ** 3 >= 2.0 ** 60:
        c *= 2.0
    return c, org, int(math.floor(span / c)) + 1


@njit(cache=True)
def _entries(lo, hi, org, inv_c):
    """How many grid cells the boxes cover in all (float: no overflow)."""
    total = 0.0
    for i in range(lo.shape[0]):
        cnt = 1.0
        for d in range(3):
            cnt *= math.floor((hi[i, d] - org[d]) * inv_c) - math.floor((lo[i, d] - org[d]) * inv_c) + 1.0
        total += cnt
    return total


@njit(cache=True)
def swept_boxes(Ys, E, pad):
    """(lo, hi) (n, 3): the boxes around each edge of E at every positions Ys[k] (K, V, 3),
    grown by ``pad``."""
    n = E.shape[0]
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    for e in range(n):
        for d in range(3):
            a = np.inf
            b = -np.inf
            for k in range(Ys.shape[0]):
                for v in (E[e, 0], E[e, 1]):
                    y = Ys[k, v, d]
                    a = min(a, y)
                    b = max(b, y)
            lo[e, d] = a - pad
            hi[e, d] = b + pad
    return lo, hi


def grid_pairs(lo: np.ndarray, hi: np.ndarray, edges: np.ndarray | None = None,
               active: np.ndarray | None = None) -> np.ndarray:
    """(P, 2) int64 pairs (i < j) of the axis-aligned boxes ``lo``, ``hi`` (n, 3) that overlap
    (closed boxes: touching counts), in the grid's order (the same for the same input).  With
    ``edges`` (n, 2), pairs of boxes whose edges share a vertex are left out; with ``active``
    (n,) bool, only pairs with at least one active box are reported."""
    n = len(lo)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError("grid_pairs: box bounds must be finite (the grid's cells are indexed by them)")
    c, org, nc = _grid_setup(lo, hi, float(MAX_ENTRIES_PER_BOX))
    E = np.zeros((0, 2), dtype=np.int64) if edges is None else np.ascontiguousarray(edges, dtype=np.int64)
    act = np.ones(n, dtype=np.bool_) if active is None else np.ascontiguousarray(active, dtype=np.bool_)
    return _grid_pairs(lo, hi, org, 1.0 / c, nc, E, edges is not None, act)


@njit(cache=True)
def _grid_pairs(lo, hi, org, inv_c, nc, E, skip_adjacent, active):
    n = lo.shape[0]
    r0 = np.empty((n, 3), dtype=np.int64)
    r1 = np.empty((n, 3), dtype=np.int64)
    total = 0
    for i in range(n):
        cnt = 1
        for d in range(3):
            a = int(math.floor((lo[i, d] - org[d]) * inv_c))
            b = int(math.floor((hi[i, d] - org[d]) * inv_c))
            if b < a:
                b = a
            r0[i, d] = a
            r1[i, d] = b
            cnt *= b - a + 1
        total += cnt
    keys = np.empty(total, dtype=np.int64)
    ids = np.empty(total, dtype=np.int64)
    k = 0
    for i in range(n):
        for x in range(r0[i, 0], r1[i, 0] + 1):
            for y in range(r0[i, 1], r1[i, 1] + 1):
                for z in range(r0[i, 2], r1[i, 2] + 1):
                    keys[k] = (x * nc + y) * nc + z
                    ids[k] = i
                    k += 1
    ncell = nc * nc * nc
    if ncell <= 8 * total + 1024:    # few cells: a counting sort by cell
        start = np.zeros(ncell + 1, dtype=np.int64)
        for k in range(total):
            start[keys[k] + 1] += 1
        for c in range(ncell):
            start[c + 1] += start[c]
        order = np.empty(total, dtype=np.int64)
        for k in range(total):
            order[start[keys[k]]] = k
            start[keys[k]] += 1
    else:
        order = np.argsort(keys)
    # the entries' boxes gathered in cell order: the pair tests below read memory in sequence
    B = np.empty((total, 6))
    C = np.empty((total, 3), dtype=np.int64)
    I = np.empty(total, dtype=np.int64)
    K = np.empty(total, dtype=np.int64)
    for p in range(total):
        i = ids[order[p]]
        I[p] = i
        K[p] = keys[order[p]]
        for d in range(3):
            B[p, d] = lo[i, d]
            B[p, 3 + d] = hi[i, d]
            C[p, d] = r0[i, d]
    cap = 4 * n + 16
    out = np.empty((cap, 2), dtype=np.int64)
    m = 0
    s = 0
    while s < total:
        key = K[s]
        e = s + 1
        while e < total and K[e] == key:
            e += 1
        for p in range(s, e):
            ap = active[I[p]]
            for q in range(p + 1, e):
                if not (ap or active[I[q]]):
                    continue
                if (B[p, 0] > B[q, 3] or B[q, 0] > B[p, 3] or B[p, 1] > B[q, 4] or B[q, 1] > B[p, 4]
                        or B[p, 2] > B[q, 5] or B[q, 2] > B[p, 5]):
                    continue
                cx = max(C[p, 0], C[q, 0])
                cy = max(C[p, 1], C[q, 1])
                cz = max(C[p, 2], C[q, 2])
                if (cx * nc + cy) * nc + cz != key:
                    continue          # reported by the pair's first common cell
                i = min(I[p], I[q])
                j = max(I[p], I[q])
                if skip_adjacent:
                    if (E[i, 0] == E[j, 0] or E[i, 0] == E[j, 1] or E[i, 1] == E[j, 0]
                            or E[i, 1] == E[j, 1]):
                        continue
                if m == cap:
                    grown = np.empty((2 * cap, 2), dtype=np.int64)
                    grown[:m] = out[:m]
                    out = grown
                    cap *= 2
                out[m, 0] = i
                out[m, 1] = j
                m += 1
        s = e
    return out[:m].copy()


@njit(cache=True, inline="always")
def segment_params(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z):
    """Closest points of segments p1q1 and p2q2: parameters (s, t) in [0, 1], the same
    operations as ``edge_ccd._closest_segment_params`` for one pair."""
    d1x, d1y, d1z = q1x - p1x, q1y - p1y, q1z - p1z
    d2x, d2y, d2z = q2x - p2x, q2y - p2y, q2z - p2z
    rx, ry, rz = p1x - p2x, p1y - p2y, p1z - p2z
    a_ = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    c = d1x * rx + d1y * ry + d1z * rz
    b_ = d1x * d2x + d1y * d2y + d1z * d2z
    den = a_ * e - b_ * b_
    if den > 1e-20:
        s = min(max((b_ * f - c * e) / max(den, 1e-300), 0.0), 1.0)
    else:
        s = 0.0
    t = (b_ * s + f) / max(e, 1e-300)
    if t < 0:
        s = min(max(-c / max(a_, 1e-300), 0.0), 1.0)
    elif t > 1:
        s = min(max((b_ - c) / max(a_, 1e-300), 0.0), 1.0)
    t = min(max(t, 0.0), 1.0)
    return s, t


@njit(cache=True, inline="always")
def segment_distance(X, a0, a1, b0, b1):
    """Distance between the segments X[a0] X[a1] and X[b0] X[b1] (``segment_params``)."""
    s, t = segment_params(X[a0, 0], X[a0, 1], X[a0, 2], X[a1, 0], X[a1, 1], X[a1, 2],
                          X[b0, 0], X[b0, 1], X[b0, 2], X[b1, 0], X[b1, 1], X[b1, 2])
    dd = 0.0
    for c in range(3):
        g = X[a0, c] + s * (X[a1, c] - X[a0, c]) - X[b0, c] - t * (X[b1, c] - X[b0, c])
        dd += g * g
    return math.sqrt(dd)


@njit(cache=True)
def reachable(x0, x1, E, pairs, h):
    """(P,) mask: pairs whose distance at x0 minus the most their vertices' displacements
    x1 - x0 can close it is below h (``HairHair.filter_reachable``)."""
    P = pairs.shape[0]
    keep = np.zeros(P, dtype=np.bool_)
    for k in range(P):
        i = pairs[k, 0]
        j = pairs[k, 1]
        a0, a1, b0, b1 = E[i, 0], E[i, 1], E[j, 0], E[j, 1]
        D = 0.0
        for va in (a0, a1):
            for vb in (b0, b1):
                w = 0.0
                for c in range(3):
                    g = (x1[va, c] - x0[va, c]) - (x1[vb, c] - x0[vb, c])
                    w += g * g
                D = max(D, math.sqrt(w))
        keep[k] = segment_distance(x0, a0, a1, b0, b1) - D < h
    return keep


@njit(cache=True, inline="always")
def _sgn(v):
    return 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)


@njit(cache=True, inline="always")
def _cubic(c0, c1, c2, c3, s):
    return ((c3 * s + c2) * s + c1) * s + c0


@njit(cache=True, inline="always")
def _triple(ax, ay, az, bx, by, bz, cx, cy, cz):
    return (ay * bz - az * by) * cx + (az * bx - ax * bz) * cy + (ax * by - ay * bx) * cz


@njit(cache=True)
def edge_edge_ccd_pairs(x0, d, E, pairs, tol, bisections, hit, s_hit, wa, wb):
    """``edge_ccd.edge_edge_ccd`` pair by pair, with the same steps (cubic coplanarity
    coefficients, its monotone pieces split at the derivative's roots, ``bisections`` bisections
    of each sign change, the earliest root where the segments come within ``tol``): x0 (V, 3)
    start positions, d (V, 3) their displacements over the step, pairs (P, 2) of edges of E.
    Fills hit, s_hit (1 where no hit), wa, wb (P,)."""
    for k in range(pairs.shape[0]):
        i = pairs[k, 0]
        j = pairs[k, 1]
        pa0, pa1, pb0, pb1 = E[i, 0], E[i, 1], E[j, 0], E[j, 1]
        e1x, e1y, e1z = x0[pa1, 0] - x0[pa0, 0], x0[pa1, 1] - x0[pa0, 1], x0[pa1, 2] - x0[pa0, 2]
        e2x, e2y, e2z = x0[pb0, 0] - x0[pa0, 0], x0[pb0, 1] - x0[pa0, 1], x0[pb0, 2] - x0[pa0, 2]
        e3x, e3y, e3z = x0[pb1, 0] - x0[pa0, 0], x0[pb1, 1] - x0[pa0, 1], x0[pb1, 2] - x0[pa0, 2]
        d1x, d1y, d1z = d[pa1, 0] - d[pa0, 0], d[pa1, 1] - d[pa0, 1], d[pa1, 2] - d[pa0, 2]
        d2x, d2y, d2z = d[pb0, 0] - d[pa0, 0], d[pb0, 1] - d[pa0, 1], d[pb0, 2] - d[pa0, 2]
        d3x, d3y, d3z = d[pb1, 0] - d[pa0, 0], d[pb1, 1] - d[pa0, 1], d[pb1, 2] - d[pa0, 2]
        c0 = _triple(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
        c1 = (_triple(d1x, d1y, d1z, e2x, e2y, e2z, e3x, e3y, e3z) + _triple(e1x, e1y, e1z, d2x, d2y, d2z, e3x, e3y, e3z)
              + _triple(e1x, e1y, e1z, e2x, e2y, e2z, d3x, d3y, d3z))
        c2 = (_triple(d1x, d1y, d1z, d2x, d2y, d2z, e3x, e3y, e3z) + _triple(d1x, d1y, d1z, e2x, e2y, e2z, d3x, d3y, d3z)
              + _triple(e1x, e1y, e1z, d2x, d2y, d2z, d3x, d3y, d3z))
        c3 = _triple(d1x, d1y, d1z, d2x, d2y, d2z, d3x, d3y, d3z)
        A, B, Cc = 3 * c3, 2 * c2, c1
        disc = B * B - 4 * A * Cc
        sq = math.sqrt(max(disc, 0.0))
        r1 = np.nan
        r2 = np.nan
        if disc >= 0:
            if abs(A) > 1e-300:
                r1 = (-B - sq) / (2 * A)
                r2 = (-B + sq) / (2 * A)
            elif abs(B) > 1e-300:
                r1 = -Cc / B
        if math.isnan(r1):
            lo_c, hi_c = r2, r2
        elif math.isnan(r2):
            lo_c, hi_c = r1, r1
        else:
            lo_c, hi_c = min(r1, r2), max(r1, r2)
        k1 = lo_c if (lo_c > 0) and (lo_c < 1) else 0.0
        k2 = hi_c if (hi_c > 0) and (hi_c < 1) else 0.0
        if k2 < k1:
            k1, k2 = k2, k1
        knots = (0.0, k1, k2, 1.0)
        hit[k] = False
        s_hit[k] = 1.0
        wa[k] = 0.0
        wb[k] = 0.0
        for m in range(3):
            lo = knots[m]
            hi = knots[m + 1]
            flo = _cubic(c0, c1, c2, c3, lo)
            fhi = _cubic(c0, c1, c2, c3, hi)
            if not (hi > lo and (flo == 0 or _sgn(flo) != _sgn(fhi))):
                continue
            for _ in range(bisections):
                mid = 0.5 * (lo + hi)
                fm = _cubic(c0, c1, c2, c3, mid)
                if _sgn(fm) == _sgn(flo):
                    lo = mid
                    flo = fm
                else:
                    hi = mid
            s = lo if flo == 0 else 0.5 * (lo + hi)
            A0x, A0y, A0z = x0[pa0, 0] + s * d[pa0, 0], x0[pa0, 1] + s * d[pa0, 1], x0[pa0, 2] + s * d[pa0, 2]
            A1x, A1y, A1z = x0[pa1, 0] + s * d[pa1, 0], x0[pa1, 1] + s * d[pa1, 1], x0[pa1, 2] + s * d[pa1, 2]
            B0x, B0y, B0z = x0[pb0, 0] + s * d[pb0, 0], x0[pb0, 1] + s * d[pb0, 1], x0[pb0, 2] + s * d[pb0, 2]
            B1x, B1y, B1z = x0[pb1, 0] + s * d[pb1, 0], x0[pb1, 1] + s * d[pb1, 1], x0[pb1, 2] + s * d[pb1, 2]
            u, v = segment_params(A0x, A0y, A0z, A1x, A1y, A1z, B0x, B0y, B0z, B1x, B1y, B1z)
            gx = A0x + u * (A1x - A0x) - B0x - v * (B1x - B0x)
            gy = A0y + u * (A1y - A0y) - B0y - v * (B1y - B0y)
            gz = A0z + u * (A1z - A0z) - B0z - v * (B1z - B0z)
            if math.sqrt(gx * gx + gy * gy + gz * gz) <= tol:
                hit[k] = True
                s_hit[k] = s
                wa[k] = u
                wb[k] = v
                break


@njit(cache=True)
def pair_distances(X, E, pairs):
    """(P,) distances between the segments of the edge pairs at positions X (``segment_params``)."""
    P = pairs.shape[0]
    out = np.empty(P)
    for k in range(P):
        out[k] = segment_distance(X, E[pairs[k, 0], 0], E[pairs[k, 0], 1], E[pairs[k, 1], 0], E[pairs[k, 1], 1])
    return out


# --- the hair-hair list frame (``HairHair.frames``): the Kabsch fit's sums and the positions mapped


@njit(cache=True)
def centred_cross(x0, x1):
    """(c0, c1, H): the centroids of x0 and x1 (V, 3) and H = (x0 - c0)^T (x1 - c1) (3, 3), in two
    passes over the vertices."""
    V = x0.shape[0]
    c0 = np.zeros(3)
    c1 = np.zeros(3)
    for i in range(V):
        for d in range(3):
            c0[d] += x0[i, d]
            c1[d] += x1[i, d]
    for d in range(3):
        c0[d] /= V
        c1[d] /= V
    H = np.zeros((3, 3))
    for i in range(V):
        for a in range(3):
            p = x0[i, a] - c0[a]
            for b in range(3):
                H[a, b] += p * (x1[i, b] - c1[b])
    return c0, c1, H


def rotation_matrix(rv: np.ndarray) -> np.ndarray:
    """The rotation by the rotation vector ``rv`` (Rodrigues' formula; scipy's
    ``Rotation.from_rotvec(rv).as_matrix()`` to round-off, without its per-call overhead)."""
    th = float(np.linalg.norm(rv))
    K = np.array([[0.0, -rv[2], rv[1]], [rv[2], 0.0, -rv[0]], [-rv[1], rv[0], 0.0]])
    if th < 1e-8:     # the series to second order: its error th^3 / 6 is below round-off
        return np.eye(3) + K + 0.5 * (K @ K)
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / (th * th)) * (K @ K)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector of the rotation matrix R (its unit quaternion by Shepperd's method, the
    largest of 1 + trace and 1 + 2 R_ii - trace under the root, then 2 atan2(|v|, w) v / |v| with
    w >= 0; scipy's ``Rotation.from_matrix(R).as_rotvec()`` to round-off, without its per-call
    overhead)."""
    t = R[0, 0] + R[1, 1] + R[2, 2]
    k = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], t]))
    q = np.empty(4)          # (x, y, z, w)
    if k == 3:
        q[3] = 1.0 + t
        q[0], q[1], q[2] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        q[i] = 1.0 - t + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[m] = R[m, i] + R[i, m]
        q[3] = R[m, j] - R[j, m]
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    v = float(np.linalg.norm(q[:3]))
    if v < 1e-300:
        return np.zeros(3)
    return (2.0 * math.atan2(v, q[3]) / v) * q[:3]


@njit(cache=True)
def frame_positions(x0, x1, s, A, b, Y):
    """Y[k] = ((1 - s[k]) x0 + s[k] x1) A[k]^T + b[k] for each instant k."""
    for k in range(s.shape[0]):
        for i in range(x0.shape[0]):
            p0 = (1 - s[k]) * x0[i, 0] + s[k] * x1[i, 0]
            p1 = (1 - s[k]) * x0[i, 1] + s[k] * x1[i, 1]
            p2 = (1 - s[k]) * x0[i, 2] + s[k] * x1[i, 2]
            for d in range(3):
                Y[k, i, d] = A[k, d, 0] * p0 + A[k, d, 1] * p1 + A[k, d, 2] * p2 + b[k, d]


@njit(cache=True)
def contact_impulses(x1, v1, x0, E, pairs, hit, wa_c, wb_c, inv_m, h, dt, repulsion):
    """``HairHair.impulses`` after its CCD (``hit``, ``wa_c``, ``wb_c`` per pair; x0 None-free:
    pass hit all False without a start), with the same formulas in the same order: the contact
    normal and weights of each pair (the CCD's hit, else the end-of-step proximity within h),
    the inelastic / repulsion impulse, its Jacobi division by the largest contact count among the
    pair's vertices and its cap; the impulses are added to v1 in place in pair order.  Returns the
    number of pairs given an impulse."""
    P = pairs.shape[0]
    act = np.zeros(P, dtype=np.bool_)
    nrm = np.zeros((P, 3))
    W = np.zeros((P, 4))
    tgt = np.zeros(P)
    for k in range(P):
        a0, a1, b0, b1 = E[pairs[k, 0], 0], E[pairs[k, 0], 1], E[pairs[k, 1], 0], E[pairs[k, 1], 1]
        if hit[k]:
            wa, wb = wa_c[k], wb_c[k]
            for c in range(3):
                pa = x0[a0, c] + wa * (x0[a1, c] - x0[a0, c])
                pb = x0[b0, c] + wb * (x0[b1, c] - x0[b0, c])
                nrm[k, c] = pa - pb                              # the side a started on
            if math.sqrt(nrm[k, 0] ** 2 + nrm[k, 1] ** 2 + nrm[k, 2] ** 2) < 1e-12:
                ux, uy, uz = x0[a1, 0] - x0[a0, 0], x0[a1, 1] - x0[a0, 1], x0[a1, 2] - x0[a0, 2]
                wx, wy, wz = x0[b1, 0] - x0[b0, 0], x0[b1, 1] - x0[b0, 1], x0[b1, 2] - x0[b0, 2]
                cr0, cr1, cr2 = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
                side = (cr0 * (x1[a0, 0] - x1[b0, 0]) + cr1 * (x1[a0, 1] - x1[b0, 1])
                        + cr2 * (x1[a0, 2] - x1[b0, 2]))
                sg = 1.0 if side < 0 else -1.0
                nrm[k, 0], nrm[k, 1], nrm[k, 2] = cr0 * sg, cr1 * sg, cr2 * sg
            tgt[k] = repulsion * h / dt
            act[k] = True
        else:
            wa, wb = segment_params(x1[a0, 0], x1[a0, 1], x1[a0, 2], x1[a1, 0], x1[a1, 1], x1[a1, 2],
                                    x1[b0, 0], x1[b0, 1], x1[b0, 2], x1[b1, 0], x1[b1, 1], x1[b1, 2])
            dd = 0.0
            for c in range(3):
                g = (x1[a0, c] + wa * (x1[a1, c] - x1[a0, c])) - (x1[b0, c] + wb * (x1[b1, c] - x1[b0, c]))
                nrm[k, c] = g
                dd += g * g
            dist = math.sqrt(dd)
            if not dist < h:
                continue
            tgt[k] = repulsion * (h - dist) / dt
            act[k] = True
        W[k, 0], W[k, 1], W[k, 2], W[k, 3] = 1 - wa, wa, -(1 - wb), -wb
    V = v1.shape[0]
    imp = np.zeros(P)
    dvn = np.zeros(P)
    count = np.zeros(V, dtype=np.int64)
    for k in range(P):
        if not act[k]:
            continue
        ln = max(math.sqrt(nrm[k, 0] ** 2 + nrm[k, 1] ** 2 + nrm[k, 2] ** 2), 1e-300)
        for c in range(3):
            nrm[k, c] /= ln
        vv = (E[pairs[k, 0], 0], E[pairs[k, 0], 1], E[pairs[k, 1], 0], E[pairs[k, 1], 1])
        vn = 0.0
        for c in range(3):
            s = 0.0
            for m in range(4):
                s += W[k, m] * v1[vv[m], c]
            vn += s * nrm[k, c]
        dvn[k] = max(tgt[k] - vn, 0.0)                      # stop approach, then separate gently
        den = 0.0
        for m in range(4):
            den += W[k, m] ** 2 * inv_m[vv[m]]
        imp[k] = dvn[k] / den if den > 0 else 0.0
        if imp[k] > 0:
            for m in range(4):
                count[vv[m]] += 1
    given = 0
    for k in range(P):
        if not act[k] or not imp[k] > 0:
            continue
        vv = (E[pairs[k, 0], 0], E[pairs[k, 0], 1], E[pairs[k, 1], 0], E[pairs[k, 1], 1])
        cmax = 1
        for m in range(4):
            cmax = max(cmax, count[vv[m]])
        I = imp[k] / cmax
        vmax = 0.0
        for m in range(4):
            vmax = max(vmax, abs(W[k, m]) * inv_m[vv[m]])
        vmax *= I
        if vmax > dvn[k]:
            I = I * dvn[k] / max(vmax, 1e-300)
        if I > 0:
            given += 1
        for m in range(4):
            f = W[k, m] * inv_m[vv[m]] * I
            for c in range(3):
                v1[vv[m], c] += f * nrm[k, c]
    return given
