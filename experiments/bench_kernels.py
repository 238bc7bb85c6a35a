"""Benchmark of the compiled per-strand kernels (``solver.kernels=numba``) against the torch path
(``solver.kernels=torch``) at Celia scale (issue 16).

Runs (``common.celia_bench``, as bench_free.py and bench_tracking.py): ``experiment=celia
variants=[] collision=off``, the Celia ponytail (301 strands x 26 vertices, 21,672 DOFs), dt =
0.04 s, settled for the config's ``scene.settle`` by ``assemble``, the head jerking after the
untimed warm-up steps.

1. One Newton iteration, phase by phase, on the real free objective at the state after the
   warm-up (the objective of the run, rebuilt with each setting from the run's own terms):
   derivatives + band assembly (``evaluate``), factor + solve, one line-search energy
   (``value``), the tension (dual) update; torch, numba's evaluate + solve on 1 thread and its
   fused pass (``evaluate_step``: derivatives, factor and step per strand in one pass) on 1 and 2
   threads, interleaved round by round so that they share the machine's load; the agreement of
   the gradient, band and Newton step between the paths.
2. The SQP's Schur complement (``SchurKKT.factor`` + one KKT solve) of the tracked run, with the
   numba and the LAPACK + torch factorisation.
3. Whole steps: free and tracked runs with each ``solver.kernels`` (``solver.threads`` as
   configured, ``auto`` by default), and the free run without the fused pass, ``--steps`` timed
   steps each, a controller's runs stepped in turn; the per-phase split.

Prints and writes reports/bench_kernels.{md,json}.
Usage:  python -m experiments.bench_kernels [--steps 30] [--repeats 30] [--report NAME]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from hairexp.app.assemble import assemble
from hairexp.app.report import header, write_report
from hairexp.control.tracking.kkt import SchurKKT
from hairexp.physics.objective import ImplicitEulerObjective
from hairexp.physics.simulator import TIME_KEYS

from experiments.bench_free import time_interleaved
from experiments.common import add_report_option, check_reports, WARMUP, celia_bench, describe_run, md_table, pct, positive_int

#: the micro-benchmarks (Newton and Schur phases) start after WARMUP + MICRO_STEPS - 1 steps, into the
#: jerk, and step once more: their runs cover that many steps at least
MICRO_STEPS = 4

PHASES = ("evaluate", "solve", "value", "tensions")
PHASE_NAMES = {"evaluate": "derivatives + assembly", "solve": "factor + solve", "value": "line-search energy",
               "tensions": "dual update"}
#: the Newton-iteration paths: (solver.kernels, solver.threads, the fused pass ``evaluate_step``)
PATHS = {"torch": ("torch", "1", False), "numba, evaluate + solve, 1 thread": ("numba", "1", False),
         "numba, fused pass, 1 thread": ("numba", "1", True), "numba, fused pass, 2 threads": ("numba", "2", True)}
TARGETS = {"free_ms": 5.0, "tracked_ms": 10.0, "ratio": 1.5}


def variant(sim, kernels: str, threads: str) -> ImplicitEulerObjective:
    """The run's objective rebuilt with another ``solver.kernels`` / ``solver.threads``."""
    o, s = sim.objective, sim.scene.strands
    obj = ImplicitEulerObjective(sim.terms, s.masses, s.kinematic, s.free_slot, o.derivatives, sim.external,
                                 o.primal_dual, kernels, threads)
    if kernels == "numba":
        assert obj.kernels is not None and obj.kernels.threads == int(threads), "numba kernels not built"
    return obj


def begin(run, obj, state):
    """``obj.begin_step`` as the run's step does it (a multi-stage integrator: its first stage)."""
    sim = run.simulator
    integ, dt = sim.integrator, run.dt
    stages = getattr(integ, "stages", None)
    if stages is not None:
        integ, dt = stages(state, run.dt)[0]
    t_next = state.time + dt
    plan = integ.plan(sim, state, dt)
    obj.begin_step(state.x, state.v, run.scene.root_positions(t_next, run.scene.motion), dt, state.tensions, plan)


def newton_phases(run, state, repeats: int) -> dict:
    """Median ms of each phase of one Newton iteration for each path (``PATHS``), interleaved.  The
    fused pass (``ImplicitEulerObjective.evaluate_step``) computes the step with the derivatives:
    its 'derivatives + assembly' includes the factor and solve, and its 'factor + solve' is 0."""
    sim = run.simulator
    objs = {}
    for name, (kern, threads, fused) in PATHS.items():
        objs[name] = variant(sim, kern, threads)
        objs[name].fused = fused
    times = {k: {p: [] for p in PHASES} for k in objs}
    cpu = {k: [] for k in objs}
    ref = {}
    for r in range(repeats + 1):
        for name, obj in objs.items():
            begin(run, obj, state)
            xf = obj.initial_guess()
            c0 = time.process_time()
            t0 = time.perf_counter()
            ev, p = obj.evaluate_step(xf)
            t1 = time.perf_counter()
            if p is None:
                p = obj.solve(ev.banded, -ev.grad)
            t2 = time.perf_counter()
            obj.value(xf + p)
            t3 = time.perf_counter()
            obj.update_tensions(xf, p)
            t4 = time.perf_counter()
            c1 = time.process_time()
            if r == 0:   # the first round compiles / warms caches: untimed; keeps the answers
                ref[name] = (ev.grad.copy(), None if ev.banded is None else np.array(ev.banded), p.copy())
                continue
            for ph, dt in zip(PHASES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                times[name][ph].append(dt)
            cpu[name].append(c1 - c0)
    out = {}
    g0, ab0, p0 = ref["torch"]
    for name in objs:
        med = {ph: 1e3 * float(np.median(v)) for ph, v in times[name].items()}
        med["iteration"] = sum(med[ph] for ph in PHASES)
        med["iteration_cpu"] = 1e3 * float(np.median(cpu[name]))   # CPU time of all the process's threads
        g, ab, p = ref[name]
        out[name] = {"ms": med, "grad_rel_err": float(np.abs(g - g0).max() / np.abs(g0).max()),
                     "band_rel_err": None if ab is None else float(np.abs(ab - ab0).max() / np.abs(ab0).max()),
                     "step_rel_err": float(np.abs(p - p0).max() / np.abs(p0).max())}
    _, _, pu = ref["numba, evaluate + solve, 1 thread"]
    for name in ("numba, fused pass, 1 thread", "numba, fused pass, 2 threads"):
        out[name]["identical_to_unfused"] = bool(np.array_equal(ref[name][2], pu)
                                                 and np.array_equal(ref[name][0], ref["numba, evaluate + solve, 1 thread"][0]))
    return out


def schur_phases(run, state, repeats: int) -> dict:
    """Median ms of the Schur complement (factor + S) and one KKT solve, numba vs LAPACK + torch."""
    sim, ctl = run.simulator, run.controller
    obj = sim.objective
    begin(run, obj, state)
    ctl.begin(state.time + run.dt, run.scene.motion)
    ev = obj.evaluate(obj.initial_guess())
    # both in the exact mode (S built at every factorisation): the run's own ``ctl.kkt`` is in the
    # default krylov mode, whose factor does not build S
    kkts = {"torch": SchurKKT(run.scene.strands, ctl.cons, obj.assembler.bandwidth),
            "numba": SchurKKT(run.scene.strands, ctl.cons, obj.assembler.bandwidth, kernels=obj.kernels)}
    assert kkts["numba"].kernels is not None and kkts["numba"].mode == kkts["torch"].mode == "exact"
    rng = np.random.default_rng(0)
    C = 1e-3 * rng.normal(size=3 * ctl.cons.K)
    times = {k: {"factor": [], "solve": []} for k in kkts}
    sols = {}
    for r in range(repeats + 1):
        for name, kkt in kkts.items():
            t0 = time.perf_counter()
            kkt.factor(ev.banded)
            t1 = time.perf_counter()
            dx, _, lam = kkt.solve(ev.grad, C)
            t2 = time.perf_counter()
            if r == 0:
                sols[name] = (dx, lam)
                continue
            times[name]["factor"].append(t1 - t0)
            times[name]["solve"].append(t2 - t1)
    out = {name: {k: 1e3 * float(np.median(v)) for k, v in t.items()} for name, t in times.items()}
    dx0, lam0 = sols["torch"]
    dx1, lam1 = sols["numba"]
    out["numba"]["dx_rel_err"] = float(np.abs(dx1 - dx0).max() / np.abs(dx0).max())
    out["numba"]["lam_rel_err"] = float(np.abs(lam1 - lam0).max() / np.abs(lam0).max())
    out["K"] = int(ctl.cons.K)
    out["threads"] = int(obj.kernels.threads)
    return out


def whole_steps(cases: list[tuple[str, str, bool]], steps: int) -> list[tuple[dict, object]]:
    """The timed steps of runs (controller, solver.kernels, fused pass), stepped in turn
    (``bench_free.time_interleaved``) so that the machine's load weighs on each alike; ``fused``
    False: the free step's Newton without the fused pass (``evaluate`` then ``solve``, as before it)."""
    runs, t_asm = [], []
    for controller, kernels, fused in cases:
        t0 = time.perf_counter()
        run = assemble(celia_bench(controller, steps, [f"solver.kernels={kernels}"]))
        run.simulator.objective.fused = fused
        runs.append(run)
        t_asm.append(time.perf_counter() - t0)
    out = []
    for (controller, kernels, fused), run, ta, tm in zip(cases, runs, t_asm, time_interleaved(runs, steps, WARMUP)):
        cpu_ms = 1e3 * float(tm.column("cpu").mean())
        k = run.simulator.objective.kernels
        res = {"controller": controller, "kernels": kernels, "fused": fused, **tm.summary(), "assemble_s": ta,
               "threads": None if k is None else k.threads, "run": describe_run(run), "cpu_ms_per_step": cpu_ms}
        res["ms_per_iteration"] = 1e3 * res["mean_s"] / max(res["iterations_mean"], 1e-9)
        print(f"{controller:>8} {kernels:>5}{'' if fused else ' unfused'}: median {1e3 * res['median_s']:6.1f} ms/step  "
              f"mean {1e3 * res['mean_s']:6.1f}  CPU {cpu_ms:6.1f}  its {res['iterations_mean']:.2f} "
              f"(max {res['iterations_max']})  {res['ms_per_iteration']:.2f} ms/iteration  "
              "split " + " ".join(f"{p[:5]} {pct(res['split'][p])}" for p in TIME_KEYS)
              + f"  (assemble + settle {ta:.0f} s)", flush=True)
        out.append((res, tm.state))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=positive_int, default=30)
    ap.add_argument("--repeats", type=positive_int, default=30)
    add_report_option(ap, "bench_kernels")
    args = ap.parse_args(argv)
    check_reports(ap, args.report)
    t_start = time.perf_counter()
    load0 = os.getloadavg()
    # 3. whole steps (first: the runs give the states the micro-benchmarks start from)
    steps, finals = {}, {}
    # each controller's runs interleaved; free also without the fused pass (the before/after ratio)
    for controller, cases in (("free", [("torch", True), ("numba", True), ("unfused", False)]),
                              ("tracking", [("torch", True), ("numba", True)])):
        done = whole_steps([(controller, "numba" if k == "unfused" else k, f) for k, f in cases], args.steps)
        for (k, _), (res, final) in zip(cases, done):
            steps[(controller, k)], finals[(controller, k)] = res, final
    # 1. and 2. on fresh runs at the state after the warm-up steps: WARMUP + 3 steps into the jerk and
    # the Schur phases' step after them, whatever --steps (with --steps 1 or 2 the tracked run's guides
    # ended before that step: "outside the guide animation", exit 2)
    micro_steps = max(args.steps, MICRO_STEPS)
    free_run = assemble(celia_bench("free", micro_steps))
    state = free_run.initial_state()
    for _ in range(WARMUP + MICRO_STEPS - 1):   # into the jerk: a moving, stretched state
        state, _ = free_run.simulator.step(state, free_run.dt)
    newton = newton_phases(free_run, state, args.repeats)
    for name, r in newton.items():
        print(f"Newton iteration, {name:>16}: " + "  ".join(f"{PHASE_NAMES[p]} {r['ms'][p]:.3f}" for p in PHASES)
              + f"  = {r['ms']['iteration']:.3f} ms (CPU {r['ms']['iteration_cpu']:.3f})  (step rel. err. vs torch "
              f"{r['step_rel_err']:.1e})", flush=True)
    tr_run = assemble(celia_bench("tracking", micro_steps))
    st = tr_run.initial_state()
    for _ in range(WARMUP + MICRO_STEPS - 1):
        st, _ = tr_run.simulator.step(st, tr_run.dt)
    schur = schur_phases(tr_run, st, args.repeats)
    print(f"Schur complement ({schur['K']} clusters, numba on {schur['threads']} thread(s)): torch factor "
          f"{schur['torch']['factor']:.2f} ms solve {schur['torch']['solve']:.2f}; numba factor {schur['numba']['factor']:.2f} "
          f"solve {schur['numba']['solve']:.2f} (dx rel. err. {schur['numba']['dx_rel_err']:.1e})", flush=True)
    load1 = os.getloadavg()
    agree = {c: float(np.abs(finals[(c, "numba")].x - finals[(c, "torch")].x).max()) for c in ("free", "tracking")}
    fr, tr = steps[("free", "numba")], steps[("tracking", "numba")]
    ratio = tr["median_s"] / fr["median_s"]
    met = {"free_ms": 1e3 * fr["median_s"] <= TARGETS["free_ms"], "tracked_ms": 1e3 * tr["median_s"] <= TARGETS["tracked_ms"],
           "ratio": ratio <= TARGETS["ratio"]}

    md = header("Compiled per-strand kernels (solver.kernels) at Celia scale")
    md += (f"Runs: {fr['run']}; the tracked runs: {tr['run'].split('; controller ')[1]}.  Head still for {WARMUP} untimed "
           f"warm-up steps, then the jerk of `common.celia_bench`; {args.steps} timed steps per run.  Load average "
           f"(1 min) at start {load0[0]:.2f}, at end {load1[0]:.2f} on {os.cpu_count()} cores: other processes shared the "
           f"machine, so compare ratios measured in this one command.\n\n")
    md += "## One Newton iteration (ms, median of %d interleaved rounds, the free objective after the jerk)\n\n" % args.repeats
    t0 = newton["torch"]["ms"]
    md += md_table(["path", *(PHASE_NAMES[p] for p in PHASES), "iteration", "speed-up vs torch",
                    "iteration, CPU ms (all threads)", "CPU ratio", "step rel. err."],
                   [[name, *(f"{r['ms'][p]:.3f}" for p in PHASES), f"{r['ms']['iteration']:.3f}",
                     f"{t0['iteration'] / r['ms']['iteration']:.1f}x", f"{r['ms']['iteration_cpu']:.2f}",
                     f"{t0['iteration_cpu'] / max(r['ms']['iteration_cpu'], 1e-9):.1f}x", f"{r['step_rel_err']:.1e}"]
                    for name, r in newton.items()])
    md += ("\nThe CPU column is `time.process_time` over the iteration (every thread of the process, torch's 2 "
           "intra-op threads included): unlike the wall times it does not count the time slices other processes "
           "took, so it is the steadier figure on a shared machine (it still pays their cache and SMT contention).\n")
    fu, un = newton["numba, fused pass, 1 thread"], newton["numba, evaluate + solve, 1 thread"]
    md += ("\nThe numba paths fuse the derivatives of stretch, bending, inertia and gravity with the band assembly "
           "(one pass per strand); torch computes the element derivatives (closed forms) then scatters them with "
           "`np.bincount`.  'evaluate + solve' is the compiled path that writes the whole band and then factors it "
           "(`evaluate`, then `solve`: what the tracked step and the runs with torch terms or contact use); the fused "
           "pass (`evaluate_step`, the free step's default) derives, factors and solves each strand in a strand-sized "
           "band that stays in cache: its 'derivatives + assembly' includes the factor and solve (in whole steps Newton "
           "evaluates without it where the iterate is predicted to be the last, `newton._likely_converged`).  Fused vs "
           f"evaluate + solve, 1 thread, within this command: {un['ms']['iteration'] / fu['ms']['iteration']:.2f}x per "
           f"iteration in wall time, {un['ms']['iteration_cpu'] / fu['ms']['iteration_cpu']:.2f}x in CPU time (gradient "
           f"and step bit-identical: {fu['identical_to_unfused']}).  Gradient and band agree with "
           f"torch to {max(newton[n]['grad_rel_err'] for n in newton):.1e} / "
           f"{max(newton[n]['band_rel_err'] for n in newton if newton[n]['band_rel_err'] is not None):.1e} "
           "(relative to their largest entry).\n\n")
    md += f"## SQP Schur complement ({schur['K']} clusters, {3 * schur['K']} constraints; ms, median)\n\n"
    md += md_table(["path", "factor H + S = A H^-1 A^T", "one KKT solve"],
                   [[n, f"{schur[n]['factor']:.2f}", f"{schur[n]['solve']:.2f}"] for n in ("torch", "numba")])
    md += (f"\nnumba ran on {schur['threads']} thread(s) (`solver.threads=auto`); its KKT step agrees with the LAPACK + "
           f"torch one to {schur['numba']['dx_rel_err']:.1e} (dx) and {schur['numba']['lam_rel_err']:.1e} (lambda).\n\n")
    md += "## Whole steps\n\n"
    md += md_table(["run", "kernels", "Newton pass", "threads", "median ms/step", "mean", "p90", "CPU ms/step (mean)",
                    "iterations (mean/max)", "ms/iteration", "converged", *TIME_KEYS],
                   [[r["controller"], r["kernels"],
                     "-" if r["kernels"] == "torch" else ("fused" if r["fused"] and r["controller"] == "free" else "evaluate + solve"),
                     r["threads"] or "-", f"{1e3 * r['median_s']:.1f}",
                     f"{1e3 * r['mean_s']:.1f}", f"{1e3 * r['p90_s']:.1f}", f"{r['cpu_ms_per_step']:.1f}",
                     f"{r['iterations_mean']:.2f} / {r['iterations_max']}", f"{r['ms_per_iteration']:.2f}",
                     pct(r["converged_fraction"]), *(pct(r["split"][k]) for k in TIME_KEYS)]
                    for r in steps.values()])
    md += ("\nEach controller's runs stepped in turn (step k of every run, then step k + 1), so they met the same "
           "load.  CPU ms/step: `time.process_time` of the process over each timed step (mean). "
           "In the numba rows 'assembly' is the compiled per-strand kernel (derivatives and band together; with the "
           "fused pass also the factor and solve, so 'solve' is 0 there) and 'derivatives' the terms left on torch "
           "(none in these runs); the tracked rows' 'solve' includes the Schur complement, the target curves and the "
           "variance penalty.\n\n")
    uf = steps[("free", "unfused")]
    same = bool(np.array_equal(finals[("free", "numba")].x, finals[("free", "unfused")].x))
    md += (f"Free step, fused pass vs evaluate + solve (the same run config, both in this command): median "
           f"{1e3 * fr['median_s']:.1f} vs {1e3 * uf['median_s']:.1f} ms/step ({uf['median_s'] / fr['median_s']:.2f}x), "
           f"CPU {fr['cpu_ms_per_step']:.1f} vs {uf['cpu_ms_per_step']:.1f} ms/step "
           f"({uf['cpu_ms_per_step'] / max(fr['cpu_ms_per_step'], 1e-9):.2f}x); final positions bit-identical: {same}.\n\n")
    sp = {c: steps[(c, "torch")]["median_s"] / steps[(c, "numba")]["median_s"] for c in ("free", "tracking")}
    md += (f"Speed-up of whole steps (median, torch / numba): free {sp['free']:.1f}x, tracked {sp['tracking']:.1f}x.  "
           f"Positions after the {args.steps} steps, numba vs torch: max difference {agree['free']:.1e} m (free), "
           f"{agree['tracking']:.1e} m (tracked) (the steps converge to rtol 1e-5, so iterates that take a different "
           "number of iterations differ at that level).\n\n")
    md += (f"Targets (issue 16): free <= {TARGETS['free_ms']:g} ms/step: **{'met' if met['free_ms'] else 'missed'}** "
           f"({1e3 * fr['median_s']:.1f}); tracked <= {TARGETS['tracked_ms']:g} ms/step: "
           f"**{'met' if met['tracked_ms'] else 'missed'}** ({1e3 * tr['median_s']:.1f}); tracked/free <= "
           f"{TARGETS['ratio']:g}: **{'met' if met['ratio'] else 'missed'}** ({ratio:.2f}).\n")
    path = write_report(args.report, md, {"targets": TARGETS, "met": met, "newton_iteration": newton, "schur": schur,
                                          "steps": list(steps.values()), "positions_max_diff_m": agree,
                                          "load_average": {"start": load0, "end": load1},
                                          "wall_s": time.perf_counter() - t_start})
    print(f"free {1e3 * fr['median_s']:.1f} ms/step, tracked {1e3 * tr['median_s']:.1f} ms/step, ratio {ratio:.2f}; "
          f"wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
