"""Peak memory of whole runs against their length (issue: run folders; "memory flat in frames").

Each case is one ``python -m hairexp`` process (the command a user runs), its peak resident set
size read from the kernel when it ends (``os.wait4``: ``ru_maxrss``).  The scene is goaling's,
small (``experiment=goaling_smoke variants=[]``, tracked, simulated guides), at 200 and at
3,000 frames, with the recording off and on, and a second hair size so that the per-frame data
(positions written to result.npz / result.usdc, 24 bytes a vertex a frame) is large against the
process itself.

The difference between the 3,000- and the 200-frame run of the same hair is what grows with the
length of a run (README "Run folder" and "Benchmarks" say what is left of it and why).

Prints and writes reports/bench_memory.{md,json}.
Usage:  python -m experiments.bench_memory [--frames 200 3000] [--repo PATH]
(``--repo``: run another checkout's code, e.g. an older commit's worktree, for a before/after.)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hairexp.app.report import header, write_report

from experiments.common import ROOT, md_table, positive_int

SIZES = {"6 x 10 vertices": ["scene.n_strands=6", "scene.n_vertices=10"],
         "40 x 20 vertices": ["scene.n_strands=40", "scene.n_vertices=20"]}


def peak_rss(cmd: list[str], cwd: Path, env: dict) -> tuple[int, float, float]:
    """(exit code, peak RSS in MB, wall seconds) of one child process."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode(errors="replace")
    p.stderr.close()
    if p.returncode:
        raise SystemExit(f"bench_memory: {' '.join(cmd)} failed with exit {p.returncode}:\n{err[-2000:]}")
    return p.returncode, usage.ru_maxrss / 1024, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=positive_int, nargs=2, default=[200, 3000], metavar=("SHORT", "LONG"))
    ap.add_argument("--repo", type=Path, default=ROOT, help="the checkout whose code runs (default: this one)")
    ap.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES))
    args = ap.parse_args(argv)
    repo = args.repo.resolve()
    if not (repo / "hairexp" / "__main__.py").is_file():
        ap.error(f"--repo {repo}: not a hairexp checkout (no hairexp/__main__.py)")
    env = dict(os.environ, PYTHONPATH=str(repo))
    rows, results = [], []
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        for size in args.sizes:
            for rerun in (False, True):
                peaks = {}
                for frames in args.frames:
                    out = Path(tmp) / f"{len(results)}"
                    cmd = [sys.executable, "-m", "hairexp", "experiment=goaling_smoke", "variants=[]",
                           *SIZES[size], f"frames={frames}", f"logging.rerun={str(rerun).lower()}",
                           "logging.progress=false", f"hydra.run.dir={out}"]
                    _, mb, wall = peak_rss(cmd, repo, env)
                    peaks[frames] = mb
                    results.append({"hair": size, "rerun": rerun, "frames": frames, "peak_rss_mb": mb,
                                    "wall_s": wall, "command": " ".join(cmd[1:])})
                    print(f"{size:>18}  rerun {'on ' if rerun else 'off'}  {frames:5d} frames: "
                          f"peak {mb:7.1f} MB  ({wall:.0f} s)", flush=True)
                short, long_ = args.frames
                rows.append([size, "on" if rerun else "off", f"{peaks[short]:.1f}", f"{peaks[long_]:.1f}",
                             f"{peaks[long_] - peaks[short]:+.1f}"])
    short, long_ = args.frames
    md = header("Peak memory against run length")
    md += (f"Code: `{repo}`.  Each row: two runs of `python -m hairexp experiment=goaling_smoke variants=[]` "
           "(tracked, simulated guides) with the hair size and recording shown; peak resident set size of "
           "the process (`ru_maxrss`).\n\n")
    md += md_table(["hair", "recording", f"{short} frames (MB)", f"{long_} frames (MB)", "growth (MB)"], rows)
    path = write_report("bench_memory", md, {"repo": str(repo), "frames": args.frames, "results": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
