"""Findings left weak by probe round 18 of issue 12 (2026-12-05), fixed."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from hairexp.app.guides import check_guide_file


def _guide_file(path, dtype):
    pos = np.zeros((3, 4, 3), dtype=dtype)
    pos[..., 2] = np.linspace(0, 0.3, 4)
    np.savez(path, guide_positions=pos, guide_offsets=np.array([0, 4]), fps=np.array(25.0))
    return path


@pytest.mark.parametrize("dtype,warned", [(np.float16, True), (np.float32, False), (np.float64, False)])
def test_low_precision_guide_positions_are_said(tmp_path, caplog, dtype, warned):
    path = _guide_file(tmp_path / "g.npz", dtype)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        check_guide_file(path)
    said = [r.getMessage() for r in caplog.records if "significant digits" in r.getMessage()]
    assert bool(said) == warned
    if warned:
        assert f"guides.file={path}" in said[0] and "float16" in said[0]


def test_a_guide_files_own_errors_name_the_key_before_the_run(tmp_path):
    """A guide file's fps of 0 was named by its path alone (``<path>: fps must be ...``) when the
    checks before the run read it; the run itself said ``guides.file=<path>: ...``."""
    from probe_helpers import run_cli

    path = _guide_file(tmp_path / "g.npz", np.float64)
    with np.load(path) as d:
        np.savez(path, guide_positions=d["guide_positions"], guide_offsets=d["guide_offsets"], fps=np.array(0.0))
    p = run_cli(["experiment=goaling_smoke", "variants=[]", "frames=3", "logging=off", "guides.source=file",
                 f"guides.file={path}", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert p.returncode == 2, p.stderr
    line = [s for s in p.stderr.splitlines() if s.startswith("hairexp: error:")]
    assert line == [f"hairexp: error: guides.file={path}: fps must be a number from 0.1 to 100000 "
                    "(frames per second), got 0.0"], p.stderr


def test_arrays_a_guide_file_holds_beside_its_own_are_said(tmp_path, caplog):
    """An npz with an extra array (``junk``, or a misspelt one) was read without a word about it."""
    path = _guide_file(tmp_path / "g.npz", np.float64)
    with np.load(path) as d:
        np.savez(path, **dict(d), junk=np.arange(3), guide_offset=np.array([0, 4]))
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        check_guide_file(path)
    said = [r.getMessage() for r in caplog.records if "not read" in r.getMessage()]
    assert said == [f"guides.file={path}: guide_offset, junk are not read (a guide file holds guide_positions, "
                    "guide_offsets and fps)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        check_guide_file(_guide_file(tmp_path / "plain.npz", np.float64))
    assert not [r for r in caplog.records if "not read" in r.getMessage()]


def test_a_write_error_names_its_file(tmp_path, monkeypatch):
    """A full disk left summary.json's error as '[Errno 28] No space left on device', no file named:
    a write to an open file raises an OSError without a filename."""
    import builtins
    import errno

    from hairexp.outputs.files import GrowingNpy, atomic_write_bytes, naming

    def full(_):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as info:
        atomic_write_bytes(tmp_path / "a.json", full)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(tmp_path / "a.json")
    assert not list(tmp_path.iterdir())   # no temporary file left

    g = GrowingNpy(tmp_path / "x.npy", (2,), np.float64)
    g.append(np.zeros(2))
    monkeypatch.setattr(g, "f", type("F", (), {"seek": lambda *a: None, "write": lambda _, b: full(b),
                                               "flush": lambda *a: None})())
    with pytest.raises(OSError) as info:
        g.flush()
    assert info.value.filename == str(tmp_path / "x.npy")

    # an error that names its file, or one of another class, goes through as it is
    for exc in (FileNotFoundError(errno.ENOENT, "No such file", "/elsewhere"), builtins.ValueError("v")):
        with pytest.raises(type(exc)) as info, naming(tmp_path / "y"):
            raise exc
        assert info.value is exc



def test_one_note_per_os_error_whatever_file_it_names(tmp_path, monkeypatch):
    """With the files named (``files.naming``), a full disk's failed ending said one "also:" line
    per file again: the same OSError (class, errno, reason) is one note, with the first file."""
    from hairexp.app import run as run_mod
    from hairexp.errors import SimulationError

    def fail(name):
        def raise_():
            raise OSError(28, "No space left on device", str(tmp_path / name))
        return raise_

    class Sinks:
        progress = None
        written = []
        plain = {"experiment": None, "config": None}

        class recorder:
            flush = align = staticmethod(fail("positions.npy"))
            close = staticmethod(fail("times.npy"))

        class table:
            steps = 3
            written = None   # nothing written yet (the parquet named this run's own: round 32)
            flush = staticmethod(fail("part-00001.parquet"))
            write = staticmethod(lambda *a: fail("metrics.parquet")())
            frame = staticmethod(lambda: None)

        class rerun:
            close = staticmethod(lambda **k: (_ for _ in ()).throw(OSError(13, "Permission denied", "rec.rrd")))

    monkeypatch.setattr(run_mod, "summarize", lambda *a, **k: {})
    exc = SimulationError("boom")
    run_mod._end_unfinished(exc, Sinks, tmp_path, "s", "free", 0.0)
    assert exc.__notes__ == [
        # (the table's flush is write's own first act since round 26: one part, metrics.parquet; each part
        # names its own file since round 28, positions.npy stood for every part)
        "while writing the failed ending (frames (positions.npy), metrics.parquet): OSError: [Errno 28] No space "
        "left on device",
        "while writing the failed ending (recording (rec.rrd)): PermissionError: [Errno 13] Permission denied"]
