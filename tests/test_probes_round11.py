"""Findings of issue 12's eleventh probe round, one test each: sweep job folders resolved with
every resolver and never shared, a failed run's aggregates under on_unconverged=fail, foreign
files inside a run's own folders, unresolvable interpolations, a dangling run-folder link, the
launch lock's corner cases, and a tracking set-up too large to build."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from hairexp.errors import InputError

SWEEP = ["-m", "experiment=goaling_smoke", "variants=[]", "frames=2"]


def test_a_subdir_through_an_environment_variable_cannot_climb_out(monkeypatch):
    from hairexp.app.cli import used_dir_error

    monkeypatch.setenv("HX_PROBE_ESC", "../../x")
    msg = used_dir_error(SWEEP + ["frames=2,3", "hydra.sweep.dir=/tmp/hx_probe11/a/b",
                                  "hydra.sweep.subdir=${oc.env:HX_PROBE_ESC}/${hydra.job.num}"])
    assert msg is not None and "outside the sweep folder" in msg and "../../x/0" in msg


def test_a_subdir_at_the_working_folder_is_refused():
    from hairexp.app.cli import used_dir_error

    msg = used_dir_error(SWEEP + ["frames=2,3", "hydra.sweep.dir=/tmp/hx_probe11/c",
                                  "hydra.sweep.subdir=${hydra:runtime.cwd}/${hydra.job.num}"])
    assert msg is not None and "outside the sweep folder" in msg


def test_two_jobs_into_one_folder_are_refused_before_hydra():
    from hairexp.app.cli import used_dir_error

    msg = used_dir_error(SWEEP + ["frames=3,03", "hydra.sweep.dir=/tmp/hx_probe11/d", "hydra.sweep.subdir=j${frames}"])
    assert msg is not None and "would both write into j3" in msg
    assert used_dir_error(SWEEP + ["frames=2,3", "hydra.sweep.dir=/tmp/hx_probe11/e",
                                   "hydra.sweep.subdir=j${frames}"]) is None


def test_on_unconverged_fail_keeps_the_metrics_aggregates(tmp_path):
    """The policy's failure is not a failed step: the aggregates are those of metrics.parquet (it
    added a phantom failed step 11 of 10)."""
    import pandas as pd

    from hairexp.app.config import compose_config
    from hairexp.app.run import run
    from hairexp.errors import SimulationError

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "solver.max_iterations=1",
                          "solver.on_failure=warn", "frames=10", "on_unconverged=fail", "logging.rerun=false",
                          "logging.progress=false"])
    with pytest.raises(SimulationError, match="did not converge"):
        run(cfg, tmp_path / "r")
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    df = pd.read_parquet(tmp_path / "r" / "metrics.parquet")
    assert s["steps"] == len(df)
    assert s["unconverged_steps"] == int((~df["converged"]).sum()) > 0
    assert s["converged_fraction"] == pytest.approx(float(df["converged"].mean()))
    assert s.get("failed_step") is None and s["converged"] is False


@pytest.mark.parametrize("inside", ["stream/notes.txt", "result.clips/notes.txt", "stream/metrics/x.csv"])
def test_overwrite_refuses_a_foreign_file_inside_a_runs_own_folder(tmp_path, inside):
    from hairexp.outputs.folder import claim, overwrite_refusal

    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text(json.dumps({"status": "completed"}))
    (run / "stream" / "metrics").mkdir(parents=True)
    (run / "stream" / "positions.npy").write_bytes(b"x")
    (run / "stream" / "metrics" / "part-00000.parquet").write_bytes(b"x")
    (run / "result.clips").mkdir()
    (run / "result.clips" / "0.usdc").write_bytes(b"x")
    (run / inside).write_text("mine")
    assert inside in overwrite_refusal(run)
    with pytest.raises(InputError):
        claim(run, overwrite=True)
    assert (run / inside).read_text() == "mine" and (run / "summary.json").is_file()
    (run / inside).unlink()   # without it, the run's own files go
    claim(run, overwrite=True)
    assert not (run / "stream").exists() and not (run / "result.clips").exists()


@pytest.mark.parametrize("override, key", [("guides.interpolation=${oc.env:HX_SURELY_UNSET_VAR}", "guides.interpolation"),
                                           ("scene.name=${foo.bar}", "scene.name"),
                                           ("frames=${oc.env:HX_SURELY_UNSET_VAR,abc}", "frames")])
def test_an_unresolvable_interpolation_is_named(override, key):
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match="cannot resolve its value") as e:
        compose_config(["experiment=goaling_smoke", override])
    assert e.value.where == key


def test_a_dangling_link_as_run_folder_is_refused(tmp_path):
    from hairexp.app.cli import run_dir_error

    link = tmp_path / "L"
    link.symlink_to(tmp_path / "nowhere")
    msg = run_dir_error(["experiment=goaling_smoke", f"hydra.run.dir={link}"])
    assert msg is not None and "symbolic link" in msg and "does not exist" in msg


def test_a_linked_lock_is_not_followed(tmp_path):
    from hairexp.outputs.folder import LOCK, hold

    run, outside = tmp_path / "run", tmp_path / "outside"
    run.mkdir()
    (run / LOCK).symlink_to(outside)
    with pytest.raises(InputError, match="symbolic link"):
        hold(run)
    assert not outside.exists()


def test_a_launch_inside_a_live_launchs_folder_is_refused(tmp_path):
    from hairexp.app.cli import hold_folder_error
    from hairexp.outputs.folder import hold

    live = tmp_path / "sweepA"
    assert hold(live)   # this process plays the live sweep: another open of its lock is another launch
    msg = hold_folder_error(["-m", "experiment=goaling_smoke", "frames=2,3", f"hydra.sweep.dir={live / '1'}"])
    assert msg is not None and "lies inside" in msg and str(live) in msg


def test_guides_count_is_checked_before_the_edits():
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config

    with pytest.raises(InputError, match="must be >= 1") as e:
        check_config(compose_config(["experiment=goaling_smoke", "controller=tracking", "guides.count=0"]))
    assert e.value.where == "guides.count"


def test_a_tracking_set_up_too_large_to_build_is_refused_before_allocating():
    """4 guides x 256 points on 200 strands: 13.8 GiB of indices were allocated, then the machine's
    memory ran out; now an InputError naming tracking.points_per_guide, at once."""
    from hairexp.app.assemble import assemble
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "controller=tracking",
                          "tracking.points_per_guide=256", "guides.count=4", "scene.n_strands=200",
                          "scene.n_vertices=40", "frames=3", "logging.rerun=false", "scene.settle=0"])
    with pytest.raises(InputError, match="Schur blocks (would|could) take") as e:
        assemble(cfg)
    assert e.value.where == "tracking.points_per_guide"


def test_the_schur_estimate_is_checked_before_any_variant_runs(tmp_path):
    """The experiment's tracked variant would be refused: nothing runs, not even the free variant."""
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment

    cfg = compose_config(["experiment=goaling_smoke", "tracking.points_per_guide=256", "guides.count=4",
                          "scene.n_strands=200", "scene.n_vertices=40", "frames=3", "logging.rerun=false"])
    with pytest.raises(InputError, match="could take .* GiB"):
        run_experiment(cfg, tmp_path / "exp")
    assert not (tmp_path / "exp" / "free").exists()


def test_the_schur_estimate_lets_the_paper_scenes_and_10000_strands_through():
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config

    for over in (["experiment=celia"], ["experiment=celia", "scene.n_strands=10000", "controller.name=tracking"],
                 ["experiment=goaling"], ["experiment=splitting"], ["experiment=spreading"]):
        check_config(compose_config(over))
