"""Baselines a user would pick instead of tracking (validation issue, part 4), on the paper's scenes.

For every scene (goaling, splitting, spreading, stylization, celia; paper section 4) we run

* ``free``: the free simulation;
* ``skinned``: the detail hair skinned to the guides (guide-deform, hairexp/control/skinning.py);
* ``attract k``: the free simulation plus a spring 1/2 k m_i |x_i - x_g,i(t)|^2 to the skinned
  position on every free vertex, k = 10, 100, 1000 1/s^2 (nHair "start curve attract",
  Vellum "pin to target");
* ``tracking``: hairexp's tracking solver (COM constraints, sliding targets, section 3), with
  the paper's hard hair-to-guide assignment;
* ``tracking soft``: the same with ``tracking.assignment=soft`` (strands shared among nearby
  guides, README "Soft assignment"; its own blend width, ``tracking.blend_width``).

All controllers of a scene see the same guides: the overrides of one representative tracked
variant of the scene's YAML (``REPRESENTATIVE``) are applied to every controller.  Every run is
measured with the same clusters and targets (a TrackingController of the tracked configuration
with hard assignment, built for measurement only; for ``tracking soft`` these are not the
clusters it tracks, so its tracking error here is that of the hard clusters' centres) and with the scene's own success measure
(hairexp/evaluation/measures.py) computed the same way for every controller, judged per run by the
per-run rule of the scene's judge (``hairexp.evaluation.judges.RUN_RULES``).  A run that fails (or a controller
that cannot drive a scene, e.g. skinning on a dynamic body) is recorded with its error.
Writes reports/baselines.{md,json}.
Usage: python -m experiments.baselines [--experiments goaling splitting ...] [--frames N] [--report NAME]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
import pandas as pd

from hairexp.app.assemble import assemble
from hairexp.app.experiment import _variant_facts, apply_overrides
from hairexp.app.report import header, write_report
from hairexp.app.run import run
from hairexp.control.skinning import GuideSkinning
from hairexp.errors import InputError
from hairexp.evaluation.judges import RUN_RULES
from hairexp.evaluation.measures import RunData, compute
from hairexp.model.dynamic_body import POSITION

from experiments.common import add_report_option, check_reports, compose, fail, md_row, md_table, positive_int, writable_dir

EXPERIMENTS = ("goaling", "splitting", "spreading", "stylization", "celia")
STIFFNESSES = (10.0, 100.0, 1000.0)
WINDOW = 5   # frames, the moving average removed from the tip trajectories
#: m^2: a free run's tip HF energy below this (1 um RMS) is a still hair; ratios to it are not
#: shown (the table gives the absolute energy instead)
HF_FLOOR = 1e-12
#: The tracked variant whose overrides (guides, edits, variance targets) every controller of a
#: scene gets; scenes not listed use their last variant with controller.name=tracking.
REPRESENTATIVE = {"splitting": "tracked_3", "spreading": "target_5v0"}


def representative_variant(cfg) -> tuple[str, list[str]]:
    """(name, overrides without controller.name) of the scene's representative tracked variant."""
    tracked = [v for v in cfg.variants if "controller.name=tracking" in list(v.overrides)]
    if not tracked:
        raise InputError("the experiment has no variant with controller.name=tracking", "variants")
    want = REPRESENTATIVE.get(str(cfg.experiment))
    pick = next((v for v in tracked if str(v.name) == want), tracked[-1])
    return str(pick.name), [o for o in pick.overrides if not str(o).startswith("controller.name=")]


def controllers() -> list[tuple[str, list[str]]]:
    out = [("free", ["controller.name=free"]), ("skinned", ["controller.name=skinned"])]
    out += [(f"attract k={k:g}", ["controller.name=attract", f"controller.attract_stiffness={k}"]) for k in STIFFNESSES]
    out.append(("tracking", ["controller.name=tracking", "tracking.assignment=hard"]))
    out.append(("tracking soft", ["controller.name=tracking", "tracking.assignment=soft"]))
    return out


def controller_cfg(base, variant_overrides: list[str], ctrl_overrides: list[str], where: str):
    cfg = apply_overrides(base, [*variant_overrides, *ctrl_overrides], where)
    cfg.variants = []
    return cfg


def measurement_tracker(cfg):
    """The tracked configuration's scene, clusters and target curves (built for measurement only)."""
    run = assemble(apply_overrides(cfg, ["controller.name=tracking"], "measurement"))   # as hairexp.app.run does
    return run.scene, run.controller


def _name(x) -> str:
    """A config enum's name (judge, measure)."""
    return str(getattr(x, "value", x))


def body_motion(scene, t: float, body_position):
    """The body's poses at time t as the run recorded them: on a dynamic body (stylization) the
    block where the run put it at t (``DynamicBody.at``), so that the guides, the targets and the
    skinned hair ride with it as in that run; otherwise the scene's keyframed motion."""
    if scene.body is None or body_position is None:
        return scene.motion
    b = scene.body.initial(np.zeros(3))
    b[POSITION] = body_position
    return scene.body.at(t, b)


# -- success: the per-run rule of each scene's judge (hairexp/evaluation/judges.py RUN_RULES) ------
def success(m: dict, cfg) -> tuple[bool, str]:
    """The scene's judge's per-run rule on one run's measures ``m`` (``cfg``: the run's config,
    whose variant facts and ``judge_tolerance`` the rule reads as the judge does)."""
    return RUN_RULES[_name(cfg.judge)](m, _variant_facts(cfg), float(cfg.judge_tolerance))


STATEMENTS = {  # judge -> its per-run rule as the report states it
    "free_misses_tracked_hits": "the hair touches the collider: measure `collider_contact` `hit` (some free vertex "
                                "within the collider's thickness + `measure.tolerance` in some frame, or a "
                                "collision-stage contact; the judge's rule for a tracked run)",
    "clumps_match_guides": "the number of clumps (measure `clumps`) equals the number of guides (`guides.count`; the "
                           "judge's rule for a tracked run)",
    "variance_follows_targets": "the tip cluster's variance ratio V/V_rest at the apex (measure `tip_variance` "
                                "`cluster_variance_ratio`, the last tracking point's cluster of the tracked "
                                "configuration, eq. 4) within `judge_tolerance` (relative) of the target ratio (the "
                                "judge's per-target rule; its monotonicity over targets needs several targets and is "
                                "not applicable to one run)",
    "tracked_leaves_rail": "the block leaves the rail (measure `block_rail` `left_rail`; the judge's rule for a "
                           "tracked run)",
    "hard_clumps_soft_fans": "with soft assignment no gap between neighbouring strands across the spread wider "
                             "than 2x the mean spacing in any frame and a residual <= 1e-6 L; otherwise >= 2 clumps "
                             "(measure `fan`; the judge's rule for a tracked run)",
}


# -- physical detail -------------------------------------------------------------------------
def tip_high_frequency(positions: np.ndarray, offsets: np.ndarray, window: int = WINDOW) -> float:
    """Mean over strands, frames and coordinates of the squared tip position minus its centred
    moving average over ``window`` frames (m^2)."""
    tips = positions[:, offsets[1:] - 1]                       # (F, S, 3)
    h = window // 2
    kernel = np.ones(window) / window
    smooth = np.apply_along_axis(lambda a: np.convolve(a, kernel, mode="valid"), 0, tips)
    r = tips[h:len(tips) - h] - smooth
    return float(np.mean(np.sum(r ** 2, axis=-1)))


def intra_cluster(dev: np.ndarray, offsets: np.ndarray, cluster_of_vertex: np.ndarray) -> np.ndarray:
    """``dev`` (F, V, 3) with, at the strand tips, the mean over the tips of the same cluster
    removed (the part of the tips' motion that the cluster-centre constraints leave free)."""
    out = dev.copy()
    tips = offsets[1:] - 1
    ck = cluster_of_vertex[tips]
    for k in np.unique(ck):
        sel = tips[ck == k]
        out[:, sel] -= dev[:, sel].mean(axis=1, keepdims=True)
    return out


def collider_clearance(scene, X_free: np.ndarray, times: np.ndarray) -> dict:
    """Per collider: the smallest signed distance (m) from a free vertex to its surface over all
    frames (< 0: inside; the skinned hair has no collision stage)."""
    out = {}
    for col in scene.colliders:
        out[col.name] = float(min((col.sdf_body(col.to_body(x, float(t)))).min() for x, t in zip(X_free, times)))
    return out


def analyse(cfg, scene, tracker, out: Path) -> dict:
    """Every column of the table for the run in ``out``, measured with ``tracker``'s clusters and
    targets and the scene's own measure ``cfg.measure``."""
    d = np.load(out / "result.npz")
    X, times = d["positions"], d["times"]
    body = d["body_positions"] if "body_positions" in d.files else None
    summary = json.loads((out / "summary.json").read_text())
    df = pd.read_parquet(out / "metrics.parquet")
    free = np.flatnonzero(~scene.strands.kinematic)
    cons, L = tracker.cons, tracker.hair_length
    sk = GuideSkinning(scene, tracker.guides)
    err, var, skinned = [], [], []
    for i, (x, t) in enumerate(zip(X, times)):
        motion = body_motion(scene, float(t), None if body is None else body[i])
        skinned.append(sk.positions(float(t), motion))
        xf = x[free].reshape(-1)
        c = cons.com(xf) - cons.target_points(cons.targets(float(t), motion), cons.t_rest)   # static (rest arc length) targets
        if i == 0:
            # every run starts where the measurement tracker was registered (e.g. after the same
            # scene.settle): a cluster centre off its target at t = 0 means a mismatched measurement
            e0 = float(np.max(np.linalg.norm(c, axis=1)) / L)
            if e0 > 1e-6:
                raise RuntimeError(f"{out}: cluster centres start {e0:.3g} L off their targets: the run's initial "
                                   "state is not the measurement tracker's registration state")
            continue
        err.append(np.linalg.norm(c, axis=1))
        var.append(tracker.variance.values(xf) / tracker.variance.rest)
    skinned = np.stack(skinned)
    depth = collider_clearance(scene, X[:, free], times)
    err, var = np.array(err), np.array(var)
    if "constraint_force_rel" in df and df["constraint_force_rel"].notna().any():
        eff = df["constraint_force_rel"]
    elif "control_force_rel" in df:
        eff = df["control_force_rel"]
    else:
        eff = pd.Series([0.0])
    # the scene's own measure, for every controller with the tracked configuration's tracker
    m = compute(cfg.measure, RunData(scene, times, X, tracker, free, body, df))
    own = summary["measures"]
    same_clusters = summary.get("config", {}).get("tracking", {}).get("assignment", "hard") == "hard"
    if summary["controller"] == "tracking" and same_clusters:    # same measure as the run's own (sanity)
        for k, v in own.items():
            if isinstance(v, float) and not np.isclose(v, m[k], rtol=1e-9, atol=1e-12):
                raise RuntimeError(f"re-measured {k} = {m[k]} differs from the run's own {v}")
    ok, detail = success(m, cfg)
    return {"status": "completed",
            "tracking_error_rms": float(np.sqrt(np.mean(err ** 2)) / L), "tracking_error_max": float(err.max() / L),
            "stretch_max": summary["stretch_max"], "effort_mean": float(eff.mean()),
            "effort_median": float(eff.median()), "effort_max": float(eff.max()),
            "tip_hf": tip_high_frequency(X, scene.strands.offsets),
            "tip_dev_hf": tip_high_frequency(X - skinned, scene.strands.offsets),
            "tip_intra_hf": tip_high_frequency(intra_cluster(X - skinned, scene.strands.offsets,
                                                             tracker.corr.cluster_of_vertex), scene.strands.offsets),
            "variance_std": float(np.mean(np.std(var, axis=0))),
            "collider_clearance": depth,
            "success": bool(ok), "success_detail": detail, "measures": m,
            "step_seconds_median": summary["step_seconds_median"], "iterations_mean": summary["iterations_mean"],
            "converged_fraction": summary["converged_fraction"], "wall_seconds": summary["wall_seconds"],
            "own_residual_rel_max": summary.get("residual_rel_max")}


def run_scene(experiment: str, frames: int | None, root: Path, only: list[str] | None = None) -> dict:
    """All controllers (or those named in ``only``; "free" always runs, the ratios need it) on one
    scene; a failing run is recorded (status, error) and the rest go on."""
    extra = [] if frames is None else [f"frames={frames}"]
    base = compose([f"experiment={experiment}", "logging=off", *extra])   # variants not yet applied
    vname, vover = representative_variant(base)
    tcfg = controller_cfg(base, vover, ["controller.name=tracking", "tracking.assignment=hard"], f"{experiment} tracked")
    scene, tracker = measurement_tracker(tcfg)
    res = {}
    for name, ov in controllers():
        if only is not None and name not in only and name != "free":
            continue
        t0 = time.perf_counter()
        out = root / experiment / name.replace(" ", "_").replace("=", "")
        try:
            cfg = controller_cfg(base, vover, ov, f"{experiment} {name}")
            run(cfg, out)
            r = analyse(cfg, scene, tracker, out)
        except InputError as exc:
            if str(exc.where or "").startswith("controller."):   # it cannot drive this scene (skinning a dynamic body)
                r = {"status": "not applicable", "error": str(exc)}
            else:                      # any other bad input (a run folder that cannot be made, ...) fails the run
                r = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
                print(f"[{experiment}] {name}: {exc}", file=sys.stderr, flush=True)
        except Exception as exc:       # a failed run: recorded, the others go on
            r = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
            traceback.print_exc()
        res[name] = r
        w = time.perf_counter() - t0
        if r["status"] == "completed":
            print(f"[{experiment}] {name:>16}: err {r['tracking_error_rms']:.3e}  stretch {r['stretch_max']:.2e}  "
                  f"effort {r['effort_mean']:.3g}  tipHF {r['tip_hf']:.3e}  devHF {r['tip_dev_hf']:.3e}  "
                  f"intraHF {r['tip_intra_hf']:.3e}  varstd {r['variance_std']:.3f}  success {r['success']} "
                  f"({r['success_detail']})  {1e3 * r['step_seconds_median']:.1f} ms/step  wall {w:.1f} s", flush=True)
        else:
            print(f"[{experiment}] {name:>16}: {r['status']}: {r['error']}  wall {w:.1f} s", flush=True)
    f = res["free"]
    for r in res.values():
        if r["status"] != "completed":
            continue
        for key in ("tip_hf", "tip_dev_hf", "tip_intra_hf"):
            ok = f.get("status") == "completed" and f[key] > HF_FLOOR
            r[f"{key}_rel"] = r[key] / f[key] if ok else float("nan")
    judge = _name(base.judge)
    return {"experiment": experiment, "variant": vname, "variant_overrides": vover,
            "n_strands": int(tcfg.scene.n_strands), "n_vertices": int(tcfg.scene.n_vertices),
            "frames": int(tcfg.frames), "fps": float(tcfg.fps), "dt": float(tcfg.solver.dt),
            "guides": int(tcfg.guides.count), "clusters": int(tracker.cons.K), "judge": judge,
            "judge_tolerance": float(base.judge_tolerance), "measure": _name(base.measure.name),
            "criterion": STATEMENTS[judge], "results": res}


# -- report ----------------------------------------------------------------------------------
COLUMNS = ("controller", "tracking error RMS / L (max)", "max stretch", "control effort / weight: mean, median (max)",
           "tip HF energy / free", "tip HF of deviation from skinned / free", "same, within clusters / free",
           "cluster variance dynamics", "scene success (measure)", "median s/step")


def _hf(r: dict, key: str) -> str:
    """The ratio to the free run, or the absolute energy when the free run's is below HF_FLOOR."""
    rel = r[f"{key}_rel"]
    return f"{rel:.3f}" if np.isfinite(rel) else f"{r[key]:.2e} m^2 (free still)"


def table(res: dict) -> str:
    md = md_table(COLUMNS)
    for name, r in res.items():
        if r["status"] != "completed":
            md += md_row([name, f"**{r['status']}**: {r['error']}"] + [""] * (len(COLUMNS) - 2))
            continue
        eff = "0 (none)" if name == "free" else f"{r['effort_mean']:.3g}, {r['effort_median']:.3g} ({r['effort_max']:.3g})"
        hf = [_hf(r, k) for k in ("tip_hf", "tip_dev_hf", "tip_intra_hf")]
        md += md_row([name, f"{r['tracking_error_rms']:.3f} ({r['tracking_error_max']:.3f})", f"{r['stretch_max']:.2e}",
                      eff, *hf, f"{r['variance_std']:.2e}",
                      f"{'**yes**' if r['success'] else 'no'} ({r['success_detail']})", f"{r['step_seconds_median']:.4f}"])
    return md


def scene_section(s: dict) -> str:
    md = (f"## {s['experiment']}\n\n"
          f"{s['n_strands']} strands x {s['n_vertices']} vertices, {s['frames']} frames at {s['fps']:g} fps, "
          f"dt = {s['dt']} s; {s['guides']} guides, {s['clusters']} clusters.  Every controller runs with the "
          f"overrides of the tracked variant `{s['variant']}`: "
          + (", ".join(f"`{o}`" for o in s["variant_overrides"]) or "none (the scene's own guides)") + ".  \n"
          f"Success (judge `{s['judge']}`, per run): {s['criterion']}"
          + (f"; tolerance {s['judge_tolerance']:g}" if s["judge"] == "variance_follows_targets" else "") + ".\n\n")
    return md + table(s["results"]) + "\n" + observations(s) + "\n"


def observations(s: dict) -> str:
    """Generic statements, every number from the results."""
    res = s["results"]
    done = {n: r for n, r in res.items() if r["status"] == "completed"}
    out = []
    bad = [f"{n} ({r['status']})" for n, r in res.items() if r["status"] != "completed"]
    if bad:
        out.append(f"Not in the comparison: {', '.join(bad)}; see the table for the reason.")
    wins = [n for n, r in done.items() if r["success"]]
    out.append(f"Scene success: {', '.join(wins) if wins else 'none'} "
               f"({len(wins)} of {len(res)} controllers).")
    sim = {n: r for n, r in done.items() if n != "skinned"}
    if sim:
        best = min(sim, key=lambda n: sim[n]["tracking_error_rms"])
        out.append(f"Smallest cluster-centre error among the simulated controllers: {best} "
                   f"({sim[best]['tracking_error_rms']:.3f} L)"
                   + (f"; skinned {done['skinned']['tracking_error_rms']:.3f} L" if "skinned" in done else "") + ".")
    tr = done.get("tracking")
    if tr is not None:
        beat = [n for n, r in sim.items() if n != "tracking" and r["tracking_error_rms"] < tr["tracking_error_rms"]]
        if beat:
            out.append(f"**Tracking loses on cluster-centre error** to {', '.join(beat)} here "
                       f"(tracking {tr['tracking_error_rms']:.3f} L).")
        beat_s = [n for n, r in done.items() if r["success"] and not tr["success"]]
        if beat_s:
            out.append(f"**Tracking fails the scene's criterion while {', '.join(beat_s)} meet(s) it.**")
        if "free" in done:
            f = done["free"]
            out.append(f"Tracking: max stretch {tr['stretch_max']:.2e} (free {f['stretch_max']:.2e}), "
                       f"control effort median {tr['effort_median']:.3g} x weight (peak {tr['effort_max']:.3g}), "
                       f"within-cluster tip HF {_hf(tr, 'tip_intra_hf')} (x free), its own (sliding-target) residual max "
                       f"{tr['own_residual_rel_max']:.1e} L, step time "
                       f"{tr['step_seconds_median'] / f['step_seconds_median']:.1f} x the free step.")
        att = {n: r for n, r in done.items() if n.startswith("attract")}
        if att:
            out.append("Attraction: " + "; ".join(
                f"k = {n.split('=')[1]}: error {r['tracking_error_rms']:.3f} L, effort median {r['effort_median']:.3g}, "
                f"deviation HF {_hf(r, 'tip_dev_hf')} (x free), {'success' if r['success'] else 'no success'}"
                for n, r in att.items()) + ".")
    sk = done.get("skinned")
    if sk is not None:
        out.append(f"Skinned: max stretch {sk['stretch_max']:.2e}, implied force median {sk['effort_median']:.3g} x weight.")
    inside = [f"{n} ({c}: {d:+.4f} m)" for n, r in done.items() for c, d in r["collider_clearance"].items() if d < 0]
    if inside:
        out.append("Hair inside a collider at some frame (smallest signed distance of a free vertex to its surface): "
                   + ", ".join(inside) + ".")
    return "".join(f"* {o}\n" for o in out)


def summary_table(scenes: list[dict]) -> str:
    names = [n for n, _ in controllers()]
    rows = []
    for s in scenes:
        cells = []
        for n in names:
            r = s["results"][n]
            cells.append(("**yes**" if r["success"] else "no") + f", {r['tracking_error_rms']:.3f} L"
                         if r["status"] == "completed" else r["status"])
        rows.append([s["experiment"], *cells])
    return md_table(["scene", *names], rows)


def report(scenes: list[dict], wall: float) -> str:
    md = header("Baselines: what a user would pick instead of tracking")
    md += ("Controllers (issue 6, part 4): `free`; `skinned` (detail hair skinned to the guides, no simulation); "
           f"`attract k` (free simulation plus springs to the skinned positions, k = "
           f"{', '.join(f'{k:g}' for k in STIFFNESSES)} 1/s^2); `tracking` (hairexp, paper section 3, hard "
           "hair-to-guide assignment); `tracking soft` (the same, `tracking.assignment=soft`: measured against the "
           "hard clusters' centres like every other controller, not its own weighted ones).  One run per "
           "controller and scene, logging off; all controllers of a scene see the same guides (one representative "
           "tracked variant's overrides, named per scene) and are measured against the tracked configuration's "
           "clusters and targets and with the scene's own success measure (paper section 4; "
           f"hairexp/evaluation/measures.py).  Total wall time {wall:.0f} s (2 shared cores).\n\n")
    md += "Scene success and cluster-centre error (RMS / L) at a glance:\n\n" + summary_table(scenes) + "\n"
    md += "".join(scene_section(s) for s in scenes)
    md += DEFINITIONS
    return md


DEFINITIONS = """
## Definitions

* **Representative variant**: splitting and spreading track in several variants (guide counts;
  variance targets).  The baselines use `tracked_3` (three guides, the outer two edited sideways:
  the hardest clump count) and `target_5v0` (tip variance target 5 v0, the middle of the paper's
  range); goaling, stylization and celia have one tracked variant.  The variant's overrides
  (minus `controller.name`) are applied to every controller.  The variance target is a tracking
  knob: the other controllers have no way to ask for it.
* **Tracking error**: for every controller the same clusters (the tracked run's correspondence:
  guide of each strand, tracking points, segments) and the same target curves (the registered
  offset of each cluster centre in the guide's parallel-transported frames) are used.  Per frame
  (1..F) and cluster k, e_k = |COM_k(x) - c_hat_k(t_k,rest)|, the target taken at its *rest* arc
  length (static); column = sqrt(mean over frames and clusters of e_k^2) / mean hair length (max in
  brackets).  The tracked run itself uses sliding targets, so its own residual (at the optimised
  t_k) is at round-off except at contacts; the static-target figure also contains the slide along the curve.
  On the dynamic block (stylization) the targets, guides and skinned positions are evaluated with the block
  where each run put it (the runs differ: the hair moves the block).
* **Max stretch**: the largest |l / l0 - 1| over all edges and steps (summary `stretch_max`).
* **Control effort**: |F_c| / |m g|, the Euclidean norm of the stacked per-vertex control forces
  over the norm of the stacked weights of the free vertices; mean and median over steps (max in brackets).
  attract: the spring forces -k m_i (x_i - x_g,i) at the end of each step; tracking: the constraint
  forces A^T lambda (metrics `constraint_force_rel`; the variance penalty's force in spreading is
  not included); skinned: no force is applied, so we report the
  *implied* force F_c = -grad H(x_g) of the implicit Euler objective (eq. 5) at the skinned
  positions, i.e. the force that, added to gravity and the hair's own elastic forces, would make a
  physical step land on the skinned trajectory (it includes the elastic force of any stretch the
  skinning causes); free: none.
* **Tip HF energy / free** (physical detail): the strand tip trajectories (per frame, F frames) minus
  their centred moving average over 5 frames (0.2 s); the mean squared remainder over strands and
  frames, divided by the same number for the free run.  1 = as much high-frequency secondary motion
  as the free run; 0 = none.  Where the free run's energy is below 1e-12 m^2 (1 um RMS: the
  free hair is still, stylization's block resting on the rail for the plain tip HF), the ratio is
  meaningless and the absolute energy (m^2) is shown instead, marked "free still".
* **Tip HF of deviation from skinned / free** (physical detail, the hair's own motion): the same
  high-frequency energy computed on the tips' deviation from their guide-skinned positions
  x_g(t) (hairexp/control/skinning.py), relative to the free run's.  The plain tip HF energy also
  counts the directed motion of the guides; this one counts only what the detail hair does beyond
  its guides.  0 for the skinned run by construction.
* **Same, within clusters / free**: as above after removing, per frame, the mean deviation of the
  tips of the same cluster (tracked run's clusters): the tip motion that cluster-centre constraints
  leave free (individual tips moving against each other), relative to the free run's.
* **Cluster variance dynamics** (physical detail): per cluster, the standard deviation over frames
  of the spread ratio V_k(t) / V_k(rest) (eq. 4), averaged over clusters (absolute, not relative to
  the free run).  0 = clusters that keep their rest spread.
* **Scene success**: the scene's measure (hairexp/evaluation/measures.py) computed from each run's
  frames the same way for every controller (with the tracked configuration's tracker where the
  measure needs clusters: spreading's cluster variance ratio), judged by the per-run rule of the
  scene's judge (hairexp/evaluation/judges.py), stated under each table:
  goaling and celia: the hair touches the collider (wheel, goblet; `collider_contact`; the skinned hair
  has no collisions, so it can "touch" by passing through, min distance < 0);
  splitting: clumps = guides; spreading: cluster variance ratio within the judge's tolerance of its
  target; stylization: the block leaves the rail.  The judges' free-run halves (the free run must
  fail) are shown by the `free` rows.
* **Inside a collider** (under each table): the smallest signed distance from a free vertex to a
  collider's surface over all frames, listed where it is negative (the skinned hair has no
  collision stage; the simulated controllers' collision stage keeps the hair on the shell up to
  round-off and the limits of the velocity filter).
* **Median s/step**: `step_seconds_median` of the run (one step per frame; 2 shared cores, other
  sessions ran at the same time: read them as +-30 %).
"""


def failures(scenes: list[dict]) -> tuple[list[str], int]:
    """(the runs that failed, as "scene/controller", the number of runs): a controller that
    cannot drive a scene ("not applicable") is no failure."""
    runs = [(s["experiment"], n, r) for s in scenes for n, r in s["results"].items()]
    return [f"{e}/{n}" for e, n, r in runs if r["status"] == "failed"], len(runs)


def check_scenes(ap, experiments, frames: int | None) -> None:
    """Every scene's tracked configuration (with ``--frames``) passes the checks ``assemble`` makes
    before it builds anything (``hairexp.app.assemble.check_config``: ranges, the step schedule, the
    resource guard), else a usage error naming the scene (exit 2) before the first run."""
    from hairexp.app.assemble import check_config

    extra = [] if frames is None else [f"frames={frames}"]
    for e in experiments:
        try:
            base = compose([f"experiment={e}", "logging=off", *extra])
            _, vover = representative_variant(base)
            check_config(controller_cfg(base, vover, ["controller.name=tracking"], f"{e} tracked"))
        except Exception as exc:   # noqa: BLE001  (InputError, Hydra's composition errors)
            ap.error(f"experiment {e}" + (f" with --frames {frames}" if frames is not None else "")
                     + f": {' '.join(str(exc).split())}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiments", nargs="+", default=list(EXPERIMENTS), choices=list(EXPERIMENTS))
    ap.add_argument("--frames", type=positive_int, default=None, help="override every scene's frame count (quick checks)")
    ap.add_argument("--out", type=writable_dir, default=None,
                    help="keep the run folders here (default: a temporary folder)")
    ap.add_argument("--no-report", action="store_true")
    add_report_option(ap, "baselines")
    args = ap.parse_args(argv)
    if args.frames is not None and args.frames <= WINDOW:
        ap.error(f"--frames must be > {WINDOW} (the tip high-frequency window is {WINDOW} frames)")
    check_scenes(ap, args.experiments, args.frames)
    if not args.no_report:
        check_reports(ap, args.report)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="baselines_"))
    t0 = time.perf_counter()
    scenes = []
    for e in args.experiments:
        ts = time.perf_counter()
        scenes.append(run_scene(e, args.frames, root))
        scenes[-1]["wall_seconds"] = time.perf_counter() - ts
        print(f"[{e}] done in {scenes[-1]['wall_seconds']:.0f} s", flush=True)
    wall = time.perf_counter() - t0
    print(f"total wall {wall:.0f} s", flush=True)
    failed, total = failures(scenes)
    completed = sum(r["status"] == "completed" for s in scenes for r in s["results"].values())
    if completed == 0:   # nothing to compare: the committed report stays as it was
        first = next((f"{s['experiment']}/{n}: {r['error']}" for s in scenes for n, r in s["results"].items()
                      if r["status"] == "failed"), "-")
        rest = "" if len(failed) == total else ", the rest not applicable"
        return fail(f"no run completed ({len(failed)} of {total} failed{rest}; the first: "
                    f"{' '.join(first.split())[:300]})"
                    + ("" if args.no_report else f"; reports/{args.report}.md/.json left as they were"))
    if not args.no_report:
        path = write_report(args.report, report(scenes, wall),
                            {"experiments": args.experiments, "frames_override": args.frames,
                             "stiffnesses": list(STIFFNESSES), "window_frames": WINDOW, "wall_seconds": wall,
                             "scenes": scenes})
        print(f"wrote {path}")
    if failed:
        return fail(f"{len(failed)} of {total} runs failed: {', '.join(failed)}"
                    + ("" if args.no_report else " (recorded as failed in the report)"))
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
