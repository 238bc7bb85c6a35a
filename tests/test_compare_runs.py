"""experiments.compare_runs: identical trees pass, a changed array or metrics value fails,
timing columns are ignored."""

from __future__ import annotations

import numpy as np
import pandas as pd

from experiments.compare_runs import compare


def tree(root, positions, residual, seconds):
    d = root / "run"
    d.mkdir(parents=True)
    np.savez(d / "result.npz", positions=positions)
    pd.DataFrame({"residual_max": residual, "step_seconds": seconds, "t_solve": seconds}).to_parquet(d / "metrics.parquet")


def test_identical_runs_compare_equal_whatever_their_timings(tmp_path):
    x = np.arange(6.0).reshape(1, 2, 3)
    tree(tmp_path / "a", x, [1e-10, 2e-10], [0.1, 0.2])
    tree(tmp_path / "b", x.copy(), [1e-10, 2e-10], [0.3, 0.4])
    assert compare(tmp_path / "a", tmp_path / "b") == (2, 0)


def test_a_changed_bit_is_a_difference(tmp_path):
    x = np.arange(6.0).reshape(1, 2, 3)
    y = x.copy()
    y[0, 0, 0] = np.nextafter(0.0, 1.0)
    tree(tmp_path / "a", x, [1e-10, 2e-10], [0.1, 0.2])
    tree(tmp_path / "b", y, [1e-10, np.nextafter(2e-10, 1.0)], [0.1, 0.2])
    assert compare(tmp_path / "a", tmp_path / "b") == (2, 2)


def test_a_corrupt_file_is_a_named_difference(tmp_path, capsys):
    x = np.arange(6.0).reshape(1, 2, 3)
    tree(tmp_path / "a", x, [1e-10, 2e-10], [0.1, 0.2])
    tree(tmp_path / "b", x, [1e-10, 2e-10], [0.1, 0.2])
    (tmp_path / "b" / "run" / "result.npz").write_bytes(b"PK\x03\x04 not a zip")
    assert compare(tmp_path / "a", tmp_path / "b") == (2, 1)
    assert "UNREADABLE run/result.npz" in capsys.readouterr().out


def test_a_run_only_the_after_tree_holds_is_a_difference(tmp_path, capsys):
    """The comparison went over the before tree's files only: a run added in the after tree
    compared equal (probe of issue 12, round 12)."""
    x = np.arange(6.0).reshape(1, 2, 3)
    tree(tmp_path / "a", x, [1e-10, 2e-10], [0.1, 0.2])
    tree(tmp_path / "b", x, [1e-10, 2e-10], [0.1, 0.2])
    tree(tmp_path / "b" / "extra", x, [1e-10, 2e-10], [0.1, 0.2])
    assert compare(tmp_path / "a", tmp_path / "b") == (4, 2)
    assert f"MISSING in {tmp_path / 'a'}: extra/run/result.npz" in capsys.readouterr().out
    assert compare(tmp_path / "b", tmp_path / "a") == (4, 2)
