"""USD exchange: a scene written in the input layout reads back exactly (up to USD's float32
points), a run from that stage reproduces the run of the config, and every run's result stage
(result.usdc by default, result.usda with output.usd_format=usda) holds the result frames under
the documented prims."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from omegaconf import OmegaConf
from pxr import Sdf, Usd, UsdGeom
from usd_helpers import (COLLIDERS, FRAMES, GUIDE_VERTICES, MOTION, N_GUIDES, N_STRANDS, N_VERTICES, edit_stage,
                         scene_overrides, set_colliders, source_cfg, usd_cfg, vec3f, write_stage)

from hairexp.errors import InputError
from hairexp.app.export_scene import export_scene, main as export_main
from hairexp.io.usd_read import stage_timing
from hairexp.io.usd_write import write_result_usd
from hairexp.model.colliders import Box, Capsule, Cylinder, Plane, Sphere
from hairexp.app.run import run
from hairexp.app.builders import build_scene
from hairexp.app.guides import build_guides

FPS = 25.0
LENGTH = 0.3          # m, hair length of the test scene
#: Run round trip: USD stores points as float32 (half an ulp at 0.3 m is 1.5e-8 m).
FLOAT32_REL = 1e-6
SHAPES = {"ball": (Sphere, "Sphere"), "crate": (Box, "Cube"), "wheel": (Cylinder, "Cylinder"),
          "pole": (Capsule, "Capsule"), "floor": (Plane, "Plane")}


def f32(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def assert_same_motion(m1, m2, times, tol=1e-12):
    for t in times:
        (R1, T1), (R2, T2) = m1.pose(t), m2.pose(t)
        np.testing.assert_allclose(R2, R1, rtol=0, atol=tol, err_msg=f"t={t}")
        np.testing.assert_allclose(T2, T1, rtol=0, atol=tol, err_msg=f"t={t}")
        for a, b in zip(m1.velocity(t), m2.velocity(t)):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-9, err_msg=f"velocity t={t}")


def read(path, **extra):
    cfg = stage_timing(usd_cfg(path, **extra))
    scene = build_scene(cfg.scene)
    return cfg, scene, build_guides(cfg, scene, cfg.frames, cfg.fps)


def test_scene_round_trip(tmp_path):
    """Hair (float32), body motion, guides (float32) and colliders come back as written."""
    path = tmp_path / "scene.usda"
    scene, guides = write_stage(path, source_cfg())
    cfg, s2, g2 = read(path)
    assert (cfg.frames, cfg.fps) == (FRAMES, FPS)
    np.testing.assert_array_equal(s2.strands.offsets, scene.strands.offsets)
    np.testing.assert_array_equal(s2.root_body, f32(scene.root_body))
    np.testing.assert_allclose(s2.strands.rest, scene.strands.rest, rtol=0, atol=3e-8)
    times = np.linspace(-0.04, 0.3, 69)  # every half frame, before, during and after the keys
    assert_same_motion(scene.motion, s2.motion, times)
    assert s2.motion.interpolation == "linear" and len(s2.motion.times) == len(MOTION["scene.motion.times"])
    np.testing.assert_array_equal(g2.offsets, guides.offsets)
    assert g2.n_frames == FRAMES + 1 and g2.fps == FPS
    for f in range(FRAMES + 1):
        np.testing.assert_array_equal(g2.positions[f], f32(guides.shape_at(f / FPS)))
    assert [c.name for c in s2.colliders] == [c["name"] for c in COLLIDERS]
    for c1, c2 in zip(scene.colliders, s2.colliders):
        assert type(c2) is SHAPES[c1.name][0]
        for k in ("radius", "half_length", "half_height", "spin", "thickness", "friction"):
            if hasattr(c1, k):
                assert getattr(c2, k) == pytest.approx(getattr(c1, k), rel=1e-12), (c1.name, k)
        if isinstance(c1, Box):
            np.testing.assert_allclose(c2.half_extents, c1.half_extents, rtol=1e-12)
        assert_same_motion(c1.motion, c2.motion, times)


def test_cubic_motion_is_sampled_per_frame(tmp_path, caplog):
    path = tmp_path / "cubic.usda"
    with caplog.at_level(logging.WARNING):
        scene, _ = write_stage(path, source_cfg(colliders=[], **{"scene.motion.interpolation": "cubic"}))
    assert "re-imports as linear" in caplog.text
    _, s2, _ = read(path)
    np.testing.assert_allclose(s2.motion.times, np.arange(FRAMES + 1) / FPS, rtol=0, atol=1e-15)
    for f in range(FRAMES + 1):  # exact at frames (velocities differ: cubic vs linear)
        for a, b in zip(scene.motion.pose(f / FPS), s2.motion.pose(f / FPS)):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)
    mid = 2.5 / FPS
    assert np.abs(scene.motion.pose(mid)[1] - s2.motion.pose(mid)[1]).max() > 1e-6  # linear in between


def test_hair_outside_the_body_is_taken_to_body_space(tmp_path):
    """Hair authored in world space at another prim (scene.usd_hair) with its own transform."""
    path = tmp_path / "scene.usda"
    scene, _ = write_stage(path, source_cfg(colliders=[]))
    shift = np.array([0.1, 0.2, -0.3])

    def move_hair(stage):
        curves = UsdGeom.BasisCurves.Define(stage, "/Root/HairWorld")
        curves.CreateCurveVertexCountsAttr(list(scene.strands.counts.tolist()))
        curves.CreatePointsAttr(vec3f(scene.strands.rest - shift))  # rest at time 0, in world space
        UsdGeom.Xformable(curves).AddTranslateOp().Set(tuple(shift))
        stage.RemovePrim("/Root/Body/Hair")

    edit_stage(path, move_hair)
    _, s2, _ = read(path, **{"scene.usd_hair": "/Root/HairWorld"})
    np.testing.assert_allclose(s2.strands.rest, scene.strands.rest, rtol=0, atol=1e-7)
    np.testing.assert_allclose(s2.root_body, scene.root_body, rtol=0, atol=1e-7)


def test_timing_from_the_stage(tmp_path):
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    double_rate = stage_timing(usd_cfg(path, fps=50.0))
    assert (double_rate.frames, double_rate.fps) == (2 * FRAMES, 50.0)
    given = stage_timing(usd_cfg(path, frames=3))
    assert (given.frames, given.fps) == (3, FPS)
    wisp = source_cfg(colliders=[], frames=None)
    with pytest.raises(InputError, match="^frames: null .* needs scene.builder=usd"):
        stage_timing(wisp)


# --------------------------------------------------------------------------------------------
# runs: the config's scene, the same scene through USD, and a second round trip
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from helpers import CONF_DIR

    tmp = tmp_path_factory.mktemp("usd_runs")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            src = compose(config_name="config", overrides=["experiment=goaling", "variants=[]", "controller=tracking", "logging=off"])
            for k, v in scene_overrides().items():
                OmegaConf.update(src, k, v, merge=False)
            set_colliders(src)
            export_scene(src, tmp / "scene.usda")
            args = ["experiment=from_usd", "logging=off", "tracking.points_per_guide=4", "collision.strain_limit=0.0"]
            via_usd = compose(config_name="config", overrides=[*args, f"scene.usd={tmp / 'scene.usda'}"])
            export_scene(via_usd, tmp / "again.usda")  # the imported scene, written again
            again = compose(config_name="config", overrides=[*args, f"scene.usd={tmp / 'again.usda'}"])
    finally:
        GlobalHydra.instance().clear()
    out = {}
    OmegaConf.update(via_usd, "output.usd_format", "usda")   # the ASCII stage for this one
    for name, cfg in (("config", src), ("usd", via_usd), ("again", again)):
        summary = run(cfg, tmp / name)
        assert summary["status"] == "completed"
        out[name] = tmp / name
    return out


def result(folder) -> dict:
    with np.load(folder / "result.npz") as r:
        return {k: r[k] for k in r.files}


def test_run_round_trip(runs):
    a, b, c = (result(runs[k]) for k in ("config", "usd", "again"))
    moved = np.abs(a["positions"][-1] - a["positions"][0]).max()
    assert moved > 0.01  # the comparison is not vacuous: the hair moved centimetres
    for k in ("positions", "guide_positions", "targets", "com"):
        assert b[k].shape == a[k].shape, k
        np.testing.assert_allclose(b[k], a[k], rtol=0, atol=FLOAT32_REL * LENGTH, err_msg=k)
        np.testing.assert_allclose(c[k], b[k], rtol=0, atol=1e-12 * LENGTH, err_msg=k)  # float32 data: exact
    np.testing.assert_array_equal(b["cluster_of_vertex"], a["cluster_of_vertex"])
    assert (b["cluster_of_vertex"] >= 0).any()
    import pandas as pd

    for k in ("config", "usd"):
        df = pd.read_parquet(runs[k] / "metrics.parquet")
        assert (df["controller"] == "tracking").all() and df["contacts"].sum() > 0  # tracked, and the ball hit
    summary = json.loads((runs["usd"] / "summary.json").read_text())
    assert summary["config"]["frames"] == FRAMES and summary["config"]["fps"] == FPS  # null resolved


def test_result_usd_formats(runs):
    """result.usdc (binary crate) by default; output.usd_format=usda writes result.usda (ASCII)."""
    assert (runs["config"] / "result.usdc").is_file() and not (runs["config"] / "result.usda").exists()
    assert (runs["config"] / "result.usdc").read_bytes()[:8] == b"PXR-USDC"
    assert (runs["usd"] / "result.usda").read_bytes()[:5] == b"#usda" and not (runs["usd"] / "result.usdc").exists()
    a, b = (Usd.Stage.Open(str(runs[k] / n)) for k, n in (("config", "result.usdc"), ("usd", "result.usda")))
    pa, pb = (UsdGeom.BasisCurves.Get(s, "/Root/Result/Hair").GetPointsAttr() for s in (a, b))
    assert pa.GetTimeSamples() == pb.GetTimeSamples() == list(range(FRAMES + 1))


def test_result_usd_holds_the_frames(runs):
    folder = runs["config"]
    r = result(folder)
    stage = Usd.Stage.Open(str(folder / "result.usdc"))
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES)
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    types = {p.GetPath().pathString: p.GetTypeName() for p in stage.Traverse()}
    expected = {"/Root": "Xform", "/Root/Body": "Xform", "/Root/Body/Hair": "BasisCurves",
                "/Root/Guides": "BasisCurves", "/Root/Result/Hair": "BasisCurves",
                **{f"/Root/Colliders/{n}": t for n, (_, t) in SHAPES.items()}}
    assert {k: types.get(k) for k in expected} == expected
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    guides = UsdGeom.BasisCurves.Get(stage, "/Root/Guides")
    assert list(hair.GetCurveVertexCountsAttr().Get()) == [N_VERTICES] * N_STRANDS
    assert list(guides.GetCurveVertexCountsAttr().Get()) == [GUIDE_VERTICES] * N_GUIDES
    assert hair.GetPointsAttr().GetTimeSamples() == list(range(FRAMES + 1))
    cfg = source_cfg()
    scene = build_scene(cfg.scene)
    body = UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Body"))
    for k in range(FRAMES + 1):
        np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(k)), r["positions"][k].astype(np.float32))
        np.testing.assert_array_equal(np.asarray(guides.GetPointsAttr().Get(k)),
                                      r["guide_positions"][k].astype(np.float32))
        R, T = scene.motion.pose(k / FPS)
        M = np.array(body.ComputeLocalToWorldTransform(k))
        np.testing.assert_allclose(M[:3, :3].T, R, atol=1e-12)
        np.testing.assert_allclose(M[3, :3], T, atol=1e-12)
    rest = UsdGeom.BasisCurves.Get(stage, "/Root/Body/Hair").GetPointsAttr()
    assert rest.GetTimeSamples() == []
    np.testing.assert_array_equal(np.asarray(rest.Get()), scene.root_body.astype(np.float32))


def test_result_usd_reimports(runs):
    """result.usdc is itself a scene in the input layout."""
    r = result(runs["config"])
    cfg, scene, guides = read(runs["config"] / "result.usdc")
    assert cfg.frames == FRAMES and scene.strands.n_strands == N_STRANDS and len(scene.colliders) == len(COLLIDERS)
    np.testing.assert_allclose(scene.strands.rest, r["positions"][0], rtol=0, atol=3e-8)
    np.testing.assert_array_equal(guides.positions, f32(r["guide_positions"]))


def test_failed_result_write_leaves_no_file(tmp_path):
    scene = build_scene(source_cfg(colliders=[]).scene)
    pos = np.stack([scene.strands.rest, scene.strands.rest])
    pos[1, 3, 0] = np.nan
    with pytest.raises(AssertionError, match="non-finite positions"):
        write_result_usd(tmp_path / "result.usda", scene, pos, np.zeros((2, 0, 3)), np.zeros(1, int), FPS)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", ["usdc", "usda"])
def test_result_usd_saved_in_blocks(tmp_path, monkeypatch, suffix):
    """The result stage is saved every SAVE_BYTES of samples (here: every frame); the file holds
    every frame all the same, and no temporary file is left."""
    import hairexp.io.usd_write as usd_write

    monkeypatch.setattr(usd_write, "SAVE_BYTES", 1)
    scene = build_scene(source_cfg(colliders=[]).scene)
    rng = np.random.default_rng(3)
    pos = scene.strands.rest + 0.01 * rng.normal(size=(7, *scene.strands.rest.shape))
    write_result_usd(tmp_path / f"result.{suffix}", scene, pos, np.zeros((7, 0, 3)), np.zeros(1, int), FPS)
    assert [p.name for p in tmp_path.iterdir()] == [f"result.{suffix}"]
    stage = Usd.Stage.Open(str(tmp_path / f"result.{suffix}"))
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == list(range(7))
    for k in range(7):
        np.testing.assert_array_equal(np.asarray(hair.GetPointsAttr().Get(k)), pos[k].astype(np.float32))


def test_export_scene_command(tmp_path, capsys):
    path = tmp_path / "goaling.usda"
    assert export_main([str(path), "experiment=goaling", "variants=[]", "frames=3", "scene.n_strands=3", "scene.n_vertices=5"]) == 0
    assert "3 strands" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == 3 and stage.GetPrimAtPath("/Root/Guides").IsA(UsdGeom.BasisCurves)
    assert export_main([str(tmp_path / "bad.usda"), "experiment=goaling", "variants=[]", "scene.length=-1"]) == 2
    assert "hairexp: error: scene.length" in capsys.readouterr().err
    assert not (tmp_path / "bad.usda").exists()


def in_centimetres(path, out) -> None:
    """The stage at ``path`` (metres) rewritten in centimetres as Maya writes them: metersPerUnit
    0.01 and every length times 100 (curve points at every time, the transforms' translations,
    the colliders' radius, height, size and hairexp:thickness); rotations and Cube scales as they were."""
    from pxr import Gf, Sdf

    stage = Usd.Stage.Open(str(path))
    stage.GetRootLayer().Export(str(out))
    stage = Usd.Stage.Open(str(out))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            name = attr.GetName()
            times = [Usd.TimeCode.Default()] + [Usd.TimeCode(t) for t in attr.GetTimeSamples()]
            for tc in times:
                v = attr.Get(tc)
                if v is None or (tc.IsDefault() and not attr.HasAuthoredValue()):
                    continue
                if name == "points":
                    attr.Set(type(v)([p * 100.0 for p in v]), tc)
                elif name == "xformOp:transform":
                    M = Gf.Matrix4d(v)
                    M.SetRow(3, Gf.Vec4d(M[3][0] * 100, M[3][1] * 100, M[3][2] * 100, 1.0))
                    attr.Set(M, tc)
                elif name.startswith("xformOp:translate"):
                    attr.Set(v * 100.0, tc)
                elif name in ("radius", "height", "size", "hairexp:thickness"):
                    attr.Set(v * 100.0, tc)
                elif name in ("extent", "widths"):
                    attr.Set(type(v)([e * 100.0 for e in v]), tc)
    stage.GetRootLayer().Save()


def test_a_stage_in_centimetres_reads_as_the_same_scene_in_metres(tmp_path):
    """metersPerUnit 0.01 (Maya's centimetres): the hair, guides, body motion and every collider's
    size and motion read as from the same stage in metres, to float32 round-off of the points."""
    path, cm = tmp_path / "scene.usda", tmp_path / "scene_cm.usda"
    write_stage(path, source_cfg())
    in_centimetres(path, cm)
    assert UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(str(cm))) == 0.01
    (cfg, s1, g1), (cfg2, s2, g2) = read(path), read(cm)
    assert (cfg2.frames, cfg2.fps) == (cfg.frames, cfg.fps)
    np.testing.assert_allclose(s2.root_body, s1.root_body, rtol=0, atol=1e-8)
    np.testing.assert_allclose(s2.strands.rest, s1.strands.rest, rtol=0, atol=1e-8)
    assert float(np.abs(s2.strands.rest).max()) < 2.0     # metres (the scene is 1 m across), not centimetres
    for f in range(cfg.frames + 1):
        np.testing.assert_allclose(g2.positions[f], g1.positions[f], rtol=0, atol=1e-8)
    times = np.linspace(-0.04, 0.3, 35)
    assert_same_motion(s1.motion, s2.motion, times, tol=1e-12)
    assert [c.name for c in s2.colliders] == [c.name for c in s1.colliders]
    for c1, c2 in zip(s1.colliders, s2.colliders):
        assert type(c2) is type(c1)
        for k in ("radius", "half_length", "half_height", "spin", "thickness", "friction"):
            if hasattr(c1, k):
                assert getattr(c2, k) == pytest.approx(getattr(c1, k), rel=1e-12), (c1.name, k)
        if isinstance(c1, Box):
            np.testing.assert_allclose(c2.half_extents, c1.half_extents, rtol=1e-12)
        assert_same_motion(c1.motion, c2.motion, times, tol=1e-12)


@pytest.mark.parametrize("mpu", [0.0, -0.01, float("inf"), float("nan")])
def test_a_stage_whose_meters_per_unit_is_no_length_is_refused(tmp_path, mpu):
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    edit_stage(path, lambda s: UsdGeom.SetStageMetersPerUnit(s, mpu))
    with pytest.raises(InputError, match=r"metersPerUnit is .*; it must be a number > 0") as info:
        read(path)
    assert info.value.where == f"scene.usd={path}"


def test_a_z_up_stage_reads_as_the_same_scene_turned_to_y_up(tmp_path):
    """upAxis Z (Blender's stages): the world is turned by -90 degrees about X to hairexp's Y up.
    The test stage made Z up by turning its whole /Root by +90 degrees about X (its up, +Y, now
    along +Z, and upAxis Z) reads as the Y-up stage: hair, guides, body and collider motions
    within round-off.  Each prim's own axes are not turned: the capsule along its own Y stays one."""
    import shutil

    from pxr import Gf

    path, zup = tmp_path / "scene.usda", tmp_path / "scene_zup.usda"
    write_stage(path, source_cfg())
    shutil.copyfile(path, zup)

    def turn(stage):
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        op = UsdGeom.Xformable(stage.GetPrimAtPath("/Root")).AddTransformOp()
        op.Set(Gf.Matrix4d(1, 0, 0, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1))   # (x, y, z) -> (x, -z, y)
    edit_stage(zup, turn)

    def guides_in_usd_world(p):   # frame 0's guide points in the stage's own world (USD's view, no turn)
        stage = Usd.Stage.Open(str(p))
        pts = np.array(UsdGeom.BasisCurves(stage.GetPrimAtPath("/Root/Guides")).GetPointsAttr().Get(0))
        M = np.array(UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Guides")).ComputeLocalToWorldTransform(0))
        return pts @ M[:3, :3] + M[3, :3]
    a, b = guides_in_usd_world(path), guides_in_usd_world(zup)
    np.testing.assert_allclose(b, np.stack([a[:, 0], -a[:, 2], a[:, 1]], 1), rtol=0, atol=1e-7)   # up is Z there
    assert np.ptp(a[:, 1]) > 0.05   # the guides hang: a real turn, not a no-op
    (cfg, s1, g1), (cfg2, s2, g2) = read(path), read(zup)
    np.testing.assert_allclose(s2.strands.rest, s1.strands.rest, rtol=0, atol=1e-12)
    for f in range(cfg.frames + 1):
        np.testing.assert_allclose(g2.positions[f], g1.positions[f], rtol=0, atol=1e-12)
    times = np.linspace(-0.04, 0.3, 35)
    assert_same_motion(s1.motion, s2.motion, times, tol=1e-12)
    assert [type(c) for c in s2.colliders] == [type(c) for c in s1.colliders]
    for c1, c2 in zip(s1.colliders, s2.colliders):
        assert_same_motion(c1.motion, c2.motion, times, tol=1e-12)


def test_hair_in_several_curve_prims_reads_as_one(tmp_path, caplog):
    """scene.usd_hair naming a parent prim: every active BasisCurves under it is hair, in the
    stage's order, each with its own transform (a group exported with an offset of its own).
    The test stage's hair split into two such groups under a Scope reads as the one-prim hair
    (rest positions within float32 round-off of the moved group); an inactive third group is
    said and not used."""
    from pxr import Gf, Vt

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    stage = Usd.Stage.Open(str(path))
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Root/Body/Hair"))
    P = np.array(hair.GetPointsAttr().Get(), dtype=np.float64)
    counts = np.array(hair.GetCurveVertexCountsAttr().Get())
    cut = int(counts[:2].sum())
    UsdGeom.Scope.Define(stage, "/Root/Body/Groups")
    shift = np.array([0.01, -0.02, 0.03])
    for name, pts, cnt, move in (("a", P[:cut], counts[:2], None), ("b", P[cut:], counts[2:], shift),
                                 ("c", P[:cut], counts[:2], None)):
        g = UsdGeom.BasisCurves.Define(stage, f"/Root/Body/Groups/{name}")
        g.CreateTypeAttr("linear")
        g.CreateCurveVertexCountsAttr(Vt.IntArray([int(c) for c in cnt]))
        if move is not None:
            g.AddTranslateOp().Set(Gf.Vec3d(*move))
            pts = pts - move
        g.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*p) for p in pts]))
    stage.GetPrimAtPath("/Root/Body/Groups/c").SetActive(False)
    stage.GetRootLayer().Save()
    _, one, _ = read(path)
    with caplog.at_level(logging.WARNING):
        _, groups, _ = read(path, **{"scene.usd_hair": "/Root/Body/Groups"})
    assert "inactive hair curves not used: /Root/Body/Groups/c" in caplog.text
    np.testing.assert_array_equal(groups.strands.offsets, one.strands.offsets)
    # group b's points were stored as float32 after the shift: a float32 ulp at 0.3 m is 3e-8
    np.testing.assert_allclose(groups.strands.rest, one.strands.rest, rtol=0, atol=6e-8)
    np.testing.assert_allclose(groups.root_body, one.root_body, rtol=0, atol=6e-8)
    assert not np.array_equal(groups.strands.rest, one.strands.rest)   # group b really went through its transform


def test_colliders_along_any_axis(tmp_path):
    """A Capsule, Cylinder or Plane lies along its ``axis`` X, Y or Z (USD's fallback is Z): the
    distances read back are the analytic ones of the shape along that axis (a moving and turning
    prim included), the Plane's half space is below the plane normal to its axis, and a
    Cylinder's spin turns about its axis."""
    from pxr import Gf
    from scipy.spatial.transform import Rotation

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Scope.Define(stage, "/Root/Colliders")
    R1 = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    cap = UsdGeom.Capsule.Define(stage, "/Root/Colliders/cap")            # axis not authored: Z
    cap.CreateRadiusAttr(0.05), cap.CreateHeightAttr(0.2)
    op = cap.AddTransformOp()
    m0, m1 = np.eye(4), np.eye(4)
    m0[3, :3] = [0.4, -0.3, 0.2]
    m1[:3, :3], m1[3, :3] = R1.T, [0.5, -0.3, 0.1]    # USD rows: the linear part transposed
    op.Set(Gf.Matrix4d(m0.tolist()), 0), op.Set(Gf.Matrix4d(m1.tolist()), 4)
    cyl = UsdGeom.Cylinder.Define(stage, "/Root/Colliders/wheel")
    cyl.CreateAxisAttr("X"), cyl.CreateRadiusAttr(0.1), cyl.CreateHeightAttr(0.04)
    cyl.AddTranslateOp().Set(Gf.Vec3d(-0.5, -0.2, 0.0))
    cyl.GetPrim().CreateAttribute("hairexp:spin", Sdf.ValueTypeNames.Double, custom=True).Set(3.0)
    ground = UsdGeom.Plane.Define(stage, "/Root/Colliders/ground")
    ground.CreateAxisAttr("Z")
    ground.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, -0.7))
    stage.GetRootLayer().Save()
    _, scene, _ = read(path)
    by = {c.name: c for c in scene.colliders}
    assert isinstance(by["cap"], Capsule) and isinstance(by["wheel"], Cylinder) and isinstance(by["ground"], Plane)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.0, 1.0, size=(400, 3))
    for k, (R, T) in ((0, (np.eye(3), m0[3, :3])), (4, (R1, m1[3, :3]))):
        t = k / FPS
        u = (x - T) @ R                                   # the prim's own coordinates
        zc = np.clip(u[:, 2], -0.1, 0.1)                  # the capsule's segment along its own Z
        want = np.linalg.norm(u - np.stack([0 * zc, 0 * zc, zc], 1), axis=1) - 0.05
        np.testing.assert_allclose(by["cap"].distance(x, t) + by["cap"].thickness, want, rtol=0, atol=1e-12)
    u = x - [-0.5, -0.2, 0.0]
    d = np.stack([np.hypot(u[:, 1], u[:, 2]) - 0.1, np.abs(u[:, 0]) - 0.02], 1)
    want = np.minimum(d.max(1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=1)
    np.testing.assert_allclose(by["wheel"].distance(x, 0.0) + by["wheel"].thickness, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(by["wheel"].surface_velocity(x, 0.0),
                               3.0 * np.cross([1.0, 0.0, 0.0], u * [0.0, 1.0, 1.0]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(by["ground"].distance(x, 0.0) + by["ground"].thickness, x[:, 2] + 0.7, rtol=0, atol=1e-12)


def test_scaled_collider_prims_read_with_their_sizes(tmp_path):
    """A collider prim scaled by its transform (as DCC artists size primitives): a Sphere scaled
    alike on its three axes, a Capsule scaled across its axis alike and along it by another
    factor, a Plane scaled any way; the sizes read are the attributes times the scales.  A Sphere
    scaled unevenly is refused, naming the scale."""
    from pxr import Gf

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Scope.Define(stage, "/Root/Colliders")
    ball = UsdGeom.Sphere.Define(stage, "/Root/Colliders/ball")
    ball.CreateRadiusAttr(1.0)
    ball.AddTranslateOp().Set(Gf.Vec3d(0.0, -0.5, 0.4))
    ball.AddRotateXYZOp().Set(Gf.Vec3f(10.0, 20.0, 30.0))
    ball.AddScaleOp().Set(Gf.Vec3f(0.05, 0.05, 0.05))
    pole = UsdGeom.Capsule.Define(stage, "/Root/Colliders/pole")
    pole.CreateAxisAttr("X"), pole.CreateRadiusAttr(1.0), pole.CreateHeightAttr(1.0)
    pole.AddTranslateOp().Set(Gf.Vec3d(0.0, -0.2, -0.4))
    pole.AddScaleOp().Set(Gf.Vec3f(0.3, 0.02, 0.02))
    ground = UsdGeom.Plane.Define(stage, "/Root/Colliders/ground")
    ground.CreateAxisAttr("Y")
    ground.AddTranslateOp().Set(Gf.Vec3d(0.0, -0.9, 0.0))
    ground.AddScaleOp().Set(Gf.Vec3f(7.0, 1.0, 3.0))
    stage.GetRootLayer().Save()
    _, scene, _ = read(path)
    by = {c.name: c for c in scene.colliders}
    assert by["ball"].radius == pytest.approx(0.05, rel=1e-6)
    assert by["pole"].radius == pytest.approx(0.02, rel=1e-6) and by["pole"].half_length == pytest.approx(0.15, rel=1e-6)
    x = np.random.default_rng(5).uniform(-1.0, 1.0, size=(300, 3))
    np.testing.assert_allclose(by["ball"].distance(x, 0.0) + by["ball"].thickness,
                               np.linalg.norm(x - [0.0, -0.5, 0.4], axis=1) - 0.05, rtol=0, atol=1e-7)
    u = x - [0.0, -0.2, -0.4]
    xc = np.clip(u[:, 0], -0.15, 0.15)
    np.testing.assert_allclose(by["pole"].distance(x, 0.0) + by["pole"].thickness,
                               np.linalg.norm(u - np.stack([xc, 0 * xc, 0 * xc], 1), axis=1) - 0.02, rtol=0, atol=1e-7)
    np.testing.assert_allclose(by["ground"].distance(x, 0.0) + by["ground"].thickness, x[:, 1] + 0.9, rtol=0, atol=1e-12)

    edit_stage(path, lambda s: UsdGeom.Xformable(s.GetPrimAtPath("/Root/Colliders/ball")).GetOrderedXformOps()[2].Set(
        Gf.Vec3f(0.05, 0.06, 0.05)))
    with pytest.raises(InputError, match=r"scales by \[0.05.*a Sphere collider may be scaled only alike along X, Y, Z"):
        read(path)


def test_a_stage_without_a_body_prim(tmp_path):
    """scene.usd_body=none: the hair is read in the stage's world at rest and moved by the config's
    scene.motion.  Under an animated prim it is refused (that prim is its body); with the body
    prim's transform made still, the hair reads where the stage puts it and the motion is the
    config's."""
    from hairexp.model.builders import build_motion

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    with pytest.raises(InputError, match=r"the transform of /Root/Body is animated: .*scene.usd_body=none, moves "
                                         r"with scene.motion only"):
        read(path, **{"scene.usd_body": "none"})
    _, with_body, _ = read(path)

    def still_body(stage):
        for op in UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Body")).GetOrderedXformOps():
            v = op.Get(0)
            op.GetAttr().Clear()
            op.Set(v)
    edit_stage(path, still_body)
    cfg, scene, _ = read(path, **{"scene.usd_body": "none"})
    np.testing.assert_allclose(scene.strands.rest, with_body.strands.rest, rtol=0, atol=1e-12)
    want = build_motion(cfg.scene.motion)
    assert_same_motion(want, scene.motion, np.linspace(0.0, 0.3, 7))
    np.testing.assert_allclose(scene.motion.transform(scene.root_body, 0.0), with_body.motion.transform(with_body.root_body, 0.0),
                               rtol=0, atol=1e-12)


def test_colliders_grouped_at_any_depth(tmp_path, caplog):
    """Colliders may sit in groups (Xform, Scope, typeless prims) under scene.usd_colliders, at any
    depth; a group's transform moves its colliders; an inactive one is said and not used; two of
    one name (in two groups) are refused, naming both."""
    from pxr import Gf

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Scope.Define(stage, "/Root/Colliders")
    grp = UsdGeom.Xform.Define(stage, "/Root/Colliders/props")
    grp.AddTranslateOp().Set(Gf.Vec3d(0.0, -0.5, 0.0))
    UsdGeom.Sphere.Define(stage, "/Root/Colliders/props/ball").CreateRadiusAttr(0.05)
    stage.DefinePrim("/Root/Colliders/props/more")                         # typeless group
    cap = UsdGeom.Capsule.Define(stage, "/Root/Colliders/props/more/pole")
    cap.CreateAxisAttr("Y"), cap.CreateRadiusAttr(0.02), cap.CreateHeightAttr(0.2)
    cap.AddTranslateOp().Set(Gf.Vec3d(0.3, 0.0, 0.0))
    off = UsdGeom.Sphere.Define(stage, "/Root/Colliders/props/more/off")
    off.CreateRadiusAttr(0.05)
    off.GetPrim().SetActive(False)
    stage.CreateClassPrim("/Root/Colliders/props/proto").SetTypeName("Sphere")   # a class: no prim of the scene
    stage.OverridePrim("/Root/Colliders/props/later").SetTypeName("Capsule")     # an over without a def: neither
    stage.DefinePrim("/Root/Colliders/rock").CreateAttribute("radius", Sdf.ValueTypeNames.Double).Set(0.1)  # typeless
    stage.GetRootLayer().Save()
    with caplog.at_level(logging.WARNING):
        _, scene, _ = read(path)
    assert "inactive collider prim(s) not used: /Root/Colliders/props/more/off" in caplog.text
    assert "no collider type and hold none (Sphere, Cube, Cylinder, Capsule, Plane), not used: /Root/Colliders/rock" in caplog.text
    by = {c.name: c for c in scene.colliders}
    assert sorted(by) == ["ball", "pole"]
    np.testing.assert_allclose(by["ball"].motion.pose(0.0)[1], [0.0, -0.5, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(by["pole"].motion.pose(0.0)[1], [0.3, -0.5, 0.0], rtol=0, atol=1e-12)
    edit_stage(path, lambda s: UsdGeom.Sphere.Define(s, "/Root/Colliders/props/more/ball").CreateRadiusAttr(0.01))
    with pytest.raises(InputError, match=r"a second collider named 'ball' \(the first is /Root/Colliders/props/ball\)"):
        read(path)


def test_a_length_error_on_a_stage_in_other_units_names_the_unit(tmp_path):
    """A stage whose metersPerUnit makes its hair microscopic: the zero-length edge it then has is
    said with the unit that made it so."""
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    edit_stage(path, lambda s: UsdGeom.SetStageMetersPerUnit(s, 1e-9))
    with pytest.raises(InputError, match=r"zero-length edge .*\(the stage's lengths are read in metres: its values x "
                                         r"its metersPerUnit 1e-09\)") as info:
        read(path)
    assert info.value.where == f"scene.usd={path}:/Root/Body/Hair"


def test_guides_in_several_curve_prims_read_as_one(tmp_path):
    """scene.usd_guides naming a parent: its BasisCurves (one prim a guide, as some exporters write
    them, each with its own transform) read as the one-prim guides, frame by frame; a parent that
    also holds the hair is refused."""
    from pxr import Gf, Vt

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Root/Guides")).GetPointsAttr()
    counts = np.array(UsdGeom.BasisCurves(stage.GetPrimAtPath("/Root/Guides")).GetCurveVertexCountsAttr().Get())
    UsdGeom.Scope.Define(stage, "/Root/GuideSet")
    off = np.concatenate([[0], np.cumsum(counts)])
    shift = np.array([0.0, 0.25, 0.0])
    for g in range(len(counts)):
        c = UsdGeom.BasisCurves.Define(stage, f"/Root/GuideSet/g{g}")
        c.CreateTypeAttr("linear")
        c.CreateCurveVertexCountsAttr(Vt.IntArray([int(counts[g])]))
        if g == 1:
            c.AddTranslateOp().Set(Gf.Vec3d(*shift))
        pa = c.CreatePointsAttr()
        for t in attr.GetTimeSamples():
            P = np.array(attr.Get(t), dtype=np.float64)[off[g]:off[g + 1]] - (shift if g == 1 else 0.0)
            pa.Set(Vt.Vec3fArray([Gf.Vec3f(*p) for p in P]), t)
    stage.GetRootLayer().Save()
    cfg, _, one = read(path)
    _, _, split = read(path, **{"scene.usd_guides": "/Root/GuideSet"})
    np.testing.assert_array_equal(split.offsets, one.offsets)
    assert split.n_frames == one.n_frames
    for f in range(cfg.frames + 1):
        np.testing.assert_allclose(split.positions[f], one.positions[f], rtol=0, atol=6e-8)   # float32 after the shift
    with pytest.raises(InputError, match=r"holds the detail hair \(/Root/Body/Hair, scene.usd_hair\)"):
        read(path, **{"scene.usd_guides": "/Root"})
