"""Baselines (validation part 4): guide skinning, the attraction term, smoke runs of the
``skinned`` and ``attract`` controllers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from derivcheck import check_term
from helpers import bent_polyline
from hairexp.physics.energies import Attraction
from hairexp.scene.builders import build_scene
from hairexp.tracking.guides import build_guides
from hairexp.tracking.skinning import GuideSkinning
from test_paper_scenes import experiment_cfg


@pytest.fixture(scope="module")
def goaling_small():
    cfg = experiment_cfg("goaling_smoke", "variants=[]", "frames=3", "guides.source=rigid", "guides.edits=[]")
    scene = build_scene(cfg.scene)
    return scene, build_guides(cfg, scene, cfg.frames, cfg.fps)


def test_skinning_at_rest_gives_rest_positions(goaling_small):
    scene, guides = goaling_small
    sk = GuideSkinning(scene, guides)
    R0, _ = scene.motion.pose(0.0)
    assert np.abs(sk.pose(guides.rest, R0) - scene.strands.rest[sk.free]).max() < 1e-13
    assert np.abs(sk.positions(0.0) - scene.strands.rest).max() < 1e-13
    assert len(set(sk.guide_of_strand)) == guides.n_guides       # every guide carries some hair


def test_rigid_motion_of_the_guides_moves_skinned_hair_rigidly(goaling_small):
    scene, guides = goaling_small
    sk = GuideSkinning(scene, guides)
    Q = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    p = np.array([0.3, -0.2, 0.5])
    R0, _ = scene.motion.pose(0.0)
    moved = sk.pose(guides.rest @ Q.T + p, Q @ R0)
    want = scene.strands.rest[sk.free] @ Q.T + p
    assert np.abs(moved - want).max() < 1e-12


def test_bending_a_guide_moves_only_its_hair(goaling_small):
    scene, guides = goaling_small
    sk = GuideSkinning(scene, guides)
    R0, _ = scene.motion.pose(0.0)
    shape = guides.rest.copy()
    a, b = guides.offsets[0], guides.offsets[1]
    shape[a + 3:b] += np.array([0.05, 0.0, 0.0]) * np.linspace(0, 1, b - a - 3)[:, None]   # bend guide 0's tip
    x = sk.pose(shape, R0)
    strand = np.repeat(np.arange(len(scene.strands.offsets) - 1), np.diff(scene.strands.offsets))[sk.free]
    mine = sk.guide_of_strand[strand] == 0
    d = np.linalg.norm(x - scene.strands.rest[sk.free], axis=1)
    assert d[mine].max() > 0.01 and d[~mine].max() < 1e-13


def test_attraction_derivatives_match_finite_differences():
    rng = np.random.default_rng(3)
    x = bent_polyline(7, seed=5)
    term = Attraction(rng.uniform(1e-5, 1e-4, 7), 100.0, np.arange(7))
    term.set_target(x + rng.normal(scale=0.01, size=x.shape))
    xs = torch.as_tensor(x + rng.normal(scale=0.01, size=x.shape))[term.stencil_t]
    rep = check_term(term, xs)
    assert rep.grad_scale > 0 and rep.hess_scale > 0
    g, H = term.closed_form(xs, True)
    assert torch.allclose(g, rep.grad, rtol=1e-12, atol=1e-18) and torch.allclose(H, rep.hess, rtol=1e-12, atol=0)
    F = term.forces(x + 0.0)
    assert np.allclose(F, -term.km.numpy()[:, None] * (x - term.target.numpy()))


@pytest.mark.parametrize("controller", ["skinned", "attract"])
def test_baseline_controllers_complete_with_finite_results(controller, tmp_path):
    from hairexp.experiment import run_experiment

    cfg = experiment_cfg("goaling_smoke", "variants=[]", "frames=8", f"controller.name={controller}")
    s = run_experiment(cfg, tmp_path)
    assert s["status"] == "completed" and s["controller"] == controller and s["converged_fraction"] == 1.0
    d = np.load(tmp_path / "result.npz")
    assert np.isfinite(d["positions"]).all() and d["positions"].shape[0] == 9
    import pandas as pd

    df = pd.read_parquet(tmp_path / "metrics.parquet")
    assert np.isfinite(df["control_force_rel"]).all() and (df["control_force_rel"] >= 0).all()
    assert json.loads((tmp_path / "summary.json").read_text())["measures"]["min_distance"] == pytest.approx(
        s["measures"]["min_distance"])
    if controller == "skinned":   # the roots stay on the body
        sc = build_scene(cfg.scene)
        k = sc.strands.kinematic
        assert np.abs(d["positions"][-1][k] - sc.root_positions(float(d["times"][-1]))[k]).max() < 1e-12


def test_attraction_pulls_toward_the_skinned_hair(tmp_path):
    """Stiffer springs bring the hair closer to the skinned positions (frame 25: the edited guide swings)."""
    from hairexp.run import run

    dist = []
    for k in (10.0, 1000.0):
        cfg = experiment_cfg("goaling_smoke", "variants=[]", "frames=25", "controller.name=attract",
                             f"controller.attract_stiffness={k}")
        run(cfg, tmp_path / str(k))
        dist.append(np.load(tmp_path / str(k) / "result.npz")["positions"][-1])
    cfg = experiment_cfg("goaling_smoke", "variants=[]", "frames=25", "controller.name=skinned")
    run(cfg, tmp_path / "sk")
    xs = np.load(tmp_path / "sk" / "result.npz")["positions"][-1]
    e = [np.linalg.norm(x - xs) for x in dist]
    assert e[1] < 0.5 * e[0]


def test_attract_stiffness_must_be_positive(tmp_path):
    from hairexp.errors import InputError
    from hairexp.run import run

    cfg = experiment_cfg("goaling_smoke", "variants=[]", "frames=1", "controller.name=attract",
                         "controller.attract_stiffness=0")
    with pytest.raises(InputError, match="attract_stiffness"):
        run(cfg, tmp_path)
