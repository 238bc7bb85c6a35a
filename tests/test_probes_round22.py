"""Findings of the independent probe round 22 of issue 12 (on ``d7712da``), fixed: a signal while
``overwrite=true`` removes the previous run, and an experiment interrupted after its variants."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from hairexp.errors import Interrupted
from probe_helpers import SMALL

SMOKE = [*SMALL, "logging=off"]


def _signal_on_second_removal(monkeypatch, signum=signal.SIGTERM):
    """Send ``signum`` to this process when overwrite=true removes its second file."""
    removed = []
    real_unlink = Path.unlink

    def unlink(self, *a, **k):
        removed.append(self.name)
        out = real_unlink(self, *a, **k)
        if len(removed) == 2:
            os.kill(os.getpid(), signum)
        return out

    monkeypatch.setattr(Path, "unlink", unlink)
    return removed


@pytest.mark.parametrize("experiment", [False, True])
def test_a_signal_while_overwrite_removes_the_old_run_ends_interrupted(tmp_path, monkeypatch, experiment):
    """SIGTERM in the middle of the removal: it is kept until the old run is gone, then the run ends
    ``interrupted`` with a summary (it left no summary beside half of the old run's files)."""
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment
    from hairexp.app.run import run

    go = run_experiment if experiment else run
    out = tmp_path / "r"
    go(compose_config(SMOKE), out)
    assert (out / "result.npz").is_file()
    removed = _signal_on_second_removal(monkeypatch)
    with pytest.raises(Interrupted) as e:
        go(compose_config([*SMOKE, "overwrite=true", "frames=3"]), out)
    monkeypatch.undo()
    assert e.value.signum == signal.SIGTERM and len(removed) >= 2
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and s.get("steps", 0) == 0
    assert not (out / "result.npz").exists() and not (out / "result.usdc").exists()   # the old run's: all gone
    assert not list(out.rglob("*.tmp*"))


def test_an_experiment_interrupted_after_its_verdict_is_no_success(tmp_path, monkeypatch):
    """A signal during the comparison recording (after the judge gave its verdict): the summary says
    interrupted and success null, the verdict kept (it said success: true)."""
    import hairexp.outputs.comparison as comparison
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment

    def interrupted(*a, **k):
        os.kill(os.getpid(), signal.SIGINT)
        return None

    monkeypatch.setattr(comparison, "write_comparison", interrupted)
    out = tmp_path / "e"
    cfg = compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=true"])
    with pytest.raises(Interrupted):
        run_experiment(cfg, out)
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and s["success"] is None and "verdict" in s
    assert all(v["status"] == "completed" for v in s["variants"].values())
    for name in s["variants"]:
        with np.load(out / name / "result.npz") as r:
            assert len(r["times"]) == 4


# ---------------------------------------------------------------------------------------------
# a user's own config file (--config-dir / --config-name) that is broken: one line, exit 2
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("body, said", [
    ("frames: [1, 2\n", "not valid YAML: while parsing a flow sequence in"),
    ("frmes: 3\n", "Key 'frmes' not in 'Config' (key frmes)"),
    ("frames: abc\n", "Value 'abc' of type 'str' could not be converted to Integer (key frames)"),
])
def test_a_broken_user_config_file_is_one_line_exit_2_and_no_folder(tmp_path, body, said):
    from probe_helpers import run_cli

    (tmp_path / "mine.yaml").write_text("defaults:\n  - config\n  - _self_\n" + body)
    out = tmp_path / "out"
    p = run_cli(["--config-dir", str(tmp_path), "--config-name", "mine", *SMALL, f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hairexp: error: --config-name=mine: ") and said in lines[0], p.stderr
    if "YAML" in said:
        assert "mine.yaml" in lines[0] and "line 4" in lines[0]
    assert not out.exists()


# ---------------------------------------------------------------------------------------------
# independent probe round 21: standard streams, Hydra's own keys and flags, export signals
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("redirect", ["stdout-closed", "stderr-closed"])
def test_a_run_with_a_closed_standard_stream_completes_exit_0(tmp_path, redirect):
    """``>&-`` / ``2>&-``: Python has no sys.stdout / sys.stderr (the final flush raised, exit 1)."""
    import subprocess
    import sys

    from probe_helpers import REPO

    out = tmp_path / "r"
    fd = 1 if redirect == "stdout-closed" else 2
    code = f"import os, runpy, sys; os.close({fd}); sys.argv[0] = {str(REPO / 'hairexp' / '__main__.py')!r}; " \
           f"runpy.run_module('hairexp', run_name='__main__', alter_sys=True)"
    p = subprocess.run([sys.executable, "-c", code, *SMOKE, f"hydra.run.dir={out}"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def test_printing_the_config_to_a_full_stdout_is_one_line_exit_4(tmp_path):
    import subprocess
    import sys

    from probe_helpers import REPO

    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE, "--cfg", "job"], cwd=tmp_path, stdout=full,
                           stderr=subprocess.PIPE, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 4, p.stderr
    assert p.stderr.strip().splitlines() == ["hairexp: error: cannot write the standard output: [Errno 28] No space "
                                             "left on device"]


@pytest.mark.parametrize("arg, said", [
    ("hydra.job.name=../../victim", "hydra.job.name=../../victim: the job's name is its log file's name"),
    ("hydra.output_subdir=../x", "hydra.output_subdir=../x: Hydra's record of the run (.hydra) goes in a folder"),
    ("hydra.output_subdir=/abs", "hydra.output_subdir=/abs: Hydra's record"),
])
def test_hydra_names_that_write_outside_the_run_folder_are_refused(tmp_path, arg, said):
    from probe_helpers import run_cli

    out = tmp_path / "a" / "b" / "r"
    p = run_cli([*SMOKE, f"hydra.run.dir={out}", arg], tmp_path)
    assert p.returncode == 2 and p.stderr.strip().splitlines()[-1].startswith(f"hairexp: error: {said}"), p.stderr
    assert not out.exists() and not list(tmp_path.rglob("victim*")) and not (tmp_path / "a" / "b" / "x").exists()


def test_a_run_with_its_hydra_record_renamed_is_not_refused_as_another_runs(tmp_path):
    from probe_helpers import run_cli

    out = tmp_path / "r"
    p = run_cli([*SMOKE, f"hydra.run.dir={out}", "hydra.output_subdir=rec"], tmp_path)
    assert p.returncode == 0, p.stderr
    assert (out / "rec" / "config.yaml").is_file() and (out / "result.npz").is_file()
    p = run_cli([*SMOKE, f"hydra.run.dir={out}", "hydra.output_subdir=rec"], tmp_path)   # a used folder, still
    assert p.returncode == 2 and "not empty (guides.npz, metrics.parquet" in p.stderr, p.stderr


@pytest.mark.parametrize("args, said", [
    (["-m", "hydra.launcher.n_jobs=0"], "hydra.launcher.n_jobs=0: the number of jobs run at once is a positive count"),
    (["--shell-completion"], "--shell-completion: give one of install=bash, install=zsh"),   # round 27: hairexp's line
    (["--experimental-rerun", "nothere.pickle"], "--experimental-rerun: File nothere.pickle does not exist"),
    # round 23
    (["--info", "nosuch"], "nosuch: not a valid override: missing EQUAL"),   # round 31: before Hydra's 27 lines
    (["hydra.output_subdir=stream"], "hydra.output_subdir=stream: Hydra's record of the run (.hydra) goes in a folder"),
    (["hydra.output_subdir=.lock"], "hydra.output_subdir=.lock: Hydra's record"),
    (["hydra.job.name=" + "j" * 300], "hydra.job.name=jjjj"),
    (["-m", "hydra.launcher.batch_size=0"], "hydra.launcher.batch_size=0: joblib's batch size is a positive count"),
])
def test_hydra_flags_and_launcher_values_it_refuses_are_one_line_exit_2(tmp_path, args, said):
    from probe_helpers import run_cli

    p = run_cli([*SMOKE, *args, f"hydra.sweep.dir={tmp_path / 's'}", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.strip().splitlines()[-1].startswith(f"hairexp: error: {said}"), \
        p.stderr
    assert not (tmp_path / "s").exists() and not (tmp_path / "r").exists()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_an_export_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys, signum):
    """Ctrl-C printed a KeyboardInterrupt traceback; SIGTERM left the temporary stage behind."""
    import hairexp.app.export_scene as ex
    import hairexp.io.usd_write as usd_write

    real = usd_write._saved

    def saved(path, write):   # the stage is being written when the signal comes
        write()
        os.kill(os.getpid(), signum)
        return real(path, lambda: None)

    monkeypatch.setattr(usd_write, "_saved", saved)
    path = tmp_path / "s.usda"
    code = ex.main([str(path), "experiment=goaling_smoke", "variants=[]", "frames=3"])
    assert code == 128 + signum
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"hairexp: interrupted by {signal.Signals(signum).name} while exporting; nothing was written "
                       f"to {path}")
    assert list(tmp_path.iterdir()) == []


def test_an_export_says_the_frames_it_wrote(tmp_path, capsys):
    import hairexp.app.export_scene as ex

    assert ex.main([str(tmp_path / "s.usda"), "experiment=goaling_smoke", "variants=[]", "frames=5"]) == 0
    assert capsys.readouterr().out.strip().endswith("3 guides, 5 frames (0..5)")


@pytest.mark.parametrize("report", ['{"scenes": {"goaling": 3}, "command": "x"}', '[1]',
                                    '{"scenes": {"goaling": {"success": true}}, "command": "x"}'])
def test_integrator_verdicts_refuses_a_foreign_report_with_a_usage_error(tmp_path, capsys, report):
    """A report without ``machine`` or with scenes of another shape: a KeyError traceback (round 21)."""
    from experiments.integrator_verdicts import main

    (tmp_path / "r.json").write_text(report)
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "r.json")])
    assert e.value.code == 2
    assert "r.json: " in capsys.readouterr().err


def test_a_judge_without_variants_is_said_not_used(tmp_path):
    from probe_helpers import run_cli

    p = run_cli([*SMOKE, "judge=free_misses_tracked_hits", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 0, p.stderr
    assert "judge (read with variants: a judge compares an experiment's variants" in p.stderr


def test_the_stylization_report_command_without_a_folder_is_a_usage_error(capsys):
    from hairexp.evaluation.stylization import main

    assert main([]) == 2
    assert capsys.readouterr().err.startswith("hairexp: error: a run folder is required (usage: ")
    assert main(["--help"]) == 0


def test_compare_runs_names_a_file_that_is_not_an_npz(tmp_path, capsys):
    import shutil

    from experiments.compare_runs import main
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    run(compose_config(SMOKE), tmp_path / "a")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    (tmp_path / "b" / "result.npz").write_bytes(b"garbage")
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    assert f"{tmp_path / 'b' / 'result.npz'} is not an .npz (zip) archive" in capsys.readouterr().err


SIGNAL_AFTER_RECORD = """
import os, runpy, signal, sys
import hydra.core.utils as u
real = u._save_config
def save(cfg, filename, output_dir):
    real(cfg, filename, output_dir)
    if filename == "overrides.yaml":   # Hydra's record is written; the job has not begun
        os.kill(os.getpid(), signal.SIGTERM)
u._save_config = save
sys.argv[0] = sys.argv.pop(1)
runpy.run_module("hairexp", run_name="__main__", alter_sys=True)
"""


def test_a_signal_after_hydra_wrote_its_record_leaves_an_interrupted_summary(tmp_path):
    """The run folder held only .hydra/ and the log (no summary.json) when a signal came between
    Hydra's record and the job."""
    import subprocess
    import sys

    from probe_helpers import REPO

    out = tmp_path / "r"
    p = subprocess.run([sys.executable, "-c", SIGNAL_AFTER_RECORD, str(REPO / "hairexp" / "__main__.py"), *SMOKE,
                        f"hydra.run.dir={out}"], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 143, p.stderr
    assert p.stderr.strip().splitlines()[-1] == (f"hairexp: interrupted by SIGTERM (while starting: no step of the "
                                                 f"hair ran; summary.json in {out} says so)"), p.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and "before the run claimed its folder" in s["refused"]
    assert (out / ".hydra" / "overrides.yaml").is_file() and not (out / "result.npz").exists()


def test_a_report_that_cannot_be_encoded_leaves_the_old_one_whole(tmp_path, monkeypatch):
    import hairexp.app.report as report

    monkeypatch.setattr(report, "REPORTS", tmp_path)
    report.write_report("x", "# old\n", {"a": 1})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(TypeError):
        report.write_report("x", "# new\n", {"a": {1, 2}})   # a set: not JSON
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_paper_scenes_refuses_a_launch_key_in_set(capsys):
    from experiments.paper_scenes import main

    with pytest.raises(SystemExit) as e:
        main(["goaling_smoke", "--set", "hydra.run.dir=/tmp/elsewhere"])
    assert e.value.code == 2 and "hydra.* and overwrite are a command line's keys" in capsys.readouterr().err


def test_a_deleted_working_folder_is_one_line_exit_2(tmp_path):
    """torch failed to load with "Intel oneMKL FATAL ERROR" in a working folder deleted meanwhile."""
    import subprocess
    import sys

    from probe_helpers import REPO

    gone = tmp_path / "gone"
    gone.mkdir()
    p = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE], cwd=gone, capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)), preexec_fn=lambda: os.rmdir(gone))
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == ["hairexp: error: the working folder no longer exists (deleted while the "
                                             "shell was in it); cd to a folder that exists and launch again"]


def test_a_failed_flush_leaves_every_stream_array_at_the_same_frames(tmp_path, monkeypatch):
    """A full disk in the middle of a flush: positions.npy held 626 frames beside 601 of
    guide_positions.npy, and the summary said neither; now every array is cut to the frames all hold,
    and the summary says how many were kept and lost."""
    import errno

    import hairexp.outputs.files as files
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    real = files.GrowingNpy.flush
    calls = {"n": 0}

    def flush(self):
        if self.path.stem == "guide_positions" and self.pending:
            calls["n"] += 1
            if calls["n"] >= 2:   # from its second flush on this array fails (the disk is full), after others succeeded
                raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        return real(self)

    monkeypatch.setattr(files.GrowingNpy, "flush", flush)
    monkeypatch.setattr("hairexp.app.run.FLUSH_FRAMES", 10)
    out = tmp_path / "r"
    with pytest.raises(OSError) as e:
        run(compose_config([*SMALL, "frames=60", "logging=off"]), out)
    s = json.loads((out / "summary.json").read_text())
    lengths = {p.stem: np.load(p, mmap_mode="r").shape[0] for p in (out / "stream").glob("*.npy")
               if p.stem in ("positions", "guide_positions", "times", "body_positions", "targets", "com")}
    assert len(set(lengths.values())) == 1, lengths
    assert s["status"] == "failed" and s["frames_kept"] == lengths["positions"] and s["frames_lost"] > 0
    assert s["frames_kept"] + s["frames_lost"] == s["steps"] + 1
    assert any("could not be written" in n for n in e.value.__notes__)


def test_overwrite_interrupted_before_the_run_began_leaves_the_previous_run_whole(tmp_path):
    """overwrite=true into a finished run, a signal between Hydra's record and the job: the folder
    held the old run's completed summary and results beside the new launch's .hydra/ config, and
    the console said "partial results" (independent probe of issue 12, round 23)."""
    import subprocess
    import sys

    from probe_helpers import REPO, run_cli

    out = tmp_path / "r"
    assert run_cli([*SMOKE, f"hydra.run.dir={out}"], tmp_path).returncode == 0
    before = {p.name: p.read_bytes() for p in (out / ".hydra").iterdir()}
    old = (out / "summary.json").read_bytes()
    log = (out / "__main__.log").read_bytes()
    p = subprocess.run([sys.executable, "-c", SIGNAL_AFTER_RECORD, str(REPO / "hairexp" / "__main__.py"), *SMOKE,
                        "frames=3", "overwrite=true", f"hydra.run.dir={out}"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    # its log too: the launch's "[ERROR] interrupted" line stood under its "completed" one (round 27)
    assert (out / "__main__.log").read_bytes() == log
    assert p.returncode == 143, p.stderr
    assert "partial results" not in p.stderr
    # the line says the folder is the previous run's (it was a bare "interrupted by SIGTERM"; round 26)
    assert p.stderr.strip().splitlines()[-1] == (f"hairexp: interrupted by SIGTERM (while starting: no step of the "
                                                 f"hair ran; {out} still holds the previous run, as it was)"), p.stderr
    assert {q.name: q.read_bytes() for q in (out / ".hydra").iterdir()} == before
    assert (out / "summary.json").read_bytes() == old


# ---------------------------------------------------------------------------------------------
# independent probe round 23
# ---------------------------------------------------------------------------------------------

def _cli_to(tmp_path, args, **streams):
    import subprocess
    import sys

    from probe_helpers import REPO

    return subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=tmp_path, text=True, timeout=180,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), **streams)


def test_a_bad_value_with_a_full_stderr_still_ends_exit_2_with_its_summary(tmp_path):
    """The error line to a full stderr raised: exit 1 (then 4), and no summary.json."""
    import subprocess

    with open("/dev/full", "w") as full:
        p = _cli_to(tmp_path, [*SMOKE, "frames=-1", f"hydra.run.dir={tmp_path / 'r'}"], stderr=full,
                    stdout=subprocess.DEVNULL)
    assert p.returncode == 2
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert s["status"] == "failed" and "frames" in s["error"]


def test_a_sweep_with_a_full_stdout_runs_its_jobs_and_says_so_exit_4(tmp_path):
    """The sweep's job lines to a full stdout raised OSError in the main process: a traceback, exit 1."""
    import subprocess

    with open("/dev/full", "w") as full:
        p = _cli_to(tmp_path, ["-m", *SMOKE, "frames=1,2", f"hydra.sweep.dir={tmp_path / 's'}"], stdout=full,
                    stderr=subprocess.PIPE)
    assert p.returncode == 4, p.stderr
    assert "Traceback" not in p.stderr
    assert p.stderr.strip().splitlines()[-1] == ("hairexp: error: cannot write the standard output: [Errno 28] No "
                                                 "space left on device")
    for job in ("0", "1"):
        assert json.loads((tmp_path / "s" / job / "summary.json").read_text())["status"] == "completed"


def test_a_launcher_timeout_is_one_line_and_the_jobs_are_said(tmp_path):
    """hydra.launcher.timeout shorter than the jobs: joblib's TimeoutError traceback, exit 1, no job lines."""
    import subprocess

    p = _cli_to(tmp_path, ["-m", *SMOKE, "frames=1,2", f"hydra.sweep.dir={tmp_path / 's'}",
                           "hydra.launcher.timeout=0.5"], capture_output=True)
    assert p.returncode == 3, p.stderr   # the sweep could not finish (1 is a bug's traceback)
    assert "Traceback" not in p.stderr
    assert "hairexp: the sweep was stopped: a job ran longer than hydra.launcher.timeout=0.5 s" in p.stderr
    assert any(line.startswith("hairexp: sweep: ") for line in p.stderr.splitlines()), p.stderr


def test_a_body_scale_round_off_between_samples_is_not_a_collider_error(tmp_path):
    """The body's transform scaled by 1.0000001 at one time code (an exporter's round-off): refused as
    'a collider keeps its size' (the body is no collider); within the rigid tolerance it is read."""
    from pxr import Gf, Usd, UsdGeom

    from hairexp.io.usd_layout import read_motion

    stage = Usd.Stage.CreateInMemory()
    x = UsdGeom.Xform.Define(stage, "/Body")
    op = x.AddTransformOp()
    op.Set(Gf.Matrix4d(1.0), 0)
    op.Set(Gf.Matrix4d(1.0).SetScale(Gf.Vec3d(1.0000001, 1.0000001, 1.0000001)), 3)
    motion, scale = read_motion(x.GetPrim(), 24.0, "s.usda:/Body")
    assert len(motion.times) == 2 and abs(scale[0] - 1) < 1e-6


def test_an_address_space_limit_below_a_runs_reservations_is_one_line_exit_2(tmp_path):
    """ulimit -v 3 GB: USD crashed with SIGSEGV writing the result (exit 139, summary left running);
    800 MB: a traceback at import."""
    import resource
    import subprocess
    import sys

    from probe_helpers import REPO

    for limit in (800 << 20, 3 << 30):
        p = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE, f"hydra.run.dir={tmp_path / 'r'}"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)),
                           preexec_fn=lambda limit=limit: resource.setrlimit(resource.RLIMIT_AS,
                                                                             (limit, resource.RLIM_INFINITY)))
        assert p.returncode == 2, p.stderr
        line, = p.stderr.strip().splitlines()
        assert line.startswith("hairexp: error: the process's address-space limit (ulimit -v) is ") and \
            "raise it to at least 6 GiB" in line
        assert not (tmp_path / "r").exists()


def test_a_partial_recording_cut_short_is_said(tmp_path, monkeypatch):
    """A full disk at the end of a run: recording.partial.rrd was kept cut mid-message (no footer),
    said nowhere, while the README calls it a valid recording of the steps done."""
    import errno

    import hairexp.app.run as run_mod
    import hairexp.outputs.rerun_sink as sink
    from hairexp.app.config import compose_config

    real_finish = sink.finish_stream

    def finish(rec, path):   # the writer stops short, as on a full disk
        real_finish(rec, path)
        with open(path, "r+b") as f:
            f.truncate(os.path.getsize(path) - 100)

    def no_room(path, folder, names=None):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(sink, "finish_stream", finish)
    monkeypatch.setattr(run_mod, "write_npz", no_room)
    out = tmp_path / "r"
    with pytest.raises(OSError) as e:
        run_mod.run(compose_config([*SMALL[:-1], "logging.rerun=true", "logging.progress=false"]), out)
    assert any("recording.partial.rrd: cut short where its writer failed" in n for n in e.value.__notes__), \
        e.value.__notes__
    assert (out / "recording.partial.rrd").is_file()


# ---------------------------------------------------------------------------------------------
# independent probe round 24
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("cmd", [["-m", "hairexp", "--help"], ["-m", "hairexp", "--hydra-help"],
                                 ["-m", "hairexp.io.export_scene", "--help"],
                                 ["-m", "experiments.traced_run", "--help"], ["-m", "experiments.bench_free", "--help"]])
def test_help_to_a_full_stdout_is_one_line_exit_4(tmp_path, cmd):
    """--help to /dev/full: exit 0 with nothing said (hairexp's), or a traceback (the export's, traced_run's)."""
    import subprocess
    import sys

    from probe_helpers import REPO

    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, *cmd], cwd=REPO, stdout=full, stderr=subprocess.PIPE, text=True,
                           timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 4, p.stderr
    assert p.stderr.strip().splitlines()[-1].endswith("error: cannot write the standard output: [Errno 28] No space "
                                                      "left on device") and "Traceback" not in p.stderr


@pytest.mark.parametrize("args, said", [
    (["--shell-completion", "query=bash"], "--shell-completion: 'COMP_LINE' is not set"),
    (["--experimental-rerun", "{yaml}"], "--experimental-rerun: "),
])
def test_hydras_flags_failing_in_its_own_code_are_one_line_exit_2(tmp_path, args, said):
    (tmp_path / "c.yaml").write_text("a: 1\n")   # not a pickle
    args = [a.replace("{yaml}", str(tmp_path / "c.yaml")) for a in args]
    env_free = {k: v for k, v in os.environ.items() if not k.startswith("COMP_")}
    import subprocess
    import sys

    from probe_helpers import REPO

    p = subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120, env=dict(env_free, PYTHONPATH=str(REPO)))
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.strip().splitlines()[-1].startswith(f"hairexp: error: {said}")


def test_hydras_record_in_a_variants_folder_is_refused_before_hydra_starts(tmp_path):
    from probe_helpers import run_cli

    out = tmp_path / "r"
    p = run_cli(["experiment=goaling_smoke", "frames=2", "logging=off", "hydra.output_subdir=free",
                 f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1] == ("hairexp: error: hydra.output_subdir=free: Hydra's record would go "
                                                 "into the folder of the variant free; give another name (the "
                                                 "variants are free, tracked)")
    assert not out.exists()


def test_an_interrupted_overwrite_says_the_previous_run_is_kept(tmp_path):
    from hairexp.app import cli

    (tmp_path / "summary.json").write_text(json.dumps({"status": "completed", "pid": os.getpid() + 1, "host": "x"}))
    assert cli.kept(tmp_path, "partial results") == (f"no step of the hair ran; {tmp_path} still holds the "
                                                      "previous run, as it was")


def test_an_experiments_variants_are_checked_together_against_the_disk(tmp_path, monkeypatch):
    """Two variants that each fitted the free disk alone: the second was refused after the first had
    run (and the recording was not in the estimate)."""
    import hairexp.app.guard as guard
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import _checked_variants
    from hairexp.errors import InputError

    cfg = compose_config(["experiment=goaling_smoke", "frames=30", "logging.rerun=true"])
    monkeypatch.setattr(guard, "run_folder", lambda: str(tmp_path))
    one = {}
    real_check = guard.check
    monkeypatch.setattr(guard, "check", lambda est, *a, **k: one.setdefault("disk", est.disk))
    _checked_variants(cfg)
    single = one["disk"]
    assert single > guard.RECORDING_BYTES   # the recording is in the estimate
    monkeypatch.setattr(guard, "check", real_check)
    monkeypatch.setattr(guard, "available_disk", lambda folder: 1.5 * single)
    with pytest.raises(InputError, match="of it for the experiment's variants checked before this one"):
        _checked_variants(cfg)
    monkeypatch.setattr(guard, "available_disk", lambda folder: 2.5 * single)
    _checked_variants(cfg)   # both fit


def test_an_open_file_limit_too_small_for_a_run_is_one_line_exit_2(tmp_path):
    import resource
    import subprocess
    import sys

    from probe_helpers import REPO

    p = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE, f"hydra.run.dir={tmp_path / 'r'}"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)),
                       preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (20, 20)))
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [
        "hairexp: error: the process's open-file limit (ulimit -n) is 20; a run holds up to about 40 files open (its "
        "libraries', its stream's and its logs'): raise it to at least 64 (ulimit -n 64)"]
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("arg, said", [
    ("hydra.launcher.pre_dispatch=0", "joblib's pre-dispatch is a positive count"),
    ("hydra.launcher.backend=nope", "Hydra's joblib launcher runs the jobs in loky worker processes"),
    ("hydra.launcher.backend=threading", "Hydra's joblib launcher runs the jobs in loky worker processes"),
    ("hydra.launcher.require=sharedmem", "Hydra's joblib launcher runs the jobs in loky worker processes"),
    ("hydra.launcher.mmap_mode=bogus", "joblib's mmap_mode is one of r, r+, w+, c or null"),
])
def test_joblib_settings_it_cannot_use_are_refused(tmp_path, arg, said):
    from probe_helpers import run_cli

    p = run_cli(["-m", *SMOKE, arg, f"hydra.sweep.dir={tmp_path / 's'}"], tmp_path)
    assert p.returncode == 2 and p.stderr.strip().splitlines()[-1].startswith(f"hairexp: error: {arg}: {said}"), \
        p.stderr
    assert not (tmp_path / "s").exists()


def test_a_config_dir_file_shadowed_by_hairexps_own_is_said(tmp_path):
    from probe_helpers import run_cli

    (tmp_path / "mine" / "experiment").mkdir(parents=True)
    (tmp_path / "mine" / "experiment" / "goaling_smoke.yaml").write_text("frames: 7\n")
    p = run_cli(["--config-dir", str(tmp_path / "mine"), *SMOKE, f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 0, p.stderr
    assert (f"hairexp: warning: --config-dir={tmp_path / 'mine'}: experiment/goaling_smoke.yaml not used: hairexp's "
            "own config folder has files of these names") in p.stderr


EARLY = """
import os, signal, sys
sys.argv = ["-m"]   # as while python -m locates the module: the package is being imported
import hairexp
assert signal.getsignal(signal.SIGINT) is hairexp._early_signal
if len(sys.argv) and os.environ.get("THEN_APP"):
    import hairexp.app.startup as startup
    sys.argv = [os.path.join(os.path.dirname(hairexp.__file__), "__main__.py")]
    assert startup.install() and signal.getsignal(signal.SIGINT) is startup._handler
os.kill(os.getpid(), signal.SIGINT)
"""


@pytest.mark.parametrize("then_app", [False, True])
def test_a_signal_while_the_libraries_load_is_one_line(tmp_path, then_app):
    """Ctrl-C 30 ms after the launch (during ``import hydra``, before the app layer's start-up handlers):
    a KeyboardInterrupt traceback; the package's own handler is in place from its import on, and the
    start-up handlers replace it."""
    import subprocess
    import sys

    from probe_helpers import REPO

    env = dict(os.environ, PYTHONPATH=str(REPO), **({"THEN_APP": "1"} if then_app else {}))
    p = subprocess.run([sys.executable, "-c", EARLY], capture_output=True, text=True, timeout=120, env=env,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert p.returncode == 130, p.stderr
    assert p.stderr.strip().splitlines() == ["hairexp: interrupted by SIGINT while starting; nothing was run or written"]


def test_a_key_into_a_list_without_an_index_is_named(tmp_path):
    from probe_helpers import run_cli

    p = run_cli([*SMOKE, "guides.edits.kind=twist", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1] == (
        "hairexp: error: guides.edits.kind: guides.edits is a list: give an item's index (guides.edits.0.kind=...) or "
        "the whole list (guides.edits=[...])")


def test_a_sweep_whose_recordings_hit_the_file_size_limit_ends(tmp_path):
    """ulimit -f 200 kB, recording on: the jobs failed (exit 4) and the sweep said so, then hung for
    ever: a worker's abandoned recording stream waited for its stuck writer at the worker's exit."""
    import resource
    import subprocess
    import sys

    from probe_helpers import REPO

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200 << 10, resource.RLIM_INFINITY))

    p = subprocess.run([sys.executable, "-m", "hairexp", "-m", "experiment=goaling_smoke", "variants=[]", "frames=20",
                        "logging.progress=false", "solver.rtol=1e-4,1e-5", f"hydra.sweep.dir={tmp_path / 's'}"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=90, preexec_fn=limit,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 4, p.stderr
    assert "hairexp: sweep: 0 of 2 jobs completed" in p.stderr


def test_a_usd_builder_without_a_stage_is_one_line_without_warnings_about_it(tmp_path):
    from probe_helpers import run_cli

    p = run_cli([*SMOKE, "scene.builder=usd", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == ["hairexp: error: scene.usd: the path of a USD stage is required "
                                             "(scene.builder=usd or guides.source=usd)"]


def test_a_stream_array_is_cut_after_its_file_object_keeps_failing(tmp_path):
    """After a write the disk refused, the file object's buffer held it and every later seek or write
    raised again: the cut failed, and the summary had no frames_kept (independent probe, round 25)."""
    import errno

    from hairexp.outputs.files import GrowingNpy

    g = GrowingNpy(tmp_path / "a.npy", (2,), np.float64)
    for i in range(3):
        g.append([i, i])
        g.flush()

    class Full:   # a buffered writer whose buffer the disk refuses
        def __init__(self, f):
            self.f = f

        def _full(self, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        seek = write = flush = truncate = _full

        def close(self):
            self.f.close()
            self._full()

    g.f = Full(g.f)
    g.append([9, 9])
    with pytest.raises(OSError):
        g.flush()
    g.cut(3)
    g.close()
    a = np.load(tmp_path / "a.npy")
    assert a.shape == (3, 2) and a[:, 0].tolist() == [0.0, 1.0, 2.0]


@pytest.mark.parametrize("body, said", [
    (b"frames: 5\n", "it begins with the line '# @package _global_'"),
    (b"# @package _global_\ndefaults:\n  - /experiment/mine\nframes: 5\n", "include one another in a loop"),
    (b"\xff\xfe\x00bin", "mine.yaml: not UTF-8 text"),
])
def test_a_users_broken_experiment_file_is_said_with_its_cause(tmp_path, body, said):
    from probe_helpers import run_cli

    (tmp_path / "cd" / "experiment").mkdir(parents=True)
    (tmp_path / "cd" / "experiment" / "mine.yaml").write_bytes(body)
    p = run_cli(["--config-dir", str(tmp_path / "cd"), "experiment=mine", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 2, p.stderr
    line, = p.stderr.strip().splitlines()
    assert line.startswith("hairexp: error: ") and said in line
