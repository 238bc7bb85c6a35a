"""Run folders that survive anything (README "Run folder"): signals end a run as interrupted with
its partial data, a write failure never leaves a truncated file under a final name nor hides
the first error, a folder belongs to one run, variant names are safe folder names, non-convergence
is reported, a sweep's bad job does not stop the others, and the USD result is a binary crate."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import hairexp.app.cli as cli_mod
import hairexp.app.run as run_mod
import hairexp.outputs.files as files
import hairexp.outputs.metrics as metrics_mod
from hairexp.app.experiment import run_experiment
from hairexp.app.run import run
from hairexp.errors import InputError, SimulationError
from hairexp.outputs.files import GrowingNpy, ResultRecorder, write_npz
from hairexp.outputs.metrics import MetricsTable
from hairexp.physics.info import MAX_ITERATIONS
from hairexp.physics.simulator import Simulator

TINY = ["experiment=goaling_smoke", "variants=[]", "scene.n_strands=3", "scene.n_vertices=6", "guides.source=rigid",
        "logging.rerun=false", "logging.progress=false"]
FINAL = ("result.npz", "result.usdc", "result.usda", "recording.rrd")


def _default_signals():
    # a test runner started in the background (sh's `cmd &`) passes SIGINT on ignored, which the
    # command line keeps ignored (POSIX): the children here get the defaults, as a terminal gives
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def cli(args, cwd, **kw):
    return subprocess.Popen([sys.executable, "-m", "hairexp", *args], cwd=cwd, env=dict(os.environ, CI="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_signals, **kw)


def leftovers(out: Path) -> list[str]:
    return [str(p.relative_to(out)) for p in out.rglob("*") if ".tmp" in p.name]


# ---------------------------------------------------------------------------------------------
# Signals: SIGINT -> 130, SIGTERM -> 143, summary interrupted, partial data readable
# ---------------------------------------------------------------------------------------------

def test_pxr_is_imported_before_the_first_step(tmp_path):
    """USD's module loader swallows an interrupt raised inside its import (a traceback, then the
    import goes on): a SIGTERM that landed in the pxr import at the end of a run was lost and the
    run ended "completed", exit 0 (probe of issue 12).  pxr is now imported where the run keeps a
    signal for later, before the first step: checked in a fresh interpreter."""
    code = (
        "import sys, json\n"
        "from hairexp.app.config import compose_config\n"
        "from hairexp.app.run import run\n"
        "from hairexp.physics.simulator import Simulator\n"
        "seen = []\n"
        "step = Simulator.step\n"
        "def spy(self, state, dt):\n"
        "    seen.append('pxr' in sys.modules)\n"
        "    return step(self, state, dt)\n"
        "Simulator.step = spy\n"
        "assert 'pxr' not in sys.modules\n"
        f"run(compose_config({TINY + ['frames=2']!r}), {str(tmp_path / 'run')!r})\n"
        "print(json.dumps(seen))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert proc.returncode == 0, proc.stderr
    seen = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen and all(seen)


def test_sigint_inherited_as_ignored_stays_ignored(tmp_path):
    """A command a script starts with ``&`` inherits SIGINT ignored: it stays ignored for the whole
    run (it was honoured once the run's handlers were installed, ignored before: inconsistent;
    probe of issue 12), and SIGTERM still ends it."""
    def ignore_sigint():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "hairexp", *TINY, "frames=20000", f"hydra.run.dir={out}"], cwd=tmp_path,
                         env=dict(os.environ, CI="1"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=ignore_sigint)
    try:
        deadline = time.monotonic() + 60
        while not list((out / "stream" / "metrics").glob("part-*.parquet")):   # the run's handlers are in place
            assert p.poll() is None, p.communicate()
            assert time.monotonic() < deadline, "no metrics part after 60 s"
            time.sleep(0.1)
        p.send_signal(signal.SIGINT)
        time.sleep(1.0)
        assert p.poll() is None   # ignored
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 143, err
        assert json.loads((out / "summary.json").read_text())["error"] == "interrupted by SIGTERM"
    finally:
        if p.poll() is None:
            p.kill()


def test_signals_end_the_run_as_interrupted(tmp_path):
    procs = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        out = tmp_path / sig.name
        procs[sig] = (out, cli(["experiment=goaling_smoke", "variants=[]", "controller=tracking", "guides.source=rigid",
                                "frames=2000", f"hydra.run.dir={out}"], tmp_path))
    try:
        for sig, (out, p) in procs.items():
            deadline = time.monotonic() + 60
            while not list((out / "stream" / "metrics").glob("part-*.parquet")):   # a few steps are on disk
                assert p.poll() is None, p.communicate()
                assert time.monotonic() < deadline, "no metrics part after 60 s"
                time.sleep(0.1)
            p.send_signal(sig)
        for sig, (out, p) in procs.items():
            _, err = p.communicate(timeout=60)
            assert p.returncode == 128 + sig, err
            assert f"interrupted by {sig.name}" in err
            summary = json.loads((out / "summary.json").read_text())
            assert summary["status"] == "interrupted" and summary["error"] == f"interrupted by {sig.name}"
            df = pd.read_parquet(out / "metrics.parquet")
            assert 0 < len(df) == summary["steps"] < 2000
            positions = np.load(out / "stream" / "positions.npy")     # the frames done, a valid .npy
            assert 1 <= len(positions) <= len(df) + 1 and np.isfinite(positions).all()
            assert not [n for n in FINAL if (out / n).exists()]
            assert (out / "recording.partial.rrd").is_file()
            # the partial recording holds the metrics of every step done, read back from the table
            from rerun.chunk import RrdReader

            rows = sum(c.num_rows for c in RrdReader(out / "recording.partial.rrd").stream()
                       .filter(content="/metrics/iterations", is_static=False))
            assert rows == len(df)
            assert leftovers(out) == []
    finally:
        for _, p in procs.values():
            if p.poll() is None:
                p.kill()


# ---------------------------------------------------------------------------------------------
# Write failures: a full disk mid-run, a late failure of a result file
# ---------------------------------------------------------------------------------------------

def full_disk_after(monkeypatch, calls: int, everything: bool):
    """Frames flush ``calls`` times, then raise ENOSPC; with ``everything`` every atomic write
    fails from then on too (the failure summary included)."""
    state = {"n": 0, "full": False}
    flush, atomic = GrowingNpy.flush, files.atomic_write_bytes

    def full_flush(self):
        if state["full"] or (self.pending and state["n"] >= calls * 6):   # 6 per-frame arrays per flush
            state["full"] = True
            raise OSError(errno.ENOSPC, "No space left on device (injected)")
        state["n"] += bool(self.pending)
        flush(self)

    def full_atomic(path, write):
        if everything and state["full"]:
            raise OSError(errno.ENOSPC, f"No space left on device (injected, {Path(path).name})")
        atomic(path, write)

    monkeypatch.setattr(GrowingNpy, "flush", full_flush)
    monkeypatch.setattr(files, "atomic_write_bytes", full_atomic)
    monkeypatch.setattr(run_mod, "atomic_write_bytes", full_atomic)
    monkeypatch.setattr(metrics_mod, "atomic_write_bytes", full_atomic)
    monkeypatch.setattr(run_mod, "FLUSH_FRAMES", 2)


def test_disk_full_mid_run(hydra_conf, tmp_path, monkeypatch):
    full_disk_after(monkeypatch, 2, everything=False)
    with pytest.raises(OSError, match="injected") as e:
        run(hydra_conf([*TINY, "frames=12"]), tmp_path)
    assert e.value.errno == errno.ENOSPC
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "failed" and "injected" in summary["error"]
    assert not [n for n in FINAL if (tmp_path / n).exists()] and leftovers(tmp_path) == []
    df = pd.read_parquet(tmp_path / "metrics.parquet")              # the steps done
    assert len(df) == summary["steps"] >= 4
    P = np.load(tmp_path / "stream" / "positions.npy")              # the frames flushed before the disk filled
    assert len(P) == 5 and np.isfinite(P).all()                     # frame 0 + 2 flushes of 2 frames


def test_disk_full_hides_nothing(hydra_conf, tmp_path, monkeypatch):
    """When the ending's files cannot be written either, the first error is still the one
    raised; the later ones are notes on it.  The summary, which no new file can hold then, is
    written over the running summary's own bytes: it says failed, not running (a full disk left it
    "running", and a later run was told the run had been killed; probe of issue 12)."""
    full_disk_after(monkeypatch, 1, everything=True)
    with pytest.raises(OSError) as e:
        run(hydra_conf([*TINY, "frames=12"]), tmp_path)
    assert str(e.value).endswith("(injected)")                      # the frames' write, not a later one
    notes = "\n".join(e.value.__notes__)
    assert "metrics.parquet" in notes and "summary.json" not in notes
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "failed" and "injected" in summary["error"]
    assert not [n for n in FINAL if (tmp_path / n).exists()] and leftovers(tmp_path) == []
    for p in tmp_path.rglob("*.parquet"):                           # the parts on disk are complete files
        pd.read_parquet(p)


def test_a_disk_too_full_for_the_first_summary_leaves_no_empty_file(hydra_conf, tmp_path, monkeypatch):
    """The folder's claim (an empty summary.json) is removed when not even the running summary
    fits (a 0-byte summary.json stayed; probe of issue 12); a run that starts holds room for its
    ending (``folder.RESERVE``) and gives it back when it ends."""
    import hairexp.outputs.folder as folder_mod

    def no_room(path, obj):
        raise OSError(errno.ENOSPC, "No space left on device (injected)")

    with monkeypatch.context() as m:
        m.setattr(run_mod, "write_json", no_room)
        with pytest.raises(OSError, match="injected"):
            run(hydra_conf([*TINY, "frames=2"]), tmp_path / "a")
    assert not (tmp_path / "a" / "summary.json").exists()
    held = []
    reserve = folder_mod.reserve
    monkeypatch.setattr(run_mod, "reserve", lambda out: (held.append((out / folder_mod.RESERVE)), reserve(out))[1])
    run(hydra_conf([*TINY, "frames=2"]), tmp_path / "b")
    assert held and not held[0].exists()                      # held during the run, given back at its end
    assert folder_mod.RESERVE in folder_mod.RUN_FILES        # one left by a killed run is the run's, for overwrite


def test_late_write_failure_leaves_no_result(hydra_conf, tmp_path, monkeypatch):
    """result.npz is written, then the USD stage fails: result.npz is removed, the summary says
    failed with the USD error."""
    import hairexp.io.usd_write as usd_write

    def blocked(path, *a, **k):
        raise PermissionError(errno.EACCES, "Permission denied (injected)", str(path))

    monkeypatch.setattr(usd_write, "write_result_usd", blocked)
    with pytest.raises(PermissionError):
        run(hydra_conf([*TINY, "frames=3"]), tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "failed" and "Permission denied" in summary["error"]
    assert not [n for n in FINAL if (tmp_path / n).exists()] and leftovers(tmp_path) == []
    assert len(pd.read_parquet(tmp_path / "metrics.parquet")) == 3


# ---------------------------------------------------------------------------------------------
# The streamed format
# ---------------------------------------------------------------------------------------------

def test_streamed_arrays_and_npz(tmp_path):
    g = GrowingNpy(tmp_path / "a.npy", (2, 3), np.float64)
    assert np.load(tmp_path / "a.npy").shape == (0, 2, 3)
    frames = np.random.default_rng(0).normal(size=(7, 2, 3))
    for k, f in enumerate(frames):
        g.append(f)
        if k in (2, 4):
            g.flush()
            np.testing.assert_array_equal(np.load(tmp_path / "a.npy", mmap_mode="r"), frames[:k + 1])
    g.flush()
    g.close()
    write_npz(tmp_path / "r.npz", tmp_path, names=("a",))
    with np.load(tmp_path / "r.npz") as r:
        assert r.files == ["a"]
        np.testing.assert_array_equal(r["a"], frames)
    with pytest.raises(ValueError, match="shape"):
        GrowingNpy(tmp_path / "b.npy", (3,), np.float64).append(np.zeros(4))


def streamed_table(folder, rows) -> MetricsTable:
    """A streamed MetricsTable of ``rows``, flushed after rows 2 and 5 (three parts)."""
    t = MetricsTable(folder)
    for i, r in enumerate(rows):
        t.on_step(r, None)
        if i in (2, 5):
            t.flush()
    return t


def test_streamed_metrics_equal_one_table(tmp_path):
    rows = [{"step": i, "x": (i if i < 3 else 0.5), "flag": i % 2 == 0, "s": "a", **({"late": 1.0} if i > 4 else {})}
            for i in range(8)]
    t = streamed_table(tmp_path / "m", rows)
    pd.testing.assert_frame_equal(t.frame(), pd.DataFrame(rows))   # parts inferred differently: one inference
    assert sum(len(pd.read_parquet(p)) for p in sorted((tmp_path / "m").glob("part-*.parquet"))) == 6


def test_written_metrics_equal_one_table(tmp_path):
    """The parquet ``write`` streams part by part has the columns and values of one table of all
    rows: a column missing from a part is null there, ints meeting floats become floats, and a
    column of clashing types is written as text."""
    rows = [{"step": i, "x": (i if i < 3 else 0.5), "flag": i % 2 == 0, "s": "a", **({"late": 1.0} if i > 4 else {}),
             "mixed": ("text" if i >= 6 else float(i))}
            for i in range(8)]
    t = streamed_table(tmp_path / "m", rows)
    cols = t.write(tmp_path / "metrics.parquet")
    got = pd.read_parquet(tmp_path / "metrics.parquet")
    want = pd.DataFrame(rows)
    assert list(got.columns) == list(want.columns) and len(cols) == 8 and "late" in cols and "nope" not in cols
    for c in ("step", "x", "flag", "s", "late"):
        pd.testing.assert_series_equal(got[c], want[c], check_dtype=False)
        pd.testing.assert_series_equal(cols[c], got[c])
    assert got["x"].dtype == np.float64 and got["late"].isna().sum() == 5
    assert [float(v) for v in got["mixed"][:6]] == list(range(6)) and list(got["mixed"][6:]) == ["text", "text"]
    assert t.write(tmp_path / "metrics.parquet") is cols                 # nothing new: not written again
    with pytest.raises(KeyError):
        cols["nope"]


def test_frames_read_one_at_a_time(tmp_path):
    a = np.random.default_rng(1).normal(size=(9, 4, 3))
    np.save(tmp_path / "a.npy", a)
    f = files.NpyFrames(tmp_path / "a.npy")
    f.BLOCK_BYTES = 2 * 4 * 3 * 8                                      # blocks of 2 frames: 5 reads
    assert len(f) == 9 and f.ndim == 3 and f.shape == a.shape
    np.testing.assert_array_equal(np.stack(list(f)), a)
    np.testing.assert_array_equal(f[-1], a[-1])
    np.testing.assert_array_equal(f[2:7:2], a[2:7:2])
    with pytest.raises(IndexError):
        f[9]
    with open(tmp_path / "a.npy", "r+b") as fh:                       # a file cut short
        fh.truncate(fh.seek(0, 2) - 8)
    with pytest.raises(OSError, match="ends before"):
        list(files.NpyFrames(tmp_path / "a.npy"))


def test_recording_footer_check(hydra_conf, tmp_path):
    """A recording is given its final name only when it ends with rerun's footer."""
    from hairexp.outputs.rerun_sink import _check_complete

    out = tmp_path / "run"
    run(hydra_conf([*TINY, "frames=3", "logging.rerun=true"]), out)
    rrd = (out / "recording.rrd").read_bytes()
    _check_complete(str(out / "recording.rrd"))
    (tmp_path / "cut.rrd").write_bytes(rrd[:len(rrd) // 2])
    with pytest.raises(OSError, match="incomplete"):
        _check_complete(str(tmp_path / "cut.rrd"))


# ---------------------------------------------------------------------------------------------
# A folder belongs to one run
# ---------------------------------------------------------------------------------------------

def test_used_folder_is_refused_unless_overwrite(hydra_conf, tmp_path):
    out = tmp_path / "run"
    run(hydra_conf([*TINY, "frames=2", "output.usd_format=usda"]), out)
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(InputError, match="not empty") as e:
        run(hydra_conf([*TINY, "frames=3"]), out)
    assert "overwrite=true" in str(e.value)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before      # untouched
    s = run(hydra_conf([*TINY, "frames=3", "overwrite=true"]), out)
    assert s["status"] == "completed" and s["steps"] == 3
    assert sorted(p.name for p in out.iterdir()) == ["guides.npz", "metrics.parquet", "result.npz", "result.usdc",
                                                     "summary.json"]            # no result.usda of the old run
    from pxr import Usd, UsdGeom                                                 # the default: a binary crate

    assert (out / "result.usdc").read_bytes()[:8] == b"PXR-USDC"
    stage = Usd.Stage.Open(str(out / "result.usdc"))
    hair = UsdGeom.BasisCurves.Get(stage, "/Root/Result/Hair")
    assert hair.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="notes.txt"):                          # never deleted
        run(hydra_conf([*TINY, "frames=1", "overwrite=true"]), out)
    assert (out / "notes.txt").read_text() == "mine" and (out / "result.npz").is_file()



def test_overwrite_replaces_a_run_with_value_clips(hydra_conf, tmp_path):
    """A run whose USD result is clipped (result.clips/, output.usd_clips) is a run's folder:
    overwrite=true replaces it, a leftover result.clips.tmp/ of a killed writer included."""
    out = tmp_path / "run"
    run(hydra_conf([*TINY, "frames=2", "output.usd_clips=always"]), out)
    assert (out / "result.clips").is_dir()
    (out / "result.clips.tmp").mkdir()
    with pytest.raises(InputError, match="not empty"):
        run(hydra_conf([*TINY, "frames=2"]), out)
    s = run(hydra_conf([*TINY, "frames=2", "output.usd_clips=never", "overwrite=true"]), out)
    assert s["status"] == "completed"
    assert not (out / "result.clips").exists() and not (out / "result.clips.tmp").exists()

def test_default_folders_are_unique(tmp_path):
    procs = [cli([*TINY, "frames=1"], tmp_path) for _ in range(2)]               # launched in the same second
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    folders = sorted((tmp_path / "outputs" / "goaling_smoke").iterdir())
    assert len(folders) == 2 and all((f / "result.npz").is_file() for f in folders)


def test_used_folder_exits_2_with_one_line(hydra_conf, tmp_path, capsys):
    """The command line's job (hairexp/app/cli.py) on a used folder: exit code 2, one line."""
    used = tmp_path / "used"
    used.mkdir()
    (used / "summary.json").write_text('{"status": "completed"}')
    res = cli_mod.job(hydra_conf([*TINY, "frames=1"]), str(used))
    assert res["code"] == 2 and res["status"] == "failed" and cli_mod.exit_code() == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("hairexp: error: ") and "not empty" in lines[0]
    assert (used / "summary.json").read_text() == '{"status": "completed"}'   # the old run's summary is kept


def test_used_folder_is_refused_before_hydra_writes_into_it(tmp_path):
    """``python -m hairexp ... hydra.run.dir=<a used folder>``: exit 2, one line, and the folder's
    ``.hydra/`` files are still the first run's (Hydra wrote the refused run's over them; probe of
    issue 12).  With overwrite=true the second run replaces the first."""
    out = tmp_path / "run"
    p = cli([*TINY, "frames=2", f"hydra.run.dir={out}"], tmp_path)
    assert p.wait(timeout=120) == 0, p.communicate()
    before = (out / ".hydra" / "overrides.yaml").read_text()
    p = cli([*TINY, "frames=1", f"hydra.run.dir={out}"], tmp_path)
    _, err = p.communicate(timeout=120)
    lines = [line for line in err.splitlines() if line.strip()]
    assert p.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"hairexp: error: {out}: the run folder is not "
                                                                          "empty"), err
    assert (out / ".hydra" / "overrides.yaml").read_text() == before
    p = cli([*TINY, "frames=1", f"hydra.run.dir={out}", "overwrite=true"], tmp_path)
    assert p.wait(timeout=120) == 0, p.communicate()
    assert "frames=1" in (out / ".hydra" / "overrides.yaml").read_text()


@pytest.mark.parametrize("names, bad, match", [
    (["../x", "tracked"], 0, "safe folder name"),
    (["free", ""], 1, "safe folder name"),
    (["/abs", "tracked"], 0, "safe folder name"),
    (["free", "a/b"], 1, "safe folder name"),
    ([".", "tracked"], 0, "safe folder name"),
    (["free", "free"], 1, "also the name of variants\\[0\\]"),
    ([".hydra", "tracked"], 0, "safe folder name"),
    (["free", "stream"], 1, "reserved"),
    (["summary.json", "tracked"], 0, "reserved"),
    (["free", "comparison"], 1, "reserved"),   # comparison.rrd is the experiment folder's own
])
def test_variant_names(hydra_conf, tmp_path, names, bad, match):
    cfg = hydra_conf(["experiment=goaling_smoke", "logging.rerun=false"])
    for v, n in zip(cfg.variants, names):
        v.name = n
    with pytest.raises(InputError, match=match) as e:
        run_experiment(cfg, tmp_path / "exp")
    assert str(e.value).startswith(f"variants[{bad}].name:")
    assert not (tmp_path / "exp").exists() and not (tmp_path / "x").exists()


# ---------------------------------------------------------------------------------------------
# Non-convergence
# ---------------------------------------------------------------------------------------------

def unconverged_steps(monkeypatch, which):
    step = Simulator.step
    count = {"n": 0}

    def flagged(self, state, dt):
        new, info = step(self, state, dt)
        count["n"] += 1
        if which(count["n"]):
            info.status = MAX_ITERATIONS
        return new, info

    monkeypatch.setattr(Simulator, "step", flagged)


def test_unconverged_steps_warn(hydra_conf, tmp_path, monkeypatch, caplog):
    unconverged_steps(monkeypatch, lambda n: n in (2, 3))
    with caplog.at_level("WARNING", logger="hairexp"):
        s = run(hydra_conf([*TINY, "frames=4"]), tmp_path)
    assert s["status"] == "completed" and s["converged"] is False and s["unconverged_steps"] == 2
    assert json.loads((tmp_path / "summary.json").read_text())["converged"] is False
    assert "2 of 4 steps did not converge" in caplog.text
    assert (tmp_path / "result.npz").is_file()


def test_unconverged_steps_fail(hydra_conf, tmp_path, monkeypatch):
    unconverged_steps(monkeypatch, lambda n: n == 2)
    with pytest.raises(SimulationError, match="1 of 4 steps did not converge"):
        run(hydra_conf([*TINY, "frames=4", "on_unconverged=fail"]), tmp_path)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"] == "failed" and s["converged"] is False and not (tmp_path / "result.npz").exists()


def test_a_step_that_cannot_be_solved_leaves_converged_false(hydra_conf, tmp_path, monkeypatch):
    """A run stopped by a step that could not be solved (SimulationError from the step) is
    ``failed`` with ``converged: false``: the failed step is not in the metrics, whose steps all
    converged (it said ``converged: true``; probe of issue 12)."""
    step = Simulator.step
    count = {"n": 0}

    def failing(self, state, dt):
        count["n"] += 1
        if count["n"] == 3:
            raise SimulationError("step from t=0.08 s with dt=0.04 s diverged")
        return step(self, state, dt)

    monkeypatch.setattr(Simulator, "step", failing)
    with pytest.raises(SimulationError, match="diverged"):
        run(hydra_conf([*TINY, "frames=4"]), tmp_path)
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"] == "failed" and s["converged"] is False and s["steps"] == 2 and "diverged" in s["error"]


def test_no_step_converged_fails(hydra_conf, tmp_path, monkeypatch):
    unconverged_steps(monkeypatch, lambda n: True)
    with pytest.raises(SimulationError, match="no step converged"):
        run(hydra_conf([*TINY, "frames=3"]), tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text())["status"] == "failed"


# ---------------------------------------------------------------------------------------------
# Sweeps: a bad job is recorded, the others complete, the sweep exits non-zero at the end
# ---------------------------------------------------------------------------------------------

def test_sweep_with_a_bad_job(tmp_path):
    sweep = tmp_path / "sweep"
    p = cli(["-m", *TINY, "frames=5", "scene.n_vertices=6,1", f"hydra.sweep.dir={sweep}"], tmp_path)
    _, err = p.communicate(timeout=180)
    assert p.returncode == 2, err
    assert json.loads((sweep / "0" / "summary.json").read_text())["status"] == "completed"
    assert (sweep / "0" / "result.npz").is_file()
    assert json.loads((sweep / "1" / "summary.json").read_text())["status"] == "failed"
    jobs = [line for line in err.splitlines() if line.startswith("hairexp: job ")]
    assert len(jobs) == 2 and "completed (exit 0)" in jobs[0] and "failed (exit 2)" in jobs[1], err
    assert "hairexp: sweep: 1 of 2 jobs completed" in err
    # said when it happened, naming the job (it read as the closing line's error said twice)
    assert [s for s in err.splitlines() if s.startswith("hairexp: error:")] == [
        "hairexp: error: job 1: scene.n_vertices: must be >= 3 (two root vertices and one free), got 1"], err


def test_a_killed_run_is_named_when_its_folder_is_reused(hydra_conf, tmp_path):
    """SIGKILL leaves summary.json saying running: it records the process, and a later run into
    the folder says the run there was killed (its process is gone)."""
    out = tmp_path / "killed"
    p = cli([*TINY, "frames=5000", f"hydra.run.dir={out}"], tmp_path)
    try:
        deadline = time.monotonic() + 60
        while not list((out / "stream").glob("positions.npy")):
            assert p.poll() is None, p.communicate()
            assert time.monotonic() < deadline, "the run did not start in 60 s"
            time.sleep(0.1)
        s = json.loads((out / "summary.json").read_text())
        assert s["status"] == "running" and s["pid"] == p.pid and s["host"]
        from hairexp.outputs.folder import running_state

        assert running_state(out) == f"a run still running (pid {p.pid})"
    finally:
        p.kill()
        p.communicate(timeout=60)
    assert json.loads((out / "summary.json").read_text())["status"] == "running"   # no ending was written
    with pytest.raises(InputError, match=rf"not empty .*a run killed while running \(pid {p.pid}\)"):
        run(hydra_conf([*TINY, "frames=1"]), out)
    s = run(hydra_conf([*TINY, "frames=1", "overwrite=true"]), out)
    assert s["status"] == "completed" and s["pid"] == os.getpid()


def test_overwrite_keeps_a_run_folder_that_is_not_a_variant(tmp_path):
    """An experiment's folder (variants free and tracked) holding a copy of another run's folder:
    ``overwrite=true`` deleted the copy with the variants (independent probe, 2026-12-07).  Only the
    variants its summary names are its own; the copy is named as foreign and the overwrite refused."""
    from hairexp.outputs.folder import overwrite_refusal

    def a_run(d, **extra):
        d.mkdir()
        (d / "summary.json").write_text(json.dumps({"status": "completed", **extra}))
        (d / "metrics.parquet").write_bytes(b"PAR1" + b"\0" * 16)

    exp = tmp_path / "exp"
    exp.mkdir()
    # interrupted in its second variant: tracked is in its config's list, not yet among those it ran
    (exp / "summary.json").write_text(json.dumps({"status": "interrupted", "variants": {"free": {}},
                                                  "config": {"variants": [{"name": "free"}, {"name": "tracked"}]}}))
    a_run(exp / "free")
    a_run(exp / "tracked")
    assert overwrite_refusal(exp) is None
    a_run(exp / "keep_this")
    msg = overwrite_refusal(exp)
    assert msg is not None and "keep_this" in msg


def test_the_api_refuses_a_folder_inside_another_run(tmp_path):
    """``run_folder(cfg, <a run's folder>/sub)`` completed where the command line refuses it (an
    overwrite of that run then deleted it; independent probe, 2026-12-07)."""
    from hairexp.app import compose_config, run_folder
    from hairexp.errors import InputError

    other = tmp_path / "other"
    other.mkdir()
    (other / "summary.json").write_text(json.dumps({"status": "completed"}))
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false"])
    with pytest.raises(InputError, match="lies inside .*other, another run's folder"):
        run_folder(cfg, other / "sub")
    assert not (other / "sub").exists()


def test_a_tracked_variant_whose_clusters_cannot_be_made_is_refused_before_any_variant_runs(tmp_path):
    """goaling_smoke with tracking.max_guide_distance=0.0001: the tracked variant's correspondence
    failed when it was assembled, after the free variant had run and written its folder (an
    outside probe, 2026-12-07); now the experiment is refused before anything runs."""
    from hairexp.app import compose_config, run_folder
    from hairexp.errors import InputError

    cfg = compose_config(["experiment=goaling_smoke", "frames=2", "logging.rerun=false",
                          "tracking.max_guide_distance=0.0001"])
    with pytest.raises(InputError, match="tracking.max_guide_distance"):
        run_folder(cfg, tmp_path / "exp")
    assert not (tmp_path / "exp" / "free").exists()
