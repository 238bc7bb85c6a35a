"""The free step at Celia scale in two checkouts of hairexp, stepped in turn (issue 16).

Each checkout runs in a worker process of its own (``python <this file> --worker`` with the
checkout on ``PYTHONPATH`` and as the working directory, so that it imports that checkout's
hairexp and experiments; the worker uses only what ``experiments.common`` has had since the
benchmarks exist).  Each worker assembles the bench's run (``common.celia_bench``: the Celia
ponytail, 301 strands x 26 vertices, dt = 0.04 s, settled, the head jerking after the warm-up
steps), steps the ``WARMUP`` untimed steps, and then the parent has them take each timed step in
turn (worker A's step k, worker B's step k, then step k + 1) so that both meet the same load of a
shared machine: compare them by ratios.  Before the timed steps each worker also times its fused
Newton pass (``ImplicitEulerObjective.evaluate_step``) at the same iterate, alternated round by
round with the other worker.  At the end the final positions of both are compared.

Usage:  python -m experiments.compare_checkouts OTHER [--steps 50] [--repeats 30] [--threads 1]
(OTHER: the path of another checkout, e.g. a ``git worktree`` at the base commit.  The output
labels the two workers "other" (OTHER's) and "this" (the checkout this file is in); "this" is a
label, not a value for OTHER.)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from itertools import islice
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (local: the worker runs in the other checkout, whose
    experiments package may predate experiments.common's)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive integer")
    return v


def worker(steps: int, threads: str) -> None:
    """Reads commands from stdin, answers one JSON line each: ``eval`` (time one fused pass at the
    iterate after the warm-up), ``step`` (one timed step), ``save PATH`` (final positions)."""
    from hairexp.app.assemble import assemble
    from experiments.common import WARMUP, celia_bench

    run = assemble(celia_bench("free", steps, [f"solver.threads={threads}"]))
    sim = run.simulator
    state = run.initial_state()
    n = WARMUP + steps
    gen = islice(run.steps(state, math.ceil(n / run.steps_per_frame)), n)
    for _ in range(WARMUP):
        _, _, state, _ = next(gen)
    # the fused pass at the first stage's start of the next step (as bench_kernels.begin)
    obj = sim.objective
    integ, dt = sim.integrator, run.dt
    stages = getattr(integ, "stages", None)
    if stages is not None:
        integ, dt = stages(state, run.dt)[0]
    plan = integ.plan(sim, state, dt)
    x0 = None

    def say(obj_):
        sys.stdout.write(json.dumps(obj_) + "\n")
        sys.stdout.flush()

    say({"ready": True, "threads": getattr(obj.kernels, "threads", None)})
    for line in sys.stdin:
        cmd = line.split()
        if cmd[0] == "eval":
            if x0 is None:
                obj.begin_step(state.x, state.v, run.scene.root_positions(state.time + dt, run.scene.motion), dt,
                               state.tensions, plan)
                x0 = obj.initial_guess()
            t0 = time.perf_counter()
            obj.evaluate_step(x0)
            say({"s": time.perf_counter() - t0})
        elif cmd[0] == "step":
            c0, t0 = time.process_time(), time.perf_counter()
            _, _, state, info = next(gen)
            say({"s": time.perf_counter() - t0, "cpu": time.process_time() - c0, "iterations": info.iterations,
                 "seconds": {k: float(v) for k, v in info.seconds.items()}})
        elif cmd[0] == "save":
            np.save(cmd[1], state.x)
            say({"saved": cmd[1]})
            return


def start(checkout: Path, steps: int, threads: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    return subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker", "--steps", str(steps),
                             "--threads", threads],
                            cwd=checkout, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def ask(p: subprocess.Popen, cmd: str | None) -> dict:
    """Send ``cmd`` (None: nothing) and read the worker's next JSON line."""
    if cmd is not None:
        p.stdin.write(cmd + "\n")
        p.stdin.flush()
    while True:
        line = p.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {p.args} ended")
        if line.startswith("{"):
            return json.loads(line)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("other", nargs="?", help="path of the other checkout (the base)")
    ap.add_argument("--steps", type=positive_int, default=50)
    ap.add_argument("--repeats", type=positive_int, default=30, help="timed fused passes per checkout")
    ap.add_argument("--threads", default="1", choices=("1", "2", "auto"),
                    help="solver.threads of both runs (default 1: auto decides per process from the load, so the "
                         "two could differ)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.steps, args.threads)
        return
    if args.other is None:
        ap.error("the path of the other checkout is required")
    if not (Path(args.other) / "hairexp" / "__init__.py").is_file():   # a traceback before (probe of issue 12)
        ap.error(f"{args.other}: not a hairexp checkout (no hairexp/__init__.py)")
    paths = {"other": Path(args.other).resolve(), "this": HERE}
    workers = {}
    for name, path in paths.items():   # one after the other: their settle does not share the cores
        workers[name] = start(path, args.steps, args.threads)
        print(name, path, ask(workers[name], None), flush=True)
        ask(workers[name], "eval")   # the first pass (untimed)
    evals = {n: [] for n in workers}
    for _ in range(args.repeats):
        for n, w in workers.items():
            evals[n].append(ask(w, "eval")["s"])
    rows = {n: [] for n in workers}
    for _ in range(args.steps):
        for n, w in workers.items():
            rows[n].append(ask(w, "step"))
    tmp = Path(tempfile.mkdtemp())
    xs = {}
    for n, w in workers.items():
        ask(w, f"save {tmp / n}.npy")
        w.wait()
        xs[n] = np.load(tmp / f"{n}.npy")
    out = {}
    for n in workers:
        s = np.array([r["s"] for r in rows[n]])
        cpu = np.array([r["cpu"] for r in rows[n]])
        its = np.array([r["iterations"] for r in rows[n]])
        asm = np.array([r["seconds"].get("assembly", 0.0) for r in rows[n]])
        out[n] = {"eval_ms": 1e3 * float(np.median(evals[n])), "median_s": float(np.median(s)),
                  "mean_s": float(s.mean()), "cpu_median_s": float(np.median(cpu)), "iterations": float(its.mean()),
                  "assembly_ms": 1e3 * float(asm.mean())}
        print(f"{n:>5} ({paths[n]}): fused pass {out[n]['eval_ms']:.3f} ms (median of {args.repeats}); step median "
              f"{1e3 * out[n]['median_s']:.1f} ms, mean {1e3 * out[n]['mean_s']:.1f}, CPU median "
              f"{1e3 * out[n]['cpu_median_s']:.1f}; Newton its {out[n]['iterations']:.2f}; 'assembly' "
              f"{out[n]['assembly_ms']:.1f} ms/step")
    a, b = out["other"], out["this"]
    diff = float(np.abs(xs["this"] - xs["other"]).max())
    scale = float(np.abs(xs["other"]).max())
    print(f"ratios other/this: fused pass {a['eval_ms'] / b['eval_ms']:.2f}, step median "
          f"{a['median_s'] / b['median_s']:.2f}, mean {a['mean_s'] / b['mean_s']:.2f}, CPU {a['cpu_median_s'] / b['cpu_median_s']:.2f}")
    print(f"final positions after {args.steps} steps: max |dx| = {diff:.3e} m (max |x| {scale:.3g} m), bit-identical: "
          f"{bool(np.array_equal(xs['this'], xs['other']))}")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
