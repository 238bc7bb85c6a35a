"""Where TR-BDF2's step cost goes on goaling (issue 13: <= 1.3 x implicit Euler's step cost):
reports/trbdf2_cost.md.

Every solve of a step (implicit Euler: one; TR-BDF2: the trapezoidal stage and the BDF2 stage)
is counted separately, on the goaling scene at dt 0.04 s, free and tracked:

1. Newton (free) / SQP (tracked) iterations per stage, against implicit Euler's per step;
2. the lower bound of better first iterates: each stage is solved again from the converged
   positions of a first pass moved back towards the stage's own first iterate, x_sol + eps
   (x_pred - x_sol) (eps = 1: the scheme as it is; 0.01: a first iterate 100 times closer);
3. first iterates a scheme could compute (what they do to the iterations, and how far the
   end positions move, against the scheme's x_pred): the trapezoidal stage from the constant
   acceleration x_0 + h v_0 + h^2/2 a_0 (= x_pred + tau^2 a_0), the BDF2 stage from
   x_pred + beta^2 a_g (a_g the first stage's end acceleration), both, the trapezoidal stage
   from x_0 + h v_0, and every stage from the positions' quadratic extrapolation;
4. warm starts from the converged stage: the spring tensions (the primal-dual stretch Hessian's
   iterate) and, tracked, the SQP's sliding parameters and multipliers;
5. the BDF2 stage's Newton (free) with the first stage's last Hessian (both stages have the same
   M/h^2, gamma = 2 - sqrt 2): for its first iteration only, or for every iteration (the chord
   method, at most ``CHORD_MAX`` iterations);
6. a looser first stage: the trapezoidal (or restart) stage solved to a larger ``rtol`` (Newton's
   and the SQP's) than the BDF2 stage, whose solve alone sets the step's end; or to one iteration,
   accepted whatever its residual (a linearly implicit first stage).

Usage: python -m experiments.trbdf2_cost [--eps 0.01 0.1 0.3 1] [--report NAME]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from dataclasses import replace

import numpy as np

from experiments.common import add_report_option, ROOT, check_reports, _number, compose, md_table, time_steps

STEPS = 56   # goaling: 56 frames of one 0.04 s step
fraction = _number(float, 0.0, True, "a number >= 0")
#: the chord method's iteration cap (section 4)
CHORD_MAX = 50
#: the first stage's tolerances of section 6 (the BDF2 stage keeps solver.rtol = 1e-5)
FIRST_RTOLS = (1e-3, 1e-2, 0.1, 0.3)


def _run(ctl: str, integrator: str):
    from hairexp.app.assemble import assemble

    return assemble(compose(["experiment=goaling", "variants=[]", f"controller.name={ctl}", "logging.rerun=false",
                             "logging.progress=false", f"solver.integrator={integrator}"]))


class StageProbe:
    """Wraps one run's Simulator and objective (instance attributes; the classes are untouched):
    counts each stage's iterations, records its converged positions, and can replace the
    objective's first iterate (``guess``: None, "oracle", "tr", "bdf2", "both", "tr-v",
    "quadratic") or warm-start a stage from its converged tensions and tracking iterates ("warm")."""

    def __init__(self, run):
        self.run, sim = run, run.simulator
        self.obj = obj = sim.objective
        self._stage, self._begin, self._initial = sim._stage, obj.begin_step, obj.initial_guess
        sim._stage, obj.begin_step, obj.initial_guess = self.stage, self.begin_step, self.initial_guess
        self.guess, self.eps, self.solutions, self.converged = None, 1.0, [], []
        self.first_rtol, self.first_one = None, False   # section 6: the first stage's tolerance
        self.reset()

    def reset(self):
        self.iterations, self.index, self.a_g, self.starts = defaultdict(list), 0, None, []

    def stage(self, state, dt, integ, step_dt, last=True):
        self.kind = type(integ).__name__
        self.starts.append((state.time, state.x))
        self.t_end = state.time + dt
        if self.guess == "warm" and state.control is not None:
            state = replace(state, control=self.converged[self.index][1])
        new, info = self._loose(state, dt, integ, step_dt, last) if self.first_rtol is not None and \
            self.kind != "_StageBDF2" else self._stage(state, dt, integ, step_dt, last=last)
        self.iterations[self.kind].append(info.iterations)
        if self.guess is None:
            self.solutions.append(new.x)
            self.converged.append((new.tensions, new.control))
        if self.kind == "Trapezoidal":   # its end acceleration, the BDF2 stage's first iterate
            self.a_g = (new.x - self.plan.x_pred) / self.plan.h ** 2
        self.index += 1
        return new, info

    def _loose(self, state, dt, integ, step_dt, last=True):
        """The first stage with Newton's and the SQP's ``rtol`` set to ``first_rtol`` (and, with
        ``first_one``, one iteration, its end accepted as converged)."""
        from hairexp.physics.info import CONVERGED, MAX_ITERATIONS

        sim = self.run.simulator
        ctl = sim.controller
        newton, sqp = sim.newton, getattr(ctl, "opts", None)
        cap = {"max_iterations": 1} if self.first_one else {}
        sim.newton = replace(newton, rtol=self.first_rtol, **cap)
        if sqp is not None:
            ctl.opts = replace(sqp, rtol=self.first_rtol, **cap)
        try:
            new, info = self._stage(state, dt, integ, step_dt, last=last)
        finally:
            sim.newton = newton
            if sqp is not None:
                ctl.opts = sqp
        if self.first_one and info.status == MAX_ITERATIONS:
            info.status = CONVERGED
        return new, info

    def begin_step(self, x_n, v_n, x_kin, dt, tensions=None, plan=None):
        self.x_n, self.v_n, self.plan = x_n, v_n, plan
        if self.guess == "warm":
            tensions = self.converged[self.index][0]
        return self._begin(x_n, v_n, x_kin, dt, tensions, plan)

    def initial_guess(self):
        x0 = self._initial()
        fv, p, g = self.obj.free_vertices, self.plan, self.guess
        if g == "oracle":
            sol = self.solutions[self.index][fv].reshape(-1)
            return sol + self.eps * (x0 - sol)
        if self.obj.x_start is not None or p is None:
            return x0
        if g == "quadratic" and len(self.starts) >= 3:
            # the quadratic through the last three stage starts, at the stage's end
            (ta, xa), (tb, xb), (tc, xc) = self.starts[-3:]
            T, t = (ta, tb, tc), self.t_end
            w = [np.prod([(t - T[m]) / (T[j] - T[m]) for m in range(3) if m != j]) for j in range(3)]
            return (w[0] * xa + w[1] * xb + w[2] * xc)[fv].reshape(-1)
        if self.kind == "Trapezoidal" and g == "tr-v":
            return (self.x_n + 2.0 * p.h * self.v_n)[fv].reshape(-1)   # x_0 + h v_0: no a_0
        if self.kind == "Trapezoidal" and g in ("tr", "both"):
            # x_pred = x_0 + 2 tau v_0 + tau^2 a_0: x_pred + tau^2 a_0 = 2 x_pred - x_0 - 2 tau v_0
            return (2.0 * p.x_pred - self.x_n - 2.0 * p.h * self.v_n)[fv].reshape(-1)
        if self.kind == "_StageBDF2" and g in ("bdf2", "both") and self.a_g is not None:
            return (p.x_pred + p.h ** 2 * self.a_g)[fv].reshape(-1)
        return x0

    def go(self, guess=None, eps=1.0, first_rtol=None, first_one=False):
        self.guess, self.eps, self.first_rtol, self.first_one = guess, eps, first_rtol, first_one
        self.reset()
        t = time_steps(self.run, STEPS)
        return t, dict(self.iterations)


def reused_hessian(run, reuse: str):
    """(its Timing, iterations by stage, steps not converged): the free ``run`` (TR-BDF2) with the
    BDF2 stage's Newton directions from the band of the first stage's solution: "first" (its first
    iteration, then Newton) or "all" (the chord method).  The Newton loop of
    hairexp/physics/newton.py without the fused pass (the band must be kept)."""
    from hairexp.physics import controller as ctl_module
    from hairexp.physics.info import CONVERGED, SolveInfo
    from hairexp.physics.newton import line_search, newton_solve

    probe = StageProbe(run)
    held = {}

    def solve(obj, x0, opts):
        if probe.kind != "_StageBDF2" or "band" not in held:
            x, info = newton_solve(obj, x0, opts)
            if probe.kind == "Trapezoidal":
                held["band"] = obj.evaluate(x, need_hessian=True).banded.copy()
            return x, info
        info, x = SolveInfo(), x0.copy()
        while True:
            ev = obj.evaluate(x, need_hessian=reuse == "first" and info.iterations > 0)
            if np.linalg.norm(ev.grad) <= opts.atol + opts.rtol * ev.force_scale:
                info.status, info.tensions = CONVERGED, obj.final_tensions(x)
                return x, info
            if info.iterations >= (CHORD_MAX if reuse == "all" else opts.max_iterations):
                return x, info
            p = obj.solve(ev.banded if ev.banded is not None else held["band"], -ev.grad)
            alpha, _, bt, x_new = line_search(obj.value, x, p, obj.value(x), float(ev.grad @ p), opts.max_backtracks,
                                              obj.value_noise)
            obj.update_tensions(x, alpha * p)
            x, info.iterations = x_new, info.iterations + 1

    real = ctl_module.newton_solve
    ctl_module.newton_solve = solve
    try:
        t, its = probe.go()
    finally:
        ctl_module.newton_solve = real
    return t, its, int((~t.column("converged").astype(bool)).sum())


def _fmt(its: dict) -> str:
    return ", ".join(f"{k.lstrip('_')} {np.mean(v):.2f}" for k, v in its.items())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eps", type=fraction, nargs="+", default=[0.01, 0.1, 0.3, 1.0])
    add_report_option(ap, "trbdf2_cost", files="md")
    a = ap.parse_args(argv)
    check_reports(ap, a.report)
    t0 = time.time()
    rows1, rows2, rows3, rows4, rows5, rows6 = [], [], [], [], [], []
    for ctl in ("free", "tracking"):
        ie = StageProbe(_run(ctl, "implicit_euler"))
        _, its_ie = ie.go()
        n_ie = np.mean(its_ie["ImplicitEuler"])
        tr = StageProbe(_run(ctl, "trbdf2"))
        base, its = tr.go()
        n_tr = sum(map(sum, its.values())) / STEPS
        rows1.append([ctl, f"{n_ie:.2f}", _fmt(its), f"{n_tr:.2f}", f"{n_tr / n_ie:.2f}",
                      f"{(n_tr + 2) / (n_ie + 1):.2f}"])
        print("stages", *rows1[-1], flush=True)
        for eps in a.eps:
            _, its = tr.go("oracle", eps)
            n = sum(map(sum, its.values())) / STEPS
            rows2.append([ctl, f"{eps:g}", _fmt(its), f"{n:.2f}", f"{(n + 2) / (n_ie + 1):.2f}"])
            print("oracle", *rows2[-1], flush=True)
        for g in ("tr", "bdf2", "both", "tr-v", "quadratic"):
            t, its = tr.go(g)
            n = sum(map(sum, its.values())) / STEPS
            dx = float(np.abs(t.state.x - base.state.x).max())
            rows3.append([ctl, g, _fmt(its), f"{n:.2f}", f"{n - n_tr:+.2f}", f"{dx:.1e}"])
            print("guess", *rows3[-1], flush=True)
        for first_rtol, one in [(r, False) for r in FIRST_RTOLS] + [(1e-5, True)]:
            t, its = tr.go("loose", first_rtol=first_rtol, first_one=one)
            n = sum(map(sum, its.values())) / STEPS
            dx = float(np.abs(t.state.x - base.state.x).max())
            unconverged = int((~t.column("converged").astype(bool)).sum())
            rows6.append([ctl, "one iteration" if one else f"{first_rtol:g}", _fmt(its), f"{n:.2f}",
                          f"{(n + 2) / (n_ie + 1):.2f}", str(unconverged), f"{dx:.1e}"])
            print("loose", *rows6[-1], flush=True)
        _, its = tr.go("warm")
        n = sum(map(sum, its.values())) / STEPS
        rows5.append([ctl, _fmt(its), f"{n:.2f}", f"{n - n_tr:+.2f}"])
        print("warm", *rows5[-1], flush=True)
        if ctl == "free":
            for reuse in ("first", "all"):
                t, its, failed = reused_hessian(_run(ctl, "trbdf2"), reuse)
                n = sum(map(sum, its.values())) / STEPS
                rows4.append([reuse, _fmt(its), f"{n:.2f}", str(failed), f"{np.abs(t.state.x - base.state.x).max():.1e}"])
                print("reuse", *rows4[-1], flush=True)
    text = f"""# TR-BDF2's step cost on goaling (issue 13)

Made by `python -m experiments.trbdf2_cost {' '.join(argv or [])}` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())},
{time.time() - t0:.0f} s); goaling at dt 0.04 s, {STEPS} steps, free (Newton) and tracked (SQP).  Every
solve of a step counted: implicit Euler has one, TR-BDF2 two (the trapezoidal stage, or the
implicit Euler restart stage after a collision stage that moved vertices, then the BDF2 stage).
Each solve evaluates the objective once more than it iterates (the final convergence check), and
the time of a stage outside its solve (kinematics, the controller's targets, the collision stage)
is about that of implicit Euler's step outside its solve, so the step-time ratio is about
(iterations per TR-BDF2 step + 2) / (iterations per implicit Euler step + 1) ("evaluations ratio").

## Iterations per solve

{md_table(["controller", "implicit Euler it/step", "TR-BDF2 it/stage (mean)", "TR-BDF2 it/step", "iterations ratio", "evaluations ratio"], rows1)}
## Lower bound from better first iterates

Each stage solved again from x_sol + eps (x_pred - x_sol), x_sol its converged positions in the
pass above (the multipliers and sliding parameters of a tracked stage warm-started as usual).

{md_table(["controller", "eps", "TR-BDF2 it/stage (mean)", "TR-BDF2 it/step", "evaluations ratio"], rows2)}
## First iterates from the scheme's own history

tr: the trapezoidal stage from x_pred + tau^2 a_0 (the constant-acceleration Taylor step); bdf2:
the BDF2 stage from x_pred + beta^2 a_g; both; tr-v: the trapezoidal stage from x_0 + h v_0 (no
a_0); quadratic: every stage from the quadratic through the last three stages' starts.  Change of iterations against x_pred, and the
largest difference of the end positions from the run started from x_pred (m; the solves'
tolerance, not the scheme).

{md_table(["controller", "first iterate", "TR-BDF2 it/stage (mean)", "it/step", "change", "max end position difference (m)"], rows3)}
## Warm starts from the converged stage

Every stage begun with the tensions (free and tracked) and the sliding parameters and
multipliers (tracked) its own converged solve ended with, from x_pred as usual.

{md_table(["controller", "TR-BDF2 it/stage (mean)", "it/step", "change"], rows5)}
## The first stage's Hessian in the BDF2 stage (free)

first: the BDF2 stage's first Newton direction from the band of the first stage's solution (then
Newton); all: every direction from it (the chord method, at most {CHORD_MAX} iterations a stage).
Against the scheme's {rows1[0][3]} iterations a step.

{md_table(["Hessian reused", "TR-BDF2 it/stage (mean)", "it/step", "steps not converged", "max end position difference (m)"], rows4)}
## A looser first stage

The trapezoidal (or restart) stage solved to the first-stage rtol given (Newton's and, tracked, the
SQP's; the constraint tolerance unchanged), the BDF2 stage to solver.rtol = 1e-5 as before: the
step's end satisfies the BDF2 stage's equation to the usual tolerance, and only the history point
x_g is less exact.  "one iteration": the first stage stops after one Newton / SQP iteration,
accepted whatever its residual (its convergence check is what it would save).  Evaluations ratio
as above (the one-iteration row still pays its check here).  Max end position difference: from the
run with both stages at 1e-5 (the hair is 0.3 m long).

{md_table(["controller", "first-stage rtol", "TR-BDF2 it/stage (mean)", "it/step", "evaluations ratio", "steps not converged", "max end position difference (m)"], rows6)}"""
    out = ROOT / "reports" / f"{a.report}.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
