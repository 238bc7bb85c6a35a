"""Scale (issue 16: "10,000 strands x 26 vertices tracked: <= 0.3 s/step, peak memory <= 4 GB; time
at 10,000 strands <= 40x the time at 301"): time per step and peak memory against the number of
strands.

Runs of ``experiment=celia variants=[] scene.colliders=[]`` (the solver's defaults: numba kernels,
``solver.threads=auto``) with ``scene.n_strands`` = 301, 1000, 3000 and 10000 (x 26 vertices; ``scene.root_radius`` grows
with sqrt(strands), so the density stays that of Celia), ``controller.name=free`` and
``tracking`` (Celia's 3 simulated guides x 8 tracking points: 24 clusters, 72 constraints),
dt = 0.04 s, assembled by ``assemble`` as ``python -m hairexp`` does: the hair (and guides)
settled for the config's ``scene.settle`` (4 s), the tracking registered on the settled hair,
no colliders (no collision stage).  The head jerks up 12 cm in 0.1 s at t = 0.2 s; steps 1-2
from ``run.initial_state()`` are untimed warm-up, then ``--steps`` (10)
steps are timed.  Each size and controller runs in its own process, whose peak resident memory
(``ru_maxrss``, settle included) is reported next to the memory before the run was assembled.
Targets: tracked at 10,000 strands <= 0.3 s/step and <= 4 GB peak; 10,000 strands <= 40 x the time
of 301 (linear: 33 x); an earlier issue's 3000 strands <= 12 x the time of 301 is kept beside it.
Writes reports/bench_scale.{md,json,png} (--report NAME: reports/NAME.{md,json,png}).
Usage: python -m experiments.bench_scale [--sizes 301 1000 3000 10000] [--steps 10] [--report NAME]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys

import numpy as np

from experiments.common import (add_report_option, ROOT, check_reports, compose, fail, frames_for, md_table, motion_overrides, positive_int,
                                strand_count, time_steps)

WARMUP = 2
MOTION = motion_overrides([0.0, 0.2, 0.3, 10.0], [[0, 0, 0], [0, 0, 0], [0, 0.12, 0], [0, 0.12, 0]])


def config(n: int, controller: str, steps: int):
    radius = 0.025 * float(np.sqrt(n / 301.0))
    return compose(["experiment=celia", "variants=[]", "scene.colliders=[]", "measure.name=none", "measure.collider=", "judge=none", f"scene.n_strands={n}",
                    f"scene.root_radius={radius}", f"controller.name={controller}",
                    f"frames={frames_for(WARMUP + steps, 0.04, 25.0)}", *MOTION])


def one(n: int, controller: str, steps: int) -> dict:
    """Runs in a child process: returns the figures of one size and controller."""
    from hairexp.app.assemble import assemble

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    run = assemble(config(n, controller, steps))
    s = time_steps(run, steps, WARMUP).summary()
    cons = getattr(run.controller, "cons", None)
    return {"strands": n, "vertices": int(run.scene.strands.n_vertices), "controller": controller,
            "constraints": 0 if cons is None else 3 * int(cons.K), "settle_s": float(run.cfg.scene.settle),
            "median_s": s["median_s"], "mean_s": s["mean_s"], "iterations_mean": s["iterations_mean"],
            "rss_before_mb": rss0, "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def check_sizes(ap, sizes, steps: int) -> None:
    """Every size's run config passes the checks ``assemble`` makes before it builds anything
    (``hairexp.app.assemble.check_config``: the resource guard refuses a run that cannot fit in the
    machine's memory), else a usage error naming the size (exit 2) before the first run."""
    from hairexp.app.assemble import check_config

    for n in sorted(set(sizes), reverse=True):   # the largest first: the one the guard refuses
        for controller in ("free", "tracking"):
            try:
                check_config(config(n, controller, steps))
            except Exception as exc:   # noqa: BLE001  (InputError of the guard or the counts)
                ap.error(f"argument --sizes: {n} strands ({controller}): {' '.join(str(exc).split())}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=strand_count, nargs="*", default=[301, 1000, 3000, 10000])
    ap.add_argument("--steps", type=positive_int, default=10)
    ap.add_argument("--one", nargs=2, metavar=("STRANDS", "CONTROLLER"), help=argparse.SUPPRESS)
    add_report_option(ap, "bench_scale", files="md,json,png")
    args = ap.parse_args(argv)
    if args.one:
        try:
            strands = strand_count(args.one[0])
        except argparse.ArgumentTypeError as exc:
            ap.error(f"argument --one STRANDS: {exc}")
        if args.one[1] not in ("free", "tracking"):
            ap.error(f"argument --one CONTROLLER: {args.one[1]!r} is not free or tracking")
        print(json.dumps(one(strands, args.one[1], args.steps)))
        return
    if not args.sizes:
        ap.error("argument --sizes: give at least one size")
    check_sizes(ap, args.sizes, args.steps)
    check_reports(ap, args.report)
    from hairexp.app.report import header, write_report

    res = []
    for controller in ("free", "tracking"):
        for n in args.sizes:
            proc = subprocess.run([sys.executable, "-m", "experiments.bench_scale", "--one", str(n), controller,
                                   "--steps", str(args.steps)], capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                print(proc.stderr[-2000:], file=sys.stderr)
                return fail(f"the {controller} run of {n} strands failed (exit {proc.returncode}); "
                            f"reports/{args.report}.md left as it was")
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            res.append(r)
            print(f"{controller:>8} {n:5d} strands ({r['constraints']} constraints): median {1e3 * r['median_s']:8.1f} "
                  f"ms/step, {r['iterations_mean']:.2f} its, peak RSS {r['rss_peak_mb']:.0f} MB (before the run "
                  f"{r['rss_before_mb']:.0f} MB)", flush=True)
    ratio, verdicts = {}, []
    for c in ("free", "tracking"):
        by = {r["strands"]: r for r in res if r["controller"] == c}
        for big, limit in ((3000, 12.0), (10000, 40.0)):
            if 301 in by and big in by:
                q = by[big]["median_s"] / by[301]["median_s"]
                ratio[f"{c}_{big}_over_301"] = q
                verdicts.append(f"{c}: {big} strands take **{q:.1f}x** the time of 301 (target <= {limit:g}x: "
                                f"**{'met' if q <= limit else 'missed'}**).")
        if c == "tracking" and 10000 in by:
            r = by[10000]
            verdicts.append(f"tracking at 10,000 strands: **{r['median_s']:.3f} s/step** (target <= 0.3: "
                            f"**{'met' if r['median_s'] <= 0.3 else 'missed'}**), peak **{r['rss_peak_mb'] / 1024:.2f} GB** "
                            f"(target <= 4: **{'met' if r['rss_peak_mb'] <= 4096 else 'missed'}**).")
    md = header("Scale: time per step and peak memory against the number of strands")
    md += ("Runs of `experiment=celia variants=[] scene.colliders=[]` (the solver's defaults) with `scene.n_strands` = N "
           "(x 26 vertices, root disk radius 2.5 cm x sqrt(N / 301)), `controller.name` free and tracking (3 simulated "
           f"guides x 8 points: {max((r['constraints'] for r in res), default=0)} constraints), dt = 0.04 s, assembled "
           f"as `python -m hairexp` does (hair and guides settled for scene.settle = {res[0]['settle_s']:g} s, no "
           f"colliders); {args.steps} steps timed after {WARMUP} warm-up steps from the "
           "run's initial state, the head jerking up at 0.2 s; one process per row (`python -m experiments.bench_scale`)."
           "\n\n")
    md += md_table(["controller", "strands", "vertices", "constraints", "median s/step", "per strand (ms)", "iterations",
                    "peak RSS MB", "RSS before the run MB"],
                   [[r["controller"], r["strands"], r["vertices"], r["constraints"], f"{r['median_s']:.4f}",
                     f"{1e3 * r['median_s'] / r['strands']:.3f}", f"{r['iterations_mean']:.2f}", f"{r['rss_peak_mb']:.0f}",
                     f"{r['rss_before_mb']:.0f}"] for r in res])
    for v in verdicts:
        md += "\n" + v + "\n"
    md += f"\n\n![time per step]({args.report}.png)\n"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for c in ("free", "tracking"):
            rr = [r for r in res if r["controller"] == c]
            ax[0].loglog([r["strands"] for r in rr], [r["median_s"] for r in rr], "o-", label=c)
            ax[1].semilogx([r["strands"] for r in rr], [r["rss_peak_mb"] for r in rr], "o-", label=c)
        n = np.array(sorted({r["strands"] for r in res}), dtype=float)
        base = [r for r in res if r["controller"] == "free" and r["strands"] == 301]
        if base:
            ax[0].loglog(n, base[0]["median_s"] * n / 301, "k--", lw=0.8, label="linear from 301 (free)")
        ax[0].set(xlabel="strands (x 26 vertices)", ylabel="median s / step", title="time per step")
        ax[1].set(xlabel="strands (x 26 vertices)", ylabel="peak RSS (MB)", title="peak memory")
        for a_ in ax:
            a_.legend()
            a_.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        fig.savefig(ROOT / "reports" / f"{args.report}.png", dpi=110)
    except ImportError:
        md += "\n(matplotlib is not installed: no plot)\n"
    path = write_report(args.report, md, {"results": res, "ratios": ratio, "targets": {"3000_over_301": 12, "10000_over_301": 40,
                                                                           "tracking_10000_s_per_step": 0.3, "tracking_10000_peak_gb": 4}})
    print(f"wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
