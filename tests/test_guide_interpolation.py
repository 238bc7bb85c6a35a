"""Guide frames interpolated in time (``guides.interpolation``, hairexp/guides/animation.py):
Catmull-Rom by default (through every frame, velocity continuous, exact for quadratic motion
between interior frames), the chord as an option."""

from __future__ import annotations

import numpy as np
import pytest

from hairexp.guides.animation import GuideAnimation

FPS = 25.0


def animation(fn, frames: int = 8, interpolation: str | None = None) -> GuideAnimation:
    """One 3-vertex guide whose vertices follow fn(t) (3,) plus fixed offsets."""
    base = np.array([[0.0, 0.0, 0.0], [0.0, -0.05, 0.0], [0.0, -0.1, 0.0]])
    pos = np.stack([base + fn(f / FPS) for f in range(frames)])
    a = GuideAnimation(pos, np.array([0, 3]), FPS)
    if interpolation is not None:
        a.interpolation = interpolation
    return a


def quadratic(t):
    return np.array([0.3 * t * t - 0.1 * t, 0.02 * t, -0.5 * t * t])


def test_default_is_catmull_rom_and_passes_through_frames():
    a = animation(lambda t: np.array([np.sin(7 * t), np.cos(5 * t), t ** 3]))
    assert a.interpolation == "catmull_rom"
    for f in range(a.n_frames):
        np.testing.assert_array_equal(a.shape_at(f / FPS), a.positions[f])


def test_quadratic_motion_is_reproduced_between_interior_frames():
    a = animation(quadratic)
    for t in np.linspace(1 / FPS, 6 / FPS, 41):   # segments whose neighbours exist on both sides
        np.testing.assert_allclose(a.shape_at(t)[0], quadratic(t), atol=1e-14)
    lin = animation(quadratic, interpolation="linear")
    t = 2.5 / FPS
    assert np.abs(lin.shape_at(t)[0] - quadratic(t)).max() > 1e-5   # the chord is not


@pytest.mark.parametrize("interpolation, continuous", [("catmull_rom", True), ("linear", False)])
def test_velocity_at_frames(interpolation, continuous):
    """One-sided velocities at an interior frame: equal for Catmull-Rom, the chord's jump for linear."""
    a = animation(lambda t: np.array([np.sin(9 * t), 0.0, 0.0]), interpolation=interpolation)
    h = 1e-7
    for f in range(1, a.n_frames - 1):
        t = f / FPS
        left = (a.shape_at(t) - a.shape_at(t - h)) / h
        right = (a.shape_at(t + h) - a.shape_at(t)) / h
        jump = np.abs(right - left).max()
        if continuous:
            assert jump < 1e-5, (f, jump)
        else:
            assert jump > 1e-2, (f, jump)


def test_ends_and_two_frames():
    """Outside the animation the first / last frame holds; two frames: the chord (no neighbours)."""
    a = animation(quadratic, frames=5)
    np.testing.assert_array_equal(a.shape_at(-1.0), a.positions[0])
    np.testing.assert_array_equal(a.shape_at(10.0), a.positions[-1])
    two = animation(quadratic, frames=2)
    t = 0.5 / FPS
    np.testing.assert_allclose(two.shape_at(t), 0.5 * (two.positions[0] + two.positions[1]), atol=1e-15)


def test_config_key_reaches_the_animation():
    from hairexp.app.config import compose_config
    from hairexp.app.assemble import assemble_scene
    from hairexp.app.guides import build_guides

    for value in ("linear", "catmull_rom"):
        cfg = compose_config(["experiment=goaling_smoke", "frames=3", f"guides.interpolation={value}"])
        cfg, scene, _ = assemble_scene(cfg, settle=False)
        assert build_guides(cfg, scene, 3, float(cfg.fps)).interpolation == value


def _frame_by_frame(P, offsets, where="guides"):
    """The checks GuideAnimation made before they were batched: every frame on its own."""
    from hairexp.errors import check_extent
    from hairexp.model.strands import check_folds, validate_polylines

    counts = np.diff(offsets)
    for f, X in enumerate(P):
        X, _ = validate_polylines(X, counts, f"{where} frame {f}", min_vertices=2, folds=False)
        check_extent(X, where, counts, frame=f)
        check_folds(X, counts, f"{where} frame {f}")


@pytest.mark.parametrize("defect", ["nan", "zero_edge", "fold", "far", "near_limits"])
@pytest.mark.parametrize("store", [False, True])
def test_batched_frame_checks_refuse_what_frame_by_frame_checks_refuse(defect, store):
    """The guide frames are checked a block at a time (``suspect_frames``) and only suspect frames
    one by one: the same error, naming the same (first) bad frame, as checking every frame; and a
    frame near the limits (an edge just over MIN_EDGE_LENGTH, a turn just under MAX_TURN_DEG) passes."""
    from hairexp.errors import InputError
    from hairexp.guides.store import FrameStore
    from hairexp.model.strands import MAX_TURN_DEG, MIN_EDGE_LENGTH, suspect_frames

    rng = np.random.default_rng(7)
    G, Vg, F = 3, 5, 1400
    offsets = np.arange(G + 1) * Vg
    base = np.zeros((G * Vg, 3))
    for g in range(G):
        base[g * Vg:(g + 1) * Vg] = [0.1 * g, 0, 0] + np.outer(np.arange(Vg), [0.0, -0.02, 0.0])
    P = base[None] + 1e-3 * rng.normal(size=(F, 1, 3))   # each frame moved rigidly
    bad_frames = [1033, 1200]
    for f in bad_frames:
        if defect == "nan":
            P[f, 7, 1] = np.nan
        elif defect == "zero_edge":
            P[f, 8] = P[f, 7]
        elif defect == "fold":
            P[f, 9] = P[f, 7] + [0.0, 1e-3, 0.0]
        elif defect == "far":
            P[f, 3, 0] = 2e4
        else:   # passes: an edge of 1.5 x MIN_EDGE_LENGTH, a turn of MAX_TURN_DEG - 0.01 degrees
            P[f, 1] = P[f, 0] + [0.0, -1.5 * MIN_EDGE_LENGTH, 0.0]
            a = np.radians(MAX_TURN_DEG - 0.01)   # the last edge of guide 2 turned back from straight down by a
            P[f, 14] = P[f, 13] + 0.02 * np.array([np.sin(a), -np.cos(a), 0.0])
    try:
        _frame_by_frame(P, offsets)
        expected = None
    except InputError as exc:
        expected = str(exc)
    positions = FrameStore.of(P) if store else P
    assert suspect_frames(P[bad_frames], np.diff(offsets)).all()   # the defects are found by the batch
    assert not suspect_frames(P[:1000], np.diff(offsets)).any()
    if expected is None:
        GuideAnimation(positions, offsets, 25.0)
        assert defect == "near_limits"
    else:
        assert f"frame {bad_frames[0]}" in expected
        with pytest.raises(InputError) as got:
            GuideAnimation(positions, offsets, 25.0)
        assert str(got.value) == expected
