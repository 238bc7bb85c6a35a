"""Shared fixtures: a Hydra context that is always cleared.  Plain helpers are in helpers.py."""

from __future__ import annotations

import os

import pytest

from helpers import CONF_DIR, REPO

# Subprocesses (``python -m hairexp``) import this checkout's hairexp, not whichever copy the
# virtual environment has installed (a git worktree shares the venv of another checkout).
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))


@pytest.fixture
def hydra_conf():
    """``compose(overrides)`` within an initialised Hydra; GlobalHydra is cleared afterwards."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        yield lambda overrides=(): compose(config_name="config", overrides=list(overrides))
    GlobalHydra.instance().clear()
