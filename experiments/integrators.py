"""Time integrators (issue 13, ``solver.integrator``): reports/integrators.md.

1. The hanging chain (``hairexp.evaluation.fidelity_chain.measure_chain``: 30 cm, 20 vertices,
   soft bending, no damping, swung 1 cm by its root, then free) for each integrator and dt:
   amplitude kept per period, damping ratio, period against the linearised chain's first mode
   (and the continuum chain's), beside the linear analysis at omega dt.
2. The goaling step cost (experiment=goaling, free and tracked, 56 steps of 0.04 s), every
   integrator's runs assembled in one process and timed interleaved (``--reps`` rounds), so the
   ratios compare like with like on the same machine.

Usage: python -m experiments.integrators [--dts 0.001 0.01 0.04] [--reps 3] [--cost-integrators implicit_euler bdf2 trbdf2 lmm2]
       [--report NAME]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from experiments.common import add_report_option, ROOT, check_reports, compose, md_table, positive_float, positive_int, time_steps
from hairexp.evaluation.fidelity_chain import linear_prediction, measure_chain
from hairexp.physics.integrators import INTEGRATORS


def chain_table(dts) -> str:
    rows = []
    for name in INTEGRATORS:
        for dt in dts:
            r = measure_chain(name, dt)
            amp, per = linear_prediction(name, r.omega_dt)
            rows.append([name, f"{dt:g}", f"{r.omega_dt:.3f}", f"{100 * r.amplitude_per_period:.2f} %",
                         f"{r.damping_ratio:.4f}", f"{r.period:.4f}", f"{100 * r.period_error:+.2f} %",
                         f"{100 * amp:.2f} %", f"{100 * per:+.2f} %", f"{r.iterations / r.steps:.2f}"])
            print("chain", *rows[-1], flush=True)
    head = ["integrator", "dt (s)", "omega dt", "amplitude kept / period", "damping ratio", "period (s)",
            "period error", "linear: amplitude", "linear: period", "Newton it/step"]
    T_lin, T_cont = r.period_linear, r.period_continuum
    return (md_table(head, rows) + f"\nPeriod references: linearised discrete chain {T_lin:.4f} s (the error "
            f"column), heavy continuum chain 4 pi / (j01 sqrt(g/L)) {T_cont:.4f} s.\n")


def cost_table(integrators, reps: int) -> str:
    from hairexp.app.assemble import assemble

    runs = {}
    for name in integrators:
        for ctl in ("free", "tracking"):
            runs[(name, ctl)] = assemble(compose(["experiment=goaling", "variants=[]", f"controller.name={ctl}", "logging.rerun=false",
                                          "logging.progress=false", f"solver.integrator={name}"]))
    secs = {k: [] for k in runs}
    med = {k: [] for k in runs}        # each round's median s/step
    its = {k: [] for k in runs}
    sub = {k: 0 for k in runs}
    keys = list(runs)
    for rep in range(reps):
        # alternate the order each round, so that a change of the machine's load hits every
        # integrator alike; the ratios are taken within a round (runs a few seconds apart)
        for k in (keys if rep % 2 == 0 else keys[::-1]):
            t = time_steps(runs[k], runs[k].frames * runs[k].steps_per_frame)
            secs[k] += list(t.seconds)
            med[k].append(float(np.median(t.seconds)))
            its[k] += list(t.column("iterations"))
            sub[k] += int(t.column("substeps").sum() - len(t.rows))
    rows = []
    for (name, ctl), s in secs.items():
        ratios = np.array(med[(name, ctl)]) / np.array(med[(integrators[0], ctl)])
        rows.append([name, ctl, f"{np.median(s) * 1e3:.1f}", f"{np.mean(s) * 1e3:.1f}", f"{np.mean(its[(name, ctl)]):.2f}",
                     str(sub[(name, ctl)]), f"{np.median(ratios):.2f}", f"{ratios.min():.2f}-{ratios.max():.2f}"])
        print("cost", *rows[-1], flush=True)
    head = ["integrator", "controller", "median ms/step", "mean ms/step", "iterations/step", "extra substeps",
            f"step time / {integrators[0]} (median of rounds)", "range over rounds"]
    return md_table(head, rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dts", type=positive_float, nargs="+", default=[0.001, 0.01, 0.04])
    ap.add_argument("--reps", type=positive_int, default=7)
    ap.add_argument("--cost-integrators", nargs="+", default=["implicit_euler", "bdf2", "trbdf2", "lmm2"], choices=list(INTEGRATORS))
    ap.add_argument("--no-chain", action="store_true", help="only the cost table (reuses nothing: the chain section is left out)")
    add_report_option(ap, "integrators", files="md")
    a = ap.parse_args(argv)
    check_reports(ap, a.report)
    t0 = time.time()
    chain = "(not run: --no-chain)\n" if a.no_chain else chain_table(a.dts)
    cost = cost_table(a.cost_integrators, a.reps)
    text = f"""# Time integrators (issue 13)

Made by `python -m experiments.integrators {' '.join(argv or [])}`
({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, {time.time() - t0:.0f} s).

## Hanging chain (hairexp/evaluation/fidelity_chain.py)

30 cm, 20 vertices, EA 20 N, EI 1e-9 N m^2, 2e-4 kg/m, no damping; the root moves 1 cm sideways
over 0.4 s (smooth step), then the first mode is fitted over 3 periods.  Targets (issue 13) at
dt 0.04 s: >= 90 % amplitude per period and the period within 1 %.

{chain}
## Goaling step cost (experiment=goaling, one process, {a.reps} interleaved rounds of 56 steps, load: {' '.join(f'{x:.2f}' for x in os.getloadavg())})

{cost}"""
    out = ROOT / "reports" / f"{a.report}.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
