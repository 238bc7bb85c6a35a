"""Findings of the seventh independent probe round (after the sixth's fixes), one test each:

1. run folders: a refused ``overwrite=true`` (the folder also holds a file no run wrote) is refused
   before Hydra starts (it had replaced the previous run's ``.hydra/`` record with its own), and
   ``overwrite=true`` with a bad value leaves the previous run in place (it was deleted first).
2. an interrupted or failed run with no step kept does not point at "partial results".
3. sweeps: a value swept twice with a ``hydra.sweep.subdir`` without the job number (two jobs, one
   folder) is refused before Hydra starts; a second SIGINT does not cut the main process's wait
   for its jobs' endings short.
4. checked before anything runs: a USD stage's ``timeCodesPerSecond`` used as the run's rate names
   the stage (it said ``fps``); a variant name longer than a folder name (exit 4 late); ``+key``
   on a key that already has a value (``+scene.colliders`` replaced goaling's wheel silently);
   ``Run.steps`` past the guide animation (it froze the guides and said converged).
5. scripts: bad arguments are usage errors, a run that is not completed is refused by
   ``scene_pictures``, and an interrupted script prints one line and exits 128 + signal.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from probe_helpers import SMALL

from hairexp.app import cli
from hairexp.app.config import compose_config
from hairexp.errors import InputError, Interrupted


def _completed_run(folder: Path) -> None:
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"status": "completed"}))
    (folder / "result.npz").write_bytes(b"PK\x03\x04results")   # a zip's first bytes: a run's file
    (folder / ".hydra").mkdir()
    (folder / ".hydra" / "config.yaml").write_text("old: record\n")


def test_a_refused_overwrite_is_refused_before_hydra_writes_its_record(tmp_path):
    folder = tmp_path / "run"
    _completed_run(folder)
    (folder / "notes.txt").write_text("mine")
    msg = cli.used_dir_error([*SMALL, "overwrite=true", f"hydra.run.dir={folder}"])
    assert msg is not None and "removes only what a run wrote" in msg and "notes.txt" in msg, msg
    assert (folder / ".hydra" / "config.yaml").read_text() == "old: record\n"
    # a folder that holds only a finished run's files is still replaced
    (folder / "notes.txt").unlink()
    assert cli.used_dir_error([*SMALL, "overwrite=true", f"hydra.run.dir={folder}"]) is None


def test_overwrite_with_a_bad_value_keeps_the_previous_run(tmp_path):
    from hairexp.app.run import run

    folder = tmp_path / "run"
    _completed_run(folder)
    cfg = compose_config([*SMALL, "overwrite=true", "solver.dt=-1"])
    with pytest.raises(InputError):
        run(cfg, folder)
    assert (folder / "result.npz").read_bytes() == b"PK\x03\x04results"
    assert json.loads((folder / "summary.json").read_text())["status"] == "completed"
    # the command line says so before Hydra replaces the run's .hydra/ record
    msg = cli.used_dir_error([*SMALL, "overwrite=true", "solver.dt=-1", f"hydra.run.dir={folder}"])
    assert msg is not None and "solver.dt: must be a finite number > 0" in msg, msg


def test_an_interruption_before_any_step_does_not_announce_partial_results(tmp_path, capsys):
    assert cli.kept(tmp_path, "partial results") == f"no step of the hair ran; summary.json in {tmp_path} says so"
    (tmp_path / "v").mkdir()
    (tmp_path / "v" / "metrics.parquet").write_bytes(b"x")
    # metrics of another run (a summary not this process's: an overwrite=true ended before its claim)
    (tmp_path / "summary.json").write_text(json.dumps({"status": "completed", "pid": os.getpid() + 1, "host": "x"}))
    assert cli.kept(tmp_path, "partial results") == (f"no step of the hair ran; {tmp_path} still holds the previous "
                                                      "run, as it was")
    from hairexp.outputs.folder import owner

    (tmp_path / "summary.json").write_text(json.dumps({"status": "interrupted", **owner()}))   # this run's
    assert cli.kept(tmp_path, "partial results") == f"partial results in {tmp_path}"


def test_a_value_swept_twice_into_one_folder_is_refused(tmp_path):
    args = ["-m", *SMALL, "solver.dt=0.04,0.04", "hydra.sweep.subdir=${hydra.job.override_dirname}",
            f"hydra.sweep.dir={tmp_path / 'sweep'}"]
    msg = cli.used_dir_error(args)
    assert msg is not None and "swept twice" in msg and "solver.dt=0.04,0.04" in msg, msg
    # the default subdir (the job number): two runs, two folders
    assert cli.used_dir_error(["-m", *SMALL, "solver.dt=0.04,0.04", f"hydra.sweep.dir={tmp_path / 's2'}"]) is None


def test_a_second_signal_does_not_cut_the_sweeps_wait_short(capsys):
    from hairexp.app.signals import InterruptSignals

    calls = []
    sig = InterruptSignals()

    def on_signal(signum):   # the sweep's wait: a second signal arrives meanwhile
        calls.append(signum)
        sig._handler(signal.SIGINT, None)
        calls.append("waited")

    sig.on_signal = on_signal
    with pytest.raises(Interrupted):
        sig._handler(signal.SIGINT, None)
    assert calls == [signal.SIGINT, "waited"]
    assert "still stopping" in capsys.readouterr().err


def test_a_stage_rate_outside_the_fps_bounds_names_the_stage(tmp_path):
    from pxr import Usd
    from usd_helpers import COLLIDERS, source_cfg, usd_cfg, write_stage

    from hairexp.app.assemble import check_config

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS[:1]))
    stage = Usd.Stage.Open(str(path))
    stage.SetTimeCodesPerSecond(0.01)
    stage.GetRootLayer().Save()
    with pytest.raises(InputError, match=r"timeCodesPerSecond is 0.01; with fps null") as err:
        check_config(usd_cfg(path))
    assert str(path) in err.value.where


def test_a_variant_name_longer_than_a_folder_name_is_refused():
    from hairexp.app.experiment import MAX_NAME_BYTES, check_variant_names
    from omegaconf import OmegaConf

    long = OmegaConf.create([{"name": "a" * (MAX_NAME_BYTES + 1), "overrides": []}])
    with pytest.raises(InputError, match=r"bytes long") as err:
        check_variant_names(long)
    assert err.value.where == "variants[0].name"
    assert check_variant_names(OmegaConf.create([{"name": "a" * MAX_NAME_BYTES, "overrides": []}]))


def test_plus_on_a_key_with_a_value_is_refused():
    with pytest.raises(InputError, match=r"already has a value.*wheel.*write scene.colliders=\.\.\. to replace") as err:
        compose_config(["experiment=goaling_smoke", "+scene.colliders=[{name: ball, shape: sphere, radius: 0.01}]"])
    assert err.value.where == "scene.colliders"
    cfg = compose_config(["experiment=goaling_smoke", "scene.colliders=[{name: ball, shape: sphere, radius: 0.01}]"])
    assert [c.name for c in cfg.scene.colliders] == ["ball"]   # replacing is said without '+'


def test_api_steps_past_the_guide_animation_are_refused():
    from hairexp.app.assemble import assemble

    r = assemble(compose_config([*SMALL, "frames=3", "controller.name=tracking"]))
    assert len(list(r.steps(frames=3))) == 3
    with pytest.raises(InputError, match=r"^Run.steps: frames: 10 frames .* past the guide animation.s end \(0.12 s, frames 0..3\)"):
        next(iter(r.steps(frames=10)))
    free = assemble(compose_config([*SMALL, "frames=3", "controller.name=free"]))
    assert len(list(free.steps(frames=5))) == 5   # a free run does not follow the guides


def test_script_arguments_and_interruptions(tmp_path, capsys, monkeypatch):
    from experiments.common import run_script
    from experiments.rrd_index_memory import main as rrd_main
    from experiments.scene_pictures import main as pictures_main

    with pytest.raises(SystemExit) as exc:
        rrd_main(["--frames", "-1"])
    assert exc.value.code == 2 and "positive integer" in capsys.readouterr().err
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"status": "interrupted"}))
    with pytest.raises(SystemExit) as exc:
        pictures_main([str(run), str(tmp_path / "x.png")])
    assert exc.value.code == 2 and "the run is interrupted" in capsys.readouterr().err

    def interrupted():
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr("sys.argv", ["/x/experiments/accuracy.py"])
    with pytest.raises(SystemExit) as exc:
        run_script(interrupted)
    err = capsys.readouterr().err
    assert exc.value.code == 143 and err.strip() == "accuracy: interrupted by SIGTERM; the runs finished before it are kept"
    with pytest.raises(SystemExit) as exc:
        run_script(lambda: 3)
    assert exc.value.code == 3
