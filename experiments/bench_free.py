"""Benchmark of the free step at Celia scale (issue: foundation).

Run (``common.celia_bench``): ``experiment=celia variants=[] controller=free collision=off``, the
head's motion replaced by a jerk: the Celia ponytail (301 strands x 26 vertices), dt = 0.04 s,
the hair settled for the config's ``scene.settle`` (4 s, by ``assemble`` as in every run), the
collision stage off (bench_collisions times it).  The head is still during the 2 untimed warm-up
steps from ``run.initial_state()`` (torch.compile builds its kernels), then jerks up 12 cm in
0.1 s, and sideways 10 cm in 0.1 s one second later; the ``--steps`` steps from the jerk on are
timed, so every timed step has moving hair.

Prints and writes reports/bench_free.{md,json}: median/mean/p90 s per step, Newton
iterations, the time split (derivatives, assembly, solve, other), the maximum stretch, and the
same figures for the ablations (penalty stretch Hessian, torch kernels instead of the numba ones,
autograd derivatives), each its own run
of the same config with the one setting changed (settle included, as such a run would do it).
Usage:  python -m experiments.bench_free [--steps 50] [--quick]
"""

from __future__ import annotations

import argparse
import time

from hairexp.app.assemble import assemble
from hairexp.app.report import header, write_report

from experiments.common import WARMUP, celia_bench, describe_run, md_table, pct, stretch_max, time_steps, positive_int

AUTOGRAD_STEPS = 15   # the autograd row: the first (violent) steps only


def run_case(name: str, overrides: list[str], steps: int, fused: bool = True):
    """One run's timed steps; ``fused`` False: Newton without the fused pass (``evaluate`` then
    ``solve``, the free step before it)."""
    t0 = time.perf_counter()
    run = assemble(celia_bench("free", steps, overrides))
    run.simulator.objective.fused = fused
    t_assemble = time.perf_counter() - t0
    tm = time_steps(run, steps, WARMUP, observe=stretch_max)
    res = {"case": name, "overrides": overrides, "fused": fused, **tm.summary(), "stretch_max": float(tm.column("stretch").max()),
           "vertices": run.scene.strands.n_vertices, "dofs": run.simulator.objective.n_dofs,
           "settle_s": float(run.cfg.scene.settle), "assemble_s": t_assemble, "run": describe_run(run),
           "integrator": run.simulator.integrator.name,
           "stages": 2 if getattr(run.simulator.integrator, "stages", None) is not None else 1}
    split = res["split"]
    print(f"{name:>28}: median {1e3 * res['median_s']:6.1f} ms/step  mean {1e3 * res['mean_s']:6.1f}  "
          f"p90 {1e3 * res['p90_s']:6.1f}  its {res['iterations_mean']:.2f} (max {res['iterations_max']})  "
          f"stretch {res['stretch_max']:.1e}  split "
          + " ".join(f"{k[:5]} {pct(split[k])}" for k in ("derivatives", "assembly", "solve", "other"))
          + f"  (assemble + settle {t_assemble:.0f} s)", flush=True)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=positive_int, default=50)
    ap.add_argument("--quick", action="store_true", help="skip the slow autograd ablation")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    main_res = run_case("free (default)", [], args.steps)
    results = [main_res, run_case("penalty stretch Hessian", ["solver.stretch_hessian=penalty"], args.steps),
               run_case("torch kernels", ["solver.kernels=torch"], args.steps),
               run_case("numba, evaluate + solve (no fused pass)", [], args.steps, fused=False)]
    unfused = results[3]
    if not args.quick:
        results.append(run_case("autograd derivatives", ["solver.derivatives=autograd"],
                                min(args.steps, AUTOGRAD_STEPS)))
    target = 0.025
    md = header("Free step at Celia scale")
    md += (f"Run: {main_res['run']}.  The head is still for {WARMUP} untimed warm-up steps from the run's initial "
           f"state, then jerks up 12 cm in 0.1 s and sideways 10 cm in 0.1 s a second later.  Timed: the "
           f"{args.steps} steps from the jerk on (`python -m experiments.bench_free`, `common.celia_bench`).\n\n")
    cols = ["case", "median s/step", "mean", "p90", "Newton its (mean/max)", "converged", "max stretch",
            "derivatives", "assembly", "solve", "other"]
    md += md_table(cols, [[r["case"], f"{r['median_s']:.4f}", f"{r['mean_s']:.4f}", f"{r['p90_s']:.4f}",
                           f"{r['iterations_mean']:.2f} / {r['iterations_max']}", pct(r["converged_fraction"]),
                           f"{r['stretch_max']:.1e}", *(pct(r["split"][k]) for k in cols[7:])] for r in results])
    ok = main_res["median_s"] <= target
    md += (f"\nTarget: median <= {target} s/step: **{'met' if ok else 'missed'}** "
           f"({main_res['median_s']:.4f} s). Paper's C++ prototype: 0.045 s/frame. "
           f"Ratios within this command: penalty/primal-dual = {results[1]['median_s'] / main_res['median_s']:.2f}, "
           f"torch/numba kernels = {results[2]['median_s'] / main_res['median_s']:.2f}"
           + f", evaluate + solve/fused pass = {unfused['median_s'] / main_res['median_s']:.2f} (wall medians; "
           f"the same iterations: {unfused['iterations_mean']:.2f} vs {main_res['iterations_mean']:.2f})"
           + (f", autograd/closed form = {results[4]['median_s'] / main_res['median_s']:.1f}" if len(results) > 4 else "")
           + ".\n")
    evals = main_res["iterations_mean"] + main_res["stages"]  # one evaluation per iterate, each solve's last included
    per = {k: 1e3 * main_res["mean_s"] * v for k, v in main_res["split"].items()}
    md += (f"\nWhat bounds it: the default step needs {main_res['iterations_mean']:.2f} Newton iterations on average "
           f"({evals:.2f} derivative evaluations; integrator `{main_res['integrator']}`, {main_res['stages']} solve(s) per step). "
           f"Per step (mean): "
           f"derivatives {per['derivatives']:.1f} ms, the fused pass ('assembly': per strand the derivatives, the band in "
           f"a strand-sized buffer, its block Cholesky and the step) {per['assembly']:.1f} ms "
           f"({per['assembly'] / evals:.2f} ms per pass on {main_res['dofs']} DOFs, half-bandwidth 8), separate solve "
           f"{per['solve']:.1f} ms, other (line-search energies, dual updates, kinematics, Python) {per['other']:.1f} ms. "
           f"Without the fused pass (evaluate, then solve): assembly "
           f"{1e3 * unfused['mean_s'] * unfused['split']['assembly'] / evals:.2f} ms per evaluation, solve "
           f"{1e3 * unfused['mean_s'] * unfused['split']['solve'] / max(unfused['iterations_mean'], 1e-9):.2f} ms per solve. "
           f"Steps right after a jerk take up to {main_res['iterations_max']} iterations.\n")
    md += ("\nThe default uses `solver.kernels=numba` (compiled per-strand kernels; the free step's Newton takes the "
           "fused pass `ImplicitEulerObjective.evaluate_step`, bit-identical to evaluate + solve; 'derivatives' is the "
           "terms left on torch); the torch-kernels row is the torch closed forms, bincount assembly and LAPACK's "
           "banded Cholesky (experiments/bench_kernels.py splits one iteration).\n")
    if len(results) > 4:
        md += (f"\nThe autograd row is timed over the first {min(args.steps, AUTOGRAD_STEPS)} steps only (the violent "
               "ones) and uses the exact Hessian with eigenvalue clamping, without the primal-dual tension; its run "
               "settles with autograd derivatives too.\n")
    path = write_report("bench_free", md, {"target_s": target, "met": ok, "results": results,
                                           "wall_s": time.perf_counter() - t0})
    print(f"target {target} s/step: {'met' if ok else 'MISSED'}; wrote {path}")


if __name__ == "__main__":
    main()
