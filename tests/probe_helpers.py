"""Shared by the probe-round tests (tests/test_probes_round*.py): a small goaling run's
overrides, a config copy with dotted keys changed, and ``python -m hairexp`` in a subprocess."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

SMALL = ["experiment=goaling_smoke", "variants=[]", "frames=2", "logging.rerun=false"]
REPO = Path(__file__).resolve().parents[1]


def updated(cfg, **kv):
    """A copy of ``cfg`` with ``kv`` set (``a__b=v`` sets ``a.b``)."""
    out = copy.deepcopy(cfg)
    for k, v in kv.items():
        OmegaConf.update(out, k.replace("__", "."), v, merge=False)
    return out


def run_cli(args, cwd, timeout=120):
    """``python -m hairexp <args>`` in ``cwd`` with this checkout first on the path."""
    env = dict(os.environ, CI="1", PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "hairexp", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)
