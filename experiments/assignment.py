"""Hard against soft hair-to-guide assignment (tracking.assignment; paper section 5 / Fig. 8) on
the paper's goaling, splitting and celia scenes (and fanning): writes reports/assignment.{md,json}.

Each scene's experiment config is run with its variants, every tracked variant twice: with
``tracking.assignment=hard`` (``<variant>_hard``) and ``soft`` (``<variant>_soft``), the free
variant once; no judge (the measures are tabulated instead).  Per run: the scene's measure
(hit, clumps), the cohesion summary every run writes (single-linkage clumps of the strands'
lower halves at 3 cm per frame: the most clumps, the frames with more than one, the widest gap),
the largest tracking residual over the hair length, the SQP iterations (mean / max) and the
converged fraction.  Runs go into outputs/assignment/<scene>/.
Usage: python -m experiments.assignment [scenes ...] [--set KEY=VALUE ...] [--report NAME]
       (default: goaling splitting celia)
"""

from __future__ import annotations

import argparse
import time

from omegaconf import OmegaConf

from hairexp.app.assemble import check_config
from hairexp.app.config import VariantConfig
from hairexp.app.experiment import run_experiment
from hairexp.app.report import header, write_report

from experiments.common import add_report_option, ROOT, check_reports, check_set, compose, experiment_names, fmt, key_value, md_row, md_table

SCENES = ["goaling", "splitting", "celia"]


def assignment_variants(cfg, modes=("hard", "soft")) -> list[dict]:
    """The experiment's variants with each tracked one once per assignment ``modes``."""
    out = []
    for v in cfg.variants:
        ov = list(v.overrides)
        if "controller.name=free" in ov:
            out.append({"name": str(v.name), "overrides": ov})
            continue
        for m in modes:
            out.append({"name": f"{v.name}_{m}", "overrides": [*ov, f"tracking.assignment={m}"]})
    return out


def run_scene(name: str, extra=(), root=None) -> dict:
    cfg = compose([f"experiment={name}", "logging.progress=false", "logging.rerun=false", *extra])
    variants = assignment_variants(cfg)
    cfg.variants = [OmegaConf.structured(VariantConfig(**v)) for v in variants]
    cfg.judge = "none"
    check_config(cfg)
    out = (root or ROOT / "outputs" / "assignment") / name
    t0 = time.perf_counter()
    s = run_experiment(cfg, out)
    rows = {}
    for vname, v in s["variants"].items():
        m, c = v["measures"], v.get("cohesion") or {}
        rows[vname] = {"hit": m.get("hit"), "min_distance": m.get("min_distance"), "clumps_at_time": m.get("clumps"),
                       "clump_sizes": m.get("clump_sizes"),
                       "clumps_max": c.get("clumps_max"), "split_frames": c.get("split_frames"),
                       "frames": c.get("frames"), "clumps_last": c.get("clumps_last"),
                       "widest_gap_max": c.get("widest_gap_max"), "widest_gap_time": c.get("widest_gap_time"),
                       "residual_rel_max": v.get("residual_rel_max"), "iterations_mean": v.get("iterations_mean"),
                       "iterations_max": v.get("iterations_max"), "converged_fraction": v.get("converged_fraction"),
                       "step_seconds_median": v.get("step_seconds_median")}
    blend = float(cfg.tracking.blend_width)
    return {"variants": rows, "wall_seconds": time.perf_counter() - t0, "blend_width": blend,
            "order": [v["name"] for v in variants]}


def iteration_ratios(rows: dict) -> dict:
    """soft / hard mean SQP iterations per tracked variant."""
    out = {}
    for n, r in rows.items():
        if n.endswith("_soft") and n[:-5] + "_hard" in rows:
            h = rows[n[:-5] + "_hard"]["iterations_mean"]
            out[n[:-5]] = r["iterations_mean"] / h if h else None
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=None)
    ap.add_argument("--set", nargs="*", default=[], type=key_value, metavar="KEY=VALUE", help="hydra overrides on every scene")
    add_report_option(ap, "assignment")
    args = ap.parse_args(argv)
    check_set(ap, args.set)   # before anything runs (a bad key would fail every run)
    check_reports(ap, args.report)
    names = experiment_names(ap, args.scenes, SCENES)
    md = header("Hard and soft hair-to-guide assignment")
    md += ("Each scene's variants run as `python -m hairexp experiment=<name>` runs them, every tracked variant "
           "with `tracking.assignment=hard` and `soft` (README \"Soft assignment\"); no judge.  Columns: the "
           "scene's measure (wheel or goblet hit; splitting: clumps at 2.4 s at 3 cm, clumps of >= 10 % of the "
           "strands), the cohesion summary of every run (single-linkage clumps of the strands' lower halves at "
           "3 cm in each frame: the most clumps, the frames with more than one, the widest gap over the run), "
           "the largest tracking residual over the hair length (its peaks are collision frames, where the "
           "collision stage moves vertices after the SQP), and the SQP (Newton for free runs) iterations per step.\n\n")
    if args.set:
        md += "Overrides on every scene: " + ", ".join(f"`{o}`" for o in args.set) + "\n\n"
    data = {}
    for name in names:
        r = run_scene(name, args.set)
        data[name] = r
        ratios = iteration_ratios(r["variants"])
        r["iteration_ratio_soft_hard"] = ratios
        md += f"## {name}\n\nblend width {r['blend_width']} m, wall {r['wall_seconds']:.0f} s\n\n"
        md += md_table(["variant", "hit", "clumps (measure)", "clumps max", "split frames", "widest gap (cm)",
                        "max residual / L", "iterations mean / max", "converged"])
        print(f"== {name} (blend width {r['blend_width']} m)")
        for vname in r["order"]:
            v = r["variants"][vname]
            gap = None if v["widest_gap_max"] is None else 100 * v["widest_gap_max"]
            cells = [vname, fmt(v["hit"]), fmt(v["clumps_at_time"]), fmt(v["clumps_max"]),
                     f"{v['split_frames']} / {v['frames']}", fmt(gap, ".3g"), fmt(v["residual_rel_max"], ".3g"),
                     f"{v['iterations_mean']:.2f} / {v['iterations_max']}", f"{v['converged_fraction']:.3f}"]
            md += md_row(cells)
            print("  " + "  ".join(str(c) for c in cells), flush=True)
        md += "\n" + "soft / hard mean iterations: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()) + "\n\n"
        print("  soft/hard iterations: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()), flush=True)
    path = write_report(args.report, md, {"scenes": data})
    print(f"wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
