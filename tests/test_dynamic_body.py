"""The dynamic block on a rail (scene.body, hairexp/model/dynamic_body.py) and the stylization
scene (paper 4, Fig. 7): the block's own dynamics (rest, rail end, friction, lift-off), the
staggered coupling with the hair (rest, free fall, momentum bookkeeping, stability for the scene's
mass ratio, substep retries), bad input, the measure and a smoke run of experiment=stylization_smoke."""

from __future__ import annotations

import os
import subprocess
import sys

from dataclasses import replace

import numpy as np
import pytest
from omegaconf import OmegaConf

from helpers import CONF_DIR, REPO, scene_cfg, solver_cfg
from hairexp.control.tracking.controller import TrackingController
from hairexp.app.config import BodyConfig, GuideEditConfig
from hairexp.errors import InputError
from hairexp.physics.info import MAX_ITERATIONS
from hairexp.physics.simulator import Simulator
from hairexp.app.builders import build_scene
from hairexp.model.dynamic_body import HAIR_FORCE, POSITION, RAIL_FORCE, VELOCITY, DynamicBody
from hairexp.model.rigid import RigidMotion
from hairexp.evaluation.stylization import block_rail_measure

G = 9.81
GRAV = np.array([0.0, -G, 0.0])


def bare_block(p0=(0.0, 0.0, 0.0), u0=(0.0, 0.0, 0.0), mass=0.05, rail_height=0.0, rail_end=0.1, mu=0.3):
    return DynamicBody(np.eye(3), np.array(p0, float), np.array(u0, float), mass, 0.0, GRAV, rail_height, rail_end, mu)


def advance_many(body, n, dt, force=(0.0, 0.0, 0.0)):
    b = body.initial(np.asarray(force, float))
    out = [b]
    for _ in range(n):
        b = body.with_hair_force(body.advance(b, dt), np.asarray(force, float))
        out.append(b)
    return np.array(out)


def dyn_scene(body: dict, **kw):
    """A small wisp on a dynamic block (scene_cfg with ``scene.body``)."""
    cfg = scene_cfg(**kw)
    cfg.body = OmegaConf.structured(BodyConfig(dynamic=True, **body))
    return build_scene(cfg)


def hair_mass(scene):
    s = scene.strands
    return float(s.masses[~s.kinematic].sum())


def total_momentum(scene, state):
    s, b = scene.strands, state.body
    free = ~s.kinematic
    return scene.motion.total_mass * b[VELOCITY] + (s.masses[free, None] * state.v[free]).sum(0)


# -- the block alone -----------------------------------------------------------------------------

def test_block_without_hair_rests_on_the_rail():
    body = bare_block(p0=(0.02, 0.3, 0.0), rail_height=0.3, mu=0.0)
    traj = advance_many(body, 200, 0.01)
    assert np.array_equal(traj[:, POSITION], np.tile([0.02, 0.3, 0.0], (201, 1)))     # no drift at all
    assert np.array_equal(traj[:, VELOCITY], np.zeros((201, 3)))
    assert np.allclose(traj[1:, RAIL_FORCE], [0.0, 0.05 * G, 0.0], rtol=1e-12, atol=0)  # the rail carries its weight


def test_block_past_the_rail_end_falls_as_g_t2_over_2():
    dt, n = 1e-3, 400
    body = bare_block(p0=(0.1005, 0.0, 0.0), u0=(0.2, 0.0, 0.0), rail_end=0.1)
    traj = advance_many(body, n, dt)
    t = dt * np.arange(n + 1)
    y = traj[:, POSITION][:, 1]
    k = np.arange(n + 1)
    assert np.allclose(y, -G * dt ** 2 * k * (k + 1) / 2, rtol=0, atol=1e-12)    # symplectic Euler, exactly
    assert np.all(np.abs(y + G * t ** 2 / 2) <= G * t * dt / 2 + 1e-12)          # g t^2 / 2 to O(dt)
    assert abs(y[-1] + G * t[-1] ** 2 / 2) / (G * t[-1] ** 2 / 2) < 3e-3
    assert np.allclose(traj[:, POSITION][:, 0], 0.1005 + 0.2 * t, atol=1e-12)   # x keeps its velocity
    assert np.all(traj[1:, RAIL_FORCE] == 0)


def test_block_slides_off_the_end_of_a_frictionless_rail():
    dt = 1e-3
    body = bare_block(p0=(0.0, 0.0, 0.0), u0=(0.5, 0.0, 0.0), rail_end=0.1, mu=0.0)
    traj = advance_many(body, 400, dt)
    x, y = traj[:, POSITION][:, 0], traj[:, POSITION][:, 1]
    on = x <= 0.1
    assert np.all(y[on] == 0.0) and y[-1] < -0.01            # held while over the rail, falls after its end
    first_off = int(np.argmax(~on))
    assert y[first_off] == 0.0 and y[first_off + 1] < 0.0     # the step that leaves the rail started on it


def test_rail_friction_decelerates_the_block_at_mu_g():
    dt, mu, u0 = 1e-3, 0.4, 1.0
    body = bare_block(u0=(u0, 0.0, 0.0), mu=mu, rail_end=10.0)
    traj = advance_many(body, 400, dt)
    vx = traj[:, VELOCITY][:, 0]
    stop = u0 / (mu * G)                                    # 0.255 s
    k = int(stop / dt)
    assert np.allclose(np.diff(vx[:k]), -mu * G * dt, rtol=1e-9, atol=0)   # exactly mu g while it slides
    assert np.all(vx[k + 1:] == 0.0)                                     # then it sticks, no reversal
    assert np.allclose(traj[1:k, RAIL_FORCE][:, 0], -mu * 0.05 * G, rtol=1e-9)
    x_end = traj[-1, POSITION][0]
    assert abs(x_end - u0 ** 2 / (2 * mu * G)) < u0 * dt                  # stopping distance u0^2 / (2 mu g)


def test_static_friction_holds_a_pulled_block_until_mu_times_the_normal_force():
    body = bare_block(mu=0.5, rail_end=10.0)
    held = advance_many(body, 50, 0.01, force=(0.49 * 0.05 * G, 0.0, 0.0))     # just below mu M g
    assert np.all(held[:, POSITION] == 0.0)
    slid = advance_many(body, 50, 0.01, force=(0.51 * 0.05 * G, 0.0, 0.0))
    assert slid[-1, POSITION][0] > 0 and np.all(slid[:, POSITION][:, 1] == 0.0)


def test_block_lifts_off_when_pulled_up_harder_than_its_weight():
    W = 0.05 * G
    stays = advance_many(bare_block(), 50, 0.01, force=(0.0, 0.9 * W, 0.0))
    assert np.all(stays[:, POSITION] == 0.0) and np.allclose(stays[1:, RAIL_FORCE][:, 1], 0.1 * W)
    lifts = advance_many(bare_block(), 50, 0.01, force=(0.0, 1.1 * W, 0.0))
    y = lifts[:, POSITION][:, 1]
    assert np.all(np.diff(y) > 0) and np.all(lifts[1:, RAIL_FORCE] == 0.0)
    assert np.isclose(y[-1], 0.1 * G * 0.01 ** 2 * 50 * 51 / 2)           # unilateral: it never pulls back


def test_pose_is_linear_within_the_step_and_unknown_outside_it():
    body = bare_block(u0=(1.0, 0.0, 0.0), mu=0.0)
    b0 = body.initial(np.zeros(3))
    b1 = body.advance(b0, 0.1)
    w = body.window(1.0, b0, 1.1, b1)
    R, T = w.pose(1.05)
    assert np.array_equal(R, np.eye(3)) and np.allclose(T, [0.05, 0.0, 0.0])
    assert np.allclose(w.velocity(1.1)[1], [1.0, 0.0, 0.0])
    X = np.array([[0.0, -0.1, 0.0]])
    assert np.allclose(w.to_body(w.transform(X, 1.07), 1.07), X)
    assert np.allclose(w.point_velocity(X, 1.02), [[1.0, 0.0, 0.0]])
    with pytest.raises(RuntimeError, match="within the step"):
        w.pose(0.9)
    with pytest.raises(RuntimeError, match="within the step"):
        w.pose(1.2)


# -- block and hair --------------------------------------------------------------------------------

def test_block_on_rail_with_hanging_hair_stays_at_rest():
    """Hanging hair at rest on a block on a frictionless rail: no drift; the rail carries block,
    roots and hair, and the hair's force settles to its weight."""
    scene = dyn_scene(dict(mass=0.01, rail_height=0.0, rail_end=0.1, rail_friction=0.0), n_strands=5, n_vertices=10)
    sim = Simulator(scene, solver_cfg(rtol=1e-10))
    state = sim.initial_state()
    x0 = state.x.copy()
    for _ in range(60):
        state, info = sim.step(state, 0.04)
        assert info.converged
    b = state.body
    # at rest to round-off: 8e-16 m after 60 steps under trbdf2 (the hair's sideways force from its
    # two stages is a few ulps, not exactly 0 as under implicit Euler); 1e-12 m would be a drift
    assert np.abs(b[POSITION]).max() <= 1e-12 and np.abs(b[VELOCITY]).max() <= 1e-12
    assert np.max(np.abs(state.x - x0)) < 1e-4                     # the hair only sags under its weight
    assert np.allclose(b[HAIR_FORCE], hair_mass(scene) * GRAV, rtol=1e-4, atol=1e-12)
    M_all = scene.motion.total_mass + hair_mass(scene)
    assert np.isclose(b[RAIL_FORCE][1], M_all * G, rtol=1e-4)


@pytest.mark.parametrize("integrator", ["implicit_euler", "trbdf2"])
def test_block_and_hair_fall_together_past_the_rail_end(integrator):
    """Implicit Euler and symplectic Euler fall by dt^2 g n (n + 1)/2 after n steps; trbdf2 and
    its block (theta = 1/2) fall exactly, g (n dt)^2 / 2.  Either way block and hair together."""
    scene = dyn_scene(dict(mass=0.01, rail_end=-0.05), n_strands=4, n_vertices=8, spread=0.3)
    sim = Simulator(scene, solver_cfg(rtol=1e-10, integrator=integrator))
    state = sim.initial_state()
    x0, dt = state.x.copy(), 0.02

    def drop(n):
        return -G * dt ** 2 * (n * (n + 1) / 2 if integrator == "implicit_euler" else n * n / 2)

    for n in range(1, 31):
        state, _ = sim.step(state, dt)
        b = state.body
        assert np.isclose(b[POSITION][1], drop(n), rtol=0, atol=1e-8)
    assert np.linalg.norm(b[HAIR_FORCE]) < 1e-8                        # free fall: no internal forces
    assert np.allclose(state.x, x0 + [0.0, drop(30), 0.0], atol=1e-8)      # the wisp falls rigidly with it


def test_sliding_block_with_light_hair_decelerates_at_about_mu_g():
    mu = 0.3
    scene = dyn_scene(dict(mass=0.01, rail_end=10.0, rail_friction=mu, velocity=[0.5, 0.0, 0.0]),
                      n_strands=3, n_vertices=8)
    assert hair_mass(scene) / scene.motion.mass < 0.01
    sim = Simulator(scene, solver_cfg())
    state = sim.initial_state()
    v = [0.5]
    for _ in range(12):                                    # 0.12 s: it stops after 0.17 s
        state, _ = sim.step(state, 0.01)
        v.append(state.body[VELOCITY][0])
    decel = -np.diff(v) / 0.01
    assert np.allclose(decel, mu * G, rtol=0.03)


def _momentum_run(controller: str, n: int = 25, dt: float = 0.02, integrator: str = "implicit_euler"):
    """Tilted strands with edge damping on a block sliding on a rail with friction; tracked: one
    guide that turns 30 degrees about its root (the tracker pushes the hair)."""
    from tracking_helpers import tracked_cfg

    cfg = tracked_cfg({"solver.integrator": integrator,
        "controller.name": controller, "scene.n_strands": 4, "scene.n_vertices": 8, "scene.length": 0.2,
        "scene.spread": 0.6, "scene.hair.edge_damping": 1e-4, "scene.body.dynamic": True, "scene.body.mass": 0.01,
        "scene.body.rail_end": 10.0, "scene.body.rail_friction": 0.3, "scene.body.velocity": [0.3, 0.0, 0.1],
        "solver.rtol": 1e-10, "tracking.rtol": 1e-10, "tracking.points_per_guide": 3,
        "guides.edits": [GuideEditConfig(guide=0, kind="rotate", axis=[0.0, 0.0, 1.0], angle_deg=30.0,
                                         times=[0.0, 0.8], weights=[0.0, 1.0])],
    })
    scene = build_scene(cfg.scene)
    tracking = guides = None
    if controller == "tracking":
        from hairexp.app.guides import build_guides

        guides = build_guides(cfg, scene, cfg.frames, cfg.fps)
        tracking = cfg.tracking
    sim = Simulator(scene, cfg.solver, TrackingController(scene, guides, tracking) if tracking is not None else None)
    states = [sim.initial_state()]
    for _ in range(n):
        s, info = sim.step(states[-1], dt)
        assert info.converged
        states.append(s)
    return scene, states, dt


@pytest.mark.parametrize("controller", ["free", "tracking"])
def test_momentum_of_block_and_hair_changes_by_gravity_rail_and_tracking_only(controller):
    """Per step: P(n+1) - P(n) = dt (M_all g + F_rail + F_tracking + F_hair(n) - F_hair(n+1)); the
    last two are the coupling lag, which telescopes: over the run it is dt (F_hair(0) - F_hair(N))."""
    scene, states, dt = _momentum_run(controller)
    s = scene.strands
    M_all = scene.motion.total_mass + hair_mass(scene)
    P = np.array([total_momentum(scene, st) for st in states])
    B = np.array([st.body for st in states])
    control = np.zeros((len(states), 3))
    if controller == "tracking":           # the tracker's force on the hair: -A^T lambda, summed
        control[1:] = [-st.control.lam.reshape(-1, 3).sum(0) for st in states[1:]]
    ext = dt * (M_all * GRAV + B[1:, RAIL_FORCE] + control[1:])
    lag = dt * (B[:-1, HAIR_FORCE] - B[1:, HAIR_FORCE])
    scale = M_all * 0.3
    assert np.abs(np.diff(P, axis=0) - ext - lag).max() < 1e-8 * scale
    total = P[-1] - P[0] - ext.sum(0)
    assert np.allclose(total, dt * (B[0, HAIR_FORCE] - B[-1, HAIR_FORCE]), rtol=0, atol=1e-8 * scale)
    assert np.abs(total).max() > 1e3 * 1e-8 * scale            # the lag term is real (and bounded)
    assert np.abs(B[:, RAIL_FORCE][:, 0]).max() > 0            # friction acted
    if controller == "tracking":
        assert np.abs(control).max() > 1e-4                    # and the tracker too
    assert np.abs(B[-1, VELOCITY] - B[0, VELOCITY]).max() > 1e-2   # the block moved and slowed


@pytest.mark.parametrize("controller", ["free", "tracking"])
def test_bdf2_momentum_of_block_and_hair_balances_in_the_schemes_own_momentum(controller):
    """BDF2 (hairexp/physics/integrators.py) balances M (v_{n+1} - 4/3 v_n + 1/3 v_{n-1}) = beta F with
    beta = 2 dt / 3, i.e. P~_{n+1} - P~_n = dt F with the scheme's momentum P~_n = M (3/2 v_n - 1/2 v_{n-1})
    (the first step is implicit Euler: M (v_1 - v_0) = dt F).  The block is advanced as before, so per
    step: dP~_hair + dP_block = dt (M_all g + F_rail + F_tracking) + the coupling lag, as for implicit Euler."""
    scene, states, dt = _momentum_run(controller, integrator="bdf2")
    s = scene.strands
    free = ~s.kinematic
    m = s.masses[free, None]
    M_all = scene.motion.total_mass + hair_mass(scene)
    V = np.array([st.v[free] for st in states])
    B = np.array([st.body for st in states])
    dP_hair = np.empty((len(states) - 1, 3))
    dP_hair[0] = (m * (V[1] - V[0])).sum(0)
    dP_hair[1:] = (m * (1.5 * V[2:] - 2.0 * V[1:-1] + 0.5 * V[:-2])).sum(1)
    dP = dP_hair + scene.motion.total_mass * np.diff(B[:, VELOCITY], axis=0)
    control = np.zeros((len(states), 3))
    if controller == "tracking":
        control[1:] = [-st.control.lam.reshape(-1, 3).sum(0) for st in states[1:]]
    ext = dt * (M_all * GRAV + B[1:, RAIL_FORCE] + control[1:])
    lag = dt * (B[:-1, HAIR_FORCE] - B[1:, HAIR_FORCE])
    scale = M_all * 0.3
    assert np.abs(dP - ext - lag).max() < 1e-8 * scale
    # the implicit-Euler momentum does not balance under BDF2 (the check can tell the two apart)
    dP_ie = (m * np.diff(V, axis=0)).sum(1) + scene.motion.total_mass * np.diff(B[:, VELOCITY], axis=0)
    assert np.abs(dP_ie - ext - lag).max() > 1e3 * 1e-8 * scale
    if controller == "tracking":
        assert np.abs(control).max() > 1e-4


def _kicked_free_fall(mass: float, steps: int, build_check: bool = True, integrator: str = "implicit_euler"):
    """The stylization wisp (40 x 20) falling with its block (past the rail end); the hair
    force carried into the first step is set wrong by the hair's weight (upward)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=stylization", "scene.body.rail_end=-1.0",
                                                       f"solver.integrator={integrator}"])
    GlobalHydra.instance().clear()
    if build_check:
        cfg.scene.body.mass = mass
        scene = build_scene(cfg.scene)
    else:  # below the limit build_dynamic_body refuses: make the block by hand
        scene = build_scene(cfg.scene)
        b = scene.motion
        scene = replace(scene, motion=DynamicBody(b.R, b.p0, b.u0, mass, b.carried_mass, b.gravity, b.rail_height,
                                                  b.rail_end, b.friction))
    sim = Simulator(scene, cfg.solver)
    state = sim.initial_state()
    kick = -hair_mass(scene) * GRAV
    state.body[HAIR_FORCE] = kick
    F = []
    for _ in range(steps):
        state, _ = sim.step(state, 0.04)
        F.append(np.linalg.norm(state.body[HAIR_FORCE]))
    return scene, np.array(F) / np.linalg.norm(kick)


def test_coupling_is_stable_for_the_stylization_mass_ratio():
    """A wrong coupling force decays geometrically when the block outweighs the hair: about
    m_hair / m_block per step in the stiff (axial) direction.  A block lighter than the hair (which
    build_dynamic_body refuses) amplifies it: the test can tell the two apart."""
    scene, F = _kicked_free_fall(0.05, 10)                           # the scene's block: 23 x the hair
    ratio = scene.motion.total_mass / hair_mass(scene)
    assert ratio > 20
    assert F[0] < 0.1 and F[6:].max() < 1e-6                     # gone within a few steps
    _, F15 = _kicked_free_fall(1.5 * 0.0022, 12)                   # 1.5 x the hair (with roots 1.6 x)
    assert F15.max() < 1.0 and F15[-1] < 1e-3                     # decays, slower
    assert np.all(F15[1:] <= F15[:-1] * 0.9)                       # monotone, no growing oscillation
    _, Fbad = _kicked_free_fall(0.8 * 0.0022, 8, build_check=False)    # 0.8 x the hair (0.9 with roots)
    assert np.all(np.diff(Fbad) > 0) and Fbad[-1] > 5.0          # grows


def test_trbdf2_coupling_is_stable_from_three_times_the_hair_and_refused_below():
    """trbdf2 (the default): the stylization block (23 x) and a block 3 x the hair damp a wrong
    coupling force; a block 2 x the hair (stable under implicit Euler) is refused before the
    first step, naming scene.body.mass (integrators.py min_body_ratio)."""
    _, F = _kicked_free_fall(0.05, 10, integrator="trbdf2")
    assert F[0] < 0.1 and F[6:].max() < 1e-4
    _, F3 = _kicked_free_fall(3 * 0.0022, 12, integrator="trbdf2")
    assert F3[-4:].max() < 0.25 * F3[:4].max()            # decays (slowly: about 5 x over 12 steps)
    with pytest.raises(InputError) as e:
        _kicked_free_fall(2 * 0.0022, 2, integrator="trbdf2")
    assert e.value.where == "scene.body.mass" and "trbdf2" in str(e.value)


@pytest.mark.parametrize("controller", ["free", "tracking"])
def test_a_retried_step_restarts_the_block_from_the_state(controller):
    """A step that fails and is retried as two half steps gives what two half steps give: the block's
    state travels in State.control, the failed attempt leaves nothing behind."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["experiment=stylization_smoke", f"controller={controller}",
                                                       "scene.body.velocity=[0.3,0.0,0.0]",
                                                       "scene.body.rail_friction=0.3"])
    GlobalHydra.instance().clear()
    from hairexp.app.assemble import assemble

    def make():
        return assemble(cfg).simulator

    dt = 0.04
    split = make()
    real_solve = split._attempt

    def failing_solve(state, h):   # every full step fails; its half steps succeed
        new, info = real_solve(state, h)
        if h > 0.75 * dt:
            info.status = MAX_ITERATIONS
        return new, info

    split._attempt = failing_solve
    halves = make()
    a, b = split.initial_state(), halves.initial_state()
    for _ in range(6):
        a, info = split.step(a, dt)
        assert info.substeps == 2 and info.recovered
        b, _ = halves.step(b, dt / 2)
        b, _ = halves.step(b, dt / 2)
    assert np.allclose(a.body, b.body, rtol=0, atol=1e-12)
    assert np.allclose(a.x, b.x, rtol=0, atol=1e-12)
    if controller == "free":   # and the block's path depends on the step: the comparison is not void
        whole = make()
        c = whole.initial_state()
        for _ in range(6):
            c, _ = whole.step(c, dt)
        assert np.abs(a.body[POSITION] - c.body[POSITION]).max() > 1e-6


# -- input -------------------------------------------------------------------------------------

BAD = [
    (dict(mass=0.0), "scene.body.mass"),
    (dict(mass=-1.0), "scene.body.mass"),
    (dict(mass=float("nan")), "scene.body.mass"),
    (dict(mass=float("inf")), "scene.body.mass"),
    (dict(mass=1e-5), "scene.body.mass"),            # lighter than the hair it carries
    (dict(rail_height=float("nan")), "scene.body.rail_height"),
    (dict(rail_end=float("inf")), "scene.body.rail_end"),
    (dict(rail_friction=-0.1), "scene.body.rail_friction"),
    (dict(rail_friction=float("nan")), "scene.body.rail_friction"),
    (dict(velocity=[float("nan"), 0.0, 0.0]), "scene.body.velocity"),
]


@pytest.mark.parametrize("body,key", BAD, ids=[k + "=" + str(list(b.values())[0]) for b, k in BAD])
def test_bad_body_values_name_the_key(body, key):
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        dyn_scene({"mass": 0.01, **body}, n_strands=3, n_vertices=8)


def test_a_dynamic_body_takes_one_keyframe():
    with pytest.raises(InputError, match=r"scene\.motion\.times"):
        dyn_scene(dict(mass=0.01), motion=dict(times=[0.0, 1.0], translations=[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]],
                                               rotations_deg=[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))


def test_dynamic_false_keeps_the_keyframed_body():
    cfg = scene_cfg()
    assert cfg.body.dynamic is False
    assert isinstance(build_scene(cfg).motion, RigidMotion)


def test_cli_bad_mass_exits_2_naming_the_key(tmp_path):
    env = dict(os.environ, CI="1")
    proc = subprocess.run([sys.executable, "-m", "hairexp", "experiment=stylization_smoke", "scene.body.mass=-1.0",
                           "logging.rerun=false", f"hydra.run.dir={tmp_path}"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "scene.body.mass" in proc.stderr


# -- the measure -----------------------------------------------------------------------------------

def test_block_rail_measure():
    t = np.arange(6) * 0.1
    still = np.zeros((6, 3))
    m = block_rail_measure(t, still, 0.0, 0.1)
    assert m["travel"] == 0.0 and m["left_rail"] is False and m["left_rail_time"] is None
    slide = np.c_[np.linspace(0, 0.15, 6), np.zeros(6), np.zeros(6)]      # past the end at x = 0.12
    m = block_rail_measure(t, slide, 0.0, 0.1)
    assert m["left_rail"] and np.isclose(m["left_rail_time"], 0.4) and np.isclose(m["travel"], 0.15)
    back = np.c_[[0.0, -0.05, -0.08, -0.02, 0.0, 0.01], np.zeros(6), np.zeros(6)]
    m = block_rail_measure(t, back, 0.0, 0.1)
    assert not m["left_rail"] and np.isclose(m["travel"], 0.08) and np.isclose(m["travel_end"], 0.01)
    hop = np.c_[np.zeros(6), [0.0, 0.02, 0.05, 0.01, 0.0, -0.0005], np.zeros(6)]   # a hop that lands
    m = block_rail_measure(t, hop, 0.0, 0.1)
    assert not m["left_rail"] and np.isclose(m["lift_max"], 0.05)
    drop = np.c_[np.zeros(6), [0.0, 0.0, 0.0, -0.002, -0.01, -0.03], np.zeros(6)]
    m = block_rail_measure(t, drop, 0.0, 0.1)
    assert m["left_rail"] and np.isclose(m["left_rail_time"], 0.3) and np.isclose(m["drop"], 0.03)
    with pytest.raises(InputError, match="body_positions"):
        block_rail_measure(t, np.zeros((5, 3)), 0.0, 0.1)
    with pytest.raises(InputError, match="rail_end"):
        block_rail_measure(t, still, 0.0, float("nan"))


# -- runs --------------------------------------------------------------------------------------------

def _run(hydra_conf, tmp_path, overrides):
    from hairexp.app.run import run

    cfg = hydra_conf(["logging.rerun=false", *overrides])
    summary = run(cfg, tmp_path)
    return summary, np.load(tmp_path / "result.npz")


def test_stylization_smoke_runs_free_and_tracked(hydra_conf, tmp_path):
    import pandas as pd

    out = {}
    for c in ("free", "tracking"):
        summary, res = _run(hydra_conf, tmp_path / c, ["experiment=stylization_smoke", f"controller={c}"])
        assert summary["status"] == "completed" and summary["converged_fraction"] == 1.0
        P = res["body_positions"]
        assert P.shape == (16, 3) and np.isfinite(P).all() and np.isfinite(res["positions"]).all()
        df = pd.read_parquet(tmp_path / c / "metrics.parquet")
        assert {"body_x", "body_y", "body_hair_force_x", "body_rail_force_y"} <= set(df.columns)
        assert np.allclose(df["body_x"], P[1:, 0])
        # the guide rides with the live block: its root is the block's position + the root centre
        assert np.allclose(res["guide_positions"][:, 0], P + [0.0, -0.01, 0.0], atol=1e-12)
        out[c] = (block_rail_measure(res["times"], P, 0.0, 0.1), df)
    free, tracked = out["free"][0], out["tracking"][0]
    assert free["travel"] < 1e-12 and not free["left_rail"]          # nothing drives the free wisp
    assert tracked["travel"] > 1e-3                                  # the tracked swing pulls the block
    assert out["tracking"][1]["residual_rel_max"].max() < 1e-6


@pytest.mark.slow
def test_stylization_free_stays_tracked_leaves_the_rail(hydra_conf, tmp_path):
    """Paper Fig. 7 at full size (40 x 20 strands, 230 frames): the free wisp leaves the block on
    the rail; the tracked swing pulls it off.  The tracking residual stays small while the cluster
    variance changes (the hair moves on its own)."""
    import pandas as pd

    res = {}
    for c in ("free", "tracking"):
        summary, r = _run(hydra_conf, tmp_path / c, ["experiment=stylization", f"controller={c}"])
        assert summary["status"] == "completed"
        res[c] = (block_rail_measure(r["times"], r["body_positions"], 0.0, 0.1),
                  pd.read_parquet(tmp_path / c / "metrics.parquet"))
    assert not res["free"][0]["left_rail"] and res["free"][0]["travel"] < 1e-9
    m, df = res["tracking"]
    assert m["left_rail"] and m["left_rail_time"] > 3.0          # after the swings have built up
    assert df["residual_rel_max"].max() < 1e-6
    v = df["variance_ratio_mean"]
    assert v.max() - v.min() > 0.5


def test_export_writes_the_initial_pose_and_the_stage_runs_dynamic_again(hydra_conf, tmp_path):
    """hairexp.io.export_scene of a dynamic scene writes the block at its initial pose (its motion is
    not known before a run); the stage imported with scene.body.dynamic=true is a dynamic scene."""
    from hairexp.app.export_scene import export_scene
    from hairexp.app.run import run

    export_scene(hydra_conf(["experiment=stylization_smoke", "controller=tracking", "frames=6"]), tmp_path / "s.usda")
    cfg = hydra_conf(["experiment=from_usd", f"scene.usd={tmp_path / 's.usda'}", "scene.body.dynamic=true",
                      "scene.body.mass=0.01", "scene.body.rail_friction=0.0", "tracking.points_per_guide=3",
                      "logging.rerun=false"])
    summary = run(cfg, tmp_path / "run")
    assert summary["status"] == "completed"
    res = np.load(tmp_path / "run" / "result.npz")
    assert res["body_positions"].shape == (7, 3) and res["body_positions"][-1, 0] > 1e-4


def test_the_stylization_report_reads_an_experiment_folder_as_its_variants(tmp_path, capsys):
    """README's commands: ``python -m hairexp experiment=stylization hydra.run.dir=out`` runs both
    variants into out/free and out/tracked; ``python -m hairexp.evaluation.stylization out`` reports
    each (it said "not a finished run folder": the README ran the experiment twice, into folders
    that hold variants, and gave those to the report)."""
    import json as _json

    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment
    from hairexp.evaluation.stylization import main, run_folders

    out = tmp_path / "out"
    run_experiment(compose_config(["experiment=stylization_smoke", "frames=4", "logging.rerun=false",
                                   "logging.progress=false"]), out)
    assert run_folders(out) == [out / "free", out / "tracked"]
    assert run_folders(out / "tracked") == [out / "tracked"]
    assert main([str(out)]) == 0
    text, runs, dec = capsys.readouterr().out.strip(), [], _json.JSONDecoder()
    while text:   # one JSON object a run
        obj, end = dec.raw_decode(text)
        runs.append(obj)
        text = text[end:].strip()
    assert [r["run"] for r in runs] == [str(out / "free"), str(out / "tracked")]
    assert [r["controller"] for r in runs] == ["free", "tracking"]
    # a variant folder that did not finish is named
    (out / "tracked" / "result.npz").unlink()
    assert main([str(out)]) == 2
    assert "tracked: not a finished run folder" in capsys.readouterr().err
