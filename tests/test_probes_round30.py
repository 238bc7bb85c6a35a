"""Findings of the independent probe rounds 29 (weak, W2) and 30 of issue 12, fixed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hairexp.app import compose_config
from hairexp.app.assemble import assemble_scene, check_clear_roots, check_config
from hairexp.errors import InputError


def test_a_collider_on_the_bodys_path_is_refused_before_the_run():
    """A wheel of radius 0.5 m in goaling: the body carries the roots into it (the first root 16 mm
    deep at t = 0.68 s).  It ran "completed" with the hair stretched by 518 % and the tracked
    variant took 85 s for 21 steps (round 29, W2); now the check before the run names it."""
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "scene.colliders.0.radius=0.5"])
    with pytest.raises(InputError, match=r"^scene\.colliders\[0\]: collider 'wheel': the hair's roots go "
                                         r"into it \(strand \d+ root by [\d.]+ mm at t = [\d.]+ s\)"):
        check_config(cfg)


def test_roots_that_start_inside_a_collider_moving_with_them_are_allowed():
    """celia's scalp roots lie up to 7 mm inside the head sphere, which moves with the body: the
    depth does not grow, so the scene is not refused; the head moving back into the roots while
    the body stays still takes them deeper, and is."""
    cfg = compose_config(["experiment=celia_smoke", "variants=[]"])
    cfg, scene, _ = assemble_scene(cfg, settle=False)
    head = next(c for c in scene.colliders if c.name == "head")
    k = scene.strands.kinematic
    assert head.sdf_body(head.to_body(scene.root_positions(0.0)[k], 0.0)).min() < -1e-3   # the premise
    check_clear_roots(scene, int(cfg.frames), float(cfg.fps), 1)
    from hairexp.model.rigid import RigidMotion

    # the head moving 5 cm back into the ponytail's roots (at z = -9 cm) in 0.5 s, the body still
    head.motion = RigidMotion(np.array([0.0, 0.5]), np.array([[0, 0, 0], [0, 0, -0.05]]), np.zeros((2, 3)), "linear")
    scene = dataclasses.replace(scene, motion=RigidMotion.static())
    with pytest.raises(InputError, match=r"collider 'head': the hair's roots go into it \(strand \d+ "
                                         r"root by [\d.]+ mm at t = 0\.[01]"):
        check_clear_roots(scene, int(cfg.frames), float(cfg.fps), 1)


def test_a_signal_swallowed_where_it_landed_is_still_known():
    """A Ctrl-C to a sweep's main process was lost under load (its Interrupted raised inside
    joblib's waiting for the jobs): the sweep ran on, its next job started, exit 0 and no line
    (round 30, 2 of 2 tries with a second sweep running).  The handler keeps what it raised, and
    ``python -m hairexp`` raises it again when the sweep's launcher returns; a signal handled
    where it landed is not raised again."""
    import os
    import signal

    from hairexp.app.signals import InterruptSignals
    from hairexp.errors import Interrupted

    with InterruptSignals() as signals:
        assert signals.lost() is None
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):   # the handler runs between bytecodes of the main thread
                pass
        except Interrupted:   # swallowed, as joblib's code did
            pass
        assert signals.lost() == signal.SIGTERM


def test_a_sweep_stopped_before_its_jobs_run_marks_them(tmp_path, monkeypatch):
    """The stop mark is written even when no job says "running" yet: a job still starting up
    under load began after the Ctrl-C and ran to its end (round 30, sw2)."""
    from hairexp.app import cli

    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    cli.stop_sweep_jobs(2)
    assert (tmp_path / cli.STOP_MARK).read_text() == "SIGINT\n"


def test_a_folder_of_a_live_run_is_not_offered_to_overwrite(tmp_path):
    """Two launches into one folder: the second was told to "set overwrite=true", which then
    refused the live run ("replaces a finished run only"), and the listing showed the run's own
    hidden reserve file (round 30, W1).  A killed run's folder still offers overwrite=true."""
    import json
    import os

    from hairexp.outputs.folder import owner, used_refusal

    (tmp_path / ".ending.reserve").write_bytes(b"\0" * 8)
    (tmp_path / "stream").mkdir()
    (tmp_path / "summary.json").write_text(json.dumps({"status": "running", **owner()}))
    why = used_refusal(tmp_path)
    assert why == (f"the run folder is not empty (stream, summary.json); it holds a run still running (pid "
                   f"{os.getpid()}); a run folder belongs to one run: choose another folder (hydra.run.dir), or wait "
                   "for that run to end (overwrite=true replaces a finished run only)")
    dead = max(int(p) for p in os.listdir("/proc") if p.isdigit()) + 100000   # no such process
    (tmp_path / "summary.json").write_text(json.dumps({"status": "running", "pid": dead, "host": owner()["host"]}))
    assert used_refusal(tmp_path).endswith(f"it holds a run killed while running (pid {dead}); a run folder belongs to "
                                           "one run: choose another folder (hydra.run.dir) or set overwrite=true to "
                                           "replace the run in it")


def test_scene_pictures_of_a_file_says_it_is_a_file(tmp_path, capsys):
    """``scene_pictures <run>/summary.json out.png`` said "not a run folder (no summary.json)" (round 30, W3)."""
    from experiments import scene_pictures

    f = tmp_path / "summary.json"
    f.write_text("{}")
    with pytest.raises(SystemExit) as exc:
        scene_pictures.main([str(f), str(tmp_path / "p.png")])
    assert exc.value.code == 2
    assert f"{f}: is a file, not a folder: give the run folder that holds summary.json" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        scene_pictures.main([str(tmp_path / "nope"), str(tmp_path / "p.png")])
    assert "nope: does not exist" in capsys.readouterr().err


def test_a_typo_in_a_users_config_file_gets_the_nearest_key():
    """``scene: {n_strandz: 5}`` in a user's experiment file (``--config-dir``) said Hydra's line
    only; the same typo on the command line names 'scene.n_strands' (round 30, W2)."""
    from hairexp.app.cli import one_line

    exc = Exception("In 'experiment/mine2': ConfigKeyError raised while composing config:\nKey 'n_strandz' not in "
                    "'SceneConfig'\n    full_key: scene.n_strandz\n    object_type=SceneConfig")
    assert one_line(exc) == ("In 'experiment/mine2': ConfigKeyError raised while composing config: Key 'n_strandz' "
                             "not in 'SceneConfig' (key scene.n_strandz); did you mean 'scene.n_strands'?")


def test_a_run_taking_a_large_share_of_memory_is_announced(caplog):
    """``scene.n_strands=200000`` (about 12 GB of 22 GB available; 20 steps in 4 minutes, under the
    long-run bounds) started without a word (round 30); a run over a quarter of the available
    memory is said with its estimate, one under it is not."""
    import logging

    from hairexp.app import guard

    est = guard.estimate(2_000_000, 20, 1)
    with caplog.at_level(logging.WARNING, logger="hairexp.app.guard"):
        guard.check(est, "k", allow_large=False, available=5.0 * est.memory)
        assert "large run" not in caplog.text
        guard.check(est, "k", allow_large=False, available=2.0 * est.memory)
    assert "large run: about 20 steps" in caplog.text and f"of {guard._size(2.0 * est.memory)} available" in caplog.text


def test_a_sweeps_resource_tracker_outlives_a_hangup_of_the_group():
    """SIGHUP or SIGQUIT to a sweep's whole process group (the terminal closed) killed joblib's
    resource tracker, which ignores only SIGINT and SIGTERM: its relaunched successor printed 9
    KeyError tracebacks after the sweep's closing line (round 31: 9 tracebacks before the fix, 0
    after, by hand).  The sweep starts it with the other handled signals ignored, which it
    inherits (SIGINT and SIGTERM it ignores itself, once it runs); the main process keeps its
    own handlers."""
    import signal
    import subprocess
    import sys

    code = ("import signal\n"
            "from hairexp.app.signals import start_resource_tracker\n"
            "from joblib.externals.loky.backend import resource_tracker as r\n"
            "before = signal.getsignal(signal.SIGHUP)\n"
            "start_resource_tracker()\n"
            "assert signal.getsignal(signal.SIGHUP) is before\n"
            "st = open(f'/proc/{r._resource_tracker._pid}/status').read()\n"
            "print(int(st.split('SigIgn:')[1].split()[0], 16))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    ignored = int(out.stdout.split()[-1])
    for s in (signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2, signal.SIGXCPU):
        assert ignored >> (s - 1) & 1, signal.Signals(s).name


def test_a_reserve_that_cannot_be_removed_is_emptied(tmp_path, monkeypatch):
    """A run folder made immutable mid-run (``chattr +i``): the 128 kB ``.ending.reserve`` could
    not be removed and stayed whole (round 31, W2); its file can still be emptied, and is, and the
    failed ending is still told that it could not be removed."""
    from pathlib import Path

    from hairexp.outputs import folder as fo

    assert fo.reserve(tmp_path)
    path = tmp_path / fo.RESERVE
    assert path.stat().st_size == fo.RESERVE_BYTES

    def refuse(self, missing_ok=False):
        raise PermissionError(1, "Operation not permitted", str(self))

    monkeypatch.setattr(Path, "unlink", refuse)
    with pytest.raises(PermissionError):
        fo.free_reserve(tmp_path, quiet=False)
    assert path.stat().st_size == 0


def test_overwrite_of_a_sweep_jobs_folder_removes_its_outcome(tmp_path):
    """``overwrite=true`` into a finished sweep job's folder left its ``.hydra/outcome.json``
    ("interrupted", code 130) beside the new run's completed summary (round 31, A O3); a job's
    own "running" outcome, written before it claims its folder, is kept."""
    import json
    import os

    from hairexp.outputs.folder import OUTCOME, claim

    (tmp_path / ".hydra").mkdir()
    (tmp_path / OUTCOME).write_text(json.dumps({"status": "interrupted", "code": 130}))
    (tmp_path / "summary.json").write_text(json.dumps({"status": "interrupted"}))
    (tmp_path / "metrics.parquet").write_bytes(b"PAR1" + bytes(8) + b"PAR1")
    claim(tmp_path, overwrite=True)
    assert not (tmp_path / OUTCOME).exists() and not (tmp_path / "metrics.parquet").exists()
    (tmp_path / "summary.json").write_text(json.dumps({"status": "completed"}))
    (tmp_path / OUTCOME).write_text(json.dumps({"status": "running", "code": 1, "pid": os.getpid()}))
    claim(tmp_path, overwrite=True)
    assert json.loads((tmp_path / OUTCOME).read_text())["status"] == "running"


def _plate(times: str, translations: str, half: float = 0.003) -> list[str]:
    return ["experiment=goaling_smoke", "variants=[]", "measure.collider=plate",
            f"scene.colliders=[{{name: plate, shape: box, half_extents: [{half}, 0.3, 0.3], motion: {{interpolation: linear, "
            f"times: {times}, translations: {translations}, rotations_deg: [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]}}}}]"]


@pytest.mark.parametrize("times", ["[0.1, 0.12]", "[0.1, 0.9]"])
def test_a_plate_swept_through_the_roots_between_two_steps_is_refused(times):
    """A 6 mm plate crossing the roots (x within 17 mm of 0) 1 m along x between two samples of the
    check (one step of 0.04 s: 50 m/s; or 5 cm a step, the body moving too) was never seen at a
    sample and passed (noticed 2026-12-07).  Between samples the check now halves every interval
    in which a root moved far enough to have gone in and out (the signed distance changes no faster
    than the root moves)."""
    cfg = compose_config(_plate(times, "[[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]"))
    with pytest.raises(InputError, match=r"^scene\.colliders\[0\]: collider 'plate': the hair's roots go into it "
                                         r"\(strand \d+ root by [\d.]+ mm at t = [\d.]+ s\)"):
        check_config(cfg)


def test_a_plate_that_passes_beside_the_roots_or_a_thin_one_through_them():
    """The same plate 0.2 m above the roots (y from 0.2 to 0.8) passes; a 2 mm plate (thinner than
    twice the 2 mm thickness allowed) through them is refused: a root gone halfway into it."""
    check_config(compose_config(_plate("[0.1, 0.12]", "[[-0.5, 0.5, 0.0], [0.5, 0.5, 0.0]]")))
    with pytest.raises(InputError, match="collider 'plate': the hair's roots go into it"):
        check_config(compose_config(_plate("[0.1, 0.12]", "[[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]", half=0.001)))
