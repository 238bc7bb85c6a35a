"""The weak findings of issue 12's eleventh probe round, one test each: the Python API's entry
points given strings, None, bools, complex numbers or fractional counts (numpy's or Python's own
error, naming neither the input nor its place, or a silent truncation), a relative input path
under ``hydra.job.chdir=true``, and a zero orientation quaternion on a USD collider."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf
from usd_helpers import COLLIDERS, edit_stage, source_cfg, usd_cfg, write_stage

from hairexp.control.tracking.correspondence import build_correspondence
from hairexp.errors import InputError
from hairexp.guides.animation import GuideAnimation
from hairexp.model import Material, RigidMotion, Scene, Strands

LINE = np.stack([np.zeros(10), -np.linspace(0.0, 0.2, 10), np.zeros(10)], 1)
GUIDE_FRAMES = np.zeros((3, 4, 3)) + np.arange(4)[None, :, None] * np.array([0.0, -0.1, 0.0])


def strands():
    return Strands.from_polylines(LINE, np.array([10]), 1e-4)


def scene(**kw):
    args = dict(name="one", strands=strands(), material=Material(1e-4, 10.0, 1e-7), motion=RigidMotion.static(),
                gravity=np.array([0.0, -9.81, 0.0]), root_body=LINE)
    args.update(kw)
    return Scene(**args)


def corr(**kw):
    args = dict(detail_rest=LINE, offsets=np.array([0, 10]), free=np.ones(10, bool), guides_rest=[LINE[:4]],
                points_per_guide=2)
    args.update(kw)
    return build_correspondence(**args)


CASES = {
    "points_string": (lambda: Strands.from_polylines("abc", np.array([10]), 1e-4),
                      "strands points: must be an array of real numbers, got str"),
    "points_strings": (lambda: Strands.from_polylines([["a", "b", "c"]] * 10, np.array([10]), 1e-4),
                       "strands points: must be an array of real numbers, got <U1 values"),
    "points_complex": (lambda: Strands.from_polylines(LINE + 1j, np.array([10]), 1e-4),
                       "strands points: must be an array of real numbers, got complex128"),
    "counts_fraction": (lambda: Strands.from_polylines(LINE, np.array([10.7]), 1e-4),
                        r"strands vertex counts: must be whole numbers, got \[10.7\]"),
    "counts_string": (lambda: Strands.from_polylines(LINE, "10", 1e-4), "strands vertex counts: must be an array"),
    "counts_none": (lambda: Strands.from_polylines(LINE, None, 1e-4), "strands vertex counts: must be an array"),
    "density_string": (lambda: Strands.from_polylines(LINE, np.array([10]), "1e-4"),
                       r"strands linear density \(kg/m\): must be a real number, got str"),
    "density_none": (lambda: Strands.from_polylines(LINE, np.array([10]), None), "must be a real number, got NoneType"),
    "material_bool": (lambda: Material(True, 10.0, 1e-7), "Material.linear_density: must be a real number, got bool"),
    "material_string": (lambda: Material(1e-4, "10", 1e-7), "Material.stretch_stiffness: must be a real number"),
    "material_negative": (lambda: Material(1e-4, 10.0, -1e-7), r"Material.bending_stiffness: must be >= 0 and <= 1e\+09, got -1e-07"),
    "scene_motion_none": (lambda: scene(motion=None), "Scene.motion: must be a RigidMotion"),
    "scene_motion_string": (lambda: scene(motion="still"), "Scene.motion: must be a RigidMotion"),
    "scene_name_int": (lambda: scene(name=5), "Scene.name: must be a non-empty string, got 5"),
    "scene_colliders_int": (lambda: scene(colliders=5), "Scene.colliders: must be a list of collider objects"),
    "rigid_times_string": (lambda: RigidMotion("0", np.zeros((1, 3)), np.zeros((1, 3))),
                           "motion.times: must be an array of real numbers, got str"),
    "guides_fps_string": (lambda: GuideAnimation(GUIDE_FRAMES, np.array([0, 4]), "25"),
                          "guides: fps must be a number from 0.1 to 100000 .*got '25'"),
    "guides_positions_string": (lambda: GuideAnimation("abc", np.array([0, 4]), 25.0),
                                "guides positions: must be an array of real numbers"),
    "shape_at_nan": (lambda: GuideAnimation(GUIDE_FRAMES, np.array([0, 4]), 25.0).shape_at(float("nan")),
                     "guides: shape_at's time must be a finite number of seconds, got nan"),
    "shape_at_string": (lambda: GuideAnimation(GUIDE_FRAMES, np.array([0, 4]), 25.0).shape_at("0.1"),
                        "shape_at's time must be a finite number of seconds, got '0.1'"),
    "corr_offsets_past_the_end": (lambda: corr(offsets=np.array([0, 12])),
                                  r"build_correspondence offsets: must start at 0, increase strictly and end at the "
                                  r"10 detail vertices, got \[0, 12\]"),
    "corr_free_shape": (lambda: corr(free=np.ones(3, bool)), r"build_correspondence free: must be a boolean mask of "
                                                            r"shape \(10,\), got bool \(3,\)"),
    "corr_masses_shape": (lambda: corr(masses=np.ones(3)), r"build_correspondence masses: must be 10 finite numbers"),
    "corr_masses_negative": (lambda: corr(masses=-np.ones(10)), r"masses: must be 10 finite numbers >= 0 .*min -1"),
    "corr_points_string": (lambda: corr(points_per_guide="4"),
                           "tracking.points_per_guide: must be an integer >= 1, got '4'"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_api_names_a_wrong_type(case):
    call, match = CASES[case]
    with pytest.raises(InputError, match=match) as info:
        call()
    assert "\n" not in str(info.value)


def test_valid_api_input_still_builds():
    """Whole float counts and numpy scalars are numbers; the checks refuse only what is not."""
    s = Strands.from_polylines(LINE.tolist(), [10.0], np.float64(1e-4))
    assert s.n_vertices == 10 and s.offsets.dtype == np.int64
    g = GuideAnimation(GUIDE_FRAMES, [0, 4], np.float32(25.0))
    assert np.allclose(g.shape_at(np.float64(0.02)), GUIDE_FRAMES[0]) and isinstance(g.fps, float)
    c = corr(masses=np.full(10, 1e-5), offsets=[0.0, 10.0])
    assert c.guide_of_strand.tolist() == [0]


def test_a_relative_input_path_is_read_from_the_launch_folder_under_chdir(tmp_path):
    """hydra.job.chdir=true runs the job inside its run folder; ``scene.usd=scene.usda`` is the
    file of the folder hairexp was started in (it was 'no such file', exit 2)."""
    write_stage(tmp_path / "scene.usda", source_cfg())
    env = dict(os.environ, PYTHONPATH=os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "hairexp", "experiment=from_usd", "scene.usd=scene.usda", "frames=2",
                        "logging.rerun=false", "logging.progress=false", "hydra.job.chdir=true",
                        f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "completed" and s["config"]["scene"]["usd"] == str(tmp_path / "scene.usda")


def test_absolute_inputs_also_makes_a_variants_path_absolute():
    from omegaconf import OmegaConf

    from hairexp.app.cli import absolute_inputs

    cfg = OmegaConf.create({"scene": {"usd": "a.usda"}, "guides": {"file": "/abs/g.npz"},
                            "variants": [{"name": "v", "overrides": ["guides.file=g.npz", "frames=3"]}]})
    absolute_inputs(cfg, "/launch")
    assert cfg.scene.usd == "/launch/a.usda" and cfg.guides.file == "/abs/g.npz"
    assert list(cfg.variants[0].overrides) == ["guides.file=/launch/g.npz", "frames=3"]
    absolute_inputs(cfg, None)   # no launch folder known: nothing changes
    assert cfg.scene.usd == "/launch/a.usda"


@pytest.mark.parametrize("quat, samples", [((0.0, 0.0, 0.0, 0.0), None), ((1.0, 0.0, 0.0, 0.0), {2: (0.0, 0.0, 0.0, 0.0)})])
def test_a_zero_orientation_quaternion_is_refused(tmp_path, quat, samples):
    """USD turned a zero quaternion into no rotation and the run went on (exit 0)."""
    from hairexp.io.usd_read import build_usd_scene

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS))

    def edit(stage):
        prim = stage.GetPrimAtPath("/Root/Colliders/wheel")
        attr = prim.CreateAttribute("xformOp:orient", Sdf.ValueTypeNames.Quatd)
        attr.Set(Gf.Quatd(quat[0], Gf.Vec3d(*quat[1:])))
        for t, q in (samples or {}).items():
            attr.Set(Gf.Quatd(q[0], Gf.Vec3d(*q[1:])), t)
        order = list(prim.GetAttribute("xformOpOrder").Get() or [])
        prim.GetAttribute("xformOpOrder").Set(order + ["xformOp:orient"])
    edit_stage(path, edit)
    at = "the default time" if samples is None else "time code 2"
    with pytest.raises(InputError, match=f"xformOp:orient at {at} is \\[0.0, 0.0, 0.0, 0.0\\], not a rotation"):
        build_usd_scene(usd_cfg(path).scene)
