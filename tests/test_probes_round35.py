"""Findings of the independent probe round 35 of issue 12, fixed."""

from __future__ import annotations

import numpy as np
import pytest

from hairexp.errors import InputError


def _one_strand_scene():
    from hairexp.model import Material, RigidMotion, Scene, Strands

    line = np.stack([np.zeros(10), -np.linspace(0.0, 0.2, 10), np.zeros(10)], 1)
    strands = Strands.from_polylines(line, np.array([10]), 1e-4)
    still = RigidMotion(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))
    return Scene("one", strands, Material(1e-4, 10.0, 1e-7), still, np.array([0.0, -9.81, 0.0]), line)


@pytest.mark.parametrize("settings, key, said", [
    ({"hair_thickness": 10.0, "hair_hair": True}, "collision.hair_thickness", "must be > 0 and <= 0.01, got 10"),
    ({"hair_thickness": -1.0, "hair_hair": True}, "collision.hair_thickness", "must be > 0 and <= 0.01, got -1"),
    ({"hair_thickness": float("nan"), "hair_hair": True}, "collision.hair_thickness", "got nan"),
    ({"skin": float("inf"), "hair_hair": True}, "collision.skin", "got inf"),
    ({"max_passes": 0, "hair_hair": True}, "collision.max_passes", "must be >= 1, got 0"),
    ({"strain_limit": -0.5}, "collision.strain_limit", "must be >= 0 and < 1, got -0.5"),
    ({"contact": "nope"}, "collision.contact", "must be one of barrier|stage, got str 'nope'"),
])
def test_the_simulator_checks_its_collision_settings_as_the_command_line_does(settings, key, said):
    """``Simulator(..., collision_cfg=CollisionConfig(hair_thickness=10, hair_hair=True))`` ran three
    "converged" steps that moved hair 14.6 m (round 35, bad B7); negative or NaN values and
    ``max_passes=0`` were taken too (B8, W4).  The command line refused them all."""
    from hairexp.app.config import CollisionConfig, SolverConfig
    from hairexp.physics import Simulator

    with pytest.raises(InputError) as err:
        Simulator(_one_strand_scene(), SolverConfig(), collision_cfg=CollisionConfig(**settings))
    assert str(err.value).startswith(f"{key}: ") and said in str(err.value)


def test_the_simulator_names_a_collision_config_of_the_wrong_kind():
    """A dict or a string failed with ``AttributeError: 'dict' object has no attribute 'objects'``
    (round 35, W5); the default config and None build."""
    from hairexp.app.config import CollisionConfig, SolverConfig
    from hairexp.physics import Simulator

    for wrong in ({"hair_thickness": -1}, "off"):
        with pytest.raises(InputError) as err:
            Simulator(_one_strand_scene(), SolverConfig(), collision_cfg=wrong)
        assert str(err.value).startswith("collision: must be a collision config") and type(wrong).__name__ in str(err.value)
    for fine in (None, CollisionConfig(), CollisionConfig(hair_hair=True)):
        Simulator(_one_strand_scene(), SolverConfig(), collision_cfg=fine)


@pytest.mark.parametrize("overrides, named", [
    (["variants=[]", "solver.on_failure=fail", "solver.max_substep_levels=7"],
     "solver.max_substep_levels (read with solver.on_failure=substep)"),
    (["variants=[]", "collision.max_travel=0", "collision.max_travel_substeps=33"],
     "collision.max_travel_substeps (read with collision.objects=true with collision.max_travel > 0)"),
    (["variants=[]", "collision.objects=false", "collision.strain_limit=0.3"], "collision.strain_limit (read with"),
    (["variants=[]", "collision.contact=barrier", "collision.strain_limit=0.3"], "collision.strain_limit (read with"),
    (["variants=[]", "controller.name=tracking", "tracking.schur=exact", "tracking.krylov_max=500"],
     "tracking.krylov_max (read with controller.name=tracking with tracking.schur=krylov"),
    (["variants=[]", "controller.name=tracking", "tracking.kkt=reference", "tracking.schur=krylov"],
     "tracking.schur (read with controller.name=tracking with tracking.kkt=schur)"),
    (["judge_tolerance=0.5"], "judge_tolerance (read with judge=variance_follows_targets"),
    # the contact planes' keys (2026-12-07): read with the post-solve stage only
    (["variants=[]", "collision.contact=barrier", "collision.plane_friction=true"], "collision.plane_friction (read with"),
    (["variants=[]", "collision.resolve=false", "collision.plane_friction=true"], "collision.plane_friction (read with"),
    (["variants=[]", "collision.objects=false", "collision.resolve=false"], "collision.resolve (read with"),
    (["variants=[]", "collision.friction_epsilon=1e-4"], "collision.friction_epsilon (read with"),
])
def test_settings_no_run_reads_are_named(overrides, named):
    """Keys accepted without a word though no run of the launch read them (round 35, bad B1-B6)."""
    from hairexp.app import compose_config
    from hairexp.app.experiment import apply_overrides
    from hairexp.app.validate import unused_settings

    cfg = compose_config(["experiment=goaling_smoke"] + overrides)
    runs = [apply_overrides(cfg, list(v.overrides), v.name) for v in cfg.variants] or [cfg]
    keys = [o.split("=", 1)[0] for o in overrides if not o.startswith("variants=")]
    unused = unused_settings(runs, keys)
    assert any(u.startswith(named) for u in unused), unused


def test_settings_that_a_run_reads_are_not_named():
    """The same keys where they are read: nothing is said."""
    from hairexp.app import compose_config
    from hairexp.app.validate import unused_settings

    for overrides in (["solver.on_failure=substep", "solver.max_substep_levels=7"],
                      ["collision.max_travel=0.5", "collision.max_travel_substeps=33"],
                      ["collision.contact=stage", "collision.strain_limit=0.3"],
                      ["collision.objects=false", "collision.hair_hair=true", "collision.strain_limit=0.3"],
                      ["controller.name=tracking", "tracking.schur=krylov", "tracking.krylov_max=500"],
                      ["controller.name=tracking", "tracking.schur=exact"],
                      # friction_epsilon smooths the contact planes' friction too (it was said unused there)
                      ["collision.plane_friction=true", "collision.friction_epsilon=1e-4"],
                      ["collision.contact=barrier", "collision.friction_epsilon=1e-4"],
                      ["collision.resolve=false"]):
        cfg = compose_config(["experiment=goaling_smoke", "variants=[]"] + overrides)
        assert unused_settings([cfg], [o.split("=", 1)[0] for o in overrides]) == [], overrides
    spreading = compose_config(["experiment=spreading_smoke", "judge_tolerance=0.5"])
    assert unused_settings([spreading], ["judge_tolerance"]) == []


def test_meaningless_measure_and_judge_bounds_are_refused():
    """``measure.cohesion_threshold=1e300`` made every strand one clump, and ``judge_tolerance=1e9``
    passed an 80 % miss of the variance target (round 35, W1 and W2)."""
    from hairexp.app import compose_config
    from hairexp.app.validate import validate_config

    for override, key, said in (("measure.cohesion_threshold=1e300", "measure.cohesion_threshold", "must be at most 1 m"),
                                ("judge_tolerance=1e9", "judge_tolerance", "must be < 1"),
                                ("judge_tolerance=1.0", "judge_tolerance", "must be < 1")):
        with pytest.raises(InputError) as err:
            validate_config(compose_config(["experiment=spreading_smoke", override]))
        assert str(err.value).startswith(f"{key}: {said}")
    validate_config(compose_config(["experiment=spreading_smoke", "judge_tolerance=0.99",
                                    "measure.cohesion_threshold=0.5"]))


def test_cfg_job_checks_the_values_as_a_run_does():
    """``--cfg job solver.dt=-1`` printed ``dt: -1.0``, exit 0 (round 35, W3)."""
    from hairexp.app import cli

    msg = cli.config_error(["experiment=goaling_smoke", "--cfg", "job", "solver.dt=-1"])
    assert msg == "hairexp: error: solver.dt: must be a finite number > 0, got -1"
    assert cli.config_error(["experiment=goaling_smoke", "--cfg", "job", "solver.dt=0.02"]) is None


@pytest.mark.parametrize("override, said", [
    ("fps=0", "fps: must be a finite number from 0.1 to 100000"),
    ("frames=0", "frames: must be >= 1, got 0"),
    ("scene.n_strands=0", "scene.n_strands: must be >= 1, got 0"),
    ("scene.length=0", "scene.length: must be a finite number > 0"),
    ("variants=[{name: stream, overrides: []}]", "variants[0].name: 'stream' is reserved"),
    ("variants=[{name: a, overrides: []},{name: a, overrides: []}]", "variants[1].name: 'a' is also the name of variants[0]"),
    ("scene.colliders=[]", "measure.collider: no collider named 'wheel' in the scene (have [])"),
])
def test_cfg_job_checks_what_a_run_checks_without_reading_files(override, said):
    """``--cfg job`` with these printed the config, exit 0, where a run refuses them (an independent
    probe, 2026-12-07): the step schedule, the sizes, the procedural scene as built, the variants'
    names and the measure's references are checked too (no file is read)."""
    from hairexp.app import cli

    msg = cli.config_error(["experiment=goaling_smoke", "--cfg", "job", override])
    assert msg is not None and msg.startswith(f"hairexp: error: {said}"), msg


def test_a_key_added_to_a_composed_config_is_refused_by_the_api(tmp_path):
    """``open_dict(cfg.solver): cfg.solver.foo = 1`` then ``run_folder``: the run completed with the
    key never refused (round 35, W6); ``assemble`` took it too."""
    from omegaconf import open_dict

    from hairexp.app import assemble, compose_config, run_folder

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2"])
    with open_dict(cfg.solver):
        cfg.solver.foo = 1
    for call in (lambda: assemble(cfg), lambda: run_folder(cfg, tmp_path / "run")):
        with pytest.raises(InputError) as err:
            call()
        assert str(err.value).startswith("solver.foo: unknown key, not in the schema")
    assert not (tmp_path / "run").exists()


def test_a_sweep_job_reads_the_stop_mark_between_steps(tmp_path):
    """A SIGTERM the sweep's main process forwarded while a job was starting was lost: the job ran
    on (its whole free variant) until the main process killed it after 30 s, or to its end (round
    35, weak W2; 10 of 18 tries).  The stop mark, written before the signal is forwarded, ends the
    run after the step it is seen at, as the signal would: summary interrupted, its steps kept."""
    import json

    from hairexp.app import compose_config, run_folder
    from hairexp.app.signals import stop_requested, watch_stop_file
    from hairexp.errors import Interrupted

    mark = tmp_path / "stopping"
    watch_stop_file(mark)
    try:
        assert stop_requested() is None
        mark.write_text("SIGHUP\n")
        assert stop_requested() == 1
        mark.write_text("\n")
        assert stop_requested() == 15   # a mark that names no signal: SIGTERM
        cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=4", "logging.rerun=false",
                              "logging.progress=false"])
        with pytest.raises(Interrupted) as err:
            run_folder(cfg, tmp_path / "run")
        assert err.value.signum == 15
    finally:
        watch_stop_file(None)
    assert stop_requested() is None
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "SIGTERM" in summary["error"]
    assert summary["steps"] == 1   # the step it was seen after, kept


def test_unhold_unused_says_whether_nothing_of_the_launch_is_left(tmp_path, monkeypatch):
    """The interruption's line says "while starting; nothing was run or written" only when the
    folders the launch locked held nothing else (round 35, W1: a bare line and a folder holding only
    .lock)."""
    from hairexp.outputs import folder

    empty, used = tmp_path / "empty", tmp_path / "used"
    for d in (empty, used):
        d.mkdir()
        (d / folder.LOCK).write_text("")
    (used / "result.npz").write_text("x")
    monkeypatch.setattr(folder, "_MADE", [empty])
    monkeypatch.setattr(folder, "_LOCKED", [])
    assert folder.unhold_unused() is True and not empty.exists()
    monkeypatch.setattr(folder, "_MADE", [])
    monkeypatch.setattr(folder, "_LOCKED", [str(used)])
    assert folder.unhold_unused() is False and (used / "result.npz").exists()


def test_a_job_stops_watching_its_sweeps_stop_mark_when_it_ends(tmp_path):
    """The watch outlived the job: a worker (or a process running jobs one after another) read a
    former sweep's stop mark in its next run, which ended interrupted at its first step."""
    from hairexp.app import cli
    from hairexp.app.signals import stop_requested

    (tmp_path / cli.STOP_MARK).write_text("SIGTERM\n")
    res = cli.job(None, str(tmp_path / "2"), sweep=True, sweep_dir=str(tmp_path))   # cfg is never read
    assert res["status"] == "interrupted"
    assert (tmp_path / cli.STOP_MARK).exists() and stop_requested() is None
