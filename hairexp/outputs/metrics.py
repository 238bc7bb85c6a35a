"""Per-step metrics, computed once per step whatever sinks are on, and the metrics table."""

from __future__ import annotations

import math

import numpy as np

from hairexp.physics.info import StepInfo
from hairexp.model.scene import Scene
from hairexp.physics.state import State

#: Columns every metrics table has (the run-folder contract, README "Run folder").
CONTRACT_COLUMNS = ("frame", "time", "controller", "iterations", "converged", "residual_max", "residual_rel_max",
                    "stretch_max", "stretch_mean", "variance_ratio_mean", "contacts", "step_seconds")


def stretch(scene: Scene, x: np.ndarray) -> np.ndarray:
    """(E,) signed edge strain l / l0 - 1."""
    e = scene.strands.edges
    return np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1) / scene.strands.rest_lengths - 1.0


def energies(scene: Scene, state: State, sim) -> tuple[float, float]:
    """Kinetic and potential (elastic + gravity) energy in J."""
    import torch

    kin = 0.5 * float(np.sum(scene.strands.masses[:, None] * state.v ** 2))
    x = torch.from_numpy(state.x)
    with torch.no_grad():
        pot = sum(float(t.total(x)) for t in sim.terms + sim.external if t.name in ("stretch", "bending", "gravity"))
    return kin, pot


def measure(scene: Scene, state: State, info: StepInfo, sim, step: int, frame: int, controller: str,
            extra: dict | None = None) -> dict:
    """The metrics row of one step.  Residual and variance columns are NaN where they do not
    apply (a free run has no tracking constraints and no clusters)."""
    eps = stretch(scene, state.x)
    kin, pot = energies(scene, state, sim)
    sec = info.seconds
    row = {
        "step": step, "frame": frame, "time": state.time, "dt": info.dt, "controller": controller,
        "status": str(info.status), "converged": bool(info.converged), "iterations": info.iterations,
        "iterations_attempted": info.iterations_attempted,
        "backtracks": info.backtracks, "substeps": info.substeps, "recovered": bool(info.recovered),
        "grad_norm": info.grad_norm, "force_scale": info.force_scale,
        "residual_max": math.nan, "residual_rms": math.nan, "residual_rel_max": math.nan,
        "stretch_max": float(np.abs(eps).max()), "stretch_mean": float(np.abs(eps).mean()),
        "variance_ratio_mean": math.nan, "constraint_force": math.nan, "constraint_force_rel": math.nan,
        "constraint_norm": info.constraint_norm,
        "contacts": info.object_contacts + info.hair_contacts, "object_contacts": info.object_contacts,
        "hair_contacts": info.hair_contacts, "penetration_max": info.penetration_max,
        "kinetic_energy": kin, "potential_energy": pot,
        "step_seconds": sec.get("total", 0.0),
        "t_derivatives": sec.get("derivatives", 0.0), "t_assembly": sec.get("assembly", 0.0),
        "t_solve": sec.get("solve", 0.0), "t_collision": sec.get("collision", 0.0), "t_other": sec.get("other", 0.0),
    }
    for name, n in info.collider_contacts.items():
        row[f"contacts_{name}"] = n
    if extra:
        row.update(extra)
    return row


class MetricsTable:
    """Collects rows; ``frame()`` gives the pandas table (one row per step)."""

    def __init__(self):
        self.rows: list[dict] = []

    def on_step(self, row: dict, state: State) -> None:
        self.rows.append(row)

    def frame(self):
        import pandas as pd

        return pd.DataFrame(self.rows)
