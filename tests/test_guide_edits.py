"""Guide authoring (paper 4: an artist edits a coarse guide simulation by keyframing, or keys the
guides directly, Fig. 7): rotate and displace edits layered on any guide source, their keyed
weights, keyframed guide poses, input errors naming the config key, the authored guides.npz reused
as a file source, and a tracked run of an edited guide."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from helpers import REPO
from tracking_helpers import tracked_cfg
from hairexp.app.config import GuideEditConfig, GuideEditKind, GuideKeyframeConfig
from hairexp.errors import InputError
from hairexp.app.run import run
from hairexp.app.builders import build_scene
from hairexp.guides.authoring import MAX_ROOT_TURN_DEG, KeyedWeight, apply_edits
from hairexp.app.guides import build_guides, source_guides

#: A body that translates and turns about a tilted axis over 1 s (cubic): body frame != world
#: frame, and the body turns the edits' axes (z) and offsets away from their world directions.
TURNING = {
    "scene.motion.times": [0.0, 1.0],
    "scene.motion.translations": [[0.0, 0.0, 0.0], [0.1, 0.05, 0.0]],
    "scene.motion.rotations_deg": [[0.0, 0.0, 0.0], [40.0, 0.0, 60.0]],
}


def edit(kind="rotate", **kw) -> GuideEditConfig:
    return GuideEditConfig(kind=GuideEditKind(kind), **kw)


def guide_cfg(edits=(), **overrides):
    """Two rigid 30 cm guides of 8 vertices on the turning body (TURNING), 26 frames at 25 fps."""
    cfg = tracked_cfg({**TURNING, "guides.count": 2, **overrides})
    cfg.guides.edits = list(edits)
    return cfg


def source_and_edited(cfg):
    scene = build_scene(cfg.scene)
    return scene, source_guides(cfg, scene, cfg.frames, cfg.fps), build_guides(cfg, scene, cfg.frames, cfg.fps)


def edge_lengths(P):
    return np.linalg.norm(np.diff(P, axis=-2), axis=-1)


def frame_times(anim):
    return np.arange(anim.n_frames) / anim.fps


# ---------------------------------------------------------------------------------------------
# Keyed weights
# ---------------------------------------------------------------------------------------------

KEY_T = [0.1, 0.3, 0.45, 0.8, 1.0]
KEY_W = [0.0, 1.0, -2.0, 0.5, 3.0]


def test_weight_passes_through_keys_and_holds_outside():
    w = KeyedWeight(KEY_T, KEY_W, "e")
    np.testing.assert_allclose(w(np.array(KEY_T)), KEY_W, rtol=1e-15, atol=1e-15)
    np.testing.assert_array_equal(w(np.array([-1.0, 0.0, 0.1])), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(w(np.array([1.0, 1.5, 10.0])), [3.0, 3.0, 3.0])
    np.testing.assert_array_equal(KeyedWeight([0.5], [0.7], "e")(np.linspace(-1, 2, 7)), np.full(7, 0.7))


def test_weight_is_C1_at_every_key():
    """One-sided difference quotients agree at each key (|left - right| = O(h)), also at the first
    and last key where the curve meets its held value (slope 0).  The same check flags the corners
    of a piecewise-linear curve through the same keys, so it can fail."""
    w = KeyedWeight(KEY_T, KEY_W, "e")
    h = 1e-6
    for tk in KEY_T:
        left = (w(tk) - w(tk - h)) / h
        right = (w(tk + h) - w(tk)) / h
        assert abs(left - right) <= 1e-3, (tk, left, right)
    for tk in (KEY_T[0], KEY_T[-1]):
        assert abs((w(tk + h) - w(tk - h)) / (2 * h)) <= 1e-3
    lin = lambda t: np.interp(t, KEY_T, KEY_W)  # noqa: E731
    tk = KEY_T[1]
    assert abs((lin(tk) - lin(tk - h)) / h - (lin(tk + h) - lin(tk)) / h) > 1.0


def test_weight_does_not_overshoot_between_keys():
    w = KeyedWeight(KEY_T, KEY_W, "e")
    for a, b, wa, wb in zip(KEY_T[:-1], KEY_T[1:], KEY_W[:-1], KEY_W[1:]):
        v = w(np.linspace(a, b, 401))
        assert v.min() >= min(wa, wb) - 1e-15 and v.max() <= max(wa, wb) + 1e-15
    up = KeyedWeight([0.0, 0.2, 0.3, 1.0], [0.0, 0.1, 0.9, 1.0], "e")(np.linspace(0, 1, 1001))
    assert np.all(np.diff(up) >= -1e-15)   # monotone keys -> monotone curve


# ---------------------------------------------------------------------------------------------
# Rotate and displace
# ---------------------------------------------------------------------------------------------

SWING = dict(guide=1, axis=[0.0, 0.0, 2.0], angle_deg=25.0, times=[0.0, 0.3, 0.6, 0.9], weights=[0.0, 1.0, -2.0, 3.0])


def test_rotate_keeps_edge_lengths_and_the_root_at_every_frame():
    cfg = guide_cfg([edit("rotate", **SWING)])
    _, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[1], ed.offsets[2]
    for f in range(ed.n_frames):
        np.testing.assert_allclose(edge_lengths(ed.positions[f, a:b]), edge_lengths(src.positions[f, a:b]),
                                   rtol=1e-14, atol=0)
    np.testing.assert_array_equal(ed.positions[:, a], src.positions[:, a])            # the root: exactly
    np.testing.assert_array_equal(ed.positions[:, :a], src.positions[:, :a])          # the other guide
    assert np.abs(ed.positions[:, a + 1:b] - src.positions[:, a + 1:b]).max() > 0.05  # it did swing
    assert np.abs(ed.positions[:, a + 1] - src.positions[:, a + 1]).max() > 0          # vertex 1 turns too


def test_rotate_is_about_the_body_frame_axis_by_weight_times_angle():
    """In the body frame the edited guide is the source guide turned about its root by
    w(t) x angle about the (normalised) axis: the edit rides with the turning body."""
    cfg = guide_cfg([edit("rotate", **SWING)])
    scene, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[1], ed.offsets[2]
    w = KeyedWeight(SWING["times"], SWING["weights"], "e")
    for f, t in enumerate(frame_times(ed)):
        Bs, Be = (scene.motion.to_body(P[f, a:b], t) for P in (src.positions, ed.positions))
        Q = Rotation.from_rotvec(np.radians(w(t) * 25.0) * np.array([0.0, 0.0, 1.0])).as_matrix()
        np.testing.assert_allclose(Be, Bs[0] + (Bs - Bs[0]) @ Q.T, rtol=0, atol=1e-13)


def test_swing_with_growing_amplitude():
    """Fig. 7 as a rigid guide with one rotate edit: at the keys the guide's tip direction (body
    frame) is at weight x angle from rest, alternating sides with growing amplitude."""
    cfg = guide_cfg([edit("rotate", **SWING)], fps=100.0, frames=100)
    scene, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[1], ed.offsets[2]

    def signed_angle(f):
        t = f / ed.fps
        d0, d1 = (scene.motion.to_body(P[f, b - 1], t) - scene.motion.to_body(P[f, a], t) for P in (src.positions, ed.positions))
        return np.degrees(np.arctan2(np.cross(d0, d1)[2], d0 @ d1))

    angles = [signed_angle(round(t * ed.fps)) for t in SWING["times"]]
    np.testing.assert_allclose(angles, [0.0, 25.0, -50.0, 75.0], rtol=0, atol=1e-9)


def test_zero_weight_changes_nothing():
    cfg = guide_cfg([edit("rotate", **{**SWING, "weights": [0.0, 0.0, 0.0, 0.0]}),
                     edit("displace", guide=0, offset=[0.1, 0.0, 0.0], times=[0.0], weights=[0.0])])
    _, src, ed = source_and_edited(cfg)
    np.testing.assert_array_equal(ed.positions, src.positions)
    # an edit that starts later leaves the frames before it exactly as they were
    cfg = guide_cfg([edit("rotate", **{**SWING, "times": [0.4, 0.8], "weights": [0.0, 1.0]})])
    _, src, ed = source_and_edited(cfg)
    before = frame_times(ed) <= 0.4
    np.testing.assert_array_equal(ed.positions[before], src.positions[before])
    assert not np.array_equal(ed.positions[~before], src.positions[~before])
    # ... and one keyed back to 0 leaves the frames after its last key exactly as they were
    cfg = guide_cfg([edit("rotate", **{**SWING, "times": [0.0, 0.2, 0.4], "weights": [0.0, 1.0, 0.0]})])
    _, src, ed = source_and_edited(cfg)
    after = frame_times(ed) >= 0.4
    np.testing.assert_array_equal(ed.positions[after], src.positions[after])
    assert not np.array_equal(ed.positions[~after], src.positions[~after])


DISPLACE = dict(guide=0, offset=[0.04, 0.0, 0.03], falloff=2.0, times=[0.0, 0.5, 1.0], weights=[0.0, 1.5, -0.5])


def test_displace_moves_the_tip_by_weight_times_the_body_offset_and_not_the_root():
    cfg = guide_cfg([edit("displace", **DISPLACE)])
    scene, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[0], ed.offsets[1]
    w = KeyedWeight(DISPLACE["times"], DISPLACE["weights"], "e")
    s = np.linspace(0.0, 1.0, b - a)   # a straight rest guide: evenly spaced vertices
    for f, t in enumerate(frame_times(ed)):
        R, _ = scene.motion.pose(t)
        move = ed.positions[f, a:b] - src.positions[f, a:b]
        np.testing.assert_allclose(move[-1], w(t) * R @ DISPLACE["offset"], rtol=0, atol=1e-15)
        np.testing.assert_allclose(move, w(t) * s[:, None] ** 2 * (R @ DISPLACE["offset"]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(ed.positions[:, a], src.positions[:, a])
    np.testing.assert_array_equal(ed.positions[:, b:], src.positions[:, b:])
    assert np.abs(edge_lengths(ed.positions[:, a:b]) - edge_lengths(src.positions[:, a:b])).max() > 1e-3  # stretches


def test_edits_compose_in_order():
    rot, disp = edit("rotate", **{**SWING, "guide": 0}), edit("displace", **DISPLACE)
    cfg = guide_cfg([rot, disp])
    scene, src, ed = source_and_edited(cfg)
    one = apply_edits(src.positions, src.offsets, src.fps, scene.motion, [rot])
    two = apply_edits(one, src.offsets, src.fps, scene.motion, [disp])
    np.testing.assert_array_equal(ed.positions, two)
    swapped = apply_edits(src.positions, src.offsets, src.fps, scene.motion, [disp, rot])
    assert np.abs(swapped - ed.positions).max() > 1e-3   # the order matters (rotating a displaced guide)


def test_edits_apply_on_top_of_a_simulated_guide():
    """The paper's workflow: a coarse best-guess guide simulation, then an edit of one guide."""
    cfg = guide_cfg([edit("rotate", **{**SWING, "times": [0.0, 0.2], "weights": [0.0, 1.0]})],
                    **{"guides.source": "simulated", "frames": 6})
    _, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[1], ed.offsets[2]
    assert np.abs(src.positions[-1] - src.positions[0]).max() > 1e-3      # the guides did simulate
    np.testing.assert_array_equal(ed.positions[:, :a + 1], src.positions[:, :a + 1])
    np.testing.assert_allclose(edge_lengths(ed.positions[:, a:b]), edge_lengths(src.positions[:, a:b]), rtol=1e-14)
    assert np.abs(ed.positions[-1, a:b] - src.positions[-1, a:b]).max() > 0.05


# ---------------------------------------------------------------------------------------------
# Keyframed guides
# ---------------------------------------------------------------------------------------------

def line(root, direction, n=4, length=0.3):
    d = np.asarray(direction, dtype=np.float64)
    return (np.asarray(root) + np.linspace(0, length, n)[:, None] * d / np.linalg.norm(d)).tolist()


def keyed_cfg(keys, **overrides):
    cfg = guide_cfg(**{"guides.source": "keyframed", "guides.count": 2, "guides.n_vertices": 4, **overrides})
    cfg.guides.keyframes = [GuideKeyframeConfig(time=t, points=p) for t, p in keys]
    return cfg


KEYS = [(0.2, line([0, 0, 0], [0, -1, 0]) + line([0.01, 0, 0], [0, -1, 0])),
        (0.6, line([0, 0, 0], [1, -1, 0]) + line([0.01, 0, 0], [0, -1, 1])),
        (0.8, line([0, 0, 0], [-1, -2, 0]) + line([0.01, 0, 0], [1, -1, 1]))]


def test_keyframed_guides_hit_their_keys_in_the_body_frame_and_keep_their_roots():
    cfg = keyed_cfg(KEYS, fps=50.0, frames=50)
    scene, _, anim = source_and_edited(cfg)
    body = np.stack([scene.motion.to_body(P, t) for P, t in zip(anim.positions, frame_times(anim))])
    for t, pts in KEYS:
        np.testing.assert_allclose(body[round(t * anim.fps)], pts, rtol=0, atol=1e-15)
    np.testing.assert_allclose(body[:round(0.2 * anim.fps)], np.repeat(body[[round(0.2 * anim.fps)]], 10, 0), atol=1e-15)
    np.testing.assert_allclose(body[round(0.8 * anim.fps):], np.broadcast_to(body[-1], body[40:].shape), atol=1e-15)
    for r in anim.offsets[:-1]:
        np.testing.assert_allclose(body[:, r], np.broadcast_to(KEYS[0][1][r], body[:, r].shape), rtol=0, atol=1e-15)

    def first_and_last_moves(fps):
        """Largest body-frame move in the frame after the first key and before the last one."""
        c = keyed_cfg(KEYS, fps=fps, frames=round(fps))
        a = build_guides(c, scene, c.frames, c.fps)
        B = np.stack([scene.motion.to_body(P, t) for P, t in zip(a.positions, frame_times(a))])
        i, j = round(0.2 * fps), round(0.8 * fps)
        return np.abs(B[i + 1] - B[i]).max(), np.abs(B[j] - B[j - 1]).max()

    # clamped cubic in time: zero velocity at the first and last key, so the move over one frame
    # next to them shrinks like h^2 (8x finer frames: 64x smaller; a non-zero velocity: 8x)
    coarse, fine = first_and_last_moves(50.0), first_and_last_moves(400.0)
    assert min(coarse) > 1e-4
    for c, f in zip(coarse, fine):
        assert f / c == pytest.approx(1 / 64, rel=0.1)


def test_keyframed_roots_within_tolerance_are_snapped_to_keyframe_0():
    """Roots keyed 1e-12 m apart are accepted (within ROOT_TOLERANCE) and held exactly where
    keyframe 0 puts them, at every frame."""
    keys = moved(1, lambda t, p: (t, [[c + 1e-12 for c in p[0]]] + p[1:]))
    cfg = keyed_cfg(keys)
    scene, _, anim = source_and_edited(cfg)
    ref = keyed_cfg(KEYS)
    exact = build_guides(ref, scene, ref.frames, ref.fps)
    np.testing.assert_array_equal(anim.positions[:, anim.offsets[:-1]], exact.positions[:, exact.offsets[:-1]])
    np.testing.assert_array_equal(anim.positions, exact.positions)


def test_keyframed_guides_take_edits_too():
    cfg = keyed_cfg(KEYS)
    cfg.guides.edits = [edit("displace", guide=1, offset=[0.0, 0.0, 0.05], times=[0.0], weights=[1.0])]
    _, src, ed = source_and_edited(cfg)
    a, b = ed.offsets[1], ed.offsets[2]
    np.testing.assert_array_equal(ed.positions[:, :a + 1], src.positions[:, :a + 1])
    assert np.abs(ed.positions[:, b - 1] - src.positions[:, b - 1]).max() == pytest.approx(0.05, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# Input errors name the config key
# ---------------------------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")
OK_ROT = dict(guide=1, axis=[0.0, 0.0, 1.0], angle_deg=20.0, times=[0.0, 0.5], weights=[0.0, 1.0])


@pytest.mark.parametrize("edits,key", [
    ([edit(**{**OK_ROT, "guide": 2})], "guides.edits[0].guide"),
    ([edit(**{**OK_ROT, "guide": -1})], "guides.edits[0].guide"),
    ([edit(**OK_ROT), edit(**{**OK_ROT, "guide": 5})], "guides.edits[1].guide"),
    ([edit(**{**OK_ROT, "weights": [0.0]})], "guides.edits[0].weights"),
    ([edit(**{**OK_ROT, "times": [0.0, 0.5, 1.0]})], "guides.edits[0].weights"),
    ([edit(**{**OK_ROT, "times": [0.5, 0.5]})], "guides.edits[0].times"),
    ([edit(**{**OK_ROT, "times": [0.5, 0.2]})], "guides.edits[0].times"),
    ([edit(**{**OK_ROT, "times": [], "weights": []})], "guides.edits[0].times"),
    ([edit(**{**OK_ROT, "times": [0.0, INF]})], "guides.edits[0].times"),
    ([edit(**{**OK_ROT, "weights": [0.0, NAN]})], "guides.edits[0].weights"),
    ([edit(**{**OK_ROT, "axis": [0.0, 0.0, 0.0]})], "guides.edits[0].axis"),
    ([edit(**{**OK_ROT, "axis": [0.0, NAN, 1.0]})], "guides.edits[0].axis"),
    ([edit(**{**OK_ROT, "axis": [0.0, 1.0]})], "guides.edits[0].axis"),
    ([edit(**{**OK_ROT, "angle_deg": INF})], "guides.edits[0].angle_deg"),
    ([edit("displace", guide=0, offset=[0.0, NAN, 0.0])], "guides.edits[0].offset"),
    ([edit("displace", guide=0, offset=[0.01, 0.0, 0.0], falloff=0.0)], "guides.edits[0].falloff"),
    ([edit("displace", guide=0, offset=[0.01, 0.0, 0.0], falloff=-1.0)], "guides.edits[0].falloff"),
    ([edit("displace", guide=0, offset=[0.01, 0.0, 0.0], falloff=NAN)], "guides.edits[0].falloff"),
    ([edit(**{**OK_ROT, "axis": [1.0, 0.0, 0.0], "angle_deg": 90.0, "weights": [0.0, 2.0]})], "guides.edits"),
], ids=lambda v: v if isinstance(v, str) else None)
def test_bad_edit_names_the_key(edits, key):
    cfg = guide_cfg(edits)
    scene = build_scene(cfg.scene)
    with pytest.raises(InputError) as info:
        build_guides(cfg, scene, cfg.frames, cfg.fps)
    assert info.value.where == key
    assert str(info.value).startswith(key + ":")


def test_root_turn_limit_is_the_documented_one():
    """A rotate edit may turn a guide's first edge up to just below MAX_ROOT_TURN_DEG."""
    ok = edit(**{**OK_ROT, "axis": [1.0, 0.0, 0.0], "angle_deg": MAX_ROOT_TURN_DEG - 1.0, "weights": [0.0, 1.0]})
    cfg = guide_cfg([ok])
    build_guides(cfg, build_scene(cfg.scene), cfg.frames, cfg.fps)


def moved(i, fn):
    keys = [(t, [list(p) for p in pts]) for t, pts in KEYS]
    keys[i] = fn(*keys[i])
    return keys


@pytest.mark.parametrize("keys,key", [
    ([], "guides.keyframes"),
    (moved(1, lambda t, p: (t, p[:-1])), "guides.keyframes[1].points"),                       # topology change
    (moved(1, lambda t, p: (t, p + [[0.0, -0.4, 0.0]])), "guides.keyframes[1].points"),
    (moved(0, lambda t, p: (t, [p[0][:2]] + p[1:])), "guides.keyframes[0].points"),           # 2 coordinates
    (moved(2, lambda t, p: (t, p[:5] + [[0.0, NAN, 0.0]] + p[6:])), "guides.keyframes[2].points"),
    (moved(1, lambda t, p: (t, p[:2] + [p[1]] + p[3:])), "guides.keyframes[1].points"),       # zero-length edge
    (moved(1, lambda t, p: (t, p[:4] + [[0.02, 0.0, 0.0]] + p[5:])), "guides.keyframes[1].points"),  # root moved
    (moved(1, lambda t, p: (0.2, p)), "guides.keyframes[1].time"),                            # not increasing
    (moved(2, lambda t, p: (0.5, p)), "guides.keyframes[2].time"),
    (moved(0, lambda t, p: (NAN, p)), "guides.keyframes[0].time"),
    (moved(2, lambda t, p: (t, line([0, 0, 0], [0, 1, 0]) + p[4:])), "guides.keyframes"),     # root edge flipped
], ids=lambda v: v if isinstance(v, str) else None)
def test_bad_keyframes_name_the_key(keys, key):
    cfg = keyed_cfg(keys)
    with pytest.raises(InputError) as info:
        build_guides(cfg, build_scene(cfg.scene), cfg.frames, cfg.fps)
    assert info.value.where == key
    assert str(info.value).startswith(key + ":")


# ---------------------------------------------------------------------------------------------
# The README's examples
# ---------------------------------------------------------------------------------------------

def readme_examples() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## Guide authoring", 1)[1].split("\n## ", 1)[0]
    return [block.split("```", 1)[0] for block in section.split("```yaml\n")[1:]]


def test_readme_guide_authoring_examples_build():
    """Every YAML example of the README's "Guide authoring" section composes against the schema
    on the wisp scene and builds a valid guide animation that the edits or keys do move."""
    from omegaconf import OmegaConf

    from hairexp.app.config import Config

    examples = readme_examples()
    assert len(examples) == 3
    for yaml_text in examples:
        cfg = OmegaConf.merge(OmegaConf.structured(Config), OmegaConf.create(yaml_text), {"frames": 70})
        scene = build_scene(cfg.scene)
        anim = build_guides(cfg, scene, cfg.frames, cfg.fps)
        assert anim.n_frames == 71 and anim.n_guides == cfg.guides.count
        if cfg.guides.edits:
            unedited = source_guides(cfg, scene, cfg.frames, cfg.fps)
            assert np.abs(anim.positions - unedited.positions).max() > 0.05
        else:
            assert np.abs(anim.positions[-1] - anim.positions[0]).max() > 0.05


# ---------------------------------------------------------------------------------------------
# Runs: guides.npz holds the authored animation; an edited guide is tracked
# ---------------------------------------------------------------------------------------------

def test_authored_guides_npz_reused_as_file_source(tmp_path):
    """A tracked run of an edited simulated guide (its second vertex turns with the edit, only the
    root stays on the body): the constraints hold, guides.npz stores the edited animation, and
    guides.source=file with no edits rebuilds exactly the same guide positions."""
    edits = [edit("rotate", guide=0, axis=[0.0, 0.0, 1.0], angle_deg=30.0, times=[0.0, 0.24], weights=[0.0, 1.0])]
    cfg = guide_cfg(edits, **{"guides.source": "simulated", "guides.count": 1, "frames": 8, "scene.n_strands": 8,
                              "scene.n_vertices": 10})
    summary = run(cfg, tmp_path / "authored")
    assert summary["status"] == "completed" and summary["converged_fraction"] == 1.0
    df = pd.read_parquet(tmp_path / "authored" / "metrics.parquet")
    assert (df["residual_rel_max"] <= 1e-8).all()
    scene = build_scene(cfg.scene)
    authored = build_guides(cfg, scene, cfg.frames, cfg.fps)
    with np.load(tmp_path / "authored" / "guides.npz") as g:
        np.testing.assert_array_equal(g["guide_positions"], authored.positions)
    assert np.abs(authored.positions - source_guides(cfg, scene, cfg.frames, cfg.fps).positions).max() > 0.05

    reuse = guide_cfg([], **{"guides.source": "file", "guides.file": str(tmp_path / "authored" / "guides.npz"),
                             "frames": 8, "scene.n_strands": 8, "scene.n_vertices": 10})
    again = build_guides(reuse, scene, reuse.frames, reuse.fps)
    np.testing.assert_array_equal(again.positions, authored.positions)
    np.testing.assert_array_equal(again.offsets, authored.offsets)
    assert again.fps == authored.fps


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------

def run_cli(args, out):
    """``python -m hairexp`` on a tiny goaling run; PYTHONPATH puts this checkout first."""
    env = dict(os.environ, CI="1", PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling", "variants=[]", "frames=2", "scene.n_strands=2",
                           "scene.n_vertices=5", "logging.rerun=false", f"hydra.run.dir={out}", *args],
                          cwd=out.parent, env=env, capture_output=True, text=True, timeout=120)


def test_cli_unknown_edit_kind_fails_at_compose(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(["guides.edits=[{guide: 0, kind: twist, times: [0.0], weights: [1.0]}]"], out)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)   # bad input, before Hydra starts
    assert "twist" in proc.stderr and "kind" in proc.stderr
    assert not (out / "summary.json").exists()   # stopped before the run started


def test_cli_bad_edit_value_exits_2_naming_the_key(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(["guides.edits=[{guide: 3, kind: rotate, angle_deg: 10.0, times: [0.0], weights: [1.0]}]"], out)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "guides.edits[0].guide" in lines[0], proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and "guides.edits[0].guide" in summary["error"]
