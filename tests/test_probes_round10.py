"""Findings of issue 12's tenth probe round (an independent tester's bad inputs and abuse), one
test each: run folders that do not mix, sweeps that stop and stay inside their folder, named
errors from the Python API, and summaries that agree with themselves."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from helpers import REPO
from hairexp.errors import InputError, SimulationError

PY = [sys.executable, "-m", "hairexp"]
ENV = {**os.environ, "CI": "true"}


def finished_run(folder: Path) -> None:
    """A folder as a completed run leaves it (the files only)."""
    folder.mkdir(parents=True)
    (folder / ".hydra").mkdir()
    for name, head in (("metrics.parquet", b"PAR1"), ("result.npz", b"PK\x03\x04"), ("guides.npz", b"PK\x03\x04")):
        (folder / name).write_bytes(head + b"x")   # the format's first bytes: a run's files
    (folder / "summary.json").write_text(json.dumps({"status": "completed"}))


# -- run folders ------------------------------------------------------------------------------

def test_overwrite_refuses_a_symlink_and_deletes_nothing(tmp_path):
    """A link planted in a finished run's folder: overwrite=true refuses (it deleted the results,
    then failed on the link, leaving a summary that said completed)."""
    from hairexp.outputs.folder import claim, overwrite_refusal

    run = tmp_path / "run"
    finished_run(run)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep").write_text("keep")
    (run / "stream").symlink_to(victim)
    assert "stream" in overwrite_refusal(run)
    with pytest.raises(InputError, match="stream"):
        claim(run, overwrite=True)
    assert sorted(p.name for p in run.iterdir()) == [".hydra", "guides.npz", "metrics.parquet", "result.npz",
                                                      "stream", "summary.json"]
    assert (victim / "keep").read_text() == "keep"


def test_overwrite_removes_the_old_summary_first(tmp_path, monkeypatch):
    """If a removal fails midway, no summary saying "completed" is left beside deleted results."""
    import hairexp.outputs.folder as folder

    run = tmp_path / "run"
    finished_run(run)
    removed = []
    real_unlink = Path.unlink

    def unlink(self, *a, **k):
        removed.append(self.name)
        if len(removed) == 2:
            raise OSError("disk went away")
        return real_unlink(self, *a, **k)

    monkeypatch.setattr(Path, "unlink", unlink)
    with pytest.raises(OSError, match="overwrite=true could not remove the previous run's"):
        folder.claim(run, overwrite=True)
    monkeypatch.undo()
    assert removed[0] == "summary.json"
    # the old "completed" summary is gone; the folder says the removal failed (round 25: it said nothing)
    s = json.loads((run / "summary.json").read_text())
    assert s["status"] == "failed" and "could not remove" in s["error"]


def test_the_launch_lock_is_exclusive(tmp_path):
    from hairexp.outputs.folder import LOCK, hold, used_entries

    f = tmp_path / "run"
    assert hold(f)
    assert not hold(f)   # a second open of the lock file: another launch
    assert (f / LOCK).is_file()
    assert used_entries(f) == []   # the lock alone is no run


def test_a_second_launch_into_a_held_folder_is_refused_before_hydra(tmp_path):
    """Another process holds the run folder (a launch that has not ended): the second launch exits 2
    and writes no .hydra/ record (it rewrote the running one's)."""
    f = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path; "
                               "from hairexp.outputs.folder import hold; assert hold(Path(sys.argv[1])); "
                               "print('held', flush=True); time.sleep(60)", str(f)],
                              cwd=REPO, stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "held"
        p = subprocess.run(PY + ["experiment=goaling_smoke", "variants=[]", "frames=2", f"hydra.run.dir={f}"],
                           cwd=REPO, capture_output=True, text=True, timeout=120, env=ENV)
    finally:
        holder.kill()
        holder.wait()
    assert p.returncode == 2, p.stderr
    assert "another launch is using this run folder" in p.stderr
    assert "Traceback" not in p.stderr
    assert not (f / ".hydra").exists()


# -- sweeps -----------------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["../../../escaped", "/../../../tmp/escaped"])
def test_a_sweep_subdir_template_cannot_climb_out_through_a_value(value):
    from hairexp.app.cli import used_dir_error

    argv = ["-m", "experiment=goaling_smoke", f"scene.name=ok,{value}", "hydra.sweep.dir=/tmp/hx_sweep_probe/a/b",
            "hydra.sweep.subdir=${hydra.job.override_dirname}"]
    msg = used_dir_error(argv)
    assert msg is not None and "outside the sweep folder" in msg and value in msg
    # values without path parts are fine
    ok = ["-m", "experiment=goaling_smoke", "scene.name=ok,other", "hydra.sweep.dir=/tmp/hx_sweep_probe/c",
          "hydra.sweep.subdir=${hydra.job.override_dirname}"]
    assert used_dir_error(ok) is None


def test_a_config_key_in_the_subdir_is_resolved_per_job():
    from hairexp.app.cli import used_dir_error

    argv = ["-m", "experiment=goaling_smoke", "scene.name=fine,../../up", "hydra.sweep.dir=/tmp/hx_sweep_probe/d",
            "hydra.sweep.subdir=${scene.name}"]
    msg = used_dir_error(argv)
    assert msg is not None and "scene.name=../../up" in msg


def _wait_for(path: Path, seconds: float = 60.0) -> None:
    deadline = time.monotonic() + seconds
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} did not appear"
        time.sleep(0.1)


def test_sigterm_stops_a_basic_launcher_sweep(tmp_path):
    """hydra/launcher=basic runs the jobs in the main process: SIGTERM ended the running job and the
    launcher went on to run the others; now the sweep ends there, the rest said as not started."""
    sweep = tmp_path / "sweep"
    p = subprocess.Popen(PY + ["-m", "experiment=goaling_smoke", "variants=[]", "frames=3000", "logging.rerun=false",
                               "solver.rtol=1e-3,1e-4,1e-5", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        _wait_for(sweep / "0" / "metrics.parquet", 240)   # job 0 ends first (90 s was short with the machine loaded)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 143, err
    assert "(2 not started)" in err, err
    assert not (sweep / "1").exists() and not (sweep / "2").exists()
    assert json.loads((sweep / "0" / "summary.json").read_text())["status"] == "interrupted"


# -- signals ----------------------------------------------------------------------------------

def test_sighup_ends_a_run_as_interrupted(tmp_path):
    run = tmp_path / "run"
    p = subprocess.Popen(PY + ["experiment=goaling_smoke", "variants=[]", "frames=3000", "logging.rerun=false",
                               f"hydra.run.dir={run}"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=ENV)
    try:
        _wait_for(run / "metrics.parquet", 90)
        p.send_signal(signal.SIGHUP)
        _, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 129, err
    assert "interrupted by SIGHUP" in err
    assert json.loads((run / "summary.json").read_text())["status"] == "interrupted"


# -- checked before any run -------------------------------------------------------------------

@pytest.mark.parametrize("edit, says", [
    ("{guide: 99, kind: rotate, axis: [0.0, 0.0, 1.0], angle_deg: 30.0, times: [0.0, 0.5], weights: [0.0, 1.0]}",
     "guide index 99 out of range"),
    ("{guide: 0, kind: rotate, axis: [0.0, 0.0, 0.0], angle_deg: 30.0, times: [0.0, 0.5], weights: [0.0, 1.0]}",
     "zero vector"),
])
def test_guide_edits_are_checked_with_the_config(edit, says):
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=goaling_smoke", f"guides.edits=[{edit}]"])
    with pytest.raises(InputError, match=says) as e:
        check_config(cfg)
    assert "guides.edits[0]" in str(e.value)


def test_an_empty_zip_is_said_to_be_empty(tmp_path):
    from hairexp.guides.animation import npz_kind

    p = tmp_path / "g.npz"
    zipfile.ZipFile(p, "w").close()
    with pytest.raises(InputError, match="empty zip archive"):
        npz_kind(p, "guides.file")


def test_a_folded_simulated_guide_is_a_simulation_failure(monkeypatch):
    """The guides the simulation produced fold: the simulation failed (exit 3), named as the guides'."""
    import hairexp.app.guides as guides
    from hairexp.app.assemble import assemble_scene
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=goaling_smoke", "frames=2", "guides.source=simulated", "guides.edits=[]",
                          "scene.settle=0"])
    cfg, scene, _ = assemble_scene(cfg, settle=False)

    def folded(*a, **k):
        raise InputError("curve 0 folds back on itself at vertex 3", "guides frame 1")

    monkeypatch.setattr(guides, "GuideAnimation", folded)
    body = guides.rest_guides(cfg.scene, int(cfg.guides.count), int(cfg.guides.n_vertices),
                              float(cfg.guides.layout_radius))
    offsets = np.arange(int(cfg.guides.count) + 1) * int(cfg.guides.n_vertices)
    with pytest.raises(SimulationError, match="guide simulation .* folds back"):
        guides.simulate_guides(cfg, scene, body, offsets, 2, float(cfg.fps))


# -- summaries --------------------------------------------------------------------------------

def test_a_failed_runs_aggregates_count_the_failed_step(tmp_path):
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    cfg = compose_config(["experiment=goaling", "variants=[]", "solver.max_iterations=1", "solver.on_failure=fail",
                          "guides.source=rigid", "guides.edits=[]", "logging.rerun=false", "logging.progress=false"])
    with pytest.raises(SimulationError):
        run(cfg, tmp_path / "r")
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert s["status"] == "failed" and s["converged"] is False
    assert s["unconverged_steps"] == 1 and s["failed_step"] == s["steps"] + 1
    assert s["converged_fraction"] == pytest.approx(s["steps"] / (s["steps"] + 1))


def test_an_interrupted_variant_keeps_its_figures_in_the_experiment_summary(tmp_path):
    run = tmp_path / "exp"
    # the first variant is short (3 frames), the second long enough to be interrupted while it streams
    p = subprocess.Popen(PY + ["experiment=goaling_smoke", "frames=1500", "logging.rerun=false",
                               "variants=[{name: free, overrides: ['controller.name=free', 'frames=3']}, "
                               "{name: tracked, overrides: ['controller.name=tracking']}]",
                               f"hydra.run.dir={run}"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=ENV)
    try:
        names = None
        deadline = time.monotonic() + 120
        while names is None:   # the second variant has written steps
            assert time.monotonic() < deadline
            try:
                names = list(json.loads((run / "summary.json").read_text())["config"]["variants"])
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        second = names[1]["name"]
        _wait_for(run / second / "stream" / "metrics" / "part-00000.parquet", 120)   # it has streamed steps
        p.send_signal(signal.SIGTERM)
        p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 143
    v = json.loads((run / "summary.json").read_text())["variants"][second]
    assert v["status"] == "interrupted"
    assert v["steps"] and v["steps"] > 0 and v["iterations_mean"] is not None


# -- the Python API ---------------------------------------------------------------------------

def _scene_parts():
    from hairexp.model.rigid import RigidMotion
    from hairexp.model.scene import Material
    from hairexp.model.strands import Strands

    line = np.stack([np.zeros(5), -0.01 * np.arange(5), np.zeros(5)], 1)
    s = Strands.from_polylines(line, [5], 1e-4)
    return s, Material(1e-4, 20.0, 2e-6), RigidMotion.static(), line


@pytest.mark.parametrize("key, value, says", [
    ("gravity", np.array([0.0, np.nan, 0.0]), "must be finite"),
    ("gravity", np.zeros(2), "shape"),
    ("root_body", np.zeros((4, 3)), "shape"),
    ("root_body", "nan", "shape|finite|real numbers"),
])
def test_scene_names_a_bad_array(key, value, says):
    from hairexp.model.scene import Scene

    s, m, motion, line = _scene_parts()
    kw = {"gravity": np.array([0.0, -9.81, 0.0]), "root_body": line}
    kw[key] = np.full((5, 3), np.nan) if isinstance(value, str) else value
    with pytest.raises(InputError, match=says) as e:
        Scene("api", s, m, motion, kw["gravity"], kw["root_body"])
    assert f"Scene.{key}" in str(e.value)


@pytest.mark.parametrize("field, value", [("linear_density", 0.0), ("bending_stiffness", float("nan")),
                                          ("edge_damping", -5.0), ("air_drag", -50.0)])
def test_material_refuses_what_the_command_line_refuses(field, value):
    from hairexp.model.scene import Material

    kw = dict(linear_density=1e-4, stretch_stiffness=20.0, bending_stiffness=2e-6)
    kw[field] = value
    with pytest.raises(InputError, match=f"Material.{field}"):
        Material(**kw)


def test_a_zero_length_guide_edge_is_named():
    from hairexp.control.tracking.correspondence import build_correspondence

    s, _, _, line = _scene_parts()
    guide = np.array([[0.0, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, -0.02, 0.0], [0.0, -0.04, 0.0]])
    free = np.ones(5, bool)
    free[:2] = False
    with pytest.raises(InputError, match="guide 0 has a zero-length edge .points 1 and 2"):
        build_correspondence(line, np.array([0, 5]), free, [guide], 2)


def test_a_step_too_short_for_double_precision_is_refused():
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    r = assemble(compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false",
                                 "scene.settle=0"]))
    with pytest.raises(ValueError, match="below 1e-09 s"):
        r.simulator.step(r.initial_state(), 1e-300)


@pytest.mark.parametrize("change, says", [({"rtol": float("nan")}, "solver.rtol"), ({"max_iterations": 0}, "solver.max_iterations"),
                                          ({"dt": -0.01}, "solver.dt"), ({"max_substep_levels": 99}, "solver.max_substep_levels")])
def test_the_simulator_checks_its_solver_settings(change, says):
    """The Python API refuses the solver settings the command line refuses."""
    import dataclasses

    from hairexp.app.config import SolverConfig
    from hairexp.model.scene import Scene
    from hairexp.physics.simulator import Simulator

    s, m, motion, line = _scene_parts()
    scene = Scene("api", s, m, motion, np.array([0.0, -9.81, 0.0]), line)
    with pytest.raises(InputError, match=says):
        Simulator(scene, dataclasses.replace(SolverConfig(), **change))


@pytest.mark.parametrize("args, says", [(("dict",), "solver"), (("cfg", "tracking"), "Simulator controller")])
def test_the_simulator_names_wrong_argument_types(args, says):
    from hairexp.app.config import SolverConfig
    from hairexp.model.scene import Scene
    from hairexp.physics.simulator import Simulator

    s, m, motion, line = _scene_parts()
    scene = Scene("api", s, m, motion, np.array([0.0, -9.81, 0.0]), line)
    given = [{"dt": 0.01} if a == "dict" else SolverConfig() if a == "cfg" else a for a in args]
    with pytest.raises(InputError, match=says):
        Simulator(scene, *given)
