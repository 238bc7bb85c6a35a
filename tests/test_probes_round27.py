"""Findings of the independent probe round 27 of issue 12 (on ``d8270ec``), fixed: a single run
with ``overwrite=true`` into a finished sweep's folder.  (The previous run's log kept whole by an
overwrite that never claimed the folder is in tests/test_probes_round22.py.)"""

from __future__ import annotations

import json


def test_overwrite_into_a_sweeps_folder_says_it_is_a_sweeps(tmp_path):
    """It was refused naming the sweep's files as foreign ones (0/.hydra, 1/__main__.log,
    multirun.yaml)."""
    from hairexp.outputs.folder import overwrite_refusal

    (tmp_path / "multirun.yaml").write_text("hydra: {}\n")
    for job in ("0", "1"):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / "summary.json").write_text(json.dumps({"status": "completed"}))
    assert overwrite_refusal(tmp_path) == ("it is a -m sweep's folder (multirun.yaml and its job folders): "
                                           "overwrite=true replaces a run's folder, not a sweep's; choose another "
                                           "folder, or remove the sweep's")
