"""Findings of the ninth independent probe round, one test each:

1. a run folder (``hydra.run.dir`` / ``hydra.sweep.dir``) whose interpolation cannot be
   resolved: an unset ``${oc.env:NAME}`` without a default, an unknown resolver, a ``${key}``
   that is not in the config.  Hydra resolved them after it started and failed with its
   traceback (exit 1); now one line, exit 2, nothing created.
2. sweeps: a ``hydra.sweep.subdir`` outside the sweep folder (``../x_${hydra.job.num}``, an
   absolute path) is refused before Hydra starts (the jobs ran outside it and the sweep's report
   said "0 of 2 jobs completed (2 not started)", exit 1); a nested one (``a/${hydra.job.num}``)
   is allowed and its jobs are reported (they were called not started).
3. a run on a disk that filled up hung for good in rerun's flush (its file writer had stopped
   without waking the flush; SIGTERM could not end it): a flush now waits at most
   FLUSH_TIMEOUT_SECONDS, then the recording is an OSError and the stream is given up without the
   calls that would wait for the same writer.
4. every variant's tracking.points_per_guide and tracking.variance.* are checked before the first
   variant runs (the free variant ran to the end and wrote its files, then the tracked one
   stopped with exit 2); an empty ``hydra.sweep.subdir`` is one line, exit 2 (it was exit 1,
   "the sweep folder is not empty (multirun.yaml)").
"""

from __future__ import annotations

import pytest
from probe_helpers import REPO, SMALL, run_cli

from hairexp.app import cli
from hairexp.outputs import rerun_sink


@pytest.mark.parametrize("value,says", [
    ("${oc.env:HAIREXP_PROBE_UNSET}/x", "environment variable HAIREXP_PROBE_UNSET is not set"),
    ("{tmp}/${foo:bar}", "unknown resolver 'foo'"),
    ("{tmp}/${scene.nme}", "${scene.nme}, which is not a key of the config"),
])
def test_run_folder_interpolation_that_cannot_be_resolved_is_one_line(tmp_path, monkeypatch, value, says):
    monkeypatch.delenv("HAIREXP_PROBE_UNSET", raising=False)
    value = value.replace("{tmp}", str(tmp_path / "runs"))
    line = cli.run_dir_value_error([*SMALL, f"hydra.run.dir={value}"])
    assert line is not None and line.startswith("hairexp: error: hydra.run.dir=") and says in line
    sweep = cli.run_dir_value_error(["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={value}"])
    assert sweep is not None and sweep.startswith("hairexp: error: hydra.sweep.dir=") and says in sweep
    p = run_cli([*SMALL, f"hydra.run.dir={value}"], tmp_path)
    assert p.returncode == 2 and "Traceback" not in p.stderr and says in p.stderr
    assert not (tmp_path / "runs").exists()


def test_run_folder_interpolations_that_resolve_are_left_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("HAIREXP_PROBE_SET", str(tmp_path))
    for value in ("${oc.env:HAIREXP_PROBE_SET}/a", "${oc.env:HAIREXP_PROBE_UNSET2," + str(tmp_path) + "}/b",
                  str(tmp_path) + "/${now:%H%M%S}", str(tmp_path) + "/${scene.name}_${hydra.job.name}"):
        assert cli.run_dir_value_error([*SMALL, f"hydra.run.dir={value}"]) is None, value
    p = run_cli([*SMALL, f"hydra.run.dir={tmp_path}/${{scene.name}}_r"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert (tmp_path / "goaling_r" / "summary.json").exists()


@pytest.mark.parametrize("subdir", ["../escape_${hydra.job.num}", "{tmp}/abs_${hydra.job.num}"])
def test_sweep_subdir_outside_the_sweep_folder_is_refused(tmp_path, subdir):
    subdir = subdir.replace("{tmp}", str(tmp_path))
    p = run_cli(["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={tmp_path}/sw", f"hydra.sweep.subdir={subdir}"],
                tmp_path)
    assert p.returncode == 2 and "must lie inside the sweep folder" in p.stderr and "Traceback" not in p.stderr
    assert not (tmp_path / "sw").exists() and not list(tmp_path.glob("escape_*")) and not list(tmp_path.glob("abs_*"))


def test_sweep_with_nested_job_folders_reports_every_job(tmp_path):
    p = run_cli(["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={tmp_path}/sw",
                 "hydra.sweep.subdir=a/${hydra.job.num}"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    out = p.stdout + p.stderr
    assert "hairexp: job a/0 [" in out and "hairexp: job a/1 [" in out
    assert "hairexp: sweep: 2 of 2 jobs completed ->" in out and "not started" not in out
    rows = cli.sweep_outcomes(tmp_path / "sw")
    assert [r[0] for r in rows] == ["a/0", "a/1"] and all(r[2]["status"] == "completed" for r in rows)


def test_a_stuck_recording_writer_is_an_error_not_a_hang(tmp_path):
    """A writer that never finishes: the recording file is a FIFO whose reader never reads, so
    rerun's writer blocks once the pipe's buffer is full (as the disk-full race left it).  In a
    process of its own that ends as hairexp's does (``os._exit`` after the exit handlers, of which
    rerun's is removed): the interpreter's teardown, or rerun's handler, would wait for the writer."""
    import os
    import subprocess
    import sys

    fifo = tmp_path / "recording.partial.rrd"
    os.mkfifo(fifo)
    script = f"""
import os, time
import numpy as np
import rerun as rr
from hairexp.outputs import rerun_sink
reader = os.open({str(fifo)!r}, os.O_RDONLY | os.O_NONBLOCK)   # a reader that never reads
rerun_sink.FLUSH_TIMEOUT_SECONDS = 1.0
rec = rr.RecordingStream("hairexp-test", recording_id="stuck")
rec.save({str(fifo)!r})
for f in range(40):   # about 1 MB: far more than a pipe holds
    rec.set_time("frame", sequence=f)
    rec.log("/a", rr.Points3D(np.random.default_rng(f).random((2000, 3))))
t0 = time.monotonic()
for attempt in (1, 2):
    try:
        rerun_sink.flush_recording(rec, {str(fifo)!r})
    except OSError as exc:
        print("attempt", attempt, round(time.monotonic() - t0, 1), exc, flush=True)
print("abandoned", rerun_sink.abandoned(rec), flush=True)
os._exit(0)   # as hairexp's entry point ends (hairexp/app/startup.py exit_now): no teardown of the stream
"""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    lines = p.stdout.splitlines()
    assert p.returncode == 0, p.stderr[-2000:]
    assert lines[0].startswith("attempt 1") and "did not finish within 1 s" in lines[0]
    assert float(lines[0].split()[2]) < 20
    assert lines[1].startswith("attempt 2") and "writer is stuck" in lines[1]   # at once, no second wait
    assert lines[2] == "abandoned True"


@pytest.mark.parametrize("bad,key", [
    (["tracking.points_per_guide=0"], "tracking.points_per_guide"),
    (["tracking.variance.stiffness=-1"], "tracking.variance.stiffness"),
    (["tracking.variance.times=[0.0,1.0]"], "tracking.variance.stiffness_scale"),
    (["tracking.variance.times=[1.0,0.0]", "tracking.variance.stiffness_scale=[1.0,1.0]",
      "tracking.variance.target_scale=[1.0,1.0]"], "tracking.variance.times"),   # the times' fault (round 14)
])
def test_tracking_keys_are_checked_before_any_variant_runs(tmp_path, bad, key):
    """goaling_smoke runs its free variant first: it must not run with a tracked variant's bad value."""
    out = tmp_path / "run"
    p = run_cli(["experiment=goaling_smoke", "frames=2", "logging.rerun=false", *bad, f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 2, p.stderr[-2000:]
    # the command line's own value: said without a variant's name (round 18), and before any variant ran
    assert p.stderr.startswith(f"hairexp: error: {key}:") and "variants[" not in p.stderr
    assert not (out / "free").exists() and not (out / "tracked").exists()


def test_a_tracked_variants_own_bad_value_is_named_before_the_free_variant_runs(tmp_path):
    out = tmp_path / "run"
    p = run_cli(["experiment=goaling_smoke", "frames=2", "logging.rerun=false", f"hydra.run.dir={out}",
                 "variants=[{name: free, overrides: ['controller.name=free']}, "
                 "{name: tracked, overrides: ['controller.name=tracking', 'tracking.points_per_guide=0']}]"], tmp_path)
    assert p.returncode == 2 and "(variants[1] tracked, checked before any variant runs)" in p.stderr
    assert not (out / "free").exists()


def test_an_empty_sweep_subdir_is_one_line(tmp_path):
    for values in ("0.04", "0.04,0.02"):
        p = run_cli(["-m", *SMALL, f"solver.dt={values}", f"hydra.sweep.dir={tmp_path}/sw{len(values)}",
                     "hydra.sweep.subdir="], tmp_path)
        assert p.returncode == 2 and "hairexp: error: hydra.sweep.subdir: is empty" in p.stderr
        assert not (tmp_path / f"sw{len(values)}").exists()
