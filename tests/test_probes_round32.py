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
