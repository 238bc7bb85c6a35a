"""The small runs whose implicit Euler results are frozen in tests/data/implicit_euler_reference.npz
(made with the code before ``solver.integrator`` existed, commit 0fa8655 (main just before the merge; the
bending change at the clamp came in before it):
``PYTHONPATH=<that checkout>:tests python tests/integrator_reference.py tests/data/implicit_euler_reference.npz``).
Only APIs that existed then are used here, so the same function runs on both versions."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np

from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Material, Scene
from hairexp.model.strands import Strands
from hairexp.physics.simulator import Simulator

SOLVER = dict(rtol=1e-6, atol=1e-12, max_iterations=30, max_backtracks=30, derivatives="closed_form",
              stretch_hessian="primal_dual", compile="off", on_failure="substep", max_substep_levels=4)


def damped_scene() -> Scene:
    """Two 8-vertex strands (one tilted) with edge damping and air drag on a root swung sideways."""
    a = np.zeros((8, 3))
    a[:, 1] = -0.02 * np.arange(8)
    b = a + [0.01, 0.0, 0.0]
    b[:, 0] += 0.01 * np.arange(8)
    pts = np.concatenate([a, b])
    s = Strands.from_polylines(pts, np.array([8, 8]), 2e-4, where="reference")
    motion = RigidMotion(np.array([0.0, 0.2]), np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.01]]), np.zeros((2, 3)),
                         "cubic", where="reference")
    mat = Material(2e-4, 20.0, 2e-6, edge_damping=1e-3, air_drag=0.3)
    return Scene("reference", s, mat, motion, np.array([0.0, -9.81, 0.0]), pts.copy())


def reference_runs(**solver) -> dict:
    """(steps, V, 3) positions and velocities of the damped scene, 12 steps of 0.04 s."""
    sim = Simulator(damped_scene(), SimpleNamespace(**{**SOLVER, **solver}))
    st = sim.initial_state()
    X, V = [], []
    for _ in range(12):
        st, _ = sim.step(st, 0.04)
        X.append(st.x.copy())
        V.append(st.v.copy())
    return {"x": np.array(X), "v": np.array(V)}


if __name__ == "__main__":
    np.savez(sys.argv[1], **reference_runs())
