"""The paper's scenes (section 4) as full experiments, judged: writes reports/paper_scenes.{md,json}.

Each experiment runs all its variants (free and tracked, or one per guide count or variance
target) exactly as ``python -m hairexp experiment=<name>`` does, into outputs/paper_scenes/<name>/,
and the report tabulates every variant's measure, iterations, step time, stretch and residual,
and the judge's verdict.
With ``--cache`` a scene whose composed config, solver source (hairexp/**/*.py, conf/**/*.yaml)
and torch/numpy/scipy versions match an entry of reports/cache/paper_scenes/ is not run again: its
figures (and timings) are those of the cached run, and the report says so with the entry's date and
hash; no run folder is written for it.  Without ``--cache`` every scene runs fresh and refreshes
its entry.
Usage: python -m experiments.paper_scenes [names ...] [--cache] [--set KEY=VALUE ...] [--report NAME]
       (default: every paper scene)
"""

from __future__ import annotations

import argparse
import json
import time

from hairexp.app.assemble import check_config
from hairexp.app.config import to_plain
from hairexp.app.experiment import run_experiment
from hairexp.app.report import header, write_report
from hairexp.app.report_cache import cached, describe

from experiments.common import (add_report_option, ROOT, check_reports, compose, experiment_names, fail, fmt, key_value, md_row,
                                md_table)
from experiments.scene_pictures import render_key_moment

SCENES = ["goaling", "splitting", "spreading", "stylization", "celia", "fanning"]
#: measure keys shown in the table, per measure
SHOW = {"collider_contact": ("hit", "contacts", "min_distance", "first_hit_time"),
        "clumps": ("clumps", "clump_sizes"),
        "tip_variance": ("cluster_variance_ratio", "cluster_target_ratio", "tip_variance_ratio", "apex_time"),
        "block_rail": ("travel", "left_rail", "left_rail_time"),
        "fan": ("clumps", "gap_ratio_max", "spread")}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("names", nargs="*", default=None)
    add_report_option(ap, "paper_scenes")
    ap.add_argument("--cache", action="store_true",
                    help="reuse reports/cache/paper_scenes/ entries with the same config, solver source and versions")
    ap.add_argument("--set", nargs="*", default=[], type=key_value, metavar="KEY=VALUE",
                    help="hydra overrides applied to every scene (e.g. frames=10)")
    args = ap.parse_args(argv)
    launch = [o for o in args.set if o.lstrip("+~").startswith(("hydra.", "overwrite="))]
    if launch:   # taken and ignored (independent probe of issue 12, round 21)
        ap.error(f"--set {' '.join(launch)}: the scenes run in outputs/paper_scenes/<name>/, replaced each time; "
                 "hydra.* and overwrite are a command line's keys")
    names = experiment_names(ap, args.names, SCENES)
    check_reports(ap, args.report)
    md = header("The paper's scenes, judged")
    md += ("Each experiment runs its variants as `python -m hairexp experiment=<name>` does; `success` is the "
           "judge's verdict on the scene's measure (README, \"Paper scenes\").  Every scene and variant states the "
           "config hash its run records.  A scene marked *cached* was not run by this command: its figures, wall "
           "and step times are those of the original run on the cache date (`--cache`, same config, solver source "
           "and versions).\n\n")
    if args.set:
        md += "Overrides on every scene: " + ", ".join(f"`{o}`" for o in args.set) + "\n\n"
    data, cfgs = {}, {}
    for name in names:   # every scene's config (and the --set overrides) checked before the first runs
        try:
            cfgs[name] = compose([f"experiment={name}", "logging.progress=false", *args.set])
            check_config(cfgs[name])
        except Exception as exc:   # hydra's composition errors, the schema's, InputError
            ap.error(f"experiment {name} with --set {' '.join(args.set)}: {exc}")
    failed = []
    for name in names:
        cfg = cfgs[name]
        out = ROOT / "outputs" / "paper_scenes" / name
        t0 = time.perf_counter()

        def compute(cfg=cfg, out=out):
            t0 = time.perf_counter()
            s = run_experiment(cfg, out)
            res = {k: s[k] for k in ("status", "success", "judge", "verdict", "variants", "config_hash") if k in s}
            res["wall_seconds"] = time.perf_counter() - t0
            res["measure"] = str(s["config"]["measure"]["name"])
            res.setdefault("variants", {})
            for vname, v in res["variants"].items():  # each variant's own run config hash
                v["config_hash"] = json.loads((out / vname / "summary.json").read_text()).get("config_hash")
            return res

        try:
            s, info = cached("paper_scenes", {"config": to_plain(cfg)}, compute, args.cache,
                             store=lambda r: r.get("status") != "failed")
        except Exception as exc:  # report the failure, go on with the other scenes
            print(f"{name}: FAILED: {exc}", flush=True)
            failed.append(name)
            data[name] = {"status": "failed", "error": str(exc)}
            md += f"## {name}\n\n**failed**: {exc}\n\n"
            continue
        wall = s["wall_seconds"]
        here = time.perf_counter() - t0
        keys = SHOW.get(s["measure"], ())
        data[name] = {**s, "cache": {k: info.get(k) for k in ("hit", "hash", "date", "source_hash")},
                      "command_seconds": here}
        src = describe(info)
        print(f"{name}: success={s['success']} ({wall:.0f} s{', ' + src if info['hit'] else ''}; "
              f"this command {here:.1f} s)", flush=True)
        md += (f"## {name}\n\nsuccess: **{s['success']}** (judge `{s['judge']}`), wall {wall:.0f} s"
               f"{' (of the original run)' if info['hit'] else ''}, config hash `{s['config_hash']}`; "
               f"{'**' + src + '**' if info['hit'] else 'run fresh by this command'}\n\n")
        md += md_table(["variant", *keys, "iterations mean/max", "converged", "median s/step", "max stretch",
                        "max residual / L", "config hash"])
        order = [str(v.name) for v in cfg.variants]   # the experiment's order (a cache entry's JSON is key-sorted)
        for vname in sorted(s["variants"], key=lambda n: order.index(n) if n in order else len(order)):
            v = s["variants"][vname]
            m = v["measures"]
            md += md_row([vname, *(fmt(m.get(k), ".4g") for k in keys),
                          f"{v['iterations_mean']:.2f} / {v['iterations_max']}", f"{v['converged_fraction']:.3f}",
                          f"{v['step_seconds_median']:.4f}", f"{v['stretch_max']:.3g}", fmt(v["residual_rel_max"], ".4g"),
                          f"`{v.get('config_hash')}`"])
        md += "\n"
        png = ROOT / "reports" / args.report / f"{name}.png"   # beside the report, named as it is
        if not info["hit"]:   # a fresh run: its picture at the key moment (experiments/scene_pictures.py)
            png.parent.mkdir(parents=True, exist_ok=True)
            pic = render_key_moment(out, png)
            data[name]["picture"] = {k: pic[k] for k in ("frame", "time", "axis")} | {"key": pic["key"]}
        if png.is_file():
            md += (f"![{name} at its key moment]({args.report}/{name}.png)\n\n"
                   f"{'Picture of the run above' if not info['hit'] else 'Picture of an earlier fresh run'}: "
                   "the variants at the key moment, from `result.npz` (`experiments/scene_pictures.py`); "
                   f"the variants side by side in rerun: `outputs/paper_scenes/{name}/comparison.rrd`.\n\n")
    if names and len(failed) == len(names):   # nothing to report: the committed report stays as it was
        return fail(f"every scene failed ({', '.join(failed)}: see above); reports/{args.report}.md/.json left as "
                    "they were")
    path = write_report(args.report, md, {"scenes": data})
    print(f"wrote {path}")
    if failed:
        return fail(f"{len(failed)} of {len(names)} scenes failed: {', '.join(failed)} (recorded as failed in the report)")
    return 0


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
