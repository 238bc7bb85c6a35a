"""``python -m hairexp`` with tracemalloc on: the child process of experiments/bench_memory.py
that measures the Python heap (``--traced``).

Usage: python -m experiments.traced_run OUT.json [hairexp arguments ...]

Starts tracemalloc (one frame per trace: the cheapest), runs ``hairexp`` as ``python -m
hairexp`` does (``runpy``) with the arguments given, and writes to OUT.json the traced heap's
peak and its size at the end (bytes), with the run's exit code.  Tracing slows a run and costs
memory of its own, so the resident-memory figures are measured in separate, untraced runs."""

from __future__ import annotations

import json
import runpy
import sys
import tracemalloc


def main() -> int:
    out, args = sys.argv[1], sys.argv[2:]
    tracemalloc.start(1)
    sys.argv = ["hairexp", *args]
    try:   # exactly as ``python -m hairexp`` (Hydra finds its config relative to the __main__ file)
        runpy.run_module("hairexp", run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    current, peak = tracemalloc.get_traced_memory()
    with open(out, "w") as f:
        json.dump({"code": code, "traced_peak": peak, "traced_end": current}, f)
    return code


if __name__ == "__main__":
    sys.exit(main())
