"""Memory flat in the run's length (issue 12): the freed heap is given back between a run's end
phases (hairexp/memory.py); the figures are experiments/bench_memory.py's (reports/bench_memory.md)."""

from __future__ import annotations

import sys

from hairexp import memory
from hairexp.app.config import compose_config


def test_release_gives_heap_back_and_never_fails():
    if sys.platform.startswith("linux"):
        assert memory._malloc_trim()        # glibc: malloc_trim found
    memory.release()                        # with or without pyarrow loaded
    import pyarrow  # noqa: F401

    memory.release()


def test_a_run_releases_between_its_phases(tmp_path, monkeypatch):
    """After the guides, before and after metrics.parquet, after the measures, result.npz and
    result.usdc: the end phases' freed blocks do not stack under the next phase."""
    import hairexp.app.run as run_mod

    calls = []
    monkeypatch.setattr(run_mod, "release", lambda: calls.append(1))
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false",
                          "logging.progress=false"])
    summary = run_mod.run(cfg, tmp_path / "run")
    assert summary["status"] == "completed" and len(calls) >= 6
