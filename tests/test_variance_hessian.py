"""The PSD model of the variance penalty's Hessian in the SQP (paper 3.3 leaves it out):
the Woodbury update solves the KKT system with U U^T added exactly, and at V = V_bar the model
equals the exact (autograd) Hessian of k (V - V_bar)^2."""

from __future__ import annotations

import numpy as np
import torch

from hairexp.control.tracking.sqp import woodbury
from hairexp.control.tracking.variance import variance


def test_woodbury_matches_the_dense_kkt_solve_with_the_low_rank_term():
    rng = np.random.default_rng(0)
    n, m, r = 12, 3, 2                  # x block, constraints, rank of U
    B = rng.normal(size=(n, n))
    H = B @ B.T + n * np.eye(n)
    A = rng.normal(size=(m, n))
    U = rng.normal(size=(n, r))

    def kkt(Hx):
        return np.block([[Hx, A.T], [A, np.zeros((m, m))]])

    def solve(r_x, c):               # s(b) = -K^-1 b, returned as (dx, dt, lam)
        sol = -np.linalg.solve(kkt(H), np.concatenate([r_x, c]))
        return sol[:n], None, sol[n:]

    g, C = rng.normal(size=n), rng.normal(size=m)
    dx, dt, lam = woodbury(solve, U, solve(g, C), np.zeros(m))
    want = -np.linalg.solve(kkt(H + U @ U.T), np.concatenate([g, C]))
    np.testing.assert_allclose(dx, want[:n], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(lam, want[n:], rtol=1e-10, atol=1e-12)
    assert dt is None


def test_hessian_model_is_exact_where_the_variance_meets_its_target():
    """At V = V_bar the curvature term 2 k (V - V_bar) hess V vanishes: diag + U U^T must equal
    the exact Hessian of k (V - V_bar)^2, which includes the cross-vertex coupling."""
    from types import SimpleNamespace

    from hairexp.control.tracking.variance import VarianceControl

    rng = np.random.default_rng(1)
    n_free, K = 10, 2
    cluster = np.array([0] * 5 + [1] * 5)
    masses = rng.uniform(0.5, 1.5, n_free)
    w = masses / np.bincount(cluster, weights=masses)[cluster]
    cons = SimpleNamespace(K=K, corr=SimpleNamespace(cluster_point=np.array([0, 1])), free_in_cluster=np.arange(n_free),
                           cluster_of_free=cluster, weights=w)
    cfg = SimpleNamespace(times=[0.0], stiffness_scale=[1.0], target_scale=[1.0], stiffness=3.0, points=[])
    xf = rng.normal(size=3 * n_free) * 0.1
    vc = VarianceControl(cfg, cons, xf)
    k = np.array([3.0, 3.0])
    vbar = vc.values(xf)                                    # the target met exactly
    diag, U = vc.hessian_parts(xf, k, vbar)
    model = np.diag(diag) + U @ U.T

    def P(x):
        V = variance(x.reshape(-1, 3), torch.as_tensor(cluster), torch.as_tensor(w), torch.arange(n_free), K)
        return (torch.as_tensor(k) * (V - torch.as_tensor(vbar)) ** 2).sum()

    exact = torch.autograd.functional.hessian(P, torch.as_tensor(xf)).numpy()
    np.testing.assert_allclose(model, exact, rtol=1e-9, atol=1e-12)
    assert np.abs(exact).max() > 0.1                       # not a vacuous comparison


def test_soft_hessian_model_is_exact_at_the_target_and_psd_above_it():
    """Overlapping clusters (soft assignment: a vertex in both, with shares): at V = V_bar the
    model diag + U U^T equals the exact Hessian of k (V - V_bar)^2 with the weighted variance
    sum_i s_ik |c_k - x_i|^2; above the target the model stays PSD and its diagonal is
    4 k (V - V_bar) s_ik where the exact curvature part is 2 k (V - V_bar) hess V."""
    from types import SimpleNamespace

    from hairexp.control.tracking.variance import VarianceControl

    rng = np.random.default_rng(3)
    n_free, K = 8, 2
    idx = np.array([0, 1, 2, 3, 4, 3, 4, 5, 6, 7])              # vertices 3, 4 in both clusters
    mc = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    share = np.array([1, 1, 1, 0.6, 0.3, 0.4, 0.7, 1, 1, 1.0])
    masses = rng.uniform(0.5, 1.5, n_free)
    ms = share * masses[idx]
    w = ms / np.bincount(mc, weights=ms)[mc]
    cons = SimpleNamespace(K=K, corr=SimpleNamespace(cluster_point=np.array([0, 1])), free_in_cluster=idx,
                           cluster_of_free=np.zeros(n_free, dtype=int), weights=w, member_cluster=mc,
                           member_share=share)
    cfg = SimpleNamespace(times=[0.0], stiffness_scale=[1.0], target_scale=[1.0], stiffness=3.0, points=[])
    xf = rng.normal(size=3 * n_free) * 0.1
    vc = VarianceControl(cfg, cons, xf)
    k = np.array([3.0, 3.0])

    def P(x, vbar):
        V = variance(x.reshape(-1, 3), torch.as_tensor(mc), torch.as_tensor(w), torch.as_tensor(idx), K,
                     torch.as_tensor(share))
        return (torch.as_tensor(k) * (V - torch.as_tensor(vbar)) ** 2).sum()

    vbar = vc.values(xf)
    diag, U = vc.hessian_parts(xf, k, vbar)
    exact = torch.autograd.functional.hessian(lambda x: P(x, vbar), torch.as_tensor(xf)).numpy()
    np.testing.assert_allclose(np.diag(diag) + U @ U.T, exact, rtol=1e-9, atol=1e-12)
    vlow = 0.5 * vbar                                        # above the target: curvature term on
    diag2, U2 = vc.hessian_parts(xf, k, vlow)
    assert np.linalg.eigvalsh(np.diag(diag2) + U2 @ U2.T).min() >= -1e-12
    want = np.zeros((n_free, 3))
    np.add.at(want, idx, (4 * k * (vbar - vlow))[mc][:, None] * share[:, None])
    np.testing.assert_allclose(diag2, want.reshape(-1), rtol=1e-12)
