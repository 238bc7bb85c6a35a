"""Ablations as Hydra sweeps (validation issue, part 3): reports/ablations.{md,json}.

For each scene and each comparison, one ``python -m hairexp -m`` sweep (the default joblib
launcher, 2 processes; ``--launcher submitit_local`` runs the same sweeps with submitit) over
the tracked controller (``variants=[] controller.name=tracking``):

* targets: ``tracking.targets=static,sliding`` (paper 3.2);
* variance: ``tracking.variance.stiffness=0,<on>`` (paper 3.3; on = the scene's value, or 5);
* hessian: ``solver.stretch_hessian=primal_dual,penalty`` (how the stretch Hessian is made PSD);
* collisions: ``collision.objects=false,true``;
* contact: ``collision.contact=stage,barrier`` (object contact after the solve, its contacts
  solved again as penalty planes by default, or inside the solve as an IPC barrier,
  hairexp/physics/barrier.py; issue 14);
* planes: ``collision.resolve=false,true`` (the post-solve stage alone, no strain limiter, or its
  contacts solved again as penalty planes, hairexp/physics/contact_planes.py; issue 14);
* line search: ``tracking.nonmonotone=1,5`` (the SQP's monotone or non-monotone merit search).

The table gives each run's iterations, converged fraction, step time, stretch, residual and
the scene's measure.  Scenes default to the small ``*_smoke`` ones (a few minutes in all);
``--full`` uses the full scenes and writes reports/ablations_full.{md,json} instead; ``--report NAME``
writes reports/NAME.{md,json}.
Usage: python -m experiments.ablations [--full] [--scenes goaling spreading ...] [--launcher submitit_local] [--report NAME]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from experiments.common import add_report_option, ROOT, check_reports, fail, fmt, md_row, md_table

COMPARISONS = {
    "targets": ["tracking.targets=static,sliding"],
    "variance": ["tracking.variance.stiffness=0.0,5.0"],
    "hessian": ["solver.stretch_hessian=primal_dual,penalty"],
    "collisions": ["collision.objects=false,true"],
    "contact": ["collision.contact=stage,barrier"],
    "planes": ["collision.resolve=false,true"],
    "line_search": ["tracking.nonmonotone=1,5"],
}
SCENES = ["goaling", "splitting", "spreading", "stylization", "celia"]


#: Hydra's launchers installed with the project, and the project's own (conf/hydra/launcher/)
LAUNCHERS = ["basic", "joblib", "submitit_local", "submitit_slurm",
             *sorted(p.stem for p in (ROOT / "conf" / "hydra" / "launcher").glob("*.yaml"))]


def sweep(scene: str, comparison: str, launcher: str | None, out: Path) -> list[dict]:
    args = [sys.executable, "-m", "hairexp", "-m", f"experiment={scene}", "variants=[]", "controller.name=tracking",
            "logging=off", f"hydra.sweep.dir={out}", *COMPARISONS[comparison]]
    if comparison == "variance" and scene.startswith("spreading"):
        args.append("tracking.variance.target_scale=[5.0,5.0,5.0,5.0]")
    if launcher:
        args.append(f"hydra/launcher={launcher}")
    proc = subprocess.run(args, capture_output=True, text=True, cwd=ROOT)
    rows = []
    for d in sorted(p for p in (out.iterdir() if out.is_dir() else ()) if p.is_dir() and p.name.isdigit()):
        f = d / "summary.json"
        s = json.loads(f.read_text()) if f.is_file() else {"status": "missing"}
        over = (d / ".hydra" / "overrides.yaml").read_text() if (d / ".hydra" / "overrides.yaml").is_file() else ""
        value = [ln.split("=", 1)[1].strip() for ln in over.splitlines()
                 if COMPARISONS[comparison][0].split("=")[0] in ln]
        rows.append({"scene": scene, "comparison": comparison, "value": value[0] if value else d.name,
                     "status": s.get("status"), "error": s.get("error"),
                     **{k: s.get(k) for k in ("iterations_mean", "iterations_max", "converged_fraction",
                                              "step_seconds_median", "stretch_max", "residual_rel_max")},
                     "measures": s.get("measures", {})})
    if proc.returncode != 0 and not rows:
        rows.append({"scene": scene, "comparison": comparison, "value": "-", "status": "failed",
                     "error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "?"})
    return rows


def findings(rows: list[dict]) -> str:
    """Per scene and comparison, the second value against the first (the table's two rows):
    iteration ratio, stretch and residual, computed from the rows (no typed-in numbers)."""
    out = "\n## Findings (second value against first, per scene)\n\n"
    out += md_table(["comparison", "scene", "iterations mean", "max stretch", "max residual / L", "measure"])
    for comp in COMPARISONS:
        for scene in dict.fromkeys(r["scene"] for r in rows):
            pair = [r for r in rows if r["scene"] == scene and r["comparison"] == comp and r.get("status") == "completed"]
            if len(pair) != 2:
                out += md_row([comp, scene, f"not comparable ({len(pair)} completed runs)", "", "", ""])
                continue
            a, b = pair
            ma, mb = a.get("measures") or {}, b.get("measures") or {}
            key = next((k for k in ("hit", "clumps", "cluster_variance_ratio", "left_rail") if k in ma), None)
            ita, itb = a.get("iterations_mean"), b.get("iterations_mean")
            ratio = f"{fmt(itb)} vs {fmt(ita)} ({itb / ita:.2f}x)" if ita and itb else "-"
            out += md_row([f"{comp}: {b['value']} vs {a['value']}", scene, ratio,
                           f"{fmt(b.get('stretch_max'))} vs {fmt(a.get('stretch_max'))}",
                           f"{fmt(b.get('residual_rel_max'))} vs {fmt(a.get('residual_rel_max'))}",
                           f"{key}: {fmt(mb.get(key))} vs {fmt(ma.get(key))}" if key else "-"])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--scenes", nargs="*", default=SCENES, choices=SCENES)
    ap.add_argument("--comparisons", nargs="*", default=list(COMPARISONS), choices=list(COMPARISONS))
    ap.add_argument("--launcher", default=None, choices=LAUNCHERS,
                    help="a Hydra launcher (default: conf/hydra/launcher/parallel.yaml, joblib with 2 jobs)")
    add_report_option(ap, None, default_text="ablations, with --full ablations_full")
    args = ap.parse_args(argv)
    report = args.report or ("ablations_full" if args.full else "ablations")
    check_reports(ap, report)
    from hairexp.app.report import header, write_report

    base = ROOT / "multirun" / "ablations" / time.strftime("%Y-%m-%d_%H-%M-%S")
    rows = []
    for scene in args.scenes:
        name = scene if args.full else f"{scene}_smoke"
        for comp in args.comparisons:
            t0 = time.perf_counter()
            r = sweep(name, comp, args.launcher, base / name / comp)
            rows += r
            print(f"{name} {comp}: " + "; ".join(f"{x['value']}: {x['status']}, its {fmt(x.get('iterations_mean'))}, "
                                                    f"stretch {fmt(x.get('stretch_max'))}" for x in r)
                  + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    failed = [f"{r['scene']} {r['comparison']} {r['value']} ({r['status']})" for r in rows if r.get("status") != "completed"]
    if rows and len(failed) == len(rows):   # nothing to compare: the committed report stays as it was
        return fail(f"no run completed ({len(failed)} failed, the first: {failed[0]}: {rows[0].get('error')}); "
                    f"reports/{report}.md/.json left as they were")
    md = header("Ablations (Hydra sweeps, tracked controller)")
    md += (f"Scenes: {'full' if args.full else 'smoke'} versions; launcher: {args.launcher or 'joblib (2 jobs)'}; each row is "
           "one run of the sweep `python -m hairexp -m experiment=<scene> variants=[] controller.name=tracking "
           "<comparison>`.\n\n")
    md += md_table(["scene", "comparison", "value", "status", "iterations mean/max", "converged", "median s/step",
                    "max stretch", "max residual / L", "measure"])
    for r in rows:
        m = r.get("measures") or {}
        key = next((k for k in ("hit", "clumps", "cluster_variance_ratio", "left_rail") if k in m), None)
        md += md_row([r["scene"], r["comparison"], r["value"], r["status"],
                      f"{fmt(r.get('iterations_mean'))} / {fmt(r.get('iterations_max'))}", fmt(r.get("converged_fraction")),
                      fmt(r.get("step_seconds_median")), fmt(r.get("stretch_max")), fmt(r.get("residual_rel_max")),
                      f"{key}={fmt(m[key])}" if key else "-"])
    md += findings(rows)
    path = write_report(report, md, {"rows": rows, "full": args.full, "launcher": args.launcher})
    print(f"wrote {path}")
    if failed:
        return fail(f"{len(failed)} of {len(rows)} runs did not complete: {', '.join(failed)} (recorded in the report)")
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
