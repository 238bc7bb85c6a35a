"""Geometry of the tracking solver (paper 3.1-3.2): arc-length Catmull-Rom splines, parallel-
transported frames, coarse-to-fine correspondence (eq. 1, tracking points, clusters) and the
centre-of-mass constraints (eqs. 2-3) with their Jacobians against finite differences."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from derivcheck import GRAD_RTOL, HESS_RTOL
from helpers import bent_polyline
from tracking_helpers import build_tracked, free_vertex_com, straight, tracked_cfg, tracking_cfg
from hairexp.control.tracking.controller import TrackingController
from hairexp.errors import InputError
from hairexp.physics.simulator import Simulator
from hairexp.app.builders import build_scene
from hairexp.guides import spline
from hairexp.control.tracking.correspondence import build_correspondence
from hairexp.guides.frames import parallel_transport, parallel_transport_batch, transport, vertex_tangents
from hairexp.guides.animation import GuideAnimation

EPS = np.finfo(np.float64).eps


# ---------------------------------------------------------------------------------------------
# Splines (3.2 "Dynamic Constraint Targets")
# ---------------------------------------------------------------------------------------------

def curves(K=3, n=7, seed=0):
    """K random curves sharing non-uniform knots s (n,): control points (K, n, 3) tensors."""
    rng = np.random.default_rng(seed)
    s = np.concatenate([[0.0], np.cumsum(rng.uniform(0.02, 0.08, n - 1))])
    P = np.stack([bent_polyline(n, seed + 10 + k, edge=0.05, max_turn=0.8) for k in range(K)])
    return torch.as_tensor(P), torch.as_tensor(s)


def ev(P, s, t):
    return spline.evaluate(P, s, torch.as_tensor(np.asarray(t, dtype=np.float64))).numpy()


def ders(P, s, t):
    return tuple(a.numpy() for a in spline.eval_with_derivatives(P, s, torch.as_tensor(np.asarray(t, dtype=np.float64))))


def test_spline_interpolates_control_points_at_knots():
    P, s = curves()
    K, n = P.shape[:2]
    for i in range(n):
        c = ev(P, s, np.full(K, float(s[i])))
        np.testing.assert_allclose(c, P[:, i].numpy(), rtol=0, atol=1e-14)
        c2 = ders(P, s, np.full(K, float(s[i])))[0]
        np.testing.assert_allclose(c2, P[:, i].numpy(), rtol=0, atol=1e-14)


def test_spline_tangents_at_knots_are_catmull_rom():
    """m_i = (P_{i+1} - P_{i-1}) / (s_{i+1} - s_{i-1}), one-sided at the ends."""
    P, s = curves()
    Pn, sn = P.numpy(), s.numpy()
    K, n = Pn.shape[:2]
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        m = (Pn[:, b] - Pn[:, a]) / (sn[b] - sn[a])
        np.testing.assert_allclose(ders(P, s, np.full(K, sn[i]))[1], m, rtol=0, atol=1e-12 * np.abs(m).max())


def test_spline_is_C1_at_interior_knots():
    """Left and right first derivatives agree at every interior knot: closed form evaluated just
    either side, and one-sided differences of ``evaluate`` (error <= h/2 max |c''|)."""
    P, s = curves()
    K, n = P.shape[:2]
    sn = s.numpy()
    L = sn[-1]
    d2max = max(np.abs(ders(P, s, np.full(K, t))[2]).max() for t in np.linspace(0, L, 200))
    for i in range(1, n - 1):
        e = 1e-12 * L
        left = ders(P, s, np.full(K, sn[i] - e))[1]
        right = ders(P, s, np.full(K, sn[i] + e))[1]
        np.testing.assert_allclose(left, right, rtol=0, atol=4 * e * d2max + 1e-12 * np.abs(left).max())
        h = 1e-6 * L
        c0 = ev(P, s, np.full(K, sn[i]))
        fd_left = (c0 - ev(P, s, np.full(K, sn[i] - h))) / h
        fd_right = (ev(P, s, np.full(K, sn[i] + h)) - c0) / h
        tol = h * d2max + 8 * EPS * np.abs(c0).max() / h
        np.testing.assert_allclose(fd_left, fd_right, rtol=0, atol=2 * tol)
        np.testing.assert_allclose(fd_left, right, rtol=0, atol=tol)


def test_spline_parameter_is_rest_arc_length_on_straight_polyline():
    """Collinear control points with non-uniform spacing, knots from ``rest_arclength``: the
    curve runs along the line at unit speed, |c(t) - c(0)| = t for t in [0, L]."""
    rng = np.random.default_rng(3)
    gaps = rng.uniform(0.01, 0.1, 9)
    assert gaps.max() / gaps.min() > 3  # really non-uniform
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    root = rng.normal(size=3) * 0.1
    Pn = root + np.concatenate([[0.0], np.cumsum(gaps)])[:, None] * d
    s = spline.rest_arclength(Pn)
    np.testing.assert_allclose(s.numpy(), np.concatenate([[0.0], np.cumsum(gaps)]), rtol=0, atol=1e-15)
    L = float(s[-1])
    t = np.linspace(0.0, L, 501)
    P = torch.as_tensor(np.repeat(Pn[None], len(t), 0))
    c = ev(P, s, t)
    np.testing.assert_allclose(np.linalg.norm(c - c[0], axis=1), t, rtol=0, atol=1e-12)
    np.testing.assert_allclose((c - root) @ d, t, rtol=0, atol=1e-12)       # on the line, in order
    _, d1, _ = ders(P, s, t)
    np.testing.assert_allclose(np.linalg.norm(d1, axis=1), 1.0, rtol=0, atol=1e-12)  # unit speed


def test_spline_derivatives_match_finite_differences():
    """c' and c'' of ``eval_with_derivatives`` against central differences of ``evaluate`` at
    points away from the knots (c'' jumps there), including the extrapolated ends."""
    P, s = curves(K=4, n=8, seed=5)
    sn = s.numpy()
    K = P.shape[0]
    L = sn[-1]
    h = 1e-5 * L
    rng = np.random.default_rng(1)
    ts = []
    for a, b in zip(sn[:-1], sn[1:]):
        ts += list(rng.uniform(a + 5 * h, b - 5 * h, 2)) + [0.5 * (a + b)]
    ts += [-0.2 * L, 1.3 * L]
    for t in ts:
        tt = np.full(K, t)
        c, d1, d2 = ders(P, s, tt)
        np.testing.assert_allclose(c, ev(P, s, tt), rtol=0, atol=1e-15)
        fd1 = (ev(P, s, tt + h) - ev(P, s, tt - h)) / (2 * h)
        fd2 = (ev(P, s, tt + h) - 2 * c + ev(P, s, tt - h)) / h ** 2
        scale1 = np.abs(fd1).max()
        np.testing.assert_allclose(d1, fd1, rtol=0, atol=GRAD_RTOL * scale1)
        # the second difference of a cubic is exact up to round-off ~ 4 eps |c| / h^2
        np.testing.assert_allclose(d2, fd2, rtol=0, atol=HESS_RTOL * np.abs(d2).max() + 4 * EPS * np.abs(c).max() / h ** 2)


def test_spline_extrapolates_linearly_beyond_the_ends():
    P, s = curves(seed=9)
    K = P.shape[0]
    L = float(s[-1])
    cL, dL, _ = ders(P, s, np.full(K, L))
    c0, d0, _ = ders(P, s, np.full(K, 0.0))
    for h in (1e-3 * L, 0.1 * L, 0.7 * L):
        np.testing.assert_allclose(ev(P, s, np.full(K, L + h)), cL + h * dL, rtol=0, atol=1e-13)
        np.testing.assert_allclose(ev(P, s, np.full(K, -h)), c0 - h * d0, rtol=0, atol=1e-13)
        c, d1, d2 = ders(P, s, np.full(K, L + h))
        np.testing.assert_allclose(d1, dL, rtol=0, atol=1e-13)
        np.testing.assert_allclose(d2, 0.0, rtol=0, atol=0)
    # the end tangent is also the inside limit (C1 across the ends)
    e = 1e-7 * L
    fd = (cL - ev(P, s, np.full(K, L - e))) / e
    d2max = np.abs(ders(P, s, np.full(K, L - e))[2]).max()
    np.testing.assert_allclose(fd, dL, rtol=0, atol=e * d2max + 8 * EPS * np.abs(cL).max() / e)


# ---------------------------------------------------------------------------------------------
# Parallel-transported frames (3.2 "Updating Offsets")
# ---------------------------------------------------------------------------------------------

def check_frames(P, T, N, B, n0):
    tol = 1e-12
    Tn = np.diff(P, axis=0)
    # vertex tangents: central differences, one-sided at the ends, normalised
    Tref = np.concatenate([Tn[:1], P[2:] - P[:-2], Tn[-1:]])
    Tref /= np.linalg.norm(Tref, axis=1, keepdims=True)
    np.testing.assert_allclose(T, Tref, rtol=0, atol=tol)
    for V in (T, N, B):
        np.testing.assert_allclose(np.linalg.norm(V, axis=1), 1.0, rtol=0, atol=tol)
    for U, V in ((T, N), (T, B), (N, B)):
        np.testing.assert_allclose(np.sum(U * V, axis=1), 0.0, rtol=0, atol=tol)
    np.testing.assert_allclose(np.linalg.det(np.stack([T, N, B], axis=-1)), 1.0, rtol=0, atol=tol)  # right-handed
    n = n0 - np.dot(n0, T[0]) * T[0]
    np.testing.assert_allclose(N[0], n / np.linalg.norm(n), rtol=0, atol=tol)


def rodrigues_transport(v, t0, t1):
    """Independent reference: rotate v by the smallest rotation taking t0 to t1 (scipy)."""
    axis = np.cross(t0, t1)
    sn = np.linalg.norm(axis)
    if sn < 1e-15:
        return v.copy()
    ang = np.arctan2(sn, np.dot(t0, t1))
    return Rotation.from_rotvec(axis / sn * ang).apply(v)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frames_orthonormal_right_handed_along_vertex_tangents(seed):
    P = bent_polyline(12, seed, edge=0.03, max_turn=0.9)
    n0 = np.random.default_rng(seed).normal(size=3)
    T, N, B = parallel_transport(P, n0)
    check_frames(P, T, N, B, n0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frames_are_twist_free(seed):
    """N_{i+1} is N_i parallel-transported from T_i to T_{i+1}: no rotation about the tangent."""
    P = bent_polyline(12, seed, edge=0.03, max_turn=0.9)
    T, N, B = parallel_transport(P, np.random.default_rng(seed + 5).normal(size=3))
    for i in range(len(P) - 1):
        ref = rodrigues_transport(N[i], T[i], T[i + 1])
        np.testing.assert_allclose(N[i + 1], ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(transport(N[i], T[i], T[i + 1]), ref, rtol=0, atol=1e-12)
        twist = np.arctan2(np.dot(np.cross(ref, N[i + 1]), T[i + 1]), np.dot(ref, N[i + 1]))
        assert abs(twist) < 1e-12


def test_frames_of_planar_curve_keep_the_plane_normal():
    """A planar curve: with n0 the plane normal every N is that normal (B in the plane); with n0
    in the plane N stays in the plane.  A twisting frame would leave the plane."""
    rng = np.random.default_rng(4)
    ang = np.cumsum(rng.uniform(-0.8, 0.8, 11))
    e = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1) * rng.uniform(0.01, 0.03, (11, 1))
    P2 = np.concatenate([np.zeros((1, 3)), np.cumsum(e, 0)])
    R = Rotation.from_rotvec([0.3, -0.7, 0.2]).as_matrix()
    P = P2 @ R.T
    z = R @ [0, 0, 1.0]
    T, N, B = parallel_transport(P, z)
    np.testing.assert_allclose(N, np.repeat(z[None], len(P), 0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(B @ z, 0.0, rtol=0, atol=1e-12)
    T, N, B = parallel_transport(P, np.cross(z, P[1] - P[0]))  # n0 in the plane
    np.testing.assert_allclose(N @ z, 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.abs(B @ z), 1.0, rtol=0, atol=1e-12)


def test_frames_rotate_with_a_rigid_rotation():
    P = bent_polyline(10, 7, edge=0.03)
    n0 = np.array([0.3, -0.2, 0.9])
    R = Rotation.from_rotvec([1.1, -0.4, 2.0]).as_matrix()
    shift = np.array([0.5, -1.0, 2.0])
    T, N, B = parallel_transport(P, n0)
    T2, N2, B2 = parallel_transport(P @ R.T + shift, R @ n0)
    for U, V in ((T, T2), (N, N2), (B, B2)):
        np.testing.assert_allclose(V, U @ R.T, rtol=0, atol=1e-12)


def test_frames_of_straight_guide_are_constant():
    P = straight([0.1, 0.2, 0.3], [1.0, -2.0, 0.5], 0.3, 9)
    T, N, B = parallel_transport(P, np.array([0.0, 0.0, 1.0]))
    for V in (T, N, B):
        np.testing.assert_allclose(V, np.repeat(V[:1], len(P), 0), rtol=0, atol=1e-14)


def test_batched_frames_equal_single_frames():
    Ps = np.stack([bent_polyline(9, s, edge=0.03) for s in range(3)])
    n0 = np.random.default_rng(0).normal(size=(3, 3))
    Tb, Nb, Bb = parallel_transport_batch(Ps, n0)
    for g in range(3):
        T, N, B = parallel_transport(Ps[g], n0[g])
        for U, V in ((T, Tb[g]), (N, Nb[g]), (B, Bb[g])):
            np.testing.assert_allclose(V, U, rtol=0, atol=1e-14)
    np.testing.assert_allclose(vertex_tangents(Ps[0]), Tb[0], rtol=0, atol=1e-15)


@pytest.mark.parametrize("shape", [(3, 10), (1, 2), (4, 3), (2, 31)])
def test_compiled_frames_equal_numpy_frames_bit_for_bit(shape):
    """The tracking targets' compiled transport (``constraints.transport_frames``) performs
    ``parallel_transport_batch``'s operations in its order: the same bits, on guides of 2 to 31
    vertices; and ``BodyCarriedFrames.frames_all`` with it equals each guide framed on its own
    (the root normal carried by the body and turned onto the root tangent, guide by guide)."""
    from hairexp.control.tracking.constraints import transport_frames
    from hairexp.guides.frames import BodyCarriedFrames

    G, n = shape
    rng = np.random.default_rng(G * 100 + n)
    Ps = np.stack([bent_polyline(n, int(rng.integers(1000)), edge=0.03, max_turn=1.2) for _ in range(G)])
    n0 = rng.normal(size=(G, 3))
    for U, V in zip(parallel_transport_batch(Ps, n0), transport_frames(Ps, n0)):
        assert np.array_equal(U, V)
    rest = [bent_polyline(n, s, edge=0.03) for s in range(G)]
    bf = BodyCarriedFrames(rest, Rotation.from_rotvec([0.1, -0.4, 0.2]).as_matrix())
    R = Rotation.from_rotvec([0.7, 0.2, -0.3]).as_matrix()
    cur = [P + 0.01 * rng.normal(size=P.shape) for P in rest]
    got = bf.frames_all(cur, R, batch=transport_frames)
    for g, P in enumerate(cur):
        n_root = transport(R @ bf.n_body[g], R @ bf.t_body[g], vertex_tangents(P)[0])
        for U, V in zip(parallel_transport_batch(P[None], n_root[None]), got[g]):
            assert np.array_equal(U[0], V)


def test_numpy_target_tangents_equal_the_spline_module():
    """The targets' numpy Catmull-Rom tangents (``TrackingConstraints.targets`` hands them to the
    compiled curve evaluation) equal ``spline.tangents`` (torch) bit for bit."""
    from hairexp.control.tracking.constraints import _tangents_numpy

    for n in (2, 3, 7):
        P, s = curves(K=4, n=n, seed=n)
        assert np.array_equal(_tangents_numpy(P.numpy(), s.numpy()), spline.tangents(P, s).numpy())


# ---------------------------------------------------------------------------------------------
# Correspondence (3.1)
# ---------------------------------------------------------------------------------------------

def free_mask(polylines):
    return np.concatenate([np.arange(len(p)) >= 2 for p in polylines])  # two root vertices per strand


def offsets_of(polylines):
    return np.concatenate([[0], np.cumsum([len(p) for p in polylines])])


def brute_prox_distance(strand, guide, samples=20001):
    """Eq. (1) by brute force: sum over vertices of the squared distance to the closest of many
    points sampled along the guide polyline."""
    seg = np.linalg.norm(np.diff(guide, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    u = np.linspace(0, s[-1], samples)
    G = np.stack([np.interp(u, s, guide[:, c]) for c in range(3)], 1)
    d2 = ((strand[:, None] - G[None]) ** 2).sum(-1).min(1)
    return float(d2.sum())


GUIDE_A = straight([0.0, 0.0, 0.0], [0, -1, 0], 0.3, 8)
GUIDE_B = straight([0.1, 0.0, 0.0], [0, -1, 0], 0.3, 8)


def two_guide_strands():
    """Three strands near guide A, three near guide B (straight, 10 vertices)."""
    near_a = [straight([dx, 0, dz], [0.02 * dx, -1, 0], 0.3, 10) for dx, dz in ((0.01, 0), (-0.01, 0.005), (0, -0.01))]
    near_b = [straight([0.1 + dx, 0, dz], [0, -1, 0.02], 0.3, 10) for dx, dz in ((0.01, 0), (-0.012, 0.005), (0, 0.01))]
    return near_a, near_b


def test_strands_near_a_guide_are_assigned_to_it():
    near_a, near_b = two_guide_strands()
    strands = near_a + near_b
    corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands), [GUIDE_A, GUIDE_B], 4)
    assert corr.guide_of_strand.tolist() == [0, 0, 0, 1, 1, 1]


def test_integrated_squared_distance_decides_assignment():
    """Eq. (1) is an integrated *squared* distance.  The test strand lies on guide B for 7 of its
    10 vertices and 0.2 m from it (0.1 m from A) for the other 3: every vertex is 0.1 m from A.
    Squared sums: A 10 x 0.01 = 0.10 < B 3 x 0.04 = 0.12, so eq. (1) picks A, while the root's
    nearest guide, the majority of vertices and the unsquared sum (1.0 vs 0.6) all pick B."""
    ys = -np.linspace(0.0, 0.27, 10)
    xs = np.array([0.1] * 7 + [-0.1] * 3)
    tricky = np.stack([xs, ys, np.zeros(10)], 1)
    near_a, near_b = two_guide_strands()
    strands = [tricky] + near_a + near_b
    d = [brute_prox_distance(tricky, g) for g in (GUIDE_A, GUIDE_B)]
    np.testing.assert_allclose(d, [0.10, 0.12], rtol=1e-6)
    corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands), [GUIDE_A, GUIDE_B], 4)
    assert corr.guide_of_strand[0] == 0
    assert corr.guide_of_strand[1:].tolist() == [0, 0, 0, 1, 1, 1]
    # swap which guide is closer in the squared sum by moving the far vertices: now B wins
    tricky2 = tricky.copy()
    tricky2[7:, 0] = -0.05  # A: 7 x 0.01 + 3 x 0.0025 = 0.0775; B: 3 x 0.0225 = 0.0675
    strands2 = [tricky2] + near_a + near_b
    corr2 = build_correspondence(np.concatenate(strands2), offsets_of(strands2), free_mask(strands2),
                                 [GUIDE_A, GUIDE_B], 4)
    assert corr2.guide_of_strand[0] == int(np.argmin([brute_prox_distance(tricky2, g) for g in (GUIDE_A, GUIDE_B)])) == 1


def test_assignment_matches_brute_force_eq1_on_random_curved_hair():
    guides = [bent_polyline(9, 20 + g, edge=0.04, max_turn=0.4) for g in range(3)]
    rng = np.random.default_rng(0)
    strands = []
    for j in range(12):
        g = guides[j % 3]
        strands.append(g[:8] + rng.normal(scale=0.03, size=(8, 3)) + 0.01 * np.arange(8)[:, None] * rng.normal(size=3))
    corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands), guides, 5)
    expect = [int(np.argmin([brute_prox_distance(s, g) for g in guides])) for s in strands]
    assert corr.guide_of_strand.tolist() == expect


def test_tracking_points_are_equidistant_in_arc_length():
    guide = bent_polyline(11, 3, edge=0.04, max_turn=0.8)
    strands = [guide[:9] + [0.005, 0, 0], guide[:9] + [0, 0.006, 0]]
    P = 6
    corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands), [guide], P,
                                placement="arc_length")
    seg = np.linalg.norm(np.diff(guide, axis=0), axis=1)
    L = seg.sum()
    s = corr.tracking_arclength[0]
    np.testing.assert_allclose(s, (np.arange(P) + 0.5) * L / P, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.diff(s), L / P, rtol=0, atol=1e-14)
    # each point lies on the guide at its arc length (walk the segments)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    for k in range(P):
        j = int(np.searchsorted(cum, s[k]) - 1)
        u = (s[k] - cum[j]) / seg[j]
        np.testing.assert_allclose(corr.tracking_points[0, k], guide[j] + u * (guide[j + 1] - guide[j]), rtol=0, atol=1e-14)


def test_free_vertices_join_the_cluster_of_their_nearest_tracking_point():
    near_a, near_b = two_guide_strands()
    strands = near_a + near_b
    X = np.concatenate(strands)
    free = free_mask(strands)
    corr = build_correspondence(X, offsets_of(strands), free, [GUIDE_A, GUIDE_B], 4)
    cov = corr.cluster_of_vertex
    strand_of = np.repeat(np.arange(len(strands)), [len(p) for p in strands])
    assert np.all(cov[~free] == -1)           # root vertices are in no cluster
    assert np.all(cov[free] >= 0)
    K = corr.n_clusters
    assert sorted(set(cov[free].tolist())) == list(range(K))
    pairs = list(zip(corr.cluster_guide.tolist(), corr.cluster_point.tolist()))
    assert len(set(pairs)) == K
    for v in np.flatnonzero(free):
        g = corr.guide_of_strand[strand_of[v]]
        p = int(np.argmin(np.linalg.norm(corr.tracking_points[g] - X[v], axis=1)))
        assert (corr.cluster_guide[cov[v]], corr.cluster_point[cov[v]]) == (g, p), v


def long_guide_over_short_hair(caplog, **kw):
    """Guide 0 with hair as long as it; guide 1 is 1 m long over two 0.3 m strands: (strands,
    correspondence with 4 points per guide), warnings captured in ``caplog``."""
    near_a, _ = two_guide_strands()
    long_b = straight([0.1, 0.0, 0.0], [0, -1, 0], 1.0, 8)
    near_b = [straight([0.1 + dx, 0, 0], [0, -1, 0], 0.3, 10) for dx in (0.01, -0.01)]
    strands = near_a + near_b
    with caplog.at_level(logging.WARNING, logger="hairexp.control.tracking.correspondence"):
        corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands),
                                    [GUIDE_A, long_b], 4, **kw)
    return strands, corr


def test_empty_cluster_is_dropped_with_a_warning_naming_it(caplog):
    """Guide 1 is 1 m long but its strands only 0.3 m: with the paper's equidistant points its
    tracking points 2 and 3 (at 0.625 and 0.875 m) have no vertex and are dropped; guide 0's
    clusters all stay."""
    strands, corr = long_guide_over_short_hair(caplog, placement="arc_length")
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(msgs) == 1, msgs   # one line for all the empty clusters
    assert re.search(r"\b2 of 8 clusters are empty\b", msgs[0]), msgs[0]
    assert "guide 1 point 2, guide 1 point 3" in msgs[0], msgs[0]
    pairs = list(zip(corr.cluster_guide.tolist(), corr.cluster_point.tolist()))
    assert pairs == [(0, 0), (0, 1), (0, 2), (0, 3), (1, 0), (1, 1)]
    assert set(corr.cluster_of_vertex[free_mask(strands)].tolist()) == set(range(6))


def test_hair_mass_points_leave_no_cluster_empty(caplog):
    """The same 1 m guide over 0.3 m strands with the default placement (hair_mass): its points
    sit at the quantiles of the hair mass projected onto it, every cluster keeps hair, no
    warning; the points of guide 0 (hair as long as the guide, 9 free vertices a strand) split
    its hair mass into near-equal parts."""
    strands, corr = long_guide_over_short_hair(caplog)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
    assert corr.n_clusters == 8
    assert corr.tracking_arclength[1].max() < 0.3        # all on the hair's 0.3 m of the 1 m guide
    counts = np.bincount(corr.cluster_of_vertex[corr.cluster_of_vertex >= 0], minlength=8)
    assert counts.min() > 0


@pytest.mark.parametrize("n_vertices,points", [(10, 8), (10, 6), (8, 6), (20, 8), (12, 8)])
def test_hair_mass_points_against_equidistant_on_a_hanging_wisp(n_vertices, points):
    """Strands as long as their guide with n - 2 free vertices each: the hair-mass points give
    every point a cluster whenever there are at least as many free heights as points, and
    cluster masses within one vertex level of equal; the paper's equidistant points leave point 0
    empty when the first free vertex is farther from the root than the first point's interval."""
    rng = np.random.default_rng(n_vertices + points)
    guide = straight([0.0, 0, 0], [0, -1, 0], 0.3, 8)
    strands = [straight([rng.uniform(-0.01, 0.01), 0, rng.uniform(-0.01, 0.01)], [0, -1, 0], 0.3, n_vertices)
               for _ in range(10)]
    X, off, free = np.concatenate(strands), offsets_of(strands), free_mask(strands)
    mass = build_correspondence(X, off, free, [guide], points)
    counts = np.bincount(mass.cluster_of_vertex[free], minlength=points)
    assert mass.n_clusters == points and counts.min() > 0
    assert counts.max() - counts.min() <= 10 * 1 + 0      # at most one height level (10 strands) apart
    equi = build_correspondence(X, off, free, [guide], points, placement="arc_length")
    first_free, first_point = 2 * 0.3 / (n_vertices - 1), 0.3 / points
    if first_free > first_point:
        assert equi.n_clusters < points                  # the paper's placement drops point 0


def test_too_many_points_for_the_hair_still_warn(caplog):
    """Strands of 4 vertices (3 free heights) and 6 points: some cluster is really empty."""
    strands = [straight([dx, 0, 0], [0, -1, 0], 0.3, 4) for dx in (0.0, 0.01, -0.01)]
    with caplog.at_level(logging.WARNING, logger="hairexp.control.tracking.correspondence"):
        corr = build_correspondence(np.concatenate(strands), offsets_of(strands), free_mask(strands),
                                    [straight([0.0, 0, 0], [0, -1, 0], 0.3, 8)], 6)
    assert corr.n_clusters <= 3
    empty = [r.getMessage() for r in caplog.records if "empty" in r.getMessage()]
    assert len(empty) == 1, empty   # one line, counting them
    assert f"{6 - corr.n_clusters} of 6 clusters are empty" in empty[0], empty


def test_no_guides_is_an_input_error():
    near_a, _ = two_guide_strands()
    with pytest.raises(InputError, match="guide"):
        build_correspondence(np.concatenate(near_a), offsets_of(near_a), free_mask(near_a), [], 4)


# ---------------------------------------------------------------------------------------------
# Constraints (3.2, eqs. 2-3)
# ---------------------------------------------------------------------------------------------

def curved_guides_animation(n_frames=3):
    """Two curved guides of different vertex counts (8 and 6) rooted near the wisp, bending more
    and shrinking over the frames."""
    def guide(root, n, bend, scale):
        s = np.linspace(0.0, 0.3 * scale, n)
        return np.asarray(root) + np.stack([bend * s ** 2 / 0.3, -s, 0.3 * bend * s ** 2 / 0.3], 1)
    frames = [np.concatenate([guide([-0.005, 0, 0], 8, 0.3 + 0.4 * f, 1 - 0.1 * f),
                              guide([0.006, 0, 0.004], 6, -0.2 - 0.3 * f, 1 - 0.05 * f)]) for f in range(n_frames)]
    return GuideAnimation(np.stack(frames), [0, 8, 14], 25.0)


def curved_tracked(sliding=True, points=5, motion=None):
    """A straight wisp (12 x 10) tracking two curved, deforming guides."""
    cfg = tracked_cfg({"scene.n_strands": 12, "scene.n_vertices": 10, "scene.gravity": [0.0, 0.0, 0.0]})
    if motion:
        for k, v in motion.items():
            cfg.scene.motion[k] = v
    scene = build_scene(cfg.scene)
    g = curved_guides_animation()
    if motion:  # carry the guides with the body like build_guides does
        pos = np.stack([scene.motion.transform(g.positions[f], f / g.fps) for f in range(g.n_frames)])
        g = GuideAnimation(pos, g.offsets, g.fps)
    tcfg = tracking_cfg(points_per_guide=points, targets="sliding" if sliding else "static")
    sim = Simulator(scene, cfg.solver, TrackingController(scene, g, tcfg))
    return scene, g, sim


def straight_tracked(**kw):
    cfg = tracked_cfg({"scene.n_strands": 12, "scene.n_vertices": 10, "guides.count": 2,
                       "guides.source": "scaled", "guides.scale_times": [0.0, 1.0],
                       "guides.scale_factors": [1.0, 0.7], **kw})
    return build_tracked(cfg)


def test_com_is_eq2_and_A_is_its_jacobian():
    scene, _, sim = straight_tracked()
    cons = sim.controller.cons
    rng = np.random.default_rng(0)
    x = scene.strands.rest + rng.normal(scale=0.01, size=scene.strands.rest.shape)
    xf = sim.free_dofs(x)
    np.testing.assert_allclose(cons.com(xf), free_vertex_com(sim, x), rtol=0, atol=1e-15)
    N = xf.size
    h = 1e-6
    J = np.empty((3 * cons.K, N))
    for j in range(N):
        e = np.zeros(N)
        e[j] = h
        J[:, j] = (cons.com(xf + e) - cons.com(xf - e)).reshape(-1) / (2 * h)
    np.testing.assert_allclose(cons.A.toarray(), J, rtol=0, atol=1e-9)
    # each row of A sums to one: the weights m_i / M_k of a centre of mass
    np.testing.assert_allclose(np.asarray(cons.A.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-14)


@pytest.mark.parametrize("case", ["straight_shrinking", "curved_deforming"])
def test_dC_dt_is_minus_target_tangent(case):
    """dC/dt = -c_hat'(t) and c_hat'' against central differences of ``target_points`` in t, at
    a time the guides are deformed (between frames for the curved case)."""
    if case == "straight_shrinking":
        _, _, sim = straight_tracked()
        t_now = 0.52
    else:
        _, _, sim = curved_tracked()
        t_now = 0.05  # between frames 1 and 2
    cons = sim.controller.cons
    tg = cons.targets(t_now)
    rng = np.random.default_rng(2)
    tk = cons.t_rest * rng.uniform(0.8, 1.3, cons.K) + 1e-3
    xf = sim.free_dofs(sim.scene.strands.rest)
    c, d1, d2 = cons.target_points(tg, tk, derivatives=True)
    np.testing.assert_allclose(c, cons.target_points(tg, tk), rtol=0, atol=1e-15)
    h = 1e-6
    fd_C, fd_c1, fd_c2 = np.zeros((cons.K, 3)), np.zeros((cons.K, 3)), np.zeros((cons.K, 3))
    for k in range(cons.K):
        e = np.zeros(cons.K)
        e[k] = h
        fd_C[k] = (cons.residual(xf, tg, tk + e)[k] - cons.residual(xf, tg, tk - e)[k]) / (2 * h)
        cp, cm = cons.target_points(tg, tk + e)[k], cons.target_points(tg, tk - e)[k]
        fd_c1[k] = (cp - cm) / (2 * h)
        fd_c2[k] = (cp - 2 * c[k] + cm) / h ** 2
    np.testing.assert_allclose(-d1, fd_C, rtol=0, atol=GRAD_RTOL * np.abs(d1).max())
    np.testing.assert_allclose(d1, fd_c1, rtol=0, atol=GRAD_RTOL * np.abs(d1).max())
    np.testing.assert_allclose(d2, fd_c2, rtol=0, atol=HESS_RTOL * np.abs(d2).max() + 8 * EPS * np.abs(c).max() / h ** 2)
    # the other clusters' residuals do not depend on t_k: dC/dt is block diagonal
    e = np.zeros(cons.K)
    e[0] = 1e-3
    diff = cons.residual(xf, tg, tk + e) - cons.residual(xf, tg, tk)
    assert np.abs(diff[1:]).max() == 0.0 and np.abs(diff[0]).max() > 0


@pytest.mark.parametrize("case", ["straight", "curved", "curved_rotated_body"])
def test_rest_state_meets_the_constraints(case):
    """At t = 0 with t = t_rest the rest hair satisfies C = 0 (eq. 3) to round-off."""
    if case == "straight":
        scene, _, sim = straight_tracked()
    elif case == "curved":
        scene, _, sim = curved_tracked()
    else:
        scene, _, sim = curved_tracked(motion={"times": [0.0, 1.0], "translations": [[0.1, -0.2, 0.3], [0.2, 0, 0]],
                                               "rotations_deg": [[20.0, -35.0, 50.0], [0, 0, 0]]})
    cons = sim.controller.cons
    st = sim.initial_state()
    C = cons.residual(sim.free_dofs(st.x), cons.targets(0.0), st.control.t)
    assert np.abs(C).max() <= 1e-12
    np.testing.assert_array_equal(st.control.t, cons.t_rest)
    m = sim.controller.measure(sim.free_dofs(st.x), 0.0, st.control)
    assert m["residual_max"] <= 1e-12


def test_offsets_encode_angle_and_distance_from_a_straight_guide():
    """(theta, d) of 3.2: d is the distance of the rest centre of mass from the guide's centre
    line and the tangential part is zero (t_rest is the closest guide point)."""
    scene, guides, sim = straight_tracked()
    cons = sim.controller.cons
    com = cons.com(sim.free_dofs(scene.strands.rest))
    for k in range(cons.K):
        G = guides.guides(guides.rest)[cons.corr.cluster_guide[k]]
        d = (G[-1] - G[0]) / np.linalg.norm(G[-1] - G[0])
        r = com[k] - G[0]
        along = r @ d
        np.testing.assert_allclose(cons.t_rest[k], along, rtol=0, atol=1e-14)
        np.testing.assert_allclose(cons.offset_d[k], np.linalg.norm(r - along * d), rtol=0, atol=1e-14)
        np.testing.assert_allclose(cons.offset_local[k, 2], 0.0, rtol=0, atol=1e-14)
        a, b = cons.offset_local[k, :2]
        np.testing.assert_allclose([a, b], cons.offset_d[k] * np.array([np.cos(cons.offset_theta[k]),
                                                                         np.sin(cons.offset_theta[k])]), atol=1e-15)


def test_targets_follow_rigid_guide_motion():
    """Guides carried rigidly by the body: the target at t_rest is the body transform of the rest
    centre of mass, at any time (the frames follow the body's rotation, 3.2)."""
    motion = {"scene.motion.times": [0.0, 0.5, 1.0],
              "scene.motion.translations": [[0, 0, 0], [0.05, 0.02, -0.03], [0.1, -0.05, 0.02]],
              "scene.motion.rotations_deg": [[0, 0, 0], [30.0, 0, 45.0], [-20.0, 60.0, 90.0]]}
    cfg = tracked_cfg({"scene.n_strands": 12, "scene.n_vertices": 10, "guides.count": 3, **motion})
    scene, guides, sim = build_tracked(cfg)
    cons = sim.controller.cons
    com0 = cons.com(sim.free_dofs(scene.strands.rest))
    for t in (0.2, 0.48, 0.8, 1.0):
        R, T = scene.motion.pose(t)
        got = cons.target_points(cons.targets(t), cons.t_rest)
        np.testing.assert_allclose(got, com0 @ R.T + T, rtol=0, atol=1e-12)


def test_sliding_target_on_shrunk_straight_guide_is_at_scaled_parameter():
    """A straight guide scaled by f about its root: c_hat(t_rest / f) is the rest centre of mass
    (the target slides), while c_hat(t_rest) moved by (1 - f) t_rest towards the root."""
    scene, guides, sim = straight_tracked()
    cons = sim.controller.cons
    com0 = cons.com(sim.free_dofs(scene.strands.rest))
    for t, f in ((0.5, 0.85), (1.0, 0.7)):
        tg = cons.targets(t)
        np.testing.assert_allclose(cons.target_points(tg, cons.t_rest / f), com0, rtol=0, atol=1e-12)
        moved = np.linalg.norm(cons.target_points(tg, cons.t_rest) - com0, axis=1)
        np.testing.assert_allclose(moved, (1 - f) * cons.t_rest, rtol=0, atol=1e-12)
