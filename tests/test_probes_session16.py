"""Findings of the user-input probe of 2026-12-07 (the sixteenth session), fixed."""

from __future__ import annotations

import pytest
from pxr import Usd, UsdGeom

from hairexp.app import compose_config
from hairexp.app.assemble import check_config
from hairexp.errors import InputError


def _stage(path, end=None) -> str:
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(24)
    if end is not None:
        stage.SetEndTimeCode(end)
    curves = UsdGeom.BasisCurves.Define(stage, "/Hair")
    curves.CreateTypeAttr("linear")
    curves.CreateCurveVertexCountsAttr([3])
    curves.CreatePointsAttr([(0, 0, 0), (0, 0, -0.05), (0, 0, -0.1)])
    stage.GetRootLayer().Save()
    return str(path)


@pytest.mark.parametrize("end", [float("inf"), float("nan"), 1e308])
def test_an_end_time_code_that_is_not_a_finite_number_of_frames_is_refused(tmp_path, end):
    """endTimeCode inf, nan or 1e308 (inf frames at the run's rate) with the frames taken from the
    stage: OverflowError / ValueError tracebacks, exit 1; now the stage and the value, exit 2."""
    cfg = compose_config(["experiment=from_usd", f"scene.usd={_stage(tmp_path / 's.usda', end)}"])
    with pytest.raises(InputError, match=r"endTimeCode \S+ is (inf|nan) frames at 24 fps, not a finite number"):
        check_config(cfg)


def test_the_guides_prim_named_as_the_hair_is_refused(tmp_path):
    """``scene.usd_hair`` naming the guides prim itself simulated the animated guides as detail
    hair, exit 0, only "the hair's points are animated" said; a parent holding the guides, and
    (by the guides' reader) guides holding the hair, were refused already.  Now it is too."""
    path = tmp_path / "g.usda"
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(24)
    stage.SetEndTimeCode(2)
    for xform in ("/Root", "/Root/Body", "/Root/Guides"):
        UsdGeom.Xform.Define(stage, xform)
    curves = UsdGeom.BasisCurves.Define(stage, "/Root/Guides/A")
    curves.CreateTypeAttr("linear")
    curves.CreateCurveVertexCountsAttr([3])
    curves.CreatePointsAttr([(0, 0, 0), (0, -0.05, 0), (0, -0.1, 0)])
    stage.GetRootLayer().Save()
    for hair, said in (("/Root/Guides", r":/Root/Guides: is the guides \(/Root/Guides, scene\.usd_guides\)"),
                       ("/Root", r":/Root: holds the guides \(/Root/Guides, scene\.usd_guides\)"),
                       ("/Root/Guides/A", r"holds the detail hair \(/Root/Guides/A, scene\.usd_hair\)")):
        cfg = compose_config(["experiment=from_usd", f"scene.usd={path}", f"scene.usd_hair={hair}"])
        with pytest.raises(InputError, match=said):
            check_config(cfg)


def test_abstract_prims_are_refused_when_named_and_said_inside_a_group(tmp_path, caplog):
    """A ``class`` BasisCurves named by scene.usd_hair was read and simulated, and one inside a
    hair group skipped, both without a word (USD's traversal and viewers skip abstract prims).
    Now a named one is refused as an inactive one is, and one inside a group is said and not used."""
    from pxr import Sdf

    path = tmp_path / "c.usda"
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(24)
    stage.SetEndTimeCode(2)
    for xform in ("/Root", "/Root/Body", "/Root/Body/Grp"):
        UsdGeom.Xform.Define(stage, xform)
    for name, x in (("A", 0.0), ("B", 0.02)):
        curves = UsdGeom.BasisCurves.Define(stage, f"/Root/Body/Grp/{name}")
        curves.CreateTypeAttr("linear")
        curves.CreateCurveVertexCountsAttr([3])
        curves.CreatePointsAttr([(x, 0, 0), (x, -0.05, 0), (x, -0.1, 0)])
    stage.GetRootLayer().GetPrimAtPath("/Root/Body/Grp/B").specifier = Sdf.SpecifierClass
    stage.GetRootLayer().Save()
    base = ["experiment=from_usd", f"scene.usd={path}", "guides.source=rigid", "guides.count=1"]
    with pytest.raises(InputError, match=r":/Root/Body/Grp/B: is abstract \(a class, or inside one\): not a prim of "
                                         r"the scene \(the detail hair\)"):
        check_config(compose_config([*base, "scene.usd_hair=/Root/Body/Grp/B"]))
    from hairexp.app.assemble import assemble_scene

    with caplog.at_level("WARNING"):
        _, scene, _ = assemble_scene(compose_config([*base, "scene.usd_hair=/Root/Body/Grp"]), settle=False)
    assert scene.strands.n_vertices == 3
    assert "abstract hair curves (classes, or inside one) not used: /Root/Body/Grp/B" in caplog.text
