"""Settle phase (``scene.settle``, hairexp/physics/settle.py): the run starts from the hair (and
simulated guides) at rest under gravity, and the tracking is registered on that state."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from hairexp.errors import InputError
from hairexp.physics.simulator import Simulator
from hairexp.app.run import run
from hairexp.physics.schedule import step_schedule
from hairexp.app.builders import build_scene

QUIET = ["logging.rerun=false", "logging.progress=false"]
# a small wisp sticking out sideways: far from equilibrium under gravity
WISP = ["scene.n_strands=4", "scene.n_vertices=8", "scene.length=0.2", "scene.direction=[1.0,-0.2,0.0]", "fps=25",
        *QUIET]
TRACKED = ["controller.name=tracking", "guides.source=simulated", "guides.count=1", "guides.n_vertices=6",
           "tracking.points_per_guide=4"]


def positions(path):
    return np.load(path / "result.npz")["positions"]


def test_settle_zero_is_the_run_without_a_settle_phase(hydra_conf, tmp_path):
    """settle = 0 (the default) runs exactly the code path without settling: bit-identical to
    stepping the built scene directly."""
    cfg = hydra_conf([*WISP, "frames=4", "scene.settle=0"])
    run(cfg, tmp_path)
    got = positions(tmp_path)
    _, dt = step_schedule(cfg.fps, cfg.solver.dt, cfg.frames)
    sim = Simulator(build_scene(cfg.scene), cfg.solver, collision_cfg=cfg.collision)
    state = sim.initial_state()
    ref = [state.x]
    for _ in range(cfg.frames):
        state, _ = sim.step(state, dt)
        ref.append(state.x)
    assert np.array_equal(got, np.stack(ref))
    # the default (no key given) is the same run
    run(hydra_conf([*WISP, "frames=4"]), tmp_path / "default")
    assert np.array_equal(positions(tmp_path / "default"), got)


def test_settled_wisp_barely_moves_at_the_first_step(hydra_conf, tmp_path):
    moved = {}
    for settle in (0.0, 2.0):
        out = tmp_path / str(settle)
        run(hydra_conf([*WISP, "frames=1", f"scene.settle={settle}"]), out)
        p = positions(out)
        moved[settle] = float(np.max(np.linalg.norm(p[1] - p[0], axis=1)))
    assert moved[0.0] > 1e-3            # the straight wisp sags: millimetres in one step
    assert moved[2.0] < 1e-2 * moved[0.0], moved


def test_settled_tracking_holds_with_almost_no_force(hydra_conf, tmp_path):
    force = {}
    for settle in (0.0, 5.0):   # 5 s: the wisp's tips move < 1e-4 mm per step at the end
        out = tmp_path / str(settle)
        run(hydra_conf([*WISP, *TRACKED, "frames=3", f"scene.settle={settle}"]), out)
        force[settle] = pd.read_parquet(out / "metrics.parquet")["constraint_force_rel"].to_numpy()
    assert force[0.0][0] > 0.1, force      # registered on the straight wisp: held against its sag
    assert np.max(force[5.0]) < 1e-3, force


def test_settle_keeps_the_elastic_rest_shape(hydra_conf):
    from hairexp.physics.settle import settle_scene

    cfg = hydra_conf([*WISP, "scene.settle=1.0"])
    scene = build_scene(cfg.scene)
    settled = settle_scene(scene, cfg)
    assert settled.strands is scene.strands                       # rest lengths and angles unchanged
    k = scene.strands.kinematic
    assert np.array_equal(settled.root_body[k], scene.root_body[k])  # roots exactly where they were
    assert np.max(np.abs(settled.initial - scene.strands.rest)) > 1e-2  # the free hair has sagged
    assert np.allclose(Simulator(settled, cfg.solver).initial_state().x, settled.initial, atol=1e-12)


@pytest.mark.parametrize("value", ["-1.0", "nan", "inf"])
def test_invalid_settle_is_an_input_error_naming_the_key(hydra_conf, tmp_path, value):
    with pytest.raises(InputError, match=r"scene\.settle"):
        run(hydra_conf([*WISP, "frames=1", f"scene.settle={value}"]), tmp_path)


def test_settled_state_does_not_depend_on_the_run_dt(hydra_conf):
    """The settle phase steps with scene.settle_dt, not the run's dt: runs at different dt start
    from the same settled hair (what the accuracy report compares against a small-dt reference)."""
    from hairexp.physics.settle import settle_scene

    init = {}
    for dt in (0.04, 0.01):
        cfg = hydra_conf([*WISP, "scene.settle=1.0", f"solver.dt={dt}"])
        init[dt] = settle_scene(build_scene(cfg.scene), cfg).initial
    assert np.array_equal(init[0.04], init[0.01])
    cfg = hydra_conf([*WISP, "scene.settle=1.0", "scene.settle_dt=0.01"])
    assert np.max(np.abs(settle_scene(build_scene(cfg.scene), cfg).initial - init[0.04])) > 0  # the key is used


@pytest.mark.parametrize("settle", ["0.5", "0.0"])   # checked even when the settle phase is off
@pytest.mark.parametrize("value", ["0.0", "-0.01", "nan"])
def test_invalid_settle_dt_is_an_input_error_naming_the_key(hydra_conf, tmp_path, value, settle):
    with pytest.raises(InputError, match=r"scene\.settle_dt"):
        run(hydra_conf([*WISP, "frames=1", f"scene.settle={settle}", f"scene.settle_dt={value}"]), tmp_path)
