"""Where the tracked SQP spends its iterations at Celia scale (issue 16: "mean SQP iterations
<= 5"; the benchmark measured 23.9 a step with ``trbdf2`` before the restart at the roots'
velocity jumps, 7.66 since; ``no_restart`` is the run without it).

Each case is the tracked run of the benchmarks' Celia config (``common.celia_bench``: the head
jerks up 12 cm after 2 still steps, collision stage off) with the case's overrides, for
``--steps`` steps.  The SQP records every iteration (``SQPOptions.trace``: step length, the
Lagrangian's gradient and its tolerance, the constraint residual, the sliding parameters'
residual).  Per case: SQP iterations a step (all solves of the step, the stages of a two-stage
scheme and the substeps of a recovered step), the iterations of each solve, how many solves
took more than ``SLOW`` iterations, and in those the contraction of the gradient over their last
ten iterations (the median of |g_k+1| / |g_k|) and the share of full steps (alpha = 1): a
contraction near 1 with full steps is Newton converging linearly, i.e. a Hessian model far from
the true one along the slow direction, not a line search that cuts the steps.

Prints and writes reports/sqp_trace.{md,json}.
Usage: python -m experiments.sqp_trace [--steps 12] [--cases NAME=OVERRIDES ...] [--report NAME]
(a case: ``name=key=value,key=value``; ``default`` has no overrides)
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from hairexp.app.assemble import assemble
from hairexp.app.report import header, write_report
from hairexp.errors import InputError

from experiments.common import add_report_option, check_reports, celia_bench, describe_run, md_table, positive_int

#: a solve with more iterations than this counts as slow
SLOW = 20
CASES = {
    "default": [],
    "no_restart": ["solver.restart_at_jumps=false"],
    "implicit_euler": ["solver.integrator=implicit_euler"],
    "exact_compression": ["tracking.exact_compression=true"],
    "static_targets": ["tracking.targets=static"],
    "rtol_1e-2": ["solver.rtol=1e-2", "tracking.rtol=1e-2"],
}


def parse_case(text: str) -> tuple[str, list[str]]:
    name, _, rest = text.partition("=")
    if not name or (not rest and name not in CASES):
        raise argparse.ArgumentTypeError(f"{text!r}: a case is NAME=key=value[,key=value...] or one of {', '.join(CASES)}")
    return name, (CASES[name] if not rest else [o for o in rest.split(",") if o])


def trace_case(overrides: list[str], steps: int) -> dict:
    run = assemble(celia_bench("tracking", steps=steps, overrides=overrides))
    trace: list = []
    run.controller.opts.trace = trace
    per_step = []
    gen = run.steps(run.initial_state(), math.ceil((steps + 1) / run.steps_per_frame))
    for k in range(steps):
        start = len(trace)
        _, _, _, info = next(gen)
        solves = [len(s) for s in trace[start:]]
        per_step.append({"iterations": info.iterations, "substeps": info.substeps, "converged": bool(info.converged),
                         "solves": solves})
    slow = [s for s in trace if len(s) > SLOW]
    rates, full = [], []
    for s in slow:
        g = np.array([r["grad"] for r in s[-11:]])
        if len(g) > 1 and np.all(g[:-1] > 0):
            rates.append(float(np.median(g[1:] / g[:-1])))
        full.append(float(np.mean([r["alpha"] == 1.0 for r in s])))
    it = np.array([p["iterations"] for p in per_step], dtype=float)
    return {"describe": describe_run(run), "steps": per_step, "iterations_mean": float(it.mean()),
            "iterations_max": int(it.max()), "solves": len(trace), "slow_solves": len(slow),
            "slow_contraction_median": float(np.median(rates)) if rates else None,
            "slow_full_step_share": float(np.mean(full)) if full else None,
            "unconverged_steps": int(sum(not p["converged"] for p in per_step)),
            "recovered_steps": int(sum(p["substeps"] > 1 for p in per_step))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=positive_int, default=12, help="steps of each run (default 12: the jerk and after)")
    ap.add_argument("--cases", type=parse_case, nargs="+", default=[(n, o) for n, o in CASES.items()],
                    help="cases as NAME=key=value,key=value (default: " + ", ".join(CASES) + ")")
    add_report_option(ap, "sqp_trace")
    args = ap.parse_args()
    check_reports(ap, args.report)
    res = {}
    for name, overrides in args.cases:
        try:
            r = trace_case(overrides, args.steps)
        except InputError as exc:   # a bad value in a case's overrides: one line, as hairexp's own
            print(f"sqp_trace.py: error: case {name}: {exc}", file=sys.stderr)
            return 2
        res[name] = {"overrides": overrides, **r}
        print(f"{name}: {r['iterations_mean']:.2f} SQP iterations a step (max {r['iterations_max']}), "
              f"{r['slow_solves']} of {r['solves']} solves over {SLOW} iterations, contraction "
              f"{r['slow_contraction_median']}, per step {[p['iterations'] for p in r['steps']]}", flush=True)
    first = next(iter(res.values()))
    md = header("Where the tracked SQP spends its iterations (Celia)")
    md += (f"Runs: {first['describe']}; the head jerks up 12 cm in 0.1 s after 2 still steps "
           f"(`common.celia_bench`); {args.steps} steps of each case.  A solve is one SQP solve (a stage of a "
           f"two-stage scheme, a substep of a recovered step); slow: more than {SLOW} iterations; contraction: the "
           f"median of |grad L|_k+1 / |grad L|_k over a slow solve's last 10 iterations (the median over the slow "
           f"solves); full steps: the share of its iterations whose line search took alpha = 1.\n\n")
    rows = []
    for name, r in res.items():
        rows.append([name, " ".join(f"`{o}`" for o in r["overrides"]) or "-", f"{r['iterations_mean']:.2f}",
                     r["iterations_max"], f"{r['slow_solves']} / {r['solves']}",
                     "-" if r["slow_contraction_median"] is None else f"{r['slow_contraction_median']:.2f}",
                     "-" if r["slow_full_step_share"] is None else f"{100 * r['slow_full_step_share']:.0f} %",
                     r["recovered_steps"], r["unconverged_steps"]])
    md += md_table(["case", "overrides", "SQP it/step", "max", "slow solves", "contraction", "full steps",
                    "recovered steps", "unconverged"], rows)
    md += "\nIterations of each solve, step by step (a cell: the solves of one step, in order):\n\n"
    md += md_table(["case", *[str(k + 1) for k in range(args.steps)]],
                   [[name, *[" ".join(map(str, p["solves"])) for p in r["steps"]]] for name, r in res.items()])
    path = write_report(args.report, md, {"steps": args.steps, "slow": SLOW, "cases": res})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
