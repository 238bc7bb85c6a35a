"""The step schedule of a run: frames at ``fps``, each split into equal steps no longer than dt."""

from __future__ import annotations

import math

from hairexp.errors import MIN_STEP_DT, InputError
from hairexp.guides.animation import check_fps


def step_schedule(fps: float, dt: float, frames: int) -> tuple[int, float]:
    """Steps per frame and the step size that divides the frame interval evenly."""
    check_fps(fps)
    if not (dt > 0 and math.isfinite(dt)):
        raise InputError(f"must be a finite number > 0, got {dt}", "solver.dt")
    if frames < 1:
        raise InputError(f"must be >= 1, got {frames}", "frames")
    frame_dt = 1.0 / fps
    n = max(1, int(math.ceil(frame_dt / dt - 1e-9)))
    if frame_dt / n < MIN_STEP_DT:   # fps=100000 with solver.dt=1e-10: a traceback from the guides' simulation
        raise InputError(f"splits a frame of {frame_dt:g} s (fps {fps:g}) into steps of {frame_dt / n:.3g} s, below "
                         f"the shortest step {MIN_STEP_DT:g} s, got {dt:g}", "solver.dt")
    return n, frame_dt / n
