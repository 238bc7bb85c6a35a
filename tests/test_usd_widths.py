"""The hair's widths a USD stage authors are read (checked, in metres) and written back to the
result's curves: a groom of 0.08 mm hair came back 1 mm wide (probe of issue 16)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, Vt
from usd_helpers import N_STRANDS, N_VERTICES, edit_stage, source_cfg, usd_cfg, write_stage

from hairexp.errors import InputError
from hairexp.io.usd_layout import HAIR_WIDTH
from hairexp.io.usd_read import build_usd_scene
from hairexp.io.usd_write import write_result_usd

HAIR = "/Root/Body/Hair"
V = N_STRANDS * N_VERTICES


@pytest.fixture
def stage(tmp_path):
    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=[]))
    return path


def with_widths(values, interpolation):
    def edit(stage):
        c = UsdGeom.BasisCurves.Get(stage, HAIR)
        c.GetWidthsAttr().Set(Vt.FloatArray([float(v) for v in values]))
        c.SetWidthsInterpolation(interpolation)
    return edit


def result_widths(tmp_path, scene) -> tuple[np.ndarray, str]:
    out = tmp_path / "result.usda"
    P = np.stack([scene.strands.rest] * 2)
    write_result_usd(out, scene, P, P[:, :0], np.array([0]), 25.0, clips="never")
    result = Usd.Stage.Open(str(out))   # held: the schema object does not keep its stage alive
    c = UsdGeom.BasisCurves.Get(result, "/Root/Result/Hair")
    return np.asarray(c.GetWidthsAttr().Get(), dtype=np.float64), c.GetWidthsInterpolation()


def test_tapered_vertex_widths_come_back_on_the_result(stage, tmp_path):
    taper = np.tile(np.linspace(8e-5, 0.0, N_VERTICES), N_STRANDS)   # 0.08 mm at the root, 0 at the tip
    edit_stage(stage, with_widths(taper, UsdGeom.Tokens.vertex))
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert np.allclose(scene.widths, taper, rtol=1e-6, atol=0)
    got, interp = result_widths(tmp_path, scene)
    assert interp == UsdGeom.Tokens.vertex and np.allclose(got, taper, rtol=1e-6, atol=0)


def test_uniform_widths_are_a_curves_and_stage_units_apply(stage, tmp_path):
    per_curve = 0.005 + 0.001 * np.arange(N_STRANDS)    # centimetres: 0.05-0.1 mm

    def edit(s):
        with_widths(per_curve, UsdGeom.Tokens.uniform)(s)
    edit_stage(stage, edit)
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert np.allclose(scene.widths, np.repeat(per_curve, N_VERTICES), rtol=1e-6)   # metersPerUnit 1 here
    got, interp = result_widths(tmp_path, scene)
    assert interp == UsdGeom.Tokens.vertex and np.allclose(got, np.repeat(per_curve, N_VERTICES), rtol=1e-6)


def test_a_stage_without_widths_keeps_the_default_display_width(stage, tmp_path):
    edit_stage(stage, lambda s: UsdGeom.BasisCurves.Get(s, HAIR).GetWidthsAttr().Clear())
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert scene.widths is None
    got, interp = result_widths(tmp_path, scene)
    assert interp == UsdGeom.Tokens.constant and np.allclose(got, [HAIR_WIDTH])


def test_a_constant_width_is_written_as_one(stage, tmp_path):
    edit_stage(stage, with_widths([6e-5], UsdGeom.Tokens.constant))
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert np.allclose(scene.widths, np.full(V, 6e-5))
    got, interp = result_widths(tmp_path, scene)
    assert interp == UsdGeom.Tokens.constant and np.allclose(got, [6e-5])


@pytest.mark.parametrize("bad, said", [(np.nan, "nan"), (-1e-4, "-0.0001")])
def test_a_width_that_is_not_finite_or_negative_is_named(stage, bad, said):
    w = np.full(V, 1e-4)
    w[N_VERTICES + 3] = bad
    edit_stage(stage, with_widths(w, UsdGeom.Tokens.vertex))
    with pytest.raises(InputError) as err:
        build_usd_scene(usd_cfg(stage).scene)
    msg = str(err.value)
    assert f"{HAIR}: widths: curve 1 vertex 3 has the width" in msg and said in msg


def test_widths_that_do_not_fit_their_interpolation_are_warned_of_and_not_used(stage, caplog):
    edit_stage(stage, with_widths([1e-4] * 5, UsdGeom.Tokens.vertex))
    with caplog.at_level(logging.WARNING):
        scene = build_usd_scene(usd_cfg(stage).scene)
    assert scene.widths is None
    assert any("widths has 5 values with vertex interpolation" in r.getMessage() and "not used" in r.getMessage()
               for r in caplog.records)


def test_the_scene_checks_widths_given_through_the_python_api(stage):
    import dataclasses

    scene = build_usd_scene(usd_cfg(stage).scene)
    for wrong, said in ((np.zeros(3), "must be None or an array of"), (np.full(V, np.inf), "must be finite and >= 0"),
                        ("thin", "must be None or an array of")):
        with pytest.raises(InputError, match=said):
            dataclasses.replace(scene, widths=wrong)


def test_widths_follow_the_curve_prims_own_scale(stage, tmp_path):
    """The points were scaled by the prim's ``xformOp:scale`` and the widths were not."""
    from pxr import Gf

    def edit(s):
        with_widths([5e-5], UsdGeom.Tokens.constant)(s)
        UsdGeom.Xformable(s.GetPrimAtPath(HAIR)).AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    edit_stage(stage, edit)
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert np.allclose(scene.widths, 1e-4, rtol=1e-6)


def test_primvars_widths_are_read(stage):
    """Widths authored as ``primvars:widths`` (as DCC exporters write them) were ignored without a word."""
    taper = np.tile(np.linspace(6e-5, 0.0, N_VERTICES), N_STRANDS)

    def edit(s):
        c = UsdGeom.BasisCurves.Get(s, HAIR)
        c.GetWidthsAttr().Clear()
        pv = UsdGeom.PrimvarsAPI(c.GetPrim()).CreatePrimvar("widths", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
        pv.Set(Vt.FloatArray([float(v) for v in taper]))
    edit_stage(stage, edit)
    scene = build_usd_scene(usd_cfg(stage).scene)
    assert np.allclose(scene.widths, taper, rtol=1e-6, atol=0)


def test_the_stage_unit_is_said_with_length_errors_only(stage):
    """A centimetre stage's count mismatch carried "(the stage's lengths are read in metres ...)"."""
    def edit(s):
        s.SetMetadata("metersPerUnit", 0.01)
        UsdGeom.BasisCurves.Get(s, HAIR).GetCurveVertexCountsAttr().Set(Vt.IntArray([N_VERTICES] * (N_STRANDS - 1) + [N_VERTICES + 1]))
    edit_stage(stage, edit)
    with pytest.raises(InputError) as err:
        build_usd_scene(usd_cfg(stage).scene)
    assert "vertex counts add up to" in str(err.value) and "metersPerUnit" not in str(err.value)
