"""Run one experiment: build the scene, step it, feed the sinks, write the run folder.

Files (see README "Run folder"): metrics.parquet, summary.json, recording.rrd, result.npz,
result.usda.
On an error, summary.json records ``"status": "failed"`` with the message, no result.npz (nor result.usda) is
written and the recording keeps its ``.partial`` name; the error propagates (non-zero exit).
"""

from __future__ import annotations

import hashlib
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

from hairexp.config import to_plain
from hairexp.errors import InputError
from hairexp.physics.integrator import Simulator
from hairexp.physics.settle import settle_scene
from hairexp.scene.builders import build_scene
from hairexp.tracking.guides import build_guides
from hairexp.sinks.files import ResultRecorder, write_json
from hairexp.sinks.metrics import MetricsTable, measure
from hairexp.sinks.progress import Progress, progress_enabled


def step_schedule(fps: float, dt: float, frames: int) -> tuple[int, float]:
    """Steps per frame and the step size that divides the frame interval evenly."""
    if not (fps > 0 and math.isfinite(fps)):
        raise InputError(f"must be > 0, got {fps}", "fps")
    if not (dt > 0 and math.isfinite(dt)):
        raise InputError(f"must be > 0, got {dt}", "solver.dt")
    if frames < 1:
        raise InputError(f"must be >= 1, got {frames}", "frames")
    frame_dt = 1.0 / fps
    n = max(1, int(math.ceil(frame_dt / dt - 1e-9)))
    return n, frame_dt / n


def body_metrics(b: np.ndarray) -> dict:
    """Metrics columns of a dynamic body's state (``State.duals['body']``): position (m),
    velocity (m/s), the hair's force on it and the rail's (N)."""
    from hairexp.scene.dynamic_body import HAIR_FORCE, POSITION, RAIL_FORCE, VELOCITY

    parts = (("body_", POSITION), ("body_v_", VELOCITY), ("body_hair_force_", HAIR_FORCE),
             ("body_rail_force_", RAIL_FORCE))
    return {f"{prefix}{c}": float(v) for prefix, sl in parts for c, v in zip("xyz", b[sl])}


def config_hash(plain: dict) -> str:
    return hashlib.sha256(json.dumps(plain, sort_keys=True, default=str).encode()).hexdigest()[:16]


def versions() -> dict:
    import scipy
    import torch

    return {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "torch": torch.__version__}


def summarize(table, plain: dict, scene_name: str, controller: str, wall: float, status: str,
              error: str | None = None) -> dict:
    df = table.frame()
    n = len(df)
    agg = {}
    if n:
        agg = {
            "steps": n,
            "iterations_mean": float(df["iterations"].mean()),
            "iterations_max": int(df["iterations"].max()),
            "converged_fraction": float(df["converged"].mean()),
            "recovered_steps": int(df["recovered"].sum()),
            "step_seconds_median": float(df["step_seconds"].median()),
            "stretch_max": float(df["stretch_max"].max()),
            "residual_rel_max": (float(df["residual_rel_max"].max()) if df["residual_rel_max"].notna().any()
                                 else None),
        }
    return {
        "scene": scene_name, "controller": controller, "experiment": plain.get("experiment"),
        "status": status, "error": error, "success": None, "measures": {},
        **agg, "wall_seconds": wall, "config_hash": config_hash(plain), "versions": versions(), "config": plain,
    }


def run(cfg, out_dir: str | Path) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plain = to_plain(cfg)
    controller = plain["controller"]["name"]
    t_start = time.perf_counter()
    table = MetricsTable()
    scene_name = plain["scene"]["name"]
    rerun_sink = progress = None
    ok = False
    try:
        if cfg.frames is None or cfg.fps is None:  # null: from the USD stage (experiment=from_usd)
            from hairexp.io.usd_read import stage_timing

            cfg = stage_timing(cfg)
            plain = to_plain(cfg)
        n_sub, dt = step_schedule(cfg.fps, cfg.solver.dt, cfg.frames)
        scene = build_scene(cfg.scene)
        scene = settle_scene(scene, cfg)   # scene.settle > 0: start from the hair at rest under gravity
        guides = build_guides(cfg, scene, cfg.frames, cfg.fps)
        tracked = controller == "tracking"
        if controller == "skinned":   # baseline: detail hair skinned to the guides, no simulation
            from hairexp.tracking.skinning import skinned_simulator

            sim = skinned_simulator(scene, cfg.solver, guides)
        else:
            attraction = None
            if controller == "attract":   # baseline: springs to the guide-skinned positions
                k = float(cfg.controller.attract_stiffness)
                if not (k > 0 and math.isfinite(k)):
                    raise InputError(f"must be > 0, got {k}", "controller.attract_stiffness")
                attraction = (guides, k)
            sim = Simulator(scene, cfg.solver, cfg.tracking if tracked else None, guides if tracked else None,
                            cfg.collision, attraction=attraction)
        tracker = sim.tracker
        guides.save(out / "guides.npz")
        recorder = ResultRecorder(scene)

        def observe(state):
            if tracker is None:
                obs = {"guides": guides.shape_at(state.time)}
            else:
                obs = tracker.measure(sim.free_dofs(state.x), state.time, state.duals)
            effort = sim.control_effort(state)
            if effort is not None:   # baselines: spring force (attract) or implied force (skinned) / weight
                obs["control_force_rel"] = effort
            if sim.body is not None:  # a dynamic block: its state as metrics columns
                obs.update(body_metrics(state.duals["body"]))
            return obs
        if cfg.logging.rerun:
            from hairexp.sinks.rerun_sink import RerunSink  # rerun is imported only here

            rerun_sink = RerunSink(str(out / "recording.rrd"), scene, strict=cfg.logging.strict)
        progress = Progress(cfg.frames * n_sub, progress_enabled(cfg.logging.progress), desc=scene_name)
        if rerun_sink:
            rerun_sink.log_static(guides, tracker)
        state = sim.initial_state()
        obs = observe(state)
        recorder.log_frame(0, state, obs.get("guides"), obs.get("targets"), obs.get("com"))
        if rerun_sink:
            rerun_sink.log_frame(0, state, obs)
        step = 0
        for frame in range(1, cfg.frames + 1):
            for _ in range(n_sub):
                state, info = sim.step(state, dt)
                step += 1
                obs = observe(state)
                extra = {k: v for k, v in obs.items() if np.isscalar(v)}
                row = measure(scene, state, info, sim, step, frame, controller, extra)
                for sink in (table, rerun_sink, progress):
                    if sink is not None:
                        sink.on_step(row, state)
            recorder.log_frame(frame, state, obs.get("guides"), obs.get("targets"), obs.get("com"))
            if rerun_sink:
                rerun_sink.log_frame(frame, state, obs)
        from hairexp.scenes.measures import RunData, compute

        measures = compute(cfg.measure, RunData(scene, np.asarray(recorder.times), np.asarray(recorder.positions),
                                                tracker, sim.objective.free_vertices,
                                                getattr(recorder, "body_positions", None), table.frame()))
        cov = None if tracker is None else tracker.corr.cluster_of_vertex
        recorder.write(out / "result.npz", guides.offsets, cov)
        from hairexp.io.usd_write import write_result_usd  # pxr is imported here

        wscene = scene
        if sim.body is not None:  # the block's recorded poses, linear between frames
            from dataclasses import replace

            from hairexp.scene.rigid import RigidMotion

            P = np.asarray(recorder.body_positions)
            rv = np.repeat(sim.body.rotvecs, len(P), axis=0)
            wscene = replace(scene, motion=RigidMotion(np.asarray(recorder.times), P, rv, "linear"))
        write_result_usd(out / "result.usda", wscene, recorder.positions, recorder.guide_positions, guides.offsets,
                         cfg.fps)
        ok = True
    except Exception as exc:
        summary = summarize(table, plain, scene_name, controller, time.perf_counter() - t_start, "failed", str(exc))
        write_json(out / "summary.json", summary)
        if len(table.rows):
            table.frame().to_parquet(out / "metrics.parquet")
        raise
    finally:
        if progress is not None:
            progress.close()
        if rerun_sink is not None:
            rerun_sink.close(success=ok)
    table.frame().to_parquet(out / "metrics.parquet")
    summary = summarize(table, plain, scene_name, controller, time.perf_counter() - t_start, "completed")
    summary["measures"] = measures
    write_json(out / "summary.json", summary)
    return summary
