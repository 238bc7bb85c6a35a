"""Twist-free reference frames along a guide by discrete parallel transport (paper 3.2,
following Bergou et al. 2008): the frame at the guide root comes from the rigid body; each
next vertex frame is the previous one rotated by the smallest rotation taking the previous
tangent to the next (no rotation about the tangent: no twist)."""

from __future__ import annotations

import numpy as np


def vertex_tangents(P: np.ndarray) -> np.ndarray:
    """(n, 3) unit tangents at the vertices of a polyline (central differences, one-sided at
    the ends)."""
    T = np.empty_like(P)
    T[0] = P[1] - P[0]
    T[-1] = P[-1] - P[-2]
    if len(P) > 2:
        T[1:-1] = P[2:] - P[:-2]
    return T / np.linalg.norm(T, axis=-1, keepdims=True)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for (..., 3) arrays: ``np.cross``'s products and differences in its order (the same
    values bit for bit) without its per-call axis handling, which cost most of the guide frames'
    time (the tracking targets are re-framed at every stage of every step)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def transport(v: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Parallel-transport vectors v (..., 3) from unit tangent t0 to t1 (..., 3): the rotation
    about t0 x t1 by the angle between them (identity when they are parallel)."""
    b = cross(t0, t1)
    c = np.sum(t0 * t1, axis=-1, keepdims=True)
    # Rodrigues with k = b/|b|, sin = |b|, cos = c:  v c + (b x v) + b (b.v) / (1 + c)
    return v * c + cross(b, v) + b * np.sum(b * v, axis=-1, keepdims=True) / (1.0 + c)


def parallel_transport(P: np.ndarray, n0: np.ndarray):
    """Frames (T, N, B), each (n, 3), along polyline P (n, 3).  ``n0`` is the desired normal at
    the root; it is projected orthogonal to the root tangent."""
    T = vertex_tangents(P)
    N = np.empty_like(P)
    n = n0 - np.dot(n0, T[0]) * T[0]
    nn = np.linalg.norm(n)
    if nn < 1e-12:
        raise ValueError("root normal is parallel to the guide's first tangent")
    N[0] = n / nn
    for i in range(1, len(P)):
        v = transport(N[i - 1], T[i - 1], T[i])
        v -= np.dot(v, T[i]) * T[i]  # remove round-off drift
        N[i] = v / np.linalg.norm(v)
    return T, N, cross(T, N)


def parallel_transport_batch(P: np.ndarray, n0: np.ndarray):
    """Frames for G guides at once: P (G, n, 3), n0 (G, 3) -> T, N, B each (G, n, 3)."""
    T = np.stack([vertex_tangents(p) for p in P])
    N = np.empty_like(P)
    n = n0 - np.sum(n0 * T[:, 0], -1, keepdims=True) * T[:, 0]
    N[:, 0] = n / np.linalg.norm(n, axis=-1, keepdims=True)
    for i in range(1, P.shape[1]):
        v = transport(N[:, i - 1], T[:, i - 1], T[:, i])
        v -= np.sum(v * T[:, i], -1, keepdims=True) * T[:, i]
        N[:, i] = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return T, N, cross(T, N)


class BodyCarriedFrames:
    """Parallel-transported frames of each guide whose root normal is carried by the rigid body
    (paper 3.2): registered on the rest guides under the body rotation R0 at t = 0, re-posed for
    any guide shape and body rotation R.  Shared by the tracking targets and the skinning baseline."""

    def __init__(self, rest_guides: list[np.ndarray], R0: np.ndarray):
        self.n_body, self.t_body = [], []
        for P in rest_guides:
            T0 = vertex_tangents(P)[0]
            e = np.eye(3)[np.argmin(np.abs(T0))]
            n = e - np.dot(e, T0) * T0
            self.n_body.append(R0.T @ (n / np.linalg.norm(n)))
            self.t_body.append(R0.T @ T0)

    def frames(self, g: int, P: np.ndarray, R: np.ndarray):
        """(T, N, B), each (n, 3), along guide g's vertices P (n, 3) under body rotation R."""
        return self.frames_all([P], R, [g])[0]

    def frames_all(self, guides: list[np.ndarray], R: np.ndarray, ids=None, batch=None) -> list:
        """``frames`` of several guides (guide ids[i], default i, along guides[i]) under body
        rotation R; the guides with the same vertex count are transported together (the same
        values as one by one: every operation is per guide).  ``batch``: the transport of a
        group, ``parallel_transport_batch`` or a function with its signature and values (the
        tracking targets pass a compiled one, hairexp/control/tracking/constraints.py)."""
        ids = range(len(guides)) if ids is None else ids
        batch = parallel_transport_batch if batch is None else batch
        # body frame, turned onto the root tangent (all guides in one ``transport``: per row, the same values)
        first = np.stack([P[1] - P[0] for P in guides])
        t_root = first / np.linalg.norm(first, axis=-1, keepdims=True)    # vertex_tangents(P)[0]
        n0 = transport(np.stack([R @ self.n_body[g] for g in ids]), np.stack([R @ self.t_body[g] for g in ids]), t_root)
        out = [None] * len(guides)
        for n in sorted({len(P) for P in guides}):
            sel = [i for i, P in enumerate(guides) if len(P) == n]
            T, N, B = batch(np.stack([guides[i] for i in sel]), np.stack([n0[i] for i in sel]))
            for j, i in enumerate(sel):
                out[i] = (T[j], N[j], B[j])
        return out
