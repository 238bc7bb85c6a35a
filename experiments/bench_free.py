"""Benchmark of the free step at Celia scale (issue: foundation).

Scene: 301 strands x 26 vertices (the paper's Celia ponytail), dt = 0.04 s.  The hair first
settles in its hanging equilibrium under a still head (not timed); then the head jerks up by
12 cm in 0.1 s, and sideways by 10 cm in 0.1 s one second later.  Only the 2 s after the first
jerk are timed, so every timed step has moving hair.

Prints and writes reports/bench_free.{md,json}: median/mean/p90 s per step, Newton
iterations, the time split (derivatives, assembly, solve, other), the maximum stretch, and the
same figures for the ablations (penalty stretch Hessian, autograd derivatives) measured in the
same run.  Usage:  .venv/bin/python experiments/bench_free.py [--steps 50] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


from hairexp.app.config import compose_config  # noqa: E402
from hairexp.physics.simulator import Simulator  # noqa: E402
from hairexp.app.report import header, write_report  # noqa: E402
from hairexp.app.builders import build_scene  # noqa: E402
from hairexp.outputs.metrics import stretch  # noqa: E402

SETTLE = 3.0   # s of still head before the first jerk (hair reaches its hanging equilibrium)


def compose_cfg(overrides):
    return compose_config(["experiment=celia", *overrides])


def motion_overrides() -> list[str]:
    t0 = SETTLE
    times = [0.0, t0, t0 + 0.1, t0 + 1.0, t0 + 1.1, t0 + 10.0]
    tr = [[0, 0, 0], [0, 0, 0], [0, 0.12, 0], [0, 0.12, 0], [0.1, 0.12, 0], [0.1, 0.12, 0]]
    fmt = lambda rows: "[" + ",".join("[" + ",".join(f"{float(v)}" for v in r) + "]" for r in rows) + "]"
    return ["scene.motion.interpolation=linear", f"scene.motion.times=[{','.join(map(str, times))}]",
            f"scene.motion.translations={fmt(tr)}", f"scene.motion.rotations_deg={fmt([[0, 0, 0]] * len(times))}"]


def run_case(name: str, overrides: list[str], steps: int, settled=None):
    cfg = compose_cfg(motion_overrides() + overrides)
    scene = build_scene(cfg.scene)
    sim = Simulator(scene, cfg.solver)
    dt = cfg.solver.dt
    if settled is None:
        state = sim.initial_state()
        while state.time < SETTLE - 1e-9:
            state, _ = sim.step(state, dt)
        settled = state
    # warm-up from the settled state (untimed): builds the compiled kernels of this case
    sim.step(settled.copy(), dt)
    sim.step(sim.step(settled.copy(), dt)[0], dt)
    state = settled.copy()
    rows = []
    for _ in range(steps):
        state, info = sim.step(state, dt)
        eps = np.abs(stretch(scene, state.x)).max()
        rows.append({"s": info.seconds["total"], "it": info.iterations, "stretch": eps, "conv": info.converged,
                     **{k: info.seconds[k] for k in ("derivatives", "assembly", "solve", "other")}})
    s = np.array([r["s"] for r in rows])
    its = np.array([r["it"] for r in rows])
    tot = s.sum()
    split = {k: float(sum(r[k] for r in rows) / tot) for k in ("derivatives", "assembly", "solve", "other")}
    res = {"case": name, "overrides": overrides, "steps": steps, "median_s": float(np.median(s)),
           "mean_s": float(s.mean()), "p90_s": float(np.percentile(s, 90)), "iterations_mean": float(its.mean()),
           "iterations_max": int(its.max()), "converged_fraction": float(np.mean([r["conv"] for r in rows])),
           "stretch_max": float(max(r["stretch"] for r in rows)), "split": split,
           "vertices": scene.strands.n_vertices, "dofs": sim.objective.n_dofs}
    print(f"{name:>28}: median {1e3 * res['median_s']:6.1f} ms/step  mean {1e3 * res['mean_s']:6.1f}  "
          f"p90 {1e3 * res['p90_s']:6.1f}  its {res['iterations_mean']:.2f} (max {res['iterations_max']})  "
          f"stretch {res['stretch_max']:.1e}  split " + " ".join(f"{k[:5]} {100 * v:.0f}%" for k, v in split.items()),
          flush=True)
    return res, settled


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--quick", action="store_true", help="skip the slow autograd ablation")
    args = ap.parse_args()
    t0 = time.perf_counter()
    main_res, settled = run_case("free (default)", [], args.steps)
    results = [main_res]
    results.append(run_case("penalty stretch Hessian", ["solver.stretch_hessian=penalty"], args.steps, settled)[0])
    if not args.quick:
        results.append(run_case("autograd derivatives", ["solver.derivatives=autograd"], min(args.steps, 15), settled)[0])
    target = 0.025
    md = header("Free step at Celia scale")
    md += (f"Scene: {main_res['vertices']} vertices (301 strands x 26), {main_res['dofs']} DOFs, dt = 0.04 s; hair settled "
           f"for {SETTLE} s, then the head jerks up 12 cm in 0.1 s and sideways 10 cm in 0.1 s a second later. "
           f"Timed: the {args.steps} steps after the first jerk.\n\n")
    md += "| case | median s/step | mean | p90 | Newton its (mean/max) | converged | max stretch | derivatives | assembly | solve | other |\n"
    md += "|---|---|---|---|---|---|---|---|---|---|---|\n"
    for r in results:
        sp = r["split"]
        md += (f"| {r['case']} | {r['median_s']:.4f} | {r['mean_s']:.4f} | {r['p90_s']:.4f} | {r['iterations_mean']:.2f} / "
               f"{r['iterations_max']} | {100 * r['converged_fraction']:.0f}% | {r['stretch_max']:.1e} | "
               f"{100 * sp['derivatives']:.0f}% | {100 * sp['assembly']:.0f}% | {100 * sp['solve']:.0f}% | {100 * sp['other']:.0f}% |\n")
    ok = main_res["median_s"] <= target
    md += (f"\nTarget: median <= {target} s/step: **{'met' if ok else 'missed'}** "
           f"({main_res['median_s']:.4f} s). Paper's C++ prototype: 0.045 s/frame. "
           f"Ratios within this run: penalty/primal-dual = {results[1]['median_s'] / main_res['median_s']:.2f}"
           + (f", autograd/closed form = {results[2]['median_s'] / main_res['median_s']:.1f}" if len(results) > 2 else "")
           + ".\n")
    evals = main_res["iterations_mean"] + 1  # one derivative evaluation per iterate, the last one included
    per = {k: 1e3 * main_res["mean_s"] * v for k, v in main_res["split"].items()}
    md += (f"\nWhat bounds it: the default step needs {main_res['iterations_mean']:.2f} Newton iterations on average "
           f"({evals:.2f} derivative evaluations). Per step (mean): derivatives {per['derivatives']:.1f} ms "
           f"({per['derivatives'] / evals:.1f} ms per evaluation), assembly {per['assembly']:.1f} ms "
           f"({per['assembly'] / evals:.1f} ms per evaluation), banded Cholesky solve {per['solve']:.1f} ms "
           f"({per['solve'] / max(main_res['iterations_mean'], 1e-9):.1f} ms per solve: LAPACK pbsv on {main_res['dofs']} DOFs with "
           f"half-bandwidth 8), other (line search, dual updates, kinematics) {per['other']:.1f} ms. "
           f"Steps right after a jerk take up to {main_res['iterations_max']} iterations (large rotations of "
           f"near-inextensible strands); calm steps converge in 2-3.\n")
    if len(results) > 2:
        md += ("\nThe autograd row is timed over the first 15 steps only (the violent ones) and uses the exact "
               "Hessian with eigenvalue clamping, without the primal-dual tension.\n")
    path = write_report("bench_free", md, {"target_s": target, "met": ok, "results": results,
                                           "wall_s": time.perf_counter() - t0})
    print(f"target {target} s/step: {'met' if ok else 'MISSED'}; wrote {path}")


if __name__ == "__main__":
    main()
