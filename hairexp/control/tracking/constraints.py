"""Tracking constraints, paper eq. (3): C_k = c_k(x) - c_hat_k(t_k), three per cluster.

* c_k(x) = sum_i m_i x_i / M_k over the cluster's (free) vertices, eq. (2): linear in x, so
  dC/dx = A is a constant (3K x N) matrix built once.  With soft assignment (correspondence
  module) vertex i belongs to cluster k with a weight s_ik (its weights sum to one) and c_k is
  the weighted centre of mass c_k = sum_i s_ik m_i x_i / M_k, M_k = sum_i s_ik m_i: still
  linear in x with a constant A (hard: s_ik = 1 for the vertex's one cluster, eq. 2 itself).
* The target curve of cluster k is the Catmull-Rom spline through the guide's vertices offset
  by the registered offset in the parallel-transported frames (3.2):
  Q_ki = g_i + a_k N_i + b_k B_i + tau_k T_i, so c_hat_k(t) = g(t) + a_k N(t) + b_k B(t) + tau_k T(t)
  (Catmull-Rom is linear in its control points).  (a, b) = d (cos theta, sin theta) is the
  paper's (theta, d) encoding; tau is the tangential part, zero when t_k is the exact closest
  guide point, and kept so that the rest state meets the constraints to round-off.
* Soft assignment: a cluster's members belong to several guides (strand shares s_sg).  Its
  target is the blend c_hat_k(t) = sum_g beta_kg c_hat_kg(t) of one target curve per guide g,
  beta_kg = sum_i w_ik s_(strand i) g its mass fraction that belongs to g, c_hat_kg the curve
  of guide g through the sub-centre c_kg = sum_i w_ik s_ig x_i / beta_kg registered in g's
  transported frames at t_k (sum_g beta_kg c_kg = c_k: C = 0 at rest).  So a hair that moves
  as the shares' blend of its guides' motions (a skinned fan) meets the constraints; one target
  per cluster on its own guide instead would pull the shared centres apart by more than the
  guides (the overlapping weighted means must then be deconvolved: measured on fanning_smoke,
  a 39 cm spread for guides 26 cm apart, 4 clumps).  Hard assignment: beta one-hot, the curve
  above.
* Static targets fix t_k at its rest value (the arc length of the guide point closest to the
  rest centre of mass); sliding targets make t_k a variable (dC/dt = -c_hat'(t)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from hairexp.model.scene import Scene
from hairexp.guides import spline
from hairexp.control.tracking.correspondence import Correspondence, closest_points_on_polyline
from hairexp.guides.frames import BodyCarriedFrames, parallel_transport_batch
from hairexp.guides.animation import GuideAnimation
from hairexp.physics.kernels import HAVE_NUMBA, njit


@njit(cache=True, error_model="numpy")
def _targets_into(P, s, m, tk, ks, add, derivatives, c, d1, d2):
    """The Catmull-Rom curves of hairexp/guides/spline.py (``hermite_numpy``, compiled: the SQP
    evaluates them at every merit evaluation) at t = tk[ks[k]] for curve k, written (``add``:
    added, the soft blend over guides) into row ks[k] of c and, with ``derivatives``, d1, d2."""
    n = s.shape[0]
    for k in range(ks.shape[0]):
        t = tk[ks[k]]
        i = min(max(np.searchsorted(s, t, side="right") - 1, 0), n - 2)
        h = s[i + 1] - s[i]
        u = (t - s[i]) / h
        u2 = u * u
        u3 = u2 * u
        for x in range(3):
            p0, p1, m0, m1 = P[k, i, x], P[k, i + 1, x], m[k, i, x], m[k, i + 1, x]
            if t < s[0]:
                v, a, b = P[k, 0, x] + (t - s[0]) * m[k, 0, x], m[k, 0, x], 0.0
            elif t > s[n - 1]:
                v, a, b = P[k, n - 1, x] + (t - s[n - 1]) * m[k, n - 1, x], m[k, n - 1, x], 0.0
            else:
                v = ((2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * h * m0 + (-2 * u3 + 3 * u2) * p1
                     + (u3 - u2) * h * m1)
                a = (6 * u2 - 6 * u) * (p0 - p1) / h + (3 * u2 - 4 * u + 1) * m0 + (3 * u2 - 2 * u) * m1
                b = (12 * u - 6) * (p0 - p1) / (h * h) + (6 * u - 4) * m0 / h + (6 * u - 2) * m1 / h
            r = ks[k]
            if add:
                c[r, x] += v
            else:
                c[r, x] = v
            if derivatives:
                if add:
                    d1[r, x] += a
                    d2[r, x] += b
                else:
                    d1[r, x] = a
                    d2[r, x] = b


@njit(cache=True, error_model="numpy", inline="always")
def _cross3(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, error_model="numpy")
def _transport_into(P, n0, T, N, B):
    """``hairexp.guides.frames.parallel_transport_batch`` compiled, into T, N, B (G, n, 3): the
    same operations in the same order (vertex tangents by central differences, the root normal
    projected, each next normal transported by Rodrigues' formula from tangent to tangent and
    re-projected), so the same values; the targets are re-framed at every stage of a tracked
    step, where numpy's per-vertex loop over 3-vectors cost 1.4 ms at Celia's 3 x 10 vertices."""
    G, n = P.shape[0], P.shape[1]
    for g in range(G):
        for i in range(n):
            lo, hi = (0, 1) if i == 0 else ((n - 2, n - 1) if i == n - 1 else (i - 1, i + 1))
            t0, t1, t2 = P[g, hi, 0] - P[g, lo, 0], P[g, hi, 1] - P[g, lo, 1], P[g, hi, 2] - P[g, lo, 2]
            nrm = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            T[g, i, 0], T[g, i, 1], T[g, i, 2] = t0 / nrm, t1 / nrm, t2 / nrm
        d = n0[g, 0] * T[g, 0, 0] + n0[g, 1] * T[g, 0, 1] + n0[g, 2] * T[g, 0, 2]
        v0, v1, v2 = n0[g, 0] - d * T[g, 0, 0], n0[g, 1] - d * T[g, 0, 1], n0[g, 2] - d * T[g, 0, 2]
        nrm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        N[g, 0, 0], N[g, 0, 1], N[g, 0, 2] = v0 / nrm, v1 / nrm, v2 / nrm
        for i in range(1, n):
            a0, a1, a2 = T[g, i - 1, 0], T[g, i - 1, 1], T[g, i - 1, 2]
            c0, c1, c2 = T[g, i, 0], T[g, i, 1], T[g, i, 2]
            w0, w1, w2 = N[g, i - 1, 0], N[g, i - 1, 1], N[g, i - 1, 2]
            b0, b1, b2 = _cross3(a0, a1, a2, c0, c1, c2)
            c = a0 * c0 + a1 * c1 + a2 * c2
            x0, x1, x2 = _cross3(b0, b1, b2, w0, w1, w2)
            bv = b0 * w0 + b1 * w1 + b2 * w2
            v0 = w0 * c + x0 + b0 * bv / (1.0 + c)
            v1 = w1 * c + x1 + b1 * bv / (1.0 + c)
            v2 = w2 * c + x2 + b2 * bv / (1.0 + c)
            d = v0 * c0 + v1 * c1 + v2 * c2
            v0, v1, v2 = v0 - d * c0, v1 - d * c1, v2 - d * c2
            nrm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            N[g, i, 0], N[g, i, 1], N[g, i, 2] = v0 / nrm, v1 / nrm, v2 / nrm
        for i in range(n):
            B[g, i, 0], B[g, i, 1], B[g, i, 2] = _cross3(T[g, i, 0], T[g, i, 1], T[g, i, 2],
                                                         N[g, i, 0], N[g, i, 1], N[g, i, 2])


def transport_frames(P: np.ndarray, n0: np.ndarray):
    """``parallel_transport_batch(P, n0)`` through the compiled ``_transport_into`` (P (G, n, 3),
    n0 (G, 3) -> T, N, B each (G, n, 3)); the numpy function itself without numba or for a guide
    of fewer than 2 vertices."""
    if not HAVE_NUMBA or P.shape[1] < 2:
        return parallel_transport_batch(P, n0)
    P = np.ascontiguousarray(P, dtype=np.float64)
    T, N, B = np.empty_like(P), np.empty_like(P), np.empty_like(P)
    _transport_into(P, np.ascontiguousarray(n0, dtype=np.float64), T, N, B)
    return T, N, B


def _tangents_numpy(P: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``hairexp.guides.spline.tangents`` on numpy arrays (the same operations, so the same
    values): the Catmull-Rom tangents dP/dt at the knots, P (..., n, 3), s (n,)."""
    m = np.empty_like(P)
    ds = s[1:] - s[:-1]
    m[..., 0, :] = (P[..., 1, :] - P[..., 0, :]) / ds[0]
    m[..., -1, :] = (P[..., -1, :] - P[..., -2, :]) / ds[-1]
    if P.shape[-2] > 2:
        m[..., 1:-1, :] = (P[..., 2:, :] - P[..., :-2, :]) / (s[2:] - s[:-2])[:, None]
    return m


@dataclass
class TargetCurves:
    """Target curves at one time: control points (K, n, 3) per cluster on its guide's knots."""
    control: list[torch.Tensor]      # per guide: (K_g, n_g, 3)
    knots: list[torch.Tensor]        # per guide: (n_g,)
    clusters: list[np.ndarray]       # per guide: cluster indices
    guide_shape: np.ndarray          # (Vg, 3)


class TrackingConstraints:
    def __init__(self, scene: Scene, corr: Correspondence, guides: GuideAnimation, sliding: bool):
        s = scene.strands
        self.scene, self.corr, self.guides, self.sliding = scene, corr, guides, sliding
        K = corr.n_clusters
        self.K = K
        free = np.flatnonzero(~s.kinematic)
        cv = corr.cluster_of_vertex[free]
        # memberships (vertex, cluster, share s_ik), vertex order: hard has one per clustered free vertex
        free_index = np.full(s.n_vertices, -1)
        free_index[free] = np.arange(len(free))
        fidx = free_index[corr.member_vertex]
        mc, share = corr.member_cluster, corr.member_weight
        ms = share * s.masses[corr.member_vertex]                                   # s_ik m_i
        self.M = np.bincount(mc, weights=ms, minlength=K)      # (K,) cluster masses, eq. (2)'s M_k
        w = ms / self.M[mc]
        rows = (3 * mc[:, None] + np.arange(3)).ravel()
        cols = (3 * fidx[:, None] + np.arange(3)).ravel()
        self.A = sp.csr_matrix((np.repeat(w, 3), (rows, cols)), shape=(3 * K, 3 * len(free)))
        self.AT = self.A.T.tocsr()
        # per membership: the free-vertex index, its cluster, the COM weight s m / M and the share s
        self.weights, self.free_in_cluster, self.member_cluster, self.member_share = w, fidx, mc, share
        self.cluster_of_free = cv          # (n_free,) each free vertex's (dominant) cluster, -1: none
        # registration at rest (t = 0)
        G = guides.n_guides
        rest = guides.guides(guides.rest)
        self.knots = [spline.rest_arclength(P) for P in rest]
        self.root_frames = BodyCarriedFrames(rest, scene.motion.pose(0.0)[0])
        com = self.com(scene.initial_positions()[free].reshape(-1))
        self.t_rest = np.zeros(K)
        self.by_guide = [np.flatnonzero(corr.cluster_guide == g) for g in range(G)]
        for g in range(G):
            ks = self.by_guide[g]
            if ks.size:
                _, arc = closest_points_on_polyline(com[ks], rest[g])
                self.t_rest[ks] = arc
        # beta (K, G): each cluster's mass fraction per guide; the sub-centres c_kg (soft only)
        gw = corr.guide_weights
        strand_of_member = s.strand_of_vertex[corr.member_vertex]
        beta = np.zeros((K, G))
        if gw is None:
            beta[np.arange(K), corr.cluster_guide] = 1.0
        else:
            for g in range(G):
                beta[:, g] = np.bincount(mc, weights=w * gw[strand_of_member, g], minlength=K)
        multi = (beta > 0).sum(1) > 1
        self.soft = bool(multi.any())      # some cluster's target blends several guides
        beta[~multi] = 0.0
        beta[~multi, corr.cluster_guide[~multi]] = 1.0      # one guide: exactly 1 (hard: every cluster)
        self.beta = beta
        xr = scene.initial_positions()[free]
        # per guide g: (its clusters, their beta, their offsets (a, b, tau) in g's frames)
        self.blend = []
        frames = self._frames(guides.rest, 0.0)
        for g in range(G):
            ks = np.flatnonzero(beta[:, g] > 0)
            off = np.zeros((len(ks), 3))
            if ks.size:
                centre = com[ks].copy()
                for j, k in enumerate(ks):
                    if multi[k]:   # the sub-centre of the members' shares of guide g
                        on = mc == k
                        ww = w[on] * gw[strand_of_member[on], g]
                        centre[j] = ww @ xr[fidx[on]] / ww.sum()
                P, (T, N, B) = rest[g], frames[g]
                basis = [torch.as_tensor(np.repeat(V[None], len(ks), 0)) for V in (P, N, B, T)]
                tk = torch.as_tensor(self.t_rest[ks])
                gp, Np, Bp, Tp = (spline.evaluate(b, self.knots[g], tk).numpy() for b in basis)
                r = centre - gp
                F = np.stack([Np, Bp, Tp], axis=-1)                 # (k, 3, 3) columns N, B, T
                off = np.linalg.solve(F, r[..., None])[..., 0]
            self.blend.append((ks, beta[ks, g], off))
        self.offset_local = np.zeros((K, 3))  # (a, b, tau) on the cluster's own guide
        for g, (ks, _, off) in enumerate(self.blend):
            own = corr.cluster_guide[ks] == g
            self.offset_local[ks[own]] = off[own]
        self.offset_d = np.linalg.norm(self.offset_local[:, :2], axis=1)
        self.offset_theta = np.arctan2(self.offset_local[:, 1], self.offset_local[:, 0])

    # -- geometry -------------------------------------------------------------------------
    def com(self, xf: np.ndarray) -> np.ndarray:
        """(K, 3) cluster centres of mass, eq. (2), from the free DOF vector."""
        return (self.A @ xf).reshape(self.K, 3)

    def _frames(self, shape: np.ndarray, t: float, motion=None):
        """Parallel-transported frames of every guide at time t: list of (T, N, B)."""
        R, _ = (motion or self.scene.motion).pose(t)
        return self.root_frames.frames_all(list(self.guides.guides(shape)), R, batch=transport_frames)

    def targets(self, t: float, motion=None) -> TargetCurves:
        """The target curves at time t; ``motion``: the body's poses at t (a dynamic body's step
        window), default the scene's motion."""
        shape = self.guides.shape_at(t, motion)
        frames = self._frames(shape, t, motion)
        ctrl, clusters = [], []
        for g, P in enumerate(self.guides.guides(shape)):
            ks, beta, off = self.blend[g]
            T, N, B = frames[g]
            a, b, tau = (off[:, j][:, None, None] for j in range(3))
            Q = P[None] + a * N[None] + b * B[None] + tau * T[None]     # (k, n, 3)
            if self.soft:
                Q = beta[:, None, None] * Q       # Catmull-Rom is linear in its control points
            ctrl.append(torch.as_tensor(Q))
            clusters.append(ks)
        return TargetCurves(ctrl, self.knots, clusters, shape)

    def _numpy_curves(self, tg: TargetCurves) -> list:
        """Per guide (control points, knots, tangents, clusters) as numpy arrays, for the target
        curves ``tg`` (kept for the last ``tg``: it is constant over a step's SQP iterations)."""
        cached = getattr(self, "_np_curves", None)
        if cached is None or cached[0] is not tg:
            # the tangents in numpy (``_tangents_numpy``, torch's values): through torch they cost
            # 0.3 ms a stage at Celia's 3 guides
            curves = [(Q.numpy(), s.numpy(), _tangents_numpy(Q.numpy(), s.numpy()), np.ascontiguousarray(ks, dtype=np.int64))
                      for Q, s, ks in zip(tg.control, tg.knots, tg.clusters) if ks.size]
            cached = self._np_curves = (tg, curves)
        return cached[1]

    def target_points(self, tg: TargetCurves, tk: np.ndarray, derivatives: bool = False):
        """c_hat(t) (K, 3) and, with ``derivatives``, c_hat' and c_hat'' (K, 3) each (the
        Catmull-Rom curves of hairexp/guides/spline.py, compiled: ``_targets_into``)."""
        c = np.zeros((self.K, 3))
        d1 = np.zeros((self.K, 3))
        d2 = np.zeros((self.K, 3))
        tk = np.ascontiguousarray(tk, dtype=np.float64)
        for Q, s, m, ks in self._numpy_curves(tg):
            # soft: the blend over the guides (a cluster appears once per guide)
            _targets_into(Q, s, m, tk, ks, self.soft, derivatives, c, d1, d2)
        return (c, d1, d2) if derivatives else c

    def residual(self, xf: np.ndarray, tg: TargetCurves, tk: np.ndarray) -> np.ndarray:
        """(K, 3) C = c(x) - c_hat(t), eq. (3)."""
        return self.com(xf) - self.target_points(tg, tk)
