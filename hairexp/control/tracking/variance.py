"""Spread control, paper 3.3: P = sum_k k_v,k(t) (V_k - V_bar_k(t))^2 with the cluster
variance V_k = sum_{i in C_k} |c_k - d_i|^2, eq. (4).  With soft assignment the variance is
weighted by the vertices' shares in the cluster: V_k = sum_i s_ik |c_k - d_i|^2 (c_k the
weighted centre of mass, hairexp/control/tracking/constraints.py; hard: s_ik = 1, eq. 4).

V_bar defaults to the rest variance.  k_v(t) = stiffness x stiffness_scale(t) and
V_bar(t) = rest variance x target_scale(t) are keyframed (linear between keys), and apply to
the clusters of the listed tracking-point indices (all when the list is empty), e.g. only the
tips.  Its gradient comes from autograd; unlike the paper, a PSD model of its Hessian enters
the SQP (``hessian_parts``: the Gauss-Newton rank one per cluster by a Woodbury update,
hairexp/control/tracking/sqp.py, plus the positive diagonal curvature).  A run with k_v = 0
builds no penalty.
"""

from __future__ import annotations

import numpy as np
import torch

from hairexp.errors import InputError


def _keys(times, values, key: str) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(list(times), dtype=np.float64)
    v = np.asarray(list(values), dtype=np.float64)
    if t.size != v.size or t.size == 0:
        raise InputError(f"needs as many keyframe values as times (got {v.size} and {t.size})", key)
    if np.any(np.diff(t) <= 0) or not np.isfinite(t).all():   # the times' fault, named so (probe, round 14)
        raise InputError(f"keyframe times must be finite and increase strictly, got {t.tolist()}", "tracking.variance.times")
    if not np.isfinite(v).all():
        raise InputError(f"keyframe values must be finite, got {v.tolist()}", key)
    return t, v


def variance(xf: torch.Tensor, cluster: torch.Tensor, w: torch.Tensor, idx: torch.Tensor, K: int,
             share: torch.Tensor | None = None) -> torch.Tensor:
    """(K,) V_k, eq. (4).  xf: (n_free, 3); per membership: idx the free-vertex index, cluster
    its cluster, w its mass weight s_ik m_i / M_k, share s_ik (None: all 1, hard assignment)."""
    x = xf[idx]
    com = torch.zeros(K, 3, dtype=x.dtype).index_add_(0, cluster, w.unsqueeze(-1) * x)
    sq = ((x - com[cluster]) ** 2).sum(-1)
    return torch.zeros(K, dtype=x.dtype).index_add_(0, cluster, sq if share is None else share * sq)


#: tracking.variance.stiffness at most this (as the material constants: beyond, the penalty's Hessian
#: against mass / dt^2 is beyond double precision)
MAX_VARIANCE_STIFFNESS = 1e9
#: tracking.variance.target_scale / stiffness_scale keys at most this (the paper's spreading asks 10)
MAX_VARIANCE_SCALE = 1e6


def check_variance_config(cfg) -> tuple[tuple, tuple]:
    """The checks of ``tracking.variance`` (keyframes, scales >= 0, stiffness >= 0) that need no
    scene: InputError naming the key.  Returns the two keyframe series ((t, stiffness scale),
    (t, target scale)).  Also called by hairexp/app/validate.py, so that an experiment refuses a
    bad value before its first variant runs, whatever that variant's controller."""
    ks = _keys(cfg.times, cfg.stiffness_scale, "tracking.variance.stiffness_scale")
    vs = _keys(cfg.times, cfg.target_scale, "tracking.variance.target_scale")
    for key, (_, v) in (("stiffness_scale", ks), ("target_scale", vs)):
        if (v < 0).any() or (v > MAX_VARIANCE_SCALE).any():   # 1e300 diverged at the first step (round 14)
            raise InputError(f"must be >= 0 and <= {MAX_VARIANCE_SCALE:g} at every keyframe (a scale of the rest "
                             f"variance or of tracking.variance.stiffness), got {v.tolist()}", f"tracking.variance.{key}")
    # nan and inf said "must be >= 0" (independent probe of issue 12, round 32): the whole range, as README says it
    if isinstance(cfg.stiffness, bool) or not (np.isfinite(cfg.stiffness) and 0 <= cfg.stiffness <= MAX_VARIANCE_STIFFNESS):
        raise InputError(f"must be a finite number from 0 to {MAX_VARIANCE_STIFFNESS:g} (J/m^4; 0 builds no penalty), "
                         f"got {cfg.stiffness}", "tracking.variance.stiffness")
    return ks, vs


class VarianceControl:
    def __init__(self, cfg, cons, rest_free: np.ndarray):
        self.cons = cons
        self.K = cons.K
        (self.t_k, self.k_scale), (self.t_v, self.v_scale) = check_variance_config(cfg)
        self.stiffness = float(cfg.stiffness)
        pts = list(cfg.points)
        self.mask = np.isin(cons.corr.cluster_point, pts) if pts else np.ones(self.K, dtype=bool)
        if pts and self.stiffness > 0 and not self.mask.any():
            raise InputError(f"none of the tracking points {pts} has a cluster (no free detail vertex is closest "
                             "to them): the variance penalty would be off", "tracking.variance.points")
        self.idx = torch.as_tensor(cons.free_in_cluster)
        mc = getattr(cons, "member_cluster", None)
        self.cluster = torch.as_tensor(cons.cluster_of_free[cons.free_in_cluster] if mc is None else mc)
        self.w = torch.as_tensor(cons.weights)
        sh = getattr(cons, "member_share", None)
        # None when every share is 1 (hard): eq. (4) exactly as written
        self.share = None if sh is None or np.all(sh == 1.0) else torch.as_tensor(sh)
        self.rest = self.values(rest_free)

    @property
    def active(self) -> bool:
        """False when k_v is zero at every keyframe: then no penalty is built at all."""
        return self.stiffness > 0 and bool(np.any(self.k_scale > 0)) and bool(self.mask.any())

    def values(self, xf: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return variance(torch.as_tensor(xf.reshape(-1, 3)), self.cluster, self.w, self.idx, self.K, self.share).numpy()

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(k_v (K,), V_bar (K,)) at time t."""
        k = self.stiffness * float(np.interp(t, self.t_k, self.k_scale)) * self.mask
        return k, self.rest * float(np.interp(t, self.t_v, self.v_scale))

    def hessian_parts(self, xf: np.ndarray, k: np.ndarray, vbar: np.ndarray):
        """A PSD model of the penalty's Hessian for the KKT matrix: (diagonal (N,), U (N, m)),
        meaning diag + U U^T.

        The exact Hessian is 2 k (grad V grad V^T + (V - V_bar) hess V) per cluster.  Its
        Gauss-Newton part is rank one per cluster, u = sqrt(2 k) grad V (from autograd), and
        goes into the solve exactly by a Woodbury update (``tracking.sqp``); of the curvature
        part, 2 k (V - V_bar) hess V, the diagonal is kept where it is positive (V > V_bar;
        hess V ~ 2 I).  The paper leaves the penalty's Hessian out; without it a stiff penalty
        made the SQP crawl (spreading: 400 iterations a step, half the steps unconverged)."""
        kk = np.asarray(k, dtype=np.float64)
        active = np.flatnonzero(kk > 0)
        x = torch.as_tensor(xf.reshape(-1, 3)).clone().requires_grad_(True)
        with torch.enable_grad():
            V = variance(x, self.cluster, self.w, self.idx, self.K, self.share)
            cols = [torch.autograd.grad(V[j], x, retain_graph=True)[0].reshape(-1).numpy() * np.sqrt(2.0 * kk[j])
                    for j in active]
        U = np.stack(cols, 1) if cols else np.zeros((xf.size, 0))
        Vn = V.detach().numpy()
        curv = np.maximum(4.0 * kk * (Vn - np.asarray(vbar)), 0.0)
        cm = curv[self.cluster.numpy()]
        if self.share is not None:     # hess V ~ 2 s_ik I
            cm = cm * self.share.numpy()
        d = np.zeros((xf.size // 3, 3))
        np.add.at(d, self.idx.numpy(), np.repeat(cm[:, None], 3, 1))
        return d.reshape(-1), U

    def value_grad(self, xf: np.ndarray, k: np.ndarray, vbar: np.ndarray, need_grad: bool = True):
        """P and its gradient over the free DOFs (N,)."""
        x = torch.as_tensor(xf.reshape(-1, 3)).clone().requires_grad_(need_grad)
        with torch.enable_grad():
            V = variance(x, self.cluster, self.w, self.idx, self.K, self.share)
            P = (torch.as_tensor(k) * (V - torch.as_tensor(vbar)) ** 2).sum()
            if not need_grad:
                return P.item(), None
            (g,) = torch.autograd.grad(P, x)
        return P.item(), g.reshape(-1).numpy()
