"""Run one experiment: assemble it (hairexp/app/assemble.py), step it, feed the sinks, write
the run folder.

Files (see README "Run folder"): metrics.parquet, summary.json, recording.rrd, result.npz,
guides.npz, result.usdc (or .usda, ``output.usd_format``) and, for a long run, its value clips
result.clips/ (``output.usd_clips``).

The folder must be empty (``hairexp.outputs.folder.claim``; ``overwrite=true`` replaces a
previous run).  ``summary.json`` says ``running`` from the start.  While the run goes, metrics
and per-frame results are streamed into ``stream/`` (flushed every FLUSH_FRAMES frames or
FLUSH_SECONDS s), so memory does not grow with the number of frames and a crash keeps what was
flushed.  At the end the result files are made from the stream and it is removed.

Endings: ``completed`` (with ``converged``: whether every step converged; under
``on_unconverged=fail`` unconverged steps fail the run; a run in which no step converged always
fails); ``failed`` with the error (metrics.parquet of the steps done, ``stream/`` with the frames
done, no result.npz / result.usd* / result.clips/ / recording.rrd: the recording keeps its
``recording.partial.rrd`` name); ``interrupted`` on SIGINT or SIGTERM (the same partial files).
A failure while writing an ending is logged and noted on the original error, which propagates.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import platform
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hairexp.app.assemble import assemble, check_config
from hairexp.app.config import require_config, to_plain
from hairexp.app.signals import InterruptSignals, note_late, stop_requested
from hairexp.errors import InputError, Interrupted, SimulationError, choice_name
from hairexp.evaluation.measures import RunData, cohesion, compute, key_moment
from hairexp.model.dynamic_body import HAIR_FORCE, POSITION, RAIL_FORCE, VELOCITY
from hairexp.model.rigid import RigidMotion
from hairexp.outputs.files import (ResultRecorder, atomic_write_bytes, json_bytes, save_npy, stream_frames, write_json,
                                   write_npz)
from hairexp.outputs.folder import (REFUSED, RESERVE, STREAM, SUMMARY, claim, free_reserve, owner, refused_summary,
                                    remove_tmp, reserve, used_entries)
from hairexp.memory import release, release_every
from hairexp.outputs.metrics import MetricsTable, measure, read_parts
from hairexp.outputs.progress import Progress, progress_enabled

log = logging.getLogger("hairexp")

FLUSH_FRAMES = 25          # the stream is flushed at least every this many frames,
FLUSH_SECONDS = 2.0        # every this many seconds,
FLUSH_BYTES = 64 << 20     # or when this many bytes of frames are buffered
#: s, a flush also gives the allocators' freed memory back (``hairexp.memory.release``) when the
#: last time was this long ago: the steps' short-lived blocks leave free holes in the C heap
#: whose pages stay resident, and its top crept up with the steps (measured on goaling_smoke,
#: 6 x 10 hair: +0.78 MB of heap between steps 1,000 and 6,000 with the heap's bytes in use flat)
RELEASE_SECONDS = 5.0
#: final result files: present only when the run completed
RESULT_FILES = ("result.npz", "result.usda", "result.usdc", "result.clips", "recording.rrd")


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


#: the most of an error's text a summary.json holds: its ending must fit the disk space held for it
#: (``outputs.folder.RESERVE_BYTES``) when the disk is full
ERROR_CHARS = 4000


def summarize(df, plain: dict, scene_name: str, controller: str, wall: float, status: str,
              error: str | None = None, agg: dict | None = None) -> dict:
    """summary.json of a run; ``df``: its metrics table (None or empty: no step yet), or ``agg``:
    its ``metrics_summary``, computed before."""
    if agg is None:
        agg = metrics_summary(df)
    if error is not None and len(error) > ERROR_CHARS:   # a library's error of pages (USD's: one line a failed write)
        error = f"{error[:ERROR_CHARS]} ... ({len(error) - ERROR_CHARS} more characters)"
    return {
        "scene": scene_name, "controller": controller, "experiment": plain.get("experiment"),
        "status": status, "error": error, **owner(), "success": None, "measures": {},
        **agg, "wall_seconds": wall, "config_hash": config_hash(plain), "versions": versions(), "config": plain,
    }


def metrics_summary(df) -> dict:
    """The summary's aggregates of the metrics table ``df`` (None or empty: none)."""
    n = 0 if df is None else len(df)
    agg = {}
    if n:
        unconverged = int((~df["converged"].astype(bool)).sum())
        agg = {
            "steps": n,
            # the step the run took (the frame interval / steps per frame: solver.dt is its upper
            # bound), and the smallest step / its substeps (a recovery splits a step in halves)
            # (probe of issue 12: the summary held only the configured solver.dt)
            "dt": float(df["dt"].max()),
            "dt_min": float((df["dt"] / df["substeps"].clip(lower=1)).min()),
            "iterations_mean": float(df["iterations"].mean()),
            "iterations_max": int(df["iterations"].max()),
            "converged_fraction": float(df["converged"].mean()),
            "converged": unconverged == 0,
            "unconverged_steps": unconverged,
            "recovered_steps": int(df["recovered"].sum()),
            "step_seconds_median": float(df["step_seconds"].median()),
            "stretch_max": float(df["stretch_max"].max()),
            "residual_rel_max": (float(df["residual_rel_max"].max()) if df["residual_rel_max"].notna().any()
                                 else None),
        }
        if "contact_planes" in df:   # collision.resolve: steps solved again with contact planes, and fallbacks
            agg["contact_plane_steps"] = int((df["contact_planes"] > 0).sum())
            agg["resolve_fallback_steps"] = int((df["resolve_fallbacks"] > 0).sum())
        if "relaxed_clusters" in df:   # tracking's elastic mode: steps and how far targets were relaxed
            agg["relaxed_steps"] = int((df["relaxed_clusters"] > 0).sum())
            agg["relaxed_clusters_max"] = int(df["relaxed_clusters"].max())
            agg["relaxed_slack_rel_max"] = float(df["relaxed_slack_rel_max"].max())
    return agg


#: a run whose largest edge strain exceeds this is told so at its end (the paper scenes stay below 0.01
#: with the contact planes; the post-solve stage alone's strain limiter clamps at its limit, 0.1 there)
STRETCH_WARN = 0.2
#: a run whose largest edge strain exceeds this (an edge 11 times its rest length; hair breaks
#: below 1) is no hair any more: the command line says so and exits 3, the results kept for a look
#: (collision.hair_thickness=1e6 threw the hair 1,182 km, "completed", exit 0; probe of issue 12, round 14)
STRETCH_FAIL = 10.0


def implausible(summary: dict) -> str | None:
    """Why ``summary`` (a run's, or an experiment's with its variants) is no hair any more: the
    largest edge strain of a run beyond STRETCH_FAIL; None otherwise."""
    runs = summary.get("variants") or {None: summary}
    wild = [(name, v["stretch_max"]) for name, v in runs.items()
            if isinstance(v, dict) and (v.get("stretch_max") or 0.0) > STRETCH_FAIL]
    if not wild:
        return None
    said = ", ".join(f"{name + ': ' if name else ''}{100 * s:.3g} %" for name, s in wild)
    return (f"the hair stretched beyond {100 * STRETCH_FAIL:.0f} % ({said}; stretch_max in summary.json): the run "
            "completed but its hair is not hair any more (forces far beyond the hair's: a collider dragging it, guides "
            "off its roots, extreme sizes or stiffness); its files are kept for a look")

#: s, a step shorter than this that never converges is told so (see ``convergence_error``)
TINY_STEP = 1e-6


def convergence_error(df, policy: str) -> str | None:
    """Why a run with these metrics fails for non-convergence, or None."""
    n = len(df)
    if not n:
        return None
    bad = ~df["converged"].astype(bool)
    k = int(bad.sum())
    if not k:
        return None
    # "3 with status max_iterations", not "max_iterations: 3" (read as the setting; probe, round 12)
    statuses = ", ".join(f"{c} with status {s}" for s, c in df["status"][bad].value_counts().items())
    if k == n:
        why = f"no step converged ({n} steps: {statuses})"
        dt = float(df["dt"].min()) if "dt" in df else float("nan")
        if dt < TINY_STEP:   # measured on goaling_smoke: steps of 1e-6 s converge, of 1e-7 s none does
            why += (f"; its steps are {dt:.3g} s long (solver.dt, or a frame of 1/fps when fps is higher than "
                    f"1/solver.dt): steps that short do not converge in double precision (goaling_smoke: "
                    f"{TINY_STEP:g} s does, 1e-7 s does not); set a larger solver.dt or a smaller fps")
        return why
    if policy == "fail":
        return (f"{k} of {n} steps did not converge (first at t={float(df['time'][bad].iloc[0]):.4g} s; "
                f"{statuses}); on_unconverged=fail")
    return None


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


@dataclass
class _Sinks:
    """What a run has opened, for its ending."""
    cfg: object
    plain: dict
    table: MetricsTable
    recorder: ResultRecorder | None = None
    rerun: object = None
    progress: Progress | None = None
    written: list = field(default_factory=list)   # final result files this run wrote
    signals: object = None                         # the run's InterruptSignals

    def flush(self, final: bool = False) -> None:
        self.table.flush()
        if self.recorder is not None:
            self.recorder.flush()
        if self.rerun is not None:
            self.rerun.flush(final=final)
        release_every(RELEASE_SECONDS)


def own_result(sinks, p: Path) -> None:
    """Note ``p`` as a result file this run is about to write (a failure removes it again), or an
    OSError when something is already there: the folder was this run's alone at its start
    (``claim``), so that is another process's, made while the run went on, and it is left as it
    is (a folder made at ``result.usdc`` mid-run was deleted with its contents; probe of issue
    12, round 12)."""
    name_free(p)
    sinks.written.append(p)


def _taken(p: Path) -> bool:
    """Whether something (a file, a folder, a link, even a broken one) is at ``p``."""
    return p.exists() or p.is_symlink()


def name_free(p: Path) -> None:
    """An OSError when something is at ``p``, the name a file of this run is about to take: it is
    another process's, made while the run went on (``own_result``; the run's metrics.parquet
    replaced a user's file of that name, exit 0; independent probe of issue 12, round 32)."""
    if _taken(p):
        kind = "folder" if p.is_dir() and not p.is_symlink() else "file"
        raise OSError(f"{p}: a {kind} of that name appeared in the run folder while the run went on (not this "
                      "run's; left as it is), so the result cannot take its name")


#: the config's input files (a run reads them; ``inputs_inside``)
INPUT_KEYS = ("scene.usd", "guides.file")


def inputs_inside(cfg, folder: Path) -> str | None:
    """Why ``overwrite=true`` may not replace the run in ``folder``: an input file of ``cfg``
    (``scene.usd``, ``guides.file``) lies inside it, such as the previous run's own
    ``guides.npz`` or ``result.usdc``.  The previous run was deleted first and the new one then
    failed with "no such file": both runs lost (probe of issue 12, round 12).  None otherwise."""
    from omegaconf import OmegaConf

    root = Path(os.path.realpath(folder))
    for key in INPUT_KEYS:
        value = OmegaConf.select(cfg, key, default=None)
        if not isinstance(value, str) or not value:
            continue
        p = Path(os.path.realpath(value))
        if p == root or root in p.parents:
            return (f"{key}={value} lies inside the run folder that overwrite=true would empty first; copy it "
                    "elsewhere, or write the new run into another folder")
        if key == "scene.usd":   # a layer or asset the stage pulls in: its sublayer result.usdc (round 27)
            for dep in _stage_files(str(p)):
                q = Path(os.path.realpath(dep))
                if q == root or root in q.parents:
                    return (f"{key}={value} reads {dep} (a sublayer, reference or asset of the stage), which lies "
                            "inside the run folder that overwrite=true would empty first; copy it elsewhere, or "
                            "write the new run into another folder")
    return None


def _stage_files(path: str) -> list[str]:
    """The files the USD stage at ``path`` reads (its layers, and the assets they name), or [] when
    it cannot be read (the run says why)."""
    try:
        from pxr import UsdUtils

        layers, assets, _ = UsdUtils.ComputeAllDependencies(path)
        return [layer.realPath for layer in layers if layer.realPath] + [a for a in assets if a]
    except Exception:  # noqa: BLE001  (a stage that does not open is the run's error to say)
        return []


def run(cfg, out_dir: str | Path, on_checked=None) -> dict:
    """Run ``cfg`` into the folder ``out_dir`` (claimed once the config is checked: ``check_config``;
    then ``on_checked()``, if given, is called) and return its summary."""
    out = run_arguments(cfg, out_dir, "run")
    with warnings_once():
        return _checked_run(cfg, out, on_checked)


def run_checked(cfg, out: Path) -> dict:
    """``run`` of a config that ``check_config`` has just passed: an experiment's variant, checked
    with the others before the first ran (``hairexp.app.experiment``).  Checked again here, it
    built its scene, guides and controller twice (Celia: 0.15 s a tracked variant)."""
    return _checked_run(cfg, out, None, checked=True)


def run_arguments(cfg, out_dir, where: str) -> Path:
    """``out_dir`` as a Path, after a TypeError naming ``where`` for a ``cfg`` that is not a
    composed config or an ``out_dir`` that is not a folder path (``Path(5)`` said "expected str,
    bytes or os.PathLike object, not int"): ``run``'s and ``run_folder``'s arguments."""
    require_config(cfg, where)
    if not isinstance(out_dir, (str, os.PathLike)) or not str(out_dir):
        raise TypeError(f"{where}: out_dir must be a folder path (str or pathlib.Path), got {out_dir!r}")
    return Path(out_dir)


def _checked_run(cfg, out: Path, on_checked, checked: bool = False) -> dict:
    plain = to_plain(cfg)
    if bool(cfg.overwrite) and used_entries(out):
        inside = inputs_inside(cfg, out)
        if inside is not None:
            raise InputError(inside, str(out))
    # the settings before the folder is claimed: a bad value removed the run it was to replace, and
    # a model-layer key (scene.length=0) left a failed summary that a retry had to overwrite
    if not checked:
        check_config(cfg)
    if on_checked is not None:
        on_checked()
    controller = plain["controller"]["name"]
    scene_name = plain["scene"]["name"]
    t_start = time.perf_counter()
    with InterruptSignals() as signals:
        with signals.deferred():   # a signal meanwhile is kept for the try below: "running" is never left behind
            # the claim too: overwrite=true removes the previous run's files there, and a SIGTERM in the
            # middle left no summary beside half of the old files (independent probe of issue 12, round 22)
            claim(out, overwrite=bool(cfg.overwrite))   # InputError (exit 2) for a used folder; nothing written
            try:
                write_json(out / SUMMARY, summarize(None, plain, scene_name, controller, 0.0, "running"))
            except OSError:   # a full disk: not even the first summary; the empty claim goes too (probe of issue 12)
                if (out / SUMMARY).is_file() and (out / SUMMARY).stat().st_size == 0:
                    (out / SUMMARY).unlink()
                raise
            reserve(out)   # room for the ending's summary, should the disk fill meanwhile
            sinks = _Sinks(cfg, plain, MetricsTable(out / STREAM / "metrics"))
            # pxr (every run writes result.usd*) is imported here, where a signal is kept: USD's
            # module loader catches the interrupt raised inside its import, prints a traceback and
            # goes on, so a signal that landed in the import at the end of a run was lost and the
            # run ended "completed", exit 0 (probe of issue 12)
            import hairexp.io.usd_write  # noqa: F401
        sinks.signals = signals
        try:
            if signals.pending is not None:
                raise Interrupted(signals.pending)
            summary = _run(sinks, out, t_start)
        except BaseException as exc:
            with signals.deferred():
                _end_unfinished(exc, sinks, out, scene_name, controller, t_start)
            if signals.pending is not None and not isinstance(exc, KeyboardInterrupt):
                raise Interrupted(signals.pending) from exc
            raise
        # _run deferred the signals from its completed summary on (and its frame is gone: the
        # recording's finaliser ran under the deferral too)
        if signals.pending is not None:
            note_late(signals.pending)
        return summary


def _run(sinks: _Sinks, out: Path, t_start: float) -> dict:
    cfg, table = sinks.cfg, sinks.table
    r = assemble(cfg)
    if r.cfg is not cfg:   # frames / fps taken from the USD stage
        cfg, sinks.cfg, sinks.plain = r.cfg, r.cfg, to_plain(r.cfg)
    plain = sinks.plain
    scene, guides, sim = r.scene, r.guides, r.simulator
    scene_name, controller = plain["scene"]["name"], plain["controller"]["name"]
    atomic_write_bytes(out / "guides.npz", guides.save)
    release()   # between phases: the freed blocks of one do not stack under the next (hairexp/memory.py)
    recorder = sinks.recorder = ResultRecorder(scene, out / STREAM, guides.offsets, r.controller.cluster_of_vertex(),
                                               r.controller.cluster_weights())
    if cfg.logging.rerun:
        from hairexp.outputs.rerun_sink import RerunSink  # rerun is imported only here

        sinks.rerun = RerunSink(str(out / "recording.rrd"), scene, strict=cfg.logging.strict)
    rerun_sink = sinks.rerun
    progress = sinks.progress = Progress(cfg.frames * r.steps_per_frame, progress_enabled(cfg.logging.progress),
                                         desc=scene_name)
    if rerun_sink:
        rerun_sink.log_static(guides, r.controller)

    def log_frame(frame, state, obs):
        motion = sim.motion_of(state)
        recorder.log_frame(frame, state, motion, obs.get("guides"), obs.get("targets"), obs.get("com"))
        if rerun_sink:
            rerun_sink.log_frame(frame, state, obs, motion)

    # a frame and a flush go to the sinks whole (``signals.whole``): a signal inside rerun's send
    # of a chunk (after its rows were taken, before they were sent) dropped 250 frames of an
    # entity from the partial recording (probe of issue 12)
    signals = sinks.signals
    state = r.initial_state()
    with signals.whole():
        log_frame(0, state, observe(r, state))
    last_flush, frames_since = time.monotonic(), 0
    for step, frame, state, info in r.steps(state):
        obs = observe(r, state)
        extra = {k: v for k, v in obs.items() if np.isscalar(v)}
        row = measure(scene, state, info, sim, step, frame, controller, extra)
        for sink in (table, progress):
            if sink is not None:
                sink.on_step(row, state)
        if step % r.steps_per_frame == 0:
            with signals.whole():
                log_frame(frame, state, obs)
            frames_since += 1
            if (frames_since >= FLUSH_FRAMES or time.monotonic() - last_flush >= FLUSH_SECONDS
                    or recorder.pending_bytes() >= FLUSH_BYTES):
                with signals.whole():
                    sinks.flush()
                last_flush, frames_since = time.monotonic(), 0
        stop = stop_requested()   # a sweep stopped while its signal could be lost (hairexp/app/signals.py)
        if stop is not None:      # after the step's row: it is kept with the others
            raise Interrupted(stop)
    with signals.whole():
        sinks.flush(final=True)
    progress.close()
    # metrics.parquet first (a failed run keeps it too), then read back column by column: the
    # end of a run holds one column or one block of frames at a time, whatever its length
    release()
    name_free(out / "metrics.parquet")
    df = table.write(out / "metrics.parquet")
    shutil.rmtree(out / STREAM / "metrics", ignore_errors=True)
    release()
    why = convergence_error(df, choice_name(cfg.on_unconverged))
    if why:
        exc = SimulationError(why)
        exc.every_step_ran = True   # a policy on the steps in metrics.parquet, not a step that failed
        raise exc
    agg = metrics_summary(df)   # here, before the heap is given back: the summary reads no column at the end
    release()
    tracker = r.controller if r.controller.cluster_of_vertex() is not None else None
    times, positions = recorder.array("times"), recorder.frames_of("positions")
    measures = compute(cfg.measure, RunData(scene, times, positions, tracker, sim.objective.free_vertices,
                                            recorder.array("body_positions"), df))
    coh = cohesion(scene.strands.offsets, times, positions, float(cfg.measure.cohesion_threshold),
                   float(cfg.measure.cohesion_fraction))
    for name in ("clumps", "widest_gap"):   # per frame, in result.npz; summary.json keeps the aggregates
        save_npy(out / STREAM / f"cohesion_{name}.npy", coh.pop(name))
    release()
    # the result files; a failure from here on removes those already written (no results beside a failed run)
    own_result(sinks, out / "result.npz")
    write_npz(out / "result.npz", out / STREAM)
    release()
    from hairexp.io.usd_write import clips_dir, write_result_usd  # pxr: imported at the start (``run``)

    wscene = scene
    if sim.body is not None:  # the block's recorded poses, linear between frames
        P = np.array(recorder.array("body_positions"))
        rv = np.repeat(sim.body.rotvecs, len(P), axis=0)
        wscene = replace(scene, motion=RigidMotion(np.array(times), P, rv, "linear"))
    usd = out / f"result.{getattr(cfg.output.usd_format, 'value', cfg.output.usd_format)}"
    for p in (usd, clips_dir(usd)):   # the clips folder (if any) goes with the stage
        own_result(sinks, p)
    write_result_usd(usd, wscene, positions, recorder.frames_of("guide_positions"), guides.offsets, cfg.fps,
                     clips=choice_name(cfg.output.usd_clips),
                     edits_applied=guides.edits_applied)
    recorder.close()
    release()
    view = None
    if rerun_sink is not None:
        own_result(sinks, out / "recording.rrd")
        sinks.rerun = None
        view = rerun_sink.close(success=True, key=key_moment(choice_name(cfg.measure.name),
                                                              measures), metrics=df)
    summary = summarize(None, plain, scene_name, controller, time.perf_counter() - t_start, "completed", agg=agg)
    summary["measures"] = measures
    summary["cohesion"] = coh
    if view is not None:   # the recording's framing and key moment (comparison.rrd unites the variants')
        summary["view"] = view
    # the run is complete once its summary says so: a signal from the write on is kept, not
    # raised, and leaves it completed (raised, it turned a completed run's summary into
    # "interrupted", or was lost inside the recording's finaliser with a printed traceback;
    # probe of issue 12): ``run`` passes it on (a failed write still ends the run as failed)
    sinks.signals.defer = True
    free_reserve(out)
    write_json(out / SUMMARY, summary)
    try:
        shutil.rmtree(out / STREAM)
    except OSError as exc:
        log.warning("%s: could not remove %s: %s", out, STREAM, exc)
    if summary.get("stretch_max", 0.0) > STRETCH_WARN:
        log.warning("%s: the hair stretched by %.1f %% (stretch_max in summary.json; more than %g %%): forces far "
                    "beyond the hair's (guides that leave the hair's roots, a collider dragging it, extreme gravity or "
                    "stiffness); look at the run before using it", out, 100 * summary["stretch_max"], 100 * STRETCH_WARN)
    if summary.get("relaxed_steps"):
        log.warning("%s: in %d of %d steps up to %d clusters were left off their targets, by up to %.2g of the hair "
                    "length (relaxed_steps and relaxed_slack_rel_max in summary.json, relaxed_clusters in "
                    "metrics.parquet): a target the hair could not reach outside the colliders and within the strain "
                    "limit", out, summary["relaxed_steps"], summary["steps"], summary["relaxed_clusters_max"],
                    summary["relaxed_slack_rel_max"])
    if summary.get("resolve_fallback_steps"):
        log.warning("%s: in %d of %d steps the second solve with the contact planes did not converge and the "
                    "collision stage's corrections stood (resolve_fallback_steps in summary.json, resolve_fallbacks in "
                    "metrics.parquet): the edges next to those contacts may be stretched (stretch_max)", out,
                    summary["resolve_fallback_steps"], summary["steps"])
    if not summary["converged"]:
        log.warning("%s: %d of %d steps did not converge; the results are kept and summary.json says converged: "
                    "false (on_unconverged=fail makes this an error)", out, summary["unconverged_steps"],
                    summary["steps"])
    return summary


def end_dead_run(folder: Path, summary: dict, status: str, why: str) -> None:
    """End, as ``status`` with the error ``why``, the run in ``folder`` whose process ended before it
    wrote its ending (``summary``: its ``running`` summary.json, ``outputs.folder.running_run``): a
    sweep's job whose worker was killed (hairexp/app/cli.py), an experiment's variant whose process
    was (hairexp/app/variant_processes.py).  Never raises: the folder is left as it is where it
    cannot be written."""
    try:
        summary.update(status=status, error=why)
        # the steps it had streamed: the summary said none while stream/ held 825 frames (round 18)
        done = read_parts(folder / STREAM / "metrics")
        if done is not None and len(done):
            try:
                summary.update(metrics_summary(done))
            except (KeyError, ValueError, TypeError):   # parts of another layout: the status and error only
                pass
        kept = stream_frames(folder / STREAM)   # as a failed run's ending says them (round 28: null)
        if kept is not None:
            summary["frames_kept"] = kept
        write_json(folder / SUMMARY, summary)
        (folder / RESERVE).unlink(missing_ok=True)
        # a file the run was writing when its process was ended (a 0-byte metrics.parquet.tmp under
        # hydra.launcher.timeout; independent probe of issue 12, round 36): its rows are in
        # stream/metrics/, which the summary names
        for tmp in folder.glob("*.tmp"):
            if tmp.is_file() and not tmp.is_symlink():
                tmp.unlink(missing_ok=True)
    except OSError:
        pass


def write_ending(path: Path, summary: dict) -> None:
    """The ending's summary.json: atomically (a new file, renamed), or, when the disk has no room
    for the new file, over the running summary's own bytes (truncated first, which frees them),
    so that a full disk does not leave the summary saying "running" (probe of issue 12); the same
    when the folder stopped taking new files (made read-only or immutable while the run went on:
    permission denied for the new file, while the summary itself can still be written; round 12)."""
    try:
        write_json(path, summary)
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EACCES, errno.EPERM) or not path.is_file():
            raise
        data = json_bytes(summary)   # before the old bytes are freed: the same JSON as write_json's
        with open(path, "r+b") as f:
            f.truncate(0)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


class _OnceFilter(logging.Filter):
    """Drops a hairexp warning whose text was already said (``warnings_once``)."""

    def __init__(self):
        super().__init__()
        self.said: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING or not record.name.startswith("hairexp"):
            return True
        text = record.getMessage()
        if text in self.said:
            return False
        self.said.add(text)
        return True


_ONCE: list = []   # the filters of the active ``warnings_once``


@contextmanager
def warnings_once():
    """Within: each hairexp warning line is said once.  A run's settings are checked with its
    scene and guides built before it claims its folder, and built again when it runs: their
    warnings (a USD stage's, a guide key's) came twice, and once more for each variant."""
    if _ONCE:   # an experiment's, around its variants' runs
        yield
        return
    added = [(h, _OnceFilter()) for h in logging.getLogger().handlers]   # one each: a handler says a line once
    for h, f in added:
        h.addFilter(f)
    _ONCE.append(added)
    try:
        yield
    finally:
        _ONCE.remove(added)
        for h, f in added:
            h.removeFilter(f)


def write_refused(cfg, out, error: str, status: str = "failed",
                  why: str = "refused by its settings, before the run claimed its folder: no step ran") -> None:
    """A run of the command line that ended before it claimed ``out`` (the folder Hydra made):
    refused by its settings, or a signal or a temporary file's failure while they were checked.
    A ``summary.json`` with ``status`` (``failed``, ``interrupted``), the error and ``refused``
    (``why``), so the folder says how the run ended (``run`` and ``run_experiment`` write nothing
    when they refuse).  Written only into an existing folder where nothing of another run is
    (``used_entries``) and no summary is; the next run into the folder replaces it without
    ``overwrite`` (``claim``).  Never raises: the error line is the refusal's."""
    out = Path(out)
    try:
        summary_path = out / SUMMARY
        if not out.is_dir() or used_entries(out) or (
                _taken(summary_path) and not refused_summary(summary_path)):
            return   # no folder (moved away mid-run, never made), or another run's (an earlier refusal's: replaced)
        try:
            plain = to_plain(cfg)
            if plain.get("variants"):
                summary = {"experiment": plain.get("experiment"), "status": status, "error": error, **owner(),
                           "success": None, "variants": {}, "config_hash": config_hash(plain), "config": plain}
            else:
                summary = summarize(None, plain, plain["scene"]["name"], plain["controller"]["name"], 0.0, status,
                                    error)
        except Exception:  # noqa: BLE001  (a config that cannot be resolved: what is known)
            summary = {"status": status, "error": error}
        summary[REFUSED] = why
        write_json(out / SUMMARY, summary)
    except Exception as exc:  # noqa: BLE001
        to_log_files(f"{out}: cannot write the refused run's summary: {type(exc).__name__}: {exc}")


def to_log_files(message: str) -> None:
    """``message`` as an error line in the run's log files only (``__main__.log``: Hydra's file
    handlers), not on the console, where the error's own line is printed: a failed or interrupted
    run's log ended without a word of how (probe of issue 12, round 15)."""
    record = logging.LogRecord("hairexp", logging.ERROR, __file__, 0, "%s", (message,), None)
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler):
            try:
                h.handle(record)
            except Exception:  # noqa: BLE001  (a log file that cannot be written: the summary says it)
                pass


def _stored_rows(parts) -> str:
    """The rows the parquet ``parts`` hold, from their footers ("?" when one cannot be read)."""
    try:
        import pyarrow.parquet as pq

        return str(sum(pq.read_metadata(p).num_rows for p in parts))
    except Exception:  # noqa: BLE001  (a part cut short by the full disk)
        return "?"


def _end_unfinished(exc: BaseException, sinks: _Sinks, out: Path, scene_name: str, controller: str,
                    t_start: float) -> None:
    """Write the ending of a run that did not complete; every step is tried, and a failure in
    one is logged and noted on ``exc`` (which the caller re-raises) instead of replacing it."""
    interrupted = isinstance(exc, KeyboardInterrupt)
    status = "interrupted" if interrupted else "failed"
    error = (str(exc) if isinstance(exc, Interrupted) else "interrupted by SIGINT") if interrupted else str(exc)

    failed: dict[str, dict[str, str]] = {}   # an error -> the parts of the ending it stopped -> how each is said

    def attempt(what: str, fn):
        try:
            return fn()
        except BaseException as e2:   # noqa: BLE001  (the ending must go on)
            # an OSError is the same error whatever file it names (a full disk: positions.npy, then
            # a metrics part, each named since files.naming): said once, each part with its own file
            # (the first file stood for every part: "metrics.parquet ... '.../positions.npy'"; round 28)
            named = isinstance(e2, OSError) and e2.errno
            key = f"{type(e2).__name__}: [Errno {e2.errno}] {e2.strerror}" if named else f"{type(e2).__name__}: {e2}"
            parts = failed.setdefault(key, {})
            if what in parts:   # the frames' flush and close failed alike: said twice
                return None
            old = f"while writing the {status} ending ({', '.join(parts.values())}): {key}"
            file = getattr(e2, "filename", None) if named else None
            if isinstance(file, str) and os.path.isabs(file) and Path(file).is_relative_to(out):
                file = Path(file).relative_to(out).as_posix()   # a file of the run folder, as the folder names it
            parts[what] = f"{what} ({file})" if isinstance(file, str) and file and file != what else what
            note = f"while writing the {status} ending ({', '.join(parts.values())}): {key}"
            # one note per error, naming every part it stopped (a full disk gave four alike "also:" lines);
            # the console gets the notes under the error's own line ("also:"), the log files here
            notes = getattr(exc, "__notes__", None)
            if notes is not None and old in notes:
                notes[notes.index(old)] = note
            else:
                exc.add_note(note)
            to_log_files(f"{out}: while writing the {status} ending ({what}): {key}")
            return None

    if sinks.progress is not None:
        attempt("progress", sinks.progress.close)
    kept = None
    if sinks.recorder is not None:
        attempt("frames", sinks.recorder.flush)
        kept = attempt("frames", sinks.recorder.align)   # every array the same frames, whatever was written
        attempt("frames", sinks.recorder.close)
    df = None   # (``write`` flushes the rows since the last part first, or writes them with the parts)
    metrics_where = None
    if sinks.table.steps:
        mp = out / "metrics.parquet"
        mine = sinks.table.written is not None and sinks.table.written.path == mp
        # a file of that name that is not this run's is left as it is (name_free): the rows stay in stream/
        df = None if not mine and _taken(mp) else attempt("metrics.parquet", lambda: sinks.table.write(mp))
        if df is not None:
            attempt("metrics", lambda: shutil.rmtree(out / STREAM / "metrics", ignore_errors=True))   # in the parquet now
        else:   # the parquet could not be written: the summary from the parts kept in stream/
            df = attempt("metrics", sinks.table.frame)
            parts = sorted((out / STREAM / "metrics").glob("part-*.parquet"))
            if parts:   # where the rows are, said (round 28: neither the summary nor the console did)
                metrics_where = "stream/metrics/"
                exc.add_note(f"metrics.parquet could not be written: {_stored_rows(parts)} of the {sinks.table.steps} "
                             f"steps' metrics rows are in {metrics_where} (pandas.read_parquet reads the folder as "
                             "one table)")
    if sinks.rerun is not None:
        attempt("recording", lambda: sinks.rerun.close(success=False, metrics=df))
    for p in sinks.written:   # files, and result.clips/ (a folder)
        if p.suffix == ".rrd" and p.is_file():
            # a recording already finished keeps the name of an unfinished run's, as the README says
            # (it was removed: a signal late in the run left no recording at all; probe of issue 12)
            attempt(p.name, lambda p=p: os.replace(p, p.with_name(f"{p.stem}.partial{p.suffix}")))
            continue
        attempt(p.name, lambda p=p: shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True))
    summary = summarize(df, sinks.plain, scene_name, controller, time.perf_counter() - t_start, status, error)
    if isinstance(exc, SimulationError) and "converged" in summary and getattr(exc, "every_step_ran", False):
        summary["converged"] = False   # on_unconverged=fail: the metrics hold every step, the aggregates are theirs
    elif isinstance(exc, SimulationError) and "converged" in summary:
        # the step that failed is not in the metrics (the steps before it are): counted here, so that
        # the aggregates agree with "converged: false" (they said converged_fraction 1.0 and 0
        # unconverged steps; probe of issue 12, round 10)
        n = int(summary.get("steps", 0))
        summary["converged"] = False
        summary["unconverged_steps"] = int(summary.get("unconverged_steps", 0)) + 1
        summary["converged_fraction"] = float(summary.get("converged_fraction", 1.0)) * n / (n + 1)
        summary["failed_step"] = n + 1   # 1-based: the step after the last one in metrics.parquet
    if metrics_where is not None:
        summary["metrics_file"] = metrics_where   # the rows of metrics.parquet, which could not be written
    if kept is not None:
        summary["frames_kept"] = int(kept)   # stream/ holds frames 0..frames_kept-1 of every array
        lost = sinks.recorder.frames - int(kept)
        if lost > 0:   # computed, not written (a full disk): said, as the steps in metrics are more
            summary["frames_lost"] = lost
            held = f"frames 0..{kept - 1} of every array" if kept else "no frame"
            exc.add_note(f"stream/ holds {held}; the last {lost} frame(s) computed could not be written")
    attempt(RESERVE, lambda: free_reserve(out, quiet=False))   # its room is the summary's
    attempt("summary.json", lambda: write_ending(out / SUMMARY, summary))
    stream = out / STREAM
    if stream.is_dir() and not any(p.is_file() for p in stream.rglob("*")):
        attempt(STREAM, lambda: shutil.rmtree(stream))
    attempt("temporary files", lambda: remove_tmp(out))
