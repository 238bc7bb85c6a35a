"""Findings of the user-input probe of 2026-12-07 (the sixteenth session), fixed."""

from __future__ import annotations

import pytest
from pxr import Usd, UsdGeom

from hairexp.app import compose_config
from hairexp.app.assemble import check_config
from hairexp.errors import InputError


def _new_stage(path, end=None, xforms=(), curves=(("/Hair", 0.0),)):
    """A stage at 24 fps (``end``: its endTimeCode) with the Xforms ``xforms`` and a 3-vertex
    hanging linear curve at each (path, x) of ``curves``; saved, and returned open."""
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(24)
    if end is not None:
        stage.SetEndTimeCode(end)
    for xform in xforms:
        UsdGeom.Xform.Define(stage, xform)
    for prim, x in curves:
        c = UsdGeom.BasisCurves.Define(stage, prim)
        c.CreateTypeAttr("linear")
        c.CreateCurveVertexCountsAttr([3])
        c.CreatePointsAttr([(x, 0, 0), (x, -0.05, 0), (x, -0.1, 0)])
    stage.GetRootLayer().Save()
    return stage


def _stage(path, end=None) -> str:
    _new_stage(path, end)
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
    _new_stage(path, 2, ("/Root", "/Root/Body", "/Root/Guides"), (("/Root/Guides/A", 0.0),))
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
    stage = _new_stage(path, 2, ("/Root", "/Root/Body", "/Root/Body/Grp"),
                       (("/Root/Body/Grp/A", 0.0), ("/Root/Body/Grp/B", 0.02)))
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


def test_a_results_guides_read_back_with_the_same_edits_are_warned(tmp_path, caplog):
    """A run's result.usdc read back (``guides.source=usd``) with the experiment's own
    ``guides.edits`` applied them a second time without a word (the guides 0.22 m off); a guide
    file in the same case was warned.  The result's guides prim now says which edits its guides
    carry (customData ``hairexp:edits_applied``), and the reading run is warned the same way."""
    from hairexp.app.assemble import assemble_scene
    from hairexp.app.run import run

    base = ["experiment=goaling_smoke", "variants=[]", "controller=tracking", "frames=3", "logging=off"]
    run(compose_config(base), tmp_path / "a")
    stage = Usd.Stage.Open(str(tmp_path / "a" / "result.usdc"))
    said = stage.GetPrimAtPath("/Root/Guides").GetCustomDataByKey("hairexp:edits_applied")
    assert said.startswith("1 edit: rotate of guide 0 keyed at")
    again = [*base, "scene.builder=usd", "guides.source=usd", f"scene.usd={tmp_path / 'a' / 'result.usdc'}",
             "scene.colliders=[]"]
    with caplog.at_level("WARNING"):
        assemble_scene(compose_config(again), settle=False)
    assert f"(its guides) was saved by a run that had applied its guides.edits ({said})" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        assemble_scene(compose_config([*again, "guides.edits=[]"]), settle=False)
    assert "applied its guides.edits" not in caplog.text


def test_a_collider_touching_the_hair_at_rest_by_round_off_is_not_refused():
    """A plane at the hair tips' exact height (written as float32) was refused as the hair starting
    inside it "by 2.98e-06 mm".  Without the barrier a vertex within 1 um of the surface is on it;
    a millimetre inside is still refused."""
    from hairexp.app.assemble import assemble_scene

    base = ["experiment=goaling_smoke", "variants=[]", "measure.collider=floor"]
    _, scene, _ = assemble_scene(compose_config([*base, "scene.colliders=[]", "measure.name=none", "measure.collider="]), settle=False)
    low = float(scene.initial_positions()[~scene.strands.kinematic][:, 1].min())

    def floor(y: float) -> list[str]:
        return [*base, f"scene.colliders=[{{name: floor, shape: plane, motion: {{times: [0.0], "
                       f"translations: [[0.0, {y!r}, 0.0]], rotations_deg: [[0.0, 0.0, 0.0]]}}}}]"]

    check_config(compose_config(floor(low + 3e-9)))
    with pytest.raises(InputError, match=r"collider 'floor': the hair starts inside it \(strand \d+ vertex \d+ by 1 mm"):
        check_config(compose_config(floor(low + 1e-3)))
