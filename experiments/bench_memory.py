"""Peak memory of whole runs against their length (issue 12: "memory at 3,000 frames no higher
than at 200 frames, beyond the fixed model").

Each measurement is one ``python -m hairexp`` process (the command a user runs) of the same
config at SHORT and at LONG frames: goaling's scene, small (``experiment=goaling_smoke
variants=[]``: the free controller, simulated guides with an edit), the recording off and on,
and a second hair size so that the per-frame data (24 bytes a vertex a frame) is large against
the process itself.  Two figures per process:

* peak resident set size, read from the kernel when the child ends (``os.wait4``: ``ru_maxrss``):
  what the machine must have;
* (``--traced``) the peak of the Python heap (tracemalloc, in separate runs through
  experiments/traced_run.py: tracing costs time and memory of its own), numpy arrays included.

A first, untimed run fills the checkout's compile caches.  Every (hair, recording, frames) case
runs ``--repeats`` times, the cases interleaved (SHORT,
LONG, SHORT, LONG, ...) so that a drift of the machine touches both lengths alike.  Growth is
median(LONG) - median(SHORT); the noise is the spread (max - min) of the repeats of one case, the
larger of the two lengths'.  A growth within the noise is no growth that this can see.

Prints and writes reports/bench_memory.{md,json}.
Usage:  python -m experiments.bench_memory [--frames 200 3000] [--repeats 3] [--traced]
        [--sizes ...] [--rerun off on] [--repo PATH] [--report NAME]
(``--repo``: run another checkout's code, e.g. an older commit's worktree, for a before/after.)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

from hairexp.app.report import header, write_report

from experiments.common import add_report_option, ROOT, check_reports, md_table, positive_int, run_child

SIZES = {"6 x 10 vertices": ["scene.n_strands=6", "scene.n_vertices=10"],
         "40 x 20 vertices": ["scene.n_strands=40", "scene.n_vertices=20"]}
TRACED_RUN = Path(__file__).resolve().parent / "traced_run.py"


def spread(values: list[float]) -> float:
    return max(values) - min(values) if values else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=positive_int, nargs=2, default=[200, 3000], metavar=("SHORT", "LONG"))
    ap.add_argument("--repeats", type=positive_int, default=3, help="runs of each case (default 3)")
    ap.add_argument("--traced", action="store_true", help="also the Python heap's peak (tracemalloc), one run a case")
    ap.add_argument("--repo", type=Path, default=ROOT, help="the checkout whose code runs (default: this one)")
    ap.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    ap.add_argument("--rerun", nargs="+", choices=["off", "on"], default=["off", "on"], help="recording off / on")
    add_report_option(ap, "bench_memory")
    args = ap.parse_args(argv)
    if args.frames[0] >= args.frames[1]:
        ap.error(f"--frames {args.frames[0]} {args.frames[1]}: SHORT must be less than LONG")
    repo = args.repo.resolve()
    if not (repo / "hairexp" / "__main__.py").is_file():
        ap.error(f"--repo {repo}: not a hairexp checkout (no hairexp/__main__.py)")
    check_reports(ap, args.report)
    env = dict(os.environ, PYTHONPATH=str(repo))
    short, long_ = args.frames
    rows, results = [], []
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        def hairexp_args(size, rerun, frames, out):
            return ["experiment=goaling_smoke", "variants=[]", *SIZES[size], f"frames={frames}",
                    f"logging.rerun={'true' if rerun == 'on' else 'false'}", "logging.progress=false",
                    f"hydra.run.dir={out}"]

        # one untimed run first: it fills the checkout's compile caches (numba's, in __pycache__), whose
        # first build raised that run's peak by 150 MB in a fresh worktree
        warm = Path(tmp) / "warm-up"
        run_child([sys.executable, "-m", "hairexp", *hairexp_args(args.sizes[0], args.rerun[-1], short, warm)], repo, env)
        print(f"warm-up run done ({short} frames, untimed)", flush=True)
        for size in args.sizes:
            for rerun in args.rerun:
                peaks = {short: [], long_: []}
                traced = {}
                for rep in range(args.repeats):
                    for frames in (short, long_):
                        out = Path(tmp) / f"{len(results)}"
                        cmd = [sys.executable, "-m", "hairexp", *hairexp_args(size, rerun, frames, out)]
                        mb, wall = run_child(cmd, repo, env)
                        peaks[frames].append(mb)
                        results.append({"hair": size, "rerun": rerun, "frames": frames, "repeat": rep,
                                        "peak_rss_mb": mb, "wall_s": wall, "command": " ".join(cmd[1:])})
                        print(f"{size:>18}  rerun {rerun:3}  {frames:5d} frames  run {rep + 1}: peak {mb:7.1f} MB  "
                              f"({wall:.0f} s)", flush=True)
                if args.traced:
                    for frames in (short, long_):
                        out = Path(tmp) / f"t{len(results)}"
                        js = Path(tmp) / f"t{len(results)}.json"
                        cmd = [sys.executable, str(TRACED_RUN), str(js), *hairexp_args(size, rerun, frames, out)]
                        _, wall = run_child(cmd, repo, env)
                        t = json.loads(js.read_text())
                        traced[frames] = t["traced_peak"] / 2 ** 20
                        results.append({"hair": size, "rerun": rerun, "frames": frames, "traced": True,
                                        "traced_peak_mb": traced[frames], "traced_end_mb": t["traced_end"] / 2 ** 20,
                                        "wall_s": wall, "command": " ".join(cmd[1:])})
                        print(f"{size:>18}  rerun {rerun:3}  {frames:5d} frames  traced: Python heap peak "
                              f"{traced[frames]:7.2f} MB ({wall:.0f} s)", flush=True)
                ms, ml = statistics.median(peaks[short]), statistics.median(peaks[long_])
                noise = max(spread(peaks[short]), spread(peaks[long_]))
                row = [size, rerun, " / ".join(f"{v:.1f}" for v in peaks[short]),
                       " / ".join(f"{v:.1f}" for v in peaks[long_]), f"{ml - ms:+.1f}", f"{noise:.1f}"]
                if args.traced:
                    row.append(f"{traced[short]:.2f} / {traced[long_]:.2f} ({traced[long_] - traced[short]:+.2f})")
                rows.append(row)
    md = header("Peak memory against run length")
    md += (f"Code: `{repo}`.  Each row: `python -m hairexp experiment=goaling_smoke variants=[]` (free controller, "
           f"simulated guides with an edit) with the hair size and recording shown, {args.repeats} runs at each "
           f"length (interleaved); peak resident set size of the process (`ru_maxrss`, MB).  Growth: median "
           f"at {long_} frames minus median at {short}; noise: the largest spread (max - min) of one case's "
           "repeats.\n\n")
    cols = ["hair", "recording", f"{short} frames (MB)", f"{long_} frames (MB)", "growth (MB)", "noise (MB)"]
    if args.traced:
        cols.append("Python heap peak, short / long (MB)")
    md += md_table(cols, rows)
    path = write_report(args.report, md, {"repo": str(repo), "frames": args.frames, "repeats": args.repeats,
                                             "results": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
