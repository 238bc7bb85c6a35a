"""Scale (validation issue, part 5): time per step and peak memory against the number of strands.

Ponytails of 30, 100, 301, 1000 and 3000 strands x 26 vertices (the root disk grows with
sqrt(strands), so the density stays that of Celia), free and tracked (3 simulated guides x 8
tracking points), dt = 0.04 s.  The head jerks up 12 cm in 0.1 s at t = 0.2 s; steps 1-2 are
warm-up (torch.compile builds its kernels, ``solver.compile=on`` at every size so that the
sizes are comparable), then 10 steps are timed.  Each size and controller runs in its own
process, whose peak resident memory (``ru_maxrss``) is reported next to the memory before the
scene was built.  Target: cost linear in the strands, 3000 strands <= 12 x the time of 301.
Writes reports/bench_scale.{md,json,png}.
Usage: .venv/bin/python experiments/bench_scale.py [--sizes 30 100 301 1000 3000] [--steps 10]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

MOTION = ["scene.motion.interpolation=linear", "scene.motion.times=[0.0,0.2,0.3,10.0]",
          "scene.motion.translations=[[0.0,0.0,0.0],[0.0,0.0,0.0],[0.0,0.12,0.0],[0.0,0.12,0.0]]",
          "scene.motion.rotations_deg=[[0.0,0.0,0.0],[0.0,0.0,0.0],[0.0,0.0,0.0],[0.0,0.0,0.0]]"]


def one(n: int, controller: str, steps: int) -> dict:
    """Runs in a child process: returns the figures of one size and controller."""
    from hairexp.app.config import compose_config
    from hairexp.physics.simulator import Simulator
    from hairexp.app.builders import build_scene
    from hairexp.app.guides import build_guides

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    radius = 0.025 * float(np.sqrt(n / 301.0))
    cfg = compose_config([
        "experiment=celia", "variants=[]", "scene.colliders=[]", f"scene.n_strands={n}", f"scene.root_radius={radius}",
        "solver.compile=on", f"controller.name={controller}", "frames=8", *MOTION])
    scene = build_scene(cfg.scene)
    tracked = controller == "tracking"
    guides = build_guides(cfg, scene, 8, cfg.fps) if tracked else None
    sim = Simulator(scene, cfg.solver, cfg.tracking if tracked else None, guides, cfg.collision)
    st = sim.initial_state()
    for _ in range(2):
        st, _ = sim.step(st, 0.04)
    rows = []
    for _ in range(steps):
        t0 = time.perf_counter()
        st, info = sim.step(st, 0.04)
        rows.append((time.perf_counter() - t0, info.iterations))
    a = np.array(rows)
    return {"strands": n, "vertices": int(scene.strands.n_vertices), "controller": controller,
            "median_s": float(np.median(a[:, 0])), "mean_s": float(a[:, 0].mean()), "iterations_mean": float(a[:, 1].mean()),
            "rss_before_mb": rss0, "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[30, 100, 301, 1000, 3000])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--one", nargs=2, metavar=("STRANDS", "CONTROLLER"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(int(args.one[0]), args.one[1], args.steps)))
        return
    from hairexp.app.report import header, write_report

    res = []
    for controller in ("free", "tracking"):
        for n in args.sizes:
            proc = subprocess.run([sys.executable, __file__, "--one", str(n), controller, "--steps", str(args.steps)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                print(proc.stderr[-2000:], file=sys.stderr)
                raise SystemExit(f"{controller} {n} strands failed")
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            res.append(r)
            print(f"{controller:>8} {n:5d} strands: median {1e3 * r['median_s']:8.1f} ms/step, {r['iterations_mean']:.2f} its, "
                  f"peak RSS {r['rss_peak_mb']:.0f} MB (before the scene {r['rss_before_mb']:.0f} MB)", flush=True)
    ratio = {}
    for c in ("free", "tracking"):
        by = {r["strands"]: r for r in res if r["controller"] == c}
        if 301 in by and 3000 in by:
            ratio[c] = by[3000]["median_s"] / by[301]["median_s"]
    md = header("Scale: time per step and peak memory against the number of strands")
    md += ("Ponytails of N strands x 26 vertices (root disk radius 2.5 cm x sqrt(N / 301)), free and tracked "
           f"(3 simulated guides x 8 points), dt = 0.04 s, compiled kernels at every size; {args.steps} steps timed after "
           "2 warm-up steps, the head jerking up at 0.2 s; one process per row.\n\n")
    md += "| controller | strands | vertices | median s/step | per strand (ms) | iterations | peak RSS MB | RSS before the scene MB |\n"
    md += "|---|---|---|---|---|---|---|---|\n"
    for r in res:
        md += (f"| {r['controller']} | {r['strands']} | {r['vertices']} | {r['median_s']:.4f} | "
               f"{1e3 * r['median_s'] / r['strands']:.3f} | {r['iterations_mean']:.2f} | {r['rss_peak_mb']:.0f} | "
               f"{r['rss_before_mb']:.0f} |\n")
    for c, q in ratio.items():
        md += f"\n{c}: 3000 strands take **{q:.1f}x** the time of 301 (target <= 12x: **{'met' if q <= 12 else 'missed'}**)."
    md += "\n\n![time per step](bench_scale.png)\n"
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
        fig.savefig(ROOT / "reports" / "bench_scale.png", dpi=110)
    except ImportError:
        md += "\n(matplotlib is not installed: no plot)\n"
    path = write_report("bench_scale", md, {"results": res, "ratio_3000_over_301": ratio, "target": 12})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
