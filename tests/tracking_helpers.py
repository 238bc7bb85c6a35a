"""Plain helpers for the tracking-solver tests (paper 3.1-3.4): small tracked scenes built from
the structured config (no Hydra needed), scenes built directly from polylines, and a recorder of
every SQP attempt the integrator makes (including attempts that recovery discarded)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import helpers
import numpy as np
from omegaconf import OmegaConf

from hairexp.app.config import Config, TrackingConfig
from hairexp.physics.simulator import Simulator
from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Material, Scene
from hairexp.model.strands import Strands
from hairexp.app.assemble import assemble
from hairexp.guides.animation import GuideAnimation

NO_GRAVITY = [0.0, 0.0, 0.0]
DT = 0.04  # s: one step per frame at 25 fps

#: The goaling body motion (conf/experiment/goaling.yaml): piecewise-constant velocity, then a stop.
GOALING_MOTION = {
    "scene.motion.interpolation": "linear",
    "scene.motion.times": [0.0, 0.2, 0.4, 0.6, 0.8, 2.24],
    "scene.motion.translations": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.2, 0.0, 0.0],
                                  [0.45, 0.0, 0.0], [0.45, 0.0, 0.0]],
    "scene.motion.rotations_deg": [[0.0, 0.0, 0.0]] * 6,
}


def tracked_cfg(overrides: dict | None = None):
    """A structured ``Config`` for a small tracked run: 16 strands x 12 vertices, one straight
    guide of 8 vertices, 4 tracking points, sliding targets, the paper's hard assignment and
    implicit Euler (these tests check the paper's formulation; tests/test_soft_assignment.py
    asks for soft), no
    recording.  ``overrides`` are dotted keys (``{"scene.n_strands": 12, "tracking.targets": "static"}``)."""
    cfg = OmegaConf.structured(Config)
    base = {
        "controller.name": "tracking",
        "scene.name": "tracking_test",
        "scene.n_strands": 16,
        "scene.n_vertices": 12,
        "guides.count": 1,
        "tracking.points_per_guide": 4,
        "tracking.assignment": "hard",
        # the paper's time step, eq. (5), which these tests re-evaluate by hand (the default,
        # trbdf2, is covered by tests/test_integrator.py with every controller)
        "solver.integrator": "implicit_euler",
        "solver.compile": "off",
        "logging.rerun": False,
        "logging.progress": False,
        "frames": 25,
    }
    base.update(overrides or {})
    for k, v in base.items():
        OmegaConf.update(cfg, k, v, merge=False)
    return cfg


def build_tracked(cfg):
    """(scene, guides, simulator) for a tracked config, assembled as a run is
    (``hairexp.app.assemble``)."""
    run = assemble(cfg)
    assert run.controller.name == "tracking"
    return run.scene, run.guides, run.simulator


def tracking_cfg(**kw):
    """A structured ``TrackingConfig`` (``variance`` as a dict); hard assignment unless ``assignment`` says."""
    var = kw.pop("variance", {})
    kw.setdefault("assignment", "hard")
    cfg = OmegaConf.structured(TrackingConfig)
    for k, v in kw.items():
        OmegaConf.update(cfg, k, v, merge=False)
    for k, v in var.items():
        OmegaConf.update(cfg, f"variance.{k}", v, merge=False)
    return cfg


def polyline_scene(polylines: list[np.ndarray], gravity=NO_GRAVITY, motion: RigidMotion | None = None,
                   linear_density: float = 2e-4) -> Scene:
    """A Scene built directly from detail polylines (any vertex counts), at rest at t = 0 under a
    static body (the world frame is the body frame)."""
    pts = np.concatenate(polylines)
    counts = np.array([len(p) for p in polylines])
    strands = Strands.from_polylines(pts, counts, linear_density, where="test scene")
    mat = Material(linear_density, 20.0, 2e-6)
    motion = RigidMotion.static() if motion is None else motion
    return Scene("polyline_test", strands, mat, motion, np.asarray(gravity, dtype=np.float64), pts.copy())


def static_guides(polylines: list[np.ndarray], fps: float = 25.0) -> GuideAnimation:
    """A one-frame guide animation (guides that never move) from guide polylines."""
    pts = np.concatenate(polylines)
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in polylines])])
    return GuideAnimation(pts[None], offsets, fps)


def straight(root, direction, length: float, n: int) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return np.asarray(root, dtype=np.float64) + np.linspace(0.0, length, n)[:, None] * d


def free_vertex_com(sim: Simulator, x: np.ndarray) -> np.ndarray:
    """(K, 3) cluster centres of mass, eq. (2), computed by hand from masses and clusters."""
    s = sim.scene.strands
    cov = sim.controller.corr.cluster_of_vertex
    K = sim.controller.cons.K
    com = np.zeros((K, 3))
    for k in range(K):
        v = np.flatnonzero(cov == k)
        com[k] = (s.masses[v, None] * x[v]).sum(0) / s.masses[v].sum()
    return com


@dataclass
class Attempts:
    """Every ``sqp_solve`` call made by the integrator: (status, iterations, backtracks)."""
    calls: list = field(default_factory=list)

    @property
    def iterations(self) -> int:
        return sum(c[1] for c in self.calls)

    @property
    def failed(self) -> list:
        return [c for c in self.calls if c[0] != "converged"]


@contextlib.contextmanager
def record_attempts(monkeypatch):
    """Wrap the integrator's ``sqp_solve`` to record every attempt (StepInfo only sums the
    substeps that were kept, not an attempt that recovery replaced)."""
    import hairexp.control.tracking.controller as integ

    rec = Attempts()
    orig = integ.sqp_solve

    def wrapped(*a, **k):
        out = orig(*a, **k)
        info = out[3]
        rec.calls.append((info.status, info.iterations, info.backtracks))
        return out

    monkeypatch.setattr(integ, "sqp_solve", wrapped)
    try:
        yield rec
    finally:
        monkeypatch.setattr(integ, "sqp_solve", orig)


def run_steps(sim: Simulator, n: int, dt: float = DT, state=None):
    """(states, infos): states[0] is the initial state."""
    return helpers.run_steps(sim, n, dt, state)


def structured_sliding_args(tr, rng, K: int):
    """The sliding-target blocks of eq. (8) as the SQP builds them (dC/dt = -c_hat'(t) at t 5 % past
    rest), with random diagonal and right-hand side: (B, diag, r_t) for ``kkt.solve``."""
    _, d1, _ = tr.cons.target_points(tr.tg, tr.cons.t_rest * 1.05, derivatives=True)
    B = np.zeros((3 * K, K))
    B[np.arange(3 * K), np.arange(3 * K) // 3] = -d1.reshape(-1)
    return B, rng.uniform(0.0, 1e-3, K), rng.normal(size=K) * 1e-4
