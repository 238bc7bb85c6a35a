"""Why the tracked SQP converges linearly under second-order schemes at Celia's jerk (issues 13
and 16; reports/sqp_curvature.md).

``experiments/sqp_trace.py`` shows the symptom: with ``trbdf2`` the Celia benchmark's tracked
step takes 19.7 SQP iterations (implicit Euler 5.2), with slow solves whose gradient falls by a
steady factor of about 0.85 an iteration at full steps, i.e. a Hessian model far from the true
one along the step.  This script measures the cause, per case:

1. every solve's end state (a stage of a two-stage scheme, a substep of a recovered step): its
   SQP iterations and the edges' strain l / l0 - 1 (how many edges are compressed, the median);
2. in the first slow solve (more than ``SLOW`` iterations), re-solved from the same start for
   ``PROBE_AT`` iterations (the spring tensions of the primal-dual Hessian restored to the
   solve's start): the curvature d^T H d along the next SQP step d, per term, of the model the
   SQP uses (the PSD element Hessians: compressed edges' negative transverse stiffness clamped
   to 0, bending Gauss-Newton) and of the true Hessian (a central difference of the term's
   gradient along d).  The model over the true curvature is how much too short Newton's step
   is along d.

Runs: the benchmarks' Celia config (``common.celia_bench``: the head jerks up 12 cm in 0.1 s,
piecewise linear: a velocity jump to 1.2 m/s at 0.08 s and back to 0 at 0.18 s; collision off),
per case (``CASES``): ``no_restart``, the default ``trbdf2`` stepping through the jumps
(``solver.restart_at_jumps=false``, where the slow solves are); ``default``, which restarts there
with one implicit Euler step (hairexp/physics/integrators.py, "Driver discontinuities");
``implicit_euler``.

Usage: python -m experiments.sqp_curvature [--steps 5] [--cases NAME ...] [--report NAME]
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace

import numpy as np
import torch

from hairexp.app.assemble import assemble
from hairexp.app.report import header, write_report
from hairexp.control.tracking.sqp import sqp_solve
from hairexp.errors import InputError
from hairexp.outputs.metrics import stretch
from hairexp.physics.controller import scaled_iterations

from experiments.common import add_report_option, celia_bench, check_reports, describe_run, md_table, positive_int

#: a solve with more iterations than this is slow
SLOW = 20
#: the slow solve is re-solved this many iterations before its curvature is probed
PROBE_AT = 15
#: the difference step along d, relative to d's largest component (m)
FD_STEP = 1e-6
#: case -> overrides of the benchmarks' Celia config
CASES = {"no_restart": ["solver.restart_at_jumps=false"], "default": [],
         "implicit_euler": ["solver.integrator=implicit_euler"]}


def tensions(obj):
    """The primal-dual tension iterates (restored before the probe's re-solve)."""
    saved = [(t, None if t.tension is None else t.tension.clone()) for t in obj._dual_terms]
    k = obj.kernels
    kt = None if k is None or k.stretch is None or k.stretch.tension is None else k.stretch.tension.clone()
    return saved, kt


def restore(obj, saved) -> None:
    terms, kt = saved
    for t, v in terms:
        t.tension = v
    if obj.kernels is not None and obj.kernels.stretch is not None:
        obj.kernels.stretch.tension = kt


def curvature(obj, xf: np.ndarray, d: np.ndarray) -> dict:
    """d^T H d per term at ``xf``: the SQP's PSD model and the true one (central differences of
    the term's gradient), and the inertia's M / h^2 (exact in both)."""
    X = obj.eval_positions(xf)
    D = torch.zeros_like(X)
    D[obj.free_vertices] = torch.from_numpy(d.reshape(-1, 3))
    D = (1.0 - obj.alpha_f) * D
    eps = FD_STEP / float(D.abs().max())
    out = {"inertia": (float(d @ (obj.mass_diag * d)),) * 2}
    for t in obj.terms:
        if obj.kernels is not None and obj.kernels.handles(t) and hasattr(t, "linearized_tension"):
            t.tension = obj.kernels.stretch.tension      # the model the compiled band uses
        with torch.no_grad():
            xs, ds = X[t.stencil_t], D[t.stencil_t]
            n = ds.shape[0]
            dd = ds.reshape(n, -1)
            _, H = t.grad_hess(xs, True, obj.derivatives)
            gp, _ = t.grad_hess(xs + eps * ds, False, obj.derivatives)
            gm, _ = t.grad_hess(xs - eps * ds, False, obj.derivatives)
            model = float(torch.einsum("ni,nij,nj->", dd, H, dd))
            exact = float(((gp - gm).reshape(n, -1) * dd).sum()) / (2.0 * eps)
        out[type(t).__name__] = (model, exact)
    return out


def run_case(overrides: list[str], steps: int) -> dict:
    run = assemble(celia_bench("tracking", steps=steps, overrides=overrides))
    ctl, sim = run.controller, run.simulator
    obj = sim.objective
    solves, probe = [], {}
    original = ctl.solve

    def solve(sim_, state, dt, t_next, motion):
        x0, it = obj.initial_guess(), state.control
        saved = tensions(obj)
        out = original(sim_, state, dt, t_next, motion)
        info = out[2]
        s = stretch(run.scene, out[0])
        solves.append({"t": t_next, "dt": dt, "iterations": info.iterations, "compressed": int((s < 0).sum()),
                       "edges": len(s), "strain_median": float(np.median(s)), "strain_min": float(s.min())})
        if info.iterations > SLOW and not probe:
            after = tensions(obj)
            restore(obj, saved)
            opts = scaled_iterations(ctl.opts, sim_)
            x, t, lam, _ = sqp_solve(obj, ctl, x0, it.t, it.lam, replace(opts, trace=None, max_iterations=PROBE_AT))
            x1, _, _, _ = sqp_solve(obj, ctl, x, t, lam, replace(opts, trace=None, max_iterations=1))
            d = x1 - x
            s15 = stretch(run.scene, obj.full_positions(x))
            probe.update({"t": t_next, "dt": dt, "h": obj.dt, "iterations": info.iterations,
                          "compressed": int((s15 < 0).sum()), "edges": len(s15),
                          "strain_median": float(np.median(s15)),
                          "mass_over_h2_median": float(np.median(obj.mass_diag)),
                          "curvature": curvature(obj, x, d)})
            restore(obj, after)
        return out

    ctl.solve = solve
    gen = run.steps(run.initial_state(), math.ceil((steps + 1) / run.steps_per_frame))
    its = []
    for _ in range(steps):
        its.append(next(gen)[3].iterations)
    return {"describe": describe_run(run), "iterations": its, "solves": solves, "probe": probe}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=positive_int, default=5, help="steps of each run (default 5: the jerk and after)")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    add_report_option(ap, "sqp_curvature")
    args = ap.parse_args()
    check_reports(ap, args.report)
    res = {}
    for name in args.cases:
        try:
            res[name] = {"overrides": CASES[name], **run_case(CASES[name], args.steps)}
        except InputError as exc:
            print(f"sqp_curvature.py: error: {name}: {exc}", file=sys.stderr)
            return 2
        r = res[name]
        print(f"{name}: SQP iterations per step {r['iterations']}", flush=True)
        for s in r["solves"]:
            print(f"  solve to t={s['t']:.4f} (dt {s['dt']:.4f}): {s['iterations']} it, {s['compressed']}/{s['edges']} "
                  f"edges compressed, median strain {s['strain_median']:.2e}", flush=True)
        if r["probe"]:
            print("  probe:", {k: (f"{m:.3e}", f"{e:.3e}") for k, (m, e) in r["probe"]["curvature"].items()}, flush=True)
    first = next(iter(res.values()))
    md = header("Why the tracked SQP converges linearly at Celia's jerk")
    md += (f"Runs: {first['describe']}; the head jerks up 12 cm in 0.1 s (piecewise linear: the root velocity jumps "
           f"to 1.2 m/s at 0.08 s and back to 0 at 0.18 s), {args.steps} steps per case; cases: "
           + "; ".join(f"`{n}` ({' '.join(r['overrides']) or 'the defaults'})" for n, r in res.items()) + ".\n\n"
           f"Every solve (a stage of a two-stage scheme, a substep of a recovered step), its SQP iterations and "
           f"the strain l/l0 - 1 of its end state's {first['solves'][0]['edges']} edges:\n\n")
    rows = [[name, f"{s['t']:.4f}", f"{s['dt']:.4f}", s["iterations"], f"{s['compressed']}",
             f"{s['strain_median']:.2e}", f"{s['strain_min']:.2e}"]
            for name, r in res.items() for s in r["solves"]]
    md += md_table(["case", "solve to t (s)", "its length (s)", "SQP iterations", "edges compressed",
                    "median strain", "min strain"], rows)
    md += (f"\nThe first slow solve (> {SLOW} iterations) of each case, re-solved from its start for {PROBE_AT} "
           f"iterations: the curvature d^T H d along the next SQP step d, of the SQP's model (PSD element Hessians: "
           f"the compressed edges' negative transverse stiffness T/l (I - u u^T) clamped to 0, bending Gauss-Newton) "
           f"and of the true Hessian (central differences of each term's gradient):\n\n")
    rows = []
    for name, r in res.items():
        p = r["probe"]
        if not p:
            rows.append([name, "no slow solve", "", "", "", ""])
            continue
        cur = p["curvature"]
        tot_m, tot_e = sum(m for m, _ in cur.values()), sum(e for _, e in cur.values())
        for k, (m, e) in cur.items():
            rows.append([name, f"t = {p['t']:.4f}, {p['compressed']}/{p['edges']} compressed", k, f"{m:.3e}", f"{e:.3e}", ""])
        rows.append([name, "", "**total**", f"{tot_m:.3e}", f"{tot_e:.3e}", f"{tot_m / tot_e:.2f}" if tot_e > 0 else "-"])
    md += md_table(["case", "solve", "term", "model d^T H d", "true d^T H d", "model / true"], rows)
    path = write_report(args.report, md, {"steps": args.steps, "slow": SLOW, "probe_at": PROBE_AT, "cases": res})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
