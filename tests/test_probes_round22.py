"""Findings of the independent probe round 22 of issue 12 (on ``d7712da``), fixed: a signal while
``overwrite=true`` removes the previous run, and an experiment interrupted after its variants."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from hairexp.errors import Interrupted
from probe_helpers import SMALL

SMOKE = [*SMALL, "logging=off"]


def _signal_on_second_removal(monkeypatch, signum=signal.SIGTERM):
    """Send ``signum`` to this process when overwrite=true removes its second file."""
    removed = []
    real_unlink = Path.unlink

    def unlink(self, *a, **k):
        removed.append(self.name)
        out = real_unlink(self, *a, **k)
        if len(removed) == 2:
            os.kill(os.getpid(), signum)
        return out

    monkeypatch.setattr(Path, "unlink", unlink)
    return removed


@pytest.mark.parametrize("experiment", [False, True])
def test_a_signal_while_overwrite_removes_the_old_run_ends_interrupted(tmp_path, monkeypatch, experiment):
    """SIGTERM in the middle of the removal: it is kept until the old run is gone, then the run ends
    ``interrupted`` with a summary (it left no summary beside half of the old run's files)."""
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment
    from hairexp.app.run import run

    go = run_experiment if experiment else run
    out = tmp_path / "r"
    go(compose_config(SMOKE), out)
    assert (out / "result.npz").is_file()
    removed = _signal_on_second_removal(monkeypatch)
    with pytest.raises(Interrupted) as e:
        go(compose_config([*SMOKE, "overwrite=true", "frames=3"]), out)
    monkeypatch.undo()
    assert e.value.signum == signal.SIGTERM and len(removed) >= 2
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and s.get("steps", 0) == 0
    assert not (out / "result.npz").exists() and not (out / "result.usdc").exists()   # the old run's: all gone
    assert not list(out.rglob("*.tmp*"))


def test_an_experiment_interrupted_after_its_verdict_is_no_success(tmp_path, monkeypatch):
    """A signal during the comparison recording (after the judge gave its verdict): the summary says
    interrupted and success null, the verdict kept (it said success: true)."""
    import hairexp.outputs.comparison as comparison
    from hairexp.app.config import compose_config
    from hairexp.app.experiment import run_experiment

    def interrupted(*a, **k):
        os.kill(os.getpid(), signal.SIGINT)
        return None

    monkeypatch.setattr(comparison, "write_comparison", interrupted)
    out = tmp_path / "e"
    cfg = compose_config(["experiment=goaling_smoke", "frames=3", "logging.rerun=true"])
    with pytest.raises(Interrupted):
        run_experiment(cfg, out)
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "interrupted" and s["success"] is None and "verdict" in s
    assert all(v["status"] == "completed" for v in s["variants"].values())
    for name in s["variants"]:
        with np.load(out / name / "result.npz") as r:
            assert len(r["times"]) == 4


# ---------------------------------------------------------------------------------------------
# a user's own config file (--config-dir / --config-name) that is broken: one line, exit 2
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("body, said", [
    ("frames: [1, 2\n", "not valid YAML: while parsing a flow sequence in"),
    ("frmes: 3\n", "Key 'frmes' not in 'Config' (key frmes)"),
    ("frames: abc\n", "Value 'abc' of type 'str' could not be converted to Integer (key frames)"),
])
def test_a_broken_user_config_file_is_one_line_exit_2_and_no_folder(tmp_path, body, said):
    from probe_helpers import run_cli

    (tmp_path / "mine.yaml").write_text("defaults:\n  - config\n  - _self_\n" + body)
    out = tmp_path / "out"
    p = run_cli(["--config-dir", str(tmp_path), "--config-name", "mine", *SMALL, f"hydra.run.dir={out}"], tmp_path)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hairexp: error: --config-name=mine: ") and said in lines[0], p.stderr
    if "YAML" in said:
        assert "mine.yaml" in lines[0] and "line 4" in lines[0]
    assert not out.exists()
