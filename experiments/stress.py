"""Numerical stress (validation issue, part 2): the solver under extreme inputs, free and tracked.

A small goaling-like scene (the goaling wisp, 12 strands x 12 vertices, 30 frames at 25 fps: the
body accelerates forward and stops suddenly at 0.8 s; 3 guides x 10 vertices, 6 tracking points
each; the goaling wheel is left out and no measure is taken).  Cases (``CASES``): the baseline;
dt = 0.1 s; stretch, bending and both stiffnesses x 1000; guides that teleport between frames,
are stretched 2x or shrunk to 50 % (with the default sliding targets, and with static targets, which
cannot slide along the guide and so must follow the change of length) or jitter with random per-frame noise (tracked only: a free run
ignores its guides); tip variance targets of 0.1 v0 and 20 v0 at a high k_v (tracked only: the
variance penalty is part of the tracking solve); a sphere collider crossing the hair at 10 m/s.

For each case and controller: finite (every recorded state, result.npz ``positions``, and the
summary's figures are finite), stretch max, converged fraction, iterations mean / max, recovered
(substepped) steps, outcome (completed, recovered = completed with substepped steps, failed with
the error's message) and wall time.  Writes reports/stress.{md,json}.
Usage: python -m experiments.stress [--cases NAME ...] [--frames 30] [--cache] [--report NAME]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from experiments.common import add_report_option, check_reports, check_set, compose, fmt, key_value, md_table, positive_int

BASE = ["experiment=goaling", "variants=[]", "scene.n_strands=12", "scene.n_vertices=12", "frames=30",
        "logging.rerun=false", "logging.progress=false", "solver.compile=off", "measure.name=none", "measure.collider="]
NO_WHEEL = ["scene.colliders=[]"]
RIGID = ["guides.source=rigid", "guides.edits=[]"]
# high k_v (100 x the spreading scene's 5 J/m^4), constant in time, on the tip clusters
VARIANCE = ["tracking.variance.stiffness=500.0", "tracking.variance.times=[0.0]",
            "tracking.variance.stiffness_scale=[1.0]", "tracking.variance.points=[5]"]
# a sphere (r = 5 cm) crossing the hanging hair sideways at 10 m/s (z: -2.5 m -> 2.5 m in 0.5 s,
# through the hair at t = 0.25 s, 0.4 m per 0.04 s step)
BALL = ('scene.colliders=[{name: ball, shape: sphere, radius: 0.05, friction: 0.3, motion: {interpolation: linear, '
        'times: [0.0, 0.5], translations: [[0.01, -0.15, -2.5], [0.01, -0.15, 2.5]], '
        'rotations_deg: [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]}}]')

#: name -> (overrides, controllers, guide file kind or None, what it stresses)
CASES: dict[str, tuple[list[str], tuple[str, ...], str | None, str]] = {
    "baseline": (NO_WHEEL, ("free", "tracking"), None, "dt = 0.04 s, goaling material, simulated guides"),
    "dt_0.1": (NO_WHEEL + ["solver.dt=0.1", "fps=10", "frames=12"], ("free", "tracking"), None,
               "dt = 0.1 s (10 fps, 12 frames: the same 1.2 s)"),
    "stretch_x1000": (NO_WHEEL + ["scene.hair.stretch_stiffness=20000.0"], ("free", "tracking"), None,
                      "EA x 1000 (20 kN)"),
    "bending_x1000": (NO_WHEEL + ["scene.hair.bending_stiffness=2.0e-3"], ("free", "tracking"), None,
                      "EI x 1000 (2e-3 N m^2)"),
    "stiff_both_x1000": (NO_WHEEL + ["scene.hair.stretch_stiffness=20000.0", "scene.hair.bending_stiffness=2.0e-3"],
                         ("free", "tracking"), None, "EA and EI x 1000"),
    "guide_teleport": (NO_WHEEL + RIGID, ("tracking",), "teleport",
                       "rigid guides jump 10 cm sideways between frames 10 and 11, back between 20 and 21"),
    "guide_stretch_2x": (NO_WHEEL + ["guides.source=scaled", "guides.edits=[]", "guides.scale_times=[0.0,0.4]",
                                     "guides.scale_factors=[1.0,2.0]"], ("tracking",), None,
                         "guides scaled 1 -> 2x about their roots over 0.4 s"),
    "guide_shrink_50": (NO_WHEEL + ["guides.source=scaled", "guides.edits=[]", "guides.scale_times=[0.0,0.4]",
                                    "guides.scale_factors=[1.0,0.5]"], ("tracking",), None,
                        "guides scaled 1 -> 0.5x about their roots over 0.4 s"),
    "guide_stretch_2x_static": (NO_WHEEL + ["guides.source=scaled", "guides.edits=[]", "guides.scale_times=[0.0,0.4]",
                                            "guides.scale_factors=[1.0,2.0]", "tracking.targets=static"],
                                ("tracking",), None, "as guide_stretch_2x with static targets (t fixed at rest)"),
    "guide_shrink_50_static": (NO_WHEEL + ["guides.source=scaled", "guides.edits=[]", "guides.scale_times=[0.0,0.4]",
                                           "guides.scale_factors=[1.0,0.5]", "tracking.targets=static"],
                               ("tracking",), None, "as guide_shrink_50 with static targets (t fixed at rest)"),
    "guide_jitter": (NO_WHEEL + RIGID, ("tracking",), "jitter",
                     "rigid guides + N(0, 5 mm) noise on every guide vertex, new every frame"),
    "variance_0.1v0": (NO_WHEEL + VARIANCE + ["tracking.variance.target_scale=[0.1]"], ("tracking",), None,
                       "tip variance target 0.1 v0, k_v = 500 J/m^4"),
    "variance_20v0": (NO_WHEEL + VARIANCE + ["tracking.variance.target_scale=[20.0]"], ("tracking",), None,
                      "tip variance target 20 v0, k_v = 500 J/m^4"),
    "collider_10ms": ([BALL], ("free", "tracking"), None,
                      "a 5 cm sphere crossing the hair at 10 m/s (through the hair at t = 0.25 s)"),
}


def compose_cfg(overrides: list[str]):
    """The base config with the case's overrides applied as YAML values (lists of records such
    as ``scene.colliders`` are typed by the schema)."""
    return compose(BASE, overrides, "stress case")


def write_guide_file(cfg, kind: str, path: Path, seed: int = 0) -> Path:
    """An npz guide animation (guides.source=file) from the config's (rigid) guides made
    non-physical: ``teleport`` (a 10 cm jump sideways between two frames and back) or ``jitter``
    (N(0, 5 mm) noise on every vertex, redrawn each frame)."""
    from hairexp.app.assemble import assemble_scene

    _, _, g = assemble_scene(cfg)   # the guides the run of ``cfg`` would track
    P = g.positions.copy()
    F = P.shape[0]
    if kind == "teleport":
        P[F // 3 + 1:2 * F // 3 + 1, :, 2] += 0.10
    elif kind == "jitter":
        P[1:] += np.random.default_rng(seed).normal(scale=0.005, size=P[1:].shape)
    else:
        raise ValueError(kind)
    np.savez_compressed(path, guide_positions=P, guide_offsets=g.offsets, fps=g.fps)
    return path


def finite_summary(s: dict) -> bool:
    keys = ("iterations_mean", "iterations_max", "converged_fraction", "stretch_max")
    vals = [s.get(k) for k in keys] + ([s["residual_rel_max"]] if s.get("residual_rel_max") is not None else [])
    return all(v is not None and math.isfinite(v) for v in vals)


def case_overrides(name: str, controller: str, frames: int | None = None, extra: tuple[str, ...] = ()) -> list[str]:
    """The case's overrides for one controller (``frames``: replaces the case's frames)."""
    overrides = CASES[name][0]
    if frames:
        overrides = [o for o in overrides if not o.startswith("frames=")]
    return overrides + [f"controller.name={controller}"] + ([f"frames={frames}"] if frames else []) + list(extra)


def case_key(name: str, controller: str, frames: int | None = None, extra: tuple[str, ...] = ()) -> dict:
    """What a row depends on: the composed config (before a generated guide file, whose temporary
    path would change the hash; the file itself follows from this config, its kind and seed 0)."""
    from hairexp.app.config import to_plain

    return {"config": to_plain(compose_cfg(case_overrides(name, controller, frames, extra))),
            "guide_file": CASES[name][2]}


def run_case(name: str, controller: str, work: Path, frames: int | None = None, extra: tuple[str, ...] = (),
             use_cache: bool | None = None) -> dict:
    """One case, one controller (``extra``: further overrides): the row of the table (never raises).
    ``use_cache`` None: no cache; False: run and refresh the cache entry; True: reuse an entry whose
    key (config, solver source, versions) matches.  Failures other than a clear error are not stored."""
    if use_cache is None:
        return _run_case(name, controller, work, frames, extra)
    from hairexp.app.report_cache import cached

    try:
        key = case_key(name, controller, frames, extra)
    except Exception:  # noqa: BLE001 - a config that does not compose fails the same way in the run
        return _run_case(name, controller, work, frames, extra)
    row, info = cached("stress", key, lambda: _run_case(name, controller, work, frames, extra), use_cache,
                       store=lambda r: r["outcome"] != "failed" or bool(r.get("clear")))
    row["cache"] = {k: info.get(k) for k in ("hit", "hash", "date", "source_hash")}
    return row


def _run_case(name: str, controller: str, work: Path, frames: int | None = None, extra: tuple[str, ...] = ()) -> dict:
    import pandas as pd

    from hairexp.app.config import to_plain
    from hairexp.errors import HairexpError
    from hairexp.app.run import config_hash, run

    _, _, gfile, _ = CASES[name]
    out = work / f"{name}_{controller}"
    row = {"case": name, "controller": controller, "config_hash": None}
    t0 = time.perf_counter()
    try:
        overrides = case_overrides(name, controller, frames, extra)
        cfg = compose_cfg(overrides)
        row["config_hash"] = config_hash(to_plain(cfg))
        if gfile:
            path = write_guide_file(cfg, gfile, work / f"{name}_guides.npz")
            cfg = compose_cfg(overrides + ["guides.source=file", f"guides.file={path}", "guides.edits=[]"])
        s = run(cfg, out)
        pos = np.load(out / "result.npz")["positions"]
        row.update(outcome="recovered" if s["recovered_steps"] else "completed", error=None,
                   finite=bool(np.isfinite(pos).all() and finite_summary(s)))
    except Exception as exc:  # noqa: BLE001 - the table records every failure
        kind = type(exc).__name__
        row.update(outcome="failed", error=f"{kind}: {exc}", finite=None, clear=isinstance(exc, HairexpError))
        if not isinstance(exc, HairexpError):
            row["traceback"] = traceback.format_exc()
    row["wall_seconds"] = time.perf_counter() - t0
    mp = out / "metrics.parquet"
    if mp.is_file():  # the steps done (also for a failed run)
        df = pd.read_parquet(mp)
        row.update(steps=len(df), converged_fraction=float(df["converged"].mean()),
                   iterations_mean=float(df["iterations"].mean()), iterations_max=int(df["iterations"].max()),
                   recovered_steps=int(df["recovered"].sum()), substeps_max=int(df["substeps"].max()),
                   unconverged_kept=int((~df["converged"]).sum()),
                   stretch_max=float(df["stretch_max"].max()),
                   metrics_finite=bool(np.isfinite(df[["stretch_max", "stretch_mean", "kinetic_energy",
                                                       "potential_energy", "grad_norm"]].to_numpy(float)).all()))
        if row["outcome"] != "failed":
            row["finite"] = bool(row["finite"] and row["metrics_finite"])
    return row


def describe(r: dict) -> str:
    """One sentence on what the solver did."""
    if r["outcome"] == "failed":
        done = f" after {r['steps']} steps" if r.get("steps") else ""
        clear = "a clear error" if r.get("clear") else "an UNEXPECTED exception"
        return f"stopped{done} with {clear}: {r['error']}"
    parts = [f"completed {r['steps']} steps, all states finite" if r["finite"] else
             f"completed {r['steps']} steps WITH NON-FINITE VALUES"]
    if r["recovered_steps"]:
        parts.append(f"{r['recovered_steps']} steps recovered by substepping (up to {r['substeps_max']} substeps)")
    if r["unconverged_kept"]:
        parts.append(f"{r['unconverged_kept']} steps kept unconverged after the deepest substep level")
    if not r["recovered_steps"] and not r["unconverged_kept"]:
        parts.append("every step converged without recovery")
    return "; ".join(parts)


def markdown(rows: list[dict], wall: float, extra=()) -> str:
    from hairexp.app.report import header

    md = header("Numerical stress (validation issue, part 2)")
    if extra:
        md += f"Every case and controller also with: `{' '.join(extra)}`.\n\n"
    md += ("Scene: the goaling wisp, 12 strands x 12 vertices, 30 frames at 25 fps (1.2 s: accelerate, sudden "
           "stop at 0.8 s), simulated guides (3 x 10 vertices, 6 tracking points) unless the case sets them, "
           "no wheel, `solver.on_failure=substep` (max 4 levels), `solver.compile=off`.  Guide and variance cases "
           "are tracked only (a free run ignores the guides and has no variance penalty).  finite: every "
           "recorded state (result.npz positions), the per-step metrics and the summary figures are finite.  "
           "Outcome: completed; recovered = completed with steps retried as substeps; failed = a clear "
           "`SimulationError`/`InputError` with its message.  config hash: `hairexp.app.run.config_hash` of the "
           "composed config (for the guide-file cases, before the generated file's temporary path is set; the file "
           "follows from that config, its kind and seed 0).  source: `fresh` = run by this command; `cached <date> "
           "(entry <hash>)` = reused from reports/cache/stress/ (`--cache`: same config, same solver source, same "
           "versions), and then its wall time is that of the original run on that date.\n\n")
    from hairexp.app.report_cache import describe as cache_source

    md += md_table(["case", "stresses", "controller", "outcome", "finite", "stretch max", "converged", "iter mean",
                    "iter max", "recovered", "unconv. kept", "wall s", "config hash", "source"],
                   [[r["case"], CASES[r["case"]][3], r["controller"], r["outcome"], fmt(r.get("finite")),
                     fmt(r.get("stretch_max")), fmt(r.get("converged_fraction"), ".3f"),
                     fmt(r.get("iterations_mean"), ".1f"), fmt(r.get("iterations_max")), fmt(r.get("recovered_steps")),
                     fmt(r.get("unconverged_kept")), f"{r['wall_seconds']:.1f}", f"`{r.get('config_hash')}`",
                     cache_source(r.get("cache") or {})] for r in rows])
    md += "\nWhat the solver did:\n\n"
    for r in rows:
        md += f"- **{r['case']}, {r['controller']}**: {describe(r)}.\n"
    n_cached = sum(bool((r.get("cache") or {}).get("hit")) for r in rows)
    md += f"\nTotal wall time of this command {wall:.0f} s ({n_cached} of {len(rows)} rows from the cache).\n"
    return md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    ap.add_argument("--frames", type=positive_int, default=None, help="override every case's frames (quick look)")
    ap.add_argument("--no-report", action="store_true")
    ap.add_argument("--set", nargs="*", default=[], type=key_value, metavar="KEY=VALUE",
                    help="overrides applied to every case and controller after the case's own "
                         "(e.g. solver.integrator=bdf2)")
    add_report_option(ap, "stress", default_text="stress; a --set study, e.g. stress_bdf2")
    ap.add_argument("--cache", action="store_true",
                    help="reuse reports/cache/stress/ entries whose config, solver source and versions match "
                         "(default: run every case fresh, refreshing the cache)")
    a = ap.parse_args(argv)
    check_set(ap, a.set)   # before anything runs (a bad key would fail every run)
    if not a.no_report:
        check_reports(ap, a.report)
    import torch

    torch.set_num_threads(1)
    from hairexp.app.report import write_report

    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="stress_") as tmp:
        for name in a.cases:
            for controller in CASES[name][1]:
                r = run_case(name, controller, Path(tmp), a.frames, tuple(a.set), use_cache=a.cache)
                rows.append(r)
                print(f"{name:18s} {controller:8s} {r['outcome']:9s} finite={r.get('finite')} "
                      f"stretch={fmt(r.get('stretch_max'))} conv={fmt(r.get('converged_fraction'))} "
                      f"it={fmt(r.get('iterations_mean'))}/{fmt(r.get('iterations_max'))} "
                      f"rec={r.get('recovered_steps')} {r['wall_seconds']:.1f}s"
                      f"{' (cached)' if r['cache']['hit'] else ''} {r.get('error') or ''}", flush=True)
    wall = time.perf_counter() - t0
    if not a.no_report:
        write_report(a.report, markdown(rows, wall, a.set), {"set": list(a.set), "cases": {k: {"overrides": v[0], "controllers": list(v[1]),
                                                                     "guide_file": v[2], "stresses": v[3]}
                                                                 for k, v in CASES.items()},
                                                       "rows": rows, "wall_seconds": wall})
    bad = [r for r in rows if (r["outcome"] != "failed" and not r["finite"]) or
           (r["outcome"] == "failed" and not r.get("clear"))]
    for r in bad:
        print("SILENT NaN / UNCLEAR FAILURE:", r["case"], r["controller"], r.get("error"), r.get("traceback", ""))
    return 1 if bad else 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
