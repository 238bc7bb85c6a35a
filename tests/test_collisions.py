"""Collision stage (issue: collisions): hair against colliders and against hair."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf

from helpers import run_steps

from hairexp.config import ColliderConfig, CollisionConfig, SceneConfig, SolverConfig
from hairexp.physics.collisions import HairHair, object_stage
from hairexp.physics.colliders import Cylinder, Plane, Sphere
from hairexp.physics.integrator import Simulator
from hairexp.scene.builders import build_scene
from hairexp.scene.rigid import RigidMotion
from hairexp.scene.strands import Strands

DT = 0.04


def collider(shape, at=(0.0, 0.0, 0.0), rot_deg=(0.0, 0.0, 0.0), **kw):
    c = OmegaConf.structured(ColliderConfig(name=shape, shape=shape, **kw))
    c.motion.translations = [list(map(float, at))]
    c.motion.rotations_deg = [list(map(float, rot_deg))]
    return c


def make_scene(colliders, motion=None, **kw):
    sc = OmegaConf.structured(SceneConfig(**kw))
    sc.colliders = colliders
    if motion:
        for k, v in motion.items():
            sc.motion[k] = v
    return build_scene(sc)


def simulate(scene, steps, cc=None):
    sim = Simulator(scene, OmegaConf.structured(SolverConfig()), collision_cfg=OmegaConf.structured(cc or CollisionConfig()))
    states, infos = run_steps(sim, steps, DT)
    return sim, states, infos


def deepest(scene, states):
    free = ~scene.strands.kinematic
    return max(float(np.max(-c.distance(s.x[free], s.time))) for c in scene.colliders for s in states[1:])


@pytest.mark.parametrize("shape", ["sphere", "plane"])
def test_dropped_strand_never_ends_a_step_inside(shape):
    if shape == "sphere":
        col = collider("sphere", at=(0.15, -0.08, 0.0), radius=0.05, thickness=0.002)
    else:
        col = collider("plane", at=(0.0, -0.1, 0.0), thickness=0.002, friction=0.5)
    scene = make_scene([col], n_strands=2, n_vertices=12, length=0.3, direction=[1.0, 0.0, 0.0], spread=0.2)
    _, states, infos = simulate(scene, 30)
    assert sum(i.object_contacts for i in infos) > 0            # it did land
    assert deepest(scene, states) <= 1e-9                        # never deeper than the thickness shell
    assert max(i.penetration_max for i in infos) <= 1e-9


def test_fast_sweep_does_not_tunnel_through_a_thin_box(monkeypatch):
    """The root sweeps at 5 m/s over a 1 cm thick wall: hanging hair must go over the top, not
    through the wall.  Every application of the collision stage (a step, or a substep when
    recovery splits a step) is checked on its own path: a vertex may change sides of the wall
    only above the wall's top."""
    import hairexp.physics.collisions as coll

    calls = []
    original = coll.collision_stage

    def recording(cfg, sc, hh, x0, x1, t0, t1, dt):
        out = original(cfg, sc, hh, x0, x1, t0, t1, dt)
        calls.append((x0.copy(), out[0].copy()))
        return out

    monkeypatch.setattr(coll, "collision_stage", recording)
    wall = collider("box", at=(0.2, -0.2, 0.0), half_extents=[0.005, 0.1, 0.2], thickness=0.001, friction=0.0)
    motion = dict(interpolation="linear", times=[0.0, 0.2], translations=[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
                  rotations_deg=[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    scene = make_scene([wall], motion, n_strands=3, n_vertices=15, length=0.3)
    _, states, infos = simulate(scene, 10)
    free = ~scene.strands.kinematic
    top = -0.2 + 0.1 + 0.001
    crossings = 0
    assert len(calls) >= 10
    for x0, x1 in calls:
        x0, x1 = x0[free], x1[free]
        sw = (x0[:, 0] < 0.2) != (x1[:, 0] < 0.2)
        crossings += int(sw.sum())
        u = (0.2 - x0[sw, 0]) / (x1[sw, 0] - x0[sw, 0])
        y = x0[sw, 1] + u * (x1[sw, 1] - x0[sw, 1])
        assert np.all(y >= top - 1e-6), f"a vertex crossed the wall below its top: y={y.min()}"
    assert crossings > 0                                       # the hair did get past the wall (over it)
    assert sum(i.object_contacts for i in infos) > 0
    assert deepest(scene, states) <= 1e-9


def test_hair_hair_impulses_conserve_linear_momentum():
    rng = np.random.default_rng(3)
    n = 8
    A = np.stack([np.linspace(-0.1, 0.1, n), np.zeros(n), np.zeros(n)], 1)
    B = np.stack([np.zeros(n), np.full(n, 0.0004), np.linspace(-0.1, 0.1, n)], 1)
    s = Strands.from_polylines(np.concatenate([A, B]), [n, n], 1e-3)
    hh = HairHair(s, thickness=0.001)
    x = s.rest.copy()
    v = rng.normal(size=x.shape) * 0.01
    v[:n, 1] += 0.1      # A moves up toward B, B down toward A: they approach
    v[n:, 1] -= 0.1
    v[s.kinematic] = 0.0
    pairs = hh.candidate_pairs(x, x)
    v1, k = hh.impulses(x, v.copy(), pairs, DT, x)
    assert k > 0
    p0 = (s.masses[:, None] * v).sum(0)
    p1 = (s.masses[:, None] * v1).sum(0)
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-15 * float(np.abs(s.masses[:, None] * v).sum()) + 1e-18)


def test_swept_strands_do_not_pass_through_each_other():
    """Strand A (launched at 1.5 m/s in +y) sweeps across strand B 2 cm above it; both are
    rooted on a still body.  Without hair-hair collisions A passes through B (it ends above B at
    their closest approach); with them A stays below B."""
    n = 12
    zs = np.linspace(-0.12, 0.12, n)
    A = np.stack([np.zeros(n), np.full(n, -0.02), zs], 1)        # along z
    B = np.stack([zs, np.zeros(n), np.full(n, 0.03)], 1)         # along x, crossing A's line at z = 0.03
    pts = np.concatenate([A, B])
    from hairexp.scene.scene import Material, Scene

    s = Strands.from_polylines(pts, [n, n], 2e-4)
    scene = Scene("cross", s, Material(2e-4, 20.0, 2e-6), RigidMotion.static(), np.zeros(3), pts)

    from hairexp.physics.collisions import _closest_segment_params

    ea, eb = np.arange(n - 1), np.arange(n - 1)
    I, J = (g.ravel() for g in np.meshgrid(ea, eb, indexing="ij"))

    def height_of_a_over_b(x):
        """y of A minus y of B at the closest approach of the two polylines (< 0: A below B)."""
        a, b = x[:n], x[n:]
        u, v = _closest_segment_params(a[I], a[I + 1], b[J], b[J + 1])
        p = a[I] + u[:, None] * (a[I + 1] - a[I])
        q = b[J] + v[:, None] * (b[J + 1] - b[J])
        k = np.argmin(np.linalg.norm(p - q, axis=1))
        return float(p[k, 1] - q[k, 1])

    out = {}
    for on in (False, True):
        cc = OmegaConf.structured(CollisionConfig(objects=False, hair_hair=on, hair_thickness=0.002))
        sim = Simulator(scene, OmegaConf.structured(SolverConfig()), collision_cfg=cc)
        st = sim.initial_state()
        st.v[:n][~s.kinematic[:n]] = [0.0, 1.5, 0.0]
        heights = []
        for _ in range(5):
            st, _ = sim.step(st, DT)
            heights.append(height_of_a_over_b(st.x))
        out[on] = heights
    assert max(out[False]) > 0.0                 # without hair-hair A passes through B
    assert max(out[True]) < 0.0                  # with it A stays below B


def test_friction_on_an_incline():
    """A free particle resting on a plane inclined by 20 degrees: it sticks for mu = 0.5
    (tan 20 deg = 0.36) and slides for mu = 0.2."""
    g = np.array([0.0, -9.81, 0.0])
    theta = np.deg2rad(20.0)
    plane_motion = RigidMotion(np.zeros(1), np.zeros((1, 3)), np.array([[0.0, 0.0, theta]]))
    moved = {}
    for mu in (0.5, 0.2):
        col = Plane("incline", plane_motion, thickness=0.0, friction=mu)
        x = np.zeros((1, 3))
        v = np.zeros((1, 3))
        for _ in range(25):
            x1 = x + DT * (v + DT * g)
            x1, v, _, _ = object_stage([col], x, x1, 0.0, DT, DT, np.array([True]))
            x = x1
        moved[mu] = float(np.linalg.norm(x))
    assert moved[0.5] < 1e-9
    assert moved[0.2] > 0.01


def test_spinning_wheel_drags_hair_along_its_surface_velocity():
    """A strand hangs with its tip resting on top of a wheel (axis along z).  Spinning one way
    the top of the wheel moves in -x and drags the tip to -x; spinning the other way, to +x."""
    moved = {}
    for spin in (20.0, -20.0):
        wheel = collider("cylinder", at=(0.0, -0.1, 0.0), rot_deg=(90.0, 0.0, 0.0), radius=0.06, half_height=0.1,
                         spin=spin, thickness=0.002, friction=0.8)
        scene = make_scene([wheel], n_strands=1, n_vertices=12, length=0.2, direction=[0.0, -1.0, 0.0],
                           root_center=[0.0, 0.1605, 0.0], root_radius=1e-6)      # tip 1.5 mm into the shell
        top = scene.colliders[0].surface_velocity(np.array([[0.0, -0.038, 0.0]]), 0.0)[0, 0]
        _, states, infos = simulate(scene, 15)
        assert sum(i.object_contacts for i in infos) > 0
        assert deepest(scene, states) <= 1e-9
        moved[spin] = (float(states[-1].x[-1, 0] - states[0].x[-1, 0]), top)
    for dx, vx in moved.values():
        assert abs(vx) > 1.0
        assert np.sign(dx) == np.sign(vx) and abs(dx) > 1e-3     # the tip follows the surface


def test_no_collision_code_runs_without_colliders_or_hair_hair(monkeypatch):
    import hairexp.physics.collisions as coll

    def boom(*a, **k):
        raise AssertionError("collision code ran")

    monkeypatch.setattr(coll, "collision_stage", boom)
    scene = make_scene([], n_strands=2, n_vertices=8)
    sim, states, infos = simulate(scene, 3)
    assert sim.hair_hair is None and not sim.collide_objects
    assert all(i.seconds["collision"] == 0.0 for i in infos)
    assert all(i.object_contacts == 0 and i.hair_contacts == 0 for i in infos)


def test_collider_motion_and_surface_velocity():
    m = RigidMotion([0.0, 1.0], [[0, 0, 0], [1.0, 0, 0]], np.zeros((2, 3)), "linear")
    s = Sphere("s", m, radius=0.1)
    x = np.array([[0.5, 0.2, 0.0]])
    assert abs(s.distance(x, 0.5)[0] - 0.1) < 1e-12
    np.testing.assert_allclose(s.surface_velocity(x, 0.5), [[1.0, 0.0, 0.0]], atol=1e-12)
    w = Cylinder("w", RigidMotion.static(), radius=0.1, half_height=0.1, spin=2.0)
    np.testing.assert_allclose(w.surface_velocity(np.array([[0.1, 0.0, 0.0]]), 0.0), [[0.0, 0.0, -0.2]], atol=1e-12)
