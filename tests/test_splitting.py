"""Splitting (paper Fig. 6, conf/experiment/splitting.yaml): a wisp pulled over a sphere, free and
tracked with 1, 2 and 3 guides, judged by the number of clumps after the sphere.

* the ``clumps`` measure on synthetic strands, at the experiment's stated threshold;
* what the scene needs from the framework: variant overrides that set a list of edits, and a
  coarse guide simulation that collides with the sphere (``guides.collide``);
* the smoke variant (splitting_smoke.yaml) runs and writes the measure in every variant;
* ``slow``: the full experiment meets its success measure."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from helpers import CONF_DIR
from hairexp.app.config import GuideEditKind, MeasureConfig
from hairexp.errors import InputError
from hairexp.app.experiment import apply_overrides, run_experiment
from hairexp.app.builders import build_scene
from hairexp.evaluation.measures import RunData, clumps
from hairexp.app.guides import build_guides

SPLITTING = OmegaConf.load(CONF_DIR / "experiment" / "splitting.yaml")
THRESHOLD = float(SPLITTING.measure.threshold)   # the stated threshold (m)
QUIET = ["logging.rerun=false", "logging.progress=false"]


# -- the clumps measure on synthetic strands ----------------------------------------------------

def strands_data(lower: np.ndarray, n_vertices: int = 10, length: float = 0.3, root_radius: float = 0.02) -> RunData:
    """One frame of straight strands hanging from roots on a circle of ``root_radius`` whose lower
    halves (the part the measure reads) are translated so that their means are the rows of
    ``lower``; the upper halves stay where the roots put them."""
    S = len(lower)
    phi = np.linspace(0, 2 * np.pi, S, endpoint=False)
    roots = np.stack([root_radius * np.cos(phi), np.zeros(S), root_radius * np.sin(phi)], 1)
    s = np.linspace(0.0, length, n_vertices)
    X = roots[:, None, :] + s[None, :, None] * np.array([0.0, -1.0, 0.0])
    half = n_vertices // 2
    shift = lower - X[:, half:].mean(1)
    X[:, half:] += shift[:, None, :]
    scene = SimpleNamespace(strands=SimpleNamespace(offsets=np.arange(S + 1) * n_vertices))
    return RunData(scene, np.array([0.0]), X.reshape(1, -1, 3))


def measure_cfg(**kw):
    return OmegaConf.structured(MeasureConfig(**{"name": "clumps", "threshold": THRESHOLD, "strand_fraction": 0.5,
                                                  "min_share": 0.1, **kw}))


def groups(k: int, per: int = 16, spacing: float = 0.1, jitter: float = 0.005, seed: int = 0) -> np.ndarray:
    """k groups of ``per`` strands, centres ``spacing`` apart along z, each within ``jitter``."""
    rng = np.random.default_rng(seed)
    centres = np.stack([np.zeros(k), np.full(k, -0.2), spacing * (np.arange(k) - (k - 1) / 2)], 1)
    return np.concatenate([c + rng.uniform(-jitter, jitter, (per, 3)) for c in centres])


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_well_separated_groups_make_that_many_clumps(k):
    m = clumps(strands_data(groups(k)), measure_cfg())
    assert m["clumps"] == k and m["clusters_all"] == k
    assert m["clump_sizes"] == [16] * k
    assert m["threshold"] == THRESHOLD


def test_even_spread_is_one_clump_at_the_stated_threshold():
    """48 strands fanned evenly over 30 cm (a curved sheet, neighbours under 1 cm apart): one
    clump at the threshold, although the fan is ten times wider than the threshold; clumps are
    found by gaps, not by size."""
    a = np.linspace(-0.6, 0.6, 48)
    lower = np.stack([0.25 * np.sin(a), -0.2 - 0.05 * np.cos(a), 0.25 * a], 1)
    gaps = np.linalg.norm(np.diff(lower, axis=0), axis=1)
    assert gaps.max() < THRESHOLD < np.ptp(lower[:, 2])
    m = clumps(strands_data(lower), measure_cfg())
    assert m["clumps"] == 1 and m["clump_sizes"] == [48]
    # below the spacing every strand is its own cluster, and none is big enough to count
    fine = clumps(strands_data(lower), measure_cfg(threshold=float(0.5 * gaps.min())))
    assert fine["clusters_all"] == 48 and fine["clumps"] == 0


def test_gap_just_above_or_below_the_threshold():
    two = groups(2, spacing=0.0)
    two[16:, 2] += THRESHOLD + 0.01 + 0.01   # group widths 1 cm: gap = threshold + 1 cm
    assert clumps(strands_data(two), measure_cfg())["clumps"] == 2
    two[16:, 2] -= 0.02                       # gap = threshold - 1 cm
    assert clumps(strands_data(two), measure_cfg())["clumps"] == 1


def test_small_stray_groups_do_not_count_and_only_the_lower_part_matters():
    lower = groups(2)
    lower[:3] += np.array([0.0, 0.0, 0.5])    # 3 of 32 strands (< 10 %) far away
    m = clumps(strands_data(lower), measure_cfg())
    assert m["clusters_all"] == 3 and m["clumps"] == 2 and m["clump_sizes"] == [16, 13]
    # upper halves far apart (roots on a 50 cm circle) change nothing: only the lower half is read
    assert clumps(strands_data(groups(3), root_radius=0.5), measure_cfg())["clumps"] == 3
    assert clumps(strands_data(groups(1), root_radius=0.5), measure_cfg())["clumps"] == 1


def test_measure_time_picks_the_frame():
    d = strands_data(groups(2))
    one = strands_data(groups(1, per=32)).positions[0]
    d = RunData(d.scene, np.array([0.0, 0.04, 0.08]), np.stack([one, d.positions[0], one]))
    assert clumps(d, measure_cfg(time=0.04))["clumps"] == 2
    assert clumps(d, measure_cfg(time=-1.0))["clumps"] == 1 and clumps(d, measure_cfg(time=-1.0))["time"] == 0.08


# -- what the scene needs from the framework ----------------------------------------------------

def test_variant_override_sets_a_list_of_typed_edits(hydra_conf):
    cfg = hydra_conf(["experiment=splitting"])
    edits = "guides.edits=[{guide: 1, kind: displace, offset: [0.0, 0.0, 0.1], times: [0.0, 1.0], weights: [0.0, 1.0]}]"
    out = apply_overrides(cfg, ["guides.count=2", edits], "variants[9] (v)")
    assert out.guides.count == 2 and len(out.guides.edits) == 1
    e = out.guides.edits[0]
    assert e.kind == GuideEditKind.displace and e.falloff == 1.0 and list(e.offset) == [0.0, 0.0, 0.1]
    assert len(cfg.guides.edits) == 0                       # the experiment's config is untouched
    assert len(apply_overrides(out, ["guides.edits=[]"], "v").guides.edits) == 0
    with pytest.raises(InputError, match=r"variants\[9\] \(v\).*falloff"):
        apply_overrides(cfg, ["guides.edits=[{guide: 0, falloff: 2.0, fallof: 1.0}]"], "variants[9] (v)")


def guide_clearance(collide: bool, hydra_conf) -> float:
    """Smallest signed distance (m) of one coarse simulated guide (its vertices and edge
    midpoints) to the sphere over the first 1.2 s of the splitting scene."""
    cfg = hydra_conf(["experiment=splitting", "guides.count=1", f"guides.collide={collide}", "frames=30"])
    scene = build_scene(cfg.scene)
    g = build_guides(cfg, scene, cfg.frames, cfg.fps)
    ball = scene.colliders[0]
    d = []
    for f, P in enumerate(g.positions):
        Q = np.concatenate([P, 0.5 * (P[1:] + P[:-1])])
        d.append(ball.sdf_body(ball.to_body(Q, f / g.fps)).min())
    return float(min(d))


def test_simulated_guides_collide_with_the_sphere_when_asked(hydra_conf):
    assert guide_clearance(False, hydra_conf) < -0.02       # passes through the sphere
    assert guide_clearance(True, hydra_conf) > -0.002        # dragged over it (within its thickness)


# -- the experiment -----------------------------------------------------------------------------

def test_smoke_variant_runs_and_writes_the_measure(hydra_conf, tmp_path):
    cfg = hydra_conf(["experiment=splitting_smoke", *QUIET])
    assert cfg.scene.colliders[0].name == "ball" and cfg.guides.collide   # the same scene as splitting
    s = run_experiment(cfg, tmp_path)
    assert s["status"] == "completed" and s["judge"] == "clumps_match_guides"
    assert set(s["variants"]) == {"free", "tracked_2"}
    assert isinstance(s["success"], bool) and set(s["verdict"]) == {"free", "tracked_2"}
    for name, v in s["variants"].items():
        m = v["measures"]
        assert v["status"] == "completed" and v["steps"] == cfg.frames
        assert m["threshold"] == THRESHOLD and m["clumps"] >= 1
        assert sum(m["clump_sizes"]) <= cfg.scene.n_strands and m["clusters_all"] >= m["clumps"]
        own = json.loads((tmp_path / name / "summary.json").read_text())
        assert own["measures"] == m and (tmp_path / name / "result.npz").exists()
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["variants"]["tracked_2"]["guides"] == 2


@pytest.mark.slow
def test_splitting_free_is_one_clump_and_k_guides_make_k_clumps(hydra_conf, tmp_path):
    cfg = hydra_conf(["experiment=splitting", *QUIET])
    s = run_experiment(cfg, tmp_path)
    assert s["status"] == "completed"
    got = {k: v["measures"]["clumps"] for k, v in s["variants"].items()}
    assert got == {"free": 1, "tracked_1": 1, "tracked_2": 2, "tracked_3": 3}, s["verdict"]
    assert s["success"] is True
    for v in s["variants"].values():
        assert v["converged_fraction"] == 1.0
