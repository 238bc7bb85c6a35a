"""``python -m hairexp`` with tracemalloc on: the child process of experiments/bench_memory.py
that measures the Python heap (``--traced``).

Usage: python -m experiments.traced_run OUT.json [hairexp arguments ...]

Starts tracemalloc (one frame per trace: the cheapest), runs ``hairexp`` as ``python -m
hairexp`` does (``runpy``) with the arguments given, and writes to OUT.json the traced heap's
peak and its size at the end (bytes), with the run's exit code.  Tracing slows a run and costs
memory of its own, so the resident-memory figures are measured in separate, untraced runs."""

from __future__ import annotations

import json
import os
import runpy
import sys
import tracemalloc
from argparse import ArgumentTypeError

try:
    from experiments.common import writable_file
except ImportError:   # bench_memory --repo runs this file with an older checkout's experiments package
    writable_file = None


USAGE = "usage: python -m experiments.traced_run OUT.json [hairexp arguments ...]"


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] in ("-h", "--help"):
        print(USAGE + "\n\n" + __doc__.strip())
        return 0
    if len(sys.argv) < 2 or sys.argv[1].startswith("-") or "=" in sys.argv[1]:
        print(f"{USAGE}\ntraced_run.py: error: the first argument is the OUT.json to write", file=sys.stderr)
        return 2
    out, args = sys.argv[1], sys.argv[2:]
    try:   # before the run: a bad OUT.json failed only when the run had ended (probe: /proc/out.json)
        if writable_file is not None:
            writable_file(out)
    except ArgumentTypeError as exc:
        print(f"{USAGE}\ntraced_run.py: error: argument OUT.json: {exc}", file=sys.stderr)
        return 2
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        print(f"{USAGE}\ntraced_run.py: error: argument OUT.json: {out!r}: cannot be written: its folder {folder} "
              "does not exist", file=sys.stderr)
        return 2
    def record(code) -> None:
        current, peak = tracemalloc.get_traced_memory()
        with open(out, "w") as f:
            json.dump({"code": code, "traced_peak": peak, "traced_end": current}, f)

    # ``python -m hairexp`` ends with os._exit (hairexp/__main__.py ``exit_now``): record on that way out too
    hard_exit = os._exit

    def _exit(code):
        record(code)
        hard_exit(code)

    os._exit = _exit
    tracemalloc.start(1)
    sys.argv = ["hairexp", *args]
    try:   # exactly as ``python -m hairexp`` (Hydra finds its config relative to the __main__ file)
        runpy.run_module("hairexp", run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    record(code)
    return code


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
