"""Collision stage (issue: collisions): hair against colliders and against hair."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from helpers import run_steps

from hairexp.errors import InputError
from hairexp.app.config import ColliderConfig, CollisionConfig, SceneConfig, SolverConfig
from hairexp.physics.collisions import HairHair, object_stage
from hairexp.physics.kernels import HAVE_NUMBA
from hairexp.model.colliders import Box, Capsule, Cylinder, Plane, Sphere
import hairexp.physics.simulator as simulator_module
from hairexp.physics.simulator import Simulator
from hairexp.app.builders import build_scene
from hairexp.model.rigid import RigidMotion
from hairexp.model.strands import Strands

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
    through the wall.  Every application of the collision stage that tests paths (a step, or a
    substep when recovery splits a step) is checked on its own path: a vertex may change sides
    of the wall only above the wall's top.  Its application after the contacts' second solve
    (``collision.resolve``) tests end points only, the solve's result being a minimiser, not a
    path: there every state's strands are checked instead, no edge crossing the wall's plane below
    its top (a strand threaded through the wall has one)."""
    import hairexp.physics.collisions as coll

    calls = []
    original = coll.collision_stage

    def recording(cfg, sc, hh, x0, x1, t0, t1, dt, *rest, **kw):
        out = original(cfg, sc, hh, x0, x1, t0, t1, dt, *rest, **kw)
        if not kw.get("discrete", False):
            calls.append((x0.copy(), out[0].copy()))
        return out

    monkeypatch.setattr(simulator_module, "collision_stage", recording)
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
    E = scene.strands.edges
    for st in states:
        a, b = st.x[E[:, 0]], st.x[E[:, 1]]
        cross = (a[:, 0] - 0.2) * (b[:, 0] - 0.2) < 0
        u = (0.2 - a[cross, 0]) / (b[cross, 0] - a[cross, 0])
        y = a[cross, 1] + u * (b[cross, 1] - a[cross, 1])
        assert np.all(y >= top - 1e-6), f"an edge crosses the wall below its top at t={st.time}: y={y.min()}"


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
    pairs, _ = hh.neighbours(hh.frames(x, x))
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
    from hairexp.model.scene import Material, Scene

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

    monkeypatch.setattr(simulator_module, "collision_stage", boom)
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


def _brute_force_reachable(hh, x0, x1):
    """All non-adjacent edge pairs whose segments come within h during the linear step,
    by sampling the step finely (a reference for the broad phase, O(E^2))."""
    from hairexp.physics.edge_ccd import _closest_segment_params

    E = hh.E
    i, j = np.triu_indices(len(E), 1)
    ei, ej = E[i], E[j]
    ok = ~((ei[:, 0] == ej[:, 0]) | (ei[:, 0] == ej[:, 1]) | (ei[:, 1] == ej[:, 0]) | (ei[:, 1] == ej[:, 1]))
    i, j = i[ok], j[ok]
    dmin = np.full(len(i), np.inf)
    for s_ in np.linspace(0.0, 1.0, 41):
        x = (1 - s_) * x0 + s_ * x1
        a, b = _closest_segment_params(x[E[i, 0]], x[E[i, 1]], x[E[j, 0]], x[E[j, 1]])
        p = x[E[i, 0]] + a[:, None] * (x[E[i, 1]] - x[E[i, 0]])
        q = x[E[j, 0]] + b[:, None] * (x[E[j, 1]] - x[E[j, 0]])
        dmin = np.minimum(dmin, np.linalg.norm(p - q, axis=1))
    return set(zip(i[dmin < hh.h].tolist(), j[dmin < hh.h].tolist()))


@pytest.mark.parametrize("motion", ["still", "calm", "swing", "violent"])
def test_hair_hair_broad_phase_finds_every_pair_that_can_touch(motion):
    """Over a sequence of steps (Verlet list reused, rebuilt, or swept boxes), every edge pair
    that comes within the thickness during a step is among the pairs the broad phase and the
    reachability filter hand to the narrow phase: compared with brute force over all pairs."""
    rng = np.random.default_rng(11)
    n_s, n_v = 14, 9
    pts = []
    for k in range(n_s):
        root = np.array([0.004 * (k % 4), 0.0, 0.004 * (k // 4)])
        d = np.array([0.3 * rng.normal(), -1.0, 0.3 * rng.normal()])
        pts.append(root + np.linspace(0, 0.08, n_v)[:, None] * d / np.linalg.norm(d))
    s = Strands.from_polylines(np.concatenate(pts), [n_v] * n_s, 1e-3)
    hh = HairHair(s, thickness=0.002, skin=0.003)
    amp = {"still": 0.0, "calm": 2e-4, "swing": 3e-3, "violent": 2e-2}[motion]
    x0 = s.rest.copy()
    hows = set()
    for step in range(6):
        # a common swing (rotation about the roots' centre) plus per-vertex noise of size amp
        ang = 0.2 * step if motion in ("swing", "violent") else 0.0
        Rz = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
        x1 = (s.rest @ Rz.T) + amp * rng.normal(size=x0.shape)
        Ys = hh.frames(x0, x1)
        pairs, how = hh.neighbours(Ys)
        hows.add(how)
        near = hh.filter_reachable(x0, x1, pairs)
        got = set(map(tuple, np.sort(near, 1).tolist()))
        want = _brute_force_reachable(hh, x0, x1)
        assert want <= got, f"step {step} ({how}): missed {sorted(want - got)[:5]}"
        hh.end_step(x0, x1)
        x0 = x1
    if motion == "still":
        assert "reused" in hows
    if motion == "violent":
        assert "swept" in hows


def test_list_frame_keeps_distances_between_simultaneous_points():
    rng = np.random.default_rng(5)
    s = Strands.from_polylines(np.concatenate([np.c_[np.zeros(6), -np.linspace(0, 0.1, 6), np.full(6, 0.01 * k)]
                                               for k in range(3)]), [6] * 3, 1e-3)
    hh = HairHair(s, thickness=0.001)
    x0 = s.rest + 1e-3 * rng.normal(size=s.rest.shape)
    x1 = x0 @ np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + np.array([0.3, 0.1, 0]) + 1e-3 * rng.normal(size=x0.shape)
    Ys = hh.frames(x0, x1)
    A, b = hh.frame_at(x0, x1, 1.0)
    for Y, sv in zip(Ys, (0.0, 0.5, 1.0)):
        x = (1 - sv) * x0 + sv * x1
        Dx = np.linalg.norm(x[:, None] - x[None], axis=-1)
        DY = np.linalg.norm(Y[:, None] - Y[None], axis=-1)
        np.testing.assert_allclose(DY, Dx, atol=1e-12)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
    # the bulk rotation is removed: the list-frame motion is the noise, not the 90 degree turn
    assert np.abs(Ys[2] - Ys[0]).max() < 0.01


def test_neighbour_list_is_rebuilt_when_hair_drifts_together():
    """Two strands drift toward each other by 0.6 mm a step (less than skin / 2, so each step
    alone is calm) from 9 mm apart: the list built at the start holds no pair, and reusing it
    for too long would miss the contact.  Every pair that comes within h is found."""
    n = 8
    A = np.c_[np.zeros(n), -np.linspace(0, 0.08, n), np.zeros(n)]
    B = A + np.array([0.009, 0.0, 0.0])
    s = Strands.from_polylines(np.concatenate([A, B]), [n, n], 1e-3)
    hh = HairHair(s, thickness=0.002, skin=0.003)
    shift = np.where(np.arange(2 * n)[:, None] < n, 1.0, -1.0) * np.array([0.0003, 0.0, 0.0])
    shift[s.kinematic] = 0.0
    x0, found_any, hows = s.rest.copy(), False, []
    for step in range(14):
        x1 = x0 + shift
        Ys = hh.frames(x0, x1)
        pairs, how = hh.neighbours(Ys)
        hows.append(how)
        got = set(map(tuple, np.sort(hh.filter_reachable(x0, x1, pairs), 1).tolist()))
        want = _brute_force_reachable(hh, x0, x1)
        assert want <= got, f"step {step} ({how}): missed {sorted(want - got)[:5]}"
        found_any |= bool(want)
        hh.end_step(x0, x1)
        x0 = x1
    assert found_any and "reused" in hows and hows.count("rebuilt") >= 2


@pytest.mark.parametrize("degrees", [25.0, 60.0])
def test_strain_limit_after_a_fast_impact(degrees):
    """A strand swung fast into a sphere: without strain limiting the collision stage leaves
    edges stretched or crushed far beyond 10 %.  With ``strain_limit=0.1`` every edge ends within
    the limit, with a 25 degree swing in one step and with 60 degrees, where the strand wraps the
    sphere with several vertices stopped farther apart than the limit allows (before the
    limiter's rounds ran to convergence, issue 14's goblet fix: 10.02 % and 24.5 %, the limiter
    then best effort).  No vertex ends inside the shell."""
    from hairexp.physics.collisions import StrainLimit, collision_stage

    n = 12
    scene = make_scene([collider("sphere", at=(0.12, -0.06, 0.0), radius=0.03, thickness=0.002, friction=0.3)],
                       None, n_strands=1, n_vertices=n, length=0.22, direction=[1.0, 0.0, 0.0], root_radius=1e-5)
    s = scene.strands
    x0 = s.rest.copy()
    ang = np.deg2rad(degrees)   # the strand swings down about its root in one step
    R = np.array([[np.cos(ang), np.sin(ang), 0], [-np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    x1 = x0.copy()
    free = ~scene.strands.kinematic
    x1[free] = (x0[free] - x0[0]) @ R.T + x0[0]
    cc = OmegaConf.structured(CollisionConfig(objects=True, hair_hair=False, resolve=False))   # the stage and its limiter alone
    strain = lambda x: np.linalg.norm(x[s.edges[:, 1]] - x[s.edges[:, 0]], axis=1) / s.rest_lengths - 1  # noqa: E731
    plain, _, info0 = collision_stage(cc, scene, None, x0, x1.copy(), 0.0, DT, DT)
    limited, _, info1 = collision_stage(cc, scene, None, x0, x1.copy(), 0.0, DT, DT, StrainLimit(s, 0.1))
    assert info0.object_contacts > 0 and np.abs(strain(plain)).max() > 0.3
    assert info1.strain_limited > 0
    assert np.abs(strain(limited)).max() <= 0.1 + 1e-6
    assert scene.colliders[0].distance(limited[free], DT).min() >= -1e-9


def _rising(c, start, end, rot0=(0.0, 0.0, 0.0), rot1=None):
    """The collider config ``c`` moving linearly from pose (start, rot0) at t = 0 to (end, rot1) at DT."""
    c.motion.interpolation = "linear"
    c.motion.times = [0.0, DT]
    c.motion.translations = [list(map(float, start)), list(map(float, end))]
    c.motion.rotations_deg = [list(map(float, rot0)), list(map(float, rot1 or rot0))]
    return c


def _pressed_strand(shape: str, degrees: float):
    """A straight strand (12 vertices, 22 cm, along +x) resting on a collider that rises 1-3 cm over
    the step while the solve's end positions press the strand down into it (a rotation about the
    root by ``degrees``, as a tracked guide drove Celia's ponytail into the goblet).  ``rim``: a
    goblet-like cylinder whose top carries the strand's outer half, the tip beyond the rim.
    ``groove``: a V of two boxes (a concave union) that rises and tilts by 20 degrees."""
    th = 0.002
    if shape == "rim":
        cols = [_rising(collider("cylinder", radius=0.035, half_height=0.07, thickness=th, friction=0.3),
                        (0.12, -0.07 - th - 1e-5, 0.0), (0.12, -0.06 - th, 0.0))]
    else:
        a, off = 0.1, 0.1 * np.sqrt(0.5)
        cols = [_rising(collider("box", half_extents=[a, 0.01, 0.05], thickness=th, friction=0.3),
                        (0.12 - off, -0.06, 0.0), (0.12 - off, -0.03, 0.0), (0.0, 0.0, -45.0), (0.0, 0.0, -25.0)),
                _rising(collider("box", half_extents=[a, 0.01, 0.05], thickness=th, friction=0.3),
                        (0.12 + off, -0.06, 0.0), (0.12 + off, -0.03, 0.0), (0.0, 0.0, 45.0), (0.0, 0.0, 65.0))]
        cols[1].name = "box_2"
    scene = make_scene(cols, None, n_strands=1, n_vertices=12, length=0.22, direction=[1.0, 0.0, 0.0], root_radius=1e-5)
    x0 = scene.strands.rest.copy()
    free = ~scene.strands.kinematic
    ang = np.deg2rad(degrees)
    R = np.array([[np.cos(ang), np.sin(ang), 0], [-np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    x1 = x0.copy()
    x1[free] = (x0[free] - x0[0]) @ R.T + x0[0]
    return scene, x0, x1


def _deepest_edge(scene, x, t) -> float:
    """m: the deepest point of an edge with a free vertex inside a collider's thickness shell
    (``contact_geometry.EdgeGaps``: the segment's closest point), 0 if none."""
    from hairexp.physics.contact_geometry import EdgeGaps

    s = scene.strands
    mov = ~(s.kinematic[s.edges[:, 0]] & s.kinematic[s.edges[:, 1]])
    deep = 0.0
    for c in scene.colliders:
        d = EdgeGaps(c, *c.motion.pose(t)).edge_gaps(x[s.edges[mov, 0]], x[s.edges[mov, 1]])
        deep = max(deep, float(np.maximum(-d, 0.0).max(initial=0.0)))
    return deep


@pytest.mark.parametrize("shape, degrees", [("rim", 25.0), ("rim", 45.0), ("groove", 45.0), ("groove", 70.0)])
def test_strain_limit_holds_on_a_rising_rim_and_groove(shape, degrees):
    """Issue 14's goblet defect: with ``tracking.exact_compression=true`` Celia's tracked hair ended a
    step at 58 % edge strain against ``strain_limit: 0.1``.  The solve pressed a strand into the
    goblet's top: its vertices slid on the top face, the tip's on the side wall (the first
    contact's normal), which tore the edge over the rim; the limiter's rounds then ended before
    the limit held (8 rounds, and as soon as its moves hit nothing) and applied friction to its own
    moves.  Here a strand pressed over a rising rim and into a rising, tilting V groove (two
    boxes): after the stage every edge is within the limit and no vertex is inside a collider
    (before the fix: 0.122 and 1.90 on the rim, 0.235 and 0.860 in the groove)."""
    from hairexp.physics.collisions import StrainLimit, collision_stage

    scene, x0, x1 = _pressed_strand(shape, degrees)
    s = scene.strands
    free = ~s.kinematic
    assert min(float(c.distance(x0[free], 0.0).min()) for c in scene.colliders) >= 0.0   # a valid start
    cc = OmegaConf.structured(CollisionConfig(objects=True, hair_hair=False, strain_limit=0.1, resolve=False))
    strain = lambda x: np.abs(np.linalg.norm(x[s.edges[:, 1]] - x[s.edges[:, 0]], axis=1) / s.rest_lengths - 1)  # noqa: E731
    plain, _, _ = collision_stage(cc, scene, None, x0, x1.copy(), 0.0, DT, DT)
    assert strain(plain).max() > 0.3                       # the contact response alone tears the strand
    out, v, info = collision_stage(cc, scene, None, x0, x1.copy(), 0.0, DT, DT, StrainLimit(s, 0.1))
    assert info.object_contacts > 0 and info.strain_limited > 0
    assert strain(out).max() <= 0.1 + 1e-6
    for c in scene.colliders:
        assert c.distance(out[free], DT).min() >= -1e-9
        on = free & c.on_shell(out, DT)                      # no approaching velocity at the contacts
        vn = np.sum((v[on] - c.surface_velocity(out[on], DT)) * c.normal(out[on], DT), axis=1)
        assert vn.min(initial=0.0) >= -1e-9
    # nor any edge, to the shells' tolerance (the rim's were 6-8 mm inside before the edge response)
    assert _deepest_edge(scene, out, DT) <= max(c.shell_tolerance() for c in scene.colliders)


def _random_moving_collider(rng, shape: str, i: int):
    """A collider config of ``shape`` near a strand along +x from the origin, translating ~1 cm and
    turning ~5 degrees over the step."""
    kw = dict(thickness=0.002, friction=float(rng.uniform(0.0, 0.6)))
    if shape == "sphere":
        kw["radius"] = float(rng.uniform(0.02, 0.06))
    elif shape == "capsule":
        kw.update(radius=float(rng.uniform(0.01, 0.04)), half_length=float(rng.uniform(0.02, 0.08)))
    elif shape == "box":
        kw["half_extents"] = [float(v) for v in rng.uniform(0.01, 0.08, 3)]
    elif shape == "cylinder":
        kw.update(radius=float(rng.uniform(0.02, 0.06)), half_height=float(rng.uniform(0.02, 0.08)))
    c = collider(shape, **kw)
    c.name = f"{shape}_{i}"
    if shape == "plane":
        p0, r0 = [0.0, float(rng.uniform(-0.1, -0.03)), 0.0], [0.0, 0.0, float(rng.uniform(-20, 20))]
    else:
        p0 = [float(rng.uniform(0.05, 0.2)), float(rng.uniform(-0.12, -0.03)), float(rng.uniform(-0.03, 0.03))]
        r0 = [float(v) for v in rng.uniform(-60, 60, 3)]
    return _rising(c, p0, [float(a + b) for a, b in zip(p0, rng.normal(0.0, 0.01, 3))], r0,
                   [float(a + b) for a, b in zip(r0, rng.normal(0.0, 5.0, 3))])


def test_strain_limit_holds_against_random_moving_colliders():
    """The goblet fix in general: a strand swung 10-80 degrees in one step against one or two
    moving colliders (sphere, capsule, box, cylinder, plane; two of them make concave unions) at
    random.  After the stage no vertex is inside, and a strand with an edge over the limit has an
    edge through a collider: the contacts are tested at vertices, so an edge can end across a
    corner or a thin part with its two vertices outside, and the limiter cannot bring them together
    without one crossing (its neighbours, pulled both ways, can stay outside the limit too).
    Measured over 240 such cases (3 seeds, 80 each): 6 ended over the limit, each with such an
    edge; before the fix 188 of the 203 cases with contacts ended over it, 160 above 10.1 %, 22 above 50 %."""
    from hairexp.physics.collisions import StrainLimit, collision_stage

    rng = np.random.default_rng(3)
    cc = OmegaConf.structured(CollisionConfig(objects=True, hair_hair=False, strain_limit=0.1, resolve=False))
    s_edge = np.linspace(0.0, 1.0, 33)
    with_contacts = threaded = 0
    while with_contacts < 12:
        shapes = rng.choice(["sphere", "capsule", "box", "cylinder", "plane"], size=int(rng.integers(1, 3)))
        cols = [_random_moving_collider(rng, str(sh), i) for i, sh in enumerate(shapes)]
        scene = make_scene(cols, None, n_strands=1, n_vertices=12, length=0.22, direction=[1.0, 0.0, 0.0],
                           root_radius=1e-5)
        s = scene.strands
        x0, free, E = s.rest.copy(), ~s.kinematic, s.edges
        ang = np.deg2rad(rng.uniform(10.0, 80.0))
        if (min(float(c.distance(x0, 0.0).min()) for c in scene.colliders) < 0         # a valid start,
                or min(float(c.distance(x0[~free], DT).min()) for c in scene.colliders) < 0.003):  # roots clear
            continue
        R = np.array([[np.cos(ang), np.sin(ang), 0], [-np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
        x1 = x0.copy()
        x1[free] = (x0[free] - x0[0]) @ R.T + x0[0]
        out, _, info = collision_stage(cc, scene, None, x0, x1, 0.0, DT, DT, StrainLimit(s, 0.1))
        if info.object_contacts == 0:
            continue
        with_contacts += 1
        for c in scene.colliders:
            assert c.distance(out[free], DT).min() >= -1e-9
        strain = np.abs(np.linalg.norm(out[E[:, 1]] - out[E[:, 0]], axis=1) / s.rest_lengths - 1)
        if strain.max() > 0.1 + 1e-6:
            pts = (out[E[:, 0], None] * (1 - s_edge)[None, :, None] + out[E[:, 1], None] * s_edge[None, :, None])
            through = [bool((c.sdf_body(c.to_body(pts.reshape(-1, 3), DT)) < 0).any()) for c in scene.colliders]
            assert any(through), f"strain {strain.max():.3g} with no edge through a collider ({list(shapes)})"
            threaded += 1
    assert threaded <= 2


def test_known_distances_give_the_same_contact_response():
    """The object stage's path test computes each collider's distance of the end points; without a
    contact they are x1's and stand in for ``Collider.distance`` in the inelastic response and the
    penetration check (``dist``/``dist_out``): the same velocities as evaluating them again, and
    the distances collision_stage hands out are those at its returned x1, with or without a
    contact."""
    from hairexp.physics.collisions import collision_stage, contact_velocities

    rng = np.random.default_rng(5)
    motion = RigidMotion(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]),
                         np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3]]))
    ball = Sphere("ball", motion, thickness=0.002, friction=0.4, radius=0.05)
    wall = Plane("wall", RigidMotion.static(), thickness=0.001, friction=0.2)
    cols = [ball, wall]
    t1 = 0.5
    # points on the ball's shell and on the plane's, and free ones; movable but for two
    R, T = motion.pose(t1)
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    on_ball = (dirs * (0.05 + 0.002)) @ R.T + T
    on_wall = np.c_[rng.uniform(-1, 1, 20), np.full(20, 0.001), rng.uniform(-1, 1, 20)]
    free = rng.uniform(0.2, 0.4, (30, 3))
    x1 = np.vstack([on_ball, on_wall, free])
    movable = np.ones(len(x1), dtype=bool)
    movable[[3, 50]] = False
    v1 = rng.normal(size=x1.shape)
    dist = [c.distance(x1[movable], t1) for c in cols]
    assert any((d < c.shell_tolerance()).sum() > 10 for d, c in zip(dist, cols))   # vertices on both shells
    a = contact_velocities(cols, x1, v1.copy(), t1, movable)
    b = contact_velocities(cols, x1, v1.copy(), t1, movable, dist=dist)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, v1)     # the response did act
    # the stage: a path that ends clear of both (no contact), and one that ends inside the ball
    sc = SimpleNamespace(colliders=cols, strands=SimpleNamespace(kinematic=~movable, edges=np.zeros((0, 2), dtype=np.int64),
                                                                inverse_masses=np.ones(len(x1))))   # loose points: no edges
    cc = OmegaConf.structured(CollisionConfig())
    x0 = x1 + np.array([0.0, 0.01, 0.0])
    clear0, clear1 = free + 0.001, free + 0.002
    kin = np.zeros(len(free), dtype=bool)
    contacts = []
    for y0, y1, km in ((clear0, clear1, kin), (x0, x1 - 0.01 * np.vstack([dirs, np.zeros((50, 3))]), ~movable)):
        sc.strands.kinematic, sc.strands.inverse_masses = km, np.ones(len(km))
        out: list = []
        xe, _, info = collision_stage(cc, sc, None, y0, y1, 0.4, t1, 0.1, dist_out=out)
        assert len(out) == len(cols)
        for d, c in zip(out, cols):   # (the path test's compiled pass: to round-off)
            np.testing.assert_allclose(d, c.distance(xe[~km], t1), rtol=0, atol=1e-15)
        assert info.penetration_max == max(float(np.maximum(-d, 0.0).max(initial=0.0)) for d in out)
        contacts.append(info.object_contacts)
    assert contacts[0] == 0 and contacts[1] > 0


@pytest.mark.parametrize("shape", ["sphere", "capsule", "box", "cylinder", "plane"])
def test_compiled_path_test_equals_the_shapes_array_form(shape):
    """``path_test`` (one compiled pass for the five shapes) returns what ``Collider.to_body`` and
    ``sdf_body`` give, for points inside, on and outside each shape (every face, edge and cap
    region of box, capsule and cylinder), under a moving pose with rotation, with a subset of the
    vertices; and a subclass that defines its own ``sdf_body`` keeps it."""
    from hairexp.model.colliders import SHAPES
    from hairexp.physics import collisions as col_mod

    if not col_mod.HAVE_NUMBA:
        pytest.skip("numba not installed: path_test is the array form")
    rng = np.random.default_rng(7)
    motion = RigidMotion(times=np.array([0.0, 1.0]), translations=np.array([[0.1, -0.2, 0.3], [0.4, 0.1, -0.2]]),
                         rotvecs=np.array([[0.3, -0.5, 0.2], [1.1, 0.4, -0.7]]), interpolation="linear")
    params = {"sphere": dict(radius=0.1), "capsule": dict(radius=0.05, half_length=0.1),
              "box": dict(half_extents=(0.1, 0.05, 0.2)), "cylinder": dict(radius=0.08, half_height=0.06),
              "plane": {}}[shape]
    col = SHAPES[shape](name=shape, motion=motion, thickness=0.003, **params)
    x0 = motion.transform(rng.uniform(-0.3, 0.3, size=(400, 3)), 0.25)
    x1 = x0 + rng.normal(scale=0.05, size=x0.shape)
    x1[:20] = x0[:20]          # paths of length 0
    idx = np.sort(rng.choice(400, size=300, replace=False))
    got = col_mod.path_test(col, x0, x1, idx, 0.25, 0.29)
    X0, X1 = col.to_body(x0[idx], 0.25), col.to_body(x1[idx], 0.29)
    want = (X0, X1, col.sdf_body(X0) - col.thickness, col.sdf_body(X1) - col.thickness,
            np.linalg.norm(X1 - X0, axis=1))
    for g, w in zip(got, want):
        assert g.shape == w.shape
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-15)
    d = want[2]
    assert (d < 0).any() and (d > 0).any()           # points on both sides of the shell

    class Shifted(type(col)):
        def sdf_body(self, X):
            return super().sdf_body(X) + 1.0

    other = Shifted(name="shifted", motion=motion, thickness=0.003, **params)
    np.testing.assert_allclose(col_mod.path_test(other, x0, x1, idx, 0.25, 0.29)[2], want[2] + 1.0, atol=1e-15)


# --- the compiled broad phase and CCD (hairexp/physics/broad_phase.py) against the numpy/scipy paths


def _pair_set(pairs):
    return set(map(tuple, np.sort(np.asarray(pairs), 1).tolist()))


@pytest.mark.parametrize("seed", range(6))
def test_grid_pairs_equal_the_kdtree_pairs(seed):
    """Every overlapping box pair once, the same set as the cKDTree path: boxes of mixed sizes
    (a few 30 x larger, as swept boxes of a violent step), boxes that only touch on a face
    (closed boxes: touching counts in both), and with edges, the adjacent ones left out."""
    from hairexp.physics.broad_phase import grid_pairs

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 2500))
    c = rng.uniform(-0.1, 0.1, (n, 3))
    ext = rng.uniform(0, 0.01, (n, 3)) * (1 + 30 * (rng.random((n, 1)) < 0.02))
    lo, hi = c - ext, c + ext
    if seed % 2 == 0:   # half the boxes end exactly where the other half begins
        hi[: n // 2, 0] = 0.0
        lo[n // 2:, 0] = 0.0
    got = grid_pairs(lo, hi)
    assert len(got) == len(_pair_set(got))                       # each pair once
    assert np.all(got[:, 0] < got[:, 1])
    assert _pair_set(got) == _pair_set(HairHair._box_pairs(lo, hi))
    E = np.stack([np.arange(n), (np.arange(n) + 1) % n], 1)      # a ring: box k and k + 1 are adjacent
    hh = HairHair(SimpleNamespace(edges=E, inverse_masses=np.ones(n)), 1e-3)
    ref = HairHair._box_pairs(lo, hi)
    assert _pair_set(grid_pairs(lo, hi, E)) == _pair_set(ref[hh._not_adjacent(ref)])


def test_grid_pairs_degenerate_inputs():
    """No box, one box, identical boxes, points (zero extent) and a box far from the rest; a
    non-finite bound is refused (its cell index would be undefined)."""
    from hairexp.physics.broad_phase import grid_pairs

    assert grid_pairs(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 2)
    assert grid_pairs(np.zeros((1, 3)), np.ones((1, 3))).shape == (0, 2)
    lo = np.zeros((4, 3))
    assert _pair_set(grid_pairs(lo, lo.copy())) == {(i, j) for i in range(4) for j in range(i + 1, 4)}
    lo = np.array([[0.0, 0, 0], [0.5, 0, 0], [1e3, 1e3, 1e3]])
    hi = lo + np.array([[0.6, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]])
    assert _pair_set(grid_pairs(lo, hi)) == {(0, 1)}
    hi[1, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        grid_pairs(lo, hi)


def test_compiled_ccd_and_reachable_equal_the_numpy_ones():
    """``edge_edge_ccd_pairs`` finds the same hits as ``edge_ccd.edge_edge_ccd`` on 19,900
    random moving edge pairs (about a tenth of them hit), with times and segment parameters to
    round-off; ``reachable`` keeps the same pairs as ``filter_reachable``'s numpy path."""
    import hairexp.physics.collisions as collisions
    from hairexp.physics.broad_phase import edge_edge_ccd_pairs
    from hairexp.physics.edge_ccd import BISECTIONS, edge_edge_ccd

    rng = np.random.default_rng(3)
    V = 400
    x0 = rng.uniform(-0.02, 0.02, (V, 3))
    d = 0.01 * rng.standard_normal((V, 3))
    E = np.stack([np.arange(0, V, 2), np.arange(1, V, 2)], 1).astype(np.int64)
    pairs = np.array([(i, j) for i in range(len(E)) for j in range(i + 1, len(E))], dtype=np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    hit_r, s_r, wa_r, wb_r = edge_edge_ccd(x0[E[i, 0]], x0[E[i, 1]], x0[E[j, 0]], x0[E[j, 1]],
                                           d[E[i, 0]], d[E[i, 1]], d[E[j, 0]], d[E[j, 1]], 1e-3)
    P = len(pairs)
    hit, s, wa, wb = np.empty(P, bool), np.empty(P), np.empty(P), np.empty(P)
    edge_edge_ccd_pairs(x0, d, E, pairs, 1e-3, BISECTIONS, hit, s, wa, wb)
    assert 500 < hit.sum() < P and np.array_equal(hit, hit_r)
    for a, b in ((s, s_r), (wa, wa_r), (wb, wb_r)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    hh = HairHair(SimpleNamespace(edges=E, inverse_masses=np.ones(V)), 2e-3)
    got = hh.filter_reachable(x0, x0 + d, pairs)
    assert 0 < len(got) < P
    saved = collisions.HAVE_NUMBA
    try:
        collisions.HAVE_NUMBA = False
        want = hh.filter_reachable(x0, x0 + d, pairs)
    finally:
        collisions.HAVE_NUMBA = saved
    np.testing.assert_array_equal(got, want)


def test_swept_boxes_bound_every_instant():
    """``swept_boxes`` equals the numpy min / max over the edges' ends at the given instants."""
    from hairexp.physics.broad_phase import swept_boxes

    rng = np.random.default_rng(5)
    Ys = rng.normal(size=(3, 50, 3))
    E = np.stack([np.arange(49), np.arange(1, 50)], 1).astype(np.int64)
    lo, hi = swept_boxes(Ys, E, 0.25)
    P = np.stack([Y[E[:, k]] for Y in Ys for k in (0, 1)], 1)
    np.testing.assert_array_equal(lo, P.min(1) - 0.25)
    np.testing.assert_array_equal(hi, P.max(1) + 0.25)


def test_near_pairs_compiled_equal_numpy():
    """``HairHair.near_pairs`` (the neighbour list's build) gives the same pairs and distances
    with the compiled grid and distances as with the cKDTree and numpy path."""
    import hairexp.physics.collisions as collisions

    rng = np.random.default_rng(11)
    n, k = 40, 12
    roots = rng.uniform(-0.01, 0.01, (n, 2))
    pts = np.concatenate([np.c_[np.full(k, r[0]), -np.linspace(0, 0.1, k), np.full(k, r[1])] for r in roots])
    pts += 5e-4 * rng.normal(size=pts.shape)
    s = Strands.from_polylines(pts, [k] * n, 1e-3)
    hh = HairHair(s, thickness=0.001)
    got_p, got_d = hh.near_pairs(pts, 0.004)
    saved = collisions.HAVE_NUMBA
    try:
        collisions.HAVE_NUMBA = False
        want_p, want_d = hh.near_pairs(pts, 0.004)
    finally:
        collisions.HAVE_NUMBA = saved
    assert len(got_p) > 100
    got = dict(zip(map(tuple, np.sort(got_p, 1).tolist()), got_d))
    want = dict(zip(map(tuple, np.sort(want_p, 1).tolist()), want_d))
    assert got.keys() == want.keys()
    np.testing.assert_allclose([got[p] for p in want], [want[p] for p in want], rtol=0, atol=1e-15)


def test_later_passes_test_only_pairs_the_last_pass_changed(monkeypatch):
    """A dense wisp jerked through a crossing one (several passes with contacts): the collision
    stage whose later passes test only pairs with an edge the pass before moved or slowed ends
    where the stage that re-tests every pair ends (to round-off), and its later passes test
    fewer pairs."""
    from hairexp.model.scene import Material, Scene
    from hairexp.physics.collisions import collision_stage

    rng = np.random.default_rng(2)
    n, k = 10, 24
    zs = np.linspace(-0.06, 0.06, k)
    A = [np.stack([np.full(k, 0.002 * i), np.full(k, -0.01), zs], 1) for i in range(n)]
    B = [np.stack([zs, np.full(k, 0.002 * i), np.full(k, 0.01)], 1) for i in range(n)]
    pts = np.concatenate(A + B)
    s = Strands.from_polylines(pts, [k] * (2 * n), 2e-4)
    scene = Scene("cross", s, Material(2e-4, 20.0, 2e-6), RigidMotion.static(), np.zeros(3), pts)
    x0 = pts.copy()
    x1 = x0 + 1e-4 * rng.normal(size=x0.shape)
    x1[: n * k, 1] += 0.03              # the first wisp sweeps up through the second
    x1[s.kinematic] = x0[s.kinematic]
    cc = OmegaConf.structured(CollisionConfig(objects=False, hair_hair=True, hair_thickness=0.001, max_passes=4))
    seen = {}
    orig = HairHair.neighbours

    def spy(tag):
        def neighbours(self, Ys, active=None):
            pairs, how = orig(self, Ys, None if tag == "all" else active)
            seen.setdefault(tag, []).append(len(pairs))
            return pairs, how
        return neighbours

    out = {}
    for tag in ("all", "active"):
        monkeypatch.setattr(HairHair, "neighbours", spy(tag))
        out[tag] = collision_stage(cc, scene, HairHair(s, 0.001), x0, x1.copy(), 0.0, DT, DT)
    (xa, va, ia), (xb, vb, ib) = out["all"], out["active"]
    assert ia.passes == ib.passes >= 2 and ia.hair_contacts == ib.hair_contacts > 0
    np.testing.assert_allclose(xb, xa, rtol=0, atol=1e-12)
    np.testing.assert_allclose(vb, va, rtol=0, atol=1e-10)
    assert seen["active"][0] == seen["all"][0] and sum(seen["active"][1:]) < sum(seen["all"][1:])


def test_list_frame_kernels_equal_scipy_and_numpy():
    """The list frame's pieces: ``rotation_matrix`` and ``rotation_vector`` are scipy's
    ``Rotation.from_rotvec`` and ``as_rotvec`` (tiny, ordinary and near-half-turn angles, a half
    turn), ``centred_cross`` the numpy centroids and cross
    covariance, and ``HairHair.frames`` the same positions with and without the kernels."""
    import hairexp.physics.collisions as collisions
    from scipy.spatial.transform import Rotation
    from hairexp.physics.broad_phase import centred_cross, rotation_matrix, rotation_vector

    rng = np.random.default_rng(8)
    for scale in (0.0, 1e-12, 1e-9, 1e-7, 1e-3, 0.5, 2.0, np.pi - 1e-7):
        for _ in range(50):
            rv = rng.normal(size=3)
            rv *= scale / np.linalg.norm(rv)
            np.testing.assert_allclose(rotation_matrix(rv), Rotation.from_rotvec(rv).as_matrix(), rtol=0, atol=1e-15)
            R = Rotation.from_rotvec(rv).as_matrix()
            np.testing.assert_allclose(rotation_vector(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-12)
    R = np.diag([1.0, -1.0, -1.0])                       # a half turn: rv and -rv are the same rotation
    np.testing.assert_allclose(Rotation.from_rotvec(rotation_vector(R)).as_matrix(), R, atol=1e-15)
    x0, x1 = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    c0, c1, H = centred_cross(x0, x1)
    np.testing.assert_allclose(c0, x0.mean(0), atol=1e-15)
    np.testing.assert_allclose(c1, x1.mean(0), atol=1e-15)
    np.testing.assert_allclose(H, (x0 - x0.mean(0)).T @ (x1 - x1.mean(0)), atol=1e-12)
    E = np.stack([np.arange(499), np.arange(1, 500)], 1)
    R = Rotation.from_rotvec([0.1, 0.4, -0.2]).as_matrix()
    y1 = x0 @ R.T + 0.3 + 1e-3 * x1
    got = HairHair(SimpleNamespace(edges=E, inverse_masses=np.ones(500)), 1e-3).frames(x0, y1)
    saved = collisions.HAVE_NUMBA
    try:
        collisions.HAVE_NUMBA = False
        want = HairHair(SimpleNamespace(edges=E, inverse_masses=np.ones(500)), 1e-3).frames(x0, y1)
    finally:
        collisions.HAVE_NUMBA = saved
    for a, b in zip(got, want):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


@pytest.mark.parametrize("with_start", [True, False])
def test_compiled_impulses_equal_the_numpy_ones(with_start):
    """``HairHair.impulses`` compiled (``broad_phase.contact_impulses``) and in numpy: the same
    pairs given impulses and the same velocities (to round-off) on a dense random wisp whose
    edges cross during the step (CCD hits) and end within the thickness (repulsion), some of
    them at the roots (infinite mass)."""
    import hairexp.physics.collisions as collisions

    rng = np.random.default_rng(4)
    n, k = 30, 10
    pts = np.concatenate([np.c_[np.full(k, x), -np.linspace(0, 0.05, k), np.full(k, z)]
                          for x, z in rng.uniform(-0.004, 0.004, (n, 2))])
    s = Strands.from_polylines(pts, [k] * n, 1e-3)
    hh = HairHair(s, thickness=0.002)
    x0 = pts.copy()
    v = 0.05 * rng.normal(size=x0.shape)
    v[s.kinematic] = 0.0
    x1 = x0 + DT * v
    pairs = hh.filter_reachable(x0, x1, hh.swept_pairs((x0, 0.5 * (x0 + x1), x1)))
    start = x0 if with_start else None
    got_v, got_n = hh.impulses(x1, v.copy(), pairs, DT, start)
    saved = collisions.HAVE_NUMBA
    try:
        collisions.HAVE_NUMBA = False
        want_v, want_n = hh.impulses(x1, v.copy(), pairs, DT, start)
    finally:
        collisions.HAVE_NUMBA = saved
    assert got_n == want_n > 20
    np.testing.assert_allclose(got_v, want_v, rtol=0, atol=1e-13)
    assert np.abs(got_v - v).max() > 1e-3      # the impulses did something


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_strain_limit_sweeps_equal_the_numpy_sweeps(seed):
    """``StrainLimit.apply``'s compiled sweeps (``limit_sweeps``: strand by strand) move every
    vertex bit for bit as the numpy sweeps (all strands' k-th edges at once) do, with strands of
    different lengths, pinned vertices (two pinned ends of an edge both move) and edges both
    stretched and crushed; the count of edges outside is the same."""
    from hairexp.physics.collisions import StrainLimit
    from hairexp.physics.kernels import HAVE_NUMBA

    if not HAVE_NUMBA:
        pytest.skip("numba not importable: only the numpy sweeps run")
    rng = np.random.default_rng(seed)
    counts = rng.integers(3, 14, size=9)
    pts = []
    for k, c in enumerate(counts):
        pts.append(np.c_[np.full(c, 0.01 * k), -0.01 * np.arange(c), np.zeros(c)])
    s = Strands.from_polylines(np.concatenate(pts), counts, 1e-3)
    x = s.rest + rng.normal(scale=0.003, size=s.rest.shape)   # edges up to +-60 % off their rest length
    x[s.kinematic] = s.rest[s.kinematic]
    x[s.offsets[3]:s.offsets[4]] = s.rest[s.offsets[3]:s.offsets[4]]   # one strand within the limit: not visited
    pinned = rng.random(len(x)) < 0.2
    for pin in (None, pinned):
        lim = StrainLimit(s, 0.1)
        a, b = x.copy(), x.copy()
        lim.compiled = False
        na = lim.apply(a, pin)
        lim.compiled = True
        nb = lim.apply(b, pin)
        assert na == nb > 0
        assert np.array_equal(a, b)
        assert not np.array_equal(a, x)


@pytest.mark.parametrize("off", [0.0, 0.001])
@pytest.mark.parametrize("shape", ["sphere", "capsule", "box", "cylinder"])
def test_an_edge_across_a_collider_between_its_vertices_is_pushed_out(shape, off):
    """A collider that rises into a hanging strand between two of its vertices (every vertex stays
    outside): the vertex response sees nothing and the edge runs through the shape; with
    ``collision.edge_response`` (the default) the stage pushes the edge out: no point of any edge
    deeper than the shell's tolerance, no vertex inside, edge lengths nearly kept (the push
    turns the edge and its neighbours), the roots unmoved."""
    from hairexp.physics.collisions import collision_stage

    kw = {"sphere": dict(radius=0.006), "capsule": dict(radius=0.004, half_length=0.02),
          "box": dict(half_extents=[0.004, 0.004, 0.02]), "cylinder": dict(radius=0.004, half_height=0.02)}[shape]
    n = 12
    probe = make_scene([], None, n_strands=1, n_vertices=n, length=0.22, direction=[0.0, -1.0, 0.0], root_radius=1e-5)
    X = probe.strands.rest
    mid = 0.5 * (X[6] + X[7])   # between vertices 6 and 7 (edge 0.02 m)
    # the shape lies across the strand (its long axis along z), its centre on the edge's midpoint, moved in
    # from 1 cm to the side (x) over the step, so that the vertices' paths never come within its shell
    rot = (90.0, 0.0, 0.0) if shape in ("capsule", "cylinder") else (0.0, 0.0, 0.0)
    # (off 0: the edge through the shape's centre or axis, where the closest point has no normal)
    cfg = _rising(collider(shape, thickness=0.001, friction=0.0, **kw), tuple(mid + [0.012, 0.0, 0.0]),
                  tuple(mid + [off, 0.0, 0.0]), rot, rot)
    scene = make_scene([cfg], None, n_strands=1, n_vertices=n, length=0.22, direction=[0.0, -1.0, 0.0], root_radius=1e-5)
    col, s = scene.colliders[0], scene.strands
    x0 = s.rest.copy()
    free = ~s.kinematic
    assert col.distance(x0[free], 0.0).min() > 0 and col.distance(x0[free], DT).min() > 0
    results = {}
    for on in (False, True):
        cc = OmegaConf.structured(CollisionConfig(objects=True, hair_hair=False, edge_response=on, resolve=False))
        out, v, info = collision_stage(cc, scene, None, x0, x0.copy(), 0.0, DT, DT)
        results[on] = (_deepest_edge(scene, out, DT), info)
        assert col.distance(out[free], DT).min() >= -1e-9
        assert np.array_equal(out[s.kinematic], x0[s.kinematic])
        if on:
            strain = np.abs(np.linalg.norm(out[s.edges[:, 1]] - out[s.edges[:, 0]], axis=1) / s.rest_lengths - 1)
            assert strain.max() < 0.2
    assert results[False][0] > 1e-3 and results[False][1].edge_contacts == 0   # 1-6 mm through the shape without it
    assert results[True][0] <= col.shell_tolerance() and results[True][1].edge_contacts > 0
    assert results[True][1].object_contacts >= results[True][1].edge_contacts
    if HAVE_NUMBA:   # the numpy path (candidates, path tests, sweeps) gives the compiled one's pushes
        import hairexp.physics.collisions as collisions_module

        saved = collisions_module.HAVE_NUMBA
        try:
            collisions_module.HAVE_NUMBA = False
            out_np, _, info_np = collision_stage(cc, scene, None, x0, x0.copy(), 0.0, DT, DT)
        finally:
            collisions_module.HAVE_NUMBA = saved
        np.testing.assert_allclose(out_np, out, rtol=0, atol=1e-12)
        assert info_np.edge_contacts == results[True][1].edge_contacts


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba not installed")
def test_edge_candidates_kernel_is_the_numpy_selection():
    """collisions._edge_candidates (edge_response's compiled candidate pass) selects exactly the
    edges of the numpy expression: tested, both gaps above -tol, (g_a + g_b)/2 - half below -tol;
    on random strands whose gaps straddle the thresholds."""
    from hairexp.physics.collisions import _edge_candidates

    rng = np.random.default_rng(3)
    V = 400
    x = rng.normal(scale=0.01, size=(V, 3))
    E = np.stack([np.arange(V - 1), np.arange(1, V)], axis=1)
    E = E[rng.random(len(E)) < 0.9]
    a, b = E[:, 0], E[:, 1]
    tol = 2e-6
    half = 0.5 * np.linalg.norm(x[b] - x[a], axis=1)
    for trial in range(5):
        g = rng.uniform(-0.5, 1.5, size=V) * half.mean()
        g[rng.random(V) < 0.1] = -tol   # on the threshold
        test = rng.random(len(E)) < 0.8
        ga, gb = g[a], g[b]
        ref = np.flatnonzero(test & (ga > -tol) & (gb > -tol) & (0.5 * (ga + gb) - half < -tol))
        out = np.empty(len(E), dtype=np.int64)
        n = _edge_candidates(x, a, b, g, test, tol, out)
        assert 0 < ref.size < test.sum()
        np.testing.assert_array_equal(out[:n], ref)


@pytest.mark.parametrize("make, key, said", [
    (lambda m: Sphere("b", m, radius=float("nan")), "colliders.b.radius", "must be a finite number > 0"),
    (lambda m: Sphere("b", m, radius=-1.0), "colliders.b.radius", "must be a finite number > 0"),
    (lambda m: Sphere("b", m, radius=None), "colliders.b.radius", "must be a real number"),
    (lambda m: Sphere("b", None), "colliders.b.motion", "must be a RigidMotion"),
    (lambda m: Sphere("b", m, thickness="1"), "colliders.b.thickness", "must be a real number"),
    (lambda m: Capsule("c", m, half_length=0.0), "colliders.c.half_length", "must be a finite number > 0"),
    (lambda m: Cylinder("w", m, half_height=float("inf")), "colliders.w.half_height", "must be a finite number > 0"),
    (lambda m: Cylinder("w", m, spin=None), "colliders.w.spin", "must be a real number"),
    (lambda m: Box("x", m, half_extents=(0.1, 0.0, 0.1)), "colliders.x.half_extents", "must be 3 finite numbers > 0"),
])
def test_collider_classes_refuse_bad_sizes(make, key, said):
    """The Python classes took a NaN or negative radius (hair passed through a sphere of radius NaN
    without a contact), None sizes and motions failed at the first step in the barrier (an outside
    probe, 2026-12-07): the API refuses them as the config does, naming the field."""
    with pytest.raises(InputError, match=said) as err:
        make(RigidMotion.static())
    assert err.value.where == key
