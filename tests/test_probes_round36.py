"""Findings of the independent probe round 36 of issue 12, fixed."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("overrides, unused", [
    # (the launch's overrides, whether its key -- the last override's -- is named as not used)
    (["collision.hair_thickness=0.009"], True),   # goaling: the object stage, no hair-hair: nothing reads it
    (["collision.hair_hair=true", "collision.hair_thickness=0.009"], False),
    (["collision.contact=barrier", "collision.hair_thickness=0.009"], False),
    (["collision.hair_hair=true", "collision.hair_hair_model=volume", "collision.hair_thickness=0.009"], True),
    (["scene.settle=0", "scene.settle_dt=0.5"], True),
    (["scene.settle=0.4", "scene.settle_dt=0.02"], False),
    (["solver.derivatives=autograd", "solver.compile=on"], True),
    (["solver.compile=on"], False),
    (["solver.kernels=torch", "solver.threads=2"], True),
    (["solver.derivatives=autograd", "solver.kernels=numba", "solver.threads=2"], True),
    (["solver.threads=2"], False),
    (["scene.usd_body=/Foo"], True),
    (["scene.usd_hair=/Nowhere"], True),
    (["collision.objects=false", "collision.max_travel=0.9"], True),
    (["collision.max_travel=0.9"], False),
    (["collision.friction=false"], True),   # the stage applies each collider's friction whatever it says
    (["collision.contact=barrier", "collision.friction=false"], False),
])
def test_settings_no_run_reads_are_named(overrides, unused):
    """Keys accepted without a word though nothing of the run read them (round 36, bad F1-F6 and
    the undecided collision.friction); each is named where it is not read, and only there."""
    from hairexp.app import compose_config
    from hairexp.app.validate import unused_settings

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]"] + overrides)
    key = overrides[-1].split("=", 1)[0]
    named = [u for u in unused_settings([cfg], [o.split("=", 1)[0] for o in overrides]) if u.startswith(f"{key} (")]
    assert bool(named) == unused, (overrides, named)


def test_a_job_ended_by_its_launcher_leaves_no_temporary_file(tmp_path, monkeypatch, capsys):
    """``hydra.launcher.timeout`` ended a job's worker while its variant wrote metrics.parquet: a
    0-byte ``free/metrics.parquet.tmp`` stayed in the job's folder (round 36, weak; 1 of 3).  The
    sweep's end (``_end_killed_jobs``) removes the run's ``*.tmp`` files where it writes the
    ending; the rows are in ``stream/metrics/``, and a file of another name stays."""
    import json
    import signal
    import socket
    import subprocess

    from hairexp.app import cli

    gone = subprocess.Popen(["true"])
    gone.wait()   # a process id that no longer runs
    job = tmp_path / "0"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("- solver.rtol=1e-5\n")
    cli._write_outcome(job, {**cli.outcome(job, "running", 1, "the job did not finish"), "pid": gone.pid})
    running = {"status": "running", "pid": gone.pid, "host": socket.gethostname()}
    (job / "summary.json").write_text(json.dumps(running))
    free = job / "free"
    (free / "stream" / "metrics").mkdir(parents=True)
    (free / "summary.json").write_text(json.dumps(running))
    (free / "metrics.parquet.tmp").write_bytes(b"")
    (free / "notes.tmp.txt").write_text("the user's")
    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 1)
    assert cli.exit_code(signal.SIGTERM) == 143
    assert "interrupted (exit 143)" in capsys.readouterr().err
    assert not (free / "metrics.parquet.tmp").exists() and (free / "notes.tmp.txt").exists()
    assert json.loads((free / "summary.json").read_text())["status"] == "interrupted"


def test_a_job_folder_outside_the_sweep_and_shared_by_every_job_gets_both_reasons(tmp_path):
    """``hydra.sweep.subdir=../out`` said only that every job would share the folder, and its advice
    (``../${hydra.job.num}``) was then refused for lying outside the sweep folder (round 36, weak)."""
    from hairexp.app import cli

    base = ["-m", "experiment=goaling_smoke", "frames=5", "solver.rtol=1e-5,1e-6", f"hydra.sweep.dir={tmp_path / 's'}"]
    msg = cli.used_dir_error(base + ["hydra.sweep.subdir=../out"])
    assert "must lie inside the sweep folder" in msg and "must differ per job" in msg, msg
    msg = cli.used_dir_error(base + ["hydra.sweep.subdir=../${hydra.job.num}"])
    assert "must lie inside the sweep folder" in msg and "differ per job" not in msg, msg
    msg = cli.used_dir_error(base + ["hydra.sweep.subdir=same"])
    assert "every job of the sweep would write into the same folder" in msg, msg


def test_simulator_step_refuses_a_bad_dt_with_an_input_error():
    """``Simulator.step(state, "0.01")`` (or 0, nan, -1) raised a plain ValueError where the README
    promises InputError (a ValueError) at the API's entry points (round 37, weak)."""
    import numpy as np

    from hairexp.app.config import SolverConfig
    from hairexp.errors import InputError
    from hairexp.model import Material, RigidMotion, Scene, Strands
    from hairexp.physics import Simulator

    line = np.stack([np.zeros(10), -np.linspace(0.0, 0.2, 10), np.zeros(10)], 1)
    strands = Strands.from_polylines(line, np.array([10]), 1e-4)
    still = RigidMotion(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))
    sim = Simulator(Scene("one", strands, Material(1e-4, 10.0, 1e-7), still, np.array([0.0, -9.81, 0.0]), line),
                    SolverConfig())
    for dt in (0.0, float("nan"), -1.0, "0.01", 1e9, 1e-300):
        with pytest.raises(InputError, match=r"^Simulator.step: dt"):
            sim.step(sim.initial_state(), dt)


def test_a_collider_keyframe_that_is_not_finite_is_named_with_its_list_and_value():
    """``scene.colliders.0.motion.times=[0,nan]`` said "keyframes contain NaN or inf", naming no
    list and no value (round 37, weak)."""
    import numpy as np

    from hairexp.errors import InputError
    from hairexp.model import RigidMotion

    with pytest.raises(InputError) as err:
        RigidMotion(np.array([0.0, np.nan]), np.zeros((2, 3)), np.zeros((2, 3)), where="scene.colliders[0].motion")
    assert str(err.value) == "scene.colliders[0].motion.times: keyframe 1 is not finite: nan (NaN or inf)"
    with pytest.raises(InputError) as err:
        RigidMotion(np.array([0.0, 1.0]), np.array([[0.0, 0, 0], [np.inf, 0, 0]]), np.zeros((2, 3)), where="m")
    assert str(err.value) == "m.translations: keyframe 1 is not finite: [inf, 0.0, 0.0] (NaN or inf)"
