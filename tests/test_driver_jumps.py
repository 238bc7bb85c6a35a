"""A step in which the keyed roots' velocity jumps is one implicit Euler step, and the scheme
restarts after it (``solver.restart_at_jumps``; hairexp/physics/integrators.py, "Driver
discontinuities")."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import run_steps, scene_cfg, solver_cfg

from hairexp.app.builders import build_scene
from hairexp.errors import InputError
from hairexp.model.rigid import RigidMotion
from hairexp.physics.integrators import History
from hairexp.physics.simulator import Simulator

DT = 0.02
#: still, then 1.2 m/s up from 0.04 s to 0.1 s, then still: velocity jumps at 0.04 and 0.1 s
JERK = dict(interpolation="linear", times=[0.0, 0.04, 0.1, 1.0], translations=[[0, 0, 0], [0, 0, 0], [0, 0.072, 0], [0, 0.072, 0]],
            rotations_deg=[[0, 0, 0]] * 4)


def linear(times, translations, rotations=None, interpolation="linear"):
    K = len(times)
    rot = np.zeros((K, 3)) if rotations is None else np.radians(np.asarray(rotations, dtype=float))
    return RigidMotion(np.asarray(times, dtype=float), np.asarray(translations, dtype=float), rot, interpolation)


def test_velocity_jumps_at_linear_keys_where_the_segments_differ():
    m = linear(JERK["times"], JERK["translations"])
    assert not m.velocity_jumps(0.0, 0.04)          # the key at the step's end belongs to the next step
    assert m.velocity_jumps(0.04, 0.06)             # 0 -> 1.2 m/s at the step's start
    assert m.velocity_jumps(0.03, 0.05)             # ... inside it
    assert not m.velocity_jumps(0.06, 0.08)
    assert m.velocity_jumps(0.1, 0.12)              # 1.2 -> 0
    assert not m.velocity_jumps(0.12, 5.0)          # the last key: still before and after it
    assert m.velocity_jumps(0.04 - 1e-12, 0.06)     # a step start off by round-off
    # the same velocity on both sides of a key is no jump
    assert not linear([0, 1, 2], [[0, 0, 0], [1, 0, 0], [2, 0, 0]]).velocity_jumps(0.5, 1.5)
    # but a motion that starts moving at its first key and stops at its last jumps at both
    m2 = linear([0.5, 1.0], [[0, 0, 0], [1, 0, 0]])
    assert m2.velocity_jumps(0.5, 0.6) and m2.velocity_jumps(0.9, 1.1) and not m2.velocity_jumps(0.6, 0.9)
    # keys at or before ``since`` are left out (a run's initial state moves with the velocity after a key at t = 0)
    m4 = linear([0.0, 1.0], [[0, 0, 0], [1, 0, 0]])
    assert m4.velocity_jumps(0.0, 0.1) and not m4.velocity_jumps(0.0, 0.1, since=0.0)
    assert m4.velocity_jumps(0.95, 1.05, since=0.0)
    # a rotation's rate counts too
    m3 = linear([0, 1, 2], [[0, 0, 0]] * 3, [[0, 0, 0], [0, 0, 10], [0, 0, 10]])
    assert m3.velocity_jumps(0.9, 1.1) and not m3.velocity_jumps(1.1, 1.9)


def test_keys_as_dense_as_the_steps_are_samples_not_jumps():
    """A motion sampled at every frame (a USD stage's time samples) changes its velocity at every
    key; only keys whose segments on both sides span >= MIN_SEGMENT_STEPS steps count."""
    t = np.arange(0.0, 1.0 + 1e-9, 1 / 24)
    m = linear(t, np.c_[np.sin(2 * np.pi * t), 0 * t, 0 * t])
    assert not any(m.velocity_jumps(s, s + 1 / 24) for s in t[:-1])                       # a step a frame
    assert m.velocity_jumps(t[5] - 0.005, t[5] + 0.005)                                  # 4 steps a frame
    jerk = linear(JERK["times"], JERK["translations"])
    assert jerk.velocity_jumps(0.04, 0.06) and not jerk.velocity_jumps(0.04, 0.065)     # 0.04 s before: 2 steps


def test_cubic_and_static_motions_never_jump():
    m = linear(JERK["times"], JERK["translations"], interpolation="cubic")
    assert not any(m.velocity_jumps(t, t + DT) for t in np.arange(0.0, 1.2, DT))
    assert not RigidMotion.static().velocity_jumps(0.0, 10.0)


def sim_of(**solver):
    scene = build_scene(scene_cfg(motion=JERK, n_strands=2, n_vertices=8))
    return Simulator(scene, solver_cfg(**solver))


def test_the_jump_step_is_one_implicit_euler_step_and_the_scheme_restarts():
    sim = sim_of(integrator="trbdf2", rtol=1e-10)
    ie = sim_of(integrator="implicit_euler", rtol=1e-10)
    states, infos = run_steps(sim, 2, DT)            # 0 -> 0.04: no jump
    assert states[-1].history is not None and states[-1].history.a is not None   # TR-BDF2's end acceleration
    before = states[-1]
    assert [i.restarts for i in infos] == [0, 0]
    new, info = sim.step(before, DT)                  # 0.04 -> 0.06: the jump
    assert info.converged and info.restarts == 1      # metrics.parquet's ``restarts`` column
    assert isinstance(new.history, History) and new.history.restart and new.history.a is None
    # the same step taken by implicit Euler from the same state
    ref, _ = ie.step(before, DT)
    np.testing.assert_allclose(new.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(new.v, ref.v, rtol=0, atol=1e-10)
    # the next step is TR-BDF2 again, from its restart (implicit Euler first stage, then BDF2)
    nxt, info = sim.step(new, DT)
    assert info.converged and info.restarts == 0 and nxt.history.a is not None and not nxt.history.restart
    assert not np.allclose(nxt.x, ie.step(new, DT)[0].x, rtol=0, atol=1e-9)


def test_restart_at_jumps_false_steps_through_the_jump():
    sim = sim_of(integrator="trbdf2", restart_at_jumps=False)
    states, _ = run_steps(sim, 3, DT)
    assert states[-1].history.a is not None and not states[-1].history.restart


@pytest.mark.parametrize("integrator", ["bdf2", "lmm2"])
def test_one_step_schemes_restart_from_their_first_step(integrator):
    sim = sim_of(integrator=integrator)
    states, infos = run_steps(sim, 5, DT)
    assert all(i.converged for i in infos)
    assert states[3].history.restart                  # the jump step (0.04 -> 0.06)
    assert np.isfinite(states[-1].x).all()


def test_a_motion_moving_at_t0_does_not_restart_the_first_step():
    """The initial state moves rigidly with the body's velocity at t = 0: no jump there (the
    Galilean invariance test's moving body, tests/test_analytic.py)."""
    moving = dict(interpolation="linear", times=[0.0, 10.0], translations=[[0, 0, 0], [5.0, 0, 0]],
                  rotations_deg=[[0, 0, 0]] * 2)
    sim = Simulator(build_scene(scene_cfg(motion=moving, n_strands=2, n_vertices=8)), solver_cfg(integrator="trbdf2"))
    states, _ = run_steps(sim, 2, DT)
    assert states[1].history.a is not None and not states[1].history.restart


def test_implicit_euler_and_dynamic_bodies_do_not_restart():
    assert not sim_of(integrator="implicit_euler").restart_at_jumps
    assert sim_of(integrator="trbdf2").restart_at_jumps


def test_a_non_boolean_restart_at_jumps_is_refused():
    class Cfg:
        rtol, atol, max_iterations, max_backtracks, derivatives, stretch_hessian = 1e-5, 1e-10, 30, 30, "closed_form", "primal_dual"
        on_failure, integrator, restart_at_jumps = "substep", "trbdf2", "false"
    scene = build_scene(scene_cfg(motion=JERK))
    with pytest.raises(InputError, match="solver.restart_at_jumps"):
        Simulator(scene, Cfg())


def test_the_metrics_row_counts_the_restarts():
    from hairexp.outputs.metrics import measure

    sim = sim_of(integrator="trbdf2")
    states, infos = run_steps(sim, 3, DT)
    rows = [measure(sim.scene, st, inf, sim, k, k, "free") for k, (st, inf) in enumerate(zip(states[1:], infos))]
    assert [r["restarts"] for r in rows] == [0, 0, 1]


def test_linear_pose_is_scipys_slerp():
    """``RigidMotion._pose`` for linear keys (Rodrigues on the key's relative rotation vector,
    ``exp_so3``) against scipy's Slerp, which it replaced in the hot path: the same segment at
    the keys and the same matrices to round-off, for rotations from 1e-9 rad to several turns."""
    from scipy.spatial.transform import Rotation, Slerp

    from hairexp.model.rigid import RigidMotion

    rng = np.random.default_rng(0)
    worst = 0.0
    for scale in (1e-9, 1e-3, 1.0, 3.0):
        for _ in range(20):
            K = int(rng.integers(2, 6))
            times = np.cumsum(np.concatenate([[0.0], rng.uniform(0.1, 1.0, K - 1)]))
            rotvecs = rng.normal(size=(K, 3)) * scale
            m = RigidMotion(times, 0.01 * rng.normal(size=(K, 3)), rotvecs, interpolation="linear")
            slerp = Slerp(times, Rotation.from_rotvec(rotvecs))
            for t in [*rng.uniform(-0.5, 3.5, 10), *times]:
                R, _ = m._pose(float(t))
                want = slerp(min(max(float(t), times[0]), times[-1])).as_matrix().reshape(3, 3)
                worst = max(worst, float(np.abs(R - want).max()))
                np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-14)
    assert worst <= 5e-15
