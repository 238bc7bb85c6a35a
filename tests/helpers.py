"""Plain helpers shared by the tests (fixtures live in conftest.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from hairexp.app.config import HairConfig, MotionConfig, SceneConfig, SolverConfig

REPO = Path(__file__).resolve().parents[1]
CONF_DIR = REPO / "conf"


def bent_polyline(n: int, seed: int, edge: float = 0.02, max_turn: float = 1.0) -> np.ndarray:
    """(n, 3) random polyline, edge lengths in [0.5, 1.5] * edge, turning angles up to max_turn rad."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    pts = [rng.normal(size=3) * 0.1]
    for _ in range(n - 1):
        axis = np.cross(d, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        ang = rng.uniform(min(0.05, 0.5 * max_turn), max_turn)
        # Rodrigues rotation of d about axis (axis is orthogonal to d)
        d = np.cos(ang) * d + np.sin(ang) * np.cross(axis, d)
        pts.append(pts[-1] + edge * rng.uniform(0.5, 1.5) * d)
    return np.asarray(pts)


def chain_stencils(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (n-1, 2) and bending triples (n-2, 3) of one open chain of n vertices."""
    i = np.arange(n)
    return np.stack([i[:-1], i[1:]], 1), np.stack([i[:-2], i[1:-1], i[2:]], 1)


def as_t(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=torch.float64)


def scene_cfg(**kw):
    """A small wisp SceneConfig (OmegaConf structured); nested ``hair``/``motion`` as dicts."""
    hair = HairConfig(**kw.pop("hair", {}))
    motion = MotionConfig(**kw.pop("motion", {}))
    base = dict(name="test", n_strands=3, n_vertices=8, length=0.2, root_radius=0.01)
    base.update(kw)
    return OmegaConf.structured(SceneConfig(hair=hair, motion=motion, **base))


def solver_cfg(**kw):
    return OmegaConf.structured(SolverConfig(**kw))


def run_steps(sim, n: int, dt: float, state=None):
    """Step ``sim`` n times: (states, infos), states[0] the initial (or given) state."""
    state = sim.initial_state() if state is None else state
    states, infos = [state], []
    for _ in range(n):
        state, info = sim.step(state, dt)
        states.append(state)
        infos.append(info)
    return states, infos
