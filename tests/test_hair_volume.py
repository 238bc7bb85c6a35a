"""The volumetric hair-hair model (``collision.hair_hair_model=volume``,
hairexp/physics/hair_volume.py): conservation and dissipation of its friction, its pressure
gradient against finite differences, its response to over-dense hair, its limits and a run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hairexp.app.config import compose_config
from hairexp.app.validate import validate_config
from hairexp.errors import InputError, SimulationError
from hairexp.physics import hair_volume as hv_mod
from hairexp.physics.hair_volume import HairVolume


def _hair(V, seed=0, kinematic=None):
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.5e-5, 2e-5, V)
    k = np.zeros(V, dtype=bool) if kinematic is None else kinematic
    # rest: what the model's grid check reads (the tests give their own positions to apply)
    return SimpleNamespace(masses=m, kinematic=k, rest=np.zeros((V, 3))), rng


def test_friction_conserves_momentum_and_never_adds_kinetic_energy():
    s, rng = _hair(500)
    x = rng.uniform(0, 0.05, (500, 3))
    v = rng.normal(size=(500, 3))
    hv = HairVolume(s, 0.01, friction=5.0, pressure_speed=0.0)
    out, pressed = hv.apply(x, v, 0.04)
    m = s.masses[:, None]
    np.testing.assert_allclose((m * out).sum(0), (m * v).sum(0), rtol=1e-12, atol=1e-18)
    ke = lambda u: 0.5 * float((m * u ** 2).sum())   # noqa: E731
    assert ke(out) < ke(v) and pressed == 0
    assert np.abs(out - v).max() > 1e-3                 # it did act


def test_a_uniform_motion_is_left_alone():
    s, rng = _hair(300)
    x = rng.uniform(0, 0.05, (300, 3))
    v = np.tile([0.3, -1.0, 0.2], (300, 1))
    out, _ = HairVolume(s, 0.01, 5.0, 0.0).apply(x, v, 0.04)
    np.testing.assert_allclose(out, v, rtol=0, atol=1e-13)


def test_kinematic_roots_drag_but_are_not_moved():
    kin = np.zeros(200, dtype=bool)
    kin[:20] = True
    s, rng = _hair(200, kinematic=kin)
    x = rng.uniform(0, 0.03, (200, 3))
    v = np.zeros((200, 3))
    v[kin] = [1.0, 0.0, 0.0]
    out, _ = HairVolume(s, 0.01, 5.0, 0.0).apply(x, v, 0.04)
    np.testing.assert_array_equal(out[kin], v[kin])
    assert out[~kin, 0].mean() > 0                      # the free hair is dragged along


def test_pressure_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    h = 0.01
    dims = np.array([7, 8, 9], dtype=np.int64)
    M = rng.uniform(0, 3, int(dims.prod()))          # cell masses over M_0 = 1: p = max(M - 1, 0)
    P = np.zeros((len(M), 3))
    origin = np.zeros(3)
    x = rng.uniform(0.015, 0.045, (50, 3))

    def fields(y):
        i0 = np.empty(y.shape, dtype=np.int64)
        f = np.empty(y.shape)
        hv_mod._cell_weights(y, origin, 1 / h, i0, f, np.empty(3, dtype=np.int64))
        vg, pv, gp = np.empty(y.shape), np.empty(len(y)), np.empty(y.shape)
        hv_mod._gather(i0, f, dims, M, P, 1.0, 1 / h, vg, pv, gp)
        return pv, gp

    _, gp = fields(x)
    eps = 1e-7
    for a in range(3):
        e = np.zeros(3)
        e[a] = eps
        fd = (fields(x + e)[0] - fields(x - e)[0]) / (2 * eps)
        np.testing.assert_allclose(gp[:, a], fd, rtol=1e-5, atol=1e-4)


def test_over_dense_hair_is_pushed_out():
    """The first state sets rho_0; hair gathered denser than that is pushed down the density
    gradient, away from the clump."""
    s, rng = _hair(400)
    hv = HairVolume(s, 0.01, friction=0.0, pressure_speed=0.1)
    spread = rng.uniform(0, 0.1, (400, 3))
    hv.apply(spread, np.zeros((400, 3)), 0.04)          # rho_0 from the spread hair
    centre = np.array([0.05, 0.05, 0.05])
    clump = centre + rng.normal(scale=0.004, size=(400, 3))
    out, pressed = hv.apply(clump, np.zeros((400, 3)), 0.04)
    assert pressed > 300
    outward = np.einsum("ij,ij->i", out, clump - centre)
    assert (outward > 0).mean() > 0.8
    assert np.linalg.norm(out, axis=1).max() <= 0.01 / 0.04 * (1 + 1e-12)   # at most a cell per step


def test_a_grid_too_large_is_refused():
    s, rng = _hair(10)
    x = rng.uniform(0, 1.0, (10, 3))
    x[0] = [1e3, 1e3, 1e3]
    with pytest.raises(SimulationError, match="volume_cell"):
        HairVolume(s, 0.01, 1.0, 0.1).apply(x, np.zeros((10, 3)), 0.04)


def test_a_cell_too_small_for_the_hair_at_rest_is_bad_input_before_the_first_step():
    """The grid over the hair at rest is checked when the model is built (exit 2 naming
    collision.volume_cell), not at the first step (a simulation error, exit 3)."""
    s, rng = _hair(10)
    s.rest = rng.uniform(0, 0.3, (10, 3))
    with pytest.raises(InputError, match=r"collision\.volume_cell.*cells"):
        HairVolume(s, 1e-7, 1.0, 0.1)
    HairVolume(s, 0.01, 1.0, 0.1)   # 33^3 cells: fine


@pytest.mark.parametrize("key,value", [("collision.volume_cell", "0"), ("collision.volume_friction", "-1"),
                                       ("collision.volume_pressure_speed", "nan")])
def test_bad_volume_settings_name_the_key(key, value):
    cfg = compose_config(["experiment=goaling_smoke", "collision=hair_hair", "collision.hair_hair_model=volume",
                          f"{key}={value}"])
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        validate_config(cfg)


def test_a_run_with_the_volume_model(tmp_path):
    from hairexp.app.run import run

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=3", "logging=off",
                          "collision=hair_hair", "collision.hair_hair_model=volume"])
    s = run(cfg, tmp_path / "run")
    assert s["status"] == "completed" and s["converged"]
    with np.load(tmp_path / "run" / "result.npz") as r:
        assert np.isfinite(r["positions"]).all()


def test_the_volume_acts_once_a_step_over_the_whole_step(tmp_path, monkeypatch):
    """Under TR-BDF2 (two stages) the volume's friction and pressure act after the last stage,
    with the step's dt (not the stage's)."""
    from hairexp.app.run import run

    calls = []
    orig = HairVolume.apply
    monkeypatch.setattr(HairVolume, "apply", lambda self, x, v, dt: calls.append(dt) or orig(self, x, v, dt))
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging=off", "solver.integrator=trbdf2",
                          "collision=hair_hair", "collision.hair_hair_model=volume", "solver.dt=0.04"])
    s = run(cfg, tmp_path / "run")
    assert s["status"] == "completed"
    assert calls and len(calls) == s["steps"] and all(abs(c - 0.04) < 1e-12 for c in calls)


# -- the volume in the step: a velocity filter (positions untouched), the integrators' history ------

from omegaconf import OmegaConf  # noqa: E402

from hairexp.app.builders import build_scene  # noqa: E402
from hairexp.app.config import ColliderConfig, CollisionConfig, SceneConfig, SolverConfig  # noqa: E402
from hairexp.physics.integrators import BDF2, History  # noqa: E402
from hairexp.physics.simulator import Simulator  # noqa: E402

DT = 0.04
INTEGRATORS = ["implicit_euler", "bdf2", "trbdf2"]


def _jerked_wisp(colliders=(), direction=(0.0, -1.0, 0.0)):
    """40 strands x 12 vertices (30 cm, tilted up to 0.3 rad: they sag, gather and cross), the
    roots still for 0.08 s, then jerked up 3 cm in 0.08 s (every step converges without
    substeps under the three integrators, so a step is one solve and one filter)."""
    sc = OmegaConf.structured(SceneConfig(n_strands=40, n_vertices=12, length=0.3, spread=0.3,
                                          direction=list(direction)))
    sc.colliders = list(colliders)
    sc.motion.interpolation = "linear"
    sc.motion.times = [0.0, 0.08, 0.16, 10.0]
    sc.motion.translations = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.03, 0.0]]
    sc.motion.rotations_deg = [[0.0, 0.0, 0.0]] * 4
    return build_scene(sc)


def _sim(scene, integrator, volume: bool, restart_at_jumps: bool = True):
    solver = OmegaConf.structured(SolverConfig())
    solver.integrator = integrator
    solver.restart_at_jumps = restart_at_jumps
    cc = OmegaConf.structured(CollisionConfig(hair_hair=volume, hair_hair_model="volume"))
    return Simulator(scene, solver, collision_cfg=cc)


def _strain(scene, x):
    E, L = scene.strands.edges, scene.strands.rest_lengths
    return np.abs(np.linalg.norm(x[E[:, 1]] - x[E[:, 0]], axis=1) / L - 1.0)


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_a_volume_step_moves_no_position_and_changes_no_edge_length(integrator, monkeypatch):
    """From the same state, a step with the volume ends at the positions of the step without it
    (the same solve; no vertex moved, no edge length changed), the filter acted on the scheme's
    end velocity, and the state leaves with the filter's velocities (no collider here)."""
    scene = _jerked_wisp()
    off, vol = _sim(scene, integrator, False), _sim(scene, integrator, True)
    calls = []
    orig = HairVolume.apply

    def recording(self, x, v, dt):
        out = orig(self, x, v, dt)
        calls.append((x.copy(), v.copy(), out[0].copy()))
        return out

    monkeypatch.setattr(HairVolume, "apply", recording)
    st = off.initial_state()
    acted = 0.0
    for _ in range(8):
        ref, ref_info = off.step(st, DT)
        new, info = vol.step(st, DT)
        assert info.status == ref_info.status and info.iterations == ref_info.iterations
        x_seen, v_seen, v_out = calls[-1]
        np.testing.assert_array_equal(new.x, ref.x)                 # no position moved
        np.testing.assert_array_equal(x_seen, ref.x)                # it saw the solve's positions
        np.testing.assert_array_equal(_strain(scene, new.x), _strain(scene, ref.x))
        np.testing.assert_array_equal(v_seen, ref.v)                # the scheme's end velocity
        np.testing.assert_allclose(new.v, v_out, rtol=0, atol=1e-14)  # the state leaves with its output (v + dv)
        acted = max(acted, float(np.abs(v_out - v_seen).max()))
        st = ref
    assert len(calls) == 8 and acted > 1e-3                         # it did act (m/s)


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_with_the_volume_a_run_stretches_the_hair_as_little_as_without(integrator):
    """12 steps through the jerk: the largest edge strain with the volume stays within 1.2 x the
    run's without hair-hair.  Measured (2026-12-02), volume vs off: trbdf2 1.421e-4 vs 1.421e-4,
    bdf2 8.010e-5 vs 8.004e-5, implicit_euler 4.973e-5 vs 4.970e-5 (ratios <= 1.001); before the
    volume became a velocity filter (it moved each vertex to x_n + dt v): 3.42e-3 (24 x),
    3.05e-2 (381 x) and 3.19e-2 (641 x).  On celia_smoke free (trbdf2): 2.65e-4 with the volume
    and without, 2.54e-2 before."""
    scene = _jerked_wisp()
    worst = {}
    for volume in (False, True):
        sim = _sim(scene, integrator, volume)
        st, w = sim.initial_state(), 0.0
        for _ in range(12):
            st, _ = sim.step(st, DT)
            w = max(w, float(_strain(scene, st.x).max()))
        worst[volume] = w
    assert worst[True] <= 1.2 * worst[False]


def test_trbdf2_does_not_restart_after_the_velocity_filter():
    """The volume changes velocities only: TR-BDF2's next step starts with its trapezoidal stage
    (the implicit Euler restart is for positions a collision moved).  The jerk's velocity jumps
    restart it too (``solver.restart_at_jumps``): off here, to see the filter alone."""
    scene = _jerked_wisp()
    sim = _sim(scene, "trbdf2", True, restart_at_jumps=False)
    st = sim.initial_state()
    firsts, pressed = [], 0
    for _ in range(8):
        firsts.append(type(sim.integrator.stages(st, DT)[0][0]).__name__)
        st, info = sim.step(st, DT)
        pressed += info.hair_contacts
    assert pressed > 0 and set(firsts) == {"Trapezoidal"}


def test_the_volume_filters_a_restart_step_and_the_restart_stays_a_restart(monkeypatch):
    """At the jerk's velocity jumps (0.08 s, 0.16 s) the step is one implicit Euler step (a stage
    of its own): the volume filters it once, as the last stage of a step, and what the step
    carries is the restart mark (the next step starts with an implicit Euler stage)."""
    scene = _jerked_wisp()
    sim = _sim(scene, "trbdf2", True)
    calls = []
    orig = HairVolume.apply

    def counting(self, x, v, dt):
        calls.append(dt)
        return orig(self, x, v, dt)

    monkeypatch.setattr(HairVolume, "apply", counting)
    st, restarts = sim.initial_state(), 0
    for _ in range(6):
        n = len(calls)
        jump = scene.motion.velocity_jumps(st.time, st.time + DT, since=0.0)
        st, info = sim.step(st, DT)
        assert info.converged and len(calls) == n + 1 and calls[-1] == DT   # once a step, over the step
        if jump:
            restarts += 1
            assert st.history is not None and st.history.restart
    assert restarts == 2


@pytest.mark.parametrize("w", [1.0, 0.5, 2.0])
def test_bdf2_carries_a_velocity_change_into_the_next_step_exactly(w):
    """A free vertex moving at v whose velocity the filter changes by dv moves at v + dv from the
    next step on under BDF2 (history shifted: v_n += dv, x_n -= dt_n dv), at any step ratio
    w = dt / dt_n: predictor x_{n+1} + dt (v + dv), velocity v + dv, as implicit Euler."""
    rng = np.random.default_rng(1)
    dt_n = 0.04
    dt = w * dt_n
    v, dv = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    x_n = rng.normal(size=(5, 3))
    x1 = x_n + dt_n * v
    bdf2 = BDF2()
    h = bdf2.after_velocity_filter(None, History(x=x_n, v=v, dt=dt_n), dv)
    state = SimpleNamespace(x=x1, v=v + dv, history=h)
    p = bdf2.plan(None, state, dt)
    np.testing.assert_allclose(p.x_pred, x1 + dt * (v + dv), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bdf2.velocity(p.x_pred, state, p), v + dv, rtol=1e-10, atol=1e-12)


def test_object_contacts_see_the_solves_path_and_the_filter_never_drives_hair_into_a_collider():
    """Hair falling sideways onto a sphere: with the volume the step ends at the positions of the
    step without it (the object contacts saw the same path), and no vertex on the shell leaves
    the step with an approaching normal velocity."""
    ball = OmegaConf.structured(ColliderConfig(name="ball", shape="sphere", radius=0.05, thickness=0.002, friction=0.3))
    ball.motion.translations = [[0.15, -0.08, 0.0]]
    ball.motion.rotations_deg = [[0.0, 0.0, 0.0]]
    scene = _jerked_wisp([ball], direction=(1.0, 0.0, 0.0))
    off, vol = _sim(scene, "trbdf2", False), _sim(scene, "trbdf2", True)
    col = scene.colliders[0]
    free = ~scene.strands.kinematic
    st = off.initial_state()
    touched = 0
    for _ in range(12):
        ref, _ = off.step(st, DT)
        new, info = vol.step(st, DT)
        np.testing.assert_array_equal(new.x, ref.x)
        shell = free & col.on_shell(new.x, new.time)
        if shell.any():
            vn = np.sum(new.v[shell] * col.normal(new.x[shell], new.time), axis=1)
            assert vn.min() >= -1e-9
        touched += info.object_contacts
        st = ref
    assert touched > 0                                              # the hair did reach the ball


@pytest.mark.parametrize("pressure", [0.0, 0.1])
def test_compiled_filter_is_the_array_formula(pressure):
    """``HairVolume.apply``'s per-vertex update (``_filter``, numba) against the array formula it
    replaced (friction blend on the movable vertices, then the pressure's dv capped at a cell a
    step; the count of pressed movable vertices): equal to the last bit."""
    V = 600
    kin = np.zeros(V, dtype=bool)
    kin[::25] = True
    s, rng = _hair(V, seed=7, kinematic=kin)
    x = rng.uniform(0, 0.03, (V, 3))
    x[:200] = rng.uniform(0.01, 0.012, (200, 3))        # a dense knot: p > 0 there, some dv capped
    v = rng.normal(size=(V, 3))
    model = HairVolume(s, 0.004, 5.0, pressure)
    model.rho0 = 0.2 * V * 1e-5 / 0.004 ** 3 / 50      # below the knot's density: pressure acts
    dt = 0.04
    got, pressed = model.apply(x, v, dt)
    vg, pv, gp = model.fields(x, v)
    fv = ~kin
    want = v.copy()
    blend = 1.0 - np.exp(-5.0 * dt)
    want[fv] += blend * (vg[fv] - want[fv])
    n_pressed = 0
    if pressure > 0:
        dv = -dt * pressure ** 2 * gp[fv]
        n = np.linalg.norm(dv, axis=1)
        cap = 0.004 / dt
        assert (n > cap).any() and (n < cap).any()
        want[fv] += dv * np.minimum(1.0, cap / np.maximum(n, 1e-300))[:, None]
        n_pressed = int(np.count_nonzero(fv & (pv > 0)))
        assert n_pressed > 0
    np.testing.assert_array_equal(got, want)
    assert pressed == n_pressed
    np.testing.assert_array_equal(got[kin], v[kin])
