"""Findings of issue 12's twelfth probe round, one test each."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hairexp.errors import InputError

SMOKE = ["experiment=goaling_smoke", "variants=[]", "frames=3", "logging.rerun=false", "logging.progress=false"]


@pytest.mark.parametrize("name", ["result.usdc", "recording.rrd"])
def test_a_folder_made_at_a_result_name_during_the_run_is_left_alone(tmp_path, monkeypatch, name):
    """Another process made a folder (with a file in it) at a result file's name while the run
    went on: the run fails (its results cannot take their names), and the folder and its file are
    left as they were (they were deleted with the run's own partial results)."""
    import hairexp.app.run as run_module
    from hairexp.app.config import compose_config

    out = tmp_path / "r"
    real = run_module.write_npz

    def write_then_intrude(*args, **kwargs):
        real(*args, **kwargs)
        (out / name).mkdir()
        (out / name / "keep.txt").write_text("someone else's")

    monkeypatch.setattr(run_module, "write_npz", write_then_intrude)
    overrides = SMOKE if name != "recording.rrd" else [o for o in SMOKE if o != "logging.rerun=false"]
    with pytest.raises(OSError, match=f"{name}: a folder of that name appeared in the run folder while the run went on"):
        run_module.run(compose_config(overrides), out)
    assert (out / name / "keep.txt").read_text() == "someone else's"
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "failed" and "appeared in the run folder" in s["error"]
    assert not (out / "result.npz").exists()   # the run's own results go, as for any late failure


def test_a_body_keyed_far_from_the_origin_is_refused():
    """A USD body translated 1e20 m at one time code ran to the end (exit 0, 7 of 10 steps
    unconverged): a motion's translations are checked like the curves' points."""
    from hairexp.model import RigidMotion

    with pytest.raises(InputError, match=r"motion.translations: the translation at keyframe 1 \(t = 0.1 s\) is "
                                         r"\[1e\+20, 0.0, 0.0\], more than 10000 m from the origin"):
        RigidMotion(np.array([0.0, 0.1]), np.array([[0.0, 0.0, 0.0], [1e20, 0.0, 0.0]]), np.zeros((2, 3)))
    RigidMotion(np.array([0.0, 100.0]), np.array([[0.0, 0.0, 0.0], [9e3, 0.0, 0.0]]), np.zeros((2, 3)))   # 90 m/s


def test_coincident_strands_are_refused():
    from hairexp.model.builders import straight_strands

    with pytest.raises(InputError, match="scene.root_radius: must be > 0 for 3 strands without scene.spread"):
        straight_strands(3, 8, 0.2, 0.0, np.zeros(3), np.array([0.0, -1.0, 0.0]), spread=0.0, seed=0)
    straight_strands(1, 8, 0.2, 0.0, np.zeros(3), np.array([0.0, -1.0, 0.0]), spread=0.0, seed=0)   # one strand: fine


def test_a_root_centre_far_from_the_origin_is_refused():
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match=r"scene.root_center: \[1e\+20, 0.0, 0.0\] is more than 10000 m"):
        assemble(compose_config(SMOKE + ["scene.root_center=[1e20,0.0,0.0]"]))


@pytest.mark.parametrize("name, content", [("summary.json", "my notes"), ("summary.json", '{"a": 1}'),
                                           ("metrics.parquet", "a,b\n1,2\n"), ("result.npz", "")])
def test_overwrite_keeps_a_file_that_only_has_a_run_files_name(tmp_path, name, content):
    """overwrite=true deleted a user's text saved as summary.json or metrics.parquet."""
    from hairexp.outputs.folder import claim

    out = tmp_path / "r"
    out.mkdir()
    (out / name).write_text(content)
    with pytest.raises(InputError, match=f"overwrite=true removes only what a run wrote; the folder also holds {name}"):
        claim(out, overwrite=True)
    assert (out / name).read_text() == content


def test_overwrite_still_replaces_a_run(tmp_path):
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    run(compose_config(SMOKE), tmp_path / "r")
    run(compose_config(SMOKE + ["overwrite=true", "frames=2"]), tmp_path / "r")
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["status"] == "completed"
    with np.load(tmp_path / "r" / "result.npz") as r:
        assert len(r["times"]) == 3   # frames 0..2: the new run's, not the replaced one's 0..3


def test_a_variant_cannot_set_overwrite():
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import apply_overrides

    with pytest.raises(InputError, match="a variant cannot set 'overwrite': it belongs to the launch"):
        apply_overrides(compose_config(SMOKE), ["overwrite=true"], "variants[0] (free)")


def test_a_full_disk_under_the_recording_is_named(monkeypatch):
    """rerun's writer only logs its ENOSPC; the run's error said 'did not finish within 60 s'."""
    import errno

    import hairexp.outputs.rerun_sink as rs

    class Stuck:
        def flush(self, timeout_sec):
            raise RuntimeError("Flush timed out - not all log messages were sent")

    monkeypatch.setattr(rs, "_free_bytes", lambda path: 0)
    monkeypatch.setattr(rs.rr, "unregister_shutdown", lambda: None)
    rec = Stuck()
    with pytest.raises(OSError, match=r"no space left on the device \(0 bytes free") as info:
        rs.flush_recording(rec, "/x/recording.partial.rrd")
    assert info.value.errno == errno.ENOSPC
    rs._ABANDONED.remove(rec)


def test_guide_shape_keys_a_file_does_not_use_are_warned(tmp_path, caplog):
    from hairexp.app.config import compose_config
    from hairexp.app.guides import unused_shape_keys
    from hairexp.guides.animation import GuideAnimation

    frames = np.zeros((2, 6, 3)) + np.arange(3)[None, :, None].repeat(2, 0).reshape(1, 6, 1) * [0.0, -0.1, 0.0]
    anim = GuideAnimation(frames, np.array([0, 3, 6]), 25.0)
    cfg = compose_config(SMOKE + ["guides.count=5"])
    with caplog.at_level("WARNING", logger="hairexp"):
        unused_shape_keys(cfg.guides, anim, "guides.file")
    assert "guides.count=5 is not used: the guides come from guides.file, which holds 2 guides" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="hairexp"):
        unused_shape_keys(compose_config(SMOKE + ["guides.count=1", "guides.n_vertices=8"]).guides, anim, "x")
    assert caplog.text == ""   # the schema's defaults were not chosen: no warning


def test_procedural_keys_a_stage_does_not_use_are_named():
    from hairexp.app.builders import unused_procedural_keys
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=from_usd", "scene.usd=x.usda", "scene.n_strands=3", "scene.direction=[0,1,0]"])
    assert unused_procedural_keys(cfg.scene) == ["scene.n_strands=3", "scene.direction=[0.0, 1.0, 0.0]"]
    assert unused_procedural_keys(compose_config(["experiment=from_usd", "scene.usd=x.usda"]).scene) == []


def test_a_launch_inside_a_live_runs_folder_is_told_so_before_its_files(tmp_path):
    """``hydra.run.dir=<live run>/stream``: the error said the folder was not empty (set
    overwrite=true) instead of naming the live launch; nothing is taken or created."""
    from hairexp.app.cli import live_folder_error, used_dir_error
    from hairexp.outputs.folder import hold

    live = tmp_path / "runA"
    assert hold(live)   # this process plays the live run: another open of its lock is another launch
    (live / "stream").mkdir()
    (live / "stream" / "positions.npy").write_bytes(b"x")
    argv = [*SMOKE, f"hydra.run.dir={live / 'stream'}"]
    assert "not empty" in (used_dir_error(argv) or "")
    msg = live_folder_error(argv)
    assert msg is not None and "lies inside" in msg and str(live) in msg
    assert not (live / "stream" / ".lock").exists()
    msg = live_folder_error([*SMOKE, f"hydra.run.dir={live}"])
    assert msg is not None and "another launch is using this run folder now" in msg
    assert live_folder_error([*SMOKE, f"hydra.run.dir={tmp_path / 'other'}"]) is None
    assert not (tmp_path / "other").exists()


def test_a_size_the_collider_shape_does_not_read_is_refused():
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    ball = "scene.colliders=[{name: b, shape: sphere, radius: 0.05, half_height: 0.3}]"
    with pytest.raises(InputError, match=r"scene.colliders\[0\].half_height: is 0.3, but a sphere does not read it "
                                         r"\(it reads radius\)"):
        validate_config(compose_config(SMOKE + [ball]))
    validate_config(compose_config(SMOKE + ["scene.colliders=[{name: b, shape: sphere, radius: 0.05}]"]))
    validate_config(compose_config(["experiment=goaling", "variants=[]"]))   # a cylinder's half_height: read


@pytest.mark.parametrize("key", ["solver.max_iterations", "tracking.max_iterations"])
def test_an_iteration_budget_no_solve_needs_is_refused(key):
    """1e8 iterations with an unreachable tolerance ran with no step for minutes (no estimate)."""
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with pytest.raises(InputError, match=f"{key}: must be at most 10000"):
        validate_config(compose_config(SMOKE + [f"{key}=100000000"]))
    validate_config(compose_config(SMOKE + [f"{key}=10000"]))


def test_no_step_converged_names_the_statuses_as_counts():
    import pandas as pd

    from hairexp.app.run import convergence_error

    why = convergence_error(pd.DataFrame({"converged": [False] * 3, "status": ["max_iterations"] * 3,
                                          "dt": [0.04] * 3, "time": [0.04, 0.08, 0.12]}), "warn")
    assert why == "no step converged (3 steps: 3 with status max_iterations)"


def test_guides_far_off_the_body_are_refused():
    """Guides made on goaling's moving body reused on a still one (roots 0.47 m off the body), or
    a guide file 2-5 m off the roots: "completed" at 515-1,395 % stretch with only a warning."""
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config
    from hairexp.app.guides import warn_far_guides
    from hairexp.guides.animation import GuideAnimation

    run = assemble(compose_config(SMOKE + ["controller=tracking"]))
    scene, g = run.scene, run.guides
    P = np.array(g.positions)
    moved = P.copy()
    moved[2:] += [0.2, 0.0, 0.0]   # from frame 2 on, the whole guide 0.2 m (2/3 of the 0.3 m wisp) aside
    with pytest.raises(InputError, match=r"guides: guide 0's root is 0.2 m from where the body carries it at frame 2 "
                                         r".*more than 0.5 of the hair's length"):
        warn_far_guides(scene, GuideAnimation(moved, g.offsets, g.fps))
    creeping = P.copy()
    creeping[1:] += [0.005, 0.0, 0.0]   # a warning's drift first (it stopped the check there), the error's later
    creeping[3:] += [0.2, 0.0, 0.0]
    with pytest.raises(InputError, match=r"guide 0's root is 0.205 m from where the body carries it at frame 3"):
        warn_far_guides(scene, GuideAnimation(creeping, g.offsets, g.fps))
    far = P + [2.0, 0.0, 0.0]
    with pytest.raises(InputError, match=r"guides: guide 0.s root is 1.98 m from the nearest hair root at frame 0, "
                                         r"farther than the hair is long"):
        warn_far_guides(scene, GuideAnimation(far, g.offsets, g.fps))
    warn_far_guides(scene, g)   # its own guides: fine


def test_a_dynamic_block_launched_at_1e9_m_per_s_is_refused():
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with pytest.raises(InputError, match=r"scene.body.velocity\[0\]: must be >= -1000 and <= 1000, got 1e\+09"):
        validate_config(compose_config(["experiment=stylization_smoke", "variants=[]", "scene.body.velocity=[1e9,0.0,0.0]"]))


def test_a_variant_that_did_not_solve_its_steps_gets_no_verdict():
    from hairexp.app.experiment import unjudgeable

    ok = {"free": {"converged_fraction": 1.0, "stretch_max": 0.01, "steps": 30, "unconverged_steps": 0},
          "tracked": {"converged_fraction": 29 / 30, "stretch_max": 0.1, "steps": 30, "unconverged_steps": 1}}
    assert unjudgeable(ok) is None
    bad = {**ok, "tracked": {"converged_fraction": 4 / 30, "stretch_max": 5.81, "steps": 30, "unconverged_steps": 26}}
    why = unjudgeable(bad)
    assert "tracked: 26 of 30 steps did not converge" in why and "tracked: its hair stretched by 581 %" in why


def test_reserved_names_and_links_in_hydras_record_are_refused(tmp_path):
    from hairexp.app.cli import reserved_part, run_dir_error, used_dir_error

    assert "keeps for Hydra" in run_dir_error([*SMOKE, f"hydra.run.dir={tmp_path}/a/.hydra"])
    assert "keeps for the launch lock" in run_dir_error(["-m", *SMOKE, f"hydra.sweep.dir={tmp_path}/.lock/s"])
    msg = used_dir_error(["-m", *SMOKE, "frames=2,3", f"hydra.sweep.dir={tmp_path}/sw",
                          "hydra.sweep.subdir=.hydra/${hydra.job.num}"])
    assert msg is not None and "cannot be a job folder" in msg
    assert reserved_part("a/.hydrated/b") is None
    victim = tmp_path / "victim.yaml"
    victim.write_text("precious")
    (tmp_path / "r" / ".hydra").mkdir(parents=True)
    (tmp_path / "r" / ".hydra" / "config.yaml").symlink_to(victim)
    msg = used_dir_error([*SMOKE, f"hydra.run.dir={tmp_path / 'r'}"])
    assert msg is not None and "holds symbolic links (config.yaml)" in msg
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / ".hydra").symlink_to(tmp_path)
    assert "is a symbolic link" in used_dir_error([*SMOKE, f"hydra.run.dir={tmp_path / 's'}"])
    assert victim.read_text() == "precious"


def test_overwrite_refuses_a_run_whose_input_is_in_the_folder(tmp_path):
    """guides.file=<dir>/guides.npz with overwrite=true into <dir>: the previous run was deleted,
    then the new one failed with 'no such file' (both lost)."""
    from hairexp.app.cli import used_dir_error
    from hairexp.app.config import compose_config
    from hairexp.app.run import inputs_inside, run

    d = tmp_path / "r"
    run(compose_config(SMOKE), d)
    again = SMOKE + ["guides.source=file", "guides.edits=[]", f"guides.file={d / 'guides.npz'}", "overwrite=true"]
    with pytest.raises(InputError, match="guides.file=.*guides.npz lies inside the run folder that overwrite=true"):
        run(compose_config(again), d)
    assert (d / "guides.npz").is_file() and (d / "result.npz").is_file()   # the previous run kept
    msg = used_dir_error([*again, f"hydra.run.dir={d}"])
    assert msg is not None and "lies inside the run folder" in msg
    assert inputs_inside(compose_config(SMOKE + ["scene.usd=/elsewhere/s.usda"]), d) is None


def test_a_killed_sweep_worker_is_one_line_not_a_traceback(monkeypatch, capsys, tmp_path):
    """joblib's TerminatedWorkerError (a worker killed by SIGKILL or the out-of-memory killer) went
    through Hydra's traceback, exit 1, and the jobs' summaries stayed running; now one line, and
    the jobs are reported (``cli.exit_code``, which ends a dead job's summary as failed)."""
    import sys

    import hairexp.__main__ as entry_module
    from joblib.externals.loky.process_executor import TerminatedWorkerError

    def killed():
        raise TerminatedWorkerError("A worker process managed by the executor was unexpectedly terminated.")

    monkeypatch.setattr(entry_module, "main", killed)
    monkeypatch.setattr(entry_module.cli, "exit_code", lambda *a: 1)
    monkeypatch.setattr(sys, "argv", ["hairexp", "-m", *SMOKE, "frames=2,3", f"hydra.sweep.dir={tmp_path / 'sw'}"])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "placeholder")   # recorded: restored (unset) after the test
    monkeypatch.delenv("HYDRA_FULL_ERROR")
    assert entry_module.entry() == 1
    err = capsys.readouterr().err
    assert "hairexp: a sweep worker process ended abruptly" in err and "Traceback" not in err
    import os
    assert os.environ.get("HYDRA_FULL_ERROR") == "1"   # so that Hydra lets the launcher's error through


def test_a_run_inside_another_runs_folder_is_refused(tmp_path):
    from hairexp.app.cli import used_dir_error

    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "summary.json").write_text('{"status": "completed"}')
    msg = used_dir_error([*SMOKE, f"hydra.run.dir={tmp_path / 'done' / 'nested'}"])
    assert msg is not None and "lies inside" in msg and "another run's folder" in msg
    msg = used_dir_error(["-m", *SMOKE, "frames=2,3", f"hydra.sweep.dir={tmp_path / 'done' / 'sw'}"])
    assert msg is not None and "another run's folder" in msg
    assert used_dir_error([*SMOKE, f"hydra.run.dir={tmp_path / 'fresh' / 'a'}"]) is None


@pytest.mark.parametrize("override, match", [
    ("scene.motion.rotations_deg=[[1e9,0.0,0.0]]", r"scene.motion.rotations_deg\[0\]: must be within \+-36000 degrees"),
    ("guides.scale_factors=[1e9]", r"guides.scale_factors\[0\]: must be > 0 and <= 1000"),
])
def test_key_values_beyond_any_use_are_named(override, match):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match=match):
        assemble(compose_config(SMOKE + ["scene.motion.times=[0.0]", "scene.motion.translations=[[0.0,0.0,0.0]]",
                                         "scene.motion.rotations_deg=[[0.0,0.0,0.0]]", override]))


def test_an_unknown_experiment_is_an_input_error():
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match=r"experiment: no such option 'nosuch' of the config group experiment "
                                         r"\(options: celia, "):
        compose_config(["experiment=nosuch"])


def test_inactive_usd_prims_are_named(tmp_path, caplog):
    from pxr import Usd
    from usd_helpers import COLLIDERS, source_cfg, usd_cfg, write_stage

    from hairexp.io.usd_read import build_usd_scene, read_guides

    base = tmp_path / "base.usda"
    write_stage(base, source_cfg(colliders=COLLIDERS))
    st = Usd.Stage.Open(str(base))
    st.GetPrimAtPath("/Root/Colliders/wheel").SetActive(False)
    st.GetRootLayer().Export(str(tmp_path / "off.usda"))
    with caplog.at_level("WARNING", logger="hairexp"):
        scene = build_usd_scene(usd_cfg(tmp_path / "off.usda").scene)
    assert "inactive collider prim(s) not used: /Root/Colliders/wheel" in caplog.text
    assert "wheel" not in [c.name for c in scene.colliders]
    st.GetPrimAtPath("/Root").SetActive(False)
    st.GetRootLayer().Export(str(tmp_path / "root_off.usda"))
    with pytest.raises(InputError, match=r":/Root: is inactive \(active = false\), so /Root/Body"):
        build_usd_scene(usd_cfg(tmp_path / "root_off.usda").scene)


def test_a_dotdot_after_an_interpolation_in_the_run_folder_is_refused(tmp_path):
    from hairexp.app.cli import run_dir_error

    msg = run_dir_error([*SMOKE, f"hydra.run.dir={tmp_path}/runs/${{now:%Y}}/../na4"])
    assert msg is not None and "a '..' after an interpolation" in msg
    assert not (tmp_path / "runs").exists()
    assert run_dir_error([*SMOKE, f"hydra.run.dir={tmp_path}/runs/${{now:%Y}}/na4"]) is None


def test_a_name_after_set_is_a_usage_error(capsys):
    from experiments import paper_scenes

    with pytest.raises(SystemExit) as info:
        paper_scenes.main(["--set", "solver.dt=0.02", "goaling_smoke"])
    assert info.value.code == 2
    assert "'goaling_smoke' is not KEY=VALUE" in capsys.readouterr().err


def test_usd_colliders_are_named_by_their_prim(tmp_path):
    from usd_helpers import COLLIDERS, source_cfg, usd_cfg, write_stage

    from hairexp.io.usd_read import build_usd_scene
    from hairexp.model import Scene

    write_stage(tmp_path / "s.usda", source_cfg(colliders=COLLIDERS))
    scene = build_usd_scene(usd_cfg(tmp_path / "s.usda").scene)
    wheel = next(c for c in scene.colliders if c.name == "wheel")
    assert wheel.where == f"scene.usd={tmp_path / 's.usda'}:/Root/Colliders/wheel"
    with pytest.raises(InputError, match=r"'wheel' is used more than once \('wheel' from scene.usd=.*/Root/Colliders/"
                                         r"wheel; 'wheel' from scene.usd="):
        Scene(scene.name, scene.strands, scene.material, scene.motion, scene.gravity, scene.strands.rest,
              colliders=[wheel, wheel])


def test_a_keyframed_jump_faster_than_sound_is_refused():
    """A USD body jumping 100 m between two samples ran "completed" at 299,900 % stretch."""
    from hairexp.model import RigidMotion

    with pytest.raises(InputError, match=r"motion.translations: moves 2500 m/s between keyframes 1 and 2 "
                                         r"\(t = 0.04 and 0.08 s\), more than 1000 m/s"):
        RigidMotion(np.array([0.0, 0.04, 0.08]), np.array([[0.0, 0, 0], [0.0, 0, 0], [100.0, 0, 0]]), np.zeros((3, 3)))
    RigidMotion(np.array([0.0, 0.04]), np.array([[0.0, 0, 0], [0.4, 0, 0]]), np.zeros((2, 3)))   # 10 m/s: fine
