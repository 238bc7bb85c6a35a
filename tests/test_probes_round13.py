"""Findings of issue 12's thirteenth probe round, one test each (one bad: export_scene replaced an
existing file; the rest weak)."""

from __future__ import annotations

import json
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

    notes = tmp_path / "notes.txt"
    notes.write_text("a user's file")
    assert export_main([str(notes), "experiment=goaling_smoke"]) == 2
    assert "notes.txt: the file exists; give --force to replace it" in capsys.readouterr().err
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
