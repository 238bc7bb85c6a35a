"""Guide-deform skinning: each detail vertex rides on its guide (the baseline a user would pick
instead of tracking; reports/baselines.md), used by the ``skinned`` and ``attract`` controllers.

At rest, every free detail vertex i is bound to the guide of its strand (the guide with the
smallest integrated squared distance, eq. (1), as in the correspondence) at the rest arc length
a_i of its closest guide point, and its offset is stored in the guide's parallel-transported
frame there: o_i = F(a_i)^T (x_i - g(a_i)).  At time t the animated guide re-poses it:
x_g,i(t) = g_t(a_i) + F_t(a_i) o_i.  g(a) interpolates the guide vertices linearly in *rest*
arc length; F(a) blends the vertex frames (T, N, B) of the two neighbouring vertices linearly
and re-orthonormalises (Gram-Schmidt on T then N).  The frames are those of the tracking
targets (hairexp/control/tracking/constraints.py): parallel transport from the root, whose normal is
carried by the body.  Everything is equivariant under rigid motions (a rigid motion of guides
and body moves x_g rigidly) and x_g(0) = the rest positions exactly.

``positions(t)`` gives all vertices: the kinematic roots from the body, free vertices skinned.
"""

from __future__ import annotations

import numpy as np

from hairexp.control.tracking.correspondence import closest_points_on_polyline, strand_guide_distances
from hairexp.guides.frames import BodyCarriedFrames


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class GuideSkinning:
    def __init__(self, scene, guides):
        s = scene.strands
        self.scene, self.guides = scene, guides
        self.free = np.flatnonzero(~s.kinematic)
        rest = guides.guides(guides.rest)
        X0 = scene.initial_positions()   # registration positions (settled when scene.settle > 0)
        # eq. (1): each strand goes to the guide with the smallest integrated squared distance
        self.guide_of_strand = np.argmin(strand_guide_distances(X0, s.offsets, rest), axis=1)
        gv = np.repeat(self.guide_of_strand, np.diff(s.offsets))[self.free]
        R0, _ = scene.motion.pose(0.0)
        self.root_frames = BodyCarriedFrames(rest, R0)   # as the tracking targets' frames
        # binding: per guide, the bound free vertices, their segment and fraction in rest arc length
        self.bind = []
        for g, P in enumerate(rest):
            idx = np.flatnonzero(gv == g)                  # positions in the free-vertex list
            X = X0[self.free[idx]]
            _, arc = closest_points_on_polyline(X, P)
            knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
            j = np.clip(np.searchsorted(knots, arc, side="right") - 1, 0, len(P) - 2)
            u = np.clip((arc - knots[j]) / (knots[j + 1] - knots[j]), 0.0, 1.0)
            self.bind.append((idx, j, u))
        base, F = self._frames_at(guides.rest, R0)
        self.offset_local = np.einsum("nji,nj->ni", F, X0[self.free] - base)   # F^T (x - g)

    def _frames_at(self, shape: np.ndarray, R: np.ndarray):
        """Guide points g(a_i) (n, 3) and blended frames F(a_i) (n, 3, 3) (columns T, N, B) of every
        free vertex for guide vertices ``shape`` (Vg, 3) and body rotation R."""
        n = len(self.free)
        base = np.zeros((n, 3))
        F = np.zeros((n, 3, 3))
        for g, P in enumerate(self.guides.guides(shape)):
            idx, j, u = self.bind[g]
            if idx.size == 0:
                continue
            T, N, _ = self.root_frames.frames(g, P, R)
            uu = u[:, None]
            base[idx] = (1 - uu) * P[j] + uu * P[j + 1]
            t = _unit((1 - uu) * T[j] + uu * T[j + 1])
            nb = (1 - uu) * N[j] + uu * N[j + 1]
            nb = _unit(nb - np.sum(nb * t, -1, keepdims=True) * t)
            F[idx] = np.stack([t, nb, np.cross(t, nb)], axis=-1)
        return base, F

    def pose(self, shape: np.ndarray, R: np.ndarray) -> np.ndarray:
        """(n_free, 3) skinned positions of the free vertices for guide vertices ``shape`` and body
        rotation R."""
        base, F = self._frames_at(shape, R)
        return base + np.einsum("nij,nj->ni", F, self.offset_local)

    def free_positions(self, t: float, motion=None) -> np.ndarray:
        """(n_free, 3) x_g(t) of the free vertices, from the guide animation at time t;
        ``motion``: the body's poses at t (a dynamic body's step window), default the scene's."""
        R, _ = (motion or self.scene.motion).pose(t)
        return self.pose(self.guides.shape_at(t, motion), R)

    def positions(self, t: float, motion=None) -> np.ndarray:
        """(V, 3): kinematic roots on the body at t, free vertices skinned to the guides."""
        x = self.scene.root_positions(t, motion)
        x[self.free] = self.free_positions(t, motion)
        return x
