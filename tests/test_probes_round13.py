"""Findings of issue 12's thirteenth probe round, one test each (one bad: export_scene replaced an
existing file; the rest weak)."""

from __future__ import annotations

import json
from pathlib import Path
import re
import logging
import os
import signal
import sys

import numpy as np
import pytest

from hairexp.errors import InputError

SMOKE = ["experiment=goaling_smoke", "variants=[]", "frames=3", "logging.rerun=false", "logging.progress=false"]


def _warnings(caplog) -> str:
    return "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)


# B1: export_scene replaced any existing file with exit 0

def test_export_scene_never_replaces_an_existing_file_without_force(tmp_path, capsys):
    from hairexp.app.export_scene import main as export_main

    notes = tmp_path / "notes.usda"   # a user's file under a stage's name (any other name: refused by its extension)
    notes.write_text("a user's file")
    assert export_main([str(notes), "experiment=goaling_smoke"]) == 2
    assert "notes.usda: the file exists; give --force to replace it" in capsys.readouterr().err
    assert notes.read_text() == "a user's file"
    stage = tmp_path / "s.usda"
    assert export_main([str(stage), "experiment=goaling_smoke"]) == 0
    first = stage.read_bytes()
    assert export_main([str(stage), "experiment=goaling_smoke", "guides.count=2"]) == 2   # kept
    assert stage.read_bytes() == first
    assert export_main(["--force", str(stage), "experiment=goaling_smoke", "guides.count=2"]) == 0
    assert stage.read_bytes() != first and b"#usda" in stage.read_bytes()[:8]


def test_export_scene_names_a_file_on_the_path_and_exits_4(tmp_path, capsys):
    from hairexp.app.export_scene import main as export_main

    (tmp_path / "f.txt").write_text("x")
    assert export_main([str(tmp_path / "f.txt" / "sub" / "s.usda"), "experiment=goaling_smoke"]) == 4
    assert f"cannot write the USD stage: {tmp_path / 'f.txt'} is a file, not a folder" in capsys.readouterr().err
    assert export_main([str(tmp_path / "missing" / "s.usda"), "experiment=goaling_smoke"]) == 4
    assert "no such directory" in capsys.readouterr().err
    assert export_main(["--bogus", str(tmp_path / "s.usda")]) == 2
    assert "unknown option --bogus" in capsys.readouterr().err


# weak findings

def test_measure_keys_the_measure_does_not_read_are_said(caplog):
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with caplog.at_level(logging.WARNING, logger="hairexp"):
        validate_config(compose_config(["experiment=goaling", "measure.time=0.5"]))
    assert ("measure.time=0.5 is not used: measure.name=collider_contact reads measure.collider, measure.tolerance"
            in _warnings(caplog))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        for exp in ("goaling", "splitting", "spreading", "stylization", "fanning", "celia"):   # the paper's scenes: none
            validate_config(compose_config([f"experiment={exp}"]))
    assert "not used" not in _warnings(caplog)


def test_guide_edits_keyed_after_the_run_are_said(caplog):
    from hairexp.app.assemble import timed_config
    from hairexp.app.config import compose_config
    from hairexp.app.validate import late_keys

    cfg = compose_config(SMOKE + ["guides.edits.0.times=[10.0,20.0,30.0,40.0]"])
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        late_keys(timed_config(cfg))
    msg = _warnings(caplog)
    assert "guides.edits[0].times: the keys at 10, 20, 30, 40 s lie after the run's end at 0.12 s" in msg
    assert "held at its first weight, the whole run" in msg
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        late_keys(timed_config(compose_config(["experiment=goaling"])))   # keys within the run: nothing
    assert "guides.edits" not in _warnings(caplog)


def test_late_edit_keys_that_shape_the_weight_before_the_end_are_not_said(caplog):
    """The first two keys after the end shape the weight inside the run (the crossing segment and
    its end slope): only later ones are never reached.  Every shipped experiment is quiet."""
    from hairexp.app.assemble import timed_config
    from hairexp.app.config import compose_config
    from hairexp.app.validate import late_keys
    from hairexp.guides.authoring import KeyedWeight

    base = ["experiment=goaling_smoke", "frames=30"]   # ends at 1.2 s (25 fps)
    keys = "guides.edits.0.times=[0.0,1.0,1.5,2.0,3.0,4.0]", "guides.edits.0.weights=[0.0,1.0,0.6,0.3,0.1,0.0]"
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        late_keys(timed_config(compose_config(base + list(keys))))
    msg = _warnings(caplog)
    assert "the keys at 3, 4 s lie after the run's end at 1.2 s" in msg and "1.5" not in msg and " 2," not in msg
    # the claim: the keys named change nothing before the end, the two not named do
    t = [0.0, 1.0, 1.5, 2.0, 3.0, 4.0]
    w = [0.0, 1.0, 0.6, 0.3, 0.1, 0.0]   # decreasing after 1 s: the slope at 1.5 s reads the key at 2 s
    inside = __import__("numpy").linspace(0.0, 1.2, 61)
    ref = KeyedWeight(t, w, "e")(inside)
    assert abs(KeyedWeight(t, w[:4] + [0.9, 0.7], "e")(inside) - ref).max() == 0.0
    assert abs(KeyedWeight(t, w[:3] + [0.5] + w[4:], "e")(inside) - ref).max() > 1e-6
    assert abs(KeyedWeight(t, w[:2] + [0.9] + w[3:], "e")(inside) - ref).max() > 1e-6
    for exp in ("goaling_smoke", "splitting_smoke", "spreading_smoke", "stylization_smoke", "celia_smoke",
                "fanning_smoke", "goaling", "celia"):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hairexp"):
            late_keys(timed_config(compose_config([f"experiment={exp}"])))
        assert "guides.edits" not in _warnings(caplog), exp


def test_a_variance_point_given_twice_is_refused():
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with pytest.raises(InputError, match=r"tracking.variance.points\[1\]: is 1, given twice \(at \[0\] too\)"):
        validate_config(compose_config(SMOKE + ["tracking.variance.points=[1,1]"]))
    validate_config(compose_config(SMOKE + ["tracking.variance.points=[1,2]"]))


def test_guide_keyframes_without_the_keyframed_source_are_refused():
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    cfg = compose_config(SMOKE + ["guides.source=simulated", "guides.keyframes=[{time:0.0,points:[[0.0,0.0,0.0]]}]"])
    with pytest.raises(InputError, match="guides.keyframes: holds 1 keyframe.* but guides.source=simulated does not "
                                         "read them"):
        validate_config(cfg)


def test_a_mirroring_usd_transform_is_named_as_a_mirror():
    from hairexp.io.usd_layout import pose_from_matrix

    M = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(InputError, match=r"it mirrors \(a negative scale, determinant -1\)"):
        pose_from_matrix(M, "/Body", 0.0)
    S = np.eye(4)
    S[1, 0] = 0.5   # a shear
    with pytest.raises(InputError, match=r"it shears \(\|R\^T R - I\| = "):
        pose_from_matrix(S, "/Body", 0.0)


def test_the_float_hint_is_for_integers_only():
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as nan:
        compose_config(SMOKE + ["guides.source=keyframed", "guides.keyframes=[{time:0.0,points:[[0.0,.nan,0.0]]}]"])
    assert "0.0, not 0" not in str(nan.value) and "a finite number is needed here" in str(nan.value)
    with pytest.raises(InputError, match=r"write such a number as a float \(0.0, not 0\)"):
        compose_config(SMOKE + ["scene.motion.translations=[[0,0,0]]"])


@pytest.mark.parametrize("make, label", [
    (lambda p: p.write_text("garbage"), "summary.json (not a run's summary: not a JSON object with a status)"),
    (lambda p: p.mkdir(), "summary.json (a folder, where a run writes a file)"),
])
def test_an_overwrite_refusal_says_why_a_run_files_name_is_not_a_run_file(tmp_path, make, label):
    from hairexp.outputs.folder import overwrite_refusal

    out = tmp_path / "r"
    out.mkdir()
    make(out / "summary.json")
    assert overwrite_refusal(out).endswith("the folder also holds " + label)


def test_a_signal_after_the_run_began_is_not_one_while_starting(monkeypatch, capsys):
    """A third quick signal landed after the run's handlers were removed and before the command
    ended: it said "interrupted ... while starting; nothing was run or written" below the run's own
    interrupted line."""
    from hairexp.app import startup

    exits = []
    monkeypatch.setattr(startup.os, "_exit", exits.append)
    monkeypatch.setattr(startup, "_BEGUN", False)
    monkeypatch.setattr(startup, "_ENDED_CODE", None)
    startup._handler(signal.SIGINT, None)
    assert "while starting; nothing was run or written" in capsys.readouterr().err
    startup.begun()
    startup._handler(signal.SIGINT, None)
    err = capsys.readouterr().err
    assert "while starting" not in err and "SIGINT while the command was ending" in err
    assert exits == [130, 130]


@pytest.mark.parametrize("argv", [["--cfg", "job"], ["--info"], ["--help"]])
def test_print_only_flags_make_no_run_folder(tmp_path, monkeypatch, argv, capsys):
    import hairexp.__main__ as entry_module

    folder = tmp_path / "r"
    monkeypatch.setattr(sys, "argv", ["hairexp", f"hydra.run.dir={folder}", "experiment=goaling_smoke", *argv])
    monkeypatch.setattr(entry_module, "main", lambda: None)   # Hydra's printing itself is not under test
    monkeypatch.setattr(entry_module.cli, "exit_code", lambda *a: 0)   # (the process's code, set by other tests)
    assert entry_module.entry() == 0
    assert not folder.exists()


def test_an_unknown_flag_is_refused_before_any_folder(tmp_path, monkeypatch, capsys):
    import hairexp.__main__ as entry_module

    folder = tmp_path / "r"
    monkeypatch.setattr(sys, "argv", ["hairexp", f"hydra.run.dir={folder}", "--bogus-flag"])
    assert entry_module.entry() == 2
    assert "hairexp: error: unknown option --bogus-flag" in capsys.readouterr().err
    assert not folder.exists()


def test_the_default_folder_of_a_run_without_an_experiment_is_named_run():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from hairexp.app.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for over, name in (([], "run"), (["experiment=goaling_smoke"], "goaling_smoke")):
            cfg = compose(config_name="config", overrides=over, return_hydra_config=True)
            assert str(cfg.hydra.run.dir).split("/")[:2] == ["outputs", name]
            assert str(cfg.hydra.sweep.dir).split("/")[:2] == ["multirun", name]
    GlobalHydra.instance().clear()


def test_run_steps_negative_frames_is_an_input_error():
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    run = assemble(compose_config(SMOKE))
    with pytest.raises(InputError, match="Run.steps: frames: must be a whole number >= 0, got -1"):
        next(run.steps(None, -1))
    with pytest.raises(TypeError):
        next(run.steps(None, 1.5))


@pytest.mark.parametrize("t, why", [(float("nan"), "finite"), ("0.1", "real number"), (True, "real number")])
def test_rigid_motion_pose_refuses_a_time_that_is_not_a_number(t, why):
    from hairexp.model import RigidMotion

    m = RigidMotion(np.array([0.0, 1.0]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError, match=f"RigidMotion.pose: t: must be a {why}"):
        m.pose(t)
    R, T = m.pose(np.float64(0.5))
    assert np.allclose(R, np.eye(3)) and np.allclose(T, 0.0)


def test_allow_large_does_not_run_what_exceeds_the_machines_memory_and_swap():
    """guard.allow_large=true with 1e8 strands ran into the out-of-memory killer (exit 137, the
    summary left running); more than memory + swap is refused even with the override."""
    from hairexp.app import guard

    est = guard.estimate(10 ** 9, 30, 1)
    with pytest.raises(InputError, match="more than the machine has .* guard.allow_large=true cannot make it fit"):
        guard.check(est, "scene.n_strands", allow_large=True, available=1e9, total=2e10)
    guard.check(guard.estimate(10 ** 6, 30, 1), "k", allow_large=True, available=1e9, total=2e10)   # warned only
    total = guard.total_memory()
    assert total is None or total > 1e8


def test_an_abbreviated_flag_is_named_with_its_full_form():
    from hairexp.app.cli import flag_error

    assert flag_error(["--multi", "frames=2,3"]) == "hairexp: error: --multi: write the option in full: --multirun"
    assert flag_error(["-m", "--cfg", "job", "-p", "solver", "--info", "config", "frames=2,3"]) is None


# round 14's probe (and a sweep of 1e300 over every unbounded number): bounds, and memory errors named

@pytest.mark.parametrize("override, key", [
    ("tracking.krylov_max=1000000000", "tracking.krylov_max"),   # a 536 GiB GMRES basis: a traceback
    ("collision.skin=1e300", "collision.skin"),                  # the neighbour grid overflowed
    ("tracking.blend_width=1e300", "tracking.blend_width"),      # OverflowError
    ("collision.hair_thickness=1e300", "collision.hair_thickness"),   # LinAlgError with hair-hair
    ("collision.hair_thickness=0.09", "collision.hair_thickness"),   # a wisp stretched 130 % apart (round 15)
    ("collision.volume_cell=1e300", "collision.volume_cell"),
    ("collision.volume_pressure_speed=1e300", "collision.volume_pressure_speed"),
    ("guides.layout_radius=1e300", "guides.layout_radius"),      # the guide simulation diverged, exit 3
    ("tracking.rtol=1", "tracking.rtol"), ("solver.rtol=5", "solver.rtol"),   # accept the first iterate
    ("solver.atol=1", "solver.atol"), ("tracking.atol=1", "tracking.atol"),
    ("tracking.ctol_rel=1e300", "tracking.ctol_rel"), ("tracking.nonmonotone=1000000000", "tracking.nonmonotone"),
    ("tracking.elastic_stiffness=1e300", "tracking.elastic_stiffness"),
    ("collision.barrier_stiffness=1e300", "collision.barrier_stiffness"),
    ("collision.friction_epsilon=1e300", "collision.friction_epsilon"),
    ("collision.volume_friction=1e300", "collision.volume_friction"),
    ("scene.hair.air_drag=1e300", "scene.hair.air_drag"),
])
def test_values_beyond_any_use_are_refused(override, key):
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as e:
        check_config(compose_config(SMOKE + ["controller=tracking", override]))
        from hairexp.app.assemble import assemble   # the material is checked where it is built
        assemble(compose_config(SMOKE + [override]))
    assert e.value.where == key


def test_an_allocation_that_fails_is_one_line_and_exit_3(tmp_path, monkeypatch, capsys):
    """A size no check foresaw (numpy's ArrayMemoryError) gave a traceback and exit 1."""
    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    def no_memory(cfg, out, **kw):
        raise MemoryError("Unable to allocate 536. GiB for an array with shape (1000000001, 72000)")

    monkeypatch.setattr(cli, "run_experiment", no_memory)
    res = cli.job(compose_config(SMOKE), str(tmp_path / "r"), overrides=[])
    err = capsys.readouterr().err
    assert res["code"] == 3 and res["status"] == "failed" and "Traceback" not in err
    assert err.startswith("hairexp: out of memory: Unable to allocate 536. GiB")


def test_a_missing_sublayer_is_one_line_without_usds_own_warning(tmp_path, capfd):
    """USD printed 'Warning: in _ReportErrors at line ... -- Could not load sublayer ...' on the
    process's stderr before hairexp's error line that said the same."""
    from hairexp.io.usd_read import open_stage

    stage = tmp_path / "s.usda"
    stage.write_text('#usda 1.0\n(\n    subLayers = [@./nope.usda@]\n)\n\ndef Xform "Root"\n{\n}\n')
    with pytest.raises(InputError, match="the stage does not compose: Could not load sublayer"):
        open_stage(str(stage))
    assert "_ReportErrors" not in capfd.readouterr().err


def test_a_bracketed_list_index_in_a_key_is_named_with_its_dotted_form():
    """``scene.colliders[0].radius=0.1`` was told to quote its value, which did not help."""
    from hairexp.app.cli import override_syntax_error

    msg = override_syntax_error(["scene.colliders[0].radius=0.1"])
    assert msg == ("hairexp: error: scene.colliders[0].radius=0.1: a list item is named with dots in a key, not "
                   "brackets: scene.colliders.0.radius=0.1")
    assert "quote a value" in override_syntax_error(["scene.usd=/tmp/a[1].usda"])   # a value's brackets: quote it


def test_a_dotted_index_past_the_lists_end_is_named():
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match=r"scene.colliders has no item 5: a dotted index sets a key of an item the "
                                         r"list already has") as e:
        compose_config(SMOKE + ["scene.colliders.5.radius=0.1"])
    assert e.value.where == "scene.colliders.5.radius"


def test_a_run_folder_climbing_out_of_a_folder_it_would_make_is_refused(tmp_path):
    """``hydra.run.dir=<dir>/b//../../z`` ran into z and left an empty folder b."""
    from hairexp.app.cli import run_dir_error

    msg = run_dir_error([*SMOKE, f"hydra.run.dir={tmp_path}/b//../../z"])
    assert msg is not None and f"the '..' after {tmp_path}/b, a folder that does not exist" in msg
    assert not (tmp_path / "b").exists()
    (tmp_path / "b").mkdir()
    assert run_dir_error([*SMOKE, f"hydra.run.dir={tmp_path}/b/../z"]) is None   # b exists: nothing is made on the way


def test_the_python_api_bounds_what_the_command_line_bounds():
    """The API took what the command line refuses: a rotation of 1e6 rad, gravity 1e9 m/s^2, a
    material constant of 1e300 (which then failed as a diverged step), and pose(None)."""
    from hairexp.model import RigidMotion
    from hairexp.model.scene import Material

    with pytest.raises(InputError, match=r"rotvecs: the rotation at keyframe 0 turns 1e\+06 rad, more than 36000"):
        RigidMotion(np.array([0.0]), np.zeros((1, 3)), np.array([[1e6, 0.0, 0.0]]))
    with pytest.raises(InputError, match="RigidMotion.pose: t: must be a real number of seconds, got NoneType"):
        RigidMotion(np.array([0.0]), np.zeros((1, 3)), np.zeros((1, 3))).pose(None)
    for key in ("stretch_stiffness", "bending_stiffness", "air_drag", "edge_damping"):
        kw = dict(linear_density=1e-4, stretch_stiffness=10.0, bending_stiffness=1e-6)
        kw[key] = 1e300
        with pytest.raises(InputError, match=f"Material.{key}"):
            Material(**kw)


def test_scene_gravity_is_bounded_in_the_api():
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config
    from dataclasses import replace

    scene = assemble(compose_config(SMOKE)).scene
    with pytest.raises(InputError, match=r"Scene.gravity: is \[0.0, -1000000000.0, 0.0\], larger than 1000 m/s\^2"):
        replace(scene, gravity=np.array([0.0, -1e9, 0.0]))


@pytest.mark.parametrize("override, key", [("scene.length=1e300", "scene.length"),
                                           ("scene.root_radius=1e300", "scene.root_radius"),
                                           ("scene.hair.linear_density=1e-300", "scene.hair.linear_density"),
                                           ("tracking.variance.stiffness=1e300", "tracking.variance.stiffness")])
def test_sizes_and_stiffnesses_that_diverged_at_the_first_step_are_refused(override, key):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as e:
        assemble(compose_config(SMOKE + ["controller=tracking", override]))
    assert e.value.where == key


def test_a_run_whose_hair_stretched_beyond_1000_percent_exits_3(tmp_path, monkeypatch, capsys):
    """collision.hair_thickness=1e6 with hair-hair threw the hair 1,182 km (4.5e9 % stretch):
    "completed", exit 0, with a warning only."""
    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config
    from hairexp.app.run import implausible

    assert implausible({"stretch_max": 0.5}) is None and implausible({"stretch_max": 10.0}) is None
    assert "tracked: 4.5e+09 %" in implausible({"variants": {"free": {"stretch_max": 0.1},
                                                              "tracked": {"stretch_max": 4.5e7}}})
    monkeypatch.setattr(cli, "run_experiment", lambda cfg, out, **kw: {"scene": "s", "controller": "free", "steps": 3,
                                                                "iterations_mean": 2.0, "step_seconds_median": 1e-3,
                                                                "stretch_max": 4.5e7, "status": "completed"})
    res = cli.job(compose_config(SMOKE), str(tmp_path / "r"), overrides=[])
    assert res["code"] == 3 and res["status"] == "completed"
    assert "hairexp: the hair stretched beyond 1000 % (4.5e+09 %" in capsys.readouterr().err


def _point_sets():
    rng = np.random.default_rng(7)
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    grid = np.stack(np.meshgrid(*[np.arange(6)] * 3), -1).reshape(-1, 3) * 0.01   # degenerate (cospherical) points
    return {"3d": rng.normal(size=(400, 3)), "plane": np.c_[rng.normal(size=(400, 2)), np.zeros(400)] @ Q,
            "line": np.outer(rng.normal(size=300), [1.0, 2.0, 3.0]), "repeated": np.repeat(rng.normal(size=(150, 3)), 3, 0),
            "grid": grid, "two": rng.normal(size=(2, 3)), "one_point_thrice": np.tile([1.0, 2.0, 3.0], (3, 1))}


@pytest.mark.parametrize("name", list(_point_sets()))
def test_the_delaunay_spanning_tree_agrees_with_single_linkage(name, monkeypatch):
    """100,000 strands asked single linkage's distance table for 37 GiB after the whole run had
    been simulated (cohesion, every run): above LINKAGE_MAX strands the merge heights come from
    the Euclidean minimum spanning tree of a Delaunay triangulation, and clumps from a k-d tree's
    pairs.  Both agree with scipy's single linkage exactly."""
    from scipy.cluster.hierarchy import fcluster, linkage

    import hairexp.evaluation.measures as measures

    X = _point_sets()[name]
    ref = linkage(X, method="single")
    np.testing.assert_allclose(np.sort(measures.emst_lengths(X)), ref[:, 2], rtol=0, atol=1e-12)
    monkeypatch.setattr(measures, "LINKAGE_MAX", 1)
    np.testing.assert_allclose(measures.merge_heights(X), ref[:, 2], rtol=0, atol=1e-12)
    h = np.unique(ref[:, 2])
    k = len(h) // 2
    t = float(h[k]) if len(h) == 1 else 0.5 * float(h[k - 1] + h[k])   # between two heights: no tie to round
    want = fcluster(ref, t=t, criterion="distance")
    got = measures.single_linkage_labels(X, t)
    pairs = {(a, b) for a, b in zip(want, got)}   # the same partition: a one-to-one map of labels
    assert len(pairs) == len(set(want)) == len(set(got))


@pytest.mark.parametrize("override, said", [("hydra.run.dir=/tmp/x", "a variant cannot set Hydra's keys (hydra.run.dir)"),
                                            ("judge=none", "a variant cannot set 'judge': it belongs to the experiment")])
def test_a_variant_cannot_set_the_launchs_or_the_experiments_keys(override, said):
    """hydra.run.dir in a variant was called an unknown key; judge=none in one variant was taken
    and did nothing (the experiment's judge judged all variants)."""
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import apply_overrides

    with pytest.raises(InputError, match=re.escape(said)):
        apply_overrides(compose_config(["experiment=goaling_smoke"]), [override], "variants[0] (a)")


def test_an_input_error_found_when_a_variant_starts_names_the_variant(tmp_path):
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment

    cfg = compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=false", "logging.progress=false",
                          "judge=none", "variants=[{name: a, overrides: ['measure.name=clumps', 'measure.time=99']}]"])
    # checked before any variant runs (round 17: it was found when the variant started, its folder made)
    with pytest.raises(InputError, match=r"measure.time: is 99.0 s, after the run's end .* \(variants\[0\] a, "
                                         r"checked before any variant runs\)"):
        run_experiment(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()   # nothing run, nothing claimed


@pytest.mark.parametrize("override, key", [
    ("scene.settle_dt=1e300", "scene.settle_dt"),   # OverflowError traceback with scene.settle
    ("tracking.variance.target_scale=[1e300]", "tracking.variance.target_scale"),   # diverged, exit 3
    ("guides.edits=[{guide: 0, kind: displace, offset: [1e300, 0.0, 0.0], times: [0.0, 0.1], weights: [0.0, 1.0]}]",
     "guides.edits[0].offset"),
    ("guides.edits=[{guide: 0, kind: rotate, angle_deg: 30.0, times: [0.0, 0.1], weights: [0.0, 1e300]}]",
     "guides.edits[0].weights"),
])
def test_more_values_beyond_any_use_are_refused(override, key):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as e:
        assemble(compose_config(SMOKE + ["controller=tracking", "scene.settle=0.1", override]))
    assert e.value.where == key


def test_keys_a_stage_replaces_are_said_not_used(tmp_path, caplog):
    """scene.motion.* with a USD scene was ignored without a word; so were the exporter's
    hydra.run.dir, overwrite=true and scene.settle."""
    from hairexp.app.builders import build_scene
    from hairexp.app.config import compose_config
    from hairexp.app.export_scene import main as export_main

    stage = tmp_path / "s.usda"
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        assert export_main([str(stage), "experiment=goaling_smoke", "frames=3", "scene.settle=0.5", "overwrite=true",
                            f"hydra.run.dir={tmp_path / 'zz'}"]) == 0
    said = _warnings(caplog)
    assert "overwrite=true, hydra.run.dir=" in said and "not used: the exporter writes one stage" in said
    assert "scene.settle=0.5 not used: the stage holds the hair at its elastic rest shape" in said
    assert not (tmp_path / "zz").exists()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        build_scene(compose_config(["experiment=from_usd", f"scene.usd={stage}"]).scene)
    assert "not used" not in _warnings(caplog)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        build_scene(compose_config(["experiment=from_usd", f"scene.usd={stage}", "scene.motion.times=[0.0,1.0]",
                                    "scene.motion.translations=[[0.0,0.0,0.0],[1.0,0.0,0.0]]",
                                    "scene.motion.rotations_deg=[[0.0,0.0,0.0],[0.0,0.0,0.0]]"]).scene)
    assert "scene.motion is not used: the body's motion comes from the stage" in _warnings(caplog)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hairexp"):   # the config's colliders are added to the stage's
        scene = build_scene(compose_config(["experiment=from_usd", f"scene.usd={stage}", "scene.colliders=[{name: extra, "
                                            "shape: sphere, radius: 0.01, motion: {times: [0.0], translations: "
                                            "[[1.0, 0.0, 0.0]], rotations_deg: [[0.0, 0.0, 0.0]]}}]"]).scene)
    assert "not used" not in _warnings(caplog) and "extra" in [c.name for c in scene.colliders]


def test_group_errors_name_the_key_and_only_real_options():
    from hairexp.app.config import compose_config

    with pytest.raises(InputError) as e:
        compose_config(["scene=nosuch"])
    assert "(options: ponytail, wisp)" in str(e.value)   # not the schema's base_scene
    with pytest.raises(InputError, match="experiment: a config group needs an option's name, got NoneType"):
        compose_config(["experiment=null"])


def test_an_empty_scene_name_is_named_as_its_key():
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with pytest.raises(InputError, match="scene.name: must be a non-empty name"):
        validate_config(compose_config(SMOKE + ["scene.name="]))


def test_the_exporter_says_it_writes_an_experiments_base_scene(tmp_path, caplog):
    from hairexp.app.export_scene import main as export_main

    with caplog.at_level(logging.WARNING, logger="hairexp"):
        assert export_main([str(tmp_path / "s.usda"), "experiment=goaling_smoke", "frames=3"]) == 0
    assert "the config has 2 variant(s) (free, tracked); the stage holds its base scene" in _warnings(caplog)


def test_a_short_or_failed_write_of_the_frame_store_is_named(monkeypatch):
    """Under ``ulimit -f`` the store's write failed short and was found later as a short read
    ("frame store: read 8192 of 22320 bytes"); or it said only "File too large"."""
    import errno as errno_module

    import hairexp.guides.store as store

    s = store.FrameStore((4, 3))
    monkeypatch.setattr(store.os, "pwrite", lambda fd, data, at: 0)
    with pytest.raises(OSError, match=r"the guide frame store \(a temporary file in .*\): wrote 0 of 96 bytes"):
        s.append(np.zeros((4, 3)))
        s.block(0, 1)

    def too_large(fd, data, at):
        raise OSError(errno_module.EFBIG, "File too large")

    s = store.FrameStore((4, 3))
    monkeypatch.setattr(store.os, "pwrite", too_large)
    with pytest.raises(OSError, match="the guide frame store .*: File too large after 0 bytes"):
        s.append(np.zeros((4, 3)))
        s.block(0, 1)


@pytest.mark.parametrize("overrides, key", [(["solver.dt"], "solver.dt"), (["frames=3", "solver.dt=[1,"], "solver.dt=[1,")])
def test_an_override_the_grammar_refuses_is_an_input_error_in_the_api(overrides, key):
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match="not a valid override") as e:
        compose_config(overrides)
    assert e.value.where == key and "\n" not in str(e.value)


@pytest.mark.parametrize("override, key, match", [
    ("scene.colliders.0.thickness=1e300", "scene.colliders[0].thickness", "thickness must be a finite number >= 0 and <= 1"),
    ("scene.colliders.0.friction=1e300", "scene.colliders[0].friction", "friction must be a finite number >= 0 and <= 100"),
    ("guides.layout_radius=0", "guides.layout_radius", "the 3 guides would all be rooted at the disk's centre"),
    ("tracking.variance.times=[1.0,0.5]", "tracking.variance.times", "keyframe times must be finite and increase"),
])
def test_the_key_at_fault_is_named(override, key, match):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match=match) as e:
        assemble(compose_config(SMOKE + ["controller=tracking", "guides.count=3", override,
                                         "tracking.variance.stiffness_scale=[1.0,1.0]",
                                         "tracking.variance.target_scale=[1.0,1.0]"]
                                if "variance.times" in override else SMOKE + ["controller=tracking", override]))
    assert e.value.where == key


def test_a_hit_between_frames_has_a_time():
    """A fast sphere touching the hair between two frames: the measure said hit: true with
    hit_frames 0 and first_hit_time null; the time is now its step's, from the metrics."""
    import pandas as pd

    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config
    from hairexp.evaluation.measures import RunData, collider_contact

    scene = assemble(compose_config(SMOKE)).scene
    x = np.asarray(scene.strands.rest)
    metrics = pd.DataFrame({"time": [0.01, 0.02, 0.03], "contacts_wheel": [0, 3, 0]})
    m = collider_contact(RunData(scene, np.array([0.0, 0.04]), np.stack([x, x]), metrics=metrics),
                         type("P", (), {"collider": "wheel", "tolerance": 0.002})())
    assert m["hit"] and m["hit_frames"] == 0 and m["contacts"] == 3 and m["first_hit_time"] == 0.02


def test_hair_inside_a_collider_with_the_barrier_is_said_to_be_inside_it():
    """With collision.contact=barrier a plane 5 cm above the hair's tips was said to hold the
    hair "within its thickness shell by 52 mm"; it is inside the plane by about 5 cm."""
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    plane = ("scene.colliders=[{name: floor, shape: plane, thickness: 0.002, motion: {times: [0.0], "
             "translations: [[0.0, -0.25, 0.0]], rotations_deg: [[0.0, 0.0, 0.0]]}}]")
    with pytest.raises(InputError, match=r"collider 'floor': the hair starts inside it \(strand .* by (4\d|5\d)(\.\d+)? mm"):
        assemble(compose_config(SMOKE + ["collision.contact=barrier", plane, "measure.name=none", "judge=none"]))


def test_a_recording_at_the_file_size_limit_is_named(tmp_path, monkeypatch):
    """Under ``ulimit -f`` the recording's writer stopped and the run waited out the 60 s flush
    time-out, naming neither the limit nor the cause."""
    import resource

    from hairexp.outputs.rerun_sink import _size_capped

    f = tmp_path / "recording.partial.rrd"
    f.write_bytes(b"x" * 1000)
    monkeypatch.setattr(resource, "getrlimit", lambda what: (1 << 20, resource.RLIM_INFINITY))
    assert _size_capped(str(f)) is None   # 1 kB against a 1 MB limit
    f.write_bytes(b"x" * ((1 << 20) - 1000))
    assert _size_capped(str(f)) == 1 << 20
    monkeypatch.setattr(resource, "getrlimit", lambda what: (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert _size_capped(str(f)) is None


def test_a_run_folder_moved_away_mid_run_is_one_line(tmp_path, monkeypatch, capsys):
    """``mv`` of the run folder during a run gave an errno line per ending file (five lines)."""
    import shutil

    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    out = tmp_path / "r"

    def moved(cfg, folder):
        folder.mkdir()
        shutil.move(str(folder), str(tmp_path / "r2"))
        err = FileNotFoundError(2, "No such file or directory", str(folder / "summary.json.tmp"))
        err.add_note("also: while writing the failed ending (metrics): FileNotFoundError")
        raise err

    monkeypatch.setattr(cli, "run_experiment", lambda cfg, folder, **kw: moved(cfg, Path(folder)))
    res = cli.job(compose_config(SMOKE), str(out), overrides=[])
    err = capsys.readouterr().err.strip().splitlines()
    assert res["code"] == 4 and len(err) == 1 and "was moved or deleted while the run went on" in err[0]


# round 15's probe

def test_a_key_given_twice_on_the_command_line_is_refused():
    """hydra.run.dir twice: hairexp locked the first folder and Hydra ran in the second."""
    from hairexp.app.cli import duplicate_key_error

    msg = duplicate_key_error(["experiment=goaling_smoke", "hydra.run.dir=a", "frames=3", "hydra.run.dir=b"])
    assert msg == ("hairexp: error: hydra.run.dir: given twice on the command line (hydra.run.dir=a and "
                   "hydra.run.dir=b); give it once")
    assert duplicate_key_error(["-m", "frames=2,3", "--cfg", "job", "solver.dt=0.01"]) is None
    assert duplicate_key_error(["frames=3", "frames=5"]) is None   # a config key: the last wins, as in Hydra


def test_hydras_flags_may_follow_the_overrides():
    """``key=value --cfg job`` gave argparse's 8-line usage and 'unrecognized arguments'."""
    from hairexp.app.cli import flags_first

    assert flags_first(["frames=3", "--cfg", "job", "solver.dt=0.01", "-m"]) == ["--cfg", "job", "-m", "frames=3",
                                                                                   "solver.dt=0.01"]
    assert flags_first(["frames=3", "--info", "config"]) == ["--info", "config", "frames=3"]
    # --info's value is optional: without one it goes last, where argparse cannot take an override as its value
    assert flags_first(["--info", "frames=3"]) == ["frames=3", "--info"]


def _checked(summary):
    """A stand-in for run_experiment: the config is checked (``on_checked`` is called), ``summary`` returned."""
    def fake(cfg, out, on_checked=None):
        if on_checked is not None:
            on_checked()
        return summary
    return fake


@pytest.mark.parametrize("overrides, said", [
    (["tracking.rtol=1e-3"], "tracking.rtol (read with controller.name=tracking)"),
    (["controller.attract_stiffness=5"], "controller.attract_stiffness (read with controller.name=attract)"),
    (["collision.volume_cell=0.5"], "collision.volume_cell (read with collision.hair_hair=true with"),
    (["collision.barrier_dhat=0.9"], "collision.barrier_dhat (read with collision.contact=barrier"),
    (["scene.body.mass=5"], "scene.body.mass (read with scene.body.dynamic=true)"),
    (["collision.objects=false", "collision.contact=barrier"], "collision.contact (read with collision.objects=true)"),
    (["controller=skinned", "collision.hair_hair=true"], "collision.hair_hair (read with a controller that simulates"),
    (["controller=tracking", "tracking.variance.stiffness=0", "tracking.variance.target_scale=[5.0]"],
     "tracking.variance.target_scale (read with controller.name=tracking with tracking.variance.stiffness > 0)"),
    (["controller=tracking", "tracking.assignment=hard", "tracking.blend_width=0.5"],
     "tracking.blend_width (read with controller.name=tracking with tracking.assignment=soft)"),
])
def test_a_command_line_key_no_run_reads_is_said(tmp_path, monkeypatch, caplog, overrides, said):
    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    monkeypatch.setattr(cli, "run_experiment", _checked({"scene": "s", "controller": "c", "steps": 1,
                                                         "iterations_mean": 1.0, "step_seconds_median": 1e-3,
                                                         "stretch_max": 0.0, "status": "completed"}))
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        cli.job(compose_config(SMOKE + overrides), str(tmp_path / "r"), overrides=SMOKE + overrides)
    assert said in _warnings(caplog) and "not used by this run" in _warnings(caplog)


def test_a_key_read_by_some_variant_is_not_said(tmp_path, monkeypatch, caplog):
    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    monkeypatch.setattr(cli, "run_experiment", _checked({"variants": {}, "experiment": "e", "success": None}))
    monkeypatch.setattr(cli, "_log_completed", lambda *a: None)
    over = ["experiment=goaling_smoke", "frames=3", "tracking.rtol=1e-3", "scene.body.mass=5"]
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        cli.job(compose_config(over), str(tmp_path / "r"), overrides=over)
    said = _warnings(caplog)
    assert "tracking.rtol" not in said   # the tracked variant reads it
    assert "scene.body.mass (read with scene.body.dynamic=true) not used by any variant" in said


def test_a_sweep_workers_startup_handler_is_quiet(monkeypatch, capsys):
    """SIGTERM forwarded to a sweep's idle workers printed "interrupted by SIGTERM while starting;
    nothing was run or written" beside the sweep's own report.  Since: a worker's start-up handler
    does not exit either (an idle worker that exited made loky kill the busy one while it wrote its
    ending: tests/test_probes_round17.py); the main process stops the sweep."""
    import multiprocessing

    from hairexp.app import startup

    exits = []
    monkeypatch.setattr(startup.os, "_exit", exits.append)
    monkeypatch.setattr(startup, "_BEGUN", False)
    monkeypatch.setattr(multiprocessing, "parent_process", lambda: object())   # as in a loky worker
    startup._handler(signal.SIGTERM, None)
    startup._handler(signal.SIGINT, None)
    assert capsys.readouterr().err == "" and exits == []
    monkeypatch.setattr(multiprocessing, "parent_process", lambda: None)   # the command's own process exits
    startup._handler(signal.SIGTERM, None)
    assert exits == [143] and "interrupted by SIGTERM while starting" in capsys.readouterr().err


def test_round_15_api_arguments():
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config
    from hairexp.model import RigidMotion, Strands

    line = np.c_[np.zeros(10), -np.linspace(0, 0.2, 10), np.zeros(10)]
    with pytest.raises(InputError, match=r"vertex counts must be a 1-D sequence .* got shape \(1, 1\)"):
        Strands.from_polylines(line, np.array([[10]]), 1e-4)
    with pytest.raises(InputError, match=r"times: must be a 1-D sequence of keyframe times, got shape \(1, 1\)"):
        RigidMotion(np.zeros((1, 1)), np.zeros((1, 3)), np.zeros((1, 3)))
    run = assemble(compose_config(SMOKE))
    with pytest.raises(ValueError, match=r"Simulator.step: dt=1000000000.0 s is above 10 s"):
        run.simulator.step(run.initial_state(), 1e9)


def test_hydra_keys_are_said_unused_where_they_cannot_act(caplog):
    from hairexp.app.cli import unused_folder_key
    from hairexp.app.config import compose_config

    with caplog.at_level(logging.WARNING, logger="hairexp"):
        cfg = compose_config(["hydra.run.dir=/tmp/x", "frames=3"])
    assert cfg.frames == 3 and "hydra.run.dir=/tmp/x not used: compose_config composes hairexp's config" in _warnings(caplog)
    assert unused_folder_key(["-m", "frames=2,3", "hydra.run.dir=a"]) == (
        "hairexp: warning: hydra.run.dir not used by a -m sweep (its jobs go under hydra.sweep.dir)")
    assert unused_folder_key(["hydra.sweep.dir=a"]).endswith("not used by a single run (a single run writes into "
                                                              "hydra.run.dir)")
    assert unused_folder_key(["hydra.run.dir=a"]) is None


@pytest.mark.parametrize("override, key", [("scene.body.rail_friction=1e9", "scene.body.rail_friction"),
                                           ("scene.body.mass=1e12", "scene.body.mass"),
                                           ("scene.colliders.0.spin=1e9", "scene.colliders[0].spin")])
def test_round_15_bounds(override, key):
    from hairexp.app.config import compose_config
    from hairexp.app.validate import validate_config

    with pytest.raises(InputError) as e:
        validate_config(compose_config(SMOKE + [override]))
    assert e.value.where == key


def test_the_exporter_checks_the_file_name_before_building(tmp_path, capsys, caplog):
    from hairexp.app.export_scene import main as export_main

    with caplog.at_level(logging.INFO, logger="hairexp"):
        assert export_main([str(tmp_path / "out.txt"), "experiment=goaling_smoke", "variants=[]"]) == 2
    assert "out.txt: a USD file name ends with one of .usda, .usdc, .usd" in capsys.readouterr().err
    assert "the stage holds" not in _warnings(caplog) and not caplog.records   # nothing was built


def test_a_failed_runs_log_file_says_how_it_ended(tmp_path, monkeypatch, capsys):
    """__main__.log of a failed or interrupted run had no line of its error (only stderr and the
    summary said it)."""
    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    def bad(cfg, out, **kw):
        raise InputError("no collider named 'nosuch'", "measure.collider")

    monkeypatch.setattr(cli, "run_experiment", bad)
    handler = logging.FileHandler(tmp_path / "run.log")
    logging.getLogger().addHandler(handler)
    try:
        cli.job(compose_config(SMOKE), str(tmp_path / "r"), overrides=[])
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    assert "failed (exit 2): measure.collider: no collider named 'nosuch'" in (tmp_path / "run.log").read_text()
    assert capsys.readouterr().err.count("no collider named") == 1   # the console says it once


def test_the_stylization_report_names_a_folder_it_cannot_read(tmp_path, capsys):
    """``python -m hairexp.evaluation.stylization /nonexist``: a traceback, exit 1; a goaling run's
    folder was measured against default rail values."""
    from hairexp.evaluation.stylization import main

    assert main([str(tmp_path / "nonexist")]) == 2
    assert "not a finished run folder" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").write_text(json.dumps({"config": {"scene": {"body": {"dynamic": False}}}}))
    np.savez(tmp_path / "run" / "result.npz", times=np.zeros(1))
    assert main([str(tmp_path / "run")]) == 2
    assert "its body is keyframed (scene.body.dynamic=false): it has no rail to measure" in capsys.readouterr().err


@pytest.mark.parametrize("subdir, said", [("${oc.env:NOPE_HAIREXP_X}", "the environment variable NOPE_HAIREXP_X is not set"),
                                          ("${foo:bar}", "unknown resolver 'foo'"),
                                          ("${scene.nope}", "refers to ${scene.nope}, which is not a key")])
def test_an_unresolvable_sweep_subdir_is_one_line_before_hydra(subdir, said, monkeypatch):
    from hairexp.app.cli import run_dir_value_error

    monkeypatch.delenv("NOPE_HAIREXP_X", raising=False)
    msg = run_dir_value_error(["-m", *SMOKE, "frames=2,3", f"hydra.sweep.subdir={subdir}"])
    assert msg is not None and msg.startswith(f"hairexp: error: hydra.sweep.subdir={subdir}: ") and said in msg


def test_the_exporter_refuses_a_stage_of_too_many_frames(tmp_path, capsys):
    from hairexp.app.export_scene import main as export_main

    assert export_main([str(tmp_path / "s.usda"), "experiment=goaling_smoke", "variants=[]", "frames=20000000"]) == 2
    assert "frames: is 20000000: a stage of more than 100,000 frames" in capsys.readouterr().err
    assert not (tmp_path / "s.usda").exists()


def test_a_signal_inside_numbas_compile_cache_callback_is_sent_again_later():
    """SIGINT inside llvmlite's object-cache callback (a ctypes callback: the exception is printed
    as "Exception ignored" and lost) left numba's library half-built and the run failed, exit 1."""
    import sys as _sys

    from hairexp.app.signals import _in_finaliser

    def _raw_object_cache_notify():
        return _in_finaliser(_sys._getframe())

    assert _raw_object_cache_notify() and not _in_finaliser(_sys._getframe())


# round 16's short probe

def test_round_16_findings(capsys):
    from hairexp.app.config import compose_config
    from hairexp.app.export_scene import main as export_main
    from hairexp.app.validate import unused_settings
    from hairexp.model.builders import check_counts

    with pytest.raises(InputError, match=r"scene.length: is 1e-12 m: a strand of 3 vertices \(the fewest\) needs at least"):
        check_counts(40, 20, 1e-12)   # it advised "use at most 1 vertices"
    cfg = compose_config(SMOKE + ["collision=off"])
    assert unused_settings([cfg], ["collision.skin"]) == ["collision.skin (read with collision.hair_hair=true)"]
    assert export_main(["--bogus", "s.usda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hairexp: error: unknown option --bogus")


def test_round_16_bounds_and_a_variants_typo(tmp_path):
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import apply_overrides

    with pytest.raises(InputError, match="solver.max_backtracks: must be at most 100"):
        assemble(compose_config(SMOKE + ["solver.max_backtracks=1000000"]))
    with pytest.raises(InputError, match=r"scene.hair.stretch_stiffness: is 1e-30 N, below 0.001"):
        assemble(compose_config(SMOKE + ["scene.hair.stretch_stiffness=1e-30"]))
    with pytest.raises(InputError, match=r"unknown key 'tracking.rtoll'; did you mean 'tracking.rtol'"):
        apply_overrides(compose_config(["experiment=goaling_smoke"]), ["tracking.rtoll=1"], "variants[0] (x)")
