"""Invariants of the time integrator (implicit Euler, paper eq. 5) on small scenes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from helpers import scene_cfg, solver_cfg, run_steps
from hairexp.physics.simulator import Simulator
from hairexp.app.builders import build_scene
from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Scene
from hairexp.model.strands import Strands
from hairexp.outputs.metrics import energies

NO_GRAVITY = [0.0, 0.0, 0.0]


def run(sim: Simulator, n: int, dt: float, state=None):
    return run_steps(sim, n, dt, state)


def strand_straightness(scene: Scene, x: np.ndarray) -> float:
    """Max over strands of 1 - |tip - root| / (sum of edge lengths): 0 for straight strands."""
    s = scene.strands
    out = 0.0
    for a, b in zip(s.offsets[:-1], s.offsets[1:]):
        p = x[a:b]
        arc = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        out = max(out, 1.0 - np.linalg.norm(p[-1] - p[0]) / arc)
    return out


def weight_norm(scene: Scene) -> float:
    s = scene.strands
    return float(np.linalg.norm(s.masses[~s.kinematic, None] * scene.gravity[None, :]))


def static_gradient(sim: Simulator, x: np.ndarray) -> np.ndarray:
    """(N,) gradient of E = stretch + bending + gravity w.r.t. the free DOFs, from the
    implicit Euler objective with no inertia (v_n = v_{n+1}, dt -> huge: M dv/dt and the
    damping potentials, which scale with 1/dt, vanish)."""
    obj = sim.objective
    s = sim.scene.strands
    x = np.array(x, dtype=np.float64)  # a writable copy (Strands arrays are read-only)
    obj.begin_step(x, np.zeros_like(x), x, 1e12)
    xf = x[~s.kinematic].reshape(-1)
    ev = obj.evaluate(xf, need_hessian=False)
    return ev.grad


def static_gradient_autograd(sim: Simulator, x: np.ndarray) -> np.ndarray:
    """The same from torch autograd of the summed term energies (an independent path)."""
    xt = torch.from_numpy(x.copy()).requires_grad_(True)
    E = sum(t.total(xt) for t in sim.terms + sim.external if t.name in ("stretch", "bending", "gravity"))
    (g,) = torch.autograd.grad(E, xt)
    return g.numpy()[~sim.scene.strands.kinematic].reshape(-1)


@pytest.mark.parametrize("hair", [{}, {"edge_damping": 0.05, "air_drag": 5.0}], ids=["undamped", "damped"])
def test_strand_at_rest_without_gravity_stays_put(hair):
    scene = build_scene(scene_cfg(n_strands=4, n_vertices=9, gravity=NO_GRAVITY, spread=0.4, hair=hair))
    sim = Simulator(scene, solver_cfg())
    states, infos = run(sim, 20, 0.04)
    assert all(i.converged for i in infos)
    disp = max(float(np.abs(s.x - scene.strands.rest).max()) for s in states)
    assert disp < 1e-10
    assert float(np.abs(states[-1].v).max()) < 1e-10 / 0.04


@pytest.mark.parametrize("hair", [{}, {"edge_damping": 0.05}], ids=["undamped", "edge_damping"])
def test_constant_velocity_root_carries_strands_rigidly(hair):
    """Galilean invariance: a body translating at constant velocity (no gravity, no air) carries
    straight strands along exactly."""
    motion = dict(interpolation="linear", times=[0.0, 10.0], translations=[[0, 0, 0], [1.0, 0, 0]],
                  rotations_deg=[[0, 0, 0], [0, 0, 0]])
    scene = build_scene(scene_cfg(n_strands=4, n_vertices=9, gravity=NO_GRAVITY, direction=[0.3, -1.0, 0.2],
                                  spread=0.4, hair=hair, motion=motion))
    sim = Simulator(scene, solver_cfg())
    s0 = sim.initial_state()
    body_v = np.array([0.1, 0.0, 0.0])  # 1 m over 10 s
    np.testing.assert_allclose(s0.v, np.broadcast_to(body_v, s0.v.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(s0.x, scene.strands.rest, rtol=0, atol=1e-15)
    dt, n = 0.04, 25
    states, infos = run(sim, n, dt, s0)
    assert all(i.converged for i in infos)
    for k, st in enumerate(states):
        shift = st.x - scene.strands.rest
        np.testing.assert_allclose(shift, np.broadcast_to(body_v * k * dt, shift.shape), rtol=0, atol=1e-9)
        assert strand_straightness(scene, st.x) < 1e-12
    np.testing.assert_allclose(states[-1].v, np.broadcast_to(body_v, s0.v.shape), rtol=0, atol=1e-9 / dt)


def test_damped_hanging_strands_settle_to_static_equilibrium():
    """Strands start horizontal, swing down under gravity with air drag and stretch damping,
    and come to rest where the elastic forces balance the weight."""
    scene = build_scene(scene_cfg(n_strands=3, n_vertices=8, direction=[1.0, 0.0, 0.0],
                                  hair={"air_drag": 5.0, "edge_damping": 0.01}))
    # Newton's tolerance bounds the residual force: keep it well below what is asserted
    sim = Simulator(scene, solver_cfg(rtol=1e-7))
    W = weight_norm(scene)
    g0 = static_gradient(sim, scene.strands.rest)
    assert np.linalg.norm(g0) > 0.1 * W  # the start is far from equilibrium
    states, infos = run(sim, 150, 0.04)
    assert all(i.converged for i in infos)
    end = states[-1]
    assert float(np.abs(end.v).max()) < 1e-5  # m/s (it swung at ~1 m/s)
    g = static_gradient(sim, end.x)
    np.testing.assert_allclose(g, static_gradient_autograd(sim, end.x), rtol=0, atol=1e-9 * W)
    assert np.linalg.norm(g) < 1e-5 * W
    # and it did swing down: every tip fell by more than a quarter of the strand length
    s = scene.strands
    tips = s.offsets[1:] - 1
    assert np.all(s.rest[tips, 1] - end.x[tips, 1] > 0.25 * s.strand_lengths())


@pytest.mark.parametrize("dt", [0.04, 0.01])
def test_total_energy_never_increases_without_damping(dt):
    """Backward Euler is dissipative: kinetic + stretch + bending + gravity potential does not
    grow from step to step (static root, no damping terms), up to the work of the residual
    force Newton leaves (|grad H| |x_{n+1} - x_n|) and round-off."""
    scene = build_scene(scene_cfg(n_strands=4, n_vertices=10, direction=[1.0, 0.0, 0.0], spread=0.3))
    sim = Simulator(scene, solver_cfg(integrator="implicit_euler"))
    assert not any(t.name in ("edge_damping", "air_drag") for t in sim.terms)
    L = float(scene.strands.strand_lengths().max())
    scale = float(scene.strands.masses.sum()) * 9.81 * L  # J, energy of the swing
    states, infos = run(sim, 60, dt)
    assert all(i.converged for i in infos)
    parts = [energies(scene, st, sim) for st in states]  # (kinetic, potential) in J
    totals = [k + p for k, p in parts]
    assert max(k for k, _ in parts) > 0.02 * scale  # it did swing ...
    assert totals[0] - totals[-1] > 0.02 * scale     # ... and lost energy
    for n, info in enumerate(infos):
        dx = np.linalg.norm(states[n + 1].x - states[n].x)
        allowed = info.grad_norm * dx + 1e-12 * scale
        assert totals[n + 1] - totals[n] <= allowed, f"energy grew at step {n + 1}: {totals[n]} -> {totals[n + 1]}"


@pytest.mark.parametrize("dt", [0.04, 0.01])
def test_trbdf2_energy_never_exceeds_the_start_and_its_step_rises_are_second_order(dt):
    """trbdf2 (the default) is not monotone step by step on the nonlinear strands (it is on a
    linear spring, tests/test_integrator.py): the energy trades between modes and the trapezoidal
    stage is not dissipative.  Without input it never exceeds the starting energy, and what it
    gains in a step shrinks as dt^2 (measured: 6.4e-4 of m g L at dt 0.04 s, 3.8e-5 at 0.01 s)."""
    scene = build_scene(scene_cfg(n_strands=4, n_vertices=10, direction=[1.0, 0.0, 0.0], spread=0.3))
    sim = Simulator(scene, solver_cfg(integrator="trbdf2"))
    assert not any(t.name in ("edge_damping", "air_drag") for t in sim.terms)
    L = float(scene.strands.strand_lengths().max())
    scale = float(scene.strands.masses.sum()) * 9.81 * L
    states, infos = run(sim, int(round(2.4 / dt)), dt)
    assert all(i.converged for i in infos)
    totals = np.array([k + p for k, p in (energies(scene, st, sim) for st in states)])
    assert totals.max() <= totals[0] + 1e-12 * scale
    assert np.diff(totals).max() <= 1.5e-3 * scale * (dt / 0.04) ** 2


def rotated_scene(scene: Scene, R: np.ndarray) -> Scene:
    """The same scene turned rigidly by R: body points, keyframes and gravity."""
    m = scene.motion
    motion = RigidMotion(m.times, m.translations @ R.T, m.rotvecs @ R.T, m.interpolation)
    body = scene.root_body @ R.T
    s = scene.strands
    strands = Strands.from_polylines(motion.transform(body, 0.0), s.counts, scene.material.linear_density)
    return Scene(scene.name + "_rotated", strands, scene.material, motion, scene.gravity @ R.T, body)


def test_rotation_equivariance():
    motion = dict(interpolation="cubic", times=[0.0, 0.2, 0.5],
                  translations=[[0, 0, 0], [0.05, 0.02, 0], [0.1, 0, 0.03]],
                  rotations_deg=[[0, 0, 0], [0, 20, 0], [10, 0, 30]])
    A = build_scene(scene_cfg(n_strands=3, n_vertices=8, direction=[1.0, 0.2, 0.0], spread=0.3,
                              hair={"edge_damping": 0.05, "air_drag": 1.0}, motion=motion))
    R = Rotation.from_rotvec([0.4, -1.2, 0.9]).as_matrix()
    B = rotated_scene(A, R)
    np.testing.assert_allclose(B.strands.rest, A.strands.rest @ R.T, rtol=0, atol=1e-14)
    sa, sb = Simulator(A, solver_cfg(rtol=1e-8)), Simulator(B, solver_cfg(rtol=1e-8))
    a, b = sa.initial_state(), sb.initial_state()
    moved = 0.0
    for _ in range(25):
        a, ia = sa.step(a, 0.02)
        b, ib = sb.step(b, 0.02)
        assert ia.converged and ib.converged
        np.testing.assert_allclose(b.x, a.x @ R.T, rtol=0, atol=1e-9)
        moved = max(moved, float(np.abs(a.x - A.strands.rest).max()))
    assert moved > 0.05  # the trajectories are not trivial
