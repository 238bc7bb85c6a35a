"""Issue 12: the findings of probe round 17 and of the session after it, one test each."""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]
SMOKE = ["experiment=goaling_smoke", "variants=[]", "frames=3", "logging.rerun=false", "logging.progress=false"]


def _hairexp(args, tmp_path, timeout=240):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=timeout)


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
        assert not (out / "summary.json").exists() and not any(p.is_dir() and p.name != ".hydra" for p in out.iterdir())
        ok = _hairexp(args + [f"hydra.run.dir={out}"], tmp_path)   # a retry into the same folder, no overwrite
        assert ok.returncode == 0, ok.stderr[-2000:]


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
    assert not (tmp_path / "r").exists()


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
    ("[{name: ball, shape: sphere}, {name: ball, shape: box}]", "scene.colliders[1].name",
     "'ball' is also the name of scene.colliders\\[0\\]"),
])
def test_collider_names_are_given_and_distinct(colliders, where, match):
    """W4 of round 17: an empty name became ``collider0`` without a word; two alike were drawn as one."""
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
