"""Findings of the sixth independent probe round (after the fifth's fixes), one test each:

1. USD: ``hairexp:spin`` authored as agreeing time samples is read (it was refused, "got None");
   a stage whose sublayer is missing is refused (USD skipped it with a C++ warning and the run
   went on without what it held, exit 0).
2. sweeps: a constant ``hydra.sweep.subdir`` (every job in one folder) is refused before Hydra starts.
3. signals: a frame goes to the run's sinks whole: a signal inside the send of a chunk of frames
   is kept until the frame is logged (it dropped 250 frames of an entity from the partial recording).
4. run folders: ``overwrite=true`` over a run that is still running is refused (it deleted the
   live run's files under it and the folder mixed two runs).
5. checked before anything runs: a tiny ``fps`` (1e-3 failed after the guide simulation, naming
   "guides: fps"), a later variant's guide file (read only when that variant started), a
   ``scene.usd_colliders`` that names one collider instead of their parent (it ran with none);
   ``experiments.compare_checkouts`` with a path that is not a checkout is a usage error.
"""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest
from probe_helpers import SMALL

from hairexp.app import cli
from hairexp.app.config import compose_config
from hairexp.errors import InputError


@pytest.fixture()
def stage(tmp_path):
    from usd_helpers import COLLIDERS, source_cfg, write_stage

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS[2:3]))   # the wheel: a cylinder with a spin
    return path


def test_a_spin_authored_as_agreeing_time_samples_is_read(stage):
    from usd_helpers import edit_stage, usd_cfg

    from hairexp.app.builders import build_scene

    def sampled(st):
        a = st.GetPrimAtPath("/Root/Colliders/wheel").GetAttribute("hairexp:spin")
        a.Clear()
        a.Set(5.0, 0.0)
        a.Set(5.0, 3.0)

    edit_stage(stage, sampled)
    assert build_scene(usd_cfg(stage).scene).colliders[0].spin == pytest.approx(5.0)


def test_a_stage_with_a_missing_sublayer_is_refused(stage, tmp_path):
    from pxr import Sdf
    from usd_helpers import usd_cfg

    from hairexp.app.builders import build_scene

    root = Sdf.Layer.CreateNew(str(tmp_path / "root.usda"))
    root.subLayerPaths.append("missing.usda")
    root.subLayerPaths.append(stage.name)
    root.Save()
    with pytest.raises(InputError, match=r"the stage does not compose: .*missing.usda") as err:
        build_scene(usd_cfg(tmp_path / "root.usda").scene)
    assert err.value.where.startswith("scene.usd=")


def test_a_sweep_with_one_folder_for_every_job_is_refused(tmp_path):
    argv = ["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={tmp_path / 's'}", "hydra.sweep.subdir=same"]
    msg = cli.used_dir_error(argv)
    assert msg is not None and "every job of the sweep would write into the same folder" in msg, msg
    ok = ["-m", *SMALL, "solver.dt=0.04,0.02", f"hydra.sweep.dir={tmp_path / 's'}", "hydra.sweep.subdir=${hydra.job.num}_x"]
    assert cli.used_dir_error(ok) is None


def test_a_signal_inside_a_frames_logging_is_kept_until_the_frame_is_whole(tmp_path, monkeypatch):
    from hairexp.outputs.files import ResultRecorder

    real = ResultRecorder.log_frame

    def log_then_signal(self, frame, *a, **k):
        if frame == 3:
            os.kill(os.getpid(), signal.SIGTERM)   # lands inside the frame's logging
        real(self, frame, *a, **k)

    monkeypatch.setattr(ResultRecorder, "log_frame", log_then_signal)
    out = tmp_path / "run"
    res = cli.job(compose_config([*SMALL[:2], "frames=6", "logging.rerun=false", "logging.progress=false"]), str(out))
    assert res["status"] == "interrupted" and res["code"] == 143, res
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"
    times = np.load(out / "stream" / "times.npy")
    assert len(times) == 4, times   # frames 0..3: the signalled frame was logged whole before the interrupt


def test_overwrite_refuses_a_folder_whose_run_is_still_running(tmp_path):
    """overwrite=true deleted a live run's files under it; the live run then failed and the folder
    mixed the two runs' files."""
    from hairexp.outputs.folder import claim, owner

    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"status": "running", **owner()}))   # this process: alive
    (folder / "metrics.parquet").write_bytes(b"x")
    with pytest.raises(InputError, match=r"holds a run still running \(pid \d+\): overwrite=true replaces a finished"):
        claim(folder, overwrite=True)
    assert (folder / "metrics.parquet").exists()   # nothing deleted
    msg = cli.used_dir_error([*SMALL, "overwrite=true", f"hydra.run.dir={folder}"])
    assert msg is not None and "still running" in msg, msg   # before Hydra writes .hydra/ into it


def test_a_tiny_fps_names_fps_before_anything_runs(tmp_path):
    from hairexp.app.assemble import check_config

    with pytest.raises(InputError, match=r"must be a finite number from 0.1 to 100000 .*got 0.001") as err:
        check_config(compose_config([*SMALL, "fps=1e-3", "frames=1"]))
    assert err.value.where == "fps"


def test_a_collider_prim_named_instead_of_their_parent_is_refused(tmp_path):
    from usd_helpers import COLLIDERS, source_cfg, usd_cfg, write_stage

    from hairexp.app.builders import build_scene

    path = tmp_path / "scene.usda"
    write_stage(path, source_cfg(colliders=COLLIDERS[:1]))
    with pytest.raises(InputError, match=r"is a Sphere: scene.usd_colliders names the parent of the colliders"):
        build_scene(usd_cfg(path, **{"scene.usd_colliders": "/Root/Colliders/ball"}).scene)


def test_a_later_variants_guide_file_is_read_before_any_variant_runs(tmp_path):
    from hairexp.app.experiment import run_experiment

    pts = np.zeros((4, 30, 3))
    pts[:, :, 1] = -np.tile(np.linspace(0, 0.3, 10), 3)
    pts[2, 5, 1] = np.nan
    bad = tmp_path / "nan.npz"
    np.savez(bad, guide_positions=pts, guide_offsets=np.array([0, 10, 20, 30]), fps=np.float64(25))
    variants = ("variants=[{name: a, overrides: ['controller.name=free']}, {name: b, overrides: "
                f"['controller.name=tracking', 'guides.source=file', 'guides.file={bad}', 'guides.edits=[]']}}]")
    cfg = compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=false", "judge=none", variants])
    out = tmp_path / "exp"
    with pytest.raises(InputError, match=r"vertex 5 is not finite.*variants\[1\] b, checked before any variant runs"):
        run_experiment(cfg, out)
    assert not (out / "a").exists()   # the first variant did not run


def test_compare_checkouts_refuses_a_path_that_is_not_a_checkout(capsys):
    from experiments.compare_checkouts import main

    with pytest.raises(SystemExit) as exc:
        main(["/nonexistent"])
    assert exc.value.code == 2 and "not a hairexp checkout" in capsys.readouterr().err


def test_a_run_folder_from_an_environment_variable_is_checked(tmp_path, monkeypatch):
    """``hydra.run.dir=${oc.env:RUNDIR}`` naming a file gave Hydra's traceback, exit 1; the
    variable is now resolved before the folder checks (a file: exit 4; a used folder: exit 2)."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    monkeypatch.setenv("RUNDIR", str(afile))
    msg = cli.run_dir_error([*SMALL, "hydra.run.dir=${oc.env:RUNDIR}"])
    assert msg is not None and f"cannot be the run folder: {afile} is a file" in msg, msg
    used = tmp_path / "used"
    used.mkdir()
    (used / "result.npz").write_bytes(b"x")
    monkeypatch.setenv("RUNDIR", str(used))
    msg = cli.used_dir_error([*SMALL, "hydra.run.dir=${oc.env:RUNDIR}"])
    assert msg is not None and "the run folder is not empty" in msg, msg
    monkeypatch.setenv("RUNDIR", str(tmp_path / "new"))
    assert cli.run_dir_error([*SMALL, "hydra.run.dir=${oc.env:RUNDIR}"]) is None
