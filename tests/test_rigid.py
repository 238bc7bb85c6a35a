"""Keyframed rigid motion: poses hit the keyframes, velocities are the time derivative of the
pose (the simulator's initial state and root velocities come from them)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hairexp.model.rigid import RigidMotion

X = np.random.default_rng(0).normal(size=(6, 3)) * 0.1  # body points, m


def motion(interp: str, K: int) -> RigidMotion:
    rng = np.random.default_rng(K)
    times = np.sort(rng.uniform(0, 1, K)) + np.arange(K) * 0.1
    return RigidMotion(times, rng.normal(size=(K, 3)) * 0.1, rng.normal(size=(K, 3)) * 0.5, interp)


CASES = [(i, K) for i in ("cubic", "linear") for K in (2, 3, 5)]


@pytest.mark.parametrize("interp,K", CASES)
def test_pose_hits_keyframes(interp, K):
    m = motion(interp, K)
    for t, T, rv in zip(m.times, m.translations, m.rotvecs):
        R, T_got = m.pose(t)
        np.testing.assert_allclose(T_got, T, rtol=0, atol=1e-12)
        np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-12)


@pytest.mark.parametrize("interp,K", CASES)
def test_point_velocity_is_the_derivative_of_the_pose(interp, K):
    m = motion(interp, K)
    h = 1e-6
    ts = np.linspace(m.times[0], m.times[-1], 9)[1:-1] + 1e-4  # inside segments, off keyframes
    for t in ts:
        fd = (m.transform(X, t + h) - m.transform(X, t - h)) / (2 * h)
        np.testing.assert_allclose(m.point_velocity(X, t), fd, rtol=0, atol=1e-8 * max(1.0, np.abs(fd).max()))


@pytest.mark.parametrize("interp,K", CASES)
def test_held_outside_the_keyed_range(interp, K):
    m = motion(interp, K)
    for t, k in ((m.times[0] - 1.0, 0), (m.times[-1] + 1.0, -1)):
        R, T = m.pose(t)
        np.testing.assert_allclose(T, m.translations[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(m.point_velocity(X, t), 0.0, rtol=0, atol=0)


def test_linear_velocity_is_constant_per_segment_and_right_continuous():
    m = RigidMotion(np.array([0.0, 1.0, 3.0]), np.array([[0, 0, 0], [1.0, 0, 0], [1.0, 2.0, 0]]), np.zeros((3, 3)),
                    "linear")
    np.testing.assert_allclose(m.velocity(0.0)[1], [1.0, 0, 0])
    np.testing.assert_allclose(m.velocity(0.7)[1], [1.0, 0, 0])
    np.testing.assert_allclose(m.velocity(1.0)[1], [0, 1.0, 0])  # the following segment's
    np.testing.assert_allclose(m.velocity(2.5)[1], [0, 1.0, 0])
    np.testing.assert_allclose(m.velocity(3.0)[1], [0, 0, 0])    # stopped at the last keyframe


def test_cubic_translation_starts_and_ends_at_rest():
    m = RigidMotion(np.array([0.0, 0.4, 1.0]), np.array([[0, 0, 0], [0.2, 0.1, 0], [0.3, 0, 0.1]]), np.zeros((3, 3)),
                    "cubic")
    for t in (0.0, 1.0):
        np.testing.assert_allclose(m.velocity(t)[1], 0.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("interp,K", CASES)
def test_to_body_inverts_transform(interp, K):
    m = motion(interp, K)
    t = 0.5 * (m.times[0] + m.times[-1])
    np.testing.assert_allclose(m.to_body(m.transform(X, t), t), X, rtol=0, atol=1e-14)


def test_static_motion_is_identity():
    m = RigidMotion.static()
    np.testing.assert_array_equal(m.transform(X, 3.0), X)
    np.testing.assert_array_equal(m.point_velocity(X, 3.0), 0.0)


@pytest.mark.parametrize("interp,K", CASES + [("cubic", 1), ("linear", 1)])
def test_poses_are_pose_at_every_time_bit_for_bit(interp, K):
    """``poses`` (all times at once: guide animations, the roots' collider check) gives ``pose``'s
    values exactly, inside, at and outside the keys."""
    m = motion(interp, K) if K > 1 else RigidMotion(np.zeros(1), [[0.1, 0.2, 0.3]], [[0.3, -0.2, 0.1]], interp)
    ts = np.concatenate([np.linspace(m.times[0] - 0.3, m.times[-1] + 0.3, 97), m.times])
    R, T = m.poses(ts)
    assert R.shape == (len(ts), 3, 3) and T.shape == (len(ts), 3)
    for i, t in enumerate(ts):
        R1, T1 = m.pose(t)
        assert np.array_equal(R[i], R1) and np.array_equal(T[i], T1), (i, t)


def test_poses_of_small_turns_and_bad_times():
    """The series branch of exp_so3 (turns below 1e-6 rad) batched as one by one; non-finite times
    are an InputError naming the argument."""
    from hairexp.errors import InputError

    m = RigidMotion([0.0, 1.0], np.zeros((2, 3)), [[0.0, 0.0, 0.0], [3e-7, -2e-7, 1e-7]], "linear")
    ts = np.linspace(0.0, 1.0, 11)
    R, _ = m.poses(ts)
    for i, t in enumerate(ts):
        assert np.array_equal(R[i], m.pose(t)[0])
    with pytest.raises(InputError, match="RigidMotion.poses: times"):
        m.poses([0.0, float("nan")])


def test_linear_config_keys_about_one_axis_turn_by_their_difference():
    """rotations_deg keys 0, 720 about y (a paddle spun twice a second): the body turns 720 degrees,
    as cubic keys do (the shortest rotation between the keys is none: it never turned; independent
    probe, 2026-12-07); keys about different axes keep the shortest rotation; a motion without
    ``turns`` (rotations read from matrices) too."""
    from hairexp.model.builders import build_motion
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"interpolation": "linear", "times": [0.0, 1.0, 2.0],
                            "translations": [[0, 0, 0]] * 3, "rotations_deg": [[0, 0, 0], [0, 720, 0], [0, 1440, 0]]})
    m = build_motion(cfg)
    for t, deg in ((0.125, 90.0), (0.25, 180.0), (0.375, -90.0), (1.125, 90.0)):
        R, _ = m.pose(t)
        assert np.degrees(np.arctan2(R[0, 2], R[0, 0])) == pytest.approx(deg, abs=1e-9), t
    np.testing.assert_allclose(m.velocity(0.3)[0], [0.0, 4 * np.pi, 0.0], rtol=1e-12)
    R, _ = m.poses(np.array([0.125, 1.25]))
    np.testing.assert_allclose(np.degrees(np.arctan2(R[:, 0, 2], R[:, 0, 0])), [90.0, 180.0], atol=1e-9)
    skew = RigidMotion(np.array([0.0, 1.0]), np.zeros((2, 3)), np.radians([[0, 0, 170.0], [0, 170.0, 0]]), "linear",
                       turns=True)
    plain = RigidMotion(skew.times, skew.translations, skew.rotvecs, "linear")
    np.testing.assert_allclose(skew.pose(0.4)[0], plain.pose(0.4)[0], atol=1e-15)
    matrices = RigidMotion(np.array([0.0, 1.0]), np.zeros((2, 3)), np.radians([[0, 0, 0], [0, 720.0, 0]]), "linear")
    np.testing.assert_allclose(matrices.pose(0.25)[0], np.eye(3), atol=1e-12)
