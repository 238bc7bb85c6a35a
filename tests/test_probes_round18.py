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
