"""The whole command's wall time (issue 16: ``python -m hairexp experiment=celia``, settle plus
both variants, in <= 15 s on the 2-core machine).

Each round runs the command as a user does, ``python -m hairexp experiment=<name>`` (a fresh
process: imports, Hydra's composition, the checks, the settle, the guide simulation, every
variant's steps, recordings, USD, metrics, the comparison), into a run folder of its own under a
temporary folder (``hydra.run.dir``), and one more fresh process that only imports the command
line (``import hairexp.app.cli``: the part of the wall before anything is read).  Per round: the
command's wall time and peak RSS (``os.wait4``: the largest single process; variants run side by side,
``variants_mode``, each have a process of their own, and their memory adds up), how many variants ran
at once, the experiment's own ``wall_seconds`` from its
``summary.json`` (from the folder's claim to the end), and per variant its steps' wall, median
step and SQP or Newton iterations a step.  ``--against PATH`` (another checkout, e.g. a
``git worktree`` at a base commit, run by this interpreter with its code first on PYTHONPATH)
runs the same command there in turn with this checkout, round by round (each of the two first
in every other round), so that both meet the same load of a shared machine: compare them by the
median of the rounds' ratios.  ``--warmup`` untimed runs of each checkout come first.  Runs
whose summary is not ``completed`` stop the script with their error.

Prints and writes reports/<REPORT>.{md,json} (default bench_experiment).
Usage: python -m experiments.bench_experiment [--experiment celia] [--rounds 3] [--warmup 1] [--against PATH]
       [--set KEY=VALUE ...] [--report NAME]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hairexp.app.report import header, write_report

from experiments.common import (add_report_option, ROOT, check_reports, check_set, experiment_names, key_value, md_table, nonnegative_int,
                                positive_int, run_child)

#: issue 16: the whole Celia experiment in at most this many seconds of wall time
TARGET_S = 15.0


def one_round(repo: Path, experiment: str, overrides: list[str], folder: Path) -> dict:
    """The command once in ``repo`` (its code first on PYTHONPATH) into ``folder``, and an
    import-only process (``common.run_child``: SystemExit with its error if either fails)."""
    env = dict(os.environ, PYTHONPATH=str(repo))
    rss, wall = run_child([sys.executable, "-m", "hairexp", f"experiment={experiment}", *overrides,
                           f"hydra.run.dir={folder}"], repo, env)
    summary_file = folder / "summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    if summary.get("status") != "completed":
        raise SystemExit(f"bench_experiment: the run in {repo} ended with status {summary.get('status')!r}: "
                         f"{summary.get('error')}")
    _, imports = run_child([sys.executable, "-c", "import hairexp.app.cli"], repo, env)
    variants = {}
    for name, v in (summary.get("variants") or {}).items():
        variants[name] = {k: v.get(k) for k in ("controller", "steps", "wall_seconds", "step_seconds_median",
                                                "iterations_mean", "iterations_max", "converged")}
    at_once = (summary.get("variants_at_once") or {}).get("at_once", 1)   # before 2026-12-07: always 1
    return {"wall_s": wall, "peak_rss_mb": rss, "experiment_wall_s": summary.get("wall_seconds"),
            "import_s": imports, "success": summary.get("success"), "variants": variants, "at_once": at_once}


def revision(repo: Path) -> str:
    """The checkout's commit (short hash, "+ changes" when its tree differs), or "unknown"."""
    try:
        rev = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "unknown") + (" + changes" if dirty else "")


def _median(rows: list[dict], key: str) -> float:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.median(vals)) if vals else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiment", default="celia", help="the experiment to run whole (default celia)")
    ap.add_argument("--rounds", type=positive_int, default=3, help="runs of the command (default 3)")
    ap.add_argument("--warmup", type=nonnegative_int, default=1,
                    help="untimed runs of each checkout first (default 1): numba compiles a kernel on its first call "
                         "in a checkout, and a kernel's 2-thread build only when solver.threads=auto first takes 2 "
                         "(a cold one cost a round 100 s)")
    ap.add_argument("--against", type=Path, default=None,
                    help="another checkout run in turn with this one, round by round (ratios)")
    ap.add_argument("--set", nargs="+", default=[], type=key_value, metavar="KEY=VALUE", help="overrides for every run")
    add_report_option(ap, "bench_experiment")
    args = ap.parse_args(argv)
    check_reports(ap, args.report)
    experiment_names(ap, [args.experiment], ())
    if any(o.split("=", 1)[0].lstrip("+~").startswith("hydra.") for o in args.set):
        ap.error("--set: hydra.* keys are the script's (each run gets a folder of its own)")
    check_set(ap, args.set, base=(f"experiment={args.experiment}",))   # before any run
    repos = {"this": ROOT}
    if args.against is not None:
        other = args.against.resolve()
        if not (other / "hairexp" / "__main__.py").is_file():
            ap.error(f"--against {other}: not a hairexp checkout (no hairexp/__main__.py)")
        repos["against"] = other
    revs = {k: revision(repo) for k, repo in repos.items()}
    rows = {k: [] for k in repos}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_experiment_") as tmp:
        for i in range(args.warmup):
            for key, repo in repos.items():
                r = one_round(repo, args.experiment, args.set, Path(tmp) / f"warmup_{key}_{i}")
                print(f"warm-up {i + 1} {key}: wall {r['wall_s']:.2f} s (not counted)", flush=True)
        for i in range(args.rounds):
            order = list(repos.items())
            for key, repo in (order if i % 2 == 0 else order[::-1]):   # neither always runs first
                r = one_round(repo, args.experiment, args.set, Path(tmp) / f"{key}_{i}")
                rows[key].append(r)
                per = ", ".join(f"{n} {v['steps']} steps median {1e3 * (v['step_seconds_median'] or 0):.1f} ms "
                                f"it {v['iterations_mean']:.2f}" for n, v in r["variants"].items())
                print(f"round {i + 1} {key}: wall {r['wall_s']:.2f} s (experiment {r['experiment_wall_s']:.2f} s, "
                      f"imports {r['import_s']:.2f} s, variants {r['at_once']} at once), peak "
                      f"{r['peak_rss_mb']:.0f} MB; {per}", flush=True)
    this = rows["this"]
    wall = _median(this, "wall_s")
    ok = wall <= TARGET_S if args.experiment == "celia" and not args.set else None
    md = header(f"The whole `experiment={args.experiment}` command")
    md += (f"Each round: `python -m hairexp experiment={args.experiment}{''.join(' ' + o for o in args.set)}` in a "
           f"fresh process into a run folder of its own (imports, composition, checks, settle, guides, every variant, "
           f"recordings, USD, metrics, comparison), then a fresh process that only imports the command line.  "
           f"{args.rounds} round{'s' if args.rounds > 1 else ''}" + (", this checkout and the other in turn" if len(repos) > 1 else "")
           + f", after {args.warmup} untimed run{'s' if args.warmup != 1 else ''} of each checkout (numba's caches).  "
           + "; ".join(f"{k}: `{repos[k]}` at {revs[k]}" for k in repos) + ".\n\n")
    head = ["checkout", "round", "wall (s)", "experiment's own (s)", "imports (s)", "variants at once",
            "peak RSS (MB)"]
    names = list(this[0]["variants"])
    for n in names:
        head += [f"{n}: median step (ms)", f"{n}: it/step"]
    table = []
    for key, rs in rows.items():
        for i, r in enumerate(rs):
            line = [key, str(i + 1), f"{r['wall_s']:.2f}", f"{r['experiment_wall_s']:.2f}", f"{r['import_s']:.2f}",
                    str(r["at_once"]), f"{r['peak_rss_mb']:.0f}"]
            for n in names:
                v = r["variants"].get(n, {})
                line += [f"{1e3 * (v.get('step_seconds_median') or float('nan')):.1f}",
                         f"{v.get('iterations_mean') or float('nan'):.2f}"]
            table.append(line)
    md += md_table(head, table) + "\n"
    md += (f"Median wall of this checkout: **{wall:.2f} s** (experiment's own {_median(this, 'experiment_wall_s'):.2f} s, "
           f"imports {_median(this, 'import_s'):.2f} s, peak {_median(this, 'peak_rss_mb'):.0f} MB)")
    if ok is not None:
        md += f"; issue 16's target <= {TARGET_S:g} s: **{'met' if ok else 'missed'}**"
    quickest = min(r["wall_s"] for r in this)
    md += (f".  Its quickest round: {quickest:.2f} s (the target is judged on the median; on a shared machine the "
           "quickest round is the nearest to the command on a quiet one).\n")
    ratios = None
    if len(repos) > 1:
        ratios = [a["wall_s"] / b["wall_s"] for a, b in zip(rows["this"], rows["against"])]
        md += (f"\nThis checkout / the other (`{repos['against']}`), round by round: "
               f"{', '.join(f'{x:.3f}' for x in ratios)}; median **{float(np.median(ratios)):.3f}**.\n")
    data = {"experiment": args.experiment, "overrides": args.set, "target_s": TARGET_S, "met": ok,
            "median_wall_s": wall, "quickest_wall_s": quickest, "rounds": rows, "ratios": ratios,
            "against": None if len(repos) == 1 else str(repos["against"]), "revisions": revs, "script_wall_s": time.perf_counter() - t0}
    path = write_report(args.report, md, data)
    verdict = "" if ok is None else f"; target {TARGET_S:g} s: {'met' if ok else 'MISSED'}"
    print(f"median wall {wall:.2f} s (quickest round {quickest:.2f} s){verdict}; wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
