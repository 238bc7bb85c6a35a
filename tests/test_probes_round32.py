"""Findings left by the independent probe round 31 of issue 12, and those of round 32, fixed."""

from __future__ import annotations

from hairexp.app import cli


def test_a_word_that_is_no_override_is_refused_before_hydra_prints_anything():
    """``--info bogus``: Hydra printed its plugins and search path (27 lines) before its grammar
    error on ``bogus`` (round 31, left).  A word without ``=`` is parsed with every override now;
    a deletion (``~key``) and a choice of ``--info`` are not overrides to refuse."""
    for argv in (["--info", "bogus"], ["--info", "config", "bogus"], ["bogus"], ["-m", "experiment=goaling", "x"]):
        msg = cli.override_syntax_error(argv)
        assert msg is not None and msg.startswith(f"hairexp: error: {argv[-1]}: not a valid override: "), (argv, msg)
        assert msg.endswith("(an override is key=value)") and "Error parsing" not in msg
    for argv in (["--info", "config"], ["--info", "defaults"], ["~scene.spread"], ["--cfg", "job"],
                 ["experiment=goaling", "scene.spread=0.1"]):
        assert cli.override_syntax_error(argv) is None, argv


def test_a_sweep_job_stopped_before_its_run_began_is_said_interrupted(tmp_path, monkeypatch, capsys):
    """A SIGHUP to a sweep as Hydra made a job's folder: the job's run never wrote its outcome and
    the sweep listed it as "failed (exit 1): the job left no outcome" (round 31, left).  Now it is
    interrupted, with the signal's exit code, and its folder's summary.json says so; a job folder
    without an outcome in a sweep that was not signalled stays failed."""
    import json
    import signal

    done, empty = tmp_path / "0", tmp_path / "1"
    for d in (done, empty):
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "overrides.yaml").write_text(f"- solver.dt={0.01 if d is done else 0.02}\n")
    cli._write_outcome(done, cli.outcome(done, "completed", 0, None, {"converged": True}))
    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 2)
    assert cli.exit_code(signal.SIGHUP) == 129
    err = capsys.readouterr().err
    assert "job 0 [solver.dt=0.01]: completed (exit 0)" in err
    assert ("job 1 [solver.dt=0.02]: interrupted (exit 129): the sweep was stopped by SIGHUP before the job's run "
            "began") in err
    assert "left no outcome" not in err and "1 of 2 jobs completed" in err
    summary = json.loads((empty / "summary.json").read_text())
    assert summary["status"] == "interrupted" and "SIGHUP" in summary["error"]
    assert json.loads((empty / ".hydra" / "outcome.json").read_text())["status"] == "interrupted"

    lone = tmp_path / "other"
    (lone / "0" / ".hydra").mkdir(parents=True)
    monkeypatch.setattr(cli, "SWEEP_DIR", lone)
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 1)
    assert cli.exit_code() == 1
    assert "failed (exit 1): the job left no outcome" in capsys.readouterr().err
    assert not (lone / "0" / "summary.json").exists()
