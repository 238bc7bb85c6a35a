"""An experiment's variants side by side, one process each (``variants_mode``,
hairexp/app/variant_processes.py): the same results as one after the other, the same run-folder
contract (a failing variant fails the experiment and stops the others; a signal ends every variant
interrupted; a variant whose process is killed is named), and ``auto`` chooses by cores, load,
the variants' length and memory."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import hairexp.app.variant_processes as vp
from hairexp.app.experiment import run_experiment
from hairexp.errors import InputError, SimulationError
from hairexp.physics.simulator import Simulator

SMOKE = ["experiment=goaling_smoke", "logging.rerun=false", "logging.progress=false"]


def _summary(p: Path) -> dict:
    return json.loads((p / "summary.json").read_text())


def test_side_by_side_gives_the_sequential_results(hydra_conf, tmp_path):
    """Each variant's result, metrics and measures are those of the sequential experiment, bit for bit."""
    runs = {}
    for mode in ("sequential", "parallel"):
        out = tmp_path / mode
        runs[mode] = run_experiment(hydra_conf([*SMOKE, f"variants_mode={mode}"]), out)
        assert runs[mode]["status"] == "completed"
        assert runs[mode]["variants_at_once"]["at_once"] == (1 if mode == "sequential" else min(2, vp.usable_cores()))
    seq, par = runs["sequential"], runs["parallel"]
    assert list(par["variants"]) == list(seq["variants"]) == ["free", "tracked"]   # the experiment's order
    assert par["success"] == seq["success"] is True
    for name in seq["variants"]:
        a, b = seq["variants"][name], par["variants"][name]
        for key in ("status", "steps", "iterations_mean", "iterations_max", "stretch_max", "measures", "cohesion"):
            assert a[key] == b[key], (name, key)
        ra = np.load(tmp_path / "sequential" / name / "result.npz")
        rb = np.load(tmp_path / "parallel" / name / "result.npz")
        assert sorted(ra.files) == sorted(rb.files)
        for k in ra.files:
            np.testing.assert_array_equal(ra[k], rb[k], err_msg=f"{name} {k}")
        assert _summary(tmp_path / "parallel" / name)["pid"] != os.getpid()   # it ran in a process of its own


def test_a_failing_variant_fails_the_experiment_and_stops_the_others(hydra_conf, tmp_path, monkeypatch):
    """The tracked variant fails at its third step; the free one, still running (slowed here), is
    stopped and ends interrupted; the experiment fails with the tracked variant's error."""
    step = Simulator.step

    def failing(self, *a, **k):
        if "tracking" in type(self.controller).__module__:   # the tracked run
            self.test_steps = getattr(self, "test_steps", 0) + 1
            if self.test_steps > 2:
                raise SimulationError("the step could not be solved (test)")
        else:
            time.sleep(0.05)
        return step(self, *a, **k)

    monkeypatch.setattr(Simulator, "step", failing)   # the forked children have it too
    out = tmp_path / "exp"
    with pytest.raises(SimulationError, match="could not be solved") as info:
        run_experiment(hydra_conf([*SMOKE, "variants_mode=parallel", "frames=200", "guides.source=rigid"]), out)
    assert info.value.run_folder == str(out / "tracked")
    s = _summary(out)
    assert s["status"] == "failed" and s["success"] is None
    assert s["error"].startswith("variant tracked: the step could not be solved")
    assert s["variants"]["tracked"]["status"] == "failed"
    free = s["variants"]["free"]
    assert free["status"] in ("interrupted", "completed"), free
    assert _summary(out / "tracked")["status"] == "failed"
    if free["status"] == "interrupted":   # stopped well before its 200 frames
        assert _summary(out / "free")["status"] == "interrupted" and (free["steps"] or 0) < 200


def _cli(args, cwd):
    def defaults():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    return subprocess.Popen([sys.executable, "-m", "hairexp", *args], cwd=cwd, env=dict(os.environ, CI="1"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=defaults)


def _wait_running(out: Path, names, p, seconds: float = 120.0) -> dict:
    """The variants' running summaries once each has a step on disk."""
    deadline = time.monotonic() + seconds
    while True:
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline, "the variants did not start"
        ready = {}
        for n in names:
            try:
                s = _summary(out / n)
            except (OSError, ValueError):
                break
            if s.get("status") != "running" or not list((out / n / "stream" / "metrics").glob("part-*.parquet")):
                break
            ready[n] = s
        if len(ready) == len(names):
            return ready
        time.sleep(0.1)


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def _run_then(out: Path, act):
    """A long goaling_smoke experiment, its variants side by side, into ``out``; ``act(process,
    running summaries)`` once both variants have steps on disk; (process, stderr, running summaries)."""
    p = _cli([*SMOKE, "variants_mode=parallel", "frames=3000", "guides.source=rigid", f"hydra.run.dir={out}"], out.parent)
    try:
        running = _wait_running(out, ["free", "tracked"], p)
        act(p, running)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    return p, err, running


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork")
def test_sigterm_to_the_experiment_ends_every_variant_interrupted(tmp_path):
    out = tmp_path / "exp"
    # to the experiment's process only: it forwards the signal
    p, err, running = _run_then(out, lambda p, running: p.send_signal(signal.SIGTERM))
    assert p.returncode == 143, err
    s = _summary(out)
    assert s["status"] == "interrupted" and s["success"] is None
    assert "interrupted by SIGTERM" in s["error"]
    for n in ("free", "tracked"):
        v = _summary(out / n)
        assert v["status"] == "interrupted" and v["error"] == "interrupted by SIGTERM", v
        assert s["variants"][n]["status"] == "interrupted" and 0 < s["variants"][n]["steps"] < 3000
        assert (out / n / "metrics.parquet").is_file()
        assert _gone(running[n]["pid"])


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork")
def test_a_killed_variant_process_is_named(tmp_path):
    out = tmp_path / "exp"
    p, err, running = _run_then(out, lambda p, running: os.kill(running["tracked"]["pid"], signal.SIGKILL))
    assert p.returncode == 3, err
    assert "variant tracked: its process was killed by SIGKILL" in err
    s = _summary(out)
    assert s["status"] == "failed" and "killed by SIGKILL" in s["error"]
    tracked = _summary(out / "tracked")   # left "running" by the killed process: said failed
    assert tracked["status"] == "failed" and "SIGKILL" in tracked["error"]
    # ended as a killed sweep job's run is (app/run.py end_dead_run): the steps it streamed, no reserve left
    assert tracked["steps"] > 0 and tracked["frames_kept"] > 0 and s["variants"]["tracked"]["steps"] == tracked["steps"]
    assert not (out / "tracked" / ".ending.reserve").exists()
    assert s["variants"]["free"]["status"] == "interrupted"   # stopped by the experiment
    assert _gone(running["free"]["pid"])


def test_auto_chooses_by_cores_load_length_and_memory(monkeypatch):
    monkeypatch.setattr(vp, "usable_cores", lambda: 2)
    monkeypatch.setattr(vp.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(vp, "available_memory", lambda: 8e9)
    idle = lambda setting="auto", *a, **k: 2   # noqa: E731
    busy = lambda setting="auto", *a, **k: 1   # noqa: E731
    monkeypatch.setattr(vp, "pick_threads", idle)
    monkeypatch.setattr(vp, "idle_cores", lambda: 1.9)
    assert vp.choose_width("auto", 2, [20.0, 20.0], [5e7, 5e7])[0] == 2
    assert vp.choose_width("auto", 3, [20.0] * 3, [5e7] * 3)[0] == 2          # at most the cores
    assert vp.choose_width("auto", 1, [20.0], [5e7])[0] == 1
    assert vp.choose_width("auto", 2, [0.2, 0.3], [5e7, 5e7])[0] == 1         # short variants
    assert vp.choose_width("auto", 2, [20.0, 20.0], [1.5e9, 1.5e9])[0] == 1   # 3 GB > a quarter of 8 GB
    assert vp.choose_width("sequential", 2, [20.0, 20.0], [5e7, 5e7])[0] == 1
    monkeypatch.setattr(vp, "idle_cores", lambda: 0.9)
    assert vp.choose_width("auto", 2, [20.0, 20.0], [5e7, 5e7]) == (1, "0.9 of 2 cores idle")   # one core busy
    monkeypatch.setattr(vp, "idle_cores", lambda: None)   # no /proc/stat: the load average decides
    assert vp.choose_width("auto", 2, [20.0, 20.0], [5e7, 5e7])[0] == 2
    monkeypatch.setattr(vp, "pick_threads", busy)
    assert vp.choose_width("auto", 2, [20.0, 20.0], [5e7, 5e7])[0] == 1       # no idle core
    assert vp.choose_width("parallel", 2, [0.2, 0.3], [5e7, 5e7])[0] == 2     # asked for
    monkeypatch.setattr(vp, "pick_threads", idle)
    vp.keep_sequential("a sweep's job")
    try:
        assert vp.choose_width("auto", 2, [20.0, 20.0], [5e7, 5e7]) == (1, "a sweep's job")
        assert vp.choose_width("parallel", 2, [20.0, 20.0], [5e7, 5e7])[0] == 2
    finally:
        vp.keep_sequential(None)
    monkeypatch.setattr(vp, "usable_cores", lambda: 1)
    assert vp.choose_width("parallel", 2, [20.0, 20.0], [5e7, 5e7])[0] == 1   # one core


def test_idle_cores_reads_the_machine_now():
    """``idle_cores`` is now's: with this process busy on one core the window sees at most the
    others idle; asleep, about all of them (a loaded machine may show fewer: only bounds here)."""
    n = os.cpu_count() or 1
    idle = vp.idle_cores(0.2)
    if idle is None:
        pytest.skip("no /proc/stat")
    assert 0.0 <= idle <= n + 1e-9
    import threading

    stop = threading.Event()

    def spin():
        while not stop.is_set():
            pass

    t = threading.Thread(target=spin)
    t.start()
    try:
        busy = vp.idle_cores(0.3)
    finally:
        stop.set()
        t.join()
    assert busy <= n - 0.5   # the spinning thread kept about one core busy


def test_a_variant_cannot_set_the_mode(hydra_conf, tmp_path):
    cfg = hydra_conf(SMOKE)
    cfg.variants[1].overrides = ["controller.name=tracking", "variants_mode=parallel"]
    with pytest.raises(InputError, match="variants_mode.*belongs to the experiment"):
        run_experiment(cfg, tmp_path / "exp")


def test_an_unknown_mode_is_refused(hydra_conf):
    with pytest.raises(Exception, match="variants_mode"):
        hydra_conf([*SMOKE, "variants_mode=both"])
