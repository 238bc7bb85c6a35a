"""Findings of the independent probe round 26 of issue 12 (on ``36d7abd``), fixed: a signal after
an export had written its stage, ``overwrite=true`` over a run with an immutable file, a speed at
the limit to round-off, roots micrometres apart, and ``--hydra-help`` with overrides.  (The signal
after Hydra's record, the sweep job stopped before it began and the guides' sample gap are in
tests/test_probes_round22.py, tests/test_probes.py and tests/test_usd_inputs.py.)"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from hairexp.errors import InputError
from probe_helpers import REPO, SMALL, run_cli

SIGNAL_AFTER_EXPORT = """
import os, runpy, signal, sys
import hairexp.app.startup as st
real = st.ended
def ended(code, told=None):   # the export has ended: a signal now lands on the start-up handler
    real(code, told)
    os.kill(os.getpid(), signal.SIGTERM)
st.ended = ended
sys.argv[0] = sys.argv.pop(1)
runpy.run_module("hairexp.io.export_scene", run_name="__main__", alter_sys=True)
"""


def test_a_signal_after_an_export_wrote_its_stage_says_it_was_written(tmp_path):
    """It said "interrupted by SIGTERM while starting; nothing was run or written" after the stage
    had replaced the old file (--force)."""
    out = tmp_path / "b.usda"
    out.write_text("#usda 1.0\n")
    p = subprocess.run([sys.executable, "-c", SIGNAL_AFTER_EXPORT, str(REPO / "hairexp" / "io" / "export_scene.py"),
                        "--force", str(out), *SMALL], cwd=tmp_path, capture_output=True, text=True, timeout=180,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.returncode == 143, p.stderr
    assert p.stdout.startswith(f"wrote {out}:"), p.stdout
    assert p.stderr.strip().splitlines()[-1] == (f"hairexp: SIGTERM while exiting, after the export had ended (exit "
                                                 f"code 0 before it): {out} was written whole"), p.stderr
    assert "while starting" not in p.stderr and out.read_text() != "#usda 1.0\n"


def _finished_run(tmp_path):
    out = tmp_path / "r"
    assert run_cli([*SMALL, f"hydra.run.dir={out}"], tmp_path).returncode == 0
    return out, {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != "__main__.log"}


def _assert_refused_whole(p, out, before, blocked):
    assert p.returncode == 4, p.stderr
    line = [ln for ln in p.stderr.splitlines() if ln.startswith("hairexp: cannot write the run folder")]
    assert len(line) == 1 and f"overwrite=true cannot remove the previous run: {blocked}" in line[0], p.stderr
    assert "nothing of that run was removed" in line[0]
    after = {q.relative_to(out): q.read_bytes() for q in out.rglob("*") if q.is_file() and q.name != "__main__.log"}
    assert after == before   # the previous run whole: its completed summary, results and Hydra record
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def test_overwrite_that_cannot_remove_a_file_removes_nothing(tmp_path):
    """An immutable result.npz stopped overwrite=true halfway: the previous run's summary and
    metrics were gone, its result.npz and result.usdc stood beside the new launch's failed
    summary.  The removals are checked first (the file's flags, injected here through the
    folder's write access: a run folder that is not writable)."""
    if os.geteuid() == 0:
        pytest.skip("root writes into a folder without write access; the chattr test below covers root")
    out, before = _finished_run(tmp_path)
    (out / "stream").chmod(0o500) if (out / "stream").is_dir() else None
    os.chmod(out, 0o500)
    try:
        p = run_cli([*SMALL, "overwrite=true", f"hydra.run.dir={out}"], tmp_path)
    finally:
        os.chmod(out, 0o755)
    _assert_refused_whole(p, out, before, f"{out} is not writable")


def test_overwrite_over_an_immutable_file_removes_nothing(tmp_path):
    """As above, with the file made immutable (``chattr +i``: root and a file system with the flag)."""
    out, before = _finished_run(tmp_path)
    chattr = shutil.which("chattr")
    if chattr is None or os.geteuid() != 0 or subprocess.run([chattr, "+i", str(out / "result.npz")],
                                                             capture_output=True).returncode != 0:
        pytest.skip("chattr +i needs root and a file system with inode flags")
    try:
        p = run_cli([*SMALL, "overwrite=true", f"hydra.run.dir={out}"], tmp_path)
    finally:
        subprocess.run([chattr, "-i", str(out / "result.npz")], check=True)
    _assert_refused_whole(p, out, before, f"{out / 'result.npz'} is immutable (chattr +i)")


def test_the_removal_check_finds_a_pinned_file_inside_a_folder(tmp_path, monkeypatch):
    """The check walks the folders a previous run wrote (a variant's folder, stream/)."""
    import hairexp.outputs.folder as folder

    (tmp_path / "free" / "stream").mkdir(parents=True)
    (tmp_path / "free" / "stream" / "x.npy").write_bytes(b"")
    (tmp_path / "summary.json").write_text("{}")
    monkeypatch.setattr(folder, "pinned", lambda p: "immutable (chattr +i)" if p.name == "x.npy" else None)
    ours = [tmp_path / "free", tmp_path / "summary.json"]
    assert folder._unremovable(tmp_path, ours) == (tmp_path / "free" / "stream" / "x.npy", "immutable (chattr +i)")
    monkeypatch.setattr(folder, "pinned", lambda p: None)
    assert folder._unremovable(tmp_path, ours) is None


def test_a_speed_at_the_limit_to_round_off_is_taken():
    """100 m in 0.1 s (1000.0000000000002 m/s by floating point) was refused as "moves 1000 m/s
    ..., more than 1000 m/s"; a speed past the limit still is."""
    from hairexp.model.rigid import RigidMotion

    times = [0.0, 0.1, 0.2, 0.3, 0.4]
    key = [[0.0, 0.0, 0.0]] * 4
    RigidMotion(times=times, translations=key + [[100.0, 0.0, 0.0]], rotvecs=[[0.0, 0.0, 0.0]] * 5)
    with pytest.raises(InputError, match=r"moves 1000 m/s .* more than 1000 m/s"):
        RigidMotion(times=times, translations=key + [[100.001, 0.0, 0.0]], rotvecs=[[0.0, 0.0, 0.0]] * 5)


@pytest.mark.parametrize("radius", [1e-300, 1e-7])
def test_roots_closer_than_a_micrometre_without_spread_are_refused(radius):
    """scene.root_radius=0 was refused for two strands without spread (they lie on one line), but
    1e-300 was taken."""
    from hairexp.model.builders import straight_strands

    with pytest.raises(InputError, match=r"the 2 roots would be .* m apart, less than 1e-06 m") as err:
        straight_strands(2, 5, 0.2, radius, np.zeros(3), np.array([0.0, -1.0, 0.0]), 0.0, 0)
    assert err.value.where == "scene.root_radius"
    assert straight_strands(2, 5, 0.2, 1e-5, np.zeros(3), np.array([0.0, -1.0, 0.0]), 0.0, 0).shape == (10, 3)
    assert straight_strands(2, 5, 0.2, radius, np.zeros(3), np.array([0.0, -1.0, 0.0]), 0.3, 0).shape == (10, 3)


def test_hydra_help_drops_the_overrides_it_does_not_read():
    """``--hydra-help experiment=goaling_smoke`` said "Could not override 'experiment'. No match in
    the defaults list": Hydra's help composes Hydra's config alone."""
    from hairexp.app import cli

    argv = ["--hydra-help", "experiment=goaling_smoke", "+frames=3", "hydra.job.name=x", "--config-dir", "conf2"]
    assert cli.hydra_help_argv(argv) == (["--hydra-help", "hydra.job.name=x", "--config-dir", "conf2"],
                                         ["experiment=goaling_smoke", "+frames=3"])
    assert cli.hydra_help_argv(["experiment=goaling_smoke"]) == (["experiment=goaling_smoke"], [])


def test_a_variant_that_failed_before_its_first_step_says_so(tmp_path, capsys):
    """The tracked variant's guide simulation failed before a step of its hair: the line said
    "partial metrics in <experiment folder>" (the free variant's, before it)."""
    from hairexp.app import cli
    from hairexp.app.config import compose_config

    variants = ('variants=[{name: free, overrides: ["controller.name=free"]}, {name: tracked, overrides: '
                '["controller.name=tracking", "solver.max_iterations=1", "solver.on_failure=fail"]}]')
    args = ["experiment=goaling_smoke", "frames=12", "logging=off", variants]
    out = tmp_path / "r"
    res = cli.job(compose_config(args), str(out), overrides=args)
    assert (res["status"], res["code"]) == ("failed", 3)
    err = capsys.readouterr().err
    assert "partial metrics" not in err, err
    assert (f"(no step of the hair of variant tracked ran: its summary.json in {out / 'tracked'} says so; the variants "
            f"before it (free) are in {out})") in err, err
    assert (out / "free" / "metrics.parquet").is_file() and not (out / "tracked" / "metrics.parquet").exists()


def test_metrics_the_stream_cannot_take_are_written_with_the_table(tmp_path, monkeypatch):
    """stream/metrics made immutable mid-run: the failed ending's metrics.parquet was not written
    (its first act, flushing the rows since the last part into the stream, failed), and every
    row of the run was lost though the run folder could take the table."""
    import pandas as pd

    from hairexp.outputs.metrics import MetricsTable

    table = MetricsTable(tmp_path / "stream" / "metrics")
    for k in range(2):
        table.on_step({"step": k, "t": 0.1 * k}, None)
    table.flush()
    for k in range(2, 5):
        table.on_step({"step": k, "t": 0.1 * k}, None)

    def blocked():
        raise PermissionError(1, "Operation not permitted", str(table.folder / "part-00001.parquet.tmp"))

    monkeypatch.setattr(table, "flush", blocked)
    table.write(tmp_path / "metrics.parquet")
    df = pd.read_parquet(tmp_path / "metrics.parquet")
    assert df["step"].tolist() == [0, 1, 2, 3, 4] and np.allclose(df["t"], [0.0, 0.1, 0.2, 0.3, 0.4])


@pytest.mark.parametrize("controller", ["free", "tracking"])
def test_the_disk_estimate_holds_a_recording_of_many_steps(tmp_path, monkeypatch, controller):
    """The recording's per-step plots were not in the estimate: a 4,000-step run on a 3 MB disk was
    let start (estimate 2.1 MB) and filled it after every step had run.  The estimate is checked
    against the files a run of 400 steps writes."""
    import hairexp.app.guard as guard
    from hairexp.app.config import compose_config
    from hairexp.app.run import run

    seen = []
    real_check = guard.check
    monkeypatch.setattr(guard, "check", lambda est, *a, **k: (seen.append(est.disk), real_check(est, *a, **k))[1])
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", f"controller={controller}", "frames=10",
                          "solver.dt=0.001", "logging.rerun=true", "logging.progress=false"])
    out = tmp_path / "r"
    run(cfg, out)
    written = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    assert seen and written <= seen[0], (written, seen)
    assert (out / "recording.rrd").stat().st_size > 0.3 * seen[0]   # the recording is most of it


def test_a_sweep_of_a_users_config_whose_jobs_cannot_be_composed_leaves_no_folder(tmp_path):
    """hydra.sweeper.params in the user's own config with a value of the wrong type: exit 2, and
    the sweep folder was left with .lock and multirun.yaml, which refused the next launch."""
    conf = tmp_path / "cfg"
    conf.mkdir()
    (conf / "sw.yaml").write_text("defaults:\n  - config\n  - _self_\nhydra:\n  sweeper:\n    params:\n"
                                  "      solver.dt: 0.04,abc\n")
    out = tmp_path / "sweep"
    p = run_cli(["-m", "--config-dir", str(conf), "--config-name", "sw", *SMALL, f"hydra.sweep.dir={out}"], tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith("hairexp: error: --config-name=sw: Error merging override "
                                                        "solver.dt=abc"), p.stderr
    assert not out.exists()


@pytest.mark.parametrize("arg, said", [
    ("hydra.sweeper.params={solver.dt:'0.01,-1'}", "hydra.sweeper.params: Hydra takes the sweeper's params from a "
                                                   "config file only"),
    ("+hydra.sweeper.params.solver.dt='0.01,0.02'", "hydra.sweeper.params.solver.dt: Hydra takes the sweeper's "
                                                    "params from a config file only"),
    ("hydra.launcher.timeout=0", "hydra.launcher.timeout=0: the most seconds a job may run is a number > 0"),
])
def test_sweep_keys_hydra_cannot_use_are_refused_up_front(arg, said):
    """Hydra's internals ("'NoneType' object has no attribute 'get'", "Unexpected type: None"), or
    a timeout of 0 that stopped every job before it began (exit 3)."""
    from hairexp.app import cli

    assert cli.hydra_key_error([arg]) == said + (
        " (hydra: sweeper: params: in your own config, --config-dir / --config-name); on the command line sweep a "
        "key as key=a,b,c" if "params" in arg else ", or null for no limit")


def test_a_disk_reserve_the_failed_ending_cannot_remove_is_said(tmp_path, monkeypatch):
    """A run folder made immutable mid-run: the 128 kB .ending.reserve stayed, and no line said so
    (the README says it is gone when the run ends)."""
    from hairexp.app import run as run_mod
    from hairexp.errors import SimulationError
    from hairexp.outputs import folder

    class Sinks:
        progress = recorder = rerun = None
        written = []
        plain = {"experiment": None, "config": None}

        class table:
            steps = 0

    (tmp_path / folder.RESERVE).write_bytes(b"\0" * 16)
    real_unlink = type(tmp_path).unlink

    def unlink(self, *a, **k):
        if self.name == folder.RESERVE:
            raise PermissionError(1, "Operation not permitted", str(self))
        return real_unlink(self, *a, **k)

    monkeypatch.setattr(type(tmp_path), "unlink", unlink)
    monkeypatch.setattr(run_mod, "summarize", lambda *a, **k: {"status": "failed"})
    exc = SimulationError("boom")
    run_mod._end_unfinished(exc, Sinks, tmp_path, "s", "free", 0.0)
    assert exc.__notes__ == ["while writing the failed ending (.ending.reserve): PermissionError: [Errno 1] Operation "
                             "not permitted"]
    assert json.loads((tmp_path / "summary.json").read_text())["status"] == "failed"


def test_shell_completion_completes_python_dash_m_hairexp(tmp_path, monkeypatch):
    """Hydra's completion script fired only for ``python script.py`` and installed commands, and
    its query of ``python -m hairexp experiment=go`` failed with "Error parsing override 'hairexp'"."""
    from hairexp.app import cli

    script, bad = cli.shell_completion(["-sc", "install=bash"])
    assert bad is None and "_hairexp_completion()" in script
    assert script.endswith("complete -o default -F _hairexp_completion python python3")
    assert cli.shell_completion(["--shell-completion=install=zsh"])[0].startswith("autoload -Uz bashcompinit")
    assert "unset -f _hairexp_completion" in cli.shell_completion(["-sc", "uninstall=bash"])[0]
    monkeypatch.setenv("COMP_LINE", "/x/.venv/bin/python3.11 -m hairexp experiment=go")
    assert cli.shell_completion(["-sc", "query=bash"]) == (None, None)
    assert os.environ["COMP_LINE"] == "python hairexp experiment=go"
    env = dict(os.environ, PYTHONPATH=str(REPO), COMP_LINE="python -m hairexp experiment=goaling_sm")
    p = subprocess.run([sys.executable, "-m", "hairexp", "-sc", "query=bash"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.split() == ["experiment=goaling_smoke"], (p.stdout, p.stderr)
