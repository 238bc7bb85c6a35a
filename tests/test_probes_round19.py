"""Findings left weak by probe round 18 of issue 12 (2026-12-05), fixed."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from hairexp.app.guides import check_guide_file


def _guide_file(path, dtype):
    pos = np.zeros((3, 4, 3), dtype=dtype)
    pos[..., 2] = np.linspace(0, 0.3, 4)
    np.savez(path, guide_positions=pos, guide_offsets=np.array([0, 4]), fps=np.array(25.0))
    return path


@pytest.mark.parametrize("dtype,warned", [(np.float16, True), (np.float32, False), (np.float64, False)])
def test_low_precision_guide_positions_are_said(tmp_path, caplog, dtype, warned):
    path = _guide_file(tmp_path / "g.npz", dtype)
    with caplog.at_level(logging.WARNING, logger="hairexp"):
        check_guide_file(path)
    said = [r.getMessage() for r in caplog.records if "significant digits" in r.getMessage()]
    assert bool(said) == warned
    if warned:
        assert f"guides.file={path}" in said[0] and "float16" in said[0]
