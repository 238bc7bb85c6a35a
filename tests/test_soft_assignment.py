"""Soft hair-to-guide assignment (tracking.assignment=soft; paper section 5 / Fig. 8 names it as
future work): weights per strand and guide from eq. (1), memberships that sum to one per vertex,
weighted centres of mass (eq. 2 with shares) whose constant Jacobian A the Schur KKT path uses,
exact rest registration, the weighted variance (eq. 4), and the limit blend_width -> 0 = hard."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers import bent_polyline
from tracking_helpers import (DT, GOALING_MOTION, build_tracked, polyline_scene, structured_sliding_args, tracked_cfg,
                              tracking_cfg)
from hairexp.control.tracking.controller import TrackingController
from hairexp.control.tracking.correspondence import WEIGHT_CUTOFF, build_correspondence
from hairexp.control.tracking.kkt import reference_solve
from hairexp.guides.animation import GuideAnimation
from hairexp.physics.assembly import BandedAssembler
from hairexp.physics.simulator import Simulator


def straight(root, direction, length, n):
    d = np.asarray(direction, dtype=np.float64)
    return np.asarray(root, dtype=np.float64) + np.linspace(0.0, length, n)[:, None] * d / np.linalg.norm(d)


def random_strands(seed: int, G: int):
    """Detail strands scattered around G parallel hanging guides (unequal lengths and counts)."""
    rng = np.random.default_rng(seed)
    roots = [np.array([0.02 * np.cos(2 * np.pi * g / G), 0.0, 0.02 * np.sin(2 * np.pi * g / G)]) for g in range(G)]
    guides = [straight(r, [0.0, -1.0, 0.0], 0.3, 8) for r in roots]
    polys = []
    for j in range(int(rng.integers(8, 20))):
        r = rng.uniform(-0.03, 0.03, 3) * [1, 0, 1]
        n = int(rng.integers(4, 12))
        polys.append(straight(r, [rng.normal(0, 0.05), -1.0, rng.normal(0, 0.05)], rng.uniform(0.15, 0.3), n))
    X = np.concatenate(polys)
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in polys])])
    free = np.ones(len(X), dtype=bool)
    free[offsets[:-1]] = False
    return X, offsets, free, guides


# -- weights -----------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(8))
def test_soft_weights_sum_to_one_and_share_strands_among_guides(seed):
    """Property test over random scenes: every free vertex's shares sum to one, each is in
    (0, 1], a vertex has at most one cluster per guide, root vertices are in no cluster, the
    dominant cluster is the one of largest share, and a strand's share of a guide falls with its
    excess RMS distance (eq. 1)."""
    G = 2 + seed % 2
    X, offsets, free, guides = random_strands(seed, G)
    b = [0.002, 0.01, 0.05][seed % 3]
    c = build_correspondence(X, offsets, free, guides, 4, assignment="soft", blend_width=b)
    sums = np.bincount(c.member_vertex, weights=c.member_weight, minlength=len(X))
    np.testing.assert_allclose(sums[free], 1.0, rtol=0, atol=1e-14)
    assert (sums[~free] == 0).all()
    assert ((c.member_weight > 0) & (c.member_weight <= 1)).all()
    pairs = set(zip(c.member_vertex.tolist(), c.cluster_guide[c.member_cluster].tolist()))
    assert len(pairs) == len(c.member_vertex)          # one cluster per (vertex, guide)
    for v in np.flatnonzero(free):
        on = c.member_vertex == v
        assert c.cluster_of_vertex[v] == c.member_cluster[on][np.argmax(c.member_weight[on])]
    np.testing.assert_allclose(c.guide_weights.sum(1), 1.0, rtol=0, atol=1e-14)
    # monotone: nearer guide (RMS eq. 1), larger weight
    from hairexp.control.tracking.correspondence import strand_guide_distances
    D = np.sqrt(strand_guide_distances(X, offsets, guides) / np.diff(offsets)[:, None])
    for s in range(len(D)):
        o = np.argsort(D[s])
        assert np.all(np.diff(c.guide_weights[s, o]) <= 1e-15)
    if b >= 0.01:   # wide enough: some strand is shared
        assert (c.guide_weights.max(1) < 1).any()


def test_blend_width_to_zero_is_hard_assignment():
    X, offsets, free, guides = random_strands(3, 3)
    hard = build_correspondence(X, offsets, free, guides, 5, assignment="hard")
    soft = build_correspondence(X, offsets, free, guides, 5, assignment="soft", blend_width=1e-7)
    for k in ("guide_of_strand", "cluster_of_vertex", "cluster_guide", "cluster_point", "member_vertex",
              "member_cluster", "member_weight", "guide_weights"):
        np.testing.assert_array_equal(getattr(soft, k), getattr(hard, k), err_msg=k)
    wide = build_correspondence(X, offsets, free, guides, 5, assignment="soft", blend_width=0.02)
    assert len(wide.member_vertex) > len(hard.member_vertex)   # the test can tell them apart


def test_cutoff_drops_far_guides():
    """A guide 2.63 blend widths farther than the nearest (raw weight < WEIGHT_CUTOFF) gets no share."""
    b = 0.01
    e = np.sqrt(-np.log(WEIGHT_CUTOFF)) * b
    guides = [straight([0, 0, 0], [0, -1, 0], 0.3, 6), straight([e * 1.05, 0, 0], [0, -1, 0], 0.3, 6),
              straight([e * 0.9, 0, 0.0], [0, -1, 0], 0.3, 6)]
    X = straight([0, 0, 0], [0, -1, 0], 0.3, 7)
    free = np.ones(7, dtype=bool)
    free[0] = False
    c = build_correspondence(X, np.array([0, 7]), free, guides, 3, assignment="soft", blend_width=b)
    assert c.guide_weights[0, 1] == 0.0 and c.guide_weights[0, 2] > 0.0


# -- constraints ------------------------------------------------------------------------------
def soft_cfg(guides=3, **kw):
    return tracked_cfg({**GOALING_MOTION, "scene.n_strands": 12, "scene.n_vertices": 10, "guides.count": guides,
                        "guides.source": "scaled", "guides.scale_times": [0.0, 0.48], "guides.scale_factors": [1.0, 0.8],
                        "tracking.assignment": "soft", "tracking.blend_width": 0.01, "frames": 12, **kw})


def test_soft_is_shared_in_the_test_scene():
    _, _, sim = build_tracked(soft_cfg())
    W = sim.controller.cluster_weights()
    assert W is not None and ((W > 0).sum(1) > 1).any()       # some vertex is in several clusters
    free = ~sim.scene.strands.kinematic
    np.testing.assert_allclose(W[free].sum(1), 1.0, rtol=0, atol=1e-14)
    assert (W[~free] == 0).all()
    assert sim.controller.kkt.R > 3 * (int(sim.controller.corr.cluster_point.max()) + 1)   # several guides per strand


def test_weighted_com_jacobian_matches_autograd_and_finite_differences():
    """A (constant) = d c / d x of c_k = sum_i s_ik m_i x_i / sum_i s_ik m_i, written here
    independently from the dense shares (autograd), and finite differences of cons.com."""
    scene, _, sim = build_tracked(soft_cfg())
    tr = sim.controller
    free = ~scene.strands.kinematic
    W = torch.as_tensor(tr.cluster_weights()[free])             # (n_free, K)
    m = torch.as_tensor(scene.strands.masses[free])

    def com(xf):
        x = xf.reshape(-1, 3)
        return ((W * m[:, None]).T @ x / (W * m[:, None]).sum(0)[:, None]).reshape(-1)

    x0 = torch.as_tensor(scene.initial_positions()[free].reshape(-1))
    J = torch.autograd.functional.jacobian(com, x0).numpy()
    np.testing.assert_allclose(tr.cons.A.toarray(), J, rtol=0, atol=1e-14)
    rng = np.random.default_rng(0)
    xf = x0.numpy() + rng.normal(scale=0.01, size=x0.shape)
    np.testing.assert_allclose(tr.cons.com(xf).reshape(-1), com(torch.as_tensor(xf)).numpy(), rtol=0, atol=1e-14)
    h = 1e-6
    for j in rng.choice(xf.size, 12, replace=False):
        e = np.zeros_like(xf)
        e[j] = h
        fd = (tr.cons.com(xf + e) - tr.cons.com(xf - e)).reshape(-1) / (2 * h)
        np.testing.assert_allclose(fd, tr.cons.A.toarray()[:, j], rtol=0, atol=1e-8)


@pytest.mark.parametrize("targets", ["sliding", "static"])
def test_soft_rest_registration_is_exact(targets):
    """C = 0 at rest (the registered offsets in the transported frames) to round-off."""
    scene, _, sim = build_tracked(soft_cfg(**{"tracking.targets": targets}))
    tr = sim.controller
    xf = sim.free_dofs(sim.initial_state().x)
    C = tr.cons.residual(xf, tr.cons.targets(0.0), tr.cons.t_rest)
    assert np.abs(C).max() <= 1e-14 * (1 + np.abs(tr.cons.com(xf)).max())


def _soft_step_system(seed):
    """(scene, objective, tracking controller, rng, xf, banded Hessian at xf) of the first step of the
    soft-assignment scene, xf the initial guess perturbed by 3 mm noise from ``seed``'s rng."""
    scene, _, sim = build_tracked(soft_cfg())
    obj, tr = sim.objective, sim.controller
    st = sim.initial_state()
    obj.begin_step(st.x, st.v, scene.root_positions(DT), DT, st.tensions)
    tr.begin(DT)
    rng = np.random.default_rng(seed)
    xf = obj.initial_guess() + rng.normal(scale=0.003, size=obj.n_dofs)
    return scene, obj, tr, rng, xf, obj.evaluate(xf).banded


@pytest.mark.parametrize("system", ["static", "sliding"])
def test_soft_schur_kkt_matches_reference_solve(system):
    _, obj, tr, rng, xf, ab = _soft_step_system(5)
    K = tr.cons.K
    r_x, C = rng.normal(size=obj.n_dofs) * 1e-3, rng.normal(size=3 * K) * 1e-3
    args = (None, None, None)
    if system == "sliding":
        args = structured_sliding_args(tr, rng, K)
    tr.kkt.factor(ab)
    got = tr.kkt.solve(r_x, C, *args)
    ref = reference_solve(ab, tr.cons.A, r_x, C, *args)
    H = BandedAssembler.to_sparse(ab)
    assert np.linalg.norm(H @ ref[0] + tr.cons.A.T @ ref[2] + r_x) < 1e-10 * np.linalg.norm(r_x)
    for name, a, b in zip(("dx", "dt", "lam"), got, ref):
        if b is None:
            assert a is None
            continue
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max(), err_msg=name)


@pytest.mark.parametrize("system", ["static", "sliding"])
def test_soft_krylov_schur_kkt_matches_reference_solve(system):
    """tracking.schur=krylov with soft assignment (a strand in clusters of several guides): the
    Krylov path, preconditioned by S of a nearby Hessian, agrees with the sparse solve."""
    from hairexp.control.tracking.kkt import SchurKKT

    scene, obj, tr, rng, xf, ab = _soft_step_system(6)
    ab_near = obj.evaluate(xf + rng.normal(scale=1e-5, size=obj.n_dofs)).banded
    K = tr.cons.K
    r_x, C = rng.normal(size=obj.n_dofs) * 1e-3, rng.normal(size=3 * K) * 1e-3
    args = (None, None, None)
    if system == "sliding":
        args = structured_sliding_args(tr, rng, K)
    kkt = SchurKKT(scene.strands, tr.cons, obj.assembler.bandwidth, obj.kernels, schur="krylov", krylov_max=30,
                   krylov_tol=1e-12)   # the direct solves' residual (the default is 1e-6)
    kkt.factor(ab_near)
    kkt.factor(ab)
    got = kkt.solve(r_x, C, *args)
    assert kkt.stats["krylov_solves"] == 1 and kkt.stats["krylov_fallbacks"] == 0
    assert kkt.stats["krylov_iterations"] >= 2
    ref = reference_solve(ab, tr.cons.A, r_x, C, *args)
    for name, a, b in zip(("dx", "dt", "lam"), got, ref):
        if b is None:
            assert a is None
            continue
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max(), err_msg=name)


def test_weighted_variance_and_its_gradient():
    """V_k = sum_i s_ik |c_k - x_i|^2 (eq. 4 with shares), against numpy; the penalty's gradient
    against central differences."""
    scene, _, sim = build_tracked(soft_cfg(**{"tracking.variance.stiffness": 1e3}))
    tr = sim.controller
    free = ~scene.strands.kinematic
    W = tr.cluster_weights()[free]
    rng = np.random.default_rng(2)
    xf = sim.free_dofs(sim.initial_state().x) + rng.normal(scale=0.005, size=tr.cons.A.shape[1])
    x = xf.reshape(-1, 3)
    c = tr.cons.com(xf)
    want = np.array([(W[:, k] * ((x - c[k]) ** 2).sum(1)).sum() for k in range(tr.cons.K)])
    np.testing.assert_allclose(tr.variance.values(xf), want, rtol=1e-13)
    k, vbar = tr.variance.at(0.0)
    vbar = vbar * 1.5
    P, g = tr.variance.value_grad(xf, k, vbar)
    h = 1e-7
    for j in rng.choice(xf.size, 10, replace=False):
        e = np.zeros_like(xf)
        e[j] = h
        fd = (tr.variance.value_grad(xf + e, k, vbar, False)[0] - tr.variance.value_grad(xf - e, k, vbar, False)[0]) / (2 * h)
        assert abs(fd - g[j]) <= 1e-6 * max(abs(g[j]), np.abs(g).max() * 1e-3)


def test_soft_tracked_steps_converge_and_meet_the_constraints():
    """A few steps of the goaling motion with 2 soft-assigned guides: converged, |C| <= 1e-8 L."""
    scene, _, sim = build_tracked(soft_cfg(guides=2))
    tr = sim.controller
    state = sim.initial_state()
    for _ in range(10):
        state, info = sim.step(state, DT)
        assert info.converged
        m = tr.measure(sim.free_dofs(state.x), state.time, state.control)
        assert m["residual_rel_max"] <= 1e-8


def test_soft_krylov_and_exact_schur_give_the_same_steps():
    """tracking.schur=krylov against exact, 10 goaling steps with 3 soft-assigned guides (a strand
    in clusters of several guides, as on Celia): the same SQP iterations every step, positions
    and sliding parameters within 1e-9 x hair length, and the Krylov path did the solves."""
    runs = {}
    for mode in ("exact", "krylov"):
        scene, _, sim = build_tracked(soft_cfg(**{"tracking.schur": mode, "tracking.krylov_tol": 1e-12}))
        state, out = sim.initial_state(), []
        for _ in range(10):
            state, info = sim.step(state, DT)
            assert info.converged
            out.append((state, info.iterations))
        runs[mode] = (out, sim.controller)
    (a, ca), (b, cb) = runs["exact"], runs["krylov"]
    L = ca.hair_length
    assert [i for _, i in a] == [i for _, i in b]
    assert max(np.abs(sa.x - sb.x).max() for (sa, _), (sb, _) in zip(a, b)) <= 1e-9 * L
    assert max(np.abs(sa.control.t - sb.control.t).max() for (sa, _), (sb, _) in zip(a, b)) <= 1e-9 * L
    st = cb.kkt.stats
    assert st["krylov_solves"] > st["krylov_fallbacks"] and st["builds"] < st["factors"]
    assert ca.kkt.stats["builds"] == ca.kkt.stats["factors"]


def test_default_krylov_tolerance_is_an_inexact_newton_step_to_the_same_solutions():
    """The default tracking.krylov_tol (1e-6: each KKT solve inexact, the SQP's convergence test on
    the true residuals) against the direct solves' 1e-12, 10 soft goaling steps: the same SQP
    iterations, every step converged with its constraints met, the positions within 1e-7 of the
    hair length (measured 1.7e-9), and fewer GMRES iterations a solve (measured 26 against 39)."""
    from hairexp.control.tracking.kkt import KRYLOV_TOL

    assert KRYLOV_TOL == 1e-6
    runs = {}
    for tol in (1e-12, None):
        _, _, sim = build_tracked(soft_cfg(**({} if tol is None else {"tracking.krylov_tol": tol})))
        assert sim.controller.kkt.krylov_tol == (tol or KRYLOV_TOL)
        state, out = sim.initial_state(), []
        for _ in range(10):
            state, info = sim.step(state, DT)
            assert info.converged
            m = sim.controller.measure(sim.free_dofs(state.x), state.time, state.control)
            assert m["residual_rel_max"] <= 1e-9
            out.append((state, info.iterations))
        runs[tol] = (out, sim.controller)
    (a, ca), (b, cb) = runs[1e-12], runs[None]
    L = ca.hair_length
    assert [i for _, i in a] == [i for _, i in b]
    assert max(np.abs(sa.x - sb.x).max() for (sa, _), (sb, _) in zip(a, b)) <= 1e-7 * L
    per = {k: c.kkt.stats["krylov_iterations"] / c.kkt.stats["krylov_solves"] for k, c in (("tight", ca), ("default", cb))}
    assert cb.kkt.stats["krylov_solves"] > 0 and per["default"] < per["tight"]


# -- run folder and recording -----------------------------------------------------------------
def test_soft_cli_run_writes_shares_and_a_recording(tmp_path):
    """A soft tracked run from the command line: result.npz has cluster_weights (V, K) whose
    clustered rows sum to one and whose argmax is cluster_of_vertex; the weighted centres meet
    their targets; the recording has the cluster entities."""
    import os
    import subprocess
    import sys

    frames, S, n = 3, 6, 8
    args = ["experiment=goaling", "variants=[]", "controller=tracking", "tracking.assignment=soft", f"frames={frames}",
            f"scene.n_strands={S}", f"scene.n_vertices={n}", f"hydra.run.dir={tmp_path}"]
    proc = subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=tmp_path, env=dict(os.environ, CI="1"),
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr
    with np.load(tmp_path / "result.npz") as r:
        W, cov = r["cluster_weights"], r["cluster_of_vertex"]
        assert W.shape == (S * n, int(cov.max()) + 1)
        on = cov >= 0
        np.testing.assert_allclose(W[on].sum(1), 1.0, rtol=0, atol=1e-14)
        assert (W[~on] == 0).all() and (np.argmax(W[on], 1) == cov[on]).all()
        assert ((W > 0).sum(1) > 1).any()
        np.testing.assert_allclose(r["com"], r["targets"], rtol=0, atol=1e-8 * 0.3)
    import json

    coh = json.loads((tmp_path / "summary.json").read_text())["cohesion"]    # every run: cohesion
    with np.load(tmp_path / "result.npz") as r:   # its per-frame series are in result.npz, not the summary
        clumps, gap = r["cohesion_clumps"], r["cohesion_widest_gap"]
    assert "clumps" not in coh and "widest_gap" not in coh
    assert coh["frames"] == frames + 1 == len(clumps) == len(gap)
    assert coh["clumps_max"] == clumps.max() >= 1 and coh["widest_gap_max"] == gap.max() > 0
    assert coh["clumps_last"] == clumps[-1] and coh["widest_gap_last"] == gap[-1] and coh["threshold"] == 0.03
    from rerun.chunk import RrdReader

    paths = {str(c.entity_path) for c in RrdReader(str(tmp_path / "recording.rrd")).stream()}
    for e in ("/world/clusters", "/world/com", "/world/targets", "/world/target_curves"):
        assert e in paths, e


def test_a_skinned_fan_meets_the_blended_targets(monkeypatch):
    """Each guide translated by its own vector d_g (transported frames unchanged), the hair moved
    as its shares' blend, x_i + sum_g s_ig d_g: the weighted centres meet the blended targets
    (sum_g beta_kg d_g) to round-off.  One target per cluster on its own guide would miss them."""
    scene, guides, sim = build_tracked(soft_cfg(**{"tracking.blend_width": 0.02}))
    tr = sim.controller
    cons = tr.cons
    assert cons.soft and (cons.beta > 0).sum(1).max() > 1
    G = guides.n_guides
    d = np.array([[0.05, 0.0, 0.02], [-0.04, 0.01, 0.0], [0.0, -0.02, -0.05]])[:G]
    rest = guides.rest.copy()
    moved = np.concatenate([P + d[g] for g, P in enumerate(guides.guides(rest))])
    monkeypatch.setattr(cons.guides, "shape_at", lambda t, motion=None: moved)
    free = ~scene.strands.kinematic
    gw = tr.corr.guide_weights[scene.strands.strand_of_vertex[free]]      # (n_free, G)
    x = scene.initial_positions()[free] + gw @ d
    C = cons.residual(x.reshape(-1), cons.targets(0.0), cons.t_rest)
    assert np.abs(C).max() <= 1e-13
    own = cons.beta.argmax(1)
    miss = cons.com(x.reshape(-1)) - (cons.com(sim.free_dofs(sim.initial_state().x)) + d[own])
    assert np.abs(miss).max() > 1e-3                                     # the own-guide target would not do
