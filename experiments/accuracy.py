"""Run time against error (validation issue, part 1): reports/accuracy.{md,json,png}.

For each scene and controller, a converged reference run (dt = --ref-dt, solver and SQP rtol
1e-9) and a grid of runs over dt and the tolerance (``solver.rtol`` and, tracked,
``tracking.rtol`` set together).  Error against the reference at every output frame: RMS and
maximum vertex distance (m), over the hair length; plus each run's largest tracking residual
and stretch.  Cost: the steps' seconds (metrics step_seconds; set-up and settle excluded) per
simulated second.  The Pareto front (no other run
is both faster and more accurate in RMS error) is marked, and the recommended setting is the
cheapest run on the front whose RMS error is below each --budget x hair length (default 1 %, 3 %
and 10 % of L: a shot that must match a reference closely, a typical one, a preview).
With ``--cache``, runs are reused from reports/cache/accuracy/ when their composed config, the solver
source (hairexp/**/*.py, conf/**/*.yaml) and the torch/numpy/scipy versions match: a reference run is
cached with its trajectory (result positions, as ``<hash>.npz`` beside the JSON) since every error
needs it; a grid run is cached as its final figures only (errors, cost, iterations...), keyed also by
its reference's config, so its trajectory is never stored.  The reference is only run (or loaded)
when a grid run of its scene and controller is not cached.  Cached rows keep the timings of their
original run, and the report marks them with the cache date and entry.
Each grid row is run with every ``--integrators`` value (``solver.integrator``, default implicit_euler and
bdf2); the reference uses ``--ref-integrator`` (default bdf2, second order).
Usage: python -m experiments.accuracy [--scenes goaling celia] [--frames N] [--budget 0.01 0.03 0.1]
       [--integrators implicit_euler bdf2 trbdf2] [--ref-integrator bdf2] [--cache] [--report NAME]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from hairexp.app.config import to_plain
from hairexp.app.report_cache import cached, describe
from hairexp.app.run import config_hash, run
from hairexp.physics.integrators import INTEGRATORS

from experiments.common import (add_report_option, ROOT, check_reports, check_set, compose, fmt, key_value, md_row, md_table, positive_float,
                                positive_int)

DTS = [0.005, 0.01, 0.02, 0.04]
RTOLS = [1e-3, 1e-5, 1e-7]


def cfg_for(scene: str, controller: str, dt: float, rtol: float, frames: int | None,
            integrator: str = "implicit_euler", extra: tuple = ()):
    over = [f"experiment={scene}", "variants=[]", f"controller.name={controller}", "logging=off",
            f"solver.dt={dt}", f"solver.rtol={rtol}", f"tracking.rtol={rtol}", "solver.on_failure=warn",
            f"solver.integrator={integrator}"]
    if frames:
        over.append(f"frames={frames}")
    return compose(over + list(extra))


def one(scene, controller, dt, rtol, frames, out: Path, integrator: str = "implicit_euler", extra: tuple = ()) -> dict:
    cfg = cfg_for(scene, controller, dt, rtol, frames, integrator, extra)
    t0 = time.perf_counter()
    s = run(cfg, out)
    wall = time.perf_counter() - t0
    with np.load(out / "result.npz") as r:
        pos = r["positions"]
    sim_seconds = cfg.frames / cfg.fps
    # cost: the steps' own time (metrics step_seconds), without set-up, compilation and the settle
    # phase (scene.settle), which are paid once per run whatever its length
    step_total = float(pd.read_parquet(out / "metrics.parquet")["step_seconds"].sum())
    return {"scene": scene, "controller": controller, "integrator": integrator, "dt": dt, "rtol": rtol,
            "positions": pos,
            "config_hash": config_hash(to_plain(cfg)), "wall_seconds": wall,
            "seconds_per_sim_second": step_total / sim_seconds, "iterations_mean": s["iterations_mean"],
            "converged_fraction": s["converged_fraction"], "stretch_max": s["stretch_max"],
            "residual_rel_max": s.get("residual_rel_max"), "length": float(cfg.scene.length)}


def pareto(rows):
    front = []
    for r in rows:
        dominated = any(o is not r and o["seconds_per_sim_second"] <= r["seconds_per_sim_second"]
                        and o["rms_rel"] <= r["rms_rel"] and (o["seconds_per_sim_second"] < r["seconds_per_sim_second"]
                                                              or o["rms_rel"] < r["rms_rel"]) for o in rows)
        r["pareto"] = not dominated
        if not dominated:
            front.append(r)
    return sorted(front, key=lambda r: r["seconds_per_sim_second"])


def recommendation(rec: dict | None) -> str:
    return (f"{rec.get('integrator', 'implicit_euler')}, dt = {rec['dt']}, rtol = {rec['rtol']:g} (RMS {rec['rms_rel']:.1e} L, "
            f"{rec['seconds_per_sim_second']:.2f} s per simulated second)" if rec else "no run within the budget")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="*", default=["goaling", "celia"], choices=sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml")))
    ap.add_argument("--frames", type=positive_int, default=None, help="output frames per run (default: the scene's)")
    ap.add_argument("--ref-dt", type=positive_float, default=0.0025)
    ap.add_argument("--budget", type=positive_float, nargs="+", default=[0.01, 0.03, 0.1],
                    help="RMS error budgets (fractions of the hair length) to recommend a setting for")
    ap.add_argument("--dts", type=positive_float, nargs="*", default=DTS)
    ap.add_argument("--rtols", type=positive_float, nargs="*", default=RTOLS)
    ap.add_argument("--integrators", nargs="+", default=["implicit_euler", "bdf2", "trbdf2"], choices=list(INTEGRATORS),
                    help="solver.integrator values of the grid runs")
    ap.add_argument("--ref-integrator", default="bdf2", choices=list(INTEGRATORS),
                    help="solver.integrator of the reference run (second order: bdf2)")
    ap.add_argument("--controllers", nargs="+", default=["free", "tracking"], choices=["free", "tracking"])
    ap.add_argument("--set", nargs="*", default=[], type=key_value, metavar="KEY=VALUE",
                    help="overrides applied to every run, the reference's included (e.g. "
                         "scene.motion.interpolation=cubic): a variant of the study, written with --report")
    add_report_option(ap, "accuracy", files="md,json,png", default_text="accuracy; a --set study: accuracy_variant")
    ap.add_argument("--cache", action="store_true",
                    help="reuse reports/cache/accuracy/ entries (same config, solver source and versions)")
    args = ap.parse_args(argv)
    check_set(ap, args.set)   # before anything runs (a bad key would fail every run)
    check_reports(ap, args.report)
    from hairexp.app.report import header, write_report

    base = ROOT / "outputs" / args.report
    extra = tuple(args.set)
    # the reference solves every stage to its rtol (1e-9): not the default 100 x for TR-BDF2's first
    ref_extra = ("solver.stage_rtol_factor=1",) + extra
    all_rows, recs, refs = [], {}, {}
    for scene in args.scenes:
        for controller in args.controllers:
            ref_plain = to_plain(cfg_for(scene, controller, args.ref_dt, 1e-9, args.frames, args.ref_integrator, ref_extra))
            ref_box = {}

            def reference(scene=scene, controller=controller, ref_plain=ref_plain, ref_box=ref_box):
                """The reference run (with its trajectory), run or loaded on first use."""
                if not ref_box:
                    ref, info = cached("accuracy", {"config": ref_plain, "role": "reference"},
                                       lambda: one(scene, controller, args.ref_dt, 1e-9, args.frames,
                                                   base / scene / controller / "ref", args.ref_integrator, ref_extra),
                                       args.cache)
                    ref_box.update(ref=ref, info=info)
                    print(f"{scene} {controller} reference: {describe(info)}", flush=True)
                return ref_box["ref"]

            rows = []
            for integrator, dt, rtol in ((i, d, r) for i in args.integrators for d in args.dts for r in args.rtols):
                if True:
                    def compute(dt=dt, rtol=rtol, scene=scene, controller=controller, reference=reference,
                                integrator=integrator):
                        r = one(scene, controller, dt, rtol, args.frames,
                                base / scene / controller / f"{integrator}_dt{dt}_rtol{rtol}", integrator, extra)
                        d = np.linalg.norm(r.pop("positions") - reference()["positions"], axis=-1)
                        r["rms_rel"] = float(np.sqrt(np.mean(d ** 2)) / r["length"])
                        r["max_rel"] = float(d.max() / r["length"])
                        return r

                    plain = to_plain(cfg_for(scene, controller, dt, rtol, args.frames, integrator, extra))
                    r, info = cached("accuracy", {"config": plain, "reference_config": ref_plain}, compute, args.cache)
                    r["cache"] = {k: info.get(k) for k in ("hit", "hash", "date", "source_hash")}
                    rows.append(r)
                    print(f"{scene} {controller} {integrator} dt {dt} rtol {rtol:g}: rms {r['rms_rel']:.2e} L, max {r['max_rel']:.2e} L, "
                          f"{r['seconds_per_sim_second']:.2f} s/sim-s, its {r['iterations_mean']:.2f}"
                          f"{' (' + describe(info) + ')' if info['hit'] else ''}", flush=True)
            front = pareto(rows)
            recs[(scene, controller)] = {}
            for b in args.budget:
                ok = [r for r in front if r["rms_rel"] <= b]
                recs[(scene, controller)][b] = min(ok, key=lambda r: r["seconds_per_sim_second"]) if ok else None
            refs[f"{scene}/{controller}"] = {"config_hash": config_hash(ref_plain),
                                             "cache": ({k: ref_box["info"].get(k) for k in ("hit", "hash", "date")}
                                                       if ref_box else None)}
            all_rows += rows
    md = header("Run time against error" + (f" with {', '.join(f'`{e}`' for e in extra)}" if extra else ""))
    if extra:
        md += f"Every run, the reference's included, with the overrides {', '.join(f'`{e}`' for e in extra)}.  "
    md += (f"Reference: `{args.ref_integrator}`, dt = {args.ref_dt} s, rtol = 1e-9 (Newton and SQP, every stage: `solver.stage_rtol_factor=1`); integrators "
           f"of the grid: {', '.join(f'`{i}`' for i in args.integrators)}; errors are vertex distances to it at every "
           "output frame, over the hair length L; cost is the steps' seconds per simulated second (set-up and the settle phase excluded); `*` marks the Pareto front "
           f"(RMS error against cost).  Recommended, per error budget: the cheapest front run with RMS error <= "
           f"{', '.join(f'{b:g}' for b in args.budget)} L.  "
           "Every row states its run's config hash; source `fresh` = run by this command, `cached <date>` = "
           "reused from reports/cache/accuracy/ (`--cache`: same config, reference config, solver source and "
           "versions), and then its cost is that of the original run on that date.\n\n")
    for scene in args.scenes:
        for controller in args.controllers:
            rows = [r for r in all_rows if r["scene"] == scene and r["controller"] == controller]
            ref = refs[f"{scene}/{controller}"]
            rsrc = ("not needed (every grid row cached)" if ref["cache"] is None else
                    describe(ref["cache"]))
            md += f"## {scene}, {controller}\n\nReference config hash `{ref['config_hash']}`: {rsrc}.\n\n"
            md += md_table(["integrator", "dt", "rtol", "RMS err / L", "max err / L", "s per sim-s", "iterations", "converged",
                            "max stretch", "max residual / L", "front", "config hash", "source"])
            for r in rows:
                md += md_row([f"`{r.get('integrator', 'implicit_euler')}`", r["dt"], f"{r['rtol']:g}", f"{r['rms_rel']:.2e}", f"{r['max_rel']:.2e}",
                              f"{r['seconds_per_sim_second']:.2f}", f"{r['iterations_mean']:.2f}",
                              f"{r['converged_fraction']:.3f}", f"{r['stretch_max']:.2e}", fmt(r["residual_rel_max"], ".1e"),
                              "*" if r["pareto"] else "", f"`{r['config_hash']}`", describe(r["cache"])])
            md += "\nRecommended:\n\n" + "".join(f"* RMS <= {b:g} L: {recommendation(rec)}\n"
                                                  for b, rec in recs[(scene, controller)].items()) + "\n"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(args.scenes), figsize=(5.5 * len(args.scenes), 4), squeeze=False)
        for ax, scene in zip(axes[0], args.scenes):
            for controller, mk in [(c, m) for c, m in (("free", "o"), ("tracking", "s")) if c in args.controllers]:
                for integrator, fill in zip(args.integrators, ("full", "none", "left", "right")):
                    rows = [r for r in all_rows if r["scene"] == scene and r["controller"] == controller
                            and r.get("integrator") == integrator]
                    ax.loglog([r["seconds_per_sim_second"] for r in rows], [r["rms_rel"] for r in rows], mk,
                              fillstyle=fill, alpha=0.7, label=f"{controller}, {integrator}")
                rows = [r for r in all_rows if r["scene"] == scene and r["controller"] == controller]
                fr = sorted((r for r in rows if r["pareto"]), key=lambda r: r["seconds_per_sim_second"])
                ax.loglog([r["seconds_per_sim_second"] for r in fr], [r["rms_rel"] for r in fr], "-")
            ax.set(title=scene, xlabel="wall s per simulated s", ylabel="RMS error / hair length")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend()
        fig.tight_layout()
        fig.savefig(ROOT / "reports" / f"{args.report}.png", dpi=110)
        md += f"![Pareto]({args.report}.png)\n"
    except ImportError:
        md += "(matplotlib is not installed: no plot)\n"
    path = write_report(args.report, md, {"rows": all_rows, "recommended": {f"{k[0]}/{k[1]}": {f"{b:g}": r for b, r in v.items()}
                                                                         for k, v in recs.items()},
                                         "references": refs, "ref_dt": args.ref_dt, "budget": args.budget,
                                         "set": list(extra)})
    print(f"wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
