"""Findings of the independent probe round 29 of issue 12 (on ``1cafdcd``), fixed: an append-only
(``chattr +a``) run folder, and an export into an append-only folder."""

from __future__ import annotations

import pytest


def test_an_append_only_run_folder_is_one_line(tmp_path, monkeypatch):
    """``hydra.run.dir`` (or the sweep's, or the working folder of a default run) append-only: the
    writability probe's folder could not be removed, and TemporaryDirectory's clean-up ended in a
    RecursionError traceback of 6,615 lines, exit 1, the probe folder left behind.  An append-only
    parent takes new folders: a run folder made in it is not refused."""
    from hairexp.outputs import folder as cli   # where the check lives (the command line imports it)

    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setattr(cli, "pinned", lambda p: "append-only (chattr +a)" if p == run else None)
    assert cli.unusable_folder(str(run)) == (f"{run} is append-only (chattr +a): a run replaces and removes its "
                                              "files in its folder")
    assert cli.unusable_folder(str(run / "outputs" / "x")) is None   # made inside it: not tried there
    assert list(run.iterdir()) == []
    monkeypatch.setattr(cli, "pinned", lambda p: "immutable (chattr +i)" if p == run else None)
    assert cli.unusable_folder(str(run / "x")) == f"{run} is immutable (chattr +i): no folder can be made in it"


def test_an_export_into_an_append_only_folder_is_refused_before_it_writes(tmp_path, monkeypatch):
    """It wrote its temporary stage there, could neither rename nor remove it, and left e.tmp.* behind."""
    from hairexp.app import export_scene

    monkeypatch.setattr(export_scene, "pinned", lambda p: "append-only (chattr +a)")
    with pytest.raises(export_scene.DestinationError, match=r"is append-only \(chattr \+a\) \(the stage is written "
                                                          r"to a temporary file there, then renamed\)"):
        export_scene.check_writable(tmp_path / "e.usda")
    assert list(tmp_path.iterdir()) == []
