"""A USD transform read as USD computes it between its time samples (hairexp/io/usd_layout.py
``read_motion``): a turn keyed at two frames, a parent's turn about a pivot, two-axis Euler keys;
and where such a motion's velocity jumps (``RigidMotion.velocity_jumps``: the keyframes, not the
samples of a motion baked at every frame)."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from hairexp.io.usd_layout import POSE_TOL_M, pose_from_matrix, read_motion, world_transform
from hairexp.model.rigid import RigidMotion

FPS = 24.0


def new_stage(path, end: float):
    st = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(st, 1.0)
    st.SetTimeCodesPerSecond(FPS)
    st.SetStartTimeCode(0)
    st.SetEndTimeCode(end)
    return st


def worst_error(st, prim, motion, end: float, point=(0.1, 0.05, -0.02)) -> float:
    """Largest distance between a body point carried by USD's transform and by ``motion``, at 161
    times from time code 0 to ``end`` (between frames too)."""
    X = np.asarray(point, dtype=np.float64)
    xf = UsdGeom.Xformable(prim)
    worst = 0.0
    for tc in np.linspace(0.0, end, 161):
        R, T, _ = pose_from_matrix(world_transform(xf, Usd.TimeCode(tc), "test"), "test", tc)
        R2, T2 = motion.pose(tc / FPS)
        worst = max(worst, float(np.linalg.norm(R @ X + T - (R2 @ X + T2))))
    return worst


@pytest.mark.parametrize("degrees", [360.0, 270.0, -200.0, 90.0])
def test_a_turn_keyed_at_two_frames_is_read_as_usd_turns_it(tmp_path, degrees):
    """rotateY keyed 0 -> degrees at time codes 0 and 8: a whole turn was read as no motion and
    270 as -90 (the shortest rotation between the two samples)."""
    st = new_stage(tmp_path / "turn.usda", 8)
    body = UsdGeom.Xform.Define(st, "/Root/Body")
    body.AddTranslateOp().Set(Gf.Vec3d(0.0, 1.5, 0.0))
    op = body.AddRotateYOp()
    op.Set(0.0, 0)
    op.Set(degrees, 8)
    motion, _ = read_motion(body.GetPrim(), FPS, "test")
    assert worst_error(st, body.GetPrim(), motion, 8) < 1e-12
    R, _ = motion.pose(4 / FPS)    # half way: half the turn, the way USD takes it
    half = np.radians(degrees / 2)
    assert np.allclose(R, [[np.cos(half), 0, np.sin(half)], [0, 1, 0], [-np.sin(half), 0, np.cos(half)]], atol=1e-12)


def test_a_parent_turning_about_its_pivot_swings_the_body_along_an_arc(tmp_path):
    st = new_stage(tmp_path / "arc.usda", 8)
    rig = UsdGeom.Xform.Define(st, "/Root/Rig")
    op = rig.AddRotateYOp()
    op.Set(0.0, 0)
    op.Set(90.0, 8)
    body = UsdGeom.Xform.Define(st, "/Root/Rig/Body")
    body.AddTranslateOp().Set(Gf.Vec3d(0.5, 1.5, 0.0))
    motion, _ = read_motion(body.GetPrim(), FPS, "test")
    # a straight line from (0.5, 0) to (0, -0.5) missed the arc by 0.146 m half way
    assert worst_error(st, body.GetPrim(), motion, 8) < 2 * POSE_TOL_M
    # the samples: every frame, and between frames where the arc is not yet straight enough
    assert len(motion.times) > 9


def test_two_axis_euler_keys_are_followed(tmp_path):
    st = new_stage(tmp_path / "euler.usda", 8)
    body = UsdGeom.Xform.Define(st, "/Root/Body")
    op = body.AddRotateXYZOp()
    op.Set(Gf.Vec3f(0, 0, 0), 0)
    op.Set(Gf.Vec3f(90, 90, 0), 8)
    motion, _ = read_motion(body.GetPrim(), FPS, "test")
    assert worst_error(st, body.GetPrim(), motion, 8) < 2 * POSE_TOL_M


def test_a_transform_keyed_at_every_frame_has_no_velocity_jump_between_its_ends(tmp_path):
    """A body baked at every frame (a smooth turn about a pivot): no frame is a jump, with two steps a
    frame (24 fps at dt 0.04: every key had counted, and the time integrator restarted every other
    step) or more; its first and last samples still count (the stillness outside them)."""
    st = new_stage(tmp_path / "baked.usda", 16)
    body = UsdGeom.Xform.Define(st, "/Root/Body")
    op = body.AddRotateYOp()
    tr = body.AddTranslateOp()
    for f in range(17):
        op.Set(3.0 * f + 0.2 * f * f, f)
        tr.Set(Gf.Vec3d(0.01 * f * f, 1.5, 0.0), f)
    motion, _ = read_motion(body.GetPrim(), FPS, "test")
    for steps in (2, 5):
        h = 1.0 / FPS / steps
        t = np.arange(0.0, 16 / FPS - 1e-12, h)
        assert not any(motion.velocity_jumps(a, a + h, since=0.0) for a in t), steps
    h = 1.0 / FPS / 2
    assert motion.velocity_jumps(16 / FPS - 1e-12, 16 / FPS + h)   # it stops at its last sample


def test_sparse_linear_keys_still_jump_at_the_keys(tmp_path):
    """translate keyed at time codes 0, 12 and 24 (a turn of direction at 12): read at every frame,
    the velocity jumps at the keys only."""
    st = new_stage(tmp_path / "keys.usda", 24)
    body = UsdGeom.Xform.Define(st, "/Root/Body")
    tr = body.AddTranslateOp()
    tr.Set(Gf.Vec3d(0, 1.5, 0), 0)
    tr.Set(Gf.Vec3d(0.2, 1.5, 0), 12)
    tr.Set(Gf.Vec3d(0.2, 1.5, 0.3), 24)
    motion, _ = read_motion(body.GetPrim(), FPS, "test")
    assert len(motion.times) == 25
    h = 1.0 / FPS / 2
    jumps = [a for a in np.arange(h, 24 / FPS, h) if motion.velocity_jumps(a, a + h, since=0.0)]
    assert np.allclose(jumps, [12 / FPS]), jumps


def test_jump_times_select_the_keys_that_can_jump():
    m = RigidMotion(np.array([0.0, 0.1, 0.2, 0.3]), np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1.0]]),
                    np.zeros((4, 3)), "linear", jump_times=np.array([0.0, 0.2, 0.3]))
    assert not m.velocity_jumps(0.09, 0.11)      # 0.1 is a sample, not a key
    assert m.velocity_jumps(0.19, 0.21)
    free = RigidMotion(m.times, m.translations, m.rotvecs, "linear")
    assert free.velocity_jumps(0.09, 0.11)       # without jump_times every key whose segments are long
