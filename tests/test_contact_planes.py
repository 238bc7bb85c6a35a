"""The stage's contacts as penalty planes of a second solve (``collision.resolve``,
hairexp/physics/contact_planes.py): the one-sided quadratic penalty and its derivatives against torch
autograd and finite differences, the band assembly against a dense Hessian, the planes the stage's
output gives, and steps against moving colliders with the strain limiter off: nothing inside, the
edges next to a contact stretched far less than by the stage alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from helpers import run_steps, scene_cfg
from test_contact_barrier import SHAPES, collider_cfg, min_edge_gap

from hairexp.app.builders import build_scene
from hairexp.app.config import CollisionConfig, SolverConfig
from hairexp.physics.assembly import BandedAssembler
from hairexp.physics.contact_planes import ContactPlanes, stage_planes
from hairexp.physics.simulator import Simulator


def random_planes(seed=0, n=12, V=10):
    """Planes on random points of a chain of V vertices (vertex 0 kinematic), some vertex planes
    (degenerate edges (v, v)), some on edge interiors, gaps on both sides of the planes."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(V, 3)) * 0.01, axis=0)
    a = rng.integers(0, V - 1, size=n)
    vertex = rng.random(n) < 0.5
    e = np.stack([a, np.where(vertex, a, a + 1)], axis=1)
    s = np.where(vertex, 0.0, rng.random(n))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    y = (1 - s)[:, None] * x[e[:, 0]] + s[:, None] * x[e[:, 1]]
    gaps = rng.uniform(-2e-3, 1.5e-3, size=n)      # below the plane and beyond it
    kin = np.zeros(V, bool)
    kin[0] = True
    slot = np.where(kin, -1, np.cumsum(~kin) - 1)
    k = rng.uniform(1e3, 1e4, size=n)
    return ContactPlanes(e, s, nrm, y, gaps, k, slot), x, kin


def torch_energy(P: ContactPlanes, x: torch.Tensor) -> torch.Tensor:
    """The penalty in torch, written from the module doc's formula: the autograd reference."""
    e = torch.as_tensor(P.e)
    w = torch.as_tensor(P.w)
    y = w[:, :1] * x[e[:, 0]] + w[:, 1:] * x[e[:, 1]]
    g = torch.as_tensor(P.c) + (torch.as_tensor(P.n) * y).sum(1)
    k = torch.as_tensor(P.k)
    return (0.5 * k * g.clamp_max(0) ** 2).sum()


def test_penalty_is_one_sided_quadratic_and_c1():
    """psi = k/2 min(g, 0)^2: C^1 at the plane (value and slope 0 from both sides), curvature k
    below it, nothing beyond it; its force linear in the depth (the Newton model exact at a fixed
    set of pressed planes: module doc)."""
    P, x, _ = random_planes()
    k = float(P.k[0])
    sel = slice(0, 1)
    h = 1e-9
    (e_m, d1_m, d2_m), (e_p, d1_p, d2_p) = (P.psi(np.array([s * h]), sel) for s in (-1, 1))
    assert abs(e_m[0] - e_p[0]) <= k * h * h and abs(d1_m[0] - d1_p[0]) <= 2 * k * h
    assert d2_m[0] == k and d2_p[0] == 0.0
    e, d1, d2 = P.psi(np.array([1e-3, -1e-3, -2e-3]), np.zeros(3, dtype=int))
    assert e[0] == d1[0] == d2[0] == 0.0      # beyond the plane: nothing
    assert d1[1] < 0 and d2[1] == k          # below the plane: pushed out, curvature k
    assert np.isclose(d1[2], 2 * d1[1]) and np.isclose(e[2], 4 * e[1])   # linear force, quadratic energy


def test_gradient_and_hessian_vs_autograd_and_fd():
    P, x, kin = random_planes(seed=3)
    X = torch.tensor(x, requires_grad=True)
    E = torch_energy(P, X)
    assert np.isclose(float(E.detach()), P.energy(x), rtol=1e-12)
    (gt,) = torch.autograd.grad(E, X, create_graph=True)
    free = np.flatnonzero(~kin)
    N = 3 * len(free)
    grad, ab = np.zeros(N), np.zeros((9, N))
    P.add_to(x, grad, ab)
    assert np.allclose(grad, gt.detach().numpy()[free].ravel(), rtol=1e-10, atol=1e-12)
    Ht = np.stack([torch.autograd.grad(gt.reshape(-1)[i], X, retain_graph=True)[0].numpy().ravel()
                   for i in range(3 * len(x))])
    dof = (3 * free[:, None] + np.arange(3)).ravel()
    H = BandedAssembler.to_sparse(ab).toarray()
    assert np.allclose(H, Ht[np.ix_(dof, dof)], rtol=1e-9, atol=1e-9 * P.k.max())
    # and the energy's own finite differences
    h = 1e-7
    for i in (3, 7, 14):
        xp, xm = x.copy(), x.copy()
        xp.reshape(-1)[i] += h
        xm.reshape(-1)[i] -= h
        fd = (P.energy(xp) - P.energy(xm)) / (2 * h)
        assert np.isclose(fd, gt.detach().numpy().reshape(-1)[i], rtol=1e-5, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(H) > -1e-9 * P.k.max())   # positive semi-definite


@pytest.mark.parametrize("shape", list(SHAPES))
def test_stage_planes_cover_the_touching_vertices_and_are_conservative(shape):
    """Every vertex on the shell gets a plane through it with the shape's normal, its zero on the
    shell; on a convex shape a point on the tangent plane's far side is outside the
    shell (the plane is a supporting one)."""
    col = SHAPES[shape]()
    rng = np.random.default_rng(1)
    R, T = col.motion.pose(0.0)
    pts = rng.normal(size=(200, 3)) * 0.06
    d = col.distance(pts, 0.0)
    n = col.normal(pts, 0.0)
    on = pts - d[:, None] * n                        # projected onto the shell
    x = np.concatenate([np.zeros((1, 3)) + 1.0, on])   # vertex 0: a far kinematic root
    V = len(x)
    edges = np.stack([np.arange(V - 1), np.arange(1, V)], 1)
    kin = np.zeros(V, bool)
    kin[0] = True
    slot = np.where(kin, -1, np.cumsum(~kin) - 1)
    P = stage_planes([col], x, 0.0, edges, ~kin, slot, np.ones(V))
    touching = np.flatnonzero(col.distance(x, 0.0) < col.shell_tolerance())
    assert set(touching[touching > 0]) <= set(P.vertices())
    vp = P.e[:, 0] == P.e[:, 1]
    # g = the distance to the shell at the plane's point: about 0 at a vertex on the shell
    assert np.allclose(P.gap(x)[vp], col.distance(x[P.e[vp, 0]], 0.0), atol=1e-9)
    assert np.all(np.abs(P.gap(x)[vp]) < 1e-6)
    # conservative: points pushed along each vertex plane's tangent and out stay outside the shell
    vp = np.flatnonzero(P.e[:, 0] == P.e[:, 1])
    t = np.cross(P.n[vp], rng.normal(size=(len(vp), 3)))
    y = x[P.e[vp, 0]] + 0.01 * t + 1e-4 * P.n[vp]
    assert np.all(col.distance(y, 0.0) > 0)


def resolve_cfg(**kw):
    return OmegaConf.structured(CollisionConfig(contact="stage", strain_limit=0.0, **kw))


@pytest.mark.parametrize("shape,speed", [("sphere", 0.5), ("capsule", 0.5), ("box", 0.3)])
def test_resolve_keeps_edges_unstretched_against_a_moving_collider(shape, speed):
    """A collider driven into hanging hair, stage mode without the strain limiter: with the
    contacts re-solved no edge sample ends inside (deeper into the thickness shell than the stage's
    own tolerance for "on the shell", ``shell_tolerance``: 2 um here; with the resting hair's planes
    the capsule's last step leaves an edge sample 1.6 um in, which the stage's edge response, like
    its vertex response, counts as on the shell) and the edge strain stays below 2 % (issue 14); the
    stage alone stretches the edges next to its contacts many times more."""
    kw = dict(radius=0.02, half_length=0.04, half_extents=(0.02, 0.02, 0.02), thickness=0.002, friction=0.3)
    col = collider_cfg(shape, [0.0, 0.4], [[0.0, -0.1, -0.1], [0.0, -0.1, -0.1 + 0.4 * speed]],
                       rot=(0.0, 0.0, 90.0) if shape == "capsule" else (0.0, 0.0, 0.0), **kw)
    sc = scene_cfg(n_strands=4, n_vertices=8)
    sc.colliders = [col]
    scene = build_scene(sc)
    worst = {}
    for resolve in (False, True):
        sim = Simulator(scene, OmegaConf.structured(SolverConfig()), collision_cfg=resolve_cfg(resolve=resolve))
        states, infos = run_steps(sim, 10, 0.04)
        strain, touched = 0.0, 0
        for st, info in zip(states[1:], infos):
            assert info.converged, (resolve, st.time, info.status)
            assert min_edge_gap(sim, st.x, st.time) > -scene.colliders[0].shell_tolerance()
            touched += info.object_contacts
            strain = max(strain, float(np.abs(np.linalg.norm(np.diff(st.x.reshape(4, 8, 3), axis=1), axis=2).ravel()
                                              / scene.strands.rest_lengths - 1).max()))
        assert touched > 0
        worst[resolve] = strain
        if resolve:
            assert sim.resolve_failures == 0
    assert worst[True] < 0.02, worst
    assert worst[True] < 0.5 * worst[False], worst


def test_resolve_is_on_by_default_and_only_with_object_contact():
    assert CollisionConfig().resolve is True
    sc = scene_cfg(n_strands=2, n_vertices=6)
    scene = build_scene(sc)     # no colliders: nothing to re-solve
    sim = Simulator(scene, OmegaConf.structured(SolverConfig()), collision_cfg=resolve_cfg(resolve=True))
    assert sim.resolve is False


def test_goaling_hard_keeps_its_constraints_and_edges_through_the_wheel_contact():
    """Goaling with hard assignment through its first wheel contacts (steps 23-28), the default
    contact (planes, no strain limiter): every cluster holds its target within 1e-6 of the hair
    length (with the stage alone and its limiter three tip clusters were left 3.2e-3 L off,
    test_restore.py), nothing is relaxed, no vertex ends inside the wheel and no edge is
    stretched by more than 2 %."""
    from experiments.common import compose
    from hairexp.app.assemble import assemble
    from hairexp.outputs.metrics import stretch

    run = assemble(compose(["experiment=goaling", "variants=[]", "controller.name=tracking", "logging.rerun=false",
                            "frames=29", "tracking.assignment=hard"]))
    ctl, wheel = run.controller, run.scene.colliders[0]
    contacts = 0
    for step, frame, state, info in run.steps(run.initial_state(), 29):
        m = ctl.observe(run.simulator, state, None)
        assert m["residual_rel_max"] <= 1e-6, step
        assert not m["relaxed_clusters"], step
        assert wheel.distance(state.x[~run.scene.strands.kinematic], state.time).min() > -1e-6
        assert np.abs(stretch(run.scene, state.x)).max() < 0.02, step
        contacts += info.object_contacts
    assert contacts > 0 and run.simulator.resolve_failures == 0


def _goaling_cfg(*extra):
    from hairexp.app.config import compose_config

    return compose_config(["experiment=goaling", "variants=[]", "controller.name=tracking", "frames=25",
                           "logging.rerun=false", "logging.progress=false", *extra])


def test_the_run_folder_counts_the_steps_solved_again_and_the_fallbacks(tmp_path, caplog, monkeypatch):
    """metrics.parquet has each step's contact planes and fallbacks, summary.json the steps with
    planes and the steps that fell back to the stage's result; a fallback is warned about at the
    run's end.  Goaling tracked through its first wheel contacts: planes, no fallback; the same
    with the second solve made to fail (its controller solve reports max_iterations): every
    contact step falls back, counted and said."""
    import logging

    import pandas as pd

    from hairexp.app.run import run
    from hairexp.physics import simulator as sim_mod
    from hairexp.physics.info import MAX_ITERATIONS

    s = run(_goaling_cfg(), tmp_path / "ok")
    df = pd.read_parquet(tmp_path / "ok" / "metrics.parquet")
    assert s["contact_plane_steps"] == int((df["contact_planes"] > 0).sum()) > 0
    assert s["resolve_fallback_steps"] == 0 and df["resolve_fallbacks"].sum() == 0
    assert (df.loc[df["contact_planes"] > 0, "object_contacts"] > 0).all()

    real = sim_mod.Simulator._resolve_contacts

    def failing(self, *a, **k):
        solve = self.controller.solve

        def unconverged(*b, **kw):
            x, c, info = solve(*b, **kw)
            info.status = MAX_ITERATIONS
            return x, c, info

        self.controller.solve = unconverged
        try:
            return real(self, *a, **k)
        finally:
            self.controller.solve = solve

    monkeypatch.setattr(sim_mod.Simulator, "_resolve_contacts", failing)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        s = run(_goaling_cfg(), tmp_path / "fallback")
    df = pd.read_parquet(tmp_path / "fallback" / "metrics.parquet")
    assert s["resolve_fallback_steps"] == int((df["resolve_fallbacks"] > 0).sum()) > 0
    assert s["contact_plane_steps"] == 0
    said = [r.getMessage() for r in caplog.records if "second solve with the contact planes" in r.getMessage()]
    assert len(said) == 1 and f"in {s['resolve_fallback_steps']} of {s['steps']} steps" in said[0]


def test_plane_friction_derivatives_vs_autograd():
    """The resting contact's friction (``ContactPlanes.set_friction``, collision.plane_friction):
    mu lam f0(|T^T (y - y_n - dc)|) with the normal forces lam held (the lag), both branches of f0
    (slip below and above eps): gradient and Hessian against torch autograd, the Hessian PSD."""
    from hairexp.physics.barrier import f0_friction  # noqa: F401  (the formula the torch form restates)

    P, x, kin = random_planes(seed=5, n=16)
    rng = np.random.default_rng(7)
    cols = [SimpleCollider(0.4, spin=3.0)]
    x_n = x + rng.normal(size=x.shape) * 2e-4       # slips of 0.1-2.5 mm (the spin adds some)
    lam = rng.uniform(0.0, 2.0, size=len(P))
    lam[::4] = 0.0                                   # planes without a normal force: no friction
    P.set_friction(cols, x_n, 0.0, 0.04, 0.02, lam)   # eps = 0.8 mm: slips on both sides of it
    assert P.lagged and P._fric is not None and len(P._fric[0]) == int((lam > 0).sum())
    sel, mu, T, y_n, dc, eps = P._fric
    r = np.linalg.norm(np.einsum("nij,ni->nj", T, (P.w[sel, 0, None] * x[P.e[sel, 0]] + P.w[sel, 1, None]
                                                   * x[P.e[sel, 1]]) - y_n - dc), axis=1)
    assert (r < eps).any() and (r > eps).any()       # both branches of f0

    def energy(X):
        w = torch.as_tensor(P.w[sel])
        e = torch.as_tensor(P.e[sel])
        y = w[:, :1] * X[e[:, 0]] + w[:, 1:] * X[e[:, 1]]
        u = torch.einsum("nij,ni->nj", torch.as_tensor(T), y - torch.as_tensor(y_n) - torch.as_tensor(dc))
        s = torch.sqrt((u * u).sum(1))
        f0 = torch.where(s < eps, -s ** 3 / (3 * eps ** 2) + s ** 2 / eps + eps / 3, s)
        return (torch.as_tensor(mu * P._lam) * f0).sum()

    X = torch.tensor(x, requires_grad=True)
    E = energy(X)
    e_np, g_np, H_np = P._friction(x, True)
    assert np.isclose(float(E.detach()), e_np, rtol=1e-12)
    (gt,) = torch.autograd.grad(E, X, create_graph=True)
    free = np.flatnonzero(~kin)
    N = 3 * len(free)
    grad, ab = np.zeros(N), np.zeros((9, N))
    from hairexp.physics.assembly import add_pair_blocks
    add_pair_blocks(grad, ab, P.slot[sel], g_np, H_np)
    assert np.allclose(grad, gt.detach().numpy()[free].ravel(), rtol=1e-9, atol=1e-12)
    Ht = np.stack([torch.autograd.grad(gt.reshape(-1)[i], X, retain_graph=True)[0].numpy().ravel()
                   for i in range(3 * len(x))])
    dof = (3 * free[:, None] + np.arange(3)).ravel()
    H = BandedAssembler.to_sparse(ab).toarray()
    assert np.allclose(H, Ht[np.ix_(dof, dof)], rtol=1e-8, atol=1e-9 * float(np.abs(H).max()))
    assert np.all(np.linalg.eigvalsh(H) > -1e-9 * float(np.abs(H).max()))


class SimpleCollider:
    """A collider stand-in for set_friction: friction, a rigid motion at rest and a spin about z."""

    def __init__(self, friction, spin=0.0):
        from hairexp.model.rigid import RigidMotion

        self.friction, self.spin = friction, spin
        self.motion = RigidMotion.static()

    def spin_velocity_body(self, X):
        return self.spin * np.stack([-X[:, 1], X[:, 0], np.zeros(len(X))], axis=1)


@pytest.mark.parametrize("mu,holds", [(0.8, True), (0.1, False)])
def test_plane_friction_holds_hair_on_a_slope_where_mu_exceeds_the_slope(mu, holds):
    """A strand lying across a 20 degree slope (tan 0.36), root fixed, 1 s at dt 0.04 s: with
    collision.plane_friction the resting contact's friction in the solve holds it where mu > tan
    (the first step, before any normal force is known, and eps's creep leave 2.4 mm) and lets it
    swing down where mu < tan (54 mm); the stage alone (resolve=false) holds it too (0 mm at mu
    0.8), the planes without it let it slide 40 mm."""
    from test_collisions import collider, make_scene, simulate

    a = np.radians(20.0)
    n = np.array([0.0, np.cos(a), np.sin(a)])
    col = collider("plane", at=tuple(-0.002 * n), rot_deg=(20.0, 0.0, 0.0), thickness=0.002, friction=mu)
    scene = make_scene([col], n_strands=1, n_vertices=12, length=0.2, direction=[1.0, 0.0, 0.0],
                       root_center=[0.0, 0.0, 0.0], root_radius=1e-6)
    _, states, infos = simulate(scene, 25, resolve_cfg(plane_friction=True))
    assert all(i.converged for i in infos)
    down = np.array([0.0, -np.sin(a), np.cos(a)])
    down = down if down[1] < 0 else -down
    slid = float(np.dot(states[-1].x[-1] - states[0].x[-1], down))
    assert (slid < 5e-3) if holds else (slid > 2e-2), slid


@pytest.mark.parametrize("integrator", ["bdf2", "lmm2"])
def test_a_vertex_the_stage_stops_on_its_path_is_solved_again(integrator):
    """goaling_smoke with a one-stage second-order scheme: at 0.96 s a tip's straight path crosses the
    wheel and the collision stage stops it where it met it, 2.8 cm from the solve's end and 17 mm
    off the wheel's shell at the step's end; that vertex had no plane (beyond ``NEAR``), so no second
    solve: its edge ended compressed by 42 % (independent probe, 2026-12-07); with lmm2 at 1.12 s a
    tip the stage moved by 3.9 mm ended 5.9 mm off the wheel, 13.5 % (a second probe).  It gets a
    plane and the step is solved again: every edge within 2 % at every step."""
    from experiments.common import compose
    from hairexp.app.assemble import assemble
    from hairexp.outputs.metrics import stretch

    run = assemble(compose(["experiment=goaling_smoke", "variants=[]", "controller.name=tracking", "logging.rerun=false",
                            "frames=30", f"solver.integrator={integrator}"]))
    contacts = 0
    for step, frame, state, info in run.steps(run.initial_state(), 30):
        assert np.abs(stretch(run.scene, state.x)).max() < 0.02, step
        contacts += info.object_contacts
    assert contacts > 0
