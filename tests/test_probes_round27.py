"""Findings of the independent probe round 27 of issue 12 (on ``d8270ec``), fixed: a single run
with ``overwrite=true`` into a finished sweep's folder.  (The previous run's log kept whole by an
overwrite that never claimed the folder is in tests/test_probes_round22.py.)"""

from __future__ import annotations

import json


def test_overwrite_into_a_sweeps_folder_says_it_is_a_sweeps(tmp_path):
    """It was refused naming the sweep's files as foreign ones (0/.hydra, 1/__main__.log,
    multirun.yaml)."""
    from hairexp.outputs.folder import overwrite_refusal

    (tmp_path / "multirun.yaml").write_text("hydra: {}\n")
    for job in ("0", "1"):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / "summary.json").write_text(json.dumps({"status": "completed"}))
    assert overwrite_refusal(tmp_path) == ("it is a -m sweep's folder (multirun.yaml and its job folders): "
                                           "overwrite=true replaces a run's folder, not a sweep's; choose another "
                                           "folder, or remove the sweep's")


def test_steps_below_the_shortest_are_refused_with_the_config():
    """scene.settle_dt=1e-10, or fps=100000 with solver.dt=1e-10: a ValueError traceback from the
    simulator's step after the checks had passed (exit 1)."""
    from types import SimpleNamespace

    import pytest

    from hairexp.errors import InputError
    from hairexp.physics.schedule import step_schedule
    from hairexp.physics.settle import settle_step

    with pytest.raises(InputError, match=r"must be at least 1e-09 and at most 1 \(seconds\), got 1e-10") as err:
        settle_step(SimpleNamespace(settle_dt=1e-10))
    assert err.value.where == "scene.settle_dt"
    assert settle_step(SimpleNamespace(settle_dt=1e-9)) == 1e-9
    with pytest.raises(InputError, match=r"splits a frame of 1e-05 s \(fps 100000\) into steps of 1e-10 s") as err:
        step_schedule(1e5, 1e-10, 1)
    assert err.value.where == "solver.dt"
    assert step_schedule(1e5, 2e-9, 1) == (5000, pytest.approx(2e-9))


def test_solver_dt_below_the_shortest_step_is_a_named_error(tmp_path):
    from probe_helpers import SMALL, run_cli

    p = run_cli([*SMALL, "solver.dt=1e-10", f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 2 and p.stderr.strip().splitlines()[-1] == (
        "hairexp: error: solver.dt: must be at least 1e-09 s (the inertia M/dt^2 overflows below it), got 1e-10"), \
        p.stderr


def test_a_summary_never_holds_a_bare_nan():
    """A one-strand spreading run wrote "tip_variance_ratio": NaN, which strict JSON readers refuse."""
    import math

    import numpy as np

    from hairexp.outputs.files import json_bytes

    def strict(text):
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))

    d = strict(json_bytes({"a": math.nan, "b": [np.inf, 1.5, -math.inf], "c": np.float32("nan"),
                           "d": np.array([1.0, np.nan]), "e": {"f": (np.float64(2.0), math.nan)}, "g": 3}))
    assert d == {"a": None, "b": [None, 1.5, None], "c": None, "d": [1.0, None], "e": {"f": [2.0, None]}, "g": 3}


def test_shell_completion_without_a_value_or_for_fish_is_one_line():
    """``-sc`` alone: an IndexError traceback (exit 1); ``--shell-completion=``: argparse's usage;
    ``install=fish``: Hydra's fish script, which never completes ``python -m hairexp``."""
    from hairexp.app import cli

    assert cli.shell_completion(["-sc"]) == (None, "hairexp: error: -sc: give one of install=bash, install=zsh, "
                                                   "uninstall=bash, uninstall=zsh (or query=bash, which the shell asks)")
    assert cli.shell_completion(["--shell-completion="])[1].startswith("hairexp: error: --shell-completion: give one")
    assert cli.shell_completion(["-sc", "install=fish"])[1].startswith(
        "hairexp: error: -sc install=fish: python -m hairexp completes in bash and zsh")
    assert cli.shell_completion(["experiment=goaling"]) == (None, None)


BASH_SESSION = r"""
_mine() { COMPREPLY=(mine); }
complete -F _mine python
eval "$(PYTHONPATH={repo} {python} -m hairexp -sc install=bash)"
t() { COMP_LINE="$1"; COMP_POINT=${#COMP_LINE}; COMPREPLY=(); _hairexp_completion; echo "${COMPREPLY[*]}"; }
PATH={bindir}:$PATH
t "python -m hairexp experiment=goaling_sm"
t "python other.py x"
eval "$(PYTHONPATH={repo} {python} -m hairexp -sc uninstall=bash)"
complete -p python
"""


def test_bash_completion_completes_hairexp_and_hands_back_the_rest(tmp_path):
    """In bash: a hairexp line completes with the shell's word breaks as they are (the ``=``
    among them), another python line gets the completion python had, which uninstall puts back
    (the install changed COMP_WORDBREAKS for every command and uninstall left python without one)."""
    import os
    import shutil
    import subprocess
    import sys

    import pytest

    from probe_helpers import REPO

    if shutil.which("bash") is None:
        pytest.skip("no bash")
    py = tmp_path / "bin"
    py.mkdir()
    (py / "python").write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')   # the line's "python" is this one
    (py / "python").chmod(0o755)
    script = BASH_SESSION.replace("{repo}", str(REPO)).replace("{python}", sys.executable).replace("{bindir}", str(py))
    p = subprocess.run(["bash", "--norc", "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.stdout.splitlines() == ["goaling_smoke", "mine", "complete -F _mine python"], (p.stdout, p.stderr)


def test_standard_descriptors_closed_at_launch_are_inherited_by_child_processes(tmp_path):
    """``-m ... >&- 2>&-``: the first files opened took descriptors 1 and 2, close-on-exec, so the
    sweep's workers started without standard streams and died (the sweep ran nothing, exit 1).
    The package fills them with /dev/null, inheritable; a child process then writes through them."""
    import os
    import subprocess
    import sys

    from probe_helpers import REPO

    report = tmp_path / "report.txt"
    code = (f"import os, subprocess, sys; sys.argv[:1] = ['-m']; import hairexp; "
            f"ok = [os.get_inheritable(fd) for fd in (1, 2)]; "
            f"rc = subprocess.run([sys.executable, '-c', 'import os; os.write(1, b\"x\"); os.write(2, b\"y\")']).returncode; "
            f"open({str(report)!r}, 'w').write(f'{{ok}} {{rc}}')")

    def close_std():
        os.close(1)
        os.close(2)

    p = subprocess.run([sys.executable, "-c", code], preexec_fn=close_std, timeout=60,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 0 and report.read_text() == "[True, True] 0"


def test_an_experiment_name_that_is_no_folder_name_is_refused_before_a_folder_is_made(tmp_path):
    """A user's experiment file with ``experiment: ../../evil`` wrote its run (and a sweep's) two
    folders above outputs/, exit 0."""
    from probe_helpers import run_cli

    conf = tmp_path / "cd" / "experiment"
    conf.mkdir(parents=True)
    (conf / "evil.yaml").write_text("# @package _global_\ndefaults:\n  - goaling_smoke\n  - _self_\n"
                                    "experiment: ../../evil\nvariants: []\nframes: 2\nlogging:\n  rerun: false\n")
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    for sweep in ([], ["-m", "solver.rtol=1e-5,1e-6"]):
        p = run_cli([*sweep, "--config-dir", str(tmp_path / "cd"), "experiment=evil"], cwd)
        assert p.returncode == 2, p.stderr
        assert p.stderr.strip().splitlines()[-1] == (
            "hairexp: error: ValueError raised while resolving interpolation: experiment: '../../evil' names the "
            "default run folder (outputs/<experiment>/...): use letters, digits, _ . - (at most 200 bytes), not "
            f"starting with . - or _ (key hydra.{'sweep' if sweep else 'run'}.dir)"), p.stderr
        assert not any(tmp_path.rglob("summary.json")) and not any(tmp_path.rglob("multirun.yaml"))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "cd"] and not any(cwd.iterdir())


def test_an_interruption_between_variants_names_no_folder_that_is_not_there(tmp_path):
    """A SIGINT as the free variant completed: "no step of the hair of variant tracked ran: its
    summary.json in R/tracked says so", and R/tracked did not exist."""
    from hairexp.app import cli
    from hairexp.outputs.folder import owner

    (tmp_path / "free").mkdir()
    (tmp_path / "free" / "metrics.parquet").write_bytes(b"PAR1")
    (tmp_path / "summary.json").write_text(json.dumps({"status": "interrupted", **owner()}))
    exc = KeyboardInterrupt()
    exc.run_folder = str(tmp_path / "tracked")
    assert cli.kept(tmp_path, "partial results", exc) == (
        f"no step of the hair of variant tracked ran: it had not begun (the experiment's summary.json in {tmp_path} "
        f"says so); the variants before it (free) are in {tmp_path}")


def test_a_fan_measure_without_gaps_is_null_not_a_crash(tmp_path, caplog):
    """One strand (or measure.axis along the hair): "ValueError: All-NaN slice encountered" after the
    whole run, exit 1."""
    import logging

    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    cfg = compose_config(["experiment=fanning_smoke", "variants=[]", "frames=3", "logging=off", "scene.n_strands=1"])
    with caplog.at_level(logging.WARNING):
        s = run(cfg, tmp_path / "r")
    assert s["status"] == "completed"
    fan = s["measures"]
    assert fan["gap_ratio_max"] is None and fan["gap_ratio_max_time"] is None, fan
    assert any("measure fan: no frame has gaps to measure" in r.getMessage() for r in caplog.records)
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["measures"]["gap_ratio_max"] is None


def test_overwrite_is_refused_when_the_stage_reads_a_file_of_the_run_it_would_remove(tmp_path):
    """A stage outside the run folder that sublayers the previous run's result.usdc: overwrite=true
    removed that run, then the stage did not open (both runs lost)."""
    from hairexp.app.config import compose_config
    from hairexp.app.run import inputs_inside

    run = tmp_path / "run"
    run.mkdir()
    (run / "result.usda").write_text("#usda 1.0\n")
    wrap = tmp_path / "wrap.usda"
    wrap.write_text(f'#usda 1.0\n(\n    subLayers = [@{run / "result.usda"}@]\n)\n')
    cfg = compose_config(["experiment=from_usd", f"scene.usd={wrap}"])
    assert inputs_inside(cfg, run) == (
        f"scene.usd={wrap} reads {run / 'result.usda'} (a sublayer, reference or asset of the stage), which lies "
        "inside the run folder that overwrite=true would empty first; copy it elsewhere, or write the new run "
        "into another folder")
    assert inputs_inside(cfg, tmp_path / "other") is None


def test_a_scripts_bad_input_met_inside_a_run_is_one_line_exit_2(monkeypatch, capsys):
    """``experiments.accuracy --scenes from_usd``: an InputError traceback (exit 1), the scene
    needing a stage it was not given."""
    import sys

    import pytest

    from experiments.common import run_script
    from hairexp.errors import InputError

    def main():
        raise InputError("the path of a USD stage is required", "scene.usd")

    monkeypatch.setattr(sys, "argv", ["/x/experiments/accuracy.py"])
    with pytest.raises(SystemExit) as e:
        run_script(main)
    assert e.value.code == 2
    assert capsys.readouterr().err == "accuracy: error: scene.usd: the path of a USD stage is required\n"


def test_settings_no_run_reads_are_said():
    """guides.scale_* with rigid guides, solver.last_attempt_iterations with on_failure=warn and
    logging.strict without a recording were taken without a word."""
    from hairexp.app.config import compose_config
    from hairexp.app.validate import unused_settings

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "solver.on_failure=warn", "logging.rerun=false",
                          "guides.source=file", "guides.file=x.npz"])
    keys = ["guides.scale_factors", "guides.layout_radius", "guides.keyframes", "solver.last_attempt_iterations",
            "logging.strict"]
    assert unused_settings([cfg], keys) == [
        "guides.scale_factors (read with guides.source=scaled)",
        "guides.layout_radius (read with a guide source that lays the guides out (not file or usd))",
        "guides.keyframes (read with guides.source=keyframed)",
        "solver.last_attempt_iterations (read with solver.on_failure=substep)",
        "logging.strict (read with logging.rerun=true)"]
    used = compose_config(["experiment=goaling_smoke", "variants=[]", "guides.source=scaled", "logging.rerun=true"])
    assert unused_settings([used], ["guides.scale_factors", "guides.layout_radius", "logging.strict",
                                    "solver.last_attempt_iterations"]) == []


def test_a_recording_cut_short_by_a_full_disk_names_it_wherever_it_is_checked(tmp_path, monkeypatch):
    """An experiment's comparison.rrd on a full disk said only "the recording is incomplete (no rerun
    stream footer at its end)"; a run's recording named the full disk."""
    import errno

    import pytest

    from hairexp.outputs import rerun_sink

    cut = tmp_path / "comparison.partial.rrd"
    cut.write_bytes(b"RRF2" + b"\0" * 100)
    with pytest.raises(OSError, match="the recording is incomplete") as e:
        rerun_sink._check_complete(str(cut))
    assert e.value.errno is None   # a disk with room: the file's own fault
    monkeypatch.setattr(rerun_sink, "_free_bytes", lambda path: 0)
    with pytest.raises(OSError, match=r"no space left on the device \(0 bytes free; .*no rerun stream footer") as e:
        rerun_sink._check_complete(str(cut))
    assert e.value.errno == errno.ENOSPC
