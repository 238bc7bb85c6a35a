"""Findings of an independent probe set, one test (or a few) each:

1. ``+key=value`` with a key not in the schema is refused (exit 2, naming the key and the
   nearest valid one), in ``compose_config`` and on the command line; documented ``+`` uses
   (``+scene.colliders=[...]``) still work.
2. A ``hydra.run.dir`` / ``hydra.sweep.dir`` that cannot be a folder is one line and exit 4,
   before Hydra creates it (it used to be Hydra's traceback, exit 1).
3. SIGTERM to the main process of a ``-m`` sweep ends every running job as ``interrupted`` in
   its own ``summary.json`` (they used to stay ``running``), exit 143.
4. A variant override ``solver.compile=off`` is the choice ``off`` (YAML 1.1 made it False).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hairexp.app import cli
from hairexp.app.config import compose_config
from hairexp.app.experiment import apply_overrides
from hairexp.errors import InputError

SMALL = ["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false"]


def run_cli(args, cwd, timeout=180, **kw):
    env = dict(os.environ, CI="1")
    return subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout, **kw)


def one_error_line(proc, *needles):
    """stderr is one ``hairexp: error:`` line (no traceback) naming every needle."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("hairexp: error:")]
    assert len(lines) == 1, proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


# 1. unknown keys added with +

@pytest.mark.parametrize("override, key, near", [
    ("+solver.foo=1", "solver.foo", "solver.dt"),         # no near spelling: the node's keys are listed
    ("+foo=1", "foo", "scene"),
    ("+guides.foo=1", "guides.foo", "guides.source"),
    ("+scene.hair.stiff=3.0", "scene.hair.stiff", "scene.hair.stretch_stiffness"),
    ("+tracking.rtoll=1e-3", "tracking.rtoll", "tracking.rtol"),
    ("+foo.bar=1", "foo", "scene"),
    ("+scene.colliders.0.frictoin=1", "scene.colliders[0].frictoin", "scene.colliders[0].friction"),
])
def test_compose_refuses_unknown_plus_keys(override, key, near):
    with pytest.raises(InputError) as ei:
        compose_config(["experiment=goaling_smoke", override])
    msg = str(ei.value)
    assert msg.startswith(f"{key}: unknown key") and near.split(".")[-1] in msg and "\n" not in msg, msg


def test_documented_plus_uses_still_compose():
    from hairexp.app.config import unknown_keys

    cfg = compose_config(["+scene.colliders=[{name: ball, shape: sphere, radius: 0.05, motion: {times: [0.0], "
                          "translations: [[0.0,-0.2,0.05]], rotations_deg: [[0.0,0.0,0.0]]}}]"])
    assert [c.name for c in cfg.scene.colliders] == ["ball"]
    assert unknown_keys(cfg) == []
    for exp in sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "conf" / "experiment").glob("*.yaml")):
        if exp == "from_usd":
            continue
        assert unknown_keys(compose_config([f"experiment={exp}"])) == [], exp


def test_cli_refuses_unknown_plus_key(tmp_path):
    out = tmp_path / "run"
    proc = run_cli([*SMALL, "+solver.foo=1", f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    one_error_line(proc, "solver.foo", "unknown key")
    assert not (out / "summary.json").exists()


def test_cli_refuses_unknown_plus_key_near_spelling(tmp_path):
    proc = run_cli([*SMALL, "+tracking.rtoll=1e-3", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    one_error_line(proc, "tracking.rtoll", "'tracking.rtol'")


# 2. run folders that cannot be written: exit 4 before Hydra

def _bad_dirs(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    return {"a file": str(f), "under a file": str(f / "sub" / "run"), "/proc": "/proc/hairexp-probe-xyz"}


@pytest.mark.parametrize("what", ["a file", "under a file", "/proc"])
def test_cli_unusable_run_dir_exits_4(tmp_path, what):
    path = _bad_dirs(tmp_path)[what]
    proc = run_cli([*SMALL, f"hydra.run.dir={path}"], cwd=tmp_path)
    assert proc.returncode == 4, proc.stderr
    one_error_line(proc, f"hydra.run.dir={path}")


def test_cli_unusable_sweep_dir_exits_4(tmp_path):
    path = _bad_dirs(tmp_path)["a file"]
    proc = run_cli(["-m", *SMALL, "solver.rtol=1e-5,1e-6", f"hydra.sweep.dir={path}"], cwd=tmp_path)
    assert proc.returncode == 4, proc.stderr
    one_error_line(proc, f"hydra.sweep.dir={path}")


def test_run_dir_error_in_process(tmp_path, monkeypatch):
    bad = _bad_dirs(tmp_path)
    assert "is a file" in cli.run_dir_error([f"hydra.run.dir={bad['a file']}"])
    assert "is a file" in cli.run_dir_error([f"hydra.run.dir={bad['under a file']}"])
    assert "is a file" in cli.run_dir_error([f"hydra.run.dir={bad['a file']}/" + "${now:%H-%M}"])
    assert cli.run_dir_error([f"hydra.run.dir={tmp_path / 'new' / 'run'}"]) is None
    assert cli.run_dir_error(["-m", f"hydra.run.dir={bad['a file']}"]) is None   # -m: the sweep dir counts
    assert cli.run_dir_error(["-m", f"hydra.sweep.dir={bad['a file']}"]) is not None
    assert not list((tmp_path).glob(".hairexp-probe-*")) and not (tmp_path / "new").exists()

    def denied(*a, **k):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(cli.tempfile, "mkdtemp", denied)   # an unwritable folder, even as root
    msg = cli.run_dir_error([f"hydra.run.dir={tmp_path / 'run'}"])
    assert msg.startswith("hairexp: error: hydra.run.dir=") and "Permission denied" in msg, msg


def _as_other_user():
    """A command prefix that runs as an unprivileged user, or None (then chmod works as is)."""
    if os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        return None
    prefix = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups"]
    try:
        ok = subprocess.run([*prefix, sys.executable, "-c", "import hydra, hairexp"], capture_output=True,
                            env=dict(os.environ, HOME="/tmp"), timeout=120).returncode == 0
    except (OSError, subprocess.SubprocessError):
        ok = False
    return prefix if ok else None


def test_cli_unwritable_run_dir_exits_4():
    prefix = _as_other_user()
    if prefix is None:
        pytest.skip("running as root and no unprivileged user can run this Python (chmod is not enforced)")
    import tempfile

    base = Path(tempfile.mkdtemp(prefix="hairexp-probe-"))   # reachable by the other user (pytest's are 0700)
    try:
        base.chmod(0o755)
        ro = base / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        env = dict(os.environ, CI="1", HOME=str(base))
        proc = subprocess.run([*prefix, sys.executable, "-m", "hairexp", *SMALL, f"hydra.run.dir={ro / 'run'}"],
                              cwd=base, env=env, capture_output=True, text=True, timeout=180)
        assert proc.returncode == 4, proc.stderr
        line = one_error_line(proc, f"hydra.run.dir={ro / 'run'}", f"cannot create a folder in {ro}")
        assert "ermission denied" in line, line
        assert not (ro / "run").exists()
    finally:
        if (base / "ro").is_dir():
            (base / "ro").chmod(0o755)
        shutil.rmtree(base, ignore_errors=True)


# 3. SIGTERM to a sweep's main process

def test_sweep_sigterm_ends_jobs_interrupted(tmp_path):
    sweep = tmp_path / "sweep"
    env = dict(os.environ, CI="1")
    proc = subprocess.Popen([sys.executable, "-m", "hairexp", "-m", "experiment=goaling_smoke", "variants=[]",
                             "frames=1000", "logging.rerun=false", "solver.rtol=1e-5,1e-6",
                             f"hydra.sweep.dir={sweep}"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        summaries = [sweep / "0" / "summary.json", sweep / "1" / "summary.json"]

        def status(p):
            try:
                return json.loads(p.read_text())["status"]
            except (OSError, ValueError, KeyError):
                return None
        deadline = time.monotonic() + 150
        while not all(status(p) == "running" for p in summaries):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the jobs did not start"
            time.sleep(0.2)
        time.sleep(1.0)   # past the run's start (its signal handler is installed after summary.json)
        assert all(status(p) == "running" for p in summaries), "the run is too short for this test"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, err
    assert [status(p) for p in summaries] == ["interrupted", "interrupted"], err
    for p in summaries:
        assert "SIGTERM" in json.loads(p.read_text())["error"]
        assert json.loads((p.parent / ".hydra" / "outcome.json").read_text())["code"] == 143
    assert "Traceback" not in err, err
    assert err.count("interrupted (exit 143)") == 2, err


# 4. variant overrides parse booleans as Hydra does

def test_parse_value_booleans_only_true_false():
    from hairexp.app.experiment import parse_value

    assert [parse_value(v) for v in ("off", "on", "yes", "no", "y", "n", "Off")] == \
        ["off", "on", "yes", "no", "y", "n", "Off"]
    assert [parse_value(v) for v in ("true", "False", "TRUE")] == [True, False, True]
    assert parse_value("3") == 3 and parse_value("1.5e-3") == 1.5e-3 and parse_value("null") is None
    assert parse_value("[1, 2.5, x]") == [1, 2.5, "x"]
    assert parse_value("{name: a, shape: sphere, on: off}") == {"name": "a", "shape": "sphere", "on": "off"}


def test_variant_override_compile_off(tmp_path):
    cfg = compose_config(["experiment=goaling_smoke"])
    for v in ("off", "on", "auto"):
        assert apply_overrides(cfg, [f"solver.compile={v}"], "variants[0] (x)").solver.compile.value == v
    assert apply_overrides(cfg, ["logging.rerun=false"], "x").logging.rerun is False
    out = tmp_path / "run"
    proc = run_cli(["experiment=goaling_smoke", "frames=2", "logging.rerun=false",
                    "variants=[{name: a, overrides: ['solver.compile=off']}, {name: b, overrides: ['solver.compile=on', "
                    "'solver.compile=auto']}]", "judge=none", f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "a" / "summary.json").read_text())["config"]["solver"]["compile"] == "off"
    assert json.loads((out / "b" / "summary.json").read_text())["config"]["solver"]["compile"] == "auto"


def test_sweep_job_started_after_stop_is_interrupted(tmp_path):
    """A job a worker picks up while the main process stops the sweep does not run."""
    (tmp_path / cli.STOP_MARK).write_text("SIGTERM\n")
    out = tmp_path / "2"
    res = cli.job(None, str(out), sweep=True, sweep_dir=str(tmp_path))   # cfg is never read
    assert (res["status"], res["code"]) == ("interrupted", 143)
    assert json.loads((out / ".hydra" / "outcome.json").read_text())["status"] == "interrupted"
    # the folder says it (it held only Hydra's record and an empty log; independent probe of issue 12, round 26)
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and s["error"] == "interrupted by SIGTERM before the job started"
    assert "stopped before this job started" in s["refused"] and not (out / "result.npz").exists()


# 5. (issue 12 probes) a guide simulation that fails is said to be the guides', and the exit line
#    does not promise partial metrics that were never written

def test_failing_guide_simulation_is_named(tmp_path):
    out = tmp_path / "run"
    proc = run_cli([*SMALL, "solver.max_iterations=1", "solver.rtol=1e-30", "solver.atol=0", "solver.on_failure=fail",
                    f"hydra.run.dir={out}"], cwd=tmp_path)
    assert proc.returncode == 3 and "Traceback" not in proc.stderr, proc.stderr
    line = [ln for ln in proc.stderr.splitlines() if ln.startswith("hairexp: simulation failed:")]
    assert len(line) == 1, proc.stderr
    assert "the guide simulation (guides.source=simulated), frame 1 of 2" in line[0]
    assert "no step of the hair ran; summary.json in" in line[0] and "partial metrics" not in line[0]
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "failed" and "guide simulation" in s["error"] and not (out / "metrics.parquet").exists()


# 6. (issue 12 probes) a bad strand count in a variant is refused before any variant runs, naming
#    the variant (the count was checked only when the variant's hair was built: variant a had
#    started, and -2 x -3 strands passed the resource guard as 6)

@pytest.mark.parametrize("override", ["scene.n_strands=-2", "scene.n_vertices=2"])
def test_bad_counts_in_a_variant_fail_before_any_variant_runs(tmp_path, override):
    from hairexp.app.experiment import run_experiment

    cfg = compose_config(["experiment=goaling_smoke", "frames=2", "logging.rerun=false",
                          f"variants=[{{name: a, overrides: ['{override}']}}]"])
    with pytest.raises(InputError, match=r"\(variants\[0\] a, checked before any variant runs\)") as err:
        run_experiment(cfg, tmp_path / "run")
    assert str(err.value).startswith(override.split("=")[0] + ": must be >=")
    assert not (tmp_path / "run" / "a").exists()


# 7. (issue 12 probes) integers in a list of float lists: OmegaConf's "Value 0 (int) is incompatible
#    with type hint 'float'" gets the fix spelled out

def test_integers_in_nested_float_lists_get_a_hint():
    msg = cli.config_error(["experiment=goaling_smoke", "variants=[]", "scene.motion.translations=[[0,0,0]]"])
    assert msg.startswith("hairexp: error: ") and "\n" not in msg
    assert "incompatible with type hint 'float'" in msg and "as a float (0.0, not 0)" in msg
    assert cli.config_error(["experiment=goaling_smoke", "variants=[]", "scene.motion.translations=[[0.0,0.0,0.0]]"]) \
        is None


# 8. (issue 12 probes) a key not in the schema without "+": Hydra advised "+key=value", which the
#    schema refuses too; the line names the key and the nearest valid one instead

@pytest.mark.parametrize("override, key, near", [("foo=1", "foo", "the keys of the top level are:"),
                                                  ("solver.rtoll=1e-3", "solver.rtoll", "did you mean 'solver.rtol'?"),
                                                  ("scene.hair.stiff=3", "scene.hair.stiff", "scene.hair.")])
def test_unknown_key_without_plus_names_the_nearest(override, key, near):
    msg = cli.config_error(["experiment=goaling_smoke", "variants=[]", override])
    assert msg.startswith(f"hairexp: error: {key}: unknown key, not in the schema") and near in msg
    assert "To append" not in msg and "\n" not in msg
