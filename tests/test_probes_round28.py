"""Findings of the independent probe round 28 of issue 12 (on ``ece9510``), fixed: the failed
ending's notes name each part's own file and where the metrics rows are when metrics.parquet
could not be written; a longer guide file's frames after the run; variants of different spans;
the export's path after the overrides."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_a_failed_ending_says_each_parts_file_and_where_the_metrics_are(tmp_path, monkeypatch):
    """A full disk: "(frames, metrics.parquet): ... '.../stream/positions.npy'" named one file for
    both parts, and the metrics rows kept in stream/metrics/ were said nowhere."""
    from hairexp.app import run as run_mod
    from hairexp.errors import SimulationError
    from hairexp.outputs.metrics import MetricsTable

    table = MetricsTable(tmp_path / "stream" / "metrics")
    for k in range(3):
        table.on_step({"step": k}, None)
    table.flush()

    def full(name):
        def fail(*a, **k):
            raise OSError(28, "No space left on device", str(tmp_path / name))
        return fail

    class Sinks:
        progress = rerun = None
        written = []
        plain = {"experiment": None, "config": None}

        class recorder:
            flush = align = close = staticmethod(full("stream/positions.npy"))

    Sinks.table = table
    monkeypatch.setattr(table, "write", full("metrics.parquet.tmp"))
    seen = {}
    monkeypatch.setattr(run_mod, "summarize", lambda *a, **k: seen.setdefault("s", {"status": "failed"}))
    exc = SimulationError("boom")
    run_mod._end_unfinished(exc, Sinks, tmp_path, "s", "free", 0.0)
    assert exc.__notes__ == [
        "while writing the failed ending (frames (stream/positions.npy), metrics.parquet (metrics.parquet.tmp)): "
        "OSError: [Errno 28] No space left on device",
        "metrics.parquet could not be written: 3 of the 3 steps' metrics rows are in stream/metrics/ "
        "(pandas.read_parquet reads the folder as one table)"]
    assert json.loads((tmp_path / "summary.json").read_text())["metrics_file"] == "stream/metrics/"


def test_a_guide_files_frames_after_the_run_are_not_checked(tmp_path, caplog):
    """A 40-frame guide file for a 20-frame run: "guide 0's root is 0.0397 m from where the body
    carries it at frame 21", a frame the run never reads."""
    import logging

    from hairexp.app.config import compose_config
    from hairexp.app.guides import build_guides
    from hairexp.app.assemble import assemble_scene

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "controller=tracking", "frames=20"])
    _, scene, _ = assemble_scene(cfg, settle=False)
    anim = build_guides(cfg, scene, 40, float(cfg.fps))
    frames = np.array(anim.frames)
    roots = frames[:, np.asarray(anim.offsets[:-1])]
    frames[21:, np.asarray(anim.offsets[:-1])] = roots[21:] + [0.0, 0.0, 0.04]   # off the body after frame 20
    path = tmp_path / "long.npz"
    np.savez(path, guide_positions=frames, guide_offsets=np.asarray(anim.offsets), fps=float(cfg.fps))
    file_cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "controller=tracking", "frames=20",
                               "guides.source=file", f"guides.file={path}"])
    with caplog.at_level(logging.WARNING):
        build_guides(file_cfg, scene, 20, float(cfg.fps))
    assert not any("from where the body carries it" in r.getMessage() for r in caplog.records)
    with caplog.at_level(logging.WARNING):
        build_guides(file_cfg, scene, 22, float(cfg.fps))
    assert any("from where the body carries it at frame 21" in r.getMessage() for r in caplog.records)


def test_variants_of_different_spans_are_said(caplog):
    """A variant's own frames=5 beside another's 10: the measures and the judge compared them as
    if they ran the same, without a word."""
    import logging

    from hairexp.app.config import compose_config
    from hairexp.app.experiment import _checked_variants

    cfg = compose_config(["experiment=goaling_smoke", "frames=10", 'variants=[{name: free, overrides: '
                          '["controller.name=free", "frames=5"]}, {name: tracked, overrides: ["controller.name=tracking"]}]'])
    with caplog.at_level(logging.WARNING):
        _checked_variants(cfg)
    said = [r.getMessage() for r in caplog.records if "different spans" in r.getMessage()]
    assert said == ["the variants run different spans (free: 5 frames at 25.0 fps, tracked: 10 frames at 25.0 fps): "
                    "their measures, the judge and comparison.rrd compare them as if they ran the same; set frames and "
                    "fps for the experiment, not in a variant"]


def test_the_exports_path_after_the_overrides_is_taken(tmp_path, capsys):
    """``export_scene experiment=goaling_smoke ... d.usda`` said "the path of the stage to write is
    required"."""
    from hairexp.app.export_scene import main

    out = tmp_path / "d.usda"
    assert main(["experiment=goaling_smoke", "variants=[]", "frames=3", str(out)]) == 0
    assert out.is_file() and capsys.readouterr().out.startswith(f"wrote {out}:")


def test_the_frames_a_killed_jobs_stream_holds_are_counted(tmp_path):
    """A sweep job ended by hydra.launcher.timeout: its failed summary had frames_kept null while
    stream/ held 751 frames.  Counted from the files: the header's frames, or fewer where a
    process killed mid-append left a file short."""
    from hairexp.outputs.files import GrowingNpy, stream_frames

    assert stream_frames(tmp_path) is None
    pos = GrowingNpy(tmp_path / "positions.npy", (4, 3), np.float64)
    times = GrowingNpy(tmp_path / "times.npy", (), np.float64)
    for k in range(7):
        pos.append(np.full((4, 3), k, dtype=np.float64))
        times.append(np.float64(k))
    pos.flush()
    times.flush()
    np.save(tmp_path / "masses.npy", np.ones(2))   # a constant: not a frame array
    assert stream_frames(tmp_path) == 7
    with open(tmp_path / "positions.npy", "r+b") as f:   # killed mid-append: the last frame half there
        f.truncate(f.seek(0, 2) - 40)
    assert stream_frames(tmp_path) == 6


@pytest.mark.parametrize("override, said", [
    ("foo=1", "variants[0] (a): unknown key 'foo'"),
    ("solver.dt=abc", "variants[0] (a): solver.dt=abc: Value 'abc' of type 'str' could not be converted to Float"),
])
def test_cfg_job_checks_a_variants_overrides_as_a_run_does(override, said):
    """``--cfg job`` with a variant's ``foo=1`` printed the config, exit 0 (a run refuses it, exit 2)."""
    from hairexp.app import cli

    argv = ["--cfg", "job", "experiment=goaling_smoke", f'variants=[{{name: a, overrides: ["{override}"]}}]']
    assert cli.config_error(argv).startswith(f"hairexp: error: {said}")
    ok = ["--cfg", "job", "experiment=goaling_smoke", 'variants=[{name: a, overrides: ["solver.dt=0.02"]}]']
    assert cli.config_error(ok) is None
