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


def test_release_every_is_rate_limited(monkeypatch):
    """``release_every(s)``: a trim only when the last one is at least s old (the steps and the
    end phases' passes over the frames call it per flush / per block of frames)."""
    trims = []
    monkeypatch.setattr(memory, "_malloc_trim", lambda: (lambda pad: trims.append(pad)))
    memory.release()
    assert len(trims) == 1
    memory.release_every(3600.0)             # the last release was just now
    assert len(trims) == 1
    memory.release_every(0.0)
    assert len(trims) == 2


def test_a_pass_over_many_frames_releases(tmp_path, monkeypatch):
    """Iterating a long frame file gives the freed heap back between its blocks (at most every
    ``RELEASE_SECONDS``), and reads the same frames."""
    import numpy as np

    from hairexp.outputs import files

    a = np.arange(4000 * 12, dtype=np.float64).reshape(4000, 4, 3)
    np.save(tmp_path / "x.npy", a)
    calls = []
    monkeypatch.setattr(files, "release_every", lambda s: calls.append(s))
    frames = files.NpyFrames(tmp_path / "x.npy")
    got = np.stack(list(frames))
    np.testing.assert_array_equal(got, a)
    per = files.NpyFrames.BLOCK_BYTES // (12 * 8)
    assert len(calls) == -(-4000 // per) and set(calls) == {files.RELEASE_SECONDS}


def test_the_command_line_runs_its_exit_handlers_before_it_ends(tmp_path):
    """``python -m hairexp`` ends with os._exit after the atexit handlers and a flush of the
    standard streams (hairexp/app/startup.py ``exit_now``): a handler registered before the run
    runs, text printed without a newline reaches the pipe, the exit code is the run's, and a bad
    input still exits 2 with its message."""
    import os
    import subprocess

    from helpers import REPO

    env = dict(os.environ, PYTHONPATH=str(REPO))
    mark, out = tmp_path / "atexit.txt", tmp_path / "run"
    script = ("import atexit, runpy, sys\n"
              f"atexit.register(lambda: open({str(mark)!r}, 'w').write('ran'))\n"
              "sys.stdout.write('unflushed-tail')\n"
              "sys.argv = ['hairexp', *sys.argv[1:]]\n"
              "runpy.run_module('hairexp', run_name='__main__', alter_sys=True)\n")
    p = subprocess.run([sys.executable, "-c", script, "experiment=goaling_smoke", "variants=[]", "frames=2",
                        "logging.rerun=false", "logging.progress=false", f"hydra.run.dir={out}"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert mark.read_text() == "ran" and "unflushed-tail" in p.stdout
    last = (out / "__main__.log").read_text().strip().splitlines()[-1]   # the run's closing line
    assert "2 steps" in last and last.endswith(str(out))
    bad = subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling_smoke", "solver.dt=-1",
                          f"hydra.run.dir={tmp_path / 'bad'}"], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=300)
    assert bad.returncode == 2 and "solver.dt" in bad.stderr


def test_metric_columns_read_a_row_group_at_a_time_equal_to_pandas(tmp_path, monkeypatch):
    """``MetricColumns`` reads one column a row group at a time, single-threaded: every column
    and ``numeric`` (float64, booleans 0/1, nulls NaN; None for text) equal pandas' reading of
    the whole file, over parts whose types differ (ints meeting floats, a column missing from a
    part, a boolean column)."""
    import numpy as np
    import pandas as pd
    import pyarrow.parquet as pq

    from hairexp.outputs import metrics
    from hairexp.outputs.metrics import MetricsTable

    monkeypatch.setattr(metrics, "ROW_GROUP_ROWS", 10)   # a row group every two parts
    table = MetricsTable(tmp_path / "parts")
    rng = np.random.default_rng(3)
    for part in range(5):
        for i in range(7 + part):
            row = {"step": part * 100 + i, "iters": int(rng.integers(0, 9)), "ok": bool(rng.integers(0, 2)),
                   "status": ["converged", "substep"][int(rng.integers(0, 2))],
                   "res": float(rng.normal()) if part != 1 else int(rng.integers(0, 4))}
            if part >= 2:
                row["late"] = float(rng.normal())
            table.rows.append(row)
        table.flush()
    cols = table.write(tmp_path / "metrics.parquet")
    assert pq.read_metadata(cols.path).num_row_groups == 3
    ref = pd.read_parquet(cols.path)
    assert cols.columns == list(ref.columns) and len(cols) == len(ref) == 45
    for k in ref.columns:
        pd.testing.assert_series_equal(cols[k], ref[k], check_names=True)
        num = cols.numeric(k)
        if k == "status":
            assert num is None
        else:
            np.testing.assert_array_equal(num, ref[k].astype("float64").to_numpy())
    assert np.isnan(cols.numeric("late")[:7 + 8]).all() and np.isfinite(cols.numeric("late")[15:]).all()
