"""A stage whose attributes are declared with a value type the readers cannot use (``string
points``, ``int curveVertexCounts = 60``, ``string xformOp:transform``, ``string radius``) stops
with an InputError naming the file, the prim, the attribute and the type found and expected; on
the command line exit code 2 and one ``hairexp: error:`` line, not a ValueError, TypeError or
pxr Tf error traceback (exit 1), nor a run that silently used the schema's fallback or dropped
the transform (``string radius = "0.03"`` read as 0.03, ``string xformOpOrder`` ignored)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom
from usd_helpers import COLLIDERS, edit_stage, source_cfg, usd_cfg, write_stage

from hairexp.errors import InputError
from hairexp.io.usd_layout import check_transform_types, world_transform
from hairexp.io.usd_read import _array, build_usd_scene, read_guides

ROOT, BODY, HAIR, GUIDES = "/Root", "/Root/Body", "/Root/Body/Hair", "/Root/Guides"
BALL, CRATE, WHEEL = "/Root/Colliders/ball", "/Root/Colliders/crate", "/Root/Colliders/wheel"
T = Sdf.ValueTypeNames


@pytest.fixture(scope="module")
def valid_stage(tmp_path_factory):
    """A valid stage in the input layout (6 x 8 hair, 2 x 6 guides, frames 0..5, the five colliders)."""
    path = tmp_path_factory.mktemp("valid") / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS))
    return path


@pytest.fixture
def stage(valid_stage, tmp_path):
    path = tmp_path / "scene.usda"
    shutil.copy(valid_stage, path)
    return path


def retype(prim, name, type_name, value=None, samples=None, order=None):
    """An edit replacing the attribute ``name`` of ``prim`` by one declared ``type_name`` holding
    ``value`` (and/or time ``samples``); ``order``: also author ``xformOpOrder``."""
    def edit(stage):
        layer = stage.GetRootLayer()
        spec = layer.GetPrimAtPath(prim)
        if name in spec.attributes:
            spec.RemoveProperty(spec.attributes[name])
        attr = Sdf.AttributeSpec(spec, name, type_name)
        if value is not None:
            attr.default = value
        for t, v in (samples or {}).items():
            layer.SetTimeSample(attr.path, t, v)
        if order is not None:
            edit_order(prim, order)(stage)
    return edit


def edit_order(prim, order):
    def edit(stage):
        stage.GetPrimAtPath(prim).CreateAttribute("xformOpOrder", T.TokenArray, variability=Sdf.VariabilityUniform
                                                  ).Set(order)
    return edit


#: name: (edit, prim the error names, text the message must hold: the attribute, the type found, expected)
CASES = {
    # 1. the hair's points
    "hair_points_string": (retype(HAIR, "points", T.String, "abc"), HAIR, "points has type string, expected point3f[]"),
    "hair_points_flat_floats": (retype(HAIR, "points", T.FloatArray, list(range(144))), HAIR,
                                "points has type float[], expected point3f[]"),
    "hair_points_one_vector": (retype(HAIR, "points", T.Point3f, (0.0, 0.0, 0.0)), HAIR,
                               "points has type point3f, expected point3f[]"),
    # 2. the hair's curveVertexCounts
    "hair_counts_string": (retype(HAIR, "curveVertexCounts", T.String, "8 8 8 8 8 8"), HAIR,
                           "curveVertexCounts has type string, expected int[]"),
    "hair_counts_scalar": (retype(HAIR, "curveVertexCounts", T.Int, 60), HAIR,
                           "curveVertexCounts has type int, expected int[]"),
    "hair_counts_floats": (retype(HAIR, "curveVertexCounts", T.FloatArray, [8.0] * 6), HAIR,
                           "curveVertexCounts has type float[], expected int[]"),
    "hair_wrap_array": (retype(HAIR, "wrap", T.TokenArray, ["nonperiodic"]), HAIR,
                        "wrap has type token[], expected token"),
    # 3. the guides'
    "guide_points_string_samples": (retype(GUIDES, "points", T.String, samples={f: "p" for f in range(6)}), GUIDES,
                                    "points has type string, expected point3f[]"),
    "guide_points_string": (retype(GUIDES, "points", T.String, "abc"), GUIDES,
                            "points has type string, expected point3f[]"),
    "guide_counts_string": (retype(GUIDES, "curveVertexCounts", T.String, "6 6"), GUIDES,
                            "curveVertexCounts has type string, expected int[]"),
    "guide_counts_scalar": (retype(GUIDES, "curveVertexCounts", T.Int, 60), GUIDES,
                            "curveVertexCounts has type int, expected int[]"),
    # 4. transforms: the body's, an ancestor's, the hair's, the guides', a collider's
    "body_transform_string": (retype(BODY, "xformOp:transform", T.String, "abc"), BODY,
                              "xformOp:transform has type string, expected matrix4d"),
    "body_transform_string_samples": (retype(BODY, "xformOp:transform", T.String, samples={0: "a", 5: "b"}), BODY,
                                      "xformOp:transform has type string, expected matrix4d"),
    "body_op_order_string": (retype(BODY, "xformOpOrder", T.String, "xformOp:transform"), BODY,
                             "xformOpOrder has type string, expected token[]"),
    "body_op_missing": (edit_order(BODY, ["xformOp:transform", "xformOp:translate"]), BODY,
                        "xformOpOrder names xformOp:translate, but the prim has no attribute xformOp:translate"),
    "body_op_not_an_op": (edit_order(BODY, ["xformOp:transform", "xformOp:wobble"]), BODY,
                          "xformOpOrder names xformOp:wobble, which is not a transform op"),
    "root_rotate_vector": (retype(ROOT, "xformOp:rotateY", T.Double3, (1.0, 2.0, 3.0), order=["xformOp:rotateY"]), BODY,
                           "/Root.xformOp:rotateY has type double3, expected double"),
    "hair_translate_string": (retype(HAIR, "xformOp:translate", T.String, "up", order=["xformOp:translate"]), HAIR,
                              "xformOp:translate has type string, expected double3"),
    "guide_transform_string": (retype(GUIDES, "xformOp:transform", T.String, "abc", order=["xformOp:transform"]),
                               GUIDES, "xformOp:transform has type string, expected matrix4d"),
    "ball_transform_string": (retype(BALL, "xformOp:transform", T.String, "abc"), BALL,
                              "xformOp:transform has type string, expected matrix4d"),
    "crate_scale_string": (retype(CRATE, "xformOp:scale", T.String, "big"), CRATE,
                           "xformOp:scale has type string, expected double3"),
    "wheel_orient_matrix": (retype(WHEEL, "xformOp:orient", T.Matrix4d, Gf.Matrix4d(1.0),
                                   order=["xformOp:transform", "xformOp:orient"]), WHEEL,
                            "xformOp:orient has type matrix4d, expected quatd"),
    # collider sizes and custom attributes
    "ball_radius_string": (retype(BALL, "radius", T.String, "0.03"), BALL, "radius has type string, expected a number"),
    "ball_radius_bool": (retype(BALL, "radius", T.Bool, True), BALL, "radius has type bool, expected a number"),
    "crate_size_vector": (retype(CRATE, "size", T.Double3, (2.0, 2.0, 2.0)), CRATE,
                          "size has type double3, expected a number"),
    "wheel_height_string": (retype(WHEEL, "height", T.String, "0.04"), WHEEL,
                            "height has type string, expected a number"),
    "wheel_spin_string": (retype(WHEEL, "hairexp:spin", T.String, "3"), WHEEL,
                          "hairexp:spin has type string, expected a number"),
    "wheel_axis_int": (retype(WHEEL, "axis", T.Int, 1), WHEEL, "axis has type int, expected token"),
    "ball_friction_array": (retype(BALL, "hairexp:friction", T.DoubleArray, [0.5]), BALL,
                            "hairexp:friction has type double[], expected a number"),
    "ball_thickness_samples": (retype(BALL, "hairexp:thickness", T.String, samples={0: "thin"}), BALL,
                               "hairexp:thickness has type string, expected a number"),
}


def read_stage(path):
    """What a run reads: the scene (body, hair, colliders), then the guides (2 frames at 25 fps)."""
    cfg = usd_cfg(path)
    scene = build_usd_scene(cfg.scene)
    return scene, read_guides(cfg, scene, 2, 25.0)


@pytest.mark.parametrize("case", sorted(CASES))
def test_wrong_type_is_an_input_error(stage, case):
    edit, prim, text = CASES[case]
    edit_stage(stage, edit)
    with pytest.raises(InputError) as info:
        read_stage(stage)
    err = info.value
    assert err.where == f"scene.usd={stage}:{prim}", str(err)
    assert text in str(err), str(err)
    assert "\n" not in str(err) and "pxrInternal" not in str(err)


def test_valid_stage_still_reads(stage):
    scene, guides = read_stage(stage)
    assert scene.strands.n_strands == 6 and len(scene.colliders) == 5


def test_other_valid_types_read_the_same(valid_stage, stage):
    """double3[] points, uint[] counts, float radius and a body transform made of translate,
    rotateXYZ, orient and an inverted pivot read like the stage as written."""
    base, _ = read_stage(valid_stage)

    def edit(s):
        hair = UsdGeom.BasisCurves.Get(s, HAIR)
        P = np.asarray(hair.GetPointsAttr().Get(), dtype=np.float64)
        retype(HAIR, "points", T.Double3Array, [tuple(p) for p in P.tolist()])(s)
        retype(HAIR, "curveVertexCounts", T.UIntArray, [8] * 6)(s)
        retype(BALL, "radius", T.Float, 0.03)(s)
        body = s.GetPrimAtPath(BODY)
        for name in body.GetPropertyNames():
            if name.startswith("xformOp"):
                body.RemoveProperty(name)
        xf = UsdGeom.Xformable(body)
        xf.AddTranslateOp(UsdGeom.XformOp.PrecisionFloat).Set((0.01, 0.0, 0.0))
        xf.AddTranslateOp(opSuffix="pivot").Set((0.0, 0.1, 0.0))
        xf.AddRotateXYZOp().Set((0.0, 0.0, 0.0))
        xf.AddOrientOp(UsdGeom.XformOp.PrecisionFloat).Set(Gf.Quatf(1.0))
        xf.AddTranslateOp(opSuffix="pivot", isInverseOp=True)

    edit_stage(stage, edit)
    scene, _ = read_stage(stage)
    np.testing.assert_array_equal(scene.strands.offsets, base.strands.offsets)
    # the body now stands still at x = 1 cm: its rest hair is the written hair moved by 1 cm
    np.testing.assert_allclose(scene.strands.rest - [0.01, 0.0, 0.0], base.strands.rest, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(scene.root_body, base.root_body)   # double3 points: the float32 values
    assert scene.colliders[0].radius == pytest.approx(0.03)


def test_reset_xform_stack_ignores_the_ancestors(stage):
    """An ancestor's bad op does not matter to a prim that resets the transform stack (USD does
    not compute it), and a prim without ops is left alone."""
    edit_stage(stage, retype(ROOT, "xformOp:rotateY", T.Double3, (1.0, 2.0, 3.0), order=["xformOp:rotateY"]))
    s = Usd.Stage.Open(str(stage))
    UsdGeom.Xformable(s.GetPrimAtPath(BODY)).SetResetXformStack(True)
    check_transform_types(s.GetPrimAtPath(BODY), "here")
    with pytest.raises(InputError, match=r"/Root.xformOp:rotateY has type double3"):
        check_transform_types(s.GetPrimAtPath(GUIDES), "there")


def test_a_transform_usd_cannot_compute_is_an_input_error(stage):
    """world_transform, past the type checks: the Tf error of ComputeLocalToWorldTransform is an
    InputError naming the prim and the time."""
    edit_stage(stage, retype(BODY, "xformOp:transform", T.String, "abc"))
    s = Usd.Stage.Open(str(stage))
    with pytest.raises(InputError, match=r"cannot compute the transform at time code 2: Invalid combination of "
                                         r"opType \(TypeTransform\) and opVal \(abc\)") as info:
        world_transform(UsdGeom.Xformable(s.GetPrimAtPath(HAIR)), Usd.TimeCode(2), "file:/Root/Body/Hair")
    assert info.value.where == "file:/Root/Body/Hair"


class _Attr:
    """An attribute whose value is not what its declared type says (a value of another layer)."""

    def __init__(self, value):
        self.value = value

    def GetName(self):
        return "points"

    def Get(self, tc):
        return self.value


@pytest.mark.parametrize("value, match", [("abc", r"points at time code 0 cannot be read as numbers"),
                                          (60, r"points at time code 0 has the shape \[\], expected an array of "
                                               r"3-vectors"),
                                          ([1.0, 2.0, 3.0], r"has the shape \[3\], expected an array of 3-vectors")])
def test_a_value_that_is_not_an_array_is_an_input_error(value, match):
    with pytest.raises(InputError, match=match) as info:
        _array(_Attr(value), Usd.TimeCode(0), "file:/H", np.float64, columns=3)
    assert info.value.where == "file:/H"


# --------------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["hair_points_string", "body_transform_string"])
def test_cli_exits_2_with_one_line(stage, tmp_path, case):
    edit, prim, text = CASES[case]
    edit_stage(stage, edit)
    out = tmp_path / "run"
    env = dict(os.environ, CI="1")  # PYTHONPATH: this checkout (conftest.py)
    proc = subprocess.run([sys.executable, "-m", "hairexp", "experiment=from_usd", f"scene.usd={stage}", "frames=2",
                           f"hydra.run.dir={out}"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"hairexp: error: scene.usd={stage}:{prim}: ") and text in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert json.loads((out / "summary.json").read_text())["status"] == "failed"
