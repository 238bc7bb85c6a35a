"""Run one experiment: assemble it (hairexp/app/assemble.py), step it, feed the sinks, write
the run folder.

Files (see README "Run folder"): metrics.parquet, summary.json, recording.rrd, result.npz,
result.usda.
On an error, summary.json records ``"status": "failed"`` with the message, no result.npz (nor result.usda) is
written and the recording keeps its ``.partial`` name; the error propagates (non-zero exit).
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from hairexp.app.assemble import assemble
from hairexp.app.config import to_plain
from hairexp.evaluation.measures import RunData, compute
from hairexp.model.dynamic_body import HAIR_FORCE, POSITION, RAIL_FORCE, VELOCITY
from hairexp.model.rigid import RigidMotion
from hairexp.outputs.files import ResultRecorder, write_json
from hairexp.outputs.metrics import MetricsTable, measure
from hairexp.outputs.progress import Progress, progress_enabled


def body_metrics(b: np.ndarray) -> dict:
    """Metrics columns of a dynamic body's state (``State.body``): position (m), velocity (m/s),
    the hair's force on it and the rail's (N)."""
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


def observe(run, state) -> dict:
    """What the sinks record of a state: the controller's quantities (``Simulator.observe``),
    the guides' shape, the control effort of the baselines and a dynamic body's state."""
    sim = run.simulator
    motion = sim.motion_of(state)
    obs = sim.observe(state)
    if "guides" not in obs:
        obs["guides"] = run.guides.shape_at(state.time, motion)
    effort = sim.control_effort(state)
    if effort is not None:   # baselines: spring force (attract) or implied force (skinned) / weight
        obs["control_force_rel"] = effort
    if state.body is not None:  # a dynamic block: its state as metrics columns
        obs.update(body_metrics(state.body))
    return obs


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
        r = assemble(cfg)
        if r.cfg is not cfg:   # frames / fps taken from the USD stage
            cfg, plain = r.cfg, to_plain(r.cfg)
        scene, guides, sim = r.scene, r.guides, r.simulator
        guides.save(out / "guides.npz")
        recorder = ResultRecorder(scene)
        if cfg.logging.rerun:
            from hairexp.outputs.rerun_sink import RerunSink  # rerun is imported only here

            rerun_sink = RerunSink(str(out / "recording.rrd"), scene, strict=cfg.logging.strict)
        progress = Progress(cfg.frames * r.steps_per_frame, progress_enabled(cfg.logging.progress), desc=scene_name)
        if rerun_sink:
            rerun_sink.log_static(guides, r.controller)

        def log_frame(frame, state, obs):
            motion = sim.motion_of(state)
            recorder.log_frame(frame, state, motion, obs.get("guides"), obs.get("targets"), obs.get("com"))
            if rerun_sink:
                rerun_sink.log_frame(frame, state, obs, motion)

        state = r.initial_state()
        log_frame(0, state, observe(r, state))
        for step, frame, state, info in r.steps(state):
            obs = observe(r, state)
            extra = {k: v for k, v in obs.items() if np.isscalar(v)}
            row = measure(scene, state, info, sim, step, frame, controller, extra)
            for sink in (table, rerun_sink, progress):
                if sink is not None:
                    sink.on_step(row, state)
            if step % r.steps_per_frame == 0:
                log_frame(frame, state, obs)
        tracker = r.controller if r.controller.cluster_of_vertex() is not None else None
        measures = compute(cfg.measure, RunData(scene, np.asarray(recorder.times), np.asarray(recorder.positions),
                                                tracker, sim.objective.free_vertices,
                                                getattr(recorder, "body_positions", None), table.frame()))
        recorder.write(out / "result.npz", guides.offsets, r.controller.cluster_of_vertex())
        from hairexp.io.usd_write import write_result_usd  # pxr is imported here

        wscene = scene
        if sim.body is not None:  # the block's recorded poses, linear between frames
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
