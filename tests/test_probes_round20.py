"""Findings of probe round 19 of issue 12 (2026-12-05, an independent round on ``3c1f8ce``), fixed:
USD's write errors, the signals that ended a run without its ending, Hydra's config flags, edit
keys of the other kind, a contact tolerance of metres, ``--help`` / ``--version``, and a refused
run's log lines."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time

import pytest
from pxr import Usd

from hairexp.app.assemble import check_config
from hairexp.errors import InputError
from probe_helpers import REPO, SMALL, run_cli, updated


def _limited(limit_bytes: int):
    """A child's ``preexec_fn``: the file-size limit ``limit_bytes`` (ulimit -f) and default signals."""
    def pre():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, resource.RLIM_INFINITY))
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_DFL)
    return pre


# ---------------------------------------------------------------------------------------------
# USD's write errors: one OSError naming the file (was: pxr.Tf.ErrorException, pages of lines)
# ---------------------------------------------------------------------------------------------

SAVE_UNDER_LIMIT = """
import errno, sys
import numpy as np
from pxr import Usd, UsdGeom, Vt
from hairexp.io import usd_write
stage = Usd.Stage.CreateInMemory()
c = UsdGeom.BasisCurves.Define(stage, "/C")
for f in range(40):
    c.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.random.rand(3000, 3).astype(np.float32)), f)
try:
    usd_write.save(stage, sys.argv[1])
except OSError as exc:
    print(exc.errno, exc.filename, str(exc), sep="|")
"""


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_a_usd_write_past_the_file_size_limit_is_one_named_oserror(tmp_path, suffix):
    """A real failure (ulimit -f 200 kB in a child process): EFBIG naming the final file, the
    temporary file removed, nothing under the final name."""
    path = tmp_path / f"scene{suffix}"
    p = subprocess.run([sys.executable, "-c", SAVE_UNDER_LIMIT, str(path)], capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=str(REPO)), preexec_fn=_limited(200_000))
    assert p.returncode == 0, p.stderr
    code, filename, text = p.stdout.strip().split("|")
    assert int(code) == 27 and filename == str(path), p.stdout
    assert text == f"[Errno 27] File too large: '{path}'"
    assert len(p.stderr.splitlines()) < 5, p.stderr   # no page of USD's lines
    assert sorted(q.name for q in tmp_path.iterdir()) == []


def test_a_usd_write_into_a_file_that_is_no_folder_says_usds_reason(tmp_path):
    """The temporary file's unlink raised ``[Errno 20] Not a directory`` over USD's error."""
    from hairexp.io.usd_write import save

    (tmp_path / "f").write_text("x")
    with pytest.raises(OSError) as err:
        save(Usd.Stage.CreateInMemory(), tmp_path / "f" / "scene.usda")
    assert err.value.filename == str(tmp_path / "f" / "scene.usda")
    assert "USD could not write it: Could not create directory" in str(err.value)


def test_usd_errors_are_mapped_to_their_errno():
    from pxr import Tf

    from hairexp.io.usd_write import usd_write_error

    class Fake(Tf.ErrorException):
        def __init__(self, text):
            self.text = text

        def __str__(self):
            return self.text

    line = "\tError in 'Ar::Write' at line 78 in file f.cpp : 'Error occurred writing file: {}'\n"
    for words, code in (("No space left on device", 28), ("File too large", 27), ("Permission denied", 13),
                        ("Insufficient permissions to write to destination directory '/x'", 13)):
        e = usd_write_error(Fake(line.format(words) * 3000), "/x/result.usda")
        assert (e.errno, e.filename) == (code, "/x/result.usda")
        assert len(str(e)) < 100
    e = usd_write_error(Fake(line.format("something else")), "/x/r.usdc")
    assert e.errno == 5 and str(e) == ("[Errno 5] USD could not write it: Error occurred writing file: something else: "
                                       "'/x/r.usdc'")


def test_a_run_whose_usda_result_passes_the_file_size_limit_fails_exit_4(tmp_path):
    """Round 19: exit 1 with pxr's traceback and ~3,500 lines, summary.json left "running" (its
    failed ending, carrying the whole of USD's text, hit the limit too)."""
    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "hairexp", "experiment=goaling_smoke", "variants=[]", "frames=300",
                        "logging=off", "output.usd_format=usda", "output.usd_clips=never", f"hydra.run.dir={out}"],
                       cwd=tmp_path, env=dict(os.environ, CI="1", PYTHONPATH=str(REPO)), capture_output=True,
                       text=True, timeout=300, preexec_fn=_limited(800 * 1024))
    # 800 kB: result.npz (stored, not deflated: 669 kB) fits, result.usda (1.1 MB) does not
    assert p.returncode == 4, p.stderr[-2000:]
    assert "Traceback" not in p.stderr and len(p.stderr.splitlines()) < 5, p.stderr[-2000:]
    assert f"[Errno 27] File too large: '{out / 'result.usda'}'" in p.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["error"] == f"[Errno 27] File too large: '{out / 'result.usda'}'"
    assert not (out / "result.usda").exists() and not [q for q in out.rglob("*") if ".tmp" in q.name]


def test_a_summary_holds_at_most_error_chars_of_an_error():
    from hairexp.app.run import ERROR_CHARS, summarize

    s = summarize(None, {}, "s", "free", 1.0, "failed", error="e" * (ERROR_CHARS + 123))
    assert s["error"] == "e" * ERROR_CHARS + " ... (123 more characters)"
    assert summarize(None, {}, "s", "free", 1.0, "failed", error="short")["error"] == "short"


# ---------------------------------------------------------------------------------------------
# Signals whose default ended the process at once: SIGQUIT, SIGUSR1/2, SIGXCPU
# ---------------------------------------------------------------------------------------------

def test_the_signals_that_kill_by_default_end_a_run_as_interrupted():
    from hairexp.app.signals import SIGNALS

    assert set(SIGNALS) >= {signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1,
                            signal.SIGUSR2, signal.SIGXCPU}


def test_sigquit_mid_run_ends_it_interrupted(tmp_path):
    """Round 19: Ctrl-\\ (SIGQUIT) and SIGUSR1 killed the run, summary.json left "running" (SIGUSR1
    takes the same handler, ``SIGNALS`` above; by hand: ``interrupted by SIGUSR1``, 335 steps kept)."""
    sig = signal.SIGQUIT
    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "hairexp", *SMALL, "frames=20000", "guides.source=rigid", f"hydra.run.dir={out}"],
                         cwd=tmp_path, env=dict(os.environ, CI="1", PYTHONPATH=str(REPO)), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=_limited(resource.RLIM_INFINITY))
    try:
        deadline = time.monotonic() + 90
        while not list((out / "stream" / "metrics").glob("part-*.parquet")):
            assert p.poll() is None, p.communicate()
            assert time.monotonic() < deadline, "no metrics part after 90 s"
            time.sleep(0.1)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 128 + sig, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["error"] == f"interrupted by {sig.name}"
    assert summary["steps"] > 0 and (out / "metrics.parquet").is_file()


def test_sigxcpu_says_the_cpu_time_limit(tmp_path):
    """Round 19: the soft CPU-time limit (ulimit -S -t) ended the run with exit 152, no word, its
    summary "running"."""
    out = tmp_path / "run"

    def pre():
        resource.setrlimit(resource.RLIMIT_CPU, (8, resource.RLIM_INFINITY))

    p = subprocess.run([sys.executable, "-m", "hairexp", *SMALL, "frames=20000", "guides.source=rigid", f"hydra.run.dir={out}"],
                       cwd=tmp_path, env=dict(os.environ, CI="1", PYTHONPATH=str(REPO)), capture_output=True,
                       text=True, timeout=300, preexec_fn=pre)
    assert p.returncode == 128 + signal.SIGXCPU, p.stderr[-2000:]
    assert "interrupted by SIGXCPU (the process's CPU-time limit, ulimit -t, was reached)" in p.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "SIGXCPU" in summary["error"]


# ---------------------------------------------------------------------------------------------
# Hydra's config flags: checked before any folder is made
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("flags,expected", [
    (["--config-name=nope"], "hairexp: error: --config-name=nope: no config nope.yaml in "),
    (["-m", "-cn", "nope"], "hairexp: error: --config-name=nope: no config nope.yaml in "),
    (["--config-dir=/nonexistent"], "hairexp: error: --config-dir=/nonexistent: no such folder"),
    (["-m", "-cd", "/etc/hostname"], "hairexp: error: --config-dir=/etc/hostname: not a folder"),
    (["-m", "-cp", "/tmp"], "hairexp: error: --config-name=config: no config config.yaml in /tmp"),
    (["--config-path=../nowhere"], "hairexp: error: --config-path=../nowhere: no such folder"),
    # own probes after round 19: a "~" the shell did not expand is a folder named "~" to Hydra; a config
    # that exists but does not compose (the schema's base, an experiment as the primary config)
    (["-cd", "~"], "hairexp: error: --config-dir=~: no such folder"),
    (["-cn", "base_config"], "hairexp: error: --config-name=base_config: Could not override '"),
    (["-m", "-cn", "experiment/goaling_smoke"], "hairexp: error: --config-name=experiment/goaling_smoke: "),
])
def test_bad_config_flags_are_one_line_exit_2_and_no_folder(tmp_path, flags, expected):
    """Round 19: exit 1 with Hydra's multi-line message and a folder holding only ``.lock``; under
    ``-m`` a traceback."""
    p = run_cli([*flags, *SMALL, f"hydra.run.dir={tmp_path / 'r'}", f"hydra.sweep.dir={tmp_path / 's'}"], tmp_path)
    assert p.returncode == 2, p.stderr
    errors = [s for s in p.stderr.splitlines() if s.startswith("hairexp: error") or "Traceback" in s]
    assert len(errors) == 1 and errors[0].startswith(expected), p.stderr
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()


def test_good_config_flags_still_run(tmp_path):
    (tmp_path / "extra").mkdir()
    p = run_cli(["-cp", "../conf", "-cn", "config", "-cd", str(tmp_path / "extra"), *SMALL,
                 f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["status"] == "completed"


def test_help_and_version_are_hairexps(tmp_path):
    p = run_cli(["--help"], tmp_path)
    assert p.returncode == 0 and p.stdout.startswith("hairexp: directable hair simulation"), p.stdout[:300]
    assert "Exit codes: 0 completed" in p.stdout and "experiment: celia" in p.stdout and "powered by Hydra" not in p.stdout
    v = run_cli(["--version"], tmp_path)
    assert v.returncode == 0 and v.stdout.startswith("hairexp 0.") and "(Hydra 1." in v.stdout
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------------
# Settings: an edit's keys of the other kind, a contact tolerance of metres
# ---------------------------------------------------------------------------------------------

def _edits_cfg(**edit):
    from hairexp.app.config import compose_config

    def value(v):
        return f"[{','.join(map(str, v))}]" if isinstance(v, list) else str(v)

    fields = ",".join(f"{k}:{value(v)}" for k, v in edit.items())   # the schema fills the other keys' defaults
    return compose_config(["experiment=goaling_smoke", "variants=[]", f"guides.edits=[{{{fields}}}]"])


@pytest.mark.parametrize("edit,key", [
    ({"guide": 0, "kind": "rotate", "angle_deg": 30.0, "falloff": 3.0}, "guides.edits[0].falloff"),
    ({"guide": 0, "kind": "rotate", "angle_deg": 30.0, "falloff": -1.0}, "guides.edits[0].falloff"),
    ({"guide": 0, "kind": "displace", "offset": [0.0, 0.0, 0.1], "axis": [1.0, 0.0, 0.0]}, "guides.edits[0].axis"),
])
def test_an_edits_key_of_the_other_kind_is_refused(edit, key):
    cfg = _edits_cfg(**edit)
    with pytest.raises(InputError) as err:
        check_config(cfg)
    assert str(err.value).startswith(f"{key}: is a ")


@pytest.mark.parametrize("edit", [
    {"guide": 0, "kind": "rotate", "angle_deg": 30.0, "axis": [1.0, 0.0, 0.0]},
    {"guide": 0, "kind": "displace", "offset": [0.0, 0.0, 0.1], "falloff": 2.0},
    {"guide": 0, "kind": "displace", "offset": [0.0, 0.0, 0.1], "axis": [0.0, 0.0, 1.0]},   # the default: unseen
])
def test_an_edits_own_keys_pass(edit):
    check_config(_edits_cfg(**edit))


def test_a_contact_tolerance_of_metres_is_refused():
    from hairexp.app.config import compose_config

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]"])
    check_config(updated(cfg, measure__tolerance=0.1))
    with pytest.raises(InputError) as err:
        check_config(updated(cfg, measure__tolerance=5.0))
    assert str(err.value).startswith("measure.tolerance: is 5 m beyond the hair's thickness")


# ---------------------------------------------------------------------------------------------
# A run into the folder of a refused one: the refused run's log lines go with its summary
# ---------------------------------------------------------------------------------------------

def test_a_run_after_a_refused_one_has_a_log_of_its_own(tmp_path):
    out = tmp_path / "r"
    p = run_cli([*SMALL, "solver.max_iterations=0", f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 2
    assert "failed (exit 2)" in (out / "__main__.log").read_text()
    p = run_cli([*SMALL, f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 0, p.stderr
    log = (out / "__main__.log").read_text()
    assert "failed (exit 2)" not in log and "goaling/free: 2 steps" in log


def test_an_export_past_the_file_size_limit_is_one_line_exit_4(tmp_path):
    """Own probe after round 19: the exporter's guide frame store (a temporary file) past ``ulimit
    -f`` ended with a ScratchError traceback, exit 1; the stage itself past it is named too."""
    env = dict(os.environ, CI="1", PYTHONPATH=str(REPO), TMPDIR=str(tmp_path))
    for limit, expected in ((30 * 1024, "hairexp: cannot write a temporary file: [Errno 27] the guide frame store"),
                            (100 * 1024, f"hairexp: error: {tmp_path / 'e.usda'}: cannot write the USD stage: "
                                         f"[Errno 27] File too large: '{tmp_path / 'e.usda'}'")):
        p = subprocess.run([sys.executable, "-m", "hairexp.io.export_scene", str(tmp_path / "e.usda"),
                            "experiment=goaling", "variants=[]"], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=300, preexec_fn=_limited(limit))
        assert p.returncode == 4, p.stderr[-2000:]
        lines = [s for s in p.stderr.splitlines() if s.startswith("hairexp:")]
        assert len(lines) == 1 and lines[0].startswith(expected) and "Traceback" not in p.stderr, p.stderr[-2000:]
        assert not (tmp_path / "e.usda").exists() and not list(tmp_path.glob("*.tmp*"))


def test_a_sweeps_signal_is_not_sent_to_the_resource_trackers():
    """Own probe after round 19: SIGQUIT to a ``-m`` sweep was forwarded to loky's resource tracker
    too (it ignores SIGINT and SIGTERM only): it died, and its successor printed a KeyError
    traceback per shared resource."""
    from hairexp.app.signals import child_pids, worker_pids

    tracker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)  # resource_tracker stand-in"])
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        deadline = time.monotonic() + 10
        while not {tracker.pid, worker.pid} <= set(child_pids()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert {tracker.pid, worker.pid} <= set(child_pids())
        pids = worker_pids()
        assert worker.pid in pids and tracker.pid not in pids
    finally:
        for p in (tracker, worker):
            p.kill()
            p.wait()


CACHED_KERNEL = """
from hairexp.physics.kernels import njit

@njit(cache=True)
def big(x):
    s = 0.0
    for i in range(x.shape[0]):
        s += x[i] * x[i] + 0.5 * x[i] - 1.0 / (1.0 + x[i] * x[i])
    return s
"""

CALL_KERNEL = """
import logging, sys
import numpy as np
logging.basicConfig(level=logging.WARNING, format="%(message)s")
sys.path.insert(0, sys.argv[1])
import cachedkernel
print(cachedkernel.big(np.arange(4.0)))
"""


def test_a_compile_cache_that_cannot_be_written_is_said_not_raised(tmp_path):
    """Independent probe round 22: under ``ulimit -f 100`` with a cold numba cache, numba's cache
    write raised EFBIG into the run, which failed as a run folder that could not be written, naming
    no file.  A real write failure here: a 1-byte file-size limit on the cache folder's files."""
    (tmp_path / "cachedkernel.py").write_text(CACHED_KERNEL)
    env = dict(os.environ, PYTHONPATH=str(REPO), NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    p = subprocess.run([sys.executable, "-c", CALL_KERNEL, str(tmp_path)], capture_output=True, text=True,
                       timeout=300, env=env, preexec_fn=_limited(1))
    assert p.returncode == 0, p.stderr[-2000:]
    expected = sum(x * x + 0.5 * x - 1.0 / (1.0 + x * x) for x in (0.0, 1.0, 2.0, 3.0))
    assert abs(float(p.stdout.strip()) - expected) < 1e-12
    said = [s for s in p.stderr.splitlines() if "compile cache could not be written" in s]
    assert len(said) == 1 and "[Errno 27] File too large" in said[0], p.stderr[-2000:]
    # without the limit the same kernel is cached, and a second process reads it without a word
    for _ in range(2):
        q = subprocess.run([sys.executable, "-c", CALL_KERNEL, str(tmp_path)], capture_output=True, text=True,
                           timeout=300, env=env)
        assert q.returncode == 0 and "compile cache" not in q.stderr, q.stderr[-2000:]
    assert list((tmp_path / "cache").rglob("*.nbc"))


@pytest.mark.parametrize("flags,expected", [
    (["-m", "--cfg", "hydra"], "hairexp: error: --multirun and --cfg given together"),
    (["--info", "-m", "solver.dt=0.01,0.02"], "hairexp: error: --info and --multirun given together"),
    (["--run", "--cfg", "job"], "hairexp: error: --run and --cfg given together"),
    (["--cfg", "job", "solver.dt=abc"], "hairexp: error: solver.dt: Value 'abc' of type 'str' could not be converted"),
    (["--cfg", "job", "tracking.rtoll=1"], "hairexp: error: tracking.rtoll: unknown key"),
])
def test_hydras_modes_and_a_printed_config_are_checked_like_a_run(tmp_path, flags, expected):
    """Independent probe round 22: two of Hydra's modes together gave its ValueError as a
    traceback, exit 1; ``--cfg job`` with a bad value, Hydra's multi-line message, exit 1."""
    p = run_cli(flags, tmp_path)
    assert p.returncode == 2, p.stderr
    errors = [s for s in p.stderr.splitlines() if s.startswith("hairexp: error") or "Traceback" in s]
    assert len(errors) == 1 and errors[0].startswith(expected), p.stderr
    assert not list(tmp_path.iterdir())


def test_a_printed_config_still_prints(tmp_path):
    p = run_cli(["--cfg", "job", "experiment=goaling_smoke", "solver.dt=0.02"], tmp_path)
    assert p.returncode == 0 and "dt: 0.02" in p.stdout, p.stderr


def test_rerun_write_errors_of_the_comparison_are_named_oserrors(tmp_path):
    """Independent probe round 22: a full disk while comparison.rrd was written ended the experiment
    with rerun's RuntimeError as a traceback, exit 1, and its summary left "running" (by hand, on a
    20 MB tmpfs filled as tracked/recording.rrd appeared: now exit 4, ``[Errno 28] No space left on
    device: '.../comparison.partial.rrd'``, the experiment's summary failed)."""
    from hairexp.outputs.comparison import _written

    def full():
        raise RuntimeError("Failed to encode LogMsg: Failed to write: No space left on device (os error 28)")

    with pytest.raises(OSError) as err:
        _written(tmp_path / "c.rrd", full)
    assert (err.value.errno, err.value.filename) == (28, str(tmp_path / "c.rrd"))

    def other():
        raise RuntimeError("some other rerun error")

    with pytest.raises(RuntimeError):
        _written(tmp_path / "c.rrd", other)
    assert _written(tmp_path / "c.rrd", lambda: 7) == 7
