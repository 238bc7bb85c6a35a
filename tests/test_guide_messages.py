"""The guide animation's input errors say what is wrong and nothing else (independent probe,
2026-12-07): offsets of the wrong shape are a shape error, and points near 1e298 are the extent's
error without numpy's overflow warning first."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from hairexp.errors import InputError
from hairexp.guides.animation import GuideAnimation


def guides(frames=3):
    P = np.zeros((frames, 8, 3))
    P[:, :4, 1] = -np.arange(4) * 0.05
    P[:, 4:, 1] = -np.arange(4) * 0.05
    P[:, 4:, 0] = 0.1
    return P


def test_offsets_of_the_wrong_shape_are_a_shape_error():
    with pytest.raises(InputError, match=r"must be a 1-D array \(G \+ 1,\) of integers, got shape \(1, 3\)"):
        GuideAnimation(guides(), np.array([[0, 4, 8]]), 25.0)
    with pytest.raises(InputError, match=r"must be integers \(G \+ 1,\), got float64"):
        GuideAnimation(guides(), np.array([0.0, 4.5, 8.0]), 25.0)


def test_points_near_the_float_limit_are_the_extent_error_alone():
    P = guides()
    P[1, 2] = [0.0, 0.0, 1e298]
    with warnings.catch_warnings():
        warnings.simplefilter("error")     # an overflow warning would fail here
        with pytest.raises(InputError, match=r"frame 1, curve 0 vertex 2 is at .* more than 10000 m from the origin"):
            GuideAnimation(P, np.array([0, 4, 8]), 25.0)
