"""Findings of the independent probe round 34 of issue 12, fixed."""

from __future__ import annotations

import logging
import zipfile

import numpy as np
import pytest

from hairexp.errors import InputError


def _guide_file(path, edits: str = "") -> None:
    from hairexp.guides.animation import GuideAnimation

    pos = np.zeros((5, 4, 3))
    pos[:, :, 1] = -np.linspace(0.0, 0.3, 4)
    anim = GuideAnimation(pos, np.array([0, 4]), 25.0)
    anim.edits_applied = edits
    anim.save(path)


def test_a_truncated_or_damaged_guide_file_is_named_as_such(tmp_path):
    """A guide npz cut short said "cannot read guide animation: BadZipFile: File is not a zip file"
    (round 34, weak): the reader's words, not what is wrong with the file."""
    from hairexp.guides.animation import file_guides

    whole = tmp_path / "whole.npz"
    _guide_file(whole)
    data = whole.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as err:
        file_guides(cut, None)
    msg = str(err.value)
    assert msg.startswith(f"guides.file={cut}: is truncated or corrupt: it begins as an npz") and "its end" in msg
    assert f"({len(data) // 2} bytes" in msg
    # a member whose compressed bytes are damaged: the archive's directory is whole
    damaged = bytearray(data)
    with zipfile.ZipFile(whole) as z:
        info = z.getinfo("guide_positions.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 8
    for i in range(start, start + 40):
        damaged[i] ^= 0x5A
    bad = tmp_path / "bad.npz"
    bad.write_bytes(bytes(damaged))
    with pytest.raises(InputError) as err:
        file_guides(bad, None)
    assert "is corrupt or truncated: an array in it cannot be read" in str(err.value)
    assert file_guides(whole, None).n_frames == 5   # the whole file reads


def test_an_unknown_top_level_key_with_a_dot_is_said_unknown(tmp_path):
    """``--set bogus.key=1`` (and ``bogus.key=1`` through compose_config) said "unknown key 'bogus'
    in an item of the value", the message of a record's field inside a list (round 34, weak)."""
    from hairexp.app import compose_config

    with pytest.raises(InputError) as err:
        compose_config(["experiment=goaling_smoke", "bogus.key=1"])
    assert str(err.value).startswith("bogus.key: unknown key, not in the schema")
    with pytest.raises(InputError) as err:   # a field of a record in a list is still named with its record's keys
        compose_config(["experiment=goaling_smoke", "guides.edits=[{guide: 0, bogus: 1}]"])
    assert "unknown key 'bogus' in an item of the value" in str(err.value)


def test_a_saved_guide_file_remembers_its_edits_and_a_second_application_is_warned(tmp_path, caplog):
    """A run's guides.npz holds the animation with its guides.edits applied; tracked again with the
    experiment's edits (guides.source=file), they were applied twice without a word (round 34, weak)."""
    from hairexp.app import assemble, compose_config
    from hairexp.guides.animation import file_guides

    base = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=5"])
    assert len(base.guides.edits) == 1
    run = assemble(base)
    assert run.guides.edits_applied.startswith("1 edit: rotate of guide 0 keyed at")
    saved = tmp_path / "guides.npz"
    run.guides.save(saved)
    assert file_guides(saved, None).edits_applied == run.guides.edits_applied

    again = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=5", "guides.source=file",
                            f"guides.file={saved}"])
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        twice = assemble(again)
    said = [r.getMessage() for r in caplog.records if "applied to it again" in r.getMessage()]
    assert len(said) == 1 and "give guides.edits=[] to track the file as it is" in said[0]
    assert twice.guides.edits_applied.startswith(run.guides.edits_applied + "; then 1 edit")

    caplog.clear()
    plain = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=5", "guides.source=file",
                            f"guides.file={saved}", "guides.edits=[]"])
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        assemble(plain)
    assert not [r for r in caplog.records if "applied to it again" in r.getMessage()]
    # a file without the member (an older run's, a user's own) reads as before, with nothing said
    bare = tmp_path / "bare.npz"
    _guide_file(bare)
    with zipfile.ZipFile(bare) as z:
        assert "edits_applied.npy" not in z.namelist()
    assert file_guides(bare, None).edits_applied == ""


def test_run_folder_refuses_a_folder_it_cannot_make_with_a_named_error(tmp_path):
    """``run_folder(cfg, "/proc/nope")`` raised mkdir's bare FileNotFoundError (round 34, weak);
    the command line refused such a folder before Hydra started."""
    from hairexp.app import compose_config, run_folder

    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for variants in ([], None):
        cfg = compose_config(["experiment=goaling_smoke", "frames=2"] + (["variants=[]"] if variants == [] else []))
        with pytest.raises(InputError) as err:
            run_folder(cfg, blocker / "run")
        assert str(err.value) == (f"{blocker / 'run'}: cannot be the run folder: {blocker} is a file, not a folder "
                                  "to create it in")
    assert blocker.read_text() == "x"


def test_a_sweep_whose_jobs_all_completed_is_known_as_such(tmp_path, monkeypatch):
    """Two SIGINTs as a sweep's last jobs ended: its lines said "2 of 2 jobs completed" on stdout
    and "interrupted" on stderr (round 34, weak).  ``sweep_completed`` tells the signal's handler
    (hairexp/__main__.py) that nothing was interrupted."""
    from hairexp.app import cli

    for name in ("0", "1"):
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "overrides.yaml").write_text(f"- solver.dt=0.0{name}1\n")
        cli._write_outcome(tmp_path / name, cli.outcome(tmp_path / name, "completed", 0, None, {"converged": True}))
    monkeypatch.setattr(cli, "SWEEP_DIR", tmp_path)
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 2)
    assert cli.sweep_completed()
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 3)   # a job not started
    assert not cli.sweep_completed()
    monkeypatch.setattr(cli, "SWEEP_TOTAL", 2)
    cli._write_outcome(tmp_path / "1", cli.outcome(tmp_path / "1", "interrupted", 130, "SIGINT", {}))
    assert not cli.sweep_completed()
    monkeypatch.setattr(cli, "SWEEP_DIR", None)
    assert not cli.sweep_completed()
