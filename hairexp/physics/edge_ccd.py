"""Continuous edge-edge collision detection over a time step (Bridson et al. 2002, 6.2).

The four endpoints move linearly, x(s) = x0 + s (x1 - x0), s in [0, 1].  The two edges can
only meet when the four points are coplanar: (a1 - a0) x (b0 - a0) . (b1 - a0) = 0, a cubic in
s.  Its real roots in [0, 1] are found robustly and vectorised: [0, 1] is split at the roots
of the derivative into monotone pieces and each sign change is bisected.  At the earliest root
where the segments' closest points are within ``tol``, the pair collides.
"""

from __future__ import annotations

import numpy as np

BISECTIONS = 40


def _closest_segment_params(p1, q1, p2, q2):
    """Closest points of segments p1q1 and p2q2 (vectorised): parameters (a, b) in [0, 1]."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a_ = np.sum(d1 * d1, 1)
    e = np.sum(d2 * d2, 1)
    f = np.sum(d2 * r, 1)
    c = np.sum(d1 * r, 1)
    b_ = np.sum(d1 * d2, 1)
    den = a_ * e - b_ * b_
    s = np.where(den > 1e-20, np.clip((b_ * f - c * e) / np.maximum(den, 1e-300), 0, 1), 0.0)
    t = (b_ * s + f) / np.maximum(e, 1e-300)
    t0 = t < 0
    t1 = t > 1
    s = np.where(t0, np.clip(-c / np.maximum(a_, 1e-300), 0, 1), np.where(t1, np.clip((b_ - c) / np.maximum(a_, 1e-300), 0, 1), s))
    t = np.clip(t, 0, 1)
    return s, t


def _triple(a, b, c):
    return np.einsum("ij,ij->i", np.cross(a, b), c)


def edge_edge_ccd(a0, a1, b0, b1, da0, da1, db0, db1, tol):
    """Arrays (P, 3): start positions and displacements over the step of the endpoints of
    edges a and b.  Returns (hit (P,), s (P,) collision time, wa (P,), wb (P,) segment
    parameters at the collision)."""
    e1, e2, e3 = a1 - a0, b0 - a0, b1 - a0
    d1, d2, d3 = da1 - da0, db0 - da0, db1 - da0
    c0 = _triple(e1, e2, e3)
    c1 = _triple(d1, e2, e3) + _triple(e1, d2, e3) + _triple(e1, e2, d3)
    c2 = _triple(d1, d2, e3) + _triple(d1, e2, d3) + _triple(e1, d2, d3)
    c3 = _triple(d1, d2, d3)
    f = lambda s: ((c3 * s + c2) * s + c1) * s + c0  # noqa: E731
    # critical points: 3 c3 s^2 + 2 c2 s + c1 = 0
    A, B, C = 3 * c3, 2 * c2, c1
    disc = B * B - 4 * A * C
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(np.abs(A) > 1e-300, (-B - sq) / (2 * A), np.where(np.abs(B) > 1e-300, -C / B, np.nan))
        r2 = np.where(np.abs(A) > 1e-300, (-B + sq) / (2 * A), np.nan)
    r1 = np.where(disc >= 0, r1, np.nan)
    r2 = np.where(disc >= 0, r2, np.nan)
    lo_c = np.fmin(r1, r2)
    hi_c = np.fmax(r1, r2)
    P = len(c0)
    knots = np.stack([np.zeros(P), np.where((lo_c > 0) & (lo_c < 1), lo_c, 0.0),
                      np.where((hi_c > 0) & (hi_c < 1), hi_c, 0.0), np.ones(P)], 1)
    knots = np.sort(knots, axis=1)
    hit = np.zeros(P, dtype=bool)
    s_hit = np.ones(P)
    wa = np.zeros(P)
    wb = np.zeros(P)
    for k in range(3):
        lo, hi = knots[:, k].copy(), knots[:, k + 1].copy()
        flo, fhi = f(lo), f(hi)
        has = (~hit) & (hi > lo) & ((flo == 0) | (np.sign(flo) != np.sign(fhi)))
        if not has.any():
            continue
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            fm = f(mid)
            left = np.sign(fm) == np.sign(flo)
            lo = np.where(has & left, mid, lo)
            flo = np.where(has & left, fm, flo)
            hi = np.where(has & ~left, mid, hi)
        s = np.where(flo == 0, lo, 0.5 * (lo + hi))
        A0, A1 = a0 + s[:, None] * da0, a1 + s[:, None] * da1
        B0, B1 = b0 + s[:, None] * db0, b1 + s[:, None] * db1
        u, v = _closest_segment_params(A0, A1, B0, B1)
        dist = np.linalg.norm(A0 + u[:, None] * (A1 - A0) - B0 - v[:, None] * (B1 - B0), axis=1)
        new = has & (dist <= tol)
        hit |= new
        s_hit = np.where(new, s, s_hit)
        wa = np.where(new, u, wa)
        wb = np.where(new, v, wb)
    return hit, s_hit, wa, wb
