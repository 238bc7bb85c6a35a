"""Findings of the fifth independent probe round (392 probes: 6 bad, 17 weak findings), one test
or a few each, checking the exit code or the error's ``where`` and the message naming the input:

1. USD: a collider attribute authored only as a time sample is read (it was the schema's
   fallback: a 1 m sphere instead of 5 cm), an animated one is refused; an inactive hair prim is
   refused; a stage with only endTimeCode gives its frames, a fractional end is refused; animated
   hair points are warned about.
2. config: ``collision.barrier_dhat`` is bounded (1e6 hung the first step); ``scene.gravity`` is
   bounded; a rotate edit's angle is bounded; ``guides.collide`` needs simulated guides; the block
   must not start under its rail; ``block_rail`` measures the body's own rail; a guide file's fps
   is bounded; procedural guides far from the origin name the keys that placed them; a long run
   is announced by its estimated time too.
3. run folders and signals: ``overwrite=true`` drops the previous run's log lines; a signal after
   the run completed leaves it completed and says so; an interrupted run keeps a finished
   recording as ``recording.partial.rrd``; a signal that lands in an object's finaliser is not
   lost; a sweep into a used sweep folder is refused; ``hydra.*`` typos are one line, exit 2.
4. API: ``Simulator.step`` names a dt that is not a number and a state time that is not finite;
   export_scene of a ``from_usd`` config says the stage's frame count.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from probe_helpers import SMALL, run_cli, updated

from hairexp.app import cli
from hairexp.app.assemble import assemble, assemble_scene
from hairexp.app.config import compose_config
from hairexp.app.signals import InterruptSignals, take_late
from hairexp.errors import Interrupted, InputError



@pytest.fixture(scope="module")
def base():
    return compose_config(SMALL)


# 1. USD

@pytest.fixture()
def stage(tmp_path):
    from usd_helpers import COLLIDERS, source_cfg, write_stage

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS[:1]))   # the ball, radius 0.03
    return path


def test_a_time_sampled_collider_radius_is_read_and_an_animated_one_refused(stage):
    from pxr import UsdGeom
    from usd_helpers import edit_stage, usd_cfg

    from hairexp.app.builders import build_scene

    def sampled_only(st):
        a = UsdGeom.Sphere(st.GetPrimAtPath("/Root/Colliders/ball")).GetRadiusAttr()
        a.Clear()
        a.Set(0.03, 0.0)
        a.Set(0.03, 3.0)
        t = st.GetPrimAtPath("/Root/Colliders/ball").GetAttribute("hairexp:thickness")
        t.Clear()
        t.Set(0.003, 0.0)

    edit_stage(stage, sampled_only)
    ball = build_scene(usd_cfg(stage).scene).colliders[0]
    assert ball.radius == pytest.approx(0.03) and ball.thickness == pytest.approx(0.003)   # not the fallback 1 m

    edit_stage(stage, lambda st: UsdGeom.Sphere(st.GetPrimAtPath("/Root/Colliders/ball")).GetRadiusAttr().Set(0.2, 3.0))
    with pytest.raises(InputError, match=r"radius is animated .*a collider keeps its radius") as err:
        build_scene(usd_cfg(stage).scene)
    assert err.value.where.endswith(":/Root/Colliders/ball")


def test_an_inactive_hair_prim_is_refused(stage):
    from usd_helpers import edit_stage, usd_cfg

    from hairexp.app.builders import build_scene

    edit_stage(stage, lambda st: st.GetPrimAtPath("/Root/Body/Hair").SetActive(False))
    with pytest.raises(InputError, match=r"is inactive \(active = false\)") as err:
        build_scene(usd_cfg(stage).scene)
    assert err.value.where.endswith(":/Root/Body/Hair")


def test_animated_hair_points_are_warned_about(stage, caplog):
    from pxr import UsdGeom
    from usd_helpers import edit_stage, usd_cfg

    from hairexp.app.builders import build_scene

    def animate(st):
        a = UsdGeom.BasisCurves(st.GetPrimAtPath("/Root/Body/Hair")).GetPointsAttr()
        a.Set(a.Get(), 1.0)
        a.Set(a.Get(), 2.0)

    edit_stage(stage, animate)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        build_scene(usd_cfg(stage).scene)
    assert any("the hair's points are animated (2 time samples)" in r.getMessage() for r in caplog.records)


def test_end_time_code_alone_gives_the_frames_and_a_fractional_end_is_refused(stage):
    from usd_helpers import edit_stage, usd_cfg

    from hairexp.io.usd_read import stage_timing

    def end_only(st):
        st.GetRootLayer().ClearStartTimeCode()
        st.GetRootLayer().endTimeCode = 3

    edit_stage(stage, end_only)
    assert stage_timing(usd_cfg(stage)).frames == 3
    edit_stage(stage, lambda st: setattr(st.GetRootLayer(), "endTimeCode", 2.5))
    with pytest.raises(InputError, match=r"endTimeCode 2.5 is 2.5 frames at \d+ fps, not a whole number"):
        stage_timing(usd_cfg(stage))


# 2. config

@pytest.mark.parametrize("overrides, key, match", [
    ({"collision__contact": "barrier", "collision__barrier_dhat": 1e6}, "collision.barrier_dhat",
     r"must be > 0 and <= 10, got 1e\+06"),
    ({"scene__gravity": [0.0, -1e300, 0.0]}, "scene.gravity", r"larger than 1000 m/s\^2"),
    ({"guides__source": "rigid", "guides__collide": True}, "guides.collide", r"does not simulate the guides"),
])
def test_unbounded_or_unused_settings_are_refused(base, overrides, key, match):
    with pytest.raises(InputError, match=match) as err:
        assemble_scene(updated(base, **overrides), settle=False)
    assert err.value.where == key


def test_a_huge_rotate_angle_names_the_edit(base):
    from hairexp.app.experiment import apply_overrides

    edit = "{guide: 0, kind: rotate, axis: [0.0, 0.0, 1.0], angle_deg: 1e308, times: [0.0, 0.1], weights: [0.0, 1.0]}"
    with pytest.raises(InputError, match=r"within \+-36000 \(100 turns\), got 1e\+308") as err:
        assemble_scene(apply_overrides(base, [f"guides.edits=[{edit}]"], "test"), settle=False)
    assert err.value.where == "guides.edits[0].angle_deg"


def test_the_block_does_not_start_under_its_rail_and_the_measure_reads_the_bodys_rail():
    cfg = compose_config(["experiment=stylization_smoke", "variants=[]", "frames=2", "logging.rerun=false"])
    with pytest.raises(InputError, match=r"5 m below its rail") as err:
        assemble(updated(cfg, scene__body__rail_height=5.0))
    assert err.value.where == "scene.body.rail_height"
    with pytest.raises(InputError, match=r"scene.body.rail_end = 1: block_rail measures the block against its own "
                                         r"rail; set measure.rail_end=1 too") as err:
        assemble(updated(cfg, scene__body__rail_end=1.0))
    assert err.value.where == "measure.rail_end"
    assemble(updated(cfg, scene__body__rail_end=1.0, measure__rail_end=1.0))   # both moved: runs


def test_a_guide_file_fps_is_bounded(base, tmp_path):
    g = tmp_path / "g.npz"
    pts = np.zeros((4, 6, 3))
    pts[:, :, 1] = -np.linspace(0, 0.3, 6)
    np.savez(g, guide_positions=pts, guide_offsets=np.array([0, 6]), fps=np.array(1e-9))
    cfg = updated(base, guides__source="file", guides__file=str(g), guides__edits=[])
    with pytest.raises(InputError, match=r"fps must be a number from 0.1 to 100000 .*got 1e-09") as err:
        assemble_scene(cfg, settle=False)
    assert err.value.where.endswith("g.npz")


def test_far_procedural_guides_name_the_keys_that_placed_them(base):
    # (scene.length itself is at most 100 m since round 14 of the probe: guides scaled 200 times reach 20 km)
    with pytest.raises(InputError, match=r"more than 10000 m from the origin.*built from scene.length"):
        assemble_scene(updated(base, scene__length=100.0, scene__n_vertices=10, guides__source="scaled",
                               guides__scale_factors=[200.0], guides__scale_times=[0.0]), settle=False)


def test_a_long_run_is_announced_by_its_estimated_time(caplog):
    from hairexp.app import guard

    est = guard.Estimate(memory=1e6, disk=1e6, steps=4000, settle_steps=0, seconds=2e4)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        guard.check(est, "scene.n_strands", allow_large=False, available=None)
    assert any("long run" in r.getMessage() and "5.56 h" in r.getMessage() for r in caplog.records), \
        [r.getMessage() for r in caplog.records]


# 3. run folders and signals

def test_overwrite_drops_the_previous_runs_log_lines(tmp_path):
    out = tmp_path / "run"
    first = run_cli([*SMALL, "solver.dt=0.05", f"hydra.run.dir={out}"], tmp_path)   # warns: dt longer than a frame
    assert first.returncode == 0, first.stderr
    assert "longer than a frame" in (out / "__main__.log").read_text()
    second = run_cli([*SMALL, "overwrite=true", f"hydra.run.dir={out}"], tmp_path)
    assert second.returncode == 0, second.stderr
    log = (out / "__main__.log").read_text()
    assert "longer than a frame" not in log and log.count("goaling/free: 2 steps") == 1, log


def test_a_signal_after_the_completed_summary_leaves_the_run_completed(tmp_path, monkeypatch):
    """A SIGTERM while the completed summary is written (or after): the run stays completed, its
    files whole, and the caller learns of the signal (the command line: exit 143, saying so)."""
    import hairexp.app.run as run_mod

    real = run_mod.write_json

    def write_then_signal(path, data, *a, **k):
        real(path, data, *a, **k)
        if isinstance(data, dict) and data.get("status") == "completed":
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(run_mod, "write_json", write_then_signal)
    take_late()
    out = tmp_path / "run"
    res = cli.job(compose_config(SMALL), str(out))
    assert res["status"] == "completed" and res["code"] == 143, res
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"
    assert (out / "result.npz").is_file() and (out / "metrics.parquet").is_file()
    assert take_late() is None


def test_a_finished_recording_of_an_interrupted_run_is_kept_as_partial(tmp_path, monkeypatch):
    """A signal after recording.rrd was finished but before the summary: the interrupted run
    keeps the recording, named as an unfinished run's (it was deleted)."""
    import hairexp.app.run as run_mod

    real = run_mod.free_reserve

    def interrupt(out):
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(run_mod, "free_reserve", lambda out: (interrupt(out) if (Path(out) / "recording.rrd").is_file()
                                                               else real(out)))
    out = tmp_path / "run"
    cfg = compose_config([*SMALL[:-1], "logging.rerun=true", "logging.progress=false"])
    res = cli.job(cfg, str(out))
    assert res["status"] == "interrupted" and res["code"] == 143, res
    assert (out / "recording.partial.rrd").is_file() and not (out / "recording.rrd").exists()
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"


def test_a_signal_inside_a_finaliser_is_raised_after_it():
    """Raised inside a __del__ the interrupt was printed as "Exception ignored" and lost (a sweep
    job ran on until it was killed, its summary left "running")."""
    class Slow:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            total = 0
            for i in range(20000):   # bytecodes after the signal, inside the finaliser
                total += i

    with pytest.raises(Interrupted):
        with InterruptSignals():
            Slow()   # finalised at once; the signal comes back once it has returned
            time.sleep(2.0)   # (ended at once by the interrupt)


def test_a_sweep_into_a_used_sweep_folder_is_refused(tmp_path):
    folder = tmp_path / "sweep"
    (folder / "0").mkdir(parents=True)
    (folder / "multirun.yaml").write_text("x: 1\n")
    msg = cli.used_dir_error(["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={folder}"])
    assert msg is not None and "the sweep folder is not empty (0, multirun.yaml)" in msg, msg
    assert cli.used_dir_error(["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={tmp_path / 'new'}"]) is None


@pytest.mark.parametrize("arg, needle", [
    ("hydra.foo=1", "hydra.foo: not a key of Hydra's config: hydra has "),   # round 32: Hydra's 'use +hydra.foo' no more
    ("hydra.job.chdir=maybe", "'maybe' is not a valid bool"),
])
def test_hydra_key_typos_are_one_line(arg, needle):
    msg = cli.config_error([*SMALL, arg])
    assert msg is not None and msg.startswith("hairexp: error: ") and needle in msg and "\n" not in msg, msg
    assert cli.config_error([*SMALL, "hydra.job.chdir=false"]) is None


# 4. API and export

def test_step_names_a_dt_that_is_not_a_number_and_a_time_that_is_not_finite(base):
    run = assemble(base)
    s0 = run.initial_state()
    with pytest.raises(ValueError, match=r"dt must be a finite number > 0 \(s\), got '0.01'"):
        run.simulator.step(s0, "0.01")
    with pytest.raises(ValueError, match=r"the state's time must be a finite number \(s\), got nan"):
        run.simulator.step(dataclasses.replace(s0, time=float("nan")), run.dt)


def test_export_of_a_stage_config_says_the_stages_frames(tmp_path, capsys):
    from hairexp.app.export_scene import main as export_main

    src = tmp_path / "a.usda"
    assert export_main([str(src), "experiment=goaling_smoke", "frames=4"]) == 0
    capsys.readouterr()
    assert export_main([str(tmp_path / "b.usda"), "experiment=from_usd", f"scene.usd={src}"]) == 0
    assert "4 frames" in capsys.readouterr().out


def test_a_sweep_job_killed_before_its_ending_is_ended_by_the_sweep(tmp_path, monkeypatch, capsys):
    """A sweep's teardown killed a worker before its job wrote its ending: the job's summary.json
    stayed "running" with its .ending.reserve, and the report said "running (exit 1)"."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()   # a pid that no longer runs
    job = tmp_path / "0"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("- solver.dt=0.04\n")
    (job / "summary.json").write_text(json.dumps({"status": "running", "pid": dead.pid,
                                                  "host": __import__("socket").gethostname()}))
    (job / ".ending.reserve").write_bytes(b"\0" * 16)
    cli._write_outcome(job, cli.outcome(job, "running", 1, "the job did not finish"))
    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 1)
    assert cli.exit_code(signal.SIGTERM) == 143
    summary = json.loads((job / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "ended before it wrote its ending" in summary["error"], summary
    assert not (job / ".ending.reserve").exists()
    assert "job 0 [solver.dt=0.04]: interrupted (exit 143)" in capsys.readouterr().err
