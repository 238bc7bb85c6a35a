"""Issue 12: the findings of probe round 17 and of the session after it, one test each."""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys

import pytest
from probe_helpers import REPO, run_cli

SMOKE = ["experiment=goaling_smoke", "variants=[]", "frames=3", "logging.rerun=false", "logging.progress=false"]


def _hairexp(args, tmp_path):
    return run_cli(args, tmp_path, timeout=240)


class _Stream:
    """A recording stream whose flush answers ``answer`` (an exception or None); counts disconnects."""

    def __init__(self, answer):
        self.answer, self.flushes, self.disconnects = answer, 0, 0

    def flush(self, timeout_sec):
        self.flushes += 1
        if self.answer is not None:
            raise self.answer

    def disconnect(self):
        self.disconnects += 1


def test_a_stream_whose_writer_failed_is_abandoned_not_disconnected(monkeypatch):
    """After rerun's ``File too large`` the failed ending's ``disconnect`` waited for the dead writer
    for ever (every thread in a futex, SIGTERM ignored, summary 'running'; round 17, 1 run in 3)."""
    import hairexp.outputs.rerun_sink as rs

    monkeypatch.setattr(rs.rr, "unregister_shutdown", lambda: None)
    monkeypatch.setattr(rs, "_size_capped", lambda path: None)
    monkeypatch.setattr(rs, "_free_bytes", lambda path: 1 << 30)
    rec = _Stream(RuntimeError("Failed to flush previous sink: File-writer thread shut down prematurely"))
    try:
        rs.finish_stream(rec, "/x/recording.partial.rrd")
        assert rec.disconnects == 0 and rec.flushes == 1
        assert rs.abandoned(rec)
        rs.finish_stream(rec, "/x/recording.partial.rrd")   # once given up, never waited for again
        assert rec.flushes == 1 and rec.disconnects == 0
        with pytest.raises(OSError, match="writer is stuck"):
            rs.flush_recording(rec, "/x/recording.partial.rrd")
    finally:
        rs._ABANDONED.remove(rec)


def test_a_healthy_stream_is_flushed_then_disconnected():
    import hairexp.outputs.rerun_sink as rs

    rec = _Stream(None)
    rs.finish_stream(rec, "/x/recording.partial.rrd")
    assert (rec.flushes, rec.disconnects) == (1, 1) and not rs.abandoned(rec)


def test_a_flush_error_of_any_kind_abandons_the_stream(monkeypatch):
    """Before, only a time-out or a file-size cap gave the stream up: a writer that stopped with
    another error was disconnected afterwards, and that could hang."""
    import hairexp.outputs.rerun_sink as rs

    monkeypatch.setattr(rs.rr, "unregister_shutdown", lambda: None)
    monkeypatch.setattr(rs, "_size_capped", lambda path: None)
    monkeypatch.setattr(rs, "_free_bytes", lambda path: 1 << 30)
    rec = _Stream(RuntimeError("Failed to write: Broken pipe"))
    try:
        with pytest.raises(OSError, match=r"could not be written \(Failed to write: Broken pipe\)"):
            rs.flush_recording(rec, "/x/recording.partial.rrd")
        assert rs.abandoned(rec)
    finally:
        rs._ABANDONED.remove(rec)


def test_a_model_layer_key_is_refused_before_the_folder_is_claimed(tmp_path):
    """W1 of round 17: ``scene.length=0`` was refused once the first variant was assembled, and
    the folder kept a failed summary (a retry needed overwrite=true)."""
    for extra in (["variants=[]"], []):
        out = tmp_path / f"run{len(extra)}"
        args = ["experiment=goaling_smoke", "frames=3", "logging.rerun=false", "logging.progress=false", *extra]
        proc = _hairexp(args + ["scene.length=0", f"hydra.run.dir={out}"], tmp_path)
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert proc.stderr.strip().splitlines()[-1].startswith("hairexp: error: scene.length: must be a finite number > 0")
        summary = json.loads((out / "summary.json").read_text())   # the folder says how the run ended
        assert summary["status"] == "failed" and summary["error"].startswith("scene.length: must be") and summary["refused"]
        assert sorted(p.name for p in out.iterdir()) == [".hydra", ".lock", "__main__.log", "summary.json"]
        ok = _hairexp(args + [f"hydra.run.dir={out}"], tmp_path)   # a retry into the same folder, no overwrite
        assert ok.returncode == 0, ok.stderr[-2000:]
        assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def test_a_later_variants_unknown_collider_is_refused_before_the_first_runs(tmp_path):
    """W2 of round 17: ``measure.collider`` of the second variant was refused after the first had run."""
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment
    from hairexp.errors import InputError

    cfg = compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=false", "logging.progress=false",
                          "judge=none", "variants=[{name: a, overrides: []}, "
                          "{name: b, overrides: ['measure.name=collider_contact', 'measure.collider=nope']}]"])
    with pytest.raises(InputError, match=r"no collider named 'nope' .*variants\[1\] b, checked before any variant runs"):
        run_experiment(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()   # no variant ran, nothing claimed


def test_unused_key_warnings_are_not_printed_above_a_refused_runs_error(tmp_path):
    """W3 of round 17: the 'not used' warning came before the error line of a refused run."""
    out = tmp_path / "run"
    proc = _hairexp(SMOKE + ["tracking.rtol=1e-4", "scene.length=0", f"hydra.run.dir={out}"], tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["hairexp: error: scene.length: must be a finite number > 0 and <= 100 "
                                                "(m), got 0.0"], proc.stderr
    ok = _hairexp(SMOKE + ["tracking.rtol=1e-4", f"hydra.run.dir={tmp_path / 'run2'}"], tmp_path)
    assert ok.returncode == 0 and "tracking.rtol (read with controller.name=tracking) not used" in ok.stderr


@pytest.mark.parametrize("colliders, where, match", [
    ("[{name: '', shape: sphere}]", "scene.colliders[0].name", "must be a non-empty name, got ''"),
    ("[{name: '  ', shape: sphere}]", "scene.colliders[0].name", "must be a non-empty name"),
])
def test_collider_names_are_given(colliders, where, match):
    """W4 of round 17: an empty name became ``collider0`` without a word (names used twice: Scene's check)."""
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config
    from hairexp.errors import InputError

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "measure.name=none",
                          f"scene.colliders={colliders}"])
    with pytest.raises(InputError, match=match) as e:
        check_config(cfg)
    assert e.value.where == where


def test_the_failed_endings_errors_are_said_once_each(tmp_path, monkeypatch):
    """The frames' flush and close failed alike, and the note came twice ('also:' lines); each note
    was printed a third time as a log line on the console."""
    import logging

    from hairexp.app import run as run_mod
    from hairexp.errors import SimulationError

    class Sinks:
        progress = None
        rerun = None
        written = []
        plain = {"experiment": None, "config": None}

        class recorder:
            @staticmethod
            def flush():
                raise OSError(27, "File too large")

            @staticmethod
            def align():
                raise OSError(27, "File too large")

            @staticmethod
            def close():
                raise OSError(27, "File too large")

        class table:
            steps = 0

            @staticmethod
            def flush():
                pass

    monkeypatch.setattr(run_mod, "summarize", lambda *a, **k: {})
    exc = SimulationError("boom")
    seen = []
    handler = logging.Handler()
    handler.emit = lambda record: seen.append(record.getMessage())
    logging.getLogger("hairexp").addHandler(handler)
    try:
        run_mod._end_unfinished(exc, Sinks, tmp_path, "s", "free", 0.0)
    finally:
        logging.getLogger("hairexp").removeHandler(handler)
    assert exc.__notes__ == ["while writing the failed ending (frames): OSError: [Errno 27] File too large"]
    assert not any("while writing" in m for m in seen)   # the console's handlers: the notes come as 'also:' lines


def test_a_guide_frame_store_that_does_not_read_back_is_a_read_error():
    """A short read of the guide frame store (a temporary file) was a plain OSError, which the
    command line called 'cannot write the run folder'."""
    import numpy as np

    from hairexp.errors import ScratchError
    from hairexp.guides.store import FrameStore

    store = FrameStore.of(np.arange(24.0).reshape(4, 2, 3))
    assert np.array_equal(store[3], np.arange(18.0, 24.0).reshape(2, 3))
    store._cache = None
    os.ftruncate(store._file.fileno(), 2 * store.frame_bytes)   # another process cut the file
    with pytest.raises(ScratchError, match=r"guide frame store .*: read 96 of 192 bytes of frames 0..3") as e:
        store[3]
    assert e.value.reading


def test_a_temporary_file_read_error_is_named_as_such(tmp_path, monkeypatch, capsys):
    import errno

    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config
    from hairexp.errors import ScratchError

    def unreadable(cfg, out, on_checked=None):
        Path(out).mkdir(parents=True, exist_ok=True)
        raise ScratchError(errno.EIO, "the guide frame store (a temporary file in /tmp): read 0 of 96 bytes",
                           reading=True)

    monkeypatch.setattr(cli, "run_experiment", unreadable)
    res = cli.job(compose_config(SMOKE), str(tmp_path / "r"), overrides=[])
    err = capsys.readouterr().err
    assert res["code"] == 4 and err.startswith("hairexp: cannot read a temporary file back: [Errno 5] the guide "
                                               "frame store"), err
    assert "cannot write" not in err


def test_a_file_size_limit_is_named_on_the_run_folders_error_line(tmp_path, monkeypatch, capsys):
    """Under ``ulimit -f`` the line said only '[Errno 27] File too large' (a numpy write names no file)."""
    import resource

    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config

    def too_large(cfg, out, on_checked=None):
        Path(out).mkdir(parents=True, exist_ok=True)
        raise OSError(27, "File too large")

    monkeypatch.setattr(cli, "run_experiment", too_large)
    monkeypatch.setattr(resource, "getrlimit", lambda which: (307200, resource.RLIM_INFINITY))
    res = cli.job(compose_config(SMOKE), str(tmp_path / "r"), overrides=[])
    err = capsys.readouterr().err
    assert res["code"] == 4
    assert err.splitlines()[0].endswith("[Errno 27] File too large (a file reached the process's file-size limit, "
                                        "ulimit -f: 307200 bytes)"), err


def test_rerun_s_own_log_lines_are_off_unless_asked_for():
    """rerun's Rust log lines (ANSI-coloured ERROR/WARN) came beside hairexp's own error line."""
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    code = "import os, hairexp; print(os.environ['RUST_LOG'])"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONPATH": str(REPO)}, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "off"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONPATH": str(REPO), "RUST_LOG": "warn"},
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == "warn"


def test_a_warning_is_said_once_per_run_or_experiment():
    """The settings are checked with the scene and guides built before the folder is claimed, and
    built again to run: each warning came twice (and once more per variant)."""
    import logging

    from hairexp.app.run import warnings_once

    seen_a, seen_b = [], []
    a, b = logging.Handler(), logging.Handler()
    a.emit = lambda r: seen_a.append(r.getMessage())
    b.emit = lambda r: seen_b.append(r.getMessage())
    root, log = logging.getLogger(), logging.getLogger("hairexp.app.test")
    root.addHandler(a), root.addHandler(b)
    try:
        with warnings_once():
            log.warning("late key %s", 1)
            with warnings_once():   # a variant's run inside the experiment's
                log.warning("late key %s", 1)
                log.warning("other")
            logging.getLogger("elsewhere").warning("other")   # not hairexp's: untouched
            logging.getLogger("elsewhere").warning("other")
            log.error("failed")   # only warnings are said once
            log.error("failed")
        log.warning("late key %s", 1)   # after the run: said again
    finally:
        root.removeHandler(a), root.removeHandler(b)
    assert seen_a == seen_b == ["late key 1", "other", "other", "other", "failed", "failed", "late key 1"]
    assert not a.filters and not b.filters


def test_an_experiments_variants_say_a_shared_warning_once(tmp_path):
    out = tmp_path / "run"
    proc = _hairexp(["experiment=goaling_smoke", "frames=3", "logging.rerun=false", "logging.progress=false",
                     f"hydra.run.dir={out}"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = [line for line in proc.stderr.splitlines() if "lies after the run's end" in line]
    assert len(said) == 1, proc.stderr
    assert (out / "__main__.log").read_text().count("lies after the run's end") == 1


def test_a_signal_during_the_checks_leaves_a_summary_that_says_so(tmp_path, monkeypatch, capsys):
    """The checks now build the scene and guides before the run claims its folder: a signal then
    ended the run with no summary.json, while the line said 'summary.json ... says so'."""
    import signal

    import hairexp.app.cli as cli
    from hairexp.app.config import compose_config
    from hairexp.app.run import run
    from hairexp.errors import Interrupted

    out = tmp_path / "r"

    def interrupted(cfg, folder, on_checked=None):
        Path(folder).mkdir(parents=True, exist_ok=True)   # Hydra made it
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(cli, "run_experiment", interrupted)
    res = cli.job(compose_config(SMOKE), str(out), overrides=[])
    assert res["code"] == 143 and res["status"] == "interrupted"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "interrupted while its settings were checked" in summary["refused"]
    assert f"summary.json in {out} says so" in capsys.readouterr().err
    s = run(compose_config(SMOKE), out)   # the next run replaces it without overwrite
    assert s["status"] == "completed" and json.loads((out / "summary.json").read_text())["status"] == "completed"


@pytest.mark.parametrize("override, where", [
    ("guides.n_vertices=2", "guides.n_vertices"),
    ("guides.edits=[{guide: 9, kind: displace, offset: [0.1, 0.0, 0.0], times: [0.0, 0.1], weights: [0.0, 1.0]}]",
     "guides.edits[0].guide"),
])
def test_simulated_guides_keys_are_checked_before_the_folder_is_claimed(override, where):
    """Simulated guides were built after the run had claimed its folder: a bad guide key left a
    failed (not refused) summary.  Their keys and edits are checked on the rest guides now."""
    from hairexp.app.assemble import check_config
    from hairexp.app.config import compose_config
    from hairexp.errors import InputError

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "controller=tracking", override])
    assert str(cfg.guides.source.value) == "simulated"
    with pytest.raises(InputError) as e:
        check_config(cfg)
    assert e.value.where == where


def test_one_note_per_error_of_the_failed_ending(tmp_path, monkeypatch):
    """A full disk stopped four parts of the ending with the same error: four alike 'also:' lines."""
    from hairexp.app import run as run_mod
    from hairexp.errors import SimulationError

    full = OSError(28, "No space left on device")

    def fail():
        raise full

    class Sinks:
        progress = None
        written = []
        plain = {"experiment": None, "config": None}

        class recorder:
            flush = align = close = staticmethod(fail)

        class table:
            steps = 3
            written = None   # nothing written yet (round 32)
            flush = write = staticmethod(lambda *a: fail())
            frame = staticmethod(lambda: None)

        class rerun:
            close = staticmethod(lambda **k: (_ for _ in ()).throw(OSError(28, "recording: no space")))

    monkeypatch.setattr(run_mod, "summarize", lambda *a, **k: {})
    exc = SimulationError("boom")
    run_mod._end_unfinished(exc, Sinks, tmp_path, "s", "free", 0.0)
    assert exc.__notes__ == [
        # (the table's flush is write's own first act since round 26: one part, metrics.parquet)
        "while writing the failed ending (frames, metrics.parquet): OSError: [Errno 28] No space left on device",
        "while writing the failed ending (recording): OSError: [Errno 28] recording: no space"]


def test_an_allow_large_warning_is_said_once_a_run(caplog):
    """The checks and the run both estimate the run: with guard.allow_large the disk warning came
    twice (its free bytes moved between the two)."""
    import logging

    from hairexp.app import guard

    est = guard.Estimate(memory=1.0, disk=100.0, steps=10, settle_steps=0, seconds=1.0)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        guard.check(est, "k", True, None, 50.0, "/x/run18")
        guard.check(est, "k", True, None, 49.0, "/x/run18")
        guard.check(est, "k", True, None, 49.0, "/x/other")   # another run (a sweep's next job): said again
    assert [r.getMessage().split(" but ")[0] for r in caplog.records] == [
        "k: the run's files would take about 0.1 kB of disk (10 steps; 72 B a vertex a frame)"] * 2


def test_a_variants_write_failure_names_the_variants_folder(tmp_path, monkeypatch, capsys):
    """A full disk in the tracked variant said 'cannot write the run folder <experiment folder>'."""
    import hairexp.app.cli as cli
    import hairexp.app.experiment as experiment
    from hairexp.app.config import compose_config

    def full(cfg, folder):
        if Path(folder).name == "tracked":
            raise OSError(28, "No space left on device")
        return {"measures": {}, "status": "completed"}

    monkeypatch.setattr(experiment, "run_checked", full)   # a variant's run
    out = tmp_path / "r"
    res = cli.job(compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=false"]), str(out),
                  overrides=[])
    err = capsys.readouterr().err
    assert res["code"] == 4
    assert f"hairexp: cannot write the run folder {out / 'tracked'}: [Errno 28] No space left on device" in err, err
    assert json.loads((out / "summary.json").read_text())["status"] == "failed"


def test_a_second_refusal_in_the_same_folder_says_its_own_error(tmp_path):
    """The refused summary of a first launch stayed when a second launch into the folder was refused
    for another reason: the folder named the first error."""
    out = tmp_path / "run"
    base = ["experiment=goaling_smoke", "variants=[]", "frames=3", "logging.rerun=false", "logging.progress=false",
            f"hydra.run.dir={out}"]
    assert _hairexp(base + ["scene.length=0"], tmp_path).returncode == 2
    assert json.loads((out / "summary.json").read_text())["error"].startswith("scene.length:")
    assert _hairexp(base + ["solver.dt=0"], tmp_path).returncode == 2
    assert json.loads((out / "summary.json").read_text())["error"].startswith("solver.dt:")


def test_a_file_size_limit_too_small_for_the_first_files_is_refused_before_hydra(tmp_path):
    """Under ``ulimit -f 1`` Hydra's write of .hydra/config.yaml failed: its traceback, exit 1, no summary."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, resource.RLIM_INFINITY))

    out = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE, f"hydra.run.dir={out}"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120, preexec_fn=limit)
    assert proc.returncode == 4, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines() == [
        "hairexp: error: the process's file-size limit (ulimit -f) is 1024 bytes, less than the 64 kB a run needs to "
        "write its first files (Hydra's .hydra/config.yaml, summary.json); raise it (ulimit -f unlimited)"]
    assert not out.exists()
    shown = subprocess.run([sys.executable, "-m", "hairexp", *SMOKE, "--cfg", "job"], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120, preexec_fn=limit)
    assert shown.returncode == 0 and "scene:" in shown.stdout   # printing writes no file


def test_a_usd_syntax_error_names_the_line_and_the_reason(tmp_path):
    """'cannot read the USD stage: Failed to open layer @...@' dropped the parser's line:column and reason."""
    from hairexp.errors import InputError
    from hairexp.io.usd_read import open_stage

    stage = tmp_path / "bad.usda"
    stage.write_text('#usda 1.0\n\ndef Xform "Root"\n{\n    def Xform "A"\n    {\n}\n')
    with pytest.raises(InputError, match=r"cannot read the USD stage: .*bad\.usda:\d+:\d+: ") as e:
        open_stage(str(stage))
    assert "Failed to open layer" not in str(e.value)


def test_a_killed_sweep_jobs_summary_counts_the_steps_it_streamed(tmp_path, monkeypatch):
    """A sweep worker killed (kill -9): the main process ended its job's summary as failed with no
    steps, while stream/metrics held 825 frames of them (round 18)."""
    import socket

    import hairexp.app.cli as cli
    from hairexp.app.run import summarize
    from hairexp.outputs.metrics import MetricsTable

    job = tmp_path / "0"
    (job / ".hydra").mkdir(parents=True)
    table = MetricsTable(job / "stream" / "metrics")
    for k in range(6):
        table.rows.append({"step": k + 1, "frame": k + 1, "time": 0.01 * (k + 1), "converged": k != 2, "dt": 0.01,
                           "substeps": 1, "iterations": 3 + k, "recovered": False, "step_seconds": 0.002,
                           "stretch_max": 1e-5 * k, "residual_rel_max": None})
        if k % 2:
            table.flush()
    running = {**summarize(None, {"experiment": "e", "config": {}}, "s", "free", 0.0, "running"),
               "pid": 2 ** 22 + 12345, "host": socket.gethostname()}   # a process that does not exist
    (job / "summary.json").write_text(json.dumps(running))
    res = {"status": "running", "code": 1, "message": "the job did not finish", "out": str(job)}
    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    cli._end_killed_jobs([("0", "", res)], None)
    s = json.loads((job / "summary.json").read_text())
    assert s["status"] == "failed" and "ended before it wrote its ending" in s["error"]
    assert (s["steps"], s["unconverged_steps"], s["iterations_max"]) == (6, 1, 8)
    assert res["status"] == "failed"
    assert res["code"] == 3   # a run that could not continue, not a bug's exit 1 (round 18's weak finding)


def test_a_section_deleted_on_the_command_line_is_named_as_such(tmp_path):
    """``~measure`` said 'missing from the config given to run_folder (compose it with
    hairexp.app.compose_config)': the Python API's advice, to a command-line user."""
    out = tmp_path / "run"
    proc = _hairexp(SMOKE + ["~measure", f"hydra.run.dir={out}"], tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["hairexp: error: measure: deleted from the config (~measure on the "
                                                "command line); every run reads it: drop the ~ override"]
    assert json.loads((out / "summary.json").read_text())["status"] == "failed"
