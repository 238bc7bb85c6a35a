"""Command-line smoke test: one tiny goaling run through ``python -m hairexp`` and the files of
its run folder; and ``logging.rerun=false`` neither writes a recording nor imports rerun."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pandas as pd
import pytest

from helpers import CONF_DIR
from hairexp.outputs.metrics import CONTRACT_COLUMNS

FRAMES, N_STRANDS, N_VERTICES = 3, 4, 8
SUMMARY_KEYS = ("scene", "controller", "success", "measures", "steps", "iterations_mean", "iterations_max",
                "step_seconds_median")
RESULT_SHAPES = {  # V = N_STRANDS * N_VERTICES vertices, F = FRAMES + 1 frames
    "positions": (FRAMES + 1, N_STRANDS * N_VERTICES, 3),
    "strand_offsets": (N_STRANDS + 1,),
    "times": (FRAMES + 1,),
    "masses": (N_STRANDS * N_VERTICES,),
    "cluster_of_vertex": (N_STRANDS * N_VERTICES,),
}
RESULT_KEYS = ("positions", "strand_offsets", "guide_positions", "guide_offsets", "times", "masses",
               "cluster_of_vertex", "targets", "com")


def run_cli(args, cwd, timeout=120):
    env = dict(os.environ, CI="1")
    return subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def goaling_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("goaling")
    # run from another directory: the entry point must find its configs by itself
    proc = run_cli(["experiment=goaling", "variants=[]", f"frames={FRAMES}", f"scene.n_strands={N_STRANDS}",
                    f"scene.n_vertices={N_VERTICES}", f"hydra.run.dir={out}"], cwd=out)
    return proc, out


def test_cli_exit_code_and_files(goaling_run):
    proc, out = goaling_run
    assert proc.returncode == 0, proc.stderr
    for name in ("metrics.parquet", "summary.json", "recording.rrd", "result.npz", "result.usdc"):
        assert (out / name).is_file(), name
    leftovers = [p.name for p in out.rglob("*") if ".partial" in p.name or ".tmp" in p.name or p.name == "stream"]
    assert leftovers == []


def test_cli_metrics_table(goaling_run):
    proc, out = goaling_run
    assert proc.returncode == 0, proc.stderr
    df = pd.read_parquet(out / "metrics.parquet")
    steps_per_frame = 1  # goaling: fps 25, dt 0.04
    assert len(df) == FRAMES * steps_per_frame
    missing = [c for c in CONTRACT_COLUMNS if c not in df.columns]
    assert missing == []
    assert list(df["frame"]) == list(range(1, FRAMES + 1))
    np.testing.assert_allclose(df["time"], np.arange(1, FRAMES + 1) * 0.04, rtol=1e-12)
    assert df["converged"].all() and (df["controller"] == "free").all()
    assert (df["iterations"] >= 0).all()


def test_cli_summary(goaling_run):
    proc, out = goaling_run
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    missing = [k for k in SUMMARY_KEYS if k not in summary]
    assert missing == []
    df = pd.read_parquet(out / "metrics.parquet")
    assert summary["scene"] == "goaling" and summary["controller"] == "free"
    assert summary["steps"] == len(df)
    assert summary["iterations_max"] == int(df["iterations"].max())
    assert summary["iterations_mean"] == pytest.approx(float(df["iterations"].mean()))
    assert summary["step_seconds_median"] > 0
    assert summary["config"]["scene"]["n_strands"] == N_STRANDS  # the overrides reached the run


def test_cli_result_arrays(goaling_run):
    proc, out = goaling_run
    assert proc.returncode == 0, proc.stderr
    with np.load(out / "result.npz") as r:
        missing = [k for k in RESULT_KEYS if k not in r.files]
        assert missing == []
        for k, shape in RESULT_SHAPES.items():
            assert r[k].shape == shape, k
        assert list(r["strand_offsets"]) == list(range(0, N_STRANDS * N_VERTICES + 1, N_VERTICES))
        np.testing.assert_allclose(r["times"], np.arange(FRAMES + 1) * 0.04, rtol=0, atol=1e-12)
        assert np.isfinite(r["positions"]).all()
        assert (r["masses"] > 0).all()
        for k in ("guide_positions", "targets", "com"):
            assert r[k].shape[0] == FRAMES + 1 and r[k].shape[-1] == 3, k
        # frame 0 is the rest pose; the hair moved afterwards (gravity)
        assert np.abs(r["positions"][-1] - r["positions"][0]).max() > 0


def test_cli_recording_reads_back(goaling_run):
    proc, out = goaling_run
    assert proc.returncode == 0, proc.stderr
    from rerun.chunk import RrdReader

    chunks = list(RrdReader(str(out / "recording.rrd")).stream().filter(
        content="/metrics/iterations", is_static=False, has_timeline="frame"))
    assert chunks
    frames, values = [], []
    for c in chunks:
        rb = c.to_record_batch()
        d = rb.to_pydict()
        frames += d["frame"]
        values += [v[0] for v in d["Scalars:scalars"]]
    assert len(frames) > 0
    df = pd.read_parquet(out / "metrics.parquet")
    assert sorted(zip(frames, values)) == sorted(zip(df["frame"], df["iterations"].astype(float)))


def test_rerun_off_writes_no_recording_and_never_imports_rerun(tmp_path):
    code = textwrap.dedent(f"""
        import sys
        from hydra import compose, initialize_config_dir
        import hairexp.app.config
        from hairexp.app.run import run
        with initialize_config_dir(config_dir={str(CONF_DIR)!r}, version_base="1.3"):
            cfg = compose(config_name="config", overrides=["experiment=goaling", "variants=[]", "frames=2", "scene.n_strands=2",
                                                           "scene.n_vertices=5", "logging.rerun=false"])
        summary = run(cfg, {str(tmp_path)!r})
        print(summary["status"], summary["steps"])
        print("rerun" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=dict(os.environ, CI="1"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.split()
    assert lines[-3:] == ["completed", "2", "False"], proc.stdout
    assert not list(tmp_path.glob("recording.rrd*"))
    assert (tmp_path / "result.npz").is_file() and (tmp_path / "metrics.parquet").is_file()



def test_a_run_folder_alone_is_not_composed_with_hydras_config(monkeypatch):
    """``hydra.run.dir=<path>`` (and the sweep's folders) take any text in Hydra's schema: the
    pre-Hydra check does not compose Hydra's config for them (0.2-0.3 s of every such launch);
    any other Hydra key, an added or deleted one, or a value that is not text still is."""
    import hydra

    from hairexp.app import cli

    composed = []
    real = hydra.compose

    def counting(*a, **k):
        composed.append(k.get("overrides"))
        return real(*a, **k)

    monkeypatch.setattr(hydra, "compose", counting)
    for ok in (["hydra.run.dir=/tmp/x"], ["hydra.sweep.dir=/tmp/s", "hydra.sweep.subdir=${hydra.job.num}"]):
        assert cli.hydra_key_error(ok) is None
    assert composed == []
    assert cli.hydra_key_error(["hydra.run.dir=/tmp/x", "hydra.job.name=run"]) is None
    assert len(composed) == 1
    assert "Cannot convert 'list' to string" in cli.hydra_key_error(["hydra.run.dir=[a,b]"])
    assert "does not support deletion" in cli.hydra_key_error(["~hydra.run.dir"])
    assert cli.hydra_key_error(["+hydra.run.foo=1"]).startswith("hydra.run.foo: not a key of Hydra's config")
