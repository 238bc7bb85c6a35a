"""The compiled per-strand kernels (``solver.kernels=numba``, hairexp/physics/kernels.py,
bandchol.py, strand_kernels.py) against the references: torch autograd of the energies
(hairexp/physics/terms.py ``autograd_grad_hess``) and finite differences for the energies,
gradients and Hessians; scipy's banded Cholesky for the factorisation; the torch path
(``solver.kernels=torch``) for whole Newton solves, simulated steps under every integrator and
tracked (SQP) steps.  Also: fallback without numba, thread choice, config validation."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg
import torch
from omegaconf import OmegaConf

from helpers import bent_polyline, scene_cfg, solver_cfg
from tracking_helpers import build_tracked, polyline_scene, tracked_cfg
from hairexp.app.builders import build_scene
from hairexp.app.config import Config
from hairexp.app.validate import validate_config
from hairexp.errors import InputError
from hairexp.physics import bandchol, kernels
from hairexp.physics.assembly import BandedAssembler
from hairexp.physics.energies import Bending, Gravity, Stretch, curvature_binormal
from hairexp.physics.objective import ImplicitEulerObjective
from hairexp.physics.simulator import Simulator
from hairexp.physics.terms import DTYPE, autograd_grad_hess

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: numba vs torch: the same formulas summed in another order
AGREE = 1e-10
DT = 0.02
MOTION = dict(interpolation="cubic", times=[0.0, 0.3], translations=[[0, 0, 0], [0.05, 0.03, -0.02]],
              rotations_deg=[[0, 0, 0], [15, -10, 5]])


def straight(n: int, direction=(0.3, -0.8, 0.2), edge: float = 0.02, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    return np.asarray(origin) + edge * np.arange(n)[:, None] * d / np.linalg.norm(d)


def strands_of(kind: str):
    """Polylines: ``straight`` (exactly straight rest shapes), ``bent`` (rest curvature), ``mixed``
    (straight and bent, and a short strand of 3 vertices: one free vertex)."""
    if kind == "straight":
        return [straight(8, origin=(0.1 * i, 0, 0)) for i in range(3)]
    if kind == "bent":
        return [bent_polyline(8, seed=s) + [0.1 * s, 0, 0] for s in range(3)]
    return [straight(7), bent_polyline(9, seed=5) + [0.2, 0, 0], straight(3, origin=(0.4, 0, 0)),
            bent_polyline(4, seed=7) + [0.6, 0, 0]]


def make_objective(kind: str, kern: str, primal_dual: bool = True, gravity=(0.0, -9.81, 0.0)):
    scene = polyline_scene(strands_of(kind), gravity=gravity)
    s, m = scene.strands, scene.material
    terms = [Stretch(s.edges, s.rest_lengths, m.stretch_stiffness), Bending(s.bends, s.rest, m.bending_stiffness)]
    free = np.flatnonzero(~s.kinematic)
    ext = [Gravity(s.masses, scene.gravity, free)]
    obj = ImplicitEulerObjective(terms, s.masses, s.kinematic, s.free_slot, "closed_form", ext, primal_dual, kern, "1")
    return scene, obj


def start(scene, obj, rng, scale: float = 3e-3):
    """begin_step from the rest shape moved at random; the prescribed roots at rest."""
    x = scene.strands.rest + scale * rng.normal(size=scene.strands.rest.shape)
    x[scene.strands.kinematic] = scene.strands.rest[scene.strands.kinematic]
    v = 0.1 * rng.normal(size=x.shape)
    obj.begin_step(x, v, scene.strands.rest, DT)
    return obj.initial_guess() + scale * rng.normal(size=obj.n_dofs)


def _dense(ab) -> np.ndarray:
    return np.asarray(BandedAssembler.to_sparse(np.ascontiguousarray(ab)).todense())


def total_energy(obj, scene, xf_t: torch.Tensor) -> torch.Tensor:
    """eq. (5) in torch: inertia + stretch + bending + gravity at xf (the autograd reference)."""
    x = torch.from_numpy(obj.x_full.copy())
    idx = torch.from_numpy(obj.free_vertices)
    x = x.index_put((idx,), xf_t.reshape(-1, 3))
    d = xf_t - torch.from_numpy(obj.x_pred)
    e = 0.5 * (torch.from_numpy(obj.mass_diag) * d * d).sum()
    for t in obj.terms + obj.external:
        e = e + t.energy(x[t.stencil_t]).sum()
    return e


# -- 1. element kernels: energy, gradient, Hessian ------------------------------------------------
@pytest.mark.parametrize("kind", ["straight", "bent", "mixed"])
def test_energy_and_gradient_match_autograd_and_finite_differences(kind):
    rng = np.random.default_rng(1)
    scene, obj = make_objective(kind, "numba")
    assert obj.kernels is not None and obj.torch_terms == []
    xf = start(scene, obj, rng)
    ev = obj.evaluate(xf, need_hessian=False)
    xt = torch.from_numpy(xf.copy()).requires_grad_(True)
    E = total_energy(obj, scene, xt)
    (g_ref,) = torch.autograd.grad(E, xt)
    assert obj.value(xf) == pytest.approx(float(E.detach()), rel=1e-13, abs=1e-18)
    np.testing.assert_allclose(ev.grad, g_ref.numpy(), rtol=0, atol=1e-11 * np.abs(g_ref.numpy()).max())
    h = 1e-7
    for j in rng.choice(obj.n_dofs, 12, replace=False):
        e = np.zeros(obj.n_dofs)
        e[j] = h
        fd = (obj.value(xf + e) - obj.value(xf - e)) / (2 * h)
        assert fd == pytest.approx(ev.grad[j], rel=1e-5, abs=1e-6 * np.abs(ev.grad).max())


@pytest.mark.parametrize("kind", ["straight", "bent", "mixed"])
def test_hessian_is_exact_where_the_solver_hessian_is(kind):
    """Penalty stretch Hessian with every spring stretched, every bend at its rest angle (straight
    strands straight): there the PSD stretch block and the Gauss-Newton bending Hessian are the
    exact Hessian, which autograd gives (at |kb| = s the residual |kb| - s vanishes)."""
    scene, obj = make_objective(kind, "numba", primal_dual=False)
    s = scene.strands
    # stretch every strand by 1 % along itself from its root: straight stays straight, springs taut
    x = scene.strands.rest.copy()
    for a, b in zip(s.offsets[:-1], s.offsets[1:]):
        x[a:b] = x[a] + 1.01 * (x[a:b] - x[a])
    obj.begin_step(scene.strands.rest.copy(), np.zeros_like(x), x, DT)   # the roots' edge stretched too
    xf = x[obj.free_vertices].reshape(-1)
    ev = obj.evaluate(xf)
    H = _dense(ev.banded)

    def f(y):
        return total_energy(obj, scene, y)

    H_ref = torch.autograd.functional.hessian(f, torch.from_numpy(xf.copy())).numpy()
    np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-9 * np.abs(H_ref).max())


@pytest.mark.parametrize("kind", ["straight", "bent", "mixed"])
@pytest.mark.parametrize("primal_dual", [True, False])
def test_kernels_agree_with_the_torch_closed_forms(kind, primal_dual):
    """Gradient, band, value and Newton direction of the numba path against the torch path (whose
    closed forms tests/test_energies.py checks against autograd), with tension iterates set."""
    objs = [make_objective(kind, k, primal_dual)[1] for k in ("torch", "numba")]
    scene = make_objective(kind, "torch")[0]
    out = []
    for obj in objs:
        r = np.random.default_rng(3)
        xf = start(scene, obj, r)
        if primal_dual:
            obj.update_tensions(xf, 1e-4 * r.normal(size=obj.n_dofs))
        ev = obj.evaluate(xf)
        out.append((ev.grad, _dense(ev.banded), obj.value(xf), obj.solve(ev.banded, -ev.grad), ev.force_scale))
    assert objs[1].kernels is not None and objs[0].kernels is None
    for a, b in zip(*out):
        np.testing.assert_allclose(b, a, rtol=0, atol=AGREE * max(np.abs(a).max(), 1e-300))


def test_zero_curvature_and_short_strands_have_finite_derivatives():
    """Exactly collinear triples (|kb| = 0) with and without rest curvature (the kink), and strands
    with a single free vertex: finite gradient and band, PSD band."""
    scene, obj = make_objective("mixed", "numba")
    s = scene.strands
    x = scene.strands.rest.copy()
    for a, b in zip(s.offsets[:-1], s.offsets[1:]):   # every strand straightened along its root edge
        d = x[a + 1] - x[a]
        x[a:b] = x[a] + np.arange(b - a)[:, None] * d
    obj.begin_step(x, np.zeros_like(x), x, DT)
    xf = x[obj.free_vertices].reshape(-1)
    ev = obj.evaluate(xf)
    assert np.isfinite(ev.grad).all() and np.isfinite(ev.banded).all()
    H = _dense(ev.banded)
    assert np.linalg.eigvalsh(H).min() > 0
    ref = make_objective("mixed", "torch")[1]
    ref.begin_step(x, np.zeros_like(x), x, DT)
    ev_ref = ref.evaluate(xf)
    np.testing.assert_allclose(ev.grad, ev_ref.grad, rtol=0, atol=AGREE * np.abs(ev_ref.grad).max())
    np.testing.assert_allclose(H, _dense(ev_ref.banded), rtol=0, atol=AGREE * np.abs(H).max())


def test_bending_jacobian_matches_autograd():
    rng = np.random.default_rng(5)
    xs = rng.normal(size=(20, 3, 3))
    xs[:4] = np.linspace(0, 1, 3)[None, :, None] * rng.normal(size=(4, 1, 3))   # collinear
    Y = xs.reshape(-1, 3)
    J, kb, e0, e1 = np.empty((3, 9)), np.empty(3), np.empty(3), np.empty(3)

    def kb_of(x):
        return curvature_binormal(x[1] - x[0], x[2] - x[1])

    for i in range(len(xs)):
        xt = torch.from_numpy(xs[i].copy())
        kb_ref = kb_of(xt).numpy()
        J_ref = torch.autograd.functional.jacobian(kb_of, xt).reshape(3, 9).numpy()
        kernels.bend_jacobian(Y, 3 * i, 3 * i + 1, 3 * i + 2, J, kb, e0, e1)
        np.testing.assert_allclose(kb, kb_ref, rtol=0, atol=1e-13 * max(np.abs(kb_ref).max(), 1.0))
        np.testing.assert_allclose(J, J_ref, rtol=0, atol=1e-12 * np.abs(J_ref).max())


def test_stretch_energy_gradient_against_autograd_elementwise():
    """Each edge's energy and gradient from the kernels' helpers against autograd_grad_hess."""
    rng = np.random.default_rng(6)
    xs = rng.normal(size=(30, 2, 3))
    l0 = 0.5 + rng.random(30)
    k_l0 = 10.0 / l0
    Y = xs.reshape(-1, 3)
    edges = np.arange(60).reshape(30, 2)
    e_ref = 0.5 * k_l0 * (np.linalg.norm(xs[:, 1] - xs[:, 0], axis=1) - l0) ** 2
    for e in range(30):
        assert kernels.stretch_energy_of(Y, edges, e, k_l0, l0) == pytest.approx(e_ref[e], rel=1e-14)
    st = Stretch(edges, l0, 10.0)
    g_ref, _ = autograd_grad_hess(st.energy, torch.from_numpy(xs), need_hessian=False)
    assert g_ref.dtype == DTYPE   # the full gradient path is checked through the objective above


# -- 2. the banded factorisation --------------------------------------------------------------------
def block_banded(rng, sizes, bw=8):
    N = sum(sizes)
    A = np.zeros((N, bw + 1))
    off = np.concatenate([[0], np.cumsum(sizes)])
    for a, b in zip(off[:-1], off[1:]):   # B B^T, B lower banded with half-bandwidth bw/2: SPD, bandwidth bw
        n = b - a
        B = np.tril(np.triu(rng.normal(size=(n, n)), -bw // 2)) + 4.0 * np.eye(n)
        M = B @ B.T
        for d in range(min(bw + 1, n)):
            A[a:b - d, d] = np.diag(M, -d)
    return A, off.astype(np.int64)


@pytest.mark.parametrize("parallel", [False, True])
def test_block_cholesky_matches_scipy(parallel):
    rng = np.random.default_rng(7)
    A, off = block_banded(rng, [3, 9, 24, 72, 5, 30])
    L, ok = np.empty_like(A), np.ones(len(off) - 1, dtype=np.bool_)
    (bandchol.factor_parallel if parallel else bandchol.factor_serial)(A, L, off, ok)
    assert ok.all()
    cb = scipy.linalg.cholesky_banded(np.ascontiguousarray(A.T), lower=True)
    N = len(A)
    for d in range(9):   # LAPACK leaves the entries past the matrix end unspecified
        np.testing.assert_allclose(L[:N - d, d], cb[d, :N - d], rtol=0, atol=1e-11 * np.abs(cb).max())
    B = rng.normal(size=(N, 3))
    X = np.empty_like(B)
    (bandchol.solve_parallel if parallel else bandchol.solve_serial)(L, B, X, off)
    np.testing.assert_allclose(X, scipy.linalg.solveh_banded(np.ascontiguousarray(A.T), B, lower=True),
                               rtol=0, atol=1e-12 * np.abs(X).max())


def test_indefinite_block_is_reported_and_shifted():
    rng = np.random.default_rng(8)
    A, off = block_banded(rng, [12, 12])
    A[15, 0] = -1.0   # a negative pivot in block 1
    L, ok = np.empty_like(A), np.ones(2, dtype=np.bool_)
    bandchol.factor_serial(A, L, off, ok)
    assert ok.tolist() == [True, False]


# -- 2b. the fused Newton pass (kernels.direction_serial / direction_parallel) -------------------------
@pytest.mark.parametrize("kind", ["straight", "bent", "mixed"])
@pytest.mark.parametrize("threads", [1, 2])
def test_fused_pass_is_bit_identical_to_evaluate_and_solve(kind, threads):
    """``evaluate_step`` (derivatives, band, factor and step per strand in one pass, blocks of equal
    size factored in pairs) gives the gradient and step of ``evaluate`` + ``solve`` bit for bit (on
    1 and 2 threads), the same force scale to round-off, and no band."""
    scene, obj = make_objective(kind, "numba")
    obj.kernels.threads = threads
    rng = np.random.default_rng(5)
    xf = start(scene, obj, rng)
    obj.update_tensions(xf, 1e-4 * rng.normal(size=obj.n_dofs))
    ev, p = obj.evaluate_step(xf)
    assert p is not None and ev.banded is None
    ev0 = obj.evaluate(xf)
    p0 = obj.solve(ev0.banded, -ev0.grad)
    np.testing.assert_array_equal(ev.grad, ev0.grad)
    np.testing.assert_array_equal(p, p0)
    assert ev.force_scale == pytest.approx(ev0.force_scale, rel=1e-14)
    obj.fused = False
    ev1, p1 = obj.evaluate_step(xf)
    assert p1 is None and ev1.banded is not None


def test_fused_pass_falls_back_where_a_block_is_indefinite():
    """A block whose pivot is not positive: ``ok`` flags it alone (its pair partner is factored on its
    own), and ``evaluate_step`` returns the band for the shifted factorisation."""
    scene, obj = make_objective("straight", "numba")   # 3 strands of equal size: a pair, then one
    xf = start(scene, obj, np.random.default_rng(6))
    blk = obj.kernels.blk_dof
    obj.mass_diag = obj.mass_diag.copy()
    obj.mass_diag[blk[1]] = -1e9   # block 1, the pair's second
    ev, p = obj.evaluate_step(xf)
    assert p is None and ev.banded is not None
    assert obj.kernels._ok.tolist() == [True, False, True]


def test_grouped_block_factorisation_is_the_single_one():
    """``factor_group`` / ``solve_group`` (up to GROUP blocks side by side, stacked) against
    ``factor_rows`` / ``solve_rows`` and bandchol's factorisation: bit-identical, for a group of
    GROUP blocks and a smaller one, and blocks shorter than the band."""
    rng = np.random.default_rng(9)
    for n, g in ((24, kernels.GROUP), (24, 3), (6, 2)):
        A, off = block_banded(rng, [n] * g)
        stack = np.zeros((kernels.GROUP, n + 2, kernels.BW + 1))
        single = [A[k * n:(k + 1) * n].copy() for k in range(g)]
        for k in range(g):
            stack[k, :n] = single[k]
        assert kernels.factor_group(stack, g, n)
        for k in range(g):
            assert kernels.factor_rows(single[k], n)
            np.testing.assert_array_equal(stack[k, :n], single[k])
        L, ok = np.empty_like(A), np.ones(g, dtype=np.bool_)
        bandchol.factor_serial(A, L, off, ok)
        np.testing.assert_array_equal(L, np.concatenate(single))
        x = rng.normal(size=g * n + 5)
        x2 = x.copy()
        kernels.solve_group(stack, g, n, x, 5)
        for k in range(g):
            kernels.solve_rows(single[k], n, x2[5 + k * n:5 + (k + 1) * n])
        np.testing.assert_array_equal(x, x2)
    bad = np.zeros((kernels.GROUP, 3, kernels.BW + 1))
    bad[:, :, 0] = 1.0
    bad[1, 2, 0] = -1.0
    assert not kernels.factor_group(bad, 2, 3)
    assert kernels.BW == bandchol.BW


def test_tensions_along_a_step_match_the_displacement_form_and_torch():
    scene, obj = make_objective("mixed", "numba")
    rng = np.random.default_rng(10)
    xf = start(scene, obj, rng)
    step = 1e-3 * rng.normal(size=obj.n_dofs)
    K = obj.kernels
    Y = K._points(obj, xf).copy()
    D = np.zeros_like(Y)
    D[obj.free_vertices] = step.reshape(-1, 3)
    ref = np.empty(len(K.edges))
    kernels.tensions(Y, D, K.edges, K.k_l0, K.l0, ref)
    np.testing.assert_array_equal(K.tensions(obj, xf, step), ref)
    exact = np.empty(len(K.edges))
    kernels.tensions(Y, np.zeros_like(Y), K.edges, K.k_l0, K.l0, exact)
    np.testing.assert_array_equal(K.tensions(obj, xf, None), exact)
    st = K.stretch
    t = st.linearized_tension(torch.from_numpy(Y)[st.stencil_t], torch.from_numpy(D)[st.stencil_t]).numpy()
    np.testing.assert_allclose(ref, t, rtol=1e-12, atol=1e-12 * np.abs(t).max())


# -- 3. whole solves and runs: numba == torch ---------------------------------------------------------
def simulate(kern: str, integrator="implicit_euler", steps=4, threads="1", hair=None, fused=True):
    hair = {"edge_damping": 0.05, "air_drag": 2.0} if hair is None else hair
    scene = build_scene(scene_cfg(n_strands=3, n_vertices=7, direction=[1.0, -0.3, 0.2], spread=0.4, hair=hair,
                                  motion=MOTION))
    cfg = solver_cfg(integrator=integrator)
    cfg.kernels, cfg.threads = kern, threads
    sim = Simulator(scene, cfg)
    sim.objective.fused = fused
    state = sim.initial_state()
    xs, its = [], []
    for _ in range(steps):
        state, info = sim.step(state, DT)
        assert info.converged
        xs.append(state.x.copy())
        its.append(info.iterations)
    return sim, np.array(xs), its


@pytest.mark.parametrize("integrator", ["implicit_euler", "bdf2", "generalized_alpha"])
def test_steps_agree_with_the_torch_path(integrator):
    """A few steps with every term (edge damping and air drag stay on torch and are added to the
    band) under each integrator's StepPlan: the same iterates to round-off."""
    sim_n, x_n, its_n = simulate("numba", integrator)
    sim_t, x_t, its_t = simulate("torch", integrator)
    assert sim_n.objective.kernels is not None and [t.name for t in sim_n.objective.torch_terms] == [
        "edge_damping", "air_drag"]
    assert its_n == its_t
    scale = np.abs(x_t).max()
    assert np.abs(x_n - x_t).max() <= AGREE * scale


def test_newton_solve_agrees_and_threads_are_bit_identical():
    _, x1, its1 = simulate("numba", threads="1", steps=3, hair={})
    _, xu, itsu = simulate("numba", threads="1", steps=3, hair={}, fused=False)
    np.testing.assert_array_equal(x1, xu)   # the fused pass is evaluate + solve, bit for bit
    assert its1 == itsu
    _, x2, _ = simulate("numba", threads="2", steps=3, hair={})
    _, xt, _ = simulate("torch", steps=3, hair={})
    np.testing.assert_array_equal(x1, x2)   # blocks are summed in the same order either way
    assert np.abs(x1 - xt).max() <= AGREE * np.abs(xt).max()


@pytest.mark.parametrize("assignment", ["hard", "soft"])
def test_tracked_steps_agree_with_the_torch_path(assignment):
    """The SQP with the numba factorisation and Schur complement (with soft assignment a strand's
    columns of A^T for one tracking point of several guides are proportional: one column kept)
    against the LAPACK + torch one."""
    res = {}
    for kern in ("numba", "torch"):
        _, _, sim = build_tracked(tracked_cfg({"frames": 3, "solver.kernels": kern, "solver.threads": "1",
                                               "tracking.assignment": assignment, "guides.count": 2}))
        kkt = sim.controller.kkt
        assert (kkt.kernels is not None) == (kern == "numba")
        if kern == "numba" and assignment == "soft":
            assert kkt._Bt.shape[1] < kkt.R
        state = sim.initial_state()
        xs = []
        for _ in range(3):
            state, info = sim.step(state, 0.04)
            assert info.converged
            xs.append(state.x.copy())
        res[kern] = np.array(xs)
    assert np.abs(res["numba"] - res["torch"]).max() <= 1e-9 * np.abs(res["torch"]).max()


# -- 4. fallback, threads, config -----------------------------------------------------------------------
def test_without_numba_the_torch_path_runs(monkeypatch):
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    sim, x, _ = simulate("numba", steps=2)
    assert sim.objective.kernels is None and sim.objective.torch_terms == sim.terms
    _, xt, _ = simulate("torch", steps=2)
    np.testing.assert_array_equal(x, xt)


def test_autograd_derivatives_keep_the_torch_path():
    scene = build_scene(scene_cfg(n_strands=2, n_vertices=5))
    cfg = solver_cfg(derivatives="autograd")
    assert Simulator(scene, cfg).objective.kernels is None


def test_thread_choice(monkeypatch):
    assert bandchol.pick_threads("1") == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert bandchol.pick_threads("2") == 2
    monkeypatch.setattr(os, "getloadavg", lambda: (3.0, 3.0, 3.0))   # busy: one thread
    assert bandchol.pick_threads("auto") == 1
    monkeypatch.setattr(os, "getloadavg", lambda: (0.2, 0.2, 0.2))
    assert bandchol.pick_threads("auto") == 2
    # a small scene keeps 1 thread on an idle machine (auto only): the parallel regions cost more
    n = bandchol.AUTO_MIN_VERTICES
    assert bandchol.pick_threads("auto", vertices=n - 1) == 1 and bandchol.pick_threads("auto", vertices=n) == 2
    assert bandchol.pick_threads("2", vertices=10) == 2
    monkeypatch.setattr(os, "getloadavg", lambda: (2.5, 2.5, 2.5))   # our own 2 threads: keep them
    assert bandchol.pick_threads("auto", current=2) == 2 and bandchol.pick_threads("auto", current=1) == 1
    monkeypatch.setattr(os, "getloadavg", lambda: (3.5, 3.5, 3.5))   # and another busy process: back to 1
    assert bandchol.pick_threads("auto", current=2) == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    assert bandchol.pick_threads("2") == 1 and bandchol.pick_threads("auto") == 1


@pytest.mark.parametrize("key,value", [("solver.kernels", "cuda"), ("solver.threads", "4"), ("solver.threads", "0")])
def test_bad_kernel_options_are_input_errors_naming_the_key(key, value):
    cfg = OmegaConf.structured(Config)
    OmegaConf.update(cfg, key, value, merge=False)
    with pytest.raises(InputError) as err:
        validate_config(cfg)
    assert err.value.where == key
    with pytest.raises(InputError) as err:
        Simulator(build_scene(scene_cfg(n_strands=2, n_vertices=5)), cfg.solver)
    assert err.value.where == key


def test_cli_bad_kernels_exits_2(tmp_path):
    env = dict(os.environ, CI="1", PYTHONPATH=os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling", "variants=[]", "frames=2",
                           "scene.n_strands=2", "scene.n_vertices=5", "logging.rerun=false", "solver.kernels=cuda",
                           f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert "solver.kernels" in proc.stderr


def test_compiled_target_points_match_the_torch_spline():
    """constraints._targets_into (hard: written, soft: added) against spline.eval_with_derivatives."""
    from hairexp.control.tracking.constraints import _targets_into
    from hairexp.guides import spline

    rng = np.random.default_rng(10)
    P = torch.from_numpy(rng.normal(size=(5, 6, 3)))
    s = torch.from_numpy(np.cumsum(0.01 + rng.random(6)))
    ks = np.array([3, 0, 4, 1, 2], dtype=np.int64)
    tk = np.array([-1.0, 0.7, float(s[-1]) + 2.0, float(s[0]), 1.9])
    ref = spline.eval_with_derivatives(P, s, torch.from_numpy(tk[ks]))
    m = spline.tangents(P, s).numpy()
    for add in (False, True):
        out = [np.full((5, 3), 1.0 if add else np.nan) for _ in range(3)]
        _targets_into(P.numpy(), s.numpy(), m, tk, ks, add, True, *out)
        for o, r in zip(out, ref):
            np.testing.assert_allclose(o[ks] - (1.0 if add else 0.0), r.numpy(), rtol=0, atol=1e-11)


def test_degenerate_iterate_is_non_finite_not_an_exception():
    """A zero-length edge divides by zero: inf/nan as on the torch path (Newton then reports the
    step diverged and the Simulator recovers it), never a ZeroDivisionError."""
    scene, obj = make_objective("straight", "numba")
    xf = start(scene, obj, np.random.default_rng(11))
    xf[3:6] = xf[0:3]   # two consecutive free vertices on top of each other
    ev = obj.evaluate(xf)
    assert not np.isfinite(ev.grad).all()
    assert not np.isfinite(obj.value(xf))


def test_newton_predicts_the_last_evaluation():
    """``newton.likely_converged``: after a full step, quadratic convergence from the last two
    gradient norms; never after a shortened step or without two norms.  It only picks the fused
    pass or evaluate + solve, whose results are the same (test_newton_solve_agrees_...)."""
    from hairexp.physics.newton import likely_converged

    assert likely_converged([1e-2, 1e-4], 1.0, 1e-7)        # predicted 1e-8
    assert not likely_converged([1e-2, 1e-4], 1.0, 1e-9)
    assert not likely_converged([1e-2, 1e-4], 0.5, 1e-7)    # shortened step: no rate
    assert not likely_converged([1e-4], 1.0, 1.0)


@pytest.mark.parametrize("kind", ["straight", "bent", "mixed"])
def test_metrics_potential_energy_by_the_kernels_is_the_terms_totals(kind):
    """outputs.metrics.energies sums stretch and bending with the compiled kernel when the run has
    one (StrandKernels.elastic_energies), and gravity in numpy (Gravity.total_numpy): the same
    joules as the torch terms' totals, at a state off the rest shape (roots included)."""
    from hairexp.outputs.metrics import energies
    from hairexp.physics.state import State

    scene = polyline_scene(strands_of(kind), gravity=(0.0, -9.81, 0.0))
    sims = {k: Simulator(scene, solver_cfg(kernels=k)) for k in ("numba", "torch")}
    assert sims["numba"].objective.kernels is not None and sims["torch"].objective.kernels is None
    rng = np.random.default_rng(4)
    x = scene.strands.rest + 4e-3 * rng.normal(size=scene.strands.rest.shape)
    v = 0.1 * rng.normal(size=x.shape)
    st = State(x=x, v=v, time=0.0)
    kin_k, pot_k = energies(scene, st, sims["numba"])
    kin_t, pot_t = energies(scene, st, sims["torch"])
    with torch.no_grad():
        xt = torch.from_numpy(x)
        ref = sum(float(t.total(xt)) for t in sims["torch"].terms + sims["torch"].external
                  if t.name in ("stretch", "bending", "gravity"))
        elastic = sum(float(t.total(xt)) for t in sims["torch"].terms if t.name in ("stretch", "bending"))
    assert elastic > 1e-6 * abs(ref)   # the elastic part is not lost in gravity's
    gravity = [t for t in sims["torch"].external if t.name == "gravity"]
    assert len(gravity) == 1 and gravity[0].total_numpy(x) == pytest.approx(float(gravity[0].total(xt)), rel=1e-14)
    assert pot_t == pytest.approx(ref, rel=1e-13, abs=1e-13 * elastic)
    assert pot_k == pytest.approx(ref, rel=1e-12, abs=1e-12 * elastic)
    assert kin_k == kin_t
    with pytest.raises(ValueError, match="shape"):
        sims["numba"].objective.kernels.elastic_energies(x[:-1])


def _readonly_twins(dispatcher) -> list:
    """Pairs of the dispatcher's compiled signatures that differ only in arrays' read-only flags."""
    import numba

    def plain(t):
        return t.copy(readonly=False) if isinstance(t, numba.types.Array) else t

    sigs = list(dispatcher.signatures)
    seen, twins = {}, []
    for sig in sigs:
        key = tuple(plain(t) for t in sig)
        if key in seen and seen[key] != sig:
            twins.append((seen[key], sig))
        seen.setdefault(key, sig)
    return twins


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba missing")
def test_one_build_whether_the_topology_is_read_only_or_not():
    """The kernels take the topology (free slots, edges, bends) as read-only arrays whether the
    scene's are (``Strands`` as built) or not (a deep copy, as an experiment's second variant
    gets): numba types the flag, and each big kernel was compiled twice, 39 s of a cold goaling
    run's 89 s (``strand_kernels._frozen``).  Same results either way."""
    def build(writable: bool):
        scene = polyline_scene(strands_of("mixed"))
        s, m = scene.strands, scene.material
        fs, ed, be = (np.array(a) for a in (s.free_slot, s.edges, s.bends))   # copies: writable
        if not writable:
            for a in (fs, ed, be):
                a.setflags(write=False)
        terms = [Stretch(ed, s.rest_lengths, m.stretch_stiffness), Bending(be, s.rest, m.bending_stiffness)]
        ext = [Gravity(s.masses, scene.gravity, np.flatnonzero(~s.kinematic))]
        obj = ImplicitEulerObjective(terms, s.masses, s.kinematic, fs, "closed_form", ext, True, "numba", "1")
        return scene, obj

    results = []
    for writable in (False, True):
        scene, obj = build(writable)
        k = obj.kernels
        assert not (k.free_slot.flags.writeable or k.edges.flags.writeable or k.bends.flags.writeable)
        xf = start(scene, obj, np.random.default_rng(3))
        ev, p = obj.evaluate_step(xf)
        ev0 = obj.evaluate(xf)
        results.append((ev.grad, p, ev0.banded, obj.value(xf)))
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)
    for d in (kernels.assemble_serial, kernels.direction_serial, kernels.energies_serial):
        assert d.signatures and _readonly_twins(d) == [], d
