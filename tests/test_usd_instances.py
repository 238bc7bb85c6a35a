"""USD composition a DCC writes: colliders and hair in instanceable assets (read through their
instance proxies), an inactive colliders' prim (said), a referenced layer in other units (said)."""

from __future__ import annotations

import logging

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom
from usd_helpers import edit_stage, source_cfg, usd_cfg, write_stage

from hairexp.app.builders import build_scene
from hairexp.io.usd_read import stage_timing


def read_scene(path):
    return build_scene(stage_timing(usd_cfg(path)).scene)


def test_collider_instances_are_colliders_named_by_their_paths(tmp_path):
    """Two instanceable Xforms referencing a ball asset: both balls are read (they were 'no collider
    type and hold none'), each named after its path below the colliders' prim."""
    asset = tmp_path / "ball.usda"
    a = Usd.Stage.CreateNew(str(asset))
    ball = UsdGeom.Xform.Define(a, "/Ball")
    UsdGeom.Sphere.Define(a, "/Ball/geo").CreateRadiusAttr(0.05)
    a.SetDefaultPrim(ball.GetPrim())
    a.GetRootLayer().Save()
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))

    def add(stage):
        UsdGeom.Scope.Define(stage, "/Root/Colliders")
        for i, x in enumerate((0.2, -0.2)):
            inst = UsdGeom.Xform.Define(stage, f"/Root/Colliders/ball{i}")
            inst.AddTranslateOp().Set(Gf.Vec3d(x, 1.0, 0.0))
            inst.GetPrim().GetReferences().AddReference(str(asset))
            inst.GetPrim().SetInstanceable(True)

    edit_stage(path, add)
    scene = read_scene(path)
    by = {c.name: c for c in scene.colliders}
    assert sorted(by) == ["ball0_geo", "ball1_geo"]
    assert by["ball0_geo"].radius == 0.05
    np.testing.assert_allclose(by["ball1_geo"].motion.pose(0.0)[1], [-0.2, 1.0, 0.0], rtol=0, atol=1e-12)


def test_hair_in_an_instanced_groom_is_read(tmp_path):
    """The detail hair's prim an instanceable reference to a groom asset: its curves are read (it
    was 'a Xform with no active BasisCurves under it')."""
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    plain = read_scene(path)
    groom = tmp_path / "groom.usda"
    st = Usd.Stage.Open(str(path))
    g = Usd.Stage.CreateNew(str(groom))
    UsdGeom.Xform.Define(g, "/Groom")
    src = UsdGeom.BasisCurves(st.GetPrimAtPath("/Root/Body/Hair"))
    c = UsdGeom.BasisCurves.Define(g, "/Groom/curves")
    c.CreateTypeAttr(UsdGeom.Tokens.linear)
    c.CreateCurveVertexCountsAttr(src.GetCurveVertexCountsAttr().Get())
    c.CreatePointsAttr(src.GetPointsAttr().Get())
    g.SetDefaultPrim(g.GetPrimAtPath("/Groom"))
    g.GetRootLayer().Save()

    def swap(stage):
        stage.RemovePrim("/Root/Body/Hair")
        hair = UsdGeom.Xform.Define(stage, "/Root/Body/Hair").GetPrim()
        hair.GetReferences().AddReference(str(groom))
        hair.SetInstanceable(True)

    edit_stage(path, swap)
    scene = read_scene(path)
    np.testing.assert_array_equal(scene.strands.offsets, plain.strands.offsets)
    np.testing.assert_allclose(scene.strands.rest, plain.strands.rest, rtol=0, atol=1e-7)


def test_an_inactive_colliders_prim_is_said(tmp_path, caplog):
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg())
    edit_stage(path, lambda s: s.GetPrimAtPath("/Root/Colliders").SetActive(False))
    with caplog.at_level(logging.WARNING):
        scene = read_scene(path)
    assert scene.colliders == []
    assert "the colliders' prim /Root/Colliders is inactive: no collider used" in caplog.text


def test_a_layer_in_other_units_is_said(tmp_path, caplog):
    """A sublayer that says it is in centimetres, under a stage in metres: its values are read in
    metres (USD converts nothing), and the log says so."""
    sub = Sdf.Layer.CreateNew(str(tmp_path / "cm.usda"))
    sub.pseudoRoot.SetInfo("metersPerUnit", 0.01)
    sub.Save()
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    edit_stage(path, lambda s: s.GetRootLayer().subLayerPaths.append(str(tmp_path / "cm.usda")))
    with caplog.at_level(logging.WARNING):
        read_scene(path)
    assert "cm.usda sets metersPerUnit = 0.01, the stage 1.0: USD does not convert" in caplog.text
