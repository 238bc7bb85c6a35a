"""Value clips (``output.usd_clips``, README "USD scenes"): a long run's result.usdc keeps its
per-frame samples in result.clips/<k>.usdc; opened with Usd.Stage.Open it reads exactly as the
single-layer stage, at every frame and between frames, and a failed write leaves nothing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom
from usd_helpers import source_cfg

import hairexp.io.usd_write as usd_write
from hairexp.app.builders import build_scene
from hairexp.app.run import run
from hairexp.io.usd_write import clipped, write_result_usd

FPS = 25.0
N = 11        # frames after the first: 3 clips of 4 frames (CLIP_FRAMES patched to 4), the last one short
CLIP = 4
TINY = ["experiment=goaling_smoke", "variants=[]", "scene.n_strands=3", "scene.n_vertices=6", "guides.source=rigid",
        "logging.rerun=false", "logging.progress=false"]


@pytest.fixture
def small_clips(monkeypatch):
    monkeypatch.setattr(usd_write, "CLIP_FRAMES", CLIP)


def frames_of(n: int = N):
    """A scene whose body and ball move (linear keys) beside still colliders, and random hair
    and guide frames."""
    scene = build_scene(source_cfg(frames=n).scene)
    rng = np.random.default_rng(7)
    pos = scene.strands.rest + 0.01 * rng.normal(size=(n + 1, *scene.strands.rest.shape))
    guides = rng.normal(size=(n + 1, 12, 3))
    return scene, pos, guides, np.array([0, 6, 12])


def times(n: int = N):
    """Every frame, quarter frames between them (interpolation across clip boundaries), and
    times before the first frame and after the last."""
    return [Usd.TimeCode.Default()] + [Usd.TimeCode(float(t)) for t in np.arange(-1.0, n + 1.75, 0.25)]


def assert_same_stage(path_a, path_b, n: int = N) -> int:
    """Every attribute of every prim of stage a reads the same from stage b (and b has no other
    prims), at the default time and at ``times``; returns the number of attributes compared
    that have time samples."""
    a, b = Usd.Stage.Open(str(path_a)), Usd.Stage.Open(str(path_b))
    assert [p.GetPath() for p in a.Traverse()] == [p.GetPath() for p in b.Traverse()]
    assert (b.GetStartTimeCode(), b.GetEndTimeCode(), b.GetTimeCodesPerSecond()) == (0, n, FPS)
    animated = 0
    for pa in a.Traverse():
        pb = b.GetPrimAtPath(pa.GetPath())
        assert pa.GetTypeName() == pb.GetTypeName()
        assert sorted(x.GetName() for x in pa.GetAttributes()) == sorted(x.GetName() for x in pb.GetAttributes())
        for xa in pa.GetAttributes():
            xb = pb.GetAttribute(xa.GetName())
            assert xb.GetTimeSamples() == xa.GetTimeSamples(), xa.GetPath()
            animated += bool(xa.GetTimeSamples())
            for t in times(n):
                va, vb = xa.Get(t), xb.Get(t)
                assert (va is None) == (vb is None), (xa.GetPath(), t)
                if va is not None:
                    np.testing.assert_array_equal(np.asarray(vb), np.asarray(va), err_msg=f"{xa.GetPath()} at {t}")
    return animated


@pytest.mark.parametrize("suffix", ["usdc", "usda"])
def test_clipped_stage_reads_as_one_layer(tmp_path, small_clips, suffix):
    """Points, extents and transforms of the clipped stage equal the single layer's at every
    frame; the hair's time samples are 0..N; the root layer holds no time sample."""
    scene, pos, guides, goff = frames_of()
    one, clipped_dir = tmp_path / "one", tmp_path / "clipped"
    one.mkdir(), clipped_dir.mkdir()
    write_result_usd(one / f"result.{suffix}", scene, pos, guides, goff, FPS, clips="never")
    write_result_usd(clipped_dir / f"result.{suffix}", scene, pos, guides, goff, FPS, clips="always")
    assert [p.name for p in one.iterdir()] == [f"result.{suffix}"]
    assert sorted(str(p.relative_to(clipped_dir)) for p in clipped_dir.rglob("*")) == [
        "result.clips", "result.clips/0.usdc", "result.clips/1.usdc", "result.clips/2.usdc",
        "result.clips/manifest.usdc", f"result.{suffix}"]
    # body, ball, guide points + extent, hair points + extent
    assert assert_same_stage(one / f"result.{suffix}", clipped_dir / f"result.{suffix}") == 6
    stage = Usd.Stage.Open(str(clipped_dir / f"result.{suffix}"))
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == [float(f) for f in range(N + 1)]
    for f in range(N + 1):   # and the values are the frames given
        np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(f)), pos[f].astype(np.float32))
    root = Sdf.Layer.FindOrOpen(str(clipped_dir / f"result.{suffix}"))
    specs = []
    root.Traverse("/", lambda p: specs.append(p))
    assert not [p for p in specs if p.IsPropertyPath() and root.ListTimeSamplesForPath(p)]
    api = Usd.ClipsAPI(stage.GetPrimAtPath("/Root"))
    assert [a.path for a in api.GetClipAssetPaths()] == [f"./result.clips/{k}.usdc" for k in range(3)]
    assert [tuple(x) for x in api.GetClipActive()] == [(0, 0), (4, 1), (8, 2)]
    for k in range(3):   # clip k holds frames 4k .. 4k + 4 (the next clip's first too), the last up to N
        clip = Sdf.Layer.FindOrOpen(str(clipped_dir / "result.clips" / f"{k}.usdc"))
        assert clip.ListTimeSamplesForPath("/Root/Result/Hair.points") == [float(f) for f in
                                                                           range(4 * k, min(4 * k + 4, N) + 1)]


def test_moved_run_folder_still_reads(tmp_path, small_clips):
    """Asset paths are relative: the folder moved elsewhere reads the same."""
    scene, pos, guides, goff = frames_of()
    (tmp_path / "a").mkdir()
    write_result_usd(tmp_path / "a" / "result.usdc", scene, pos, guides, goff, FPS, clips="never")
    (tmp_path / "b").mkdir()
    write_result_usd(tmp_path / "b" / "result.usdc", scene, pos, guides, goff, FPS, clips="always")
    shutil.move(tmp_path / "b", tmp_path / "moved")
    assert assert_same_stage(tmp_path / "a" / "result.usdc", tmp_path / "moved" / "result.usdc") == 6


def test_flattened_copy_is_one_file(tmp_path, small_clips):
    """README: ``Usd.Stage.Open(p).Export(out)`` gives one self-contained file with the same
    samples (it still reads with the clips folder gone)."""
    scene, pos, guides, goff = frames_of()
    write_result_usd(tmp_path / "one.usdc", scene, pos, guides, goff, FPS, clips="never")
    (tmp_path / "run").mkdir()
    write_result_usd(tmp_path / "run" / "result.usdc", scene, pos, guides, goff, FPS, clips="always")
    assert Usd.Stage.Open(str(tmp_path / "run" / "result.usdc")).Export(str(tmp_path / "flat.usdc"))
    shutil.rmtree(tmp_path / "run")
    flat = Sdf.Layer.FindOrOpen(str(tmp_path / "flat.usdc"))
    assert not flat.GetExternalReferences() and "clips" not in flat.GetPrimAtPath("/Root").ListInfoKeys()
    assert flat.ListTimeSamplesForPath("/Root/Result/Hair.points") == [float(f) for f in range(N + 1)]
    assert assert_same_stage(tmp_path / "one.usdc", tmp_path / "flat.usdc") == 6


def test_policy(tmp_path, small_clips):
    """auto: one layer up to CLIP_FRAMES frames, clips beyond; never / always whatever the length."""
    assert [clipped("auto", n) for n in (0, CLIP, CLIP + 1)] == [False, False, True]
    assert [clipped("never", n) for n in (0, 1000)] == [False, False]
    assert [clipped("always", n) for n in (0, 1000)] == [True, True]
    with pytest.raises(ValueError, match="usd_clips"):
        clipped("sometimes", 10)
    for n, expect in ((CLIP, ["result.usdc"]), (CLIP + 1, ["result.clips", "result.usdc"])):
        out = tmp_path / str(n)
        out.mkdir()
        scene, pos, guides, goff = frames_of(n)
        write_result_usd(out / "result.usdc", scene, pos, guides, goff, FPS)   # the default: auto
        assert sorted(p.name for p in out.iterdir()) == expect
    # one clip: frames=0 under always
    out = tmp_path / "zero"
    out.mkdir()
    scene, pos, guides, goff = frames_of(0)
    write_result_usd(out / "result.usdc", scene, pos, guides, goff, FPS, clips="always")
    stage = Usd.Stage.Open(str(out / "result.usdc"))   # kept: a prim does not keep its stage alive
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == [0.0]
    np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(0)), pos[0].astype(np.float32))


def test_rewrite_replaces_the_clips(tmp_path, small_clips):
    """A stage written again replaces the earlier clips; a single layer written over a clipped
    stage removes them."""
    scene, pos, guides, goff = frames_of()
    write_result_usd(tmp_path / "result.usdc", scene, pos, guides, goff, FPS, clips="always")
    write_result_usd(tmp_path / "result.usdc", scene, pos[:6], guides[:6], goff, FPS, clips="always")
    assert sorted(p.name for p in (tmp_path / "result.clips").iterdir()) == ["0.usdc", "1.usdc", "manifest.usdc"]
    stage = Usd.Stage.Open(str(tmp_path / "result.usdc"))   # kept: a prim does not keep its stage alive
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == [float(f) for f in range(6)]
    write_result_usd(tmp_path / "result.usdc", scene, pos, guides, goff, FPS, clips="never")
    assert [p.name for p in tmp_path.iterdir()] == ["result.usdc"]


def test_failed_clipped_write_leaves_nothing(tmp_path, small_clips, monkeypatch):
    """A non-finite frame in the last clip, or a failure of the root layer after the clips were
    renamed: neither result.usdc nor result.clips/ nor a temporary is left."""
    scene, pos, guides, goff = frames_of()
    bad = pos.copy()
    bad[N - 1, 2, 1] = np.nan
    with pytest.raises(AssertionError, match=f"non-finite positions \\(frame {N - 1}\\)"):
        write_result_usd(tmp_path / "result.usdc", scene, bad, guides, goff, FPS, clips="always")
    assert list(tmp_path.iterdir()) == []

    def failing_save(stage, path):
        assert (tmp_path / "result.clips" / "2.usdc").is_file()   # the clips are in place by now
        raise OSError("cannot write (injected)")

    monkeypatch.setattr(usd_write, "save", failing_save)
    with pytest.raises(OSError, match="injected"):
        write_result_usd(tmp_path / "result.usdc", scene, pos, guides, goff, FPS, clips="always")
    assert list(tmp_path.iterdir()) == []


def test_run_writes_clips(hydra_conf, tmp_path, small_clips):
    """A run with output.usd_clips=always: result.usdc and result.clips/ in the run folder, every
    frame of the hair in the stage, as in result.npz."""
    out = tmp_path / "run"
    s = run(hydra_conf([*TINY, "frames=6", "output.usd_clips=always"]), out)
    assert s["status"] == "completed" and s["config"]["output"]["usd_clips"] == "always"
    assert sorted(p.name for p in out.iterdir()) == ["guides.npz", "metrics.parquet", "result.clips", "result.npz",
                                                     "result.usdc", "summary.json"]
    assert sorted(p.name for p in (out / "result.clips").iterdir()) == ["0.usdc", "1.usdc", "manifest.usdc"]
    stage = Usd.Stage.Open(str(out / "result.usdc"))   # kept: a prim does not keep its stage alive
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == [float(f) for f in range(7)]
    with np.load(out / "result.npz") as z:
        P = z["positions"]
    for f in range(7):
        np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(f)), P[f].astype(np.float32))


def test_failed_run_removes_the_clips(hydra_conf, tmp_path, small_clips, monkeypatch):
    """A run failing after its stage was written: no result.usdc, no result.clips/."""
    from hairexp.outputs.files import ResultRecorder

    close = ResultRecorder.close
    calls = []

    def failing_close(self):
        calls.append(1)
        close(self)
        if len(calls) == 1:   # the close right after write_result_usd
            assert (tmp_path / "result.clips" / "manifest.usdc").is_file()
            raise OSError("injected after the USD write")

    monkeypatch.setattr(ResultRecorder, "close", failing_close)
    with pytest.raises(OSError, match="injected"):
        run(hydra_conf([*TINY, "frames=6", "output.usd_clips=always"]), tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "failed" and "injected" in summary["error"]
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith("result")]
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]


def test_config_key_is_documented():
    """The schema's default is auto; the other values parse; README names the key."""
    from omegaconf import OmegaConf

    from hairexp.app.config import Config, UsdClips

    cfg = OmegaConf.structured(Config)
    assert cfg.output.usd_clips == UsdClips.auto
    assert {v.value for v in UsdClips} == set(usd_write.CLIP_POLICIES)
    assert "output.usd_clips" in (Path(__file__).resolve().parents[1] / "README.md").read_text()


def test_clipped_result_reimports(tmp_path, small_clips):
    """``experiment=from_usd`` reads a clipped result as the single layer: the body's and the
    colliders' motions, the guides and the hair at rest."""
    from usd_helpers import usd_cfg

    from hairexp.app.guides import build_guides
    from hairexp.io.usd_read import stage_timing

    scene, pos, _, _ = frames_of()
    rng = np.random.default_rng(5)   # guides of the scene's layout (the reader checks them)
    gscene = build_scene(source_cfg(frames=N).scene)
    st = gscene.strands   # each guide the first 6 vertices of a strand (not across two strands: a fold)
    base = np.concatenate([st.rest[st.offsets[k]:st.offsets[k] + 6] for k in (0, 1)])
    guides = np.stack([base + 0.001 * rng.normal(size=(12, 3)) for _ in range(N + 1)])
    goff = np.array([0, 6, 12])
    read = {}
    for mode in ("never", "always"):
        (tmp_path / mode).mkdir()
        write_result_usd(tmp_path / mode / "result.usdc", scene, pos, guides, goff, FPS, clips=mode)
        cfg = stage_timing(usd_cfg(tmp_path / mode / "result.usdc"))
        s = build_scene(cfg.scene)
        read[mode] = (cfg, s, build_guides(cfg, s, cfg.frames, cfg.fps))
    (c1, s1, g1), (c2, s2, g2) = read["never"], read["always"]
    assert (c2.frames, c2.fps) == (c1.frames, c1.fps) == (N, FPS)
    np.testing.assert_array_equal(s2.root_body, s1.root_body)
    assert len(s2.colliders) == len(s1.colliders) == 5
    for t in np.arange(0, N + 1) / FPS:
        for m1, m2 in [(s1.motion, s2.motion), *((a.motion, b.motion) for a, b in zip(s1.colliders, s2.colliders))]:
            for x, y in zip(m1.pose(t), m2.pose(t)):
                np.testing.assert_array_equal(y, x)
        np.testing.assert_array_equal(g2.shape_at(t), g1.shape_at(t))
