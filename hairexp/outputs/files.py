"""Result files of the run folder, written atomically (temp file, then rename) so a crash
never leaves a half-written file under its final name."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def atomic_write_bytes(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        write(f)
    os.replace(tmp, path)


def write_json(path: Path, obj) -> None:
    def default(o):
        if isinstance(o, (np.integer,)):
            return int(o)
        if isinstance(o, (np.floating,)):
            return float(o)
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)

    atomic_write_bytes(Path(path), lambda f: f.write(json.dumps(obj, indent=2, default=default, allow_nan=True).encode()))


class ResultRecorder:
    """Keeps per-frame arrays for ``result.npz`` (frame 0 is the initial state)."""

    def __init__(self, scene):
        self.scene = scene
        self.positions, self.times = [], []
        self.guide_positions, self.targets, self.com = [], [], []
        self.body_positions = []   # (3,) per frame: the body's pose translation (any body, keyframed or dynamic)

    def log_frame(self, frame: int, state, motion=None, guides: np.ndarray | None = None,
                  targets: np.ndarray | None = None, com: np.ndarray | None = None) -> None:
        """Frame ``frame`` of ``state``; ``motion``: the body's poses at ``state.time``
        (``Simulator.motion_of``), default the scene's motion."""
        self.positions.append(state.x.copy())
        self.times.append(state.time)
        self.guide_positions.append(np.zeros((0, 3)) if guides is None else guides)
        self.targets.append(np.zeros((0, 3)) if targets is None else targets)
        self.com.append(np.zeros((0, 3)) if com is None else com)
        self.body_positions.append((motion or self.scene.motion).pose(state.time)[1])

    def write(self, path: Path, guide_offsets: np.ndarray | None = None, cluster_of_vertex: np.ndarray | None = None) -> None:
        s = self.scene.strands
        arrays = dict(
            positions=np.asarray(self.positions), strand_offsets=s.offsets, times=np.asarray(self.times),
            guide_positions=np.asarray(self.guide_positions), masses=s.masses,
            guide_offsets=np.zeros(1, dtype=np.int64) if guide_offsets is None else guide_offsets,
            cluster_of_vertex=np.full(s.n_vertices, -1, dtype=np.int64) if cluster_of_vertex is None else cluster_of_vertex,
            targets=np.asarray(self.targets), com=np.asarray(self.com),
            body_positions=np.asarray(self.body_positions).reshape(-1, 3),
        )
        for k, a in arrays.items():
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                raise AssertionError(f"refusing to write non-finite {k} to {path}")
        atomic_write_bytes(Path(path), lambda f: np.savez_compressed(f, **arrays))
