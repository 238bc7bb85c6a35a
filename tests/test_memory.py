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


def test_metrics_use_the_system_arrow_pool(tmp_path, monkeypatch):
    """pyarrow's default mimalloc pool keeps 2 MB segments (a 3,000-row text column read cost
    +2.0 MB resident, the system pool +0.07): the metrics table switches pyarrow to the C heap,
    which ``release`` trims; a pool the user chose is left alone."""
    import pyarrow as pa

    from hairexp.outputs.metrics import MetricsTable

    before = pa.default_memory_pool()
    try:
        monkeypatch.setenv("ARROW_DEFAULT_MEMORY_POOL", "jemalloc")
        pa.set_memory_pool(pa.mimalloc_memory_pool())
        MetricsTable(tmp_path / "a")
        assert pa.default_memory_pool().backend_name == "mimalloc"   # the user's choice kept
        monkeypatch.delenv("ARROW_DEFAULT_MEMORY_POOL")
        MetricsTable(tmp_path / "b")
        assert pa.default_memory_pool().backend_name == "system"
    finally:
        pa.set_memory_pool(before)
